//! The scenario of the negative valid-usage tests (`tests/vuid_*.rs`, one file per command
//! family): one test per valid-usage check the driver implements for acceleration-structure
//! builds, copies and property queries. Arbor reports each violation it can see, data in device
//! memory included, with its VUID, skips the invalid command and writes nothing outside its
//! destination and scratch.
//!
//! The validation layer is off: every input is invalid on purpose, in exactly one way. Each test
//! checks that
//! 1. the diagnostics channel names the VUID (`arbor: error: <command>: [VUID-...] ...`), and
//!    reports nothing else for the command;
//! 2. the process survives and the queue keeps working (every submission's fence signals);
//! 3. no byte outside destination and scratch changed: destinations and scratch live inside
//!    larger buffers filled with 0xA5 guard bytes, inputs inside guarded buffers too, and every
//!    buffer of the test is compared with a snapshot taken before the command;
//! 4. the destination of the invalid build (which held a valid structure before) is marked
//!    invalid (`arbor::accel::header` of its bytes, read through the mapping, is None);
//! 5. a valid build on the same device afterwards traverses correctly.
//!
//! Diagnostics are per process and the tests of one binary run in parallel: every scenario holds
//! `SERIAL`, so the diagnostics appended while a test runs are that test's own.

use std::sync::{Mutex, MutexGuard};

use arbor::accel::{self, MapView, NoDevice, Ray, RayFlags};
use ash::vk;
use glam::Vec3;

pub use super::accel::{instance_record, Accel, ALL_USAGE};

pub type Geom = vk::AccelerationStructureGeometryKHR<'static>;
pub type Info<'a> = vk::AccelerationStructureBuildGeometryInfoKHR<'a>;
pub type Range = vk::AccelerationStructureBuildRangeInfoKHR;

pub const BLAS: vk::AccelerationStructureTypeKHR = vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL;
pub const TLAS: vk::AccelerationStructureTypeKHR = vk::AccelerationStructureTypeKHR::TOP_LEVEL;
pub const DEVICE: vk::AccelerationStructureBuildTypeKHR = vk::AccelerationStructureBuildTypeKHR::DEVICE;
pub const NO_FLAGS: vk::BuildAccelerationStructureFlagsKHR = vk::BuildAccelerationStructureFlagsKHR::empty();
pub const ALLOW_UPDATE: vk::BuildAccelerationStructureFlagsKHR = vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE;

pub const CMD: &str = "vkCmdBuildAccelerationStructuresKHR";
pub const CMD_INDIRECT: &str = "vkCmdBuildAccelerationStructuresIndirectKHR";
pub const HOST: &str = "vkBuildAccelerationStructuresKHR";

/// Guard bytes before and after every destination, scratch and input region.
pub const GUARD: u64 = 4096;
pub const FILL: u8 = 0xA5;
/// The test mesh: a GRID x GRID grid of quads (two triangles each) over [0,1]^2 at z = 0.
pub const GRID: u32 = 8;
pub const IDENTITY: [f32; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

static SERIAL: Mutex<()> = Mutex::new(());

pub fn serial() -> MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

// ---------------------------------------------------------------------------------------------
// Regions, guards, snapshots

/// `len` bytes at `offset` in buffer `buf` of the test's `Accel`.
#[derive(Clone, Copy, Debug)]
pub struct Region {
    pub buf: usize,
    pub offset: u64,
    pub len: u64,
}

impl Region {
    pub fn address(&self, a: &Accel) -> u64 {
        a.buf(self.buf).address + self.offset
    }
    pub fn host_ptr(&self, a: &Accel) -> *mut u8 {
        // SAFETY: offset is inside the mapped buffer.
        unsafe { a.buf(self.buf).ptr.add(self.offset as usize) }
    }
    pub fn read(&self, a: &Accel) -> Vec<u8> {
        a.buf(self.buf).read(self.offset as usize, self.len as usize)
    }
    pub fn write(&self, a: &Accel, at: u64, data: &[u8]) {
        a.buf(self.buf).write((self.offset + at) as usize, data)
    }
}

/// `len` bytes with GUARD bytes of 0xA5 before and at least GUARD after, in a buffer of its own
/// (offset GUARD: 256-aligned, so usable for structures, scratch and every input).
pub fn guarded_with(a: &Accel, len: u64, usage: vk::BufferUsageFlags) -> Region {
    let b = a.buffer_with(GUARD + len.next_multiple_of(256) + GUARD, usage);
    a.fill(b, FILL);
    Region { buf: b, offset: GUARD, len }
}

pub fn guarded(a: &Accel, len: u64) -> Region {
    guarded_with(a, len, ALL_USAGE)
}

pub fn guarded_data(a: &Accel, data: &[u8]) -> Region {
    let r = guarded(a, data.len() as u64);
    r.write(a, 0, data);
    r
}

pub fn assert_guards(a: &Accel, r: Region) {
    let b = a.buf(r.buf);
    let all = b.read(0, b.size as usize);
    let (before, after) = (&all[..r.offset as usize], &all[(r.offset + r.len) as usize..]);
    if let Some(k) = before.iter().position(|&x| x != FILL) {
        panic!("guard byte {} before the region of buffer {} was overwritten", before.len() - k, r.buf);
    }
    if let Some(k) = after.iter().position(|&x| x != FILL) {
        panic!("guard byte {k} after the region of buffer {} was overwritten", r.buf);
    }
}

/// Every byte of every buffer of the test.
pub struct Snapshot(Vec<Vec<u8>>);

pub fn snapshot(a: &Accel) -> Snapshot {
    Snapshot(
        (0..a.buffer_count())
            .map(|i| {
                let b = a.buf(i);
                b.read(0, b.size as usize)
            })
            .collect(),
    )
}

/// Nothing changed outside `writable`.
pub fn verify(a: &Accel, snap: &Snapshot, writable: &[Region]) {
    for (i, before) in snap.0.iter().enumerate() {
        let after = a.buf(i).read(0, before.len());
        for (k, (x, y)) in before.iter().zip(&after).enumerate() {
            let k = k as u64;
            if x != y && !writable.iter().any(|r| r.buf == i && k >= r.offset && k < r.offset + r.len) {
                panic!("buffer {i} byte {k} changed from {x:#04x} to {y:#04x}: outside destination and scratch");
            }
        }
    }
}

/// An address that was device memory once and is not any more.
pub fn freed_address(a: &Accel, size: u64) -> u64 {
    let (buffer, memory, _) = a.ctx.host_buffer(size, ALL_USAGE);
    // SAFETY: buffer with SHADER_DEVICE_ADDRESS usage bound to DEVICE_ADDRESS memory; destroyed
    // right after, never used again.
    unsafe {
        let address = a.bda.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(buffer));
        a.ctx.device.destroy_buffer(buffer, None);
        a.ctx.device.free_memory(memory, None);
        address
    }
}
// ---------------------------------------------------------------------------------------------
// Structures, geometry, builds

/// A structure placed at offset GUARD of a guarded buffer.
pub struct Dst {
    pub s: vk::AccelerationStructureKHR,
    pub r: Region,
}

pub fn guarded_structure(a: &Accel, ty: vk::AccelerationStructureTypeKHR, size: u64) -> Dst {
    let r = guarded(a, size);
    Dst { s: a.structure_at(r.buf, r.offset, size, ty), r }
}

/// A structure at `offset` of an existing region's buffer.
pub fn structure_in(a: &Accel, buf: usize, offset: u64, size: u64, ty: vk::AccelerationStructureTypeKHR) -> Dst {
    Dst { s: a.structure_at(buf, offset, size, ty), r: Region { buf, offset, len: size } }
}

pub fn header_of(a: &Accel, d: &Dst) -> Option<accel::Header> {
    accel::header(&d.r.read(a))
}

pub fn cadr(address: u64) -> vk::DeviceOrHostAddressConstKHR {
    vk::DeviceOrHostAddressConstKHR { device_address: address }
}

pub fn madr(address: u64) -> vk::DeviceOrHostAddressKHR {
    vk::DeviceOrHostAddressKHR { device_address: address }
}

pub struct Mesh {
    pub v: Region,
    pub i: Region,
    pub vertex_bytes: Vec<u8>,
    pub index_bytes: Vec<u8>,
    pub max_vertex: u32,
    pub count: u32,
}

pub fn grid() -> (Vec<u8>, Vec<u8>) {
    let n = GRID;
    let mut v = Vec::new();
    for y in 0..=n {
        for x in 0..=n {
            for c in [x as f32 / n as f32, y as f32 / n as f32, 0.0f32] {
                v.extend(c.to_le_bytes());
            }
        }
    }
    let mut i = Vec::new();
    for y in 0..n {
        for x in 0..n {
            let k = y * (n + 1) + x;
            for idx in [k, k + 1, k + n + 1, k + 1, k + n + 2, k + n + 1] {
                i.extend(idx.to_le_bytes());
            }
        }
    }
    (v, i)
}

pub fn upload_grid(a: &Accel) -> Mesh {
    let (vertex_bytes, index_bytes) = grid();
    Mesh {
        v: guarded_data(a, &vertex_bytes),
        i: guarded_data(a, &index_bytes),
        max_vertex: (GRID + 1) * (GRID + 1) - 1,
        count: 2 * GRID * GRID,
        vertex_bytes,
        index_bytes,
    }
}

/// Triangles (R32G32B32_SFLOAT, stride 12, UINT32 indices, optional transform).
pub fn tri(vertex: u64, index: u64, max_vertex: u32, transform: u64) -> Geom {
    Geom::default()
        .geometry_type(vk::GeometryTypeKHR::TRIANGLES)
        .flags(vk::GeometryFlagsKHR::OPAQUE)
        .geometry(vk::AccelerationStructureGeometryDataKHR {
            triangles: vk::AccelerationStructureGeometryTrianglesDataKHR::default()
                .vertex_format(vk::Format::R32G32B32_SFLOAT)
                .vertex_data(cadr(vertex))
                .vertex_stride(12)
                .max_vertex(max_vertex)
                .index_type(vk::IndexType::UINT32)
                .index_data(cadr(index))
                .transform_data(cadr(transform)),
        })
}

pub fn mesh_geom(a: &Accel, m: &Mesh) -> Geom {
    tri(m.v.address(a), m.i.address(a), m.max_vertex, 0)
}

pub fn aabbs_geom(data: u64, stride: u64) -> Geom {
    Geom::default()
        .geometry_type(vk::GeometryTypeKHR::AABBS)
        .flags(vk::GeometryFlagsKHR::OPAQUE)
        .geometry(vk::AccelerationStructureGeometryDataKHR {
            aabbs: vk::AccelerationStructureGeometryAabbsDataKHR::default().data(cadr(data)).stride(stride),
        })
}

pub fn instances_geom(data: u64, array_of_pointers: bool) -> Geom {
    Geom::default().geometry_type(vk::GeometryTypeKHR::INSTANCES).geometry(vk::AccelerationStructureGeometryDataKHR {
        instances: vk::AccelerationStructureGeometryInstancesDataKHR::default()
            .array_of_pointers(array_of_pointers)
            .data(cadr(data)),
    })
}

pub fn instance(reference: u64) -> [u8; 64] {
    instance_record(IDENTITY, 0, 0xFF, 0, 0, reference)
}

pub fn info(ty: vk::AccelerationStructureTypeKHR, flags: vk::BuildAccelerationStructureFlagsKHR, geoms: &[Geom]) -> Info<'_> {
    Info::default().ty(ty).flags(flags).mode(vk::BuildAccelerationStructureModeKHR::BUILD).geometries(geoms)
}

pub fn update_info<'a>(
    ty: vk::AccelerationStructureTypeKHR,
    flags: vk::BuildAccelerationStructureFlagsKHR,
    geoms: &'a [Geom],
    src: &Dst,
    dst: &Dst,
    scratch: u64,
) -> Info<'a> {
    info(ty, flags, geoms)
        .mode(vk::BuildAccelerationStructureModeKHR::UPDATE)
        .src_acceleration_structure(src.s)
        .dst_acceleration_structure(dst.s)
        .scratch_data(madr(scratch))
}

pub fn range(count: u32) -> Range {
    Range::default().primitive_count(count)
}

pub fn cmd_build(a: &Accel, infos: &[Info], ranges: &[&[Range]]) {
    a.submit(|cb| {
        // SAFETY: recording command buffer; the arrays match (ash asserts the lengths).
        unsafe { a.ext.cmd_build_acceleration_structures(cb, infos, ranges) };
    });
}

/// One indirect build of one info with one geometry; `update` first writes a range record with
/// vkCmdUpdateBuffer (and a barrier) in the same command buffer.
pub fn cmd_build_indirect(a: &Accel, inf: &Info, address: u64, stride: u32, max_count: u32, update: Option<(Region, [u32; 4])>) {
    a.submit(|cb| {
        let d = &a.ctx.device;
        // SAFETY: recording command buffer, live buffers; arrays of one element each.
        unsafe {
            if let Some((r, record)) = update {
                let bytes: Vec<u8> = record.iter().flat_map(|w| w.to_le_bytes()).collect();
                d.cmd_update_buffer(cb, a.buf(r.buf).buffer, r.offset, &bytes);
                let barrier = vk::MemoryBarrier::default()
                    .src_access_mask(vk::AccessFlags::TRANSFER_WRITE)
                    .dst_access_mask(vk::AccessFlags::INDIRECT_COMMAND_READ);
                d.cmd_pipeline_barrier(
                    cb,
                    vk::PipelineStageFlags::TRANSFER,
                    vk::PipelineStageFlags::ACCELERATION_STRUCTURE_BUILD_KHR,
                    vk::DependencyFlags::empty(),
                    &[barrier],
                    &[],
                    &[],
                );
            }
            a.ext.cmd_build_acceleration_structures_indirect(cb, std::slice::from_ref(inf), &[address], &[stride], &[&[max_count]]);
        }
    });
}

pub fn record(count: u32) -> Vec<u8> {
    [count, 0, 0, 0].iter().flat_map(|w| w.to_le_bytes()).collect()
}

/// A guarded BOTTOM_LEVEL destination of at least `min_size` bytes holding a valid build of the
/// first `count` grid triangles, and a guarded scratch region of at least `min_scratch` bytes
/// (and at least the build and update scratch of the whole grid).
pub fn prebuilt_blas(a: &Accel, m: &Mesh, min_size: u64, min_scratch: u64, count: u32, flags: vk::BuildAccelerationStructureFlagsKHR) -> (Dst, Region) {
    let geoms = [mesh_geom(a, m)];
    let inf = info(BLAS, flags, &geoms);
    let sizes = a.sizes(DEVICE, &inf, &[count]);
    let full = a.sizes(DEVICE, &inf, &[m.count]);
    let dst = guarded_structure(a, BLAS, min_size.max(sizes.acceleration_structure_size));
    let scratch = guarded(a, min_scratch.max(full.build_scratch_size).max(full.update_scratch_size));
    build_grid_into(a, m, &dst, scratch.address(a), count, flags);
    (dst, scratch)
}

pub fn build_grid_into(a: &Accel, m: &Mesh, dst: &Dst, scratch: u64, count: u32, flags: vk::BuildAccelerationStructureFlagsKHR) {
    let geoms = [mesh_geom(a, m)];
    let inf = info(BLAS, flags, &geoms).dst_acceleration_structure(dst.s).scratch_data(madr(scratch));
    cmd_build(a, &[inf], &[&[range(count)]]);
    let h = header_of(a, dst).expect("the valid build produced a structure");
    assert_eq!(h.primitive_count, count);
}

/// A valid BLAS of the whole grid that traverses like the grid.
pub fn valid_blas(a: &Accel, m: &Mesh, flags: vk::BuildAccelerationStructureFlagsKHR) -> (Dst, Region) {
    let (dst, scratch) = prebuilt_blas(a, m, 0, 0, m.count, flags);
    assert_grid_hits(&dst.r.read(a), &NoDevice);
    assert_guards(a, dst.r);
    assert_guards(a, scratch);
    (dst, scratch)
}

/// A guarded TOP_LEVEL destination of at least `min_size` bytes holding a valid build of one
/// identity instance of `blas`, and a guarded scratch region of at least `min_scratch` bytes.
pub fn prebuilt_tlas(a: &Accel, blas: &Dst, min_size: u64, min_scratch: u64) -> (Dst, Region) {
    let inst = guarded_data(a, &instance(a.address_of(blas.s)));
    let geoms = [instances_geom(inst.address(a), false)];
    let inf = info(TLAS, NO_FLAGS, &geoms);
    let sizes = a.sizes(DEVICE, &inf, &[1]);
    let dst = guarded_structure(a, TLAS, min_size.max(sizes.acceleration_structure_size));
    let scratch = guarded(a, min_scratch.max(sizes.build_scratch_size).max(sizes.update_scratch_size));
    let inf = inf.dst_acceleration_structure(dst.s).scratch_data(madr(scratch.address(a)));
    cmd_build(a, &[inf], &[&[range(1)]]);
    assert_tlas_hits(a, &dst, blas);
    (dst, scratch)
}

/// Rays straight down onto the grid hit at t = 1; rays beside it miss.
pub fn assert_grid_hits(structure: &[u8], view: &dyn accel::DeviceView) {
    assert!(accel::header(structure).is_some(), "not a valid structure");
    for (x, y) in [(0.1, 0.13), (0.3, 0.55), (0.93, 0.27), (0.61, 0.87), (0.02, 0.98)] {
        let ray = Ray { origin: Vec3::new(x, y, 1.0), direction: Vec3::new(0.0, 0.0, -1.0), tmin: 0.0, tmax: 10.0 };
        let hit = accel::closest_hit(structure, view, ray, RayFlags(0), 0xFF);
        let hit = hit.unwrap_or_else(|| panic!("the ray at ({x}, {y}) misses the grid"));
        assert!((hit.t - 1.0).abs() < 1e-5, "hit at t = {}", hit.t);
    }
    for (x, y) in [(1.5, 0.5), (-0.5, 0.3)] {
        let ray = Ray { origin: Vec3::new(x, y, 1.0), direction: Vec3::new(0.0, 0.0, -1.0), tmin: 0.0, tmax: 10.0 };
        assert!(accel::closest_hit(structure, view, ray, RayFlags(0), 0xFF).is_none(), "the ray at ({x}, {y}) hits");
    }
}

pub fn assert_tlas_hits(a: &Accel, tlas: &Dst, blas: &Dst) {
    let mut view = MapView::new();
    view.insert(a.address_of(blas.s), blas.r.read(a));
    assert_grid_hits(&tlas.r.read(a), &view);
}

pub fn grid_sizes(a: &Accel, m: &Mesh) -> vk::AccelerationStructureBuildSizesInfoKHR<'static> {
    let geoms = [mesh_geom(a, m)];
    a.sizes(DEVICE, &info(BLAS, NO_FLAGS, &geoms), &[m.count])
}

pub fn host_grid_geom(a: &Accel, m: &Mesh) -> Geom {
    tri(m.v.host_ptr(a) as u64, m.i.host_ptr(a) as u64, m.max_vertex, 0)
}

/// A buffer with no memory bound and a structure on it (destroyed by the caller's `unbound_done`).
pub fn unbound_structure(a: &Accel, size: u64, ty: vk::AccelerationStructureTypeKHR) -> (vk::Buffer, vk::AccelerationStructureKHR) {
    // SAFETY: valid create infos; destroyed by `unbound_done`.
    unsafe {
        let buffer = a.ctx.device.create_buffer(&vk::BufferCreateInfo::default().size(size).usage(ALL_USAGE), None).unwrap();
        let s = a
            .ext
            .create_acceleration_structure(&vk::AccelerationStructureCreateInfoKHR::default().buffer(buffer).size(size).ty(ty), None)
            .unwrap();
        (buffer, s)
    }
}

pub fn unbound_done(a: &Accel, (buffer, s): (vk::Buffer, vk::AccelerationStructureKHR)) {
    // SAFETY: the device is idle after the submission's wait; destroyed once.
    unsafe {
        a.ext.destroy_acceleration_structure(s, None);
        a.ctx.device.destroy_buffer(buffer, None);
    }
}
/// A handle that viewed `victim`'s memory and was destroyed: a value no command may accept.
pub fn destroyed_handle(a: &Accel, victim: &Dst) -> vk::AccelerationStructureKHR {
    let ci = vk::AccelerationStructureCreateInfoKHR::default()
        .buffer(a.buf(victim.r.buf).buffer)
        .offset(victim.r.offset)
        .size(victim.r.len)
        .ty(BLAS);
    // SAFETY: valid create info; the handle is destroyed at once and only passed as a value.
    unsafe {
        let s = a.ext.create_acceleration_structure(&ci, None).unwrap();
        a.ext.destroy_acceleration_structure(s, None);
        s
    }
}

// ---------------------------------------------------------------------------------------------
// The checks

/// What one invalid command must produce.
pub struct Expect<'a> {
    /// The command the diagnostic names.
    pub command: &'a str,
    /// The full VUID.
    pub vuid: String,
    /// Texts that some line naming the VUID must contain (indices, messages).
    pub needles: &'a [&'a str],
    /// The only regions the command may write (destinations and scratch).
    pub writable: &'a [Region],
    /// Destinations that held a valid structure and must be invalid afterwards.
    pub invalidated: &'a [&'a Dst],
}

/// Run `submit` (records, submits and waits for one invalid command) and check 1-4.
pub fn expect_invalid(a: &Accel, e: Expect, submit: impl FnOnce()) {
    for d in e.invalidated {
        assert!(header_of(a, d).is_some(), "test setup: the destination should hold a valid structure before");
    }
    let snap = snapshot(a);
    let mark = super::diagnostics().len();
    submit();
    let tail = super::diagnostics()[mark..].to_string();
    // A VUID starting with '-' is matched by its last components only (VUIDs of structures, whose
    // first component the driver may name after the command).
    let prefix = format!("arbor: error: {}: [{}", e.command, if e.vuid.starts_with('-') { "VUID-" } else { &e.vuid });
    let close = format!("{}] ", if e.vuid.starts_with('-') { &e.vuid } else { "" });
    let names_it = |l: &str| l.starts_with(&prefix) && l[prefix.len()..].split_once("] ").is_some_and(|(v, _)| format!("{v}] ").ends_with(&close));
    let lines: Vec<&str> = tail.lines().filter(|l| names_it(l)).collect();
    assert!(!lines.is_empty(), "expected a line starting with {prefix:?} naming {}; the driver reported:\n{tail}", e.vuid);
    for n in e.needles {
        assert!(lines.iter().any(|l| l.contains(n)), "no [{}] line contains {n:?}; the driver reported:\n{tail}", e.vuid);
    }
    for l in tail.lines() {
        assert!(!l.contains("panic") && !l.contains("internal error"), "the driver hit an internal error: {l}");
        if l.starts_with("arbor: error:") {
            assert!(names_it(l), "unexpected diagnostic besides [{}]: {l}", e.vuid);
        }
    }
    verify(a, &snap, e.writable);
    for d in e.invalidated {
        assert!(header_of(a, d).is_none(), "the destination of the invalid command still reads as a valid structure");
    }
}

/// A context with the validation layer off. Instance creation is retried a few times: other
/// processes sharing target/ rewrite the test ICD manifest (and the driver) in place, and a
/// loader reading it at that moment answers ERROR_INCOMPATIBLE_DRIVER.
pub fn context() -> super::Context {
    let opts = super::Options { validation: false, acceleration_structure: true, ..Default::default() };
    let mut attempt = 0;
    loop {
        match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| super::Context::new(opts.clone()))) {
            Ok(ctx) => return ctx,
            Err(e) if attempt < 5 => {
                let what = e.downcast_ref::<String>().cloned().or_else(|| e.downcast_ref::<&str>().map(|s| s.to_string()));
                eprintln!("context creation failed ({what:?}); retrying");
                attempt += 1;
                std::thread::sleep(std::time::Duration::from_millis(300));
            }
            Err(e) => std::panic::resume_unwind(e),
        }
    }
}

/// A test device (validation layer off), the helper and the grid; after `f`, a valid build on
/// the same device and queue must traverse.
pub fn scenario(f: impl FnOnce(&Accel, &Mesh)) {
    let _serial = serial();
    let ctx = context();
    let a = Accel::new(&ctx);
    let m = upload_grid(&a);
    f(&a, &m);
    assert_eq!(m.v.read(&a), m.vertex_bytes, "vertex input changed");
    assert_eq!(m.i.read(&a), m.index_bytes, "index input changed");
    assert_guards(&a, m.v);
    assert_guards(&a, m.i);
    valid_blas(&a, &m, vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE);
    a.destroy();
    ctx.finish();
}

/// "pInfos-03711" → the VUID of vkCmdBuildAccelerationStructuresKHR; "-type-03789" (a VUID of a
/// structure) stays a suffix to match.
pub fn cmd_vuid(vuid: &str) -> String {
    if vuid.starts_with('-') {
        vuid.to_string()
    } else {
        format!("VUID-{CMD}-{vuid}")
    }
}

pub fn without(usage: vk::BufferUsageFlags) -> vk::BufferUsageFlags {
    vk::BufferUsageFlags::from_raw(ALL_USAGE.as_raw() & !usage.as_raw())
}

//! Issue 4: one negative test per valid-usage check the driver implements for acceleration-
//! structure builds, copies and property queries (DESIGN.md principle 7).
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
//! Diagnostics are per process and the tests of this binary run in parallel: every test holds
//! `SERIAL`, so the diagnostics appended while a test runs are that test's own.
mod support;

use std::ffi::c_void;
use std::sync::{Mutex, MutexGuard};

use arbor::accel::{self, MapView, NoDevice, Ray, RayFlags};
use ash::vk;
use glam::Vec3;
use support::accel::{instance_record, Accel, ALL_USAGE};

type Geom = vk::AccelerationStructureGeometryKHR<'static>;
type Info<'a> = vk::AccelerationStructureBuildGeometryInfoKHR<'a>;
type Range = vk::AccelerationStructureBuildRangeInfoKHR;

const BLAS: vk::AccelerationStructureTypeKHR = vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL;
const TLAS: vk::AccelerationStructureTypeKHR = vk::AccelerationStructureTypeKHR::TOP_LEVEL;
const DEVICE: vk::AccelerationStructureBuildTypeKHR = vk::AccelerationStructureBuildTypeKHR::DEVICE;
const NO_FLAGS: vk::BuildAccelerationStructureFlagsKHR = vk::BuildAccelerationStructureFlagsKHR::empty();
const ALLOW_UPDATE: vk::BuildAccelerationStructureFlagsKHR = vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE;

const CMD: &str = "vkCmdBuildAccelerationStructuresKHR";
const CMD_INDIRECT: &str = "vkCmdBuildAccelerationStructuresIndirectKHR";
const HOST: &str = "vkBuildAccelerationStructuresKHR";

/// Guard bytes before and after every destination, scratch and input region.
const GUARD: u64 = 4096;
const FILL: u8 = 0xA5;
/// The test mesh: a GRID x GRID grid of quads (two triangles each) over [0,1]^2 at z = 0.
const GRID: u32 = 8;
const IDENTITY: [f32; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

static SERIAL: Mutex<()> = Mutex::new(());

fn serial() -> MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

// ---------------------------------------------------------------------------------------------
// Regions, guards, snapshots

/// `len` bytes at `offset` in buffer `buf` of the test's `Accel`.
#[derive(Clone, Copy, Debug)]
struct Region {
    buf: usize,
    offset: u64,
    len: u64,
}

impl Region {
    fn address(&self, a: &Accel) -> u64 {
        a.buf(self.buf).address + self.offset
    }
    fn host_ptr(&self, a: &Accel) -> *mut u8 {
        // SAFETY: offset is inside the mapped buffer.
        unsafe { a.buf(self.buf).ptr.add(self.offset as usize) }
    }
    fn read(&self, a: &Accel) -> Vec<u8> {
        a.buf(self.buf).read(self.offset as usize, self.len as usize)
    }
    fn write(&self, a: &Accel, at: u64, data: &[u8]) {
        a.buf(self.buf).write((self.offset + at) as usize, data)
    }
}

/// `len` bytes with GUARD bytes of 0xA5 before and at least GUARD after, in a buffer of its own
/// (offset GUARD: 256-aligned, so usable for structures, scratch and every input).
fn guarded_with(a: &Accel, len: u64, usage: vk::BufferUsageFlags) -> Region {
    let b = a.buffer_with(GUARD + len.next_multiple_of(256) + GUARD, usage);
    a.fill(b, FILL);
    Region { buf: b, offset: GUARD, len }
}

fn guarded(a: &Accel, len: u64) -> Region {
    guarded_with(a, len, ALL_USAGE)
}

fn guarded_data(a: &Accel, data: &[u8]) -> Region {
    let r = guarded(a, data.len() as u64);
    r.write(a, 0, data);
    r
}

fn assert_guards(a: &Accel, r: Region) {
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
struct Snapshot(Vec<Vec<u8>>);

fn snapshot(a: &Accel) -> Snapshot {
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
fn verify(a: &Accel, snap: &Snapshot, writable: &[Region]) {
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
fn freed_address(a: &Accel, size: u64) -> u64 {
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
struct Dst {
    s: vk::AccelerationStructureKHR,
    r: Region,
}

fn guarded_structure(a: &Accel, ty: vk::AccelerationStructureTypeKHR, size: u64) -> Dst {
    let r = guarded(a, size);
    Dst { s: a.structure_at(r.buf, r.offset, size, ty), r }
}

/// A structure at `offset` of an existing region's buffer.
fn structure_in(a: &Accel, buf: usize, offset: u64, size: u64, ty: vk::AccelerationStructureTypeKHR) -> Dst {
    Dst { s: a.structure_at(buf, offset, size, ty), r: Region { buf, offset, len: size } }
}

fn header_of(a: &Accel, d: &Dst) -> Option<accel::Header> {
    accel::header(&d.r.read(a))
}

fn cadr(address: u64) -> vk::DeviceOrHostAddressConstKHR {
    vk::DeviceOrHostAddressConstKHR { device_address: address }
}

fn madr(address: u64) -> vk::DeviceOrHostAddressKHR {
    vk::DeviceOrHostAddressKHR { device_address: address }
}

struct Mesh {
    v: Region,
    i: Region,
    vertex_bytes: Vec<u8>,
    index_bytes: Vec<u8>,
    max_vertex: u32,
    count: u32,
}

fn grid() -> (Vec<u8>, Vec<u8>) {
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

fn upload_grid(a: &Accel) -> Mesh {
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
fn tri(vertex: u64, index: u64, max_vertex: u32, transform: u64) -> Geom {
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

fn mesh_geom(a: &Accel, m: &Mesh) -> Geom {
    tri(m.v.address(a), m.i.address(a), m.max_vertex, 0)
}

fn aabbs_geom(data: u64, stride: u64) -> Geom {
    Geom::default()
        .geometry_type(vk::GeometryTypeKHR::AABBS)
        .flags(vk::GeometryFlagsKHR::OPAQUE)
        .geometry(vk::AccelerationStructureGeometryDataKHR {
            aabbs: vk::AccelerationStructureGeometryAabbsDataKHR::default().data(cadr(data)).stride(stride),
        })
}

fn instances_geom(data: u64, array_of_pointers: bool) -> Geom {
    Geom::default().geometry_type(vk::GeometryTypeKHR::INSTANCES).geometry(vk::AccelerationStructureGeometryDataKHR {
        instances: vk::AccelerationStructureGeometryInstancesDataKHR::default()
            .array_of_pointers(array_of_pointers)
            .data(cadr(data)),
    })
}

fn instance(reference: u64) -> [u8; 64] {
    instance_record(IDENTITY, 0, 0xFF, 0, 0, reference)
}

fn info(ty: vk::AccelerationStructureTypeKHR, flags: vk::BuildAccelerationStructureFlagsKHR, geoms: &[Geom]) -> Info<'_> {
    Info::default().ty(ty).flags(flags).mode(vk::BuildAccelerationStructureModeKHR::BUILD).geometries(geoms)
}

fn update_info<'a>(
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

fn range(count: u32) -> Range {
    Range::default().primitive_count(count)
}

fn cmd_build(a: &Accel, infos: &[Info], ranges: &[&[Range]]) {
    a.submit(|cb| {
        // SAFETY: recording command buffer; the arrays match (ash asserts the lengths).
        unsafe { a.ext.cmd_build_acceleration_structures(cb, infos, ranges) };
    });
}

/// One indirect build of one info with one geometry; `update` first writes a range record with
/// vkCmdUpdateBuffer (and a barrier) in the same command buffer.
fn cmd_build_indirect(a: &Accel, inf: &Info, address: u64, stride: u32, max_count: u32, update: Option<(Region, [u32; 4])>) {
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

fn record(count: u32) -> Vec<u8> {
    [count, 0, 0, 0].iter().flat_map(|w| w.to_le_bytes()).collect()
}

/// A guarded BOTTOM_LEVEL destination of at least `min_size` bytes holding a valid build of the
/// first `count` grid triangles, and a guarded scratch region of at least `min_scratch` bytes
/// (and at least the build and update scratch of the whole grid).
fn prebuilt_blas(a: &Accel, m: &Mesh, min_size: u64, min_scratch: u64, count: u32, flags: vk::BuildAccelerationStructureFlagsKHR) -> (Dst, Region) {
    let geoms = [mesh_geom(a, m)];
    let inf = info(BLAS, flags, &geoms);
    let sizes = a.sizes(DEVICE, &inf, &[count]);
    let full = a.sizes(DEVICE, &inf, &[m.count]);
    let dst = guarded_structure(a, BLAS, min_size.max(sizes.acceleration_structure_size));
    let scratch = guarded(a, min_scratch.max(full.build_scratch_size).max(full.update_scratch_size));
    build_grid_into(a, m, &dst, scratch.address(a), count, flags);
    (dst, scratch)
}

fn build_grid_into(a: &Accel, m: &Mesh, dst: &Dst, scratch: u64, count: u32, flags: vk::BuildAccelerationStructureFlagsKHR) {
    let geoms = [mesh_geom(a, m)];
    let inf = info(BLAS, flags, &geoms).dst_acceleration_structure(dst.s).scratch_data(madr(scratch));
    cmd_build(a, &[inf], &[&[range(count)]]);
    let h = header_of(a, dst).expect("the valid build produced a structure");
    assert_eq!(h.primitive_count, count);
}

/// A valid BLAS of the whole grid that traverses like the grid.
fn valid_blas(a: &Accel, m: &Mesh, flags: vk::BuildAccelerationStructureFlagsKHR) -> (Dst, Region) {
    let (dst, scratch) = prebuilt_blas(a, m, 0, 0, m.count, flags);
    assert_grid_hits(&dst.r.read(a), &NoDevice);
    assert_guards(a, dst.r);
    assert_guards(a, scratch);
    (dst, scratch)
}

/// A guarded TOP_LEVEL destination of at least `min_size` bytes holding a valid build of one
/// identity instance of `blas`, and a guarded scratch region of at least `min_scratch` bytes.
fn prebuilt_tlas(a: &Accel, blas: &Dst, min_size: u64, min_scratch: u64) -> (Dst, Region) {
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
fn assert_grid_hits(structure: &[u8], view: &dyn accel::DeviceView) {
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

fn assert_tlas_hits(a: &Accel, tlas: &Dst, blas: &Dst) {
    let mut view = MapView::new();
    view.insert(a.address_of(blas.s), blas.r.read(a));
    assert_grid_hits(&tlas.r.read(a), &view);
}

// ---------------------------------------------------------------------------------------------
// The checks

/// What one invalid command must produce.
struct Expect<'a> {
    /// The command the diagnostic names.
    command: &'a str,
    /// The full VUID.
    vuid: String,
    /// Texts that some line naming the VUID must contain (indices, messages).
    needles: &'a [&'a str],
    /// The only regions the command may write (destinations and scratch).
    writable: &'a [Region],
    /// Destinations that held a valid structure and must be invalid afterwards.
    invalidated: &'a [&'a Dst],
}

/// Run `submit` (records, submits and waits for one invalid command) and check 1-4.
fn expect_invalid(a: &Accel, e: Expect, submit: impl FnOnce()) {
    for d in e.invalidated {
        assert!(header_of(a, d).is_some(), "test setup: the destination should hold a valid structure before");
    }
    let snap = snapshot(a);
    let mark = support::diagnostics().len();
    submit();
    let tail = support::diagnostics()[mark..].to_string();
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
fn context() -> support::Context {
    let opts = support::Options { validation: false, acceleration_structure: true, ..Default::default() };
    let mut attempt = 0;
    loop {
        match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| support::Context::new(opts.clone()))) {
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
fn scenario(f: impl FnOnce(&Accel, &Mesh)) {
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
fn cmd_vuid(vuid: &str) -> String {
    if vuid.starts_with('-') {
        vuid.to_string()
    } else {
        format!("VUID-{CMD}-{vuid}")
    }
}

fn without(usage: vk::BufferUsageFlags) -> vk::BufferUsageFlags {
    vk::BufferUsageFlags::from_raw(ALL_USAGE.as_raw() & !usage.as_raw())
}

// ---------------------------------------------------------------------------------------------
// Handles and types

#[test]
fn build_into_a_destroyed_handle_03800() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        // A second handle viewing the victim's memory, destroyed before the build.
        let ci = vk::AccelerationStructureCreateInfoKHR::default()
            .buffer(a.buf(victim.r.buf).buffer)
            .offset(victim.r.offset)
            .size(victim.r.len)
            .ty(BLAS);
        // SAFETY: valid create info; the handle is destroyed at once and only passed as a value.
        let stale = unsafe {
            let s = a.ext.create_acceleration_structure(&ci, None).unwrap();
            a.ext.destroy_acceleration_structure(s, None);
            s
        };
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(stale).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-dstAccelerationStructure-03800"),
                needles: &["pInfos[0]: dstAccelerationStructure", "is not a valid handle"],
                writable: &[],
                invalidated: &[],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        // The handle lookup fails: nothing is written, not even the memory the handle viewed.
        assert!(header_of(a, &victim).is_some());
    });
}

#[test]
fn top_level_build_into_a_bottom_level_structure_03699() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(a.address_of(blas.s)));
        let geoms = [instances_geom(inst.address(a), false)];
        let inf = info(TLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(DEVICE, &inf, &[1]);
        let (victim, scratch) = prebuilt_blas(a, m, sizes.acceleration_structure_size, sizes.build_scratch_size, m.count, NO_FLAGS);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03699"),
                needles: &["pInfos[0]: dstAccelerationStructure was created with another type"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(1)]]),
        );
    });
}

#[test]
fn bottom_level_build_into_a_top_level_structure_03700() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(DEVICE, &inf, &[m.count]);
        let (victim, scratch) = prebuilt_tlas(a, &blas, sizes.acceleration_structure_size, sizes.build_scratch_size);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03700"),
                needles: &["pInfos[0]: dstAccelerationStructure was created with another type"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Indirect builds

#[test]
fn indirect_primitive_count_above_max_03653() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let records = guarded(a, 16);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        let needle = format!("pInfos[0]: geometry 0: indirect primitiveCount {} exceeds ppMaxPrimitiveCounts 64", m.count);
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-ppMaxPrimitiveCounts-03653"),
                needles: &[&needle],
                // The record itself is written by the vkCmdUpdateBuffer of the same submission.
                writable: &[victim.r, scratch, records],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, records.address(a), 16, 64, Some((records, [m.count, 0, 0, 0]))),
        );
        assert_eq!(records.read(a), record(m.count));
        assert_guards(a, records);
        // The same record within its maximum builds: the indirect path itself works.
        cmd_build_indirect(a, &inf, records.address(a), 16, m.count, None);
        assert_grid_hits(&victim.r.read(a), &NoDevice);
    });
}

#[test]
fn indirect_records_outside_their_buffer_03646() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        // A 64-byte buffer: a 16-byte record at offset 56 runs 8 bytes past its end.
        let b = a.buffer(64);
        a.fill(b, FILL);
        let address = a.buf(b).address + 56;
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-pIndirectDeviceAddresses-03646"),
                needles: &["pInfos[0]: indirect records", "are not inside one buffer"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, address, 16, m.count, None),
        );
    });
}

#[test]
fn indirect_buffer_without_indirect_usage_03647() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let records = guarded_with(a, 16, without(vk::BufferUsageFlags::INDIRECT_BUFFER));
        records.write(a, 0, &record(m.count));
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-pIndirectDeviceAddresses-03647"),
                needles: &["pInfos[0]: the buffer of the indirect records lacks INDIRECT_BUFFER usage"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, records.address(a), 16, m.count, None),
        );
    });
}

#[test]
fn indirect_address_not_a_multiple_of_4_03648() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let records = guarded(a, 18);
        records.write(a, 2, &record(m.count));
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-pIndirectDeviceAddresses-03648"),
                needles: &["pInfos[0]: indirect address", "is not a multiple of 4"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, records.address(a) + 2, 16, m.count, None),
        );
    });
}

#[test]
fn indirect_stride_not_a_multiple_of_4_03787() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let records = guarded_data(a, &record(m.count));
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-pIndirectStrides-03787"),
                needles: &["pInfos[0]: indirect stride 18 is not a multiple of 4"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, records.address(a), 18, m.count, None),
        );
    });
}

#[test]
fn indirect_destination_smaller_than_the_size_query_03652() {
    scenario(|a, m| {
        // Sized (and validly built) for 8 triangles; the indirect build allows the whole grid.
        let (victim, scratch) = prebuilt_blas(a, m, 0, 0, 8, NO_FLAGS);
        let records = guarded_data(a, &record(8));
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        assert!(a.sizes(DEVICE, &inf, &[m.count]).acceleration_structure_size > victim.r.len);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-pInfos-03652"),
                needles: &["pInfos[0]: dstAccelerationStructure size", "the size query requires"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, records.address(a), 16, m.count, None),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Geometry inputs

/// A BLAS build of `geoms` (one range of `count` each) into a prebuilt victim: checks `vuid`.
fn invalid_blas_build(a: &Accel, m: &Mesh, geoms: &[Geom], count: u32, vuid: &str, needles: &[&str]) {
    let inf = info(BLAS, NO_FLAGS, geoms);
    let counts = vec![count; geoms.len()];
    let sizes = a.sizes(DEVICE, &inf, &counts);
    let (victim, scratch) = prebuilt_blas(a, m, sizes.acceleration_structure_size, sizes.build_scratch_size, m.count, NO_FLAGS);
    let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
    let ranges = vec![range(count); geoms.len()];
    expect_invalid(
        a,
        Expect { command: CMD, vuid: cmd_vuid(vuid), needles, writable: &[victim.r, scratch], invalidated: &[&victim] },
        || cmd_build(a, &[inf], &[&ranges]),
    );
}

#[test]
fn vertex_data_not_mapped_03804() {
    scenario(|a, m| {
        let gone = freed_address(a, 4096);
        let geoms = [tri(gone, m.i.address(a), m.max_vertex, 0)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03804", &["pInfos[0]: geometry 0: [0x"]);
    });
}

#[test]
fn vertex_data_misaligned_03711() {
    scenario(|a, m| {
        let v = guarded(a, m.vertex_bytes.len() as u64 + 2);
        v.write(a, 2, &m.vertex_bytes);
        let geoms = [tri(v.address(a) + 2, m.i.address(a), m.max_vertex, 0)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03711", &["pInfos[0]: geometry 0: vertexData", "is not aligned to 4"]);
    });
}

#[test]
fn index_data_misaligned_03712() {
    scenario(|a, m| {
        let i = guarded(a, m.index_bytes.len() as u64 + 2);
        i.write(a, 2, &m.index_bytes);
        let geoms = [tri(m.v.address(a), i.address(a) + 2, m.max_vertex, 0)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03712", &["pInfos[0]: geometry 0: indexData", "is not aligned to 4"]);
    });
}

#[test]
fn transform_data_misaligned_03810() {
    scenario(|a, m| {
        let t = guarded(a, 48 + 4);
        let bytes: Vec<u8> = IDENTITY.iter().flat_map(|f| f.to_le_bytes()).collect();
        t.write(a, 4, &bytes);
        let geoms = [tri(m.v.address(a), m.i.address(a), m.max_vertex, t.address(a) + 4)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03810", &["pInfos[0]: geometry 0: transformData", "is not aligned to 16"]);
    });
}

fn boxes(n: usize) -> Vec<u8> {
    (0..n)
        .flat_map(|k| {
            let x = k as f32 / n as f32;
            [x, 0.0, -0.1, x + 0.5 / n as f32, 1.0, 0.1].into_iter().flat_map(f32::to_le_bytes)
        })
        .collect()
}

#[test]
fn aabb_data_misaligned_03714() {
    scenario(|a, m| {
        let data = boxes(4);
        let r = guarded(a, data.len() as u64 + 4);
        r.write(a, 4, &data);
        let geoms = [aabbs_geom(r.address(a) + 4, 24)];
        invalid_blas_build(a, m, &geoms, 4, "pInfos-03714", &["pInfos[0]: geometry 0: aabbs.data", "is not aligned to 8"]);
    });
}

/// A TLAS build over `geom` (one range of `count`) into a prebuilt TLAS victim: checks `vuid`.
fn invalid_tlas_build(a: &Accel, blas: &Dst, geom: Geom, count: u32, vuid: &str, needles: &[&str]) {
    let geoms = [geom];
    let inf = info(TLAS, NO_FLAGS, &geoms);
    let sizes = a.sizes(DEVICE, &inf, &[count]);
    let (victim, scratch) = prebuilt_tlas(a, blas, sizes.acceleration_structure_size, sizes.build_scratch_size);
    let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
    expect_invalid(
        a,
        Expect { command: CMD, vuid: cmd_vuid(vuid), needles, writable: &[victim.r, scratch], invalidated: &[&victim] },
        || cmd_build(a, &[inf], &[&[range(count)]]),
    );
}

#[test]
fn instance_array_misaligned_03715() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let r = guarded(a, 64 + 8);
        r.write(a, 8, &instance(a.address_of(blas.s)));
        invalid_tlas_build(a, &blas, instances_geom(r.address(a) + 8, false), 1, "pInfos-03715", &["pInfos[0]: geometry 0: instances.data", "is not aligned to 16"]);
    });
}

#[test]
fn instance_pointer_array_misaligned_03716() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(a.address_of(blas.s)));
        let pointers = guarded(a, 8 + 4);
        pointers.write(a, 4, &inst.address(a).to_le_bytes());
        invalid_tlas_build(a, &blas, instances_geom(pointers.address(a) + 4, true), 1, "pInfos-03716", &["pInfos[0]: geometry 0: instances.data", "is not aligned to 8"]);
    });
}

#[test]
fn instance_pointer_element_misaligned_03717() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded(a, 64 + 8);
        inst.write(a, 8, &instance(a.address_of(blas.s)));
        let pointers = guarded_data(a, &(inst.address(a) + 8).to_le_bytes());
        invalid_tlas_build(a, &blas, instances_geom(pointers.address(a), true), 1, "pInfos-03717", &["pInfos[0]: geometry 0: instance pointer 0", "is not aligned to 16"]);
    });
}

#[test]
fn vertex_buffer_without_build_input_usage_03673() {
    scenario(|a, m| {
        let v = guarded_with(a, m.vertex_bytes.len() as u64, without(vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR));
        v.write(a, 0, &m.vertex_bytes);
        let geoms = [tri(v.address(a), m.i.address(a), m.max_vertex, 0)];
        invalid_blas_build(a, m, &geoms, m.count, "geometry-03673", &["pInfos[0]: geometry 0: the buffer at", "lacks ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY usage"]);
    });
}

#[test]
fn index_above_max_vertex_03651() {
    scenario(|a, m| {
        let mut indices = m.index_bytes.clone();
        let n = indices.len();
        indices[n - 4..].copy_from_slice(&(m.max_vertex + 1).to_le_bytes());
        let i = guarded_data(a, &indices);
        let geoms = [tri(m.v.address(a), i.address(a), m.max_vertex, 0)];
        let needle = format!("pInfos[0]: geometry 0 primitive {}: index {} exceeds maxVertex", m.count - 1, m.max_vertex + 1);
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03651", &[&needle]);
    });
}

#[test]
fn instance_reference_to_plain_memory_12281() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(m.v.address(a)));
        invalid_tlas_build(a, &blas, instances_geom(inst.address(a), false), 1, "pInfos-12281", &["pInfos[0]: geometry 0: instance 0: accelerationStructureReference", "is neither 0 nor a built bottom-level structure"]);
    });
}

#[test]
fn instance_reference_to_a_top_level_structure_12281() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let (other_tlas, _) = prebuilt_tlas(a, &blas, 0, 0);
        let inst = guarded_data(a, &instance(a.address_of(other_tlas.s)));
        invalid_tlas_build(a, &blas, instances_geom(inst.address(a), false), 1, "pInfos-12281", &["pInfos[0]: geometry 0: instance 0: accelerationStructureReference", "is neither 0 nor a built bottom-level structure"]);
        assert_tlas_hits(a, &other_tlas, &blas);
    });
}

// ---------------------------------------------------------------------------------------------
// Destination and scratch

#[test]
fn destination_smaller_than_the_size_query_03675() {
    scenario(|a, m| {
        // Sized (and validly built) for 8 triangles; the build is of the whole grid. The guard
        // right after the destination is in the same buffer.
        let (victim, scratch) = prebuilt_blas(a, m, 0, 0, 8, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        assert!(a.sizes(DEVICE, &inf, &[m.count]).acceleration_structure_size > victim.r.len);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03675"),
                needles: &["pInfos[0]: dstAccelerationStructure size", "the size query requires"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        assert_guards(a, victim.r);
    });
}

#[test]
fn scratch_running_past_its_buffer_12258() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let need = a.sizes(DEVICE, &inf, &[m.count]).build_scratch_size;
        assert!(need >= 256, "the grid needs scratch ({need})");
        // Half the scratch the build needs, at the start of a buffer of that size.
        let b = a.buffer(need / 2);
        a.fill(b, FILL);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(a.buf(b).address));
        let short = Region { buf: b, offset: 0, len: need / 2 };
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-12258"),
                needles: &["pInfos[0]: scratch", "(buildScratchSize) is not inside one buffer"],
                writable: &[victim.r, short],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn scratch_misaligned_03710() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        // Enough scratch, inside its buffer, but 64 bytes past a 128-byte boundary.
        let scratch = guarded(a, a.sizes(DEVICE, &inf, &[m.count]).build_scratch_size + 64);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a) + 64));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03710"),
                needles: &["pInfos[0]: scratchData", "is not a multiple of 128"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Overlaps between the elements of one command

fn grid_sizes(a: &Accel, m: &Mesh) -> vk::AccelerationStructureBuildSizesInfoKHR<'static> {
    let geoms = [mesh_geom(a, m)];
    a.sizes(DEVICE, &info(BLAS, NO_FLAGS, &geoms), &[m.count])
}

#[test]
fn destinations_overlap_03702() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let size = sizes.acceleration_structure_size;
        // Two structures 256 bytes apart in one buffer.
        let both = guarded(a, size + 256);
        let s0 = structure_in(a, both.buf, GUARD, size, BLAS);
        let s1 = structure_in(a, both.buf, GUARD + 256, size, BLAS);
        let sc0 = guarded(a, sizes.build_scratch_size);
        let sc1 = guarded(a, sizes.build_scratch_size);
        build_grid_into(a, m, &s0, sc0.address(a), m.count, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s0.s).scratch_data(madr(sc0.address(a)));
        let i1 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s1.s).scratch_data(madr(sc1.address(a)));
        let r = [range(m.count)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-dstAccelerationStructure-03702"),
                needles: &["pInfos[0]: dst overlaps the dst of pInfos[1]", "pInfos[1]: dst overlaps the dst of pInfos[0]"],
                writable: &[both, sc0, sc1],
                invalidated: &[&s0],
            },
            || cmd_build(a, &[i0, i1], &[&r, &r]),
        );
        assert!(header_of(a, &s1).is_none());
        assert_guards(a, both);
    });
}

#[test]
fn destination_overlaps_the_scratch_of_another_element_03703() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        // Element 0's destination, in a buffer large enough to also hold element 1's scratch
        // starting at the same byte.
        let shared = guarded(a, sizes.acceleration_structure_size.max(sizes.build_scratch_size));
        let s0 = structure_in(a, shared.buf, GUARD, sizes.acceleration_structure_size, BLAS);
        let sc0 = guarded(a, sizes.build_scratch_size);
        build_grid_into(a, m, &s0, sc0.address(a), m.count, NO_FLAGS);
        let s1 = guarded_structure(a, BLAS, sizes.acceleration_structure_size);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s0.s).scratch_data(madr(sc0.address(a)));
        let i1 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s1.s).scratch_data(madr(shared.address(a)));
        let r = [range(m.count)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-dstAccelerationStructure-03703"),
                needles: &["pInfos[0]: dst overlaps the scratch of pInfos[1]"],
                writable: &[shared, sc0, s1.r],
                invalidated: &[&s0],
            },
            || cmd_build(a, &[i0, i1], &[&r, &r]),
        );
        assert_guards(a, shared);
    });
}

#[test]
fn destination_overlaps_its_own_scratch_03703() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let shared = guarded(a, sizes.acceleration_structure_size.max(sizes.build_scratch_size));
        let s0 = structure_in(a, shared.buf, GUARD, sizes.acceleration_structure_size, BLAS);
        let sc0 = guarded(a, sizes.build_scratch_size);
        build_grid_into(a, m, &s0, sc0.address(a), m.count, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s0.s).scratch_data(madr(shared.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-dstAccelerationStructure-03703"),
                needles: &["pInfos[0]: dst overlaps its own scratch memory"],
                writable: &[shared],
                invalidated: &[&s0],
            },
            || cmd_build(a, &[i0], &[&[range(m.count)]]),
        );
        assert_guards(a, shared);
    });
}

#[test]
fn scratch_regions_overlap_03704() {
    scenario(|a, m| {
        let (s0, sc) = valid_blas(a, m, NO_FLAGS);
        let (s1, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s0.s).scratch_data(madr(sc.address(a)));
        let i1 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s1.s).scratch_data(madr(sc.address(a)));
        let r = [range(m.count)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-scratchData-03704"),
                needles: &["pInfos[0]: scratch overlaps the scratch of pInfos[1]", "pInfos[1]: scratch overlaps the scratch of pInfos[0]"],
                writable: &[s0.r, s1.r, sc],
                invalidated: &[&s0, &s1],
            },
            || cmd_build(a, &[i0, i1], &[&r, &r]),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Updates

#[test]
fn update_of_a_structure_built_without_allow_update_03667() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, NO_FLAGS, &geoms, &victim, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03667"),
                needles: &["pInfos[0]: srcAccelerationStructure was not built with ALLOW_UPDATE"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn update_from_a_structure_never_built_03667() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, ALLOW_UPDATE);
        let src = guarded_structure(a, BLAS, victim.r.len);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &src, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03667"),
                needles: &["pInfos[0]: srcAccelerationStructure has not been built"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        assert_guards(a, src.r);
    });
}

#[test]
fn update_with_another_geometry_count_03758() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, ALLOW_UPDATE);
        let geoms = [mesh_geom(a, m), mesh_geom(a, m)];
        let sizes = a.sizes(DEVICE, &info(BLAS, ALLOW_UPDATE, &geoms), &[m.count, m.count]);
        let scratch = guarded(a, sizes.update_scratch_size.max(sizes.build_scratch_size));
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &victim, &victim, scratch.address(a));
        let r = [range(m.count), range(m.count)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03758"),
                needles: &["pInfos[0]: geometryCount differs from the last build of srcAccelerationStructure"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&r]),
        );
    });
}

#[test]
fn update_with_other_flags_03759() {
    scenario(|a, m| {
        let built = ALLOW_UPDATE | vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE;
        let (victim, scratch) = valid_blas(a, m, built);
        let geoms = [mesh_geom(a, m)];
        let flags = ALLOW_UPDATE | vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD;
        let inf = update_info(BLAS, flags, &geoms, &victim, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03759"),
                needles: &["pInfos[0]: flags differ from the last build of srcAccelerationStructure"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn update_with_another_type_03760() {
    scenario(|a, m| {
        // Source: a BLAS built with ALLOW_UPDATE. Update: a TLAS (same flags, one geometry) into
        // a TOP_LEVEL destination that holds a valid TLAS.
        let (src, _) = valid_blas(a, m, ALLOW_UPDATE);
        let inst = guarded_data(a, &instance(a.address_of(src.s)));
        let geoms = [instances_geom(inst.address(a), false)];
        let sizes = a.sizes(DEVICE, &info(TLAS, ALLOW_UPDATE, &geoms), &[1]);
        // Large enough for the TLAS and for the source's size (an update writes that much).
        let (victim, scratch) = prebuilt_tlas(a, &src, sizes.acceleration_structure_size.max(src.r.len), sizes.update_scratch_size);
        let inf = update_info(TLAS, ALLOW_UPDATE, &geoms, &src, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03760"),
                needles: &["pInfos[0]: type differs from the last build of srcAccelerationStructure"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(1)]]),
        );
        // The source was only read.
        assert_grid_hits(&src.r.read(a), &NoDevice);
    });
}

// ---------------------------------------------------------------------------------------------
// Host builds

#[test]
fn host_build_into_a_structure_of_another_type_03700() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let host_geoms = [tri(m.v.host_ptr(a) as u64, m.i.host_ptr(a) as u64, m.max_vertex, 0)];
        let inf = info(BLAS, NO_FLAGS, &host_geoms);
        let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::HOST, &inf, &[m.count]);
        let (victim, _) = prebuilt_tlas(a, &blas, sizes.acceleration_structure_size, 0);
        let mut host_scratch = vec![FILL; sizes.build_scratch_size as usize + 2 * GUARD as usize];
        let scratch_ptr = host_scratch[GUARD as usize..].as_mut_ptr() as *mut c_void;
        let inf = inf
            .dst_acceleration_structure(victim.s)
            .scratch_data(vk::DeviceOrHostAddressKHR { host_address: scratch_ptr });
        let mut result = Ok(());
        expect_invalid(
            a,
            Expect {
                command: HOST,
                vuid: format!("VUID-{HOST}-pInfos-03700"),
                needles: &["pInfos[0]: dstAccelerationStructure was created with another type"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            // SAFETY: host pointers into mapped memory and a live Vec, valid for the call.
            || result = unsafe { a.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[inf], &[&[range(m.count)]]) },
        );
        assert_eq!(result, Ok(()), "outside strict mode an invalid host build is reported, not failed");
        let n = host_scratch.len();
        assert!(host_scratch[..GUARD as usize].iter().chain(&host_scratch[n - GUARD as usize..]).all(|&b| b == FILL));
    });
}

// ---------------------------------------------------------------------------------------------
// Copies

fn cmd_copy(a: &Accel, src: &Dst, dst: &Dst, mode: vk::CopyAccelerationStructureModeKHR) {
    let info = vk::CopyAccelerationStructureInfoKHR::default().src(src.s).dst(dst.s).mode(mode);
    // SAFETY: recording command buffer, valid info.
    a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure(cb, &info) });
}

#[test]
fn compact_without_allow_compaction_03411() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-src-03411".into(),
                needles: &["src was not built with ALLOW_COMPACTION"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_copy(a, &src, &victim, vk::CopyAccelerationStructureModeKHR::COMPACT),
        );
        assert_grid_hits(&src.r.read(a), &NoDevice);
    });
}

#[test]
fn clone_into_a_destination_too_small_12284() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let (victim, _) = prebuilt_blas(a, m, 0, 0, 8, NO_FLAGS);
        assert!(victim.r.len < src.r.len);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-dst-12284".into(),
                needles: &["dst size", "is below the"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_copy(a, &src, &victim, vk::CopyAccelerationStructureModeKHR::CLONE),
        );
        assert_guards(a, victim.r);
    });
}

#[test]
fn clone_from_a_structure_never_built_04963() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let src = guarded_structure(a, BLAS, victim.r.len);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-src-04963".into(),
                needles: &["src has not been built"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_copy(a, &src, &victim, vk::CopyAccelerationStructureModeKHR::CLONE),
        );
    });
}

#[test]
fn deserialize_data_of_another_driver_03749() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let mut blob = a.serialize(src.s);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        blob[0] ^= 0xFF; // driver UUID
        let data = guarded_data(a, &blob);
        let deserialize = |a: &Accel| {
            let info = vk::CopyMemoryToAccelerationStructureInfoKHR::default()
                .src(cadr(data.address(a)))
                .dst(victim.s)
                .mode(vk::CopyAccelerationStructureModeKHR::DESERIALIZE);
            // SAFETY: recording command buffer, valid info.
            a.submit(|cb| unsafe { a.ext.cmd_copy_memory_to_acceleration_structure(cb, &info) });
        };
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyMemoryToAccelerationStructureKHR",
                vuid: "VUID-VkCopyMemoryToAccelerationStructureInfoKHR-pInfo-03749".into(),
                needles: &["not compatible with this device"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || deserialize(a),
        );
        // The same data with the right UUID deserializes.
        blob[0] ^= 0xFF;
        data.write(a, 0, &blob);
        deserialize(a);
        assert_grid_hits(&victim.r.read(a), &NoDevice);
    });
}

#[test]
fn serialize_to_a_misaligned_address_03740() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let size = a.query(src.s, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR);
        let out = guarded(a, size + 16);
        let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
            .src(src.s)
            .dst(madr(out.address(a) + 16))
            .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureToMemoryKHR",
                // The spec's name is VUID-vkCmdCopyAccelerationStructureToMemoryKHR-pInfo-03740;
                // the driver says VkCopyAccelerationStructureToMemoryInfoKHR-dst-03740.
                vuid: "-03740".into(),
                needles: &["is not aligned to 256"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: recording command buffer, valid info.
            || a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) }),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Property queries

#[test]
fn property_query_of_a_structure_never_built_04964() {
    scenario(|a, m| {
        let _ = m;
        let unbuilt = guarded_structure(a, BLAS, 4096);
        let d = &a.ctx.device;
        let ty = vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR;
        // SAFETY: valid create info; destroyed below.
        let pool = unsafe { d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(ty).query_count(1), None) }.unwrap();
        const WRITE: &str = "vkCmdWriteAccelerationStructuresPropertiesKHR";
        expect_invalid(
            a,
            Expect {
                command: WRITE,
                vuid: format!("VUID-{WRITE}-pAccelerationStructures-04964"),
                needles: &["element 0 has not been built"],
                writable: &[],
                invalidated: &[],
            },
            || {
                a.submit(|cb| {
                    // SAFETY: recording command buffer, valid pool and structure.
                    unsafe {
                        d.cmd_reset_query_pool(cb, pool, 0, 1);
                        a.ext.cmd_write_acceleration_structures_properties(cb, &[unbuilt.s], ty, pool, 0);
                    }
                })
            },
        );
        // The query stays unavailable (not waited on: it would never become available).
        let mut out = [0u64; 1];
        // SAFETY: valid pool.
        let r = unsafe { d.get_query_pool_results(pool, 0, &mut out, vk::QueryResultFlags::TYPE_64) };
        assert_eq!(r, Err(vk::Result::NOT_READY));
        // SAFETY: the pool is idle.
        unsafe { d.destroy_query_pool(pool, None) };

        // The host command reports the same and leaves the output alone.
        const HOST_WRITE: &str = "vkWriteAccelerationStructuresPropertiesKHR";
        let mut data = [0xA5u8; 8];
        expect_invalid(
            a,
            Expect {
                command: HOST_WRITE,
                vuid: format!("VUID-{HOST_WRITE}-pAccelerationStructures-04964"),
                needles: &["element 0 has not been built"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: 8 bytes of output for one query with stride 8.
            || {
                let _ = unsafe { a.ext.write_acceleration_structures_properties(&[unbuilt.s], ty, &mut data, 8) };
            },
        );
        assert_eq!(data, [0xA5u8; 8]);
    });
}

#[test]
fn compacted_size_query_without_allow_compaction_03431() {
    scenario(|a, m| {
        let (s, _) = valid_blas(a, m, NO_FLAGS);
        const HOST_WRITE: &str = "vkWriteAccelerationStructuresPropertiesKHR";
        let mut data = [0xA5u8; 8];
        expect_invalid(
            a,
            Expect {
                command: HOST_WRITE,
                vuid: format!("VUID-{HOST_WRITE}-accelerationStructures-03431"),
                needles: &["element 0 was not built with ALLOW_COMPACTION"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: 8 bytes of output for one query with stride 8.
            || {
                let _ = unsafe {
                    a.ext.write_acceleration_structures_properties(&[s.s], vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR, &mut data, 8)
                };
            },
        );
        assert_eq!(data, [0xA5u8; 8]);
    });
}

// ---------------------------------------------------------------------------------------------
// Strict mode (ARBOR_STRICT is read once per process: checked in a child process)

const STRICT_CHILD: &str = "strict_mode_child_invalid_build_loses_the_device";

#[test]
fn strict_mode_turns_an_invalid_build_into_device_lost() {
    let out = std::process::Command::new(std::env::current_exe().unwrap())
        .args([STRICT_CHILD, "--exact", "--ignored", "--nocapture", "--test-threads=1"])
        .env("ARBOR_STRICT", "1")
        .output()
        .expect("run the test binary as a child");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the strict-mode child failed:\n{text}");
    assert!(text.contains("1 passed"), "the strict-mode child did not run:\n{text}");
    assert!(text.contains("strict child: device lost as expected"), "the strict-mode child skipped its checks:\n{text}");
}

#[test]
#[ignore = "run by strict_mode_turns_an_invalid_build_into_device_lost in a child process with ARBOR_STRICT=1"]
fn strict_mode_child_invalid_build_loses_the_device() {
    if std::env::var("ARBOR_STRICT").as_deref() != Ok("1") {
        return;
    }
    let ctx = context();
    let a = Accel::new(&ctx);
    let m = upload_grid(&a);
    let (victim, scratch) = valid_blas(&a, &m, NO_FLAGS);
    // Misaligned scratch (03710): one invalid build.
    let geoms = [mesh_geom(&a, &m)];
    let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(&a) + 64));
    // A host build with a violation (BLAS build into a TOP_LEVEL structure) fails with
    // DEVICE_LOST itself.
    let host_geoms = [host_grid_geom(&a, &m)];
    let host_inf = info(BLAS, NO_FLAGS, &host_geoms);
    let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::HOST, &host_inf, &[m.count]);
    let tlas = guarded_structure(&a, TLAS, sizes.acceleration_structure_size);
    let mut host_scratch = vec![0u8; sizes.build_scratch_size as usize];
    let host_inf = host_inf
        .dst_acceleration_structure(tlas.s)
        .scratch_data(vk::DeviceOrHostAddressKHR { host_address: host_scratch.as_mut_ptr() as *mut c_void });
    // SAFETY: host pointers into mapped memory and a live Vec, valid for the call.
    let r = unsafe { a.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[host_inf], &[&[range(m.count)]]) };
    assert_eq!(r, Err(vk::Result::ERROR_DEVICE_LOST));
    let d = &ctx.device;
    // SAFETY: valid objects; everything is destroyed with the device below.
    unsafe {
        let cbs = d
            .allocate_command_buffers(&vk::CommandBufferAllocateInfo::default().command_pool(a.pool).command_buffer_count(2))
            .unwrap();
        for &cb in &cbs {
            d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
            a.ext.cmd_build_acceleration_structures(cb, &[inf], &[&[range(m.count)]]);
            d.end_command_buffer(cb).unwrap();
        }
        let fence = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs[..1])], fence).unwrap();
        assert_eq!(d.wait_for_fences(&[fence], true, 5_000_000_000), Err(vk::Result::ERROR_DEVICE_LOST));
        let again = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        assert_eq!(
            d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs[1..])], again),
            Err(vk::Result::ERROR_DEVICE_LOST)
        );
        d.destroy_fence(fence, None);
        d.destroy_fence(again, None);
    }
    let diag = support::diagnostics();
    assert!(diag.contains(&format!("[VUID-{CMD}-pInfos-03710]")), "{diag}");
    assert!(diag.contains("device lost"), "{diag}");
    assert!(header_of(&a, &victim).is_none());
    println!("strict child: device lost as expected");
    // The device is lost: no valid build afterwards; tear down without waiting for results.
    drop(a);
    drop(ctx);
}

// ---------------------------------------------------------------------------------------------
// More build checks: memory binding, handles of updates, aliasing with sources and instances,
// geometry types, strides, unmapped inputs

/// A buffer with no memory bound and a structure on it (destroyed by the caller's `unbound_done`).
fn unbound_structure(a: &Accel, size: u64, ty: vk::AccelerationStructureTypeKHR) -> (vk::Buffer, vk::AccelerationStructureKHR) {
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

fn unbound_done(a: &Accel, (buffer, s): (vk::Buffer, vk::AccelerationStructureKHR)) {
    // SAFETY: the device is idle after the submission's wait; destroyed once.
    unsafe {
        a.ext.destroy_acceleration_structure(s, None);
        a.ctx.device.destroy_buffer(buffer, None);
    }
}

#[test]
fn destination_without_memory_03707() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let unbound = unbound_structure(a, sizes.acceleration_structure_size, BLAS);
        let scratch = guarded(a, sizes.build_scratch_size);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(unbound.1).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-03707"),
                needles: &["pInfos[0]: dstAccelerationStructure is not bound to device memory"],
                writable: &[],
                invalidated: &[],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        unbound_done(a, unbound);
    });
}

#[test]
fn update_source_without_memory_03708() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, ALLOW_UPDATE);
        let unbound = unbound_structure(a, victim.r.len, BLAS);
        let src = Dst { s: unbound.1, r: victim.r };
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &src, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-03708"),
                needles: &["pInfos[0]: srcAccelerationStructure is not bound to device memory"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        unbound_done(a, unbound);
    });
}

#[test]
fn update_from_a_destroyed_source_04630() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, ALLOW_UPDATE);
        let ci = vk::AccelerationStructureCreateInfoKHR::default().buffer(a.buf(victim.r.buf).buffer).offset(victim.r.offset).size(victim.r.len).ty(BLAS);
        // SAFETY: valid create info; the handle is destroyed at once and only passed as a value.
        let stale = unsafe {
            let s = a.ext.create_acceleration_structure(&ci, None).unwrap();
            a.ext.destroy_acceleration_structure(s, None);
            s
        };
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &Dst { s: stale, r: victim.r }, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-04630"),
                needles: &["pInfos[0]: mode is UPDATE but srcAccelerationStructure", "is not valid"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn update_source_and_destination_alias_03668() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let size = sizes.acceleration_structure_size;
        let both = guarded(a, size + 256);
        let src = structure_in(a, both.buf, GUARD, size, BLAS);
        let dst = structure_in(a, both.buf, GUARD + 256, size, BLAS);
        let scratch = guarded(a, sizes.build_scratch_size.max(sizes.update_scratch_size));
        build_grid_into(a, m, &src, scratch.address(a), m.count, ALLOW_UPDATE);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &src, &dst, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-03668"),
                needles: &["pInfos[0]: srcAccelerationStructure and dstAccelerationStructure alias without being the same"],
                writable: &[dst.r, scratch],
                invalidated: &[],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        assert!(header_of(a, &dst).is_none());
        // Marking dst invalid writes only dst's own first bytes: src's header is intact.
        assert!(header_of(a, &src).is_some());
    });
}

#[test]
fn update_scratch_overlaps_its_source_03705() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        // The source, in a buffer large enough to also hold the update scratch from its start.
        let region = guarded(a, sizes.acceleration_structure_size.max(sizes.update_scratch_size));
        let src = structure_in(a, region.buf, GUARD, sizes.acceleration_structure_size, BLAS);
        let sc = guarded(a, sizes.build_scratch_size);
        build_grid_into(a, m, &src, sc.address(a), m.count, ALLOW_UPDATE);
        let (victim, _) = valid_blas(a, m, ALLOW_UPDATE);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &src, &victim, region.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("scratchData-03705"),
                needles: &["pInfos[0]: scratch overlaps its own srcAccelerationStructure"],
                // The build is skipped: not even the (aliased) scratch is written.
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        assert_grid_hits(&src.r.read(a), &NoDevice);
    });
}

#[test]
fn destination_overlaps_the_source_of_another_update_03701() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let size = sizes.acceleration_structure_size;
        // Element 0 builds into d0 at GUARD; element 1 updates s1 (at GUARD + 256, overlapping
        // d0's tail) into d1.
        let both = guarded(a, size + 256);
        let d0 = structure_in(a, both.buf, GUARD, size, BLAS);
        let s1 = structure_in(a, both.buf, GUARD + 256, size, BLAS);
        let (sc0, sc1) = (guarded(a, sizes.build_scratch_size), guarded(a, sizes.update_scratch_size.max(sizes.build_scratch_size)));
        build_grid_into(a, m, &s1, sc1.address(a), m.count, ALLOW_UPDATE);
        let d1 = guarded_structure(a, BLAS, size);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(d0.s).scratch_data(madr(sc0.address(a)));
        let i1 = update_info(BLAS, ALLOW_UPDATE, &geoms, &s1, &d1, sc1.address(a));
        let r = [range(m.count)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("dstAccelerationStructure-03701"),
                needles: &["pInfos[0]: dst overlaps the src of pInfos[1]"],
                writable: &[d0.r, sc0, d1.r, sc1],
                invalidated: &[],
            },
            || cmd_build(a, &[i0, i1], &[&r, &r]),
        );
        assert!(header_of(a, &d0).is_none());
        // Element 1 was valid: its update ran from an intact source.
        assert_grid_hits(&s1.r.read(a), &NoDevice);
        assert_grid_hits(&d1.r.read(a), &NoDevice);
    });
}

#[test]
fn destination_referenced_by_an_instance_of_another_element_03706() {
    scenario(|a, m| {
        // Element 0 rebuilds `victim`; element 1 builds a TLAS over an instance of `victim`.
        let (victim, sc0) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(a.address_of(victim.s)));
        let tgeoms = [instances_geom(inst.address(a), false)];
        let tsizes = a.sizes(DEVICE, &info(TLAS, NO_FLAGS, &tgeoms), &[1]);
        let tlas = guarded_structure(a, TLAS, tsizes.acceleration_structure_size);
        let sc1 = guarded(a, tsizes.build_scratch_size);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(sc0.address(a)));
        let i1 = info(TLAS, NO_FLAGS, &tgeoms).dst_acceleration_structure(tlas.s).scratch_data(madr(sc1.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("dstAccelerationStructure-03706"),
                needles: &["pInfos[0]: dst is referenced by an instance of pInfos[1]"],
                writable: &[victim.r, sc0, tlas.r, sc1],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[i0, i1], &[&[range(m.count)], &[range(1)]]),
        );
    });
}

#[test]
fn top_level_build_with_two_geometries_03789() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(a.address_of(blas.s)));
        let geoms = [instances_geom(inst.address(a), false), instances_geom(inst.address(a), false)];
        let inf = info(TLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(DEVICE, &inf, &[1, 1]);
        let (victim, scratch) = prebuilt_tlas(a, &blas, sizes.acceleration_structure_size, sizes.build_scratch_size);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: "-type-03789".into(),
                needles: &["pInfos[0]: a top-level build must have exactly one geometry of type INSTANCES"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(1), range(1)]]),
        );
    });
}

#[test]
fn bottom_level_build_with_instances_03790() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(a.address_of(blas.s)));
        let geoms = [instances_geom(inst.address(a), false)];
        invalid_blas_build(a, m, &geoms, 1, "-type-03790", &["pInfos[0]: a bottom-level build must not have INSTANCES geometry"]);
    });
}

#[test]
fn bottom_level_build_mixing_triangles_and_aabbs_03791() {
    scenario(|a, m| {
        let data = guarded_data(a, &boxes(4));
        let geoms = [mesh_geom(a, m), aabbs_geom(data.address(a), 24)];
        invalid_blas_build(a, m, &geoms, 4, "-type-03791", &["pInfos[0]: all geometries of a bottom-level build must have the same type"]);
    });
}

#[test]
fn vertex_stride_not_a_multiple_of_the_component_size_03735() {
    scenario(|a, m| {
        let mut g = mesh_geom(a, m);
        g.geometry.triangles.vertex_stride = 6;
        invalid_blas_build(a, m, &[g], m.count, "-vertexStride-03735", &["pInfos[0]: geometry 0: vertexStride 6"]);
    });
}

#[test]
fn aabb_stride_not_a_multiple_of_8_03545() {
    scenario(|a, m| {
        let data = guarded_data(a, &boxes(4));
        invalid_blas_build(a, m, &[aabbs_geom(data.address(a), 12)], 4, "-stride-03545", &["pInfos[0]: geometry 0: aabbs.stride 12 is not a multiple of 8"]);
    });
}

#[test]
fn index_data_not_mapped_03806() {
    scenario(|a, m| {
        let gone = freed_address(a, 4096);
        let geoms = [tri(m.v.address(a), gone, m.max_vertex, 0)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03806", &["pInfos[0]: geometry 0: [0x"]);
    });
}

#[test]
fn transform_data_not_mapped_03808() {
    scenario(|a, m| {
        let gone = freed_address(a, 4096);
        let geoms = [tri(m.v.address(a), m.i.address(a), m.max_vertex, gone)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03808", &["pInfos[0]: geometry 0: [0x"]);
    });
}

#[test]
fn aabb_data_not_mapped_03811() {
    scenario(|a, m| {
        let gone = freed_address(a, 4096);
        invalid_blas_build(a, m, &[aabbs_geom(gone, 24)], 4, "pInfos-03811", &["pInfos[0]: geometry 0: [0x"]);
    });
}

#[test]
fn instance_data_not_mapped_03813() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let gone = freed_address(a, 4096);
        invalid_tlas_build(a, &blas, instances_geom(gone, false), 1, "pInfos-03813", &["pInfos[0]: geometry 0: [0x"]);
    });
}

#[test]
fn instance_pointer_not_mapped_03813() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let gone = freed_address(a, 4096);
        let pointers = guarded_data(a, &gone.to_le_bytes());
        invalid_tlas_build(a, &blas, instances_geom(pointers.address(a), true), 1, "pInfos-03813", &["pInfos[0]: geometry 0: instance pointer 0", "does not address 64 valid bytes"]);
    });
}

// ---------------------------------------------------------------------------------------------
// Checks whose VUID names were corrected in the driver (6f2b917)

#[test]
fn scratch_without_storage_usage_12261() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let scratch = guarded_with(a, grid_sizes(a, m).build_scratch_size, without(vk::BufferUsageFlags::STORAGE_BUFFER));
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-12261"),
                needles: &["pInfos[0]: the scratch buffer lacks STORAGE_BUFFER usage"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn unsupported_vertex_format_03797() {
    scenario(|a, m| {
        let mut g = mesh_geom(a, m);
        g.geometry.triangles.vertex_format = vk::Format::R64G64B64_SFLOAT;
        invalid_blas_build(a, m, &[g], m.count, "-vertexFormat-03797", &["pInfos[0]"]);
    });
}

#[test]
fn primitive_offset_not_a_multiple_of_the_index_size_03656() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        let r = [Range::default().primitive_count(m.count - 1).primitive_offset(2)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: "-primitiveOffset-03656".into(),
                needles: &["pInfos[0]: geometry 0: primitiveOffset 2"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&r]),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// More copies

fn cmd_deserialize(a: &Accel, src: u64, dst: &Dst) {
    let info = vk::CopyMemoryToAccelerationStructureInfoKHR::default()
        .src(cadr(src))
        .dst(dst.s)
        .mode(vk::CopyAccelerationStructureModeKHR::DESERIALIZE);
    // SAFETY: recording command buffer, valid info.
    a.submit(|cb| unsafe { a.ext.cmd_copy_memory_to_acceleration_structure(cb, &info) });
}

#[test]
fn compact_into_a_destination_too_small_12285() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION);
        let compacted = a.query(src.s, vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR);
        let (victim, _) = prebuilt_blas(a, m, 0, 0, 2, NO_FLAGS);
        assert!(victim.r.len < compacted, "test setup: {} < {compacted}", victim.r.len);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-dst-12285".into(),
                needles: &["dst size", "is below the"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_copy(a, &src, &victim, vk::CopyAccelerationStructureModeKHR::COMPACT),
        );
        assert_guards(a, victim.r);
    });
}

#[test]
fn clone_between_overlapping_structures_07791() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let size = sizes.acceleration_structure_size;
        let both = guarded(a, size + 256);
        let src = structure_in(a, both.buf, GUARD, size, BLAS);
        let dst = structure_in(a, both.buf, GUARD + 256, size, BLAS);
        let sc = guarded(a, sizes.build_scratch_size);
        build_grid_into(a, m, &src, sc.address(a), m.count, NO_FLAGS);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-dst-07791".into(),
                needles: &["the memory of src and dst overlap"],
                writable: &[dst.r],
                invalidated: &[],
            },
            || cmd_copy(a, &src, &dst, vk::CopyAccelerationStructureModeKHR::CLONE),
        );
        assert!(header_of(a, &src).is_some());
    });
}

#[test]
fn copy_with_an_invalid_mode_03410() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-mode-03410".into(),
                needles: &["mode must be CLONE or COMPACT"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_copy(a, &src, &victim, vk::CopyAccelerationStructureModeKHR::SERIALIZE),
        );
    });
}

#[test]
fn serialize_a_structure_never_built_04959() {
    scenario(|a, m| {
        let _ = m;
        let unbuilt = guarded_structure(a, BLAS, 4096);
        let out = guarded(a, 4096);
        let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
            .src(unbuilt.s)
            .dst(madr(out.address(a)))
            .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureToMemoryKHR",
                vuid: "VUID-VkCopyAccelerationStructureToMemoryInfoKHR-src-04959".into(),
                needles: &["src has not been built"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: recording command buffer, valid info.
            || a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) }),
        );
    });
}

#[test]
fn serialize_to_memory_too_small_03561() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let size = a.query(src.s, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR);
        // Half the serialization size, at the start of a buffer of that size.
        let b = a.buffer(size / 2);
        a.fill(b, FILL);
        let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
            .src(src.s)
            .dst(madr(a.buf(b).address))
            .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureToMemoryKHR",
                vuid: "VUID-VkCopyAccelerationStructureToMemoryInfoKHR-dst-03561".into(),
                needles: &["is not writable device memory"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: recording command buffer, valid info.
            || a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) }),
        );
    });
}

#[test]
fn deserialize_into_a_destination_too_small_03746() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let blob = a.serialize(src.s);
        let data = guarded_data(a, &blob);
        let (victim, _) = prebuilt_blas(a, m, 0, 0, 2, NO_FLAGS);
        assert!(victim.r.len < src.r.len);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyMemoryToAccelerationStructureKHR",
                vuid: "VUID-VkCopyMemoryToAccelerationStructureInfoKHR-dst-03746".into(),
                needles: &["cannot deserialize into dst"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_deserialize(a, data.address(a), &victim),
        );
        assert_guards(a, victim.r);
    });
}

#[test]
fn deserialize_from_a_misaligned_address_03743() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let blob = a.serialize(src.s);
        let data = guarded(a, blob.len() as u64 + 16);
        data.write(a, 16, &blob);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyMemoryToAccelerationStructureKHR",
                // The spec's name is VUID-vkCmdCopyMemoryToAccelerationStructureKHR-pInfo-03743;
                // the driver says VkCopyMemoryToAccelerationStructureInfoKHR-src-03743.
                vuid: "-03743".into(),
                needles: &["is not aligned to 256"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_deserialize(a, data.address(a) + 16, &victim),
        );
    });
}

#[test]
fn deserialize_from_unmapped_memory_03742() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let gone = freed_address(a, 4096);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyMemoryToAccelerationStructureKHR",
                // The spec's name is VUID-vkCmdCopyMemoryToAccelerationStructureKHR-pInfo-03742;
                // the driver says VkCopyMemoryToAccelerationStructureInfoKHR-src-03742.
                vuid: "-03742".into(),
                needles: &["does not address a serialized structure"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_deserialize(a, gone, &victim),
        );
    });
}

#[test]
fn deserialize_with_a_length_past_the_buffer_03742() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let mut blob = a.serialize(src.s);
        // The header's total size claims far more than the buffer holds.
        blob[32..40].copy_from_slice(&(1u64 << 40).to_le_bytes());
        let data = guarded_data(a, &blob);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyMemoryToAccelerationStructureKHR",
                vuid: "-03742".into(),
                needles: &["is not readable"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_deserialize(a, data.address(a), &victim),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Updates whose inputs differ from the last build (checked when the update runs)

/// Build the grid with ALLOW_UPDATE into a victim, then update it in place with `geom` and
/// `range`: checks `vuid`.
fn invalid_update(a: &Accel, m: &Mesh, geom: Geom, r: Range, vuid: &str, needles: &[&str]) {
    let (victim, scratch) = valid_blas(a, m, ALLOW_UPDATE);
    let geoms = [geom];
    let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &victim, &victim, scratch.address(a));
    expect_invalid(
        a,
        Expect { command: CMD, vuid: cmd_vuid(vuid), needles, writable: &[victim.r, scratch], invalidated: &[&victim] },
        || cmd_build(a, &[inf], &[&[r]]),
    );
}

#[test]
fn update_with_changed_indices_03768() {
    scenario(|a, m| {
        let mut indices = m.index_bytes.clone();
        // The first triangle's indices rotated: same triangle, other index values.
        let first: Vec<u8> = indices[..12].to_vec();
        indices[..4].copy_from_slice(&first[4..8]);
        indices[4..8].copy_from_slice(&first[8..12]);
        indices[8..12].copy_from_slice(&first[..4]);
        let i = guarded_data(a, &indices);
        let g = tri(m.v.address(a), i.address(a), m.max_vertex, 0);
        invalid_update(a, m, g, range(m.count), "pInfos-03768", &["pInfos[0]: update does not match the last build"]);
    });
}

#[test]
fn update_with_another_primitive_count_03769() {
    scenario(|a, m| {
        invalid_update(a, m, mesh_geom(a, m), range(m.count - 1), "primitiveCount-03769", &["pInfos[0]"]);
    });
}

#[test]
fn update_with_other_geometry_flags_03762() {
    scenario(|a, m| {
        let g = mesh_geom(a, m).flags(vk::GeometryFlagsKHR::NO_DUPLICATE_ANY_HIT_INVOCATION);
        invalid_update(a, m, g, range(m.count), "pInfos-03762", &["pInfos[0]"]);
    });
}

#[test]
fn update_with_another_max_vertex_03764() {
    scenario(|a, m| {
        let g = tri(m.v.address(a), m.i.address(a), m.max_vertex + 1, 0);
        invalid_update(a, m, g, range(m.count), "pInfos-03764", &["pInfos[0]"]);
    });
}

#[test]
fn update_into_a_destination_too_small_03675() {
    scenario(|a, m| {
        let (src, scratch) = valid_blas(a, m, ALLOW_UPDATE);
        let (victim, _) = prebuilt_blas(a, m, 0, 0, 2, ALLOW_UPDATE);
        assert!(victim.r.len < src.r.len);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &src, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-03675"),
                needles: &["pInfos[0]"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        assert_guards(a, victim.r);
        assert_grid_hits(&src.r.read(a), &NoDevice);
    });
}

// ---------------------------------------------------------------------------------------------
// Robustness: absurd counts

#[test]
fn primitive_count_of_u32_max_03675() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        let mark = support::diagnostics().len();
        let snap = snapshot(a);
        cmd_build(a, &[inf], &[&[range(u32::MAX)]]);
        let tail = support::diagnostics()[mark..].to_string();
        assert!(tail.contains(&format!("[VUID-{CMD}-pInfos-03675] pInfos[0]")), "{tail}");
        assert!(!tail.contains("panic") && !tail.contains("internal error"), "{tail}");
        verify(a, &snap, &[victim.r, scratch]);
        assert!(header_of(a, &victim).is_none());
    });
}

// ---------------------------------------------------------------------------------------------
// Host commands: deferred builds, copies, property writes

fn host_grid_geom(a: &Accel, m: &Mesh) -> Geom {
    tri(m.v.host_ptr(a) as u64, m.i.host_ptr(a) as u64, m.max_vertex, 0)
}

#[test]
fn deferred_host_build_into_a_structure_of_another_type_03700() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [host_grid_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::HOST, &inf, &[m.count]);
        let (victim, _) = prebuilt_tlas(a, &blas, sizes.acceleration_structure_size, 0);
        let mut host_scratch = vec![0u8; sizes.build_scratch_size as usize];
        let inf = inf
            .dst_acceleration_structure(victim.s)
            .scratch_data(vk::DeviceOrHostAddressKHR { host_address: host_scratch.as_mut_ptr() as *mut c_void });
        // SAFETY: plain create; destroyed below after completion.
        let op = unsafe { a.deferred.create_deferred_operation(None) }.unwrap();
        let mut joined = vk::Result::SUCCESS;
        expect_invalid(
            a,
            Expect {
                command: HOST,
                vuid: format!("VUID-{HOST}-pInfos-03700"),
                needles: &["pInfos[0]: dstAccelerationStructure was created with another type"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || {
                // SAFETY: host pointers valid until the operation completes (joined here).
                let r = unsafe { a.ext.build_acceleration_structures(op, &[inf], &[&[range(m.count)]]) };
                assert!(matches!(r, Ok(()) | Err(vk::Result::OPERATION_DEFERRED_KHR) | Err(vk::Result::OPERATION_NOT_DEFERRED_KHR)), "{r:?}");
                if r == Err(vk::Result::OPERATION_DEFERRED_KHR) {
                    loop {
                        // SAFETY: live operation.
                        match unsafe { a.deferred.deferred_operation_join(op) } {
                            Ok(()) => break,
                            Err(vk::Result::THREAD_DONE_KHR) | Err(vk::Result::THREAD_IDLE_KHR) => std::thread::yield_now(),
                            Err(e) => panic!("join: {e:?}"),
                        }
                    }
                }
                // SAFETY: live operation.
                joined = unsafe { a.deferred.get_deferred_operation_result(op) }.err().unwrap_or(vk::Result::SUCCESS);
            },
        );
        assert_eq!(joined, vk::Result::SUCCESS, "outside strict mode an invalid deferred build completes with SUCCESS");
        // SAFETY: complete operation.
        unsafe { a.deferred.destroy_deferred_operation(op, None) };
    });
}

#[test]
fn host_compact_without_allow_compaction_03411() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let info = vk::CopyAccelerationStructureInfoKHR::default().src(src.s).dst(victim.s).mode(vk::CopyAccelerationStructureModeKHR::COMPACT);
        let mut result = Ok(());
        expect_invalid(
            a,
            Expect {
                command: "vkCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-src-03411".into(),
                needles: &["src was not built with ALLOW_COMPACTION"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            // SAFETY: valid info, no deferred operation.
            || result = unsafe { a.ext.copy_acceleration_structure(vk::DeferredOperationKHR::null(), &info) },
        );
        assert_eq!(result, Ok(()));
    });
}

#[test]
fn host_property_write_with_a_stride_not_a_multiple_of_8_03448() {
    scenario(|a, m| {
        let (s, _) = valid_blas(a, m, NO_FLAGS);
        const HOST_WRITE: &str = "vkWriteAccelerationStructuresPropertiesKHR";
        let mut data = [0xA5u8; 24];
        expect_invalid(
            a,
            Expect { command: HOST_WRITE, vuid: format!("VUID-{HOST_WRITE}-queryType-03448"), needles: &["stride must be a multiple of 8"], writable: &[], invalidated: &[] },
            // SAFETY: 24 bytes of output for one query; the stride is the invalid part.
            || {
                let _ = unsafe { a.ext.write_acceleration_structures_properties(&[s.s], vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR, &mut data, 12) };
            },
        );
        assert_eq!(data, [0xA5u8; 24]);
    });
}

#[test]
fn host_property_write_with_data_too_small_03452() {
    scenario(|a, m| {
        let (s0, _) = valid_blas(a, m, NO_FLAGS);
        const HOST_WRITE: &str = "vkWriteAccelerationStructuresPropertiesKHR";
        let mut data = [0xA5u8; 8];
        expect_invalid(
            a,
            Expect { command: HOST_WRITE, vuid: format!("VUID-{HOST_WRITE}-dataSize-03452"), needles: &["dataSize is smaller than"], writable: &[], invalidated: &[] },
            // SAFETY: two structures with stride 8 need 16 bytes; 8 are given (the invalid part).
            || {
                let _ = unsafe { a.ext.write_acceleration_structures_properties(&[s0.s, s0.s], vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR, &mut data, 8) };
            },
        );
        assert_eq!(data, [0xA5u8; 8]);
    });
}

#[test]
fn property_write_into_a_pool_of_another_type_02493() {
    scenario(|a, m| {
        let (s, _) = valid_blas(a, m, NO_FLAGS);
        let d = &a.ctx.device;
        // SAFETY: valid create info; destroyed below.
        let pool = unsafe {
            d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR).query_count(1), None)
        }
        .unwrap();
        const WRITE: &str = "vkCmdWriteAccelerationStructuresPropertiesKHR";
        expect_invalid(
            a,
            Expect { command: WRITE, vuid: format!("VUID-{WRITE}-queryPool-02493"), needles: &["queryPool was created with another queryType"], writable: &[], invalidated: &[] },
            || {
                a.submit(|cb| {
                    // SAFETY: recording command buffer, valid pool and structure.
                    unsafe {
                        d.cmd_reset_query_pool(cb, pool, 0, 1);
                        a.ext.cmd_write_acceleration_structures_properties(cb, &[s.s], vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR, pool, 0);
                    }
                })
            },
        );
        let mut out = [0u64; 1];
        // SAFETY: valid pool.
        let r = unsafe { d.get_query_pool_results(pool, 0, &mut out, vk::QueryResultFlags::TYPE_64) };
        assert_eq!(r, Err(vk::Result::NOT_READY));
        // SAFETY: idle pool.
        unsafe { d.destroy_query_pool(pool, None) };
    });
}

// ---------------------------------------------------------------------------------------------
// The harness itself: each check above must be able to fail

#[test]
#[should_panic(expected = "outside destination and scratch")]
fn harness_catches_a_write_outside_destination_and_scratch() {
    scenario(|a, m| {
        let snap = snapshot(a);
        // One guard byte before the vertex data.
        a.buf(m.v.buf).write((m.v.offset - 1) as usize, &[0]);
        verify(a, &snap, &[]);
    });
}

#[test]
#[should_panic(expected = "expected a line starting with")]
fn harness_catches_a_missing_diagnostic() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        expect_invalid(
            a,
            Expect { command: CMD, vuid: cmd_vuid("pInfos-03675"), needles: &[], writable: &[victim.r, scratch], invalidated: &[] },
            || build_grid_into(a, m, &victim, scratch.address(a), m.count, NO_FLAGS),
        );
    });
}

#[test]
#[should_panic(expected = "still reads as a valid structure")]
fn harness_catches_a_destination_left_valid() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let (bystander, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a) + 64));
        expect_invalid(
            a,
            Expect { command: CMD, vuid: cmd_vuid("pInfos-03710"), needles: &[], writable: &[victim.r, scratch], invalidated: &[&bystander] },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
#[should_panic(expected = "unexpected diagnostic besides")]
fn harness_catches_a_second_violation() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let geoms = [tri(m.v.address(a) + 2, m.i.address(a), m.max_vertex, 0)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a) + 64));
        expect_invalid(
            a,
            Expect { command: CMD, vuid: cmd_vuid("pInfos-03710"), needles: &[], writable: &[victim.r, scratch], invalidated: &[&victim] },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Malformed build infos

#[test]
fn geometry_arrays_both_null_03788() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let mut inf = info(BLAS, NO_FLAGS, &[]).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        // Both NULL (an empty slice's pointer is dangling, not NULL).
        inf.p_geometries = std::ptr::null();
        inf.pp_geometries = std::ptr::null();
        inf.geometry_count = 1;
        expect_invalid(
            a,
            Expect { command: CMD, vuid: "-pGeometries-03788".into(), needles: &["pInfos[0]"], writable: &[victim.r, scratch], invalidated: &[&victim] },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn host_build_into_a_destroyed_handle_03800() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let ci = vk::AccelerationStructureCreateInfoKHR::default().buffer(a.buf(victim.r.buf).buffer).offset(victim.r.offset).size(victim.r.len).ty(BLAS);
        // SAFETY: valid create info; the handle is destroyed at once and only passed as a value.
        let stale = unsafe {
            let s = a.ext.create_acceleration_structure(&ci, None).unwrap();
            a.ext.destroy_acceleration_structure(s, None);
            s
        };
        let geoms = [host_grid_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::HOST, &inf, &[m.count]);
        let mut host_scratch = vec![FILL; sizes.build_scratch_size as usize];
        let inf = inf
            .dst_acceleration_structure(stale)
            .scratch_data(vk::DeviceOrHostAddressKHR { host_address: host_scratch.as_mut_ptr() as *mut c_void });
        let mut result = Ok(());
        expect_invalid(
            a,
            Expect {
                command: HOST,
                vuid: format!("VUID-{HOST}-dstAccelerationStructure-03800"),
                needles: &["pInfos[0]: dstAccelerationStructure", "is not a valid handle"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: host pointers into mapped memory and a live Vec, valid for the call.
            || result = unsafe { a.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[inf], &[&[range(m.count)]]) },
        );
        assert_eq!(result, Ok(()));
        assert!(host_scratch.iter().all(|&b| b == FILL), "the skipped host build wrote its scratch");
        assert!(header_of(a, &victim).is_some());
    });
}

/// No VUID names it, but a build whose vertex input lies inside its own scratch would read what
/// it writes (and Arbor would alias a shared and a mutable view): reported and skipped.
#[test]
fn vertex_input_inside_the_scratch_is_reported() {
    scenario(|a, m| {
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(DEVICE, &inf, &[m.count]);
        let (victim, scratch) = prebuilt_blas(a, m, sizes.acceleration_structure_size, sizes.build_scratch_size, m.count, NO_FLAGS);
        // Put the vertices at the start of the scratch region and point the geometry there.
        scratch.write(a, 0, &m.vertex_bytes);
        let geoms = [tri(scratch.address(a), m.i.address(a), m.max_vertex, 0)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: "ARBOR-build-input-aliases-output".into(),
                needles: &["pInfos[0]: a geometry input overlaps the dst or scratch memory of pInfos[0]"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

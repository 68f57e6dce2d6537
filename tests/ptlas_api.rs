//! VK_NV_partitioned_acceleration_structure through the loader, validation on: a PTLAS built
//! with vkCmdBuildPartitionedAccelerationStructuresNV from op records in device memory (the op
//! count and some records written by vkCmdUpdateBuffer earlier in the same command buffer),
//! read back and traversed, equals brute force (tests/reference) and a KHR TLAS built through
//! the API from the equivalent instance list, and a ray-query shader that reaches it by address
//! (OpConvertUToAccelerationStructureKHR) gets the same hits; then incremental builds in place
//! and src → dst.
//!
//! The validation layer here (Debian 12's, 1.3.239) predates the extension. Exactly one of its
//! messages is filtered, by the harness (`KNOWN_UNSUPPORTED_EXTENSIONS`, matched by its full
//! text): the warning, once at vkCreateDevice, that it does not support
//! VK_NV_partitioned_acceleration_structure — it names no rule broken, only that the layer
//! cannot check the extension. The NV structs are never put in a pNext chain it
//! inspects (the feature struct is not chained at vkCreateDevice: Arbor gates the commands on
//! the enabled extension), and the feature and property queries run in a context with
//! validation off, since the layer would report the NV structs as unknown pNext structs.
mod harness;
mod reference;

use std::collections::HashMap;
use std::ffi::c_void;

use arbor::accel::{self, Geometry, GeometryData, GeometryFlags, IndexType, MapView, Ray, RayFlags, VertexFormat};
use arbor_scene::{InstanceRecord, Rng};
use ash::vk;
use harness::ptlas::*;
use harness::vuid::*;
use reference::brute_force::{compare_ray, RefScene, Tolerance};

const EXPLICIT_AABB: u32 = 0x10;

// The NV structs, written here from the registry (spec/nv-extensions.md A.4), not taken from Arbor.
#[repr(C)]
struct FeaturesNV {
    s_type: i32,
    p_next: *mut c_void,
    partitioned_acceleration_structure: u32,
}

#[repr(C)]
struct PropertiesNV {
    s_type: i32,
    p_next: *mut c_void,
    max_partition_count: u32,
}

/// One instance as the test knows it.
#[derive(Clone, Copy, Debug)]
struct Inst {
    transform: [f32; 12],
    aabb: Option<[f32; 6]>,
    id: u32,
    mask: u32,
    sbt: u32,
    flags: u32,
    index: u32,
    partition: u32,
    blas: u64,
}

/// VkPartitionedAccelerationStructureWriteInstanceDataNV (104 bytes).
fn write_record(i: &Inst) -> Vec<u8> {
    let mut b = Vec::with_capacity(104);
    i.transform.iter().chain(i.aabb.unwrap_or([0.0; 6]).iter()).for_each(|x| b.extend(x.to_le_bytes()));
    let flags = i.flags | if i.aabb.is_some() { EXPLICIT_AABB } else { 0 };
    for w in [i.id, i.mask, i.sbt, flags, i.index, i.partition] {
        b.extend(w.to_le_bytes());
    }
    b.extend(i.blas.to_le_bytes());
    b
}

fn random_instances(rng: &mut Rng, n: u32, partitions: u32, blas: u64) -> Vec<Inst> {
    (0..n)
        .map(|index| {
            let t = [rng.range(-3.0, 3.0), rng.range(-3.0, 3.0), rng.range(-3.0, 3.0)];
            let s = rng.range(0.5, 1.5);
            let explicit = rng.below(3) == 0;
            Inst {
                transform: [s, 0.0, 0.0, t[0], 0.0, s, 0.0, t[1], 0.0, 0.0, s, t[2]],
                // The grid spans [0, 1]^2 at z = 0: a loose box around it after the transform.
                aabb: explicit.then(|| [t[0] - 0.1, t[1] - 0.1, t[2] - 0.1, t[0] + s + 0.1, t[1] + s + 0.1, t[2] + 0.1]),
                id: rng.next_u32() & 0xFF_FFFF,
                mask: [0xFF, 0x01, 0x02, 0x80][rng.below(4) as usize],
                sbt: rng.next_u32() & 0xFFF,
                // FORCE_OPAQUE and FORCE_NO_OPAQUE together are invalid: at most one.
                flags: [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11][rng.below(12) as usize],
                index,
                partition: if rng.below(5) == 0 { GLOBAL } else { rng.below(partitions) },
                blas: if rng.below(7) == 0 { 0 } else { blas },
            }
        })
        .collect()
}

/// The equivalent KHR instance list: translation added, disabled slots inactive.
fn equivalent(slots: &[Option<Inst>], translations: &HashMap<u32, [f32; 3]>) -> Vec<InstanceRecord> {
    slots
        .iter()
        .map(|s| match s {
            Some(i) => {
                let mut m = i.transform;
                let t = translations.get(&i.partition).copied().unwrap_or([0.0; 3]);
                m[3] += t[0];
                m[7] += t[1];
                m[11] += t[2];
                InstanceRecord { transform: m, custom_index: i.id, mask: i.mask as u8, sbt_offset: i.sbt, flags: i.flags as u8, reference: i.blas }
            }
            None => InstanceRecord { transform: IDENTITY, custom_index: 0, mask: 0, sbt_offset: 0, flags: 0, reference: 0 },
        })
        .collect()
}

/// The test's view of the state and its checks against brute force and the KHR TLAS.
struct Checker<'m> {
    view: MapView,
    blas_address: u64,
    grid: Vec<Geometry<'m>>,
}

impl Checker<'_> {
    fn check(&self, a: &Accel, ptlas: &[u8], slots: &[Option<Inst>], translations: &HashMap<u32, [f32; 3]>, seed: u64) {
        assert!(accel::header(ptlas).is_some(), "the PTLAS is not valid");
        let records = equivalent(slots, translations);
        let khr = khr_tlas(a, &records).r.read(a);
        let blases: HashMap<u64, &[Geometry]> = [(self.blas_address, self.grid.as_slice())].into_iter().collect();
        let scene = RefScene::Tlas { instances: records, blases };
        let rays = reference::random_rays([-4.0, -4.0, -4.0, 5.0, 5.0, 5.0], 300, seed);
        let mut hits = 0;
        for (k, ray) in rays.iter().enumerate() {
            for mask in [0xFF, 0x01, 0x82] {
                hits += compare_ray(ptlas, &self.view, &scene, ray, 0, mask, Tolerance { exact: false }, &format!("ray {k} mask {mask:#x}"));
                let key = |h: &accel::Hit| (h.instance_index, h.primitive_index, h.t.to_bits(), h.instance_custom_index, h.sbt_record_offset);
                let r: Ray = *ray;
                let mut p: Vec<_> = accel::all_hits(ptlas, &self.view, r, RayFlags(0), mask).iter().map(key).collect();
                let mut q: Vec<_> = accel::all_hits(&khr, &self.view, r, RayFlags(0), mask).iter().map(key).collect();
                p.sort_unstable();
                q.sort_unstable();
                assert_eq!(p, q, "ray {k}: the PTLAS and the KHR TLAS disagree");
            }
        }
        assert!(hits > 50, "only {hits} reference hits: the rays miss the scene");
    }
}

/// Records one build: the op count is written by vkCmdUpdateBuffer first, and `update_data`
/// (offset, bytes) too, so the build must read them when it executes.
fn build(a: &Accel, nv: &Nv, info: &BuildInfo, count_word: &Region, count: u32, update_data: Option<(&Region, &[u8])>) {
    let d = &a.ctx.device;
    a.submit(|cb| {
        // SAFETY: valid command buffer, buffers with TRANSFER_DST usage, 4-byte aligned updates.
        unsafe {
            d.cmd_update_buffer(cb, a.buf(count_word.buf).buffer, count_word.offset, &count.to_le_bytes());
            if let Some((r, bytes)) = update_data {
                d.cmd_update_buffer(cb, a.buf(r.buf).buffer, r.offset, bytes);
            }
            let barrier = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::TRANSFER_WRITE).dst_access_mask(vk::AccessFlags::ACCELERATION_STRUCTURE_READ_KHR)];
            d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::ACCELERATION_STRUCTURE_BUILD_KHR, vk::DependencyFlags::empty(), &barrier, &[], &[]);
            (nv.build)(cb, info);
        }
    });
}

/// tests/shaders/ptlas_rq.comp over `rays` against the structure at `address` (converted in
/// the shader with OpConvertUToAccelerationStructureKHR); the hits buffer.
fn trace(a: &Accel, address: u64, rays: &[Ray]) -> Vec<u8> {
    let (rb, hb) = (a.upload(&harness::trace::ray_bytes(rays)), a.buffer(16 * rays.len() as u64));
    let push: Vec<u8> = [address as u32, (address >> 32) as u32, rays.len() as u32].iter().flat_map(|x| x.to_le_bytes()).collect();
    harness::trace::dispatch(a, &harness::compute::glsl("ptlas_rq.comp"), None, &[rb, hb], &push, (rays.len() as u32).div_ceil(64));
    a.buf(hb).read(0, 16 * rays.len())
}

/// A ray-query shader tracing the PTLAS by address gets `closest_hit`'s answers on the bytes read back.
fn assert_shader_hits(a: &Accel, address: u64, ptlas: &[u8], view: &MapView) {
    let rays = reference::random_rays([-4.0, -4.0, -4.0, 5.0, 5.0, 5.0], 200, 77);
    let out = trace(a, address, &rays);
    let mut hits = 0;
    for (i, (ray, got)) in rays.iter().zip(out.chunks(16)).enumerate() {
        let word = |k: usize| u32::from_le_bytes(got[4 * k..4 * k + 4].try_into().unwrap());
        match accel::closest_hit(ptlas, view, *ray, RayFlags(RayFlags::OPAQUE), 0xFF) {
            Some(h) => {
                hits += 1;
                assert_eq!((f32::from_bits(word(0)), word(1), word(2), word(3)), (h.t, h.primitive_index, h.instance_index, h.instance_custom_index), "ray {i}");
            }
            None => assert_eq!((word(1), word(2)), (u32::MAX, u32::MAX), "ray {i}: miss"),
        }
    }
    assert!(hits > 20, "only {hits} hits");
}

fn grid_geometry(m: &Mesh) -> Geometry<'_> {
    Geometry {
        flags: GeometryFlags(1),
        primitive_count: m.count,
        data: GeometryData::Triangles {
            format: VertexFormat::R32G32B32Sfloat,
            vertices: &m.vertex_bytes,
            stride: 12,
            max_vertex: m.max_vertex,
            index_type: IndexType::U32,
            indices: &m.index_bytes,
            transform: None,
        },
    }
}

// One function: each build continues from the state the builds before it left.
#[test]
fn ptlas_builds_through_the_loader_match_brute_force_and_a_khr_tlas() {
    // Diagnostics are per process: the negative test's must not land in this one's.
    let _serial = serial();
    let mut exts = harness::default_device_extensions();
    exts.push(EXT);
    exts.push("VK_KHR_ray_query");
    let ctx = harness::Context::new(harness::Options { acceleration_structure: true, device_extensions: exts, ..Default::default() });
    let a = Accel::new(&ctx);
    let nv = functions(&ctx);
    let mesh = upload_grid(&a);
    let (blas, _) = valid_blas(&a, &mesh, NO_FLAGS);
    let blas_address = a.address_of(blas.s);
    let mut view = MapView::new();
    view.insert(blas_address, blas.r.read(&a));
    let checker = Checker { view, blas_address, grid: vec![grid_geometry(&mesh)] };
    let mut rng = Rng::new(24);
    let (n, partitions) = (48u32, 5u32);
    let flags = translation_enabled();
    let inp = InstancesInput { p_next: &flags as *const _ as *const c_void, ..input(n, n, partitions, n) };
    let mut sizes = vk::AccelerationStructureBuildSizesInfoKHR::default();
    // SAFETY: valid input and output structs.
    unsafe { (nv.sizes)(ctx.device.handle(), &inp, &mut sizes) };
    assert!(sizes.acceleration_structure_size > 0 && sizes.build_scratch_size > 0);
    let (dst, dst2, scratch) = (guarded(&a, sizes.acceleration_structure_size), guarded(&a, sizes.acceleration_structure_size), guarded(&a, sizes.build_scratch_size));
    let count_word = guarded(&a, 4);

    // From scratch: some slots never written (disabled), translations for a partition and the global one.
    let all = random_instances(&mut rng, n, partitions, blas_address);
    let mut slots: Vec<Option<Inst>> = vec![None; n as usize];
    let written: Vec<Inst> = all.iter().filter(|_| rng.below(6) != 0).copied().collect();
    written.iter().for_each(|i| slots[i.index as usize] = Some(*i));
    let translations: HashMap<u32, [f32; 3]> = [(1, [0.5, -1.0, 0.25]), (GLOBAL, [-0.5, 0.0, 1.0])].into_iter().collect();
    let w_bytes: Vec<u8> = written.iter().flat_map(write_record).collect();
    let t_bytes: Vec<u8> = translations.iter().flat_map(|(p, t)| [p.to_le_bytes(), t[0].to_le_bytes(), t[1].to_le_bytes(), t[2].to_le_bytes()].concat()).collect();
    let (w_reg, t_reg) = (guarded_data(&a, &w_bytes), guarded_data(&a, &t_bytes));
    let ops: Vec<u8> = [op_record(0, written.len() as u32, w_reg.address(&a), 104), op_record(2, 2, t_reg.address(&a), 16)].concat();
    let ops_reg = guarded_data(&a, &ops);
    let mut info = build_info(inp, 0, dst.address(&a), scratch.address(&a), ops_reg.address(&a), count_word.address(&a));
    build(&a, &nv, &info, &count_word, 2, None);
    let first = dst.read(&a);
    checker.check(&a, &first, &slots, &translations, 1);
    assert_shader_hits(&a, dst.address(&a), &first, &checker.view);

    // In place: three writes whose records vkCmdUpdateBuffer writes in the same command buffer
    // (one moves an instance, one reactivates a never-written slot), and updates that disable one
    // instance and give another a new SBT offset.
    let mut moved: Vec<Inst> = random_instances(&mut rng, 3, partitions, blas_address);
    let free = (0..n).find(|&k| slots[k as usize].is_none()).unwrap();
    let taken: Vec<u32> = (0..n).filter(|&k| slots[k as usize].is_some_and(|i| i.blas != 0)).collect();
    for (m, index) in moved.iter_mut().zip([taken[0], taken[1], free]) {
        m.index = index;
        m.blas = blas_address;
        slots[index as usize] = Some(*m);
    }
    let upd_bytes: Vec<u8> = [(taken[2], 7u32, 0u64), (taken[3], 9, blas_address)].iter().flat_map(|&(i, sbt, b)| [i.to_le_bytes().as_slice(), &sbt.to_le_bytes(), &b.to_le_bytes()].concat()).collect();
    for (i, sbt, b) in [(taken[2], 7u32, 0u64), (taken[3], 9, blas_address)] {
        let s = slots[i as usize].as_mut().unwrap();
        (s.sbt, s.blas) = (sbt, b);
    }
    let w2 = guarded(&a, 3 * 104);
    let u2 = guarded_data(&a, &upd_bytes);
    let ops2: Vec<u8> = [op_record(1, 2, u2.address(&a), 16), op_record(0, 3, w2.address(&a), 0)].concat();
    let ops2_reg = guarded_data(&a, &ops2);
    info.src = dst.address(&a);
    info.src_infos = ops2_reg.address(&a);
    let w2_bytes: Vec<u8> = moved.iter().flat_map(write_record).collect();
    build(&a, &nv, &info, &count_word, 2, Some((&w2, &w2_bytes)));
    let second = dst.read(&a);
    checker.check(&a, &second, &slots, &translations, 2);

    // src → dst with no ops: the same state, the same bytes; the source is left as it was.
    info.dst = dst2.address(&a);
    build(&a, &nv, &info, &count_word, 0, None);
    let copy = dst2.read(&a);
    let diff = copy.iter().zip(&second).position(|(x, y)| x != y);
    assert!(diff.is_none(), "a copy build with no ops changed the bytes (first at {diff:?} of {})", second.len());
    assert!(dst.read(&a) == second, "the source changed");
    for r in [dst, dst2, scratch, count_word, w_reg, t_reg, ops_reg, w2, u2, ops2_reg] {
        assert_guards(&a, r);
    }
    assert!(!harness::diagnostics().contains(EXT) && !harness::diagnostics().contains("PartitionedAccelerationStructures"), "diagnostics: {}", harness::diagnostics());
    a.destroy();
    ctx.finish();
}

/// The feature, the property and the extension, with validation off: the layer here does not
/// know the NV structs and would report them as unknown pNext structs.
#[test]
fn ptlas_feature_property_and_extension_are_advertised() {
    let ctx = harness::Context::new(harness::Options { validation: false, ..Default::default() });
    // SAFETY: plain queries with valid output chains.
    unsafe {
        let exts = ctx.instance.enumerate_device_extension_properties(ctx.physical).unwrap();
        assert!(exts.iter().any(|e| e.extension_name_as_c_str().unwrap().to_str().unwrap() == EXT));
        let mut f = FeaturesNV { s_type: 1000570000, p_next: std::ptr::null_mut(), partitioned_acceleration_structure: 0 };
        let mut f2 = vk::PhysicalDeviceFeatures2 { p_next: &mut f as *mut _ as *mut c_void, ..Default::default() };
        ctx.instance.get_physical_device_features2(ctx.physical, &mut f2);
        assert_eq!(f.partitioned_acceleration_structure, vk::TRUE);
        let mut p = PropertiesNV { s_type: 1000570001, p_next: std::ptr::null_mut(), max_partition_count: 0 };
        let mut p2 = vk::PhysicalDeviceProperties2 { p_next: &mut p as *mut _ as *mut c_void, ..Default::default() };
        ctx.instance.get_physical_device_properties2(ctx.physical, &mut p2);
        assert!(p.max_partition_count >= (1 << 24) - 1);
    }
    ctx.finish();
}

/// A misaligned destination (VUID 10545) and an op type repeated in srcInfos are reported,
/// the build skipped, nothing outside the command's regions written, and the queue lives.
/// Validation off: the inputs are invalid on purpose.
#[test]
fn ptlas_invalid_builds_are_reported_and_skipped() {
    let _serial = serial();
    let mut exts = harness::default_device_extensions();
    exts.push(EXT);
    let ctx = harness::Context::new(harness::Options { validation: false, acceleration_structure: true, device_extensions: exts, ..Default::default() });
    let a = Accel::new(&ctx);
    let nv = functions(&ctx);
    let inp = input(4, 4, 1, 0);
    let mut sizes = vk::AccelerationStructureBuildSizesInfoKHR::default();
    // SAFETY: valid input and output structs.
    unsafe { (nv.sizes)(ctx.device.handle(), &inp, &mut sizes) };
    let (dst, scratch, count_word) = (guarded(&a, sizes.acceleration_structure_size + 256), guarded(&a, sizes.build_scratch_size), guarded(&a, 4));
    let ops_reg = guarded_data(&a, &[op_record(0, 0, 0, 104), op_record(0, 0, 0, 104)].concat());
    let snap = snapshot(&a);
    let mut info = build_info(inp, 0, dst.address(&a) + 64, scratch.address(&a), ops_reg.address(&a), count_word.address(&a));
    let before = harness::diagnostics().len();
    build(&a, &nv, &info, &count_word, 0, None);
    let said = harness::diagnostics()[before..].to_string();
    assert!(said.contains("VUID-vkCmdBuildPartitionedAccelerationStructuresNV-pBuildInfo-10545"), "diagnostics: {said}");
    info.dst = dst.address(&a);
    let before = harness::diagnostics().len();
    build(&a, &nv, &info, &count_word, 2, None);
    let said = harness::diagnostics()[before..].to_string();
    assert!(said.contains("srcInfos[1].opType 0 is unknown or repeats"), "diagnostics: {said}");
    // Only the count word (vkCmdUpdateBuffer) changed; the destination was never written.
    verify(&a, &snap, &[count_word]);
    // The queue still works: a valid build (no ops) into the same destination.
    build(&a, &nv, &info, &count_word, 0, None);
    assert!(accel::header(&dst.read(&a)).is_some());
    a.destroy();
    ctx.finish();
}

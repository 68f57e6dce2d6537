//! A PTLAS bound with VK_DESCRIPTOR_TYPE_PARTITIONED_ACCELERATION_STRUCTURE_NV, through the
//! loader with validation on: a ray-query compute shader (tests/shaders/ptlas_rq_desc.comp)
//! traces the PTLAS reached by that descriptor, by a copy of it (vkUpdateDescriptorSets with a
//! VkCopyDescriptorSet), and by its address converted in the shader
//! (OpConvertUToAccelerationStructureKHR), and gets, ray by ray, the hits of a KHR TLAS of the
//! equivalent instance list (translations applied, disabled slots inactive) bound with an
//! ordinary acceleration-structure descriptor to the same shader.
//!
//! The validation layer here (Debian 12's, 1.3.239) predates the extension, and it crashes
//! (SIGSEGV inside the layer) in vkUpdateDescriptorSets on a write of descriptor type
//! 1000570000: no message to filter. So the traces through PTLAS descriptors run on a device
//! without the layer (`ptlas_descriptors_trace_like_the_khr_tlas`), and everything that does not
//! pass the NV descriptor type — the KHR TLAS descriptor, the PTLAS by converted address, the
//! NV build — runs validated as well (`ptlas_by_address_traces_like_the_khr_tlas_validated`).
mod harness;
mod reference;

use std::collections::HashMap;
use std::ffi::c_void;

use arbor::accel::Ray;
use arbor_scene::{InstanceRecord, Rng};
use ash::vk;
use harness::ptlas::*;
use harness::vuid::*;

const PTLAS_DESCRIPTOR: vk::DescriptorType = vk::DescriptorType::from_raw(1000570000);
const WRITE_PTLAS_STYPE: vk::StructureType = vk::StructureType::from_raw(1000570002);

/// VkWriteDescriptorSetPartitionedAccelerationStructureNV.
#[repr(C)]
struct WritePtlas {
    s_type: vk::StructureType,
    p_next: *const c_void,
    acceleration_structure_count: u32,
    p_acceleration_structures: *const u64,
}

/// One PTLAS instance as the test knows it.
#[derive(Clone, Copy)]
struct Inst {
    transform: [f32; 12],
    id: u32,
    flags: u32,
    index: u32,
    partition: u32,
    blas: u64,
}

fn write_record(i: &Inst) -> Vec<u8> {
    let mut b: Vec<u8> = i.transform.iter().chain(&[0.0f32; 6]).flat_map(|x| x.to_le_bytes()).collect();
    for w in [i.id, 0xFF, 0, i.flags, i.index, i.partition] {
        b.extend(w.to_le_bytes());
    }
    b.extend(i.blas.to_le_bytes());
    b
}

fn instances(rng: &mut Rng, n: u32, partitions: u32, blas: u64) -> Vec<Inst> {
    let kept: Vec<u32> = (0..n).filter(|_| rng.below(6) != 0).collect();
    kept.into_iter()
        .map(|index| {
            let (t, s) = ([rng.range(-3.0, 3.0), rng.range(-3.0, 3.0), rng.range(-3.0, 3.0)], rng.range(0.5, 1.5));
            Inst {
                transform: [s, 0.0, 0.0, t[0], 0.0, s, 0.0, t[1], 0.0, 0.0, s, t[2]],
                id: rng.next_u32() & 0xFF_FFFF,
                flags: rng.below(4),
                index,
                partition: if rng.below(4) == 0 { GLOBAL } else { rng.below(partitions) },
                blas: if rng.below(8) == 0 { 0 } else { blas },
            }
        })
        .collect()
}

/// The equivalent KHR instance list: translation added, unwritten slots inactive.
fn equivalent(n: u32, written: &[Inst], translations: &HashMap<u32, [f32; 3]>) -> Vec<InstanceRecord> {
    let mut records = vec![InstanceRecord { transform: IDENTITY, custom_index: 0, mask: 0, sbt_offset: 0, flags: 0, reference: 0 }; n as usize];
    for i in written {
        let (mut m, t) = (i.transform, translations.get(&i.partition).copied().unwrap_or([0.0; 3]));
        (m[3], m[7], m[11]) = (m[3] + t[0], m[7] + t[1], m[11] + t[2]);
        records[i.index as usize] = InstanceRecord { transform: m, custom_index: i.id, mask: 0xFF, sbt_offset: 0, flags: i.flags as u8, reference: i.blas };
    }
    records
}

/// Builds the PTLAS of `written` and `translations` from scratch; its region.
fn build_ptlas(a: &Accel, n: u32, partitions: u32, written: &[Inst], translations: &HashMap<u32, [f32; 3]>) -> Region {
    let ctx = a.ctx;
    let nv = functions(ctx);
    let flags = translation_enabled();
    let input = InstancesInput { p_next: &flags as *const _ as *const c_void, ..input(n, n, partitions, n) };
    let mut sizes = vk::AccelerationStructureBuildSizesInfoKHR::default();
    // SAFETY: valid input and output structs.
    unsafe { (nv.sizes)(ctx.device.handle(), &input, &mut sizes) };
    let (dst, scratch) = (guarded(a, sizes.acceleration_structure_size), guarded(a, sizes.build_scratch_size));
    let writes = guarded_data(a, &written.iter().flat_map(write_record).collect::<Vec<u8>>());
    let t_bytes: Vec<u8> = translations.iter().flat_map(|(p, t)| [p.to_le_bytes(), t[0].to_le_bytes(), t[1].to_le_bytes(), t[2].to_le_bytes()].concat()).collect();
    let t_reg = guarded_data(a, &t_bytes);
    let ops = guarded_data(a, &[op_record(0, written.len() as u32, writes.address(a), 104), op_record(2, translations.len() as u32, t_reg.address(a), 16)].concat());
    let count = guarded_data(a, &2u32.to_le_bytes());
    let info = build_info(input, 0, dst.address(a), scratch.address(a), ops.address(a), count.address(a));
    // SAFETY: a valid command buffer; the info lives through the call.
    a.submit(|cb| unsafe { (nv.build)(cb, &info) });
    dst
}

/// How binding 2 of the set the shader traces is filled.
enum Scene {
    /// A PTLAS descriptor written with this address; `copied`: the set traced is a copy.
    Ptlas { address: u64, copied: bool },
    Khr(vk::AccelerationStructureKHR),
}

/// The shader over `rays` with binding 2 filled per `scene`, or through `by_address` when it is
/// non-zero; the hits buffer.
// One function: the objects of one dispatch, created and destroyed around it.
fn trace(a: &Accel, scene: &Scene, by_address: u64, rays: &[Ray]) -> Vec<u8> {
    let d = &a.ctx.device;
    let (rb, hb) = (a.upload(&harness::trace::ray_bytes(rays)), a.buffer(16 * rays.len() as u64));
    let spirv = harness::compute::glsl("ptlas_rq_desc.comp");
    let stage = vk::ShaderStageFlags::COMPUTE;
    let as_type = if matches!(scene, Scene::Khr(_)) { vk::DescriptorType::ACCELERATION_STRUCTURE_KHR } else { PTLAS_DESCRIPTOR };
    let types = [vk::DescriptorType::STORAGE_BUFFER, vk::DescriptorType::STORAGE_BUFFER, as_type];
    let bindings = [0, 1, 2].map(|b| vk::DescriptorSetLayoutBinding::default().binding(b).descriptor_type(types[b as usize]).descriptor_count(1).stage_flags(stage));
    // SAFETY: valid create infos and pNext chains; everything is destroyed before returning, after the wait.
    unsafe {
        let set_layout = d.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings), None).unwrap();
        let sizes = [vk::DescriptorPoolSize { ty: vk::DescriptorType::STORAGE_BUFFER, descriptor_count: 4 }, vk::DescriptorPoolSize { ty: as_type, descriptor_count: 2 }];
        let pool = d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(2).pool_sizes(&sizes), None).unwrap();
        let layouts = [set_layout, set_layout];
        let sets = d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&layouts)).unwrap();
        let infos = [rb, hb].map(|b| [vk::DescriptorBufferInfo { buffer: a.buf(b).buffer, offset: 0, range: vk::WHOLE_SIZE }]);
        let mut writes: Vec<vk::WriteDescriptorSet> = (0..2).map(|k| vk::WriteDescriptorSet::default().dst_set(sets[0]).dst_binding(k as u32).descriptor_type(vk::DescriptorType::STORAGE_BUFFER).buffer_info(&infos[k])).collect();
        let handles: [vk::AccelerationStructureKHR; 1];
        let mut khr_write;
        let addresses: [u64; 1];
        let ptlas_write;
        let structure = vk::WriteDescriptorSet::default().dst_set(sets[0]).dst_binding(2).descriptor_type(as_type).descriptor_count(1);
        match scene {
            Scene::Khr(s) => {
                handles = [*s];
                khr_write = vk::WriteDescriptorSetAccelerationStructureKHR::default().acceleration_structures(&handles);
                writes.push(structure.push_next(&mut khr_write));
            }
            Scene::Ptlas { address, .. } => {
                addresses = [*address];
                ptlas_write = WritePtlas { s_type: WRITE_PTLAS_STYPE, p_next: std::ptr::null(), acceleration_structure_count: 1, p_acceleration_structures: addresses.as_ptr() };
                writes.push(vk::WriteDescriptorSet { p_next: &ptlas_write as *const _ as *const c_void, ..structure });
            }
        }
        d.update_descriptor_sets(&writes, &[]);
        let copied = matches!(scene, Scene::Ptlas { copied: true, .. });
        if copied {
            let copy = [vk::CopyDescriptorSet::default().src_set(sets[0]).dst_set(sets[1]).descriptor_count(1)];
            let copies: Vec<vk::CopyDescriptorSet> = (0..3).map(|b| vk::CopyDescriptorSet { src_binding: b, dst_binding: b, ..copy[0] }).collect();
            d.update_descriptor_sets(&[], &copies);
        }
        let set = sets[copied as usize];
        let pipeline = harness::trace::Pipeline::new(d, &spirv, set_layout, 16);
        let push: Vec<u8> = [by_address as u32, (by_address >> 32) as u32, rays.len() as u32, (by_address != 0) as u32].iter().flat_map(|x| x.to_le_bytes()).collect();
        a.submit(|cb| pipeline.record(d, cb, set, &push, (rays.len() as u32).div_ceil(64)));
        pipeline.destroy(d);
        d.destroy_descriptor_pool(pool, None);
        d.destroy_descriptor_set_layout(set_layout, None);
    }
    a.buf(hb).read(0, 16 * rays.len())
}

/// Builds the scene (the same on every device: seeded) and compares each way of reaching the
/// PTLAS in `ways` with the KHR TLAS, ray by ray.
fn compare_with_khr(validation: bool, ways: &[&str]) {
    let mut exts = harness::default_device_extensions();
    exts.push(EXT);
    exts.push("VK_KHR_ray_query");
    let ctx = harness::Context::new(harness::Options { validation, acceleration_structure: true, device_extensions: exts, ..Default::default() });
    let a = Accel::new(&ctx);
    let mesh = upload_grid(&a);
    let (blas, _) = valid_blas(&a, &mesh, NO_FLAGS);
    let blas_address = a.address_of(blas.s);
    let (n, partitions) = (96u32, 4u32);
    let written = instances(&mut Rng::new(2024), n, partitions, blas_address);
    let translations: HashMap<u32, [f32; 3]> = [(1, [0.75, -0.5, 0.25]), (GLOBAL, [-0.5, 0.25, 1.0])].into_iter().collect();
    let ptlas = build_ptlas(&a, n, partitions, &written, &translations);
    let tlas = khr_tlas(&a, &equivalent(n, &written, &translations));
    let rays = reference::random_rays([-4.0, -4.0, -4.0, 5.0, 5.0, 5.0], 512, 11);
    let address = ptlas.address(&a);
    let khr = trace(&a, &Scene::Khr(tlas.s), 0, &rays);
    let word = |h: &[u8], k: usize| u32::from_le_bytes(h[4 * k..4 * k + 4].try_into().unwrap());
    let hits = khr.chunks(16).filter(|h| word(h, 2) != u32::MAX).count();
    assert!(hits > 50 && hits < rays.len() - 50, "{hits} of {} rays hit the KHR TLAS: the scene is not exercised", rays.len());
    for how in ways {
        let got = match *how {
            "descriptor" => trace(&a, &Scene::Ptlas { address, copied: false }, 0, &rays),
            "copied descriptor" => trace(&a, &Scene::Ptlas { address, copied: true }, 0, &rays),
            // Binding 2 holds a null PTLAS descriptor (address 0), which the shader never reads.
            "address, null descriptor bound" => trace(&a, &Scene::Ptlas { address: 0, copied: false }, address, &rays),
            "address" => trace(&a, &Scene::Khr(tlas.s), address, &rays),
            other => panic!("unknown way {other}"),
        };
        for (i, (p, k)) in got.chunks(16).zip(khr.chunks(16)).enumerate() {
            let fields = |h: &[u8]| (word(h, 0), word(h, 1), word(h, 2), word(h, 3));
            assert_eq!(fields(p), fields(k), "ray {i}: the PTLAS by {how} and the KHR TLAS disagree (t bits, primitive, instance, custom index)");
        }
    }
    for r in [ptlas, tlas.r] {
        assert_guards(&a, r);
    }
    a.destroy();
    ctx.finish();
}

#[test]
fn ptlas_descriptors_trace_like_the_khr_tlas() {
    compare_with_khr(false, &["descriptor", "copied descriptor", "address, null descriptor bound"]);
}

#[test]
fn ptlas_by_address_traces_like_the_khr_tlas_validated() {
    compare_with_khr(true, &["address"]);
}

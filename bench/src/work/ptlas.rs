//! Partitioned top-level workloads (VK_NV_partitioned_acceleration_structure) over an instance
//! scene, through the API: `ptlas-build` (every instance written, src = 0), `ptlas-update-1pct`
//! (1 % of the instances rewritten in place with moved transforms, spread over the partitions,
//! src == dst as real clients do every frame) and `ptlas-khr-tlas` (the KHR TLAS build of the
//! same instances, PREFER_FAST_BUILD). Drivers without the extension read "not supported".
//!
//! Instances go to partitions spatially (Morton order of their positions, cut into equal runs),
//! as clients partition a world. Where the result can be read (Arbor, host-visible memory) the
//! row is checked: the structure's active-instance count must be the scene's.
use std::ffi::{c_void, CStr};

use arbor_scene::InstanceRecord;
use ash::vk;

use super::inputs::{device_target, Inputs};
use super::device::fill_times;
use super::{Options, Row, Status, Workload};
use crate::vkctx::{Arena, Buf, Gpu, Place};

const OP_WRITE_INSTANCE: u32 = 0;
const WRITE_INSTANCE_SIZE: usize = 104;
/// Offsets in the op buffer: the count, the op record, the write records (256-aligned each).
const OPS_AT: u64 = 256;
const RECORDS_AT: u64 = 512;

#[repr(C)]
#[derive(Clone, Copy)]
struct InstancesInput {
    s_type: vk::StructureType,
    p_next: *const c_void,
    flags: u32,
    instance_count: u32,
    max_instance_per_partition_count: u32,
    partition_count: u32,
    max_instance_in_global_partition_count: u32,
}

#[repr(C)]
struct BuildInfo {
    s_type: vk::StructureType,
    p_next: *const c_void,
    input: InstancesInput,
    src: u64,
    dst: u64,
    scratch: u64,
    src_infos: u64,
    src_infos_count: u64,
}

type PfnSizes = unsafe extern "system" fn(vk::Device, *const InstancesInput, *mut vk::AccelerationStructureBuildSizesInfoKHR<'_>);
type PfnBuild = unsafe extern "system" fn(vk::CommandBuffer, *const BuildInfo);

struct Nv {
    sizes: PfnSizes,
    build: PfnBuild,
}

fn functions(gpu: &Gpu) -> Result<Nv, String> {
    let get = |name: &CStr| {
        // SAFETY: a live device; the name is a command of an enabled extension.
        unsafe { (gpu.get_device_proc_addr)(gpu.device.handle(), name.as_ptr()) }.ok_or_else(|| format!("{name:?} not found"))
    };
    let (s, b) = (get(c"vkGetPartitionedAccelerationStructuresBuildSizesNV")?, get(c"vkCmdBuildPartitionedAccelerationStructuresNV")?);
    // SAFETY: the pointers are the commands of these names, with these signatures (vk.xml).
    unsafe { Ok(Nv { sizes: std::mem::transmute::<unsafe extern "system" fn(), PfnSizes>(s), build: std::mem::transmute::<unsafe extern "system" fn(), PfnBuild>(b) }) }
}

/// Spreads the bits of a 10-bit value three apart.
fn spread(v: u32) -> u32 {
    let mut x = v & 0x3ff;
    x = (x | (x << 16)) & 0x0300_00ff;
    x = (x | (x << 8)) & 0x0300_f00f;
    x = (x | (x << 4)) & 0x030c_30c3;
    (x | (x << 2)) & 0x0924_9249
}

/// The partition of each instance (Morton order of its position, `per` instances a partition)
/// and `per`.
fn partitions_of(records: &[InstanceRecord], partitions: u32) -> (Vec<u32>, u32) {
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    let pos = |r: &InstanceRecord| [r.transform[3], r.transform[7], r.transform[11]];
    for r in records {
        for (a, v) in pos(r).into_iter().enumerate() {
            lo[a] = lo[a].min(v);
            hi[a] = hi[a].max(v);
        }
    }
    let code = |r: &InstanceRecord| {
        let p = pos(r);
        let q = |a: usize| (((p[a] - lo[a]) / (hi[a] - lo[a]).max(1e-20)) * 1023.0) as u32;
        spread(q(0)) | spread(q(1)) << 1 | spread(q(2)) << 2
    };
    let mut order: Vec<(u32, u32)> = records.iter().enumerate().map(|(i, r)| (code(r), i as u32)).collect();
    order.sort_unstable();
    let per = (records.len() as u32).div_ceil(partitions.max(1)).max(1);
    let mut part = vec![0u32; records.len()];
    for (k, &(_, i)) in order.iter().enumerate() {
        part[i as usize] = k as u32 / per;
    }
    (part, per)
}

/// VkPartitionedAccelerationStructureWriteInstanceDataNV of instance `index`.
fn write_record(r: &InstanceRecord, index: u32, partition: u32, out: &mut Vec<u8>) {
    r.transform.iter().chain([0.0f32; 6].iter()).for_each(|x| out.extend(x.to_le_bytes()));
    for w in [r.custom_index & 0xff_ffff, r.mask as u32, r.sbt_offset & 0xff_ffff, r.flags as u32 & 0xf, index, partition] {
        out.extend(w.to_le_bytes());
    }
    out.extend(r.reference.to_le_bytes());
}

/// One op buffer: the op count (1) and one WRITE_INSTANCE op over `writes` (packed records).
fn op_buffer(a: &Arena, writes: &[u8]) -> Result<Buf, String> {
    let mut bytes = vec![0u8; RECORDS_AT as usize];
    bytes[..4].copy_from_slice(&1u32.to_le_bytes());
    bytes.extend_from_slice(writes);
    let b = a.upload(&bytes)?;
    // The op record holds the records' address, known once the buffer exists.
    let count = (writes.len() / WRITE_INSTANCE_SIZE) as u32;
    let op = [OP_WRITE_INSTANCE.to_le_bytes().as_slice(), &count.to_le_bytes(), &(b.address + RECORDS_AT).to_le_bytes(), &(WRITE_INSTANCE_SIZE as u64).to_le_bytes()].concat();
    a.gpu.submit(|cb| {
        // SAFETY: a recording command buffer; 24 bytes inside a live buffer.
        unsafe { a.gpu.device.cmd_update_buffer(cb, b.buffer, OPS_AT, &op) }
    })?;
    Ok(b)
}

/// The 1 % of instances the update rewrites: one in each run of 100, at a seeded place in it.
fn update_slots(n: u32) -> Vec<u32> {
    let mut rng = arbor_scene::Rng::new(24);
    (0..n / 100).map(|k| k * 100 + rng.below(100)).collect()
}

/// The record of instance i moved a little (stays in its partition, as a frame's animation).
fn moved(r: &InstanceRecord, i: u32) -> InstanceRecord {
    let mut m = *r;
    m.transform[3] += 0.02 * (i as f32 * 0.7).sin();
    m.transform[7] += 0.02 * (i as f32 * 1.3).cos();
    m
}

pub(super) fn run(gpu: &Gpu, inp: &Inputs, w: Workload, opts: &Options, row: &mut Row) -> Result<(), String> {
    if inp.ty != vk::AccelerationStructureTypeKHR::TOP_LEVEL {
        row.status = Status::NotSupported("needs an instance scene (--scene ptlas)".into());
        return Ok(());
    }
    if w == Workload::PtlasKhrTlas {
        return khr_tlas(gpu, inp, opts, row);
    }
    if !gpu.caps.ptlas {
        row.status = Status::NotSupported(format!("no {}", crate::vkctx::PTLAS_EXTENSION));
        return Ok(());
    }
    let nv = functions(gpu)?;
    let a = Arena::new(gpu);
    let n = inp.count;
    let (part, per) = partitions_of(&inp.records, opts.partitions);
    let input = InstancesInput {
        s_type: vk::StructureType::from_raw(1_000_570_003),
        p_next: std::ptr::null(),
        flags: 0,
        instance_count: n,
        max_instance_per_partition_count: per,
        partition_count: opts.partitions.max(1),
        max_instance_in_global_partition_count: 0,
    };
    let mut sizes = vk::AccelerationStructureBuildSizesInfoKHR::default();
    // SAFETY: a live device, a valid input struct, a writable sizes struct.
    unsafe { (nv.sizes)(gpu.device.handle(), &input, &mut sizes) };
    let dst = a.buffer(sizes.acceleration_structure_size, Place::Device)?;
    let scratch = a.buffer(sizes.build_scratch_size, Place::Device)?;
    let mut all = Vec::with_capacity(n as usize * WRITE_INSTANCE_SIZE);
    for (i, r) in inp.records.iter().enumerate() {
        write_record(r, i as u32, part[i], &mut all);
    }
    let full = op_buffer(&a, &all)?;
    drop(all);
    let info = |ops: &Buf, src: u64| BuildInfo {
        s_type: vk::StructureType::from_raw(1_000_570_004),
        p_next: std::ptr::null(),
        input,
        src,
        dst: dst.address,
        scratch: scratch.address,
        src_infos: ops.address + OPS_AT,
        src_infos_count: ops.address,
    };
    let full_info = info(&full, 0);
    let record = |cb: vk::CommandBuffer, bi: &BuildInfo| {
        // SAFETY: a recording command buffer; every address lives until the work has completed.
        unsafe { (nv.build)(cb, bi) }
    };
    let slots = update_slots(n);
    let times = if w == Workload::PtlasBuild {
        gpu.timed(opts.warmup, opts.repeat, |cb| record(cb, &full_info))?
    } else {
        gpu.submit(|cb| record(cb, &full_info))?;
        let mut upd = Vec::with_capacity(slots.len() * WRITE_INSTANCE_SIZE);
        for &i in &slots {
            write_record(&moved(&inp.records[i as usize], i), i, part[i as usize], &mut upd);
        }
        let ops = op_buffer(&a, &upd)?;
        let upd_info = info(&ops, dst.address);
        gpu.timed(opts.warmup, opts.repeat, |cb| record(cb, &upd_info))?
    };
    fill_times(row, &times);
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.build_scratch_size;
    let touched = if w == Workload::PtlasBuild { n } else { slots.len() as u32 };
    row.note = format!("{} partitions of {per}, {touched} instances written", input.partition_count);
    check(&dst, n, row)
}

/// Where the structure is Arbor's and readable: its active-instance count must be `n`.
fn check(dst: &Buf, n: u32, row: &mut Row) -> Result<(), String> {
    if dst.ptr.is_null() {
        row.note.push_str("; unchecked (not host-visible)");
        return Ok(());
    }
    let head = dst.read(0, arbor::accel::ptlas::HEADER_SIZE);
    let Some(h) = arbor::accel::ptlas::header(&head) else {
        row.note.push_str("; unchecked (not an Arbor structure)");
        return Ok(());
    };
    let bytes = dst.read(0, h.used_size as usize);
    let active = arbor::accel::header(&bytes).map(|e| e.leaf_count);
    if active != Some(n) {
        return Err(format!("the built structure holds {active:?} active instances, not {n}"));
    }
    Ok(())
}

/// The KHR TLAS build of the same instances (PREFER_FAST_BUILD), checked the same way.
fn khr_tlas(gpu: &Gpu, inp: &Inputs, opts: &Options, row: &mut Row) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [inp.geom];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let (sizes, _s, info) = device_target(&a, inp, info)?;
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(inp.count)];
    let times = gpu.timed(opts.warmup, opts.repeat, |cb| {
        // SAFETY: valid infos; buffers live until `timed` has waited.
        unsafe { gpu.ext.cmd_build_acceleration_structures(cb, &[info], &[&range]) };
    })?;
    fill_times(row, &times);
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.build_scratch_size;
    row.note = "PREFER_FAST_BUILD".into();
    Ok(())
}

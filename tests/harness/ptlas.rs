//! VK_NV_partitioned_acceleration_structure as the PTLAS tests (`tests/ptlas_*.rs`) call it:
//! the NV structs, written here from the registry (spec/nv-extensions.md A.4), not taken from
//! Arbor; its two commands resolved through the loader; the 24-byte op record; and the KHR TLAS
//! of an equivalent instance list that the tests compare a PTLAS with.
use std::ffi::c_void;

use arbor_scene::InstanceRecord;
use ash::vk;

use super::vuid::{cmd_build, guarded, guarded_data, guarded_structure, info, instances_geom, madr, range, Accel, Dst, DEVICE, NO_FLAGS, TLAS};

pub const EXT: &str = "VK_NV_partitioned_acceleration_structure";
/// The partition index of the global partition.
pub const GLOBAL: u32 = u32::MAX;

/// VkPartitionedAccelerationStructureInstancesInputNV.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct InstancesInput {
    pub s_type: i32,
    pub p_next: *const c_void,
    pub flags: u32,
    pub instance_count: u32,
    pub max_instance_per_partition_count: u32,
    pub partition_count: u32,
    pub max_instance_in_global_partition_count: u32,
}

/// VkPartitionedAccelerationStructureFlagsNV.
#[repr(C)]
pub struct TranslationFlags {
    pub s_type: i32,
    pub p_next: *const c_void,
    pub enable_partition_translation: u32,
}

/// VkBuildPartitionedAccelerationStructureInfoNV.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct BuildInfo {
    pub s_type: i32,
    pub p_next: *const c_void,
    pub input: InstancesInput,
    pub src: u64,
    pub dst: u64,
    pub scratch: u64,
    pub src_infos: u64,
    pub src_infos_count: u64,
}

pub type PfnSizes = unsafe extern "system" fn(vk::Device, *const InstancesInput, *mut vk::AccelerationStructureBuildSizesInfoKHR<'_>);
pub type PfnBuild = unsafe extern "system" fn(vk::CommandBuffer, *const BuildInfo);

/// An input of `n` instances, `per` per partition, `partitions` partitions and `global` in the
/// global one, with no pNext chain.
pub fn input(n: u32, per: u32, partitions: u32, global: u32) -> InstancesInput {
    InstancesInput { s_type: 1000570003, p_next: std::ptr::null(), flags: 0, instance_count: n, max_instance_per_partition_count: per, partition_count: partitions, max_instance_in_global_partition_count: global }
}

/// The flags struct with partition translation enabled.
pub fn translation_enabled() -> TranslationFlags {
    TranslationFlags { s_type: 1000570005, p_next: std::ptr::null(), enable_partition_translation: 1 }
}

/// A build of `input` from `src` (0: from scratch) into `dst`, op records at `src_infos`, their
/// count at `src_infos_count`; no pNext chain.
pub fn build_info(input: InstancesInput, src: u64, dst: u64, scratch: u64, src_infos: u64, src_infos_count: u64) -> BuildInfo {
    BuildInfo { s_type: 1000570004, p_next: std::ptr::null(), input, src, dst, scratch, src_infos, src_infos_count }
}

/// VkBuildPartitionedAccelerationStructureIndirectCommandNV (24 bytes).
pub fn op_record(op: u32, count: u32, address: u64, stride: u64) -> Vec<u8> {
    [op.to_le_bytes().as_slice(), &count.to_le_bytes(), &address.to_le_bytes(), &stride.to_le_bytes()].concat()
}

/// The extension's commands on one device.
pub struct Nv {
    pub sizes: PfnSizes,
    pub build: PfnBuild,
}

/// Resolves the commands through the loader; panics where the device does not expose them.
pub fn functions(ctx: &super::Context) -> Nv {
    let get = |name: &std::ffi::CStr| {
        // SAFETY: a live device; the name is a command of an enabled extension.
        let f = unsafe { ctx.instance.get_device_proc_addr(ctx.device.handle(), name.as_ptr()) };
        f.unwrap_or_else(|| panic!("{name:?} not found"))
    };
    // SAFETY: the pointers are the commands of these names, with these signatures.
    unsafe {
        Nv {
            sizes: std::mem::transmute::<unsafe extern "system" fn(), PfnSizes>(get(c"vkGetPartitionedAccelerationStructuresBuildSizesNV")),
            build: std::mem::transmute::<unsafe extern "system" fn(), PfnBuild>(get(c"vkCmdBuildPartitionedAccelerationStructuresNV")),
        }
    }
}

/// A KHR TLAS of `records` built through the API (vkCmdBuildAccelerationStructuresKHR) into a
/// guarded destination.
pub fn khr_tlas(a: &Accel, records: &[InstanceRecord]) -> Dst {
    let inst = guarded_data(a, &records.iter().flat_map(|r| r.to_bytes()).collect::<Vec<u8>>());
    let geoms = [instances_geom(inst.address(a), false)];
    let inf = info(TLAS, NO_FLAGS, &geoms);
    let n = records.len() as u32;
    let sizes = a.sizes(DEVICE, &inf, &[n]);
    let tlas = guarded_structure(a, TLAS, sizes.acceleration_structure_size);
    let scratch = guarded(a, sizes.build_scratch_size);
    cmd_build(a, &[inf.dst_acceleration_structure(tlas.s).scratch_data(madr(scratch.address(a)))], &[&[range(n)]]);
    tlas
}

//! VK_NV_partitioned_acceleration_structure: the types of vk.xml that ash 0.38 lacks (layouts
//! tested below against spec/nv-extensions.md A.4), the feature and property structs of the
//! `*2` chains, and the two entry points. Lowering turns the build info into an owned
//! `runtime::accel::ptlas::PtlasBuild`; the op records themselves live in device memory and are
//! read when the command executes, never here.
#![allow(non_camel_case_types)]
use std::ffi::c_void;

use ash::vk;

use super::command::command_buffer_from;
use super::table::{void_fn, Implemented};
use super::{guard, util};
use crate::runtime::accel::ptlas::{self as rt, PtlasBuild, PtlasCommand, PtlasInput};

pub const EXTENSION_NAME: &str = "VK_NV_partitioned_acceleration_structure";
pub const SPEC_VERSION: u32 = 1;

pub const STRUCTURE_TYPE_PHYSICAL_DEVICE_PARTITIONED_ACCELERATION_STRUCTURE_FEATURES_NV: vk::StructureType = vk::StructureType::from_raw(1000570000);
pub const STRUCTURE_TYPE_PHYSICAL_DEVICE_PARTITIONED_ACCELERATION_STRUCTURE_PROPERTIES_NV: vk::StructureType = vk::StructureType::from_raw(1000570001);
pub const STRUCTURE_TYPE_WRITE_DESCRIPTOR_SET_PARTITIONED_ACCELERATION_STRUCTURE_NV: vk::StructureType = vk::StructureType::from_raw(1000570002);
pub const STRUCTURE_TYPE_PARTITIONED_ACCELERATION_STRUCTURE_INSTANCES_INPUT_NV: vk::StructureType = vk::StructureType::from_raw(1000570003);
pub const STRUCTURE_TYPE_BUILD_PARTITIONED_ACCELERATION_STRUCTURE_INFO_NV: vk::StructureType = vk::StructureType::from_raw(1000570004);
pub const STRUCTURE_TYPE_PARTITIONED_ACCELERATION_STRUCTURE_FLAGS_NV: vk::StructureType = vk::StructureType::from_raw(1000570005);
pub const DESCRIPTOR_TYPE_PARTITIONED_ACCELERATION_STRUCTURE_NV: vk::DescriptorType = vk::DescriptorType::from_raw(1000570000);
pub const PARTITIONED_ACCELERATION_STRUCTURE_PARTITION_INDEX_GLOBAL_NV: u32 = !0;

/// VkPartitionedAccelerationStructureOpTypeNV.
pub const OP_TYPE_WRITE_INSTANCE_NV: i32 = 0;
pub const OP_TYPE_UPDATE_INSTANCE_NV: i32 = 1;
pub const OP_TYPE_WRITE_PARTITION_TRANSLATION_NV: i32 = 2;

/// VkPartitionedAccelerationStructureInstanceFlagBitsNV.
pub const INSTANCE_FLAG_TRIANGLE_FACING_CULL_DISABLE_BIT_NV: u32 = 0x1;
pub const INSTANCE_FLAG_TRIANGLE_FLIP_FACING_BIT_NV: u32 = 0x2;
pub const INSTANCE_FLAG_FORCE_OPAQUE_BIT_NV: u32 = 0x4;
pub const INSTANCE_FLAG_FORCE_NO_OPAQUE_BIT_NV: u32 = 0x8;
pub const INSTANCE_FLAG_ENABLE_EXPLICIT_BOUNDING_BOX_NV: u32 = 0x10;

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct PhysicalDevicePartitionedAccelerationStructureFeaturesNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub partitioned_acceleration_structure: vk::Bool32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct PhysicalDevicePartitionedAccelerationStructurePropertiesNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub max_partition_count: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct PartitionedAccelerationStructureInstancesInputNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub flags: vk::BuildAccelerationStructureFlagsKHR,
    pub instance_count: u32,
    pub max_instance_per_partition_count: u32,
    pub partition_count: u32,
    pub max_instance_in_global_partition_count: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct PartitionedAccelerationStructureFlagsNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub enable_partition_translation: vk::Bool32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct BuildPartitionedAccelerationStructureInfoNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub input: PartitionedAccelerationStructureInstancesInputNV,
    pub src_acceleration_structure_data: vk::DeviceAddress,
    pub dst_acceleration_structure_data: vk::DeviceAddress,
    pub scratch_data: vk::DeviceAddress,
    pub src_infos: vk::DeviceAddress,
    pub src_infos_count: vk::DeviceAddress,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default)]
pub struct StridedDeviceAddressNV {
    pub start_address: vk::DeviceAddress,
    pub stride_in_bytes: vk::DeviceSize,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default)]
pub struct BuildPartitionedAccelerationStructureIndirectCommandNV {
    pub op_type: i32,
    pub arg_count: u32,
    pub arg_data: StridedDeviceAddressNV,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct PartitionedAccelerationStructureWriteInstanceDataNV {
    pub transform: vk::TransformMatrixKHR,
    pub explicit_aabb: [f32; 6],
    pub instance_id: u32,
    pub instance_mask: u32,
    pub instance_contribution_to_hit_group_index: u32,
    pub instance_flags: u32,
    pub instance_index: u32,
    pub partition_index: u32,
    pub acceleration_structure: vk::DeviceAddress,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default)]
pub struct PartitionedAccelerationStructureUpdateInstanceDataNV {
    pub instance_index: u32,
    pub instance_contribution_to_hit_group_index: u32,
    pub acceleration_structure: vk::DeviceAddress,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default)]
pub struct PartitionedAccelerationStructureWritePartitionTranslationDataNV {
    pub partition_index: u32,
    pub partition_translation: [f32; 3],
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct WriteDescriptorSetPartitionedAccelerationStructureNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub acceleration_structure_count: u32,
    pub p_acceleration_structures: *const vk::DeviceAddress,
}

pub type PFN_vkGetPartitionedAccelerationStructuresBuildSizesNV = unsafe extern "system" fn(
    device: vk::Device,
    p_info: *const PartitionedAccelerationStructureInstancesInputNV,
    p_size_info: *mut vk::AccelerationStructureBuildSizesInfoKHR,
);
pub type PFN_vkCmdBuildPartitionedAccelerationStructuresNV =
    unsafe extern "system" fn(command_buffer: vk::CommandBuffer, p_build_info: *const BuildPartitionedAccelerationStructureInfoNV);

/// The largest `partitionCount + maxInstanceInGlobalPartitionCount` (the spec's minimum, 2^24 − 1).
pub const MAX_PARTITION_COUNT: u32 = rt::MAX_PARTITION_COUNT;

pub fn commands() -> Vec<Implemented> {
    vec![
        Implemented {
            pfn: "PFN_vkGetPartitionedAccelerationStructuresBuildSizesNV",
            f: void_fn!(@local PFN_vkGetPartitionedAccelerationStructuresBuildSizesNV => get_partitioned_acceleration_structures_build_sizes_nv),
        },
        Implemented {
            pfn: "PFN_vkCmdBuildPartitionedAccelerationStructuresNV",
            f: void_fn!(@local PFN_vkCmdBuildPartitionedAccelerationStructuresNV => cmd_build_partitioned_acceleration_structures_nv),
        },
    ]
}

/// The feature struct of a `vkGetPhysicalDeviceFeatures2` chain (false: not this extension's).
///
/// # Safety
/// `p` points to a writable struct of type `s_type`.
pub unsafe fn fill_feature_struct(s_type: vk::StructureType, p: *mut c_void) -> bool {
    if s_type != STRUCTURE_TYPE_PHYSICAL_DEVICE_PARTITIONED_ACCELERATION_STRUCTURE_FEATURES_NV {
        return false;
    }
    let v = PhysicalDevicePartitionedAccelerationStructureFeaturesNV { s_type, p_next: std::ptr::null_mut(), partitioned_acceleration_structure: vk::TRUE };
    // SAFETY: the sType identifies the struct (this function's contract); pNext is kept.
    unsafe { util::write_keep_chain(p, v) };
    true
}

/// The property struct of a `vkGetPhysicalDeviceProperties2` chain (false: not this extension's).
///
/// # Safety
/// `p` points to a writable struct of type `s_type`.
pub unsafe fn fill_property_struct(s_type: vk::StructureType, p: *mut c_void) -> bool {
    if s_type != STRUCTURE_TYPE_PHYSICAL_DEVICE_PARTITIONED_ACCELERATION_STRUCTURE_PROPERTIES_NV {
        return false;
    }
    let v = PhysicalDevicePartitionedAccelerationStructurePropertiesNV { s_type, p_next: std::ptr::null_mut(), max_partition_count: MAX_PARTITION_COUNT };
    // SAFETY: the sType identifies the struct (this function's contract); pNext is kept.
    unsafe { util::write_keep_chain(p, v) };
    true
}

/// The instance input with the translation flag of its pNext chain.
///
/// # Safety
/// `input` is a valid VkPartitionedAccelerationStructureInstancesInputNV (pNext chain included).
unsafe fn lower_input(input: &PartitionedAccelerationStructureInstancesInputNV) -> PtlasInput {
    // SAFETY: a valid pNext chain (this function's contract).
    let flags = unsafe { util::find_in::<PartitionedAccelerationStructureFlagsNV>(input.p_next, STRUCTURE_TYPE_PARTITIONED_ACCELERATION_STRUCTURE_FLAGS_NV) };
    PtlasInput {
        flags: input.flags.as_raw(),
        instance_count: input.instance_count,
        max_instance_per_partition_count: input.max_instance_per_partition_count,
        partition_count: input.partition_count,
        max_instance_in_global_partition_count: input.max_instance_in_global_partition_count,
        translation: flags.is_some_and(|f| f.enable_partition_translation != 0),
    }
}

unsafe extern "system" fn get_partitioned_acceleration_structures_build_sizes_nv(
    _device: vk::Device,
    p_info: *const PartitionedAccelerationStructureInstancesInputNV,
    p_size_info: *mut vk::AccelerationStructureBuildSizesInfoKHR,
) {
    const CMD: &str = "vkGetPartitionedAccelerationStructuresBuildSizesNV";
    guard(CMD, (), || {
        if p_info.is_null() || p_size_info.is_null() {
            return;
        }
        // SAFETY: a valid input struct per the spec.
        let input = unsafe { lower_input(&*p_info) };
        if input.partition_count as u64 + input.max_instance_in_global_partition_count as u64 > MAX_PARTITION_COUNT as u64 {
            let what = format!("partitionCount {} + maxInstanceInGlobalPartitionCount {} exceeds maxPartitionCount {MAX_PARTITION_COUNT}", input.partition_count, input.max_instance_in_global_partition_count);
            crate::diag::vuid("VUID-VkPartitionedAccelerationStructureInstancesInputNV-partitionCount-10535", CMD, &what);
        }
        let s = rt::build_sizes(&input);
        // SAFETY: a valid output struct; sType and pNext are kept.
        unsafe {
            (*p_size_info).acceleration_structure_size = s.acceleration_structure_size;
            (*p_size_info).build_scratch_size = s.build_scratch_size;
            (*p_size_info).update_scratch_size = s.update_scratch_size;
        }
    })
}

unsafe extern "system" fn cmd_build_partitioned_acceleration_structures_nv(
    command_buffer: vk::CommandBuffer,
    p_build_info: *const BuildPartitionedAccelerationStructureInfoNV,
) {
    const CMD: &str = "vkCmdBuildPartitionedAccelerationStructuresNV";
    guard(CMD, (), || {
        let Some(cb) = command_buffer_from(command_buffer) else { return };
        if p_build_info.is_null() {
            crate::diag::vuid("VUID-vkCmdBuildPartitionedAccelerationStructuresNV-pBuildInfo-parameter", CMD, "pBuildInfo is NULL");
            return;
        }
        // SAFETY: a valid build info per the spec.
        let info = unsafe { &*p_build_info };
        let build = PtlasBuild {
            // SAFETY: the embedded input is valid with the info.
            input: unsafe { lower_input(&info.input) },
            src: info.src_acceleration_structure_data,
            dst: info.dst_acceleration_structure_data,
            scratch: info.scratch_data,
            src_infos: info.src_infos,
            src_infos_count: info.src_infos_count,
        };
        // Rules the parameters alone decide are reported now; the queue skips the build.
        let rejected = rt::record_check(&build).map(|(vuid, message)| crate::diag::vuid(&vuid, CMD, &format!("{message}; build skipped"))).is_some();
        cb.record_custom(Box::new(PtlasCommand { build, rejected }));
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::{align_of, offset_of, size_of};

    // Sizes, alignments and offsets from spec/nv-extensions.md A.4 (gcc offsetof of vk.xml).
    #[test]
    fn layouts_match_the_registry() {
        assert_eq!((size_of::<PhysicalDevicePartitionedAccelerationStructureFeaturesNV>(), align_of::<PhysicalDevicePartitionedAccelerationStructureFeaturesNV>()), (24, 8));
        assert_eq!(offset_of!(PhysicalDevicePartitionedAccelerationStructureFeaturesNV, partitioned_acceleration_structure), 16);
        assert_eq!((size_of::<PhysicalDevicePartitionedAccelerationStructurePropertiesNV>(), align_of::<PhysicalDevicePartitionedAccelerationStructurePropertiesNV>()), (24, 8));
        assert_eq!(offset_of!(PhysicalDevicePartitionedAccelerationStructurePropertiesNV, max_partition_count), 16);
        type In = PartitionedAccelerationStructureInstancesInputNV;
        assert_eq!((size_of::<In>(), align_of::<In>()), (40, 8));
        assert_eq!(
            [offset_of!(In, flags), offset_of!(In, instance_count), offset_of!(In, max_instance_per_partition_count), offset_of!(In, partition_count), offset_of!(In, max_instance_in_global_partition_count)],
            [16, 20, 24, 28, 32]
        );
        assert_eq!((size_of::<PartitionedAccelerationStructureFlagsNV>(), offset_of!(PartitionedAccelerationStructureFlagsNV, enable_partition_translation)), (24, 16));
        type B = BuildPartitionedAccelerationStructureInfoNV;
        assert_eq!((size_of::<B>(), align_of::<B>()), (96, 8));
        assert_eq!(
            [offset_of!(B, input), offset_of!(B, src_acceleration_structure_data), offset_of!(B, dst_acceleration_structure_data), offset_of!(B, scratch_data), offset_of!(B, src_infos), offset_of!(B, src_infos_count)],
            [16, 56, 64, 72, 80, 88]
        );
        type C = BuildPartitionedAccelerationStructureIndirectCommandNV;
        assert_eq!((size_of::<C>(), align_of::<C>(), offset_of!(C, arg_count), offset_of!(C, arg_data)), (24, 8, 4, 8));
        assert_eq!((size_of::<StridedDeviceAddressNV>(), offset_of!(StridedDeviceAddressNV, stride_in_bytes)), (16, 8));
        type W = PartitionedAccelerationStructureWriteInstanceDataNV;
        assert_eq!((size_of::<W>(), align_of::<W>()), (104, 8));
        assert_eq!(
            [
                offset_of!(W, explicit_aabb),
                offset_of!(W, instance_id),
                offset_of!(W, instance_mask),
                offset_of!(W, instance_contribution_to_hit_group_index),
                offset_of!(W, instance_flags),
                offset_of!(W, instance_index),
                offset_of!(W, partition_index),
                offset_of!(W, acceleration_structure)
            ],
            [48, 72, 76, 80, 84, 88, 92, 96]
        );
        type U = PartitionedAccelerationStructureUpdateInstanceDataNV;
        assert_eq!((size_of::<U>(), align_of::<U>(), offset_of!(U, instance_contribution_to_hit_group_index), offset_of!(U, acceleration_structure)), (16, 8, 4, 8));
        type T = PartitionedAccelerationStructureWritePartitionTranslationDataNV;
        assert_eq!((size_of::<T>(), align_of::<T>(), offset_of!(T, partition_translation)), (16, 4, 4));
        type D = WriteDescriptorSetPartitionedAccelerationStructureNV;
        assert_eq!((size_of::<D>(), align_of::<D>(), offset_of!(D, acceleration_structure_count), offset_of!(D, p_acceleration_structures)), (32, 8, 16, 24));
    }

    #[test]
    fn device_record_sizes_agree_with_the_library() {
        use crate::accel::ptlas;
        assert_eq!(size_of::<PartitionedAccelerationStructureWriteInstanceDataNV>(), ptlas::WRITE_INSTANCE_SIZE);
        assert_eq!(size_of::<PartitionedAccelerationStructureUpdateInstanceDataNV>(), ptlas::UPDATE_INSTANCE_SIZE);
        assert_eq!(size_of::<PartitionedAccelerationStructureWritePartitionTranslationDataNV>(), ptlas::WRITE_TRANSLATION_SIZE);
        assert_eq!(size_of::<BuildPartitionedAccelerationStructureIndirectCommandNV>(), ptlas::INDIRECT_COMMAND_SIZE);
    }
}

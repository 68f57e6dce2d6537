//! VK_NV_cluster_acceleration_structure at the API boundary: the host structs ash 0.38 lacks
//! (layouts of nv-extensions.md B.4, tested below), the feature and property structs of the
//! `*2` chains, vkGetClusterAccelerationStructureBuildSizesNV and the recording of
//! vkCmdBuildClusterAccelerationStructureIndirectNV. The argument records read from device
//! memory live in `accel::clas::args`: the recorded command reads them when it executes, below
//! this layer.
#![allow(non_camel_case_types)]
use std::ffi::c_void;
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::handle::{self, dispatchable};
use super::device;
use super::table::{Implemented, VoidFn};
use super::{guard, util};
use crate::accel::clas::args::{ObjectType, OpMode, OpType};
use crate::accel::clas::{self, SizeInput};
use crate::accel::VertexFormat;
use crate::diag;
use crate::runtime::accel::clas::{ClusterCommand, InputBounds, Strided};
use crate::runtime::command::CommandBuffer;

pub const EXTENSION_NAME: &str = "VK_NV_cluster_acceleration_structure";
pub const SPEC_VERSION: u32 = 4;

pub const STYPE_FEATURES: vk::StructureType = vk::StructureType::from_raw(1_000_569_000);
pub const STYPE_PROPERTIES: vk::StructureType = vk::StructureType::from_raw(1_000_569_001);
pub const STYPE_CLUSTERS_BOTTOM_LEVEL_INPUT: vk::StructureType = vk::StructureType::from_raw(1_000_569_002);
pub const STYPE_TRIANGLE_CLUSTER_INPUT: vk::StructureType = vk::StructureType::from_raw(1_000_569_003);
pub const STYPE_MOVE_OBJECTS_INPUT: vk::StructureType = vk::StructureType::from_raw(1_000_569_004);
pub const STYPE_INPUT_INFO: vk::StructureType = vk::StructureType::from_raw(1_000_569_005);
pub const STYPE_COMMANDS_INFO: vk::StructureType = vk::StructureType::from_raw(1_000_569_006);
pub const STYPE_RAY_TRACING_PIPELINE_CREATE_INFO: vk::StructureType = vk::StructureType::from_raw(1_000_569_007);

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct PhysicalDeviceClusterAccelerationStructureFeaturesNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub cluster_acceleration_structure: vk::Bool32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct PhysicalDeviceClusterAccelerationStructurePropertiesNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub max_vertices_per_cluster: u32,
    pub max_triangles_per_cluster: u32,
    pub cluster_scratch_byte_alignment: u32,
    pub cluster_byte_alignment: u32,
    pub cluster_template_byte_alignment: u32,
    pub cluster_bottom_level_byte_alignment: u32,
    pub cluster_template_bounds_byte_alignment: u32,
    pub max_cluster_geometry_index: u32,
}

/// Extends VkRayTracingPipelineCreateInfoKHR. Arbor has no ray-tracing pipelines yet; the struct
/// is defined so its layout is pinned for when they come (traversal needs no opt-in).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct RayTracingPipelineClusterAccelerationStructureCreateInfoNV {
    pub s_type: vk::StructureType,
    pub p_next: *const c_void,
    pub allow_cluster_acceleration_structure: vk::Bool32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct ClusterAccelerationStructureInputInfoNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub max_acceleration_structure_count: u32,
    pub flags: vk::BuildAccelerationStructureFlagsKHR,
    pub op_type: i32,
    pub op_mode: i32,
    /// VkClusterAccelerationStructureOpInputNV: a union of three pointers chosen by opType.
    pub op_input: *mut c_void,
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct ClusterAccelerationStructureClustersBottomLevelInputNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub max_total_cluster_count: u32,
    pub max_cluster_count_per_acceleration_structure: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct ClusterAccelerationStructureTriangleClusterInputNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub vertex_format: vk::Format,
    pub max_geometry_index_value: u32,
    pub max_cluster_unique_geometry_count: u32,
    pub max_cluster_triangle_count: u32,
    pub max_cluster_vertex_count: u32,
    pub max_total_triangle_count: u32,
    pub max_total_vertex_count: u32,
    pub min_position_truncate_bit_count: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct ClusterAccelerationStructureMoveObjectsInputNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub ty: i32,
    pub no_move_overlap: vk::Bool32,
    pub max_moved_bytes: vk::DeviceSize,
}

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct ClusterAccelerationStructureCommandsInfoNV {
    pub s_type: vk::StructureType,
    pub p_next: *mut c_void,
    pub input: ClusterAccelerationStructureInputInfoNV,
    pub dst_implicit_data: vk::DeviceAddress,
    pub scratch_data: vk::DeviceAddress,
    pub dst_addresses_array: vk::StridedDeviceAddressRegionKHR,
    pub dst_sizes_array: vk::StridedDeviceAddressRegionKHR,
    pub src_infos_array: vk::StridedDeviceAddressRegionKHR,
    pub src_infos_count: vk::DeviceAddress,
    pub address_resolution_flags: u32,
}

pub type PFN_vkGetClusterAccelerationStructureBuildSizesNV =
    unsafe extern "system" fn(vk::Device, *const ClusterAccelerationStructureInputInfoNV, *mut vk::AccelerationStructureBuildSizesInfoKHR);
pub type PFN_vkCmdBuildClusterAccelerationStructureIndirectNV = unsafe extern "system" fn(vk::CommandBuffer, *const ClusterAccelerationStructureCommandsInfoNV);

/// `void_fn!` for the PFN types defined here (ash 0.38 has none of them).
macro_rules! local_imp {
    ($pfn:ident => $f:path) => {{
        let f: $pfn = $f;
        // SAFETY: function pointers of any signature have the same size; the loader casts back
        // to the command's PFN type before calling.
        Implemented { pfn: stringify!($pfn), f: unsafe { std::mem::transmute::<$pfn, VoidFn>(f) } }
    }};
}

pub fn commands() -> Vec<Implemented> {
    vec![
        local_imp!(PFN_vkGetClusterAccelerationStructureBuildSizesNV => get_cluster_acceleration_structure_build_sizes_nv),
        local_imp!(PFN_vkCmdBuildClusterAccelerationStructureIndirectNV => cmd_build_cluster_acceleration_structure_indirect_nv),
    ]
}

/// Answers the feature struct in a VkPhysicalDeviceFeatures2 chain.
///
/// # Safety
/// `p` points to a writable VkPhysicalDeviceClusterAccelerationStructureFeaturesNV.
pub unsafe fn write_features(p: *mut c_void) {
    let f = PhysicalDeviceClusterAccelerationStructureFeaturesNV { s_type: STYPE_FEATURES, p_next: std::ptr::null_mut(), cluster_acceleration_structure: vk::TRUE };
    // SAFETY: the caller's promise; write_keep_chain keeps pNext.
    unsafe { util::write_keep_chain(p, f) }
}

/// The limits Arbor reports (README, "Cluster acceleration structures").
pub fn properties() -> PhysicalDeviceClusterAccelerationStructurePropertiesNV {
    PhysicalDeviceClusterAccelerationStructurePropertiesNV {
        s_type: STYPE_PROPERTIES,
        p_next: std::ptr::null_mut(),
        max_vertices_per_cluster: clas::MAX_VERTICES,
        max_triangles_per_cluster: clas::MAX_TRIANGLES,
        cluster_scratch_byte_alignment: clas::SCRATCH_ALIGNMENT as u32,
        cluster_byte_alignment: clas::CLAS_ALIGNMENT as u32,
        cluster_template_byte_alignment: clas::TEMPLATE_ALIGNMENT as u32,
        cluster_bottom_level_byte_alignment: clas::BLAS_ALIGNMENT as u32,
        cluster_template_bounds_byte_alignment: clas::TEMPLATE_BOUNDS_ALIGNMENT as u32,
        max_cluster_geometry_index: clas::MAX_GEOMETRY_INDEX,
    }
}

/// Answers the property struct in a VkPhysicalDeviceProperties2 chain.
///
/// # Safety
/// `p` points to a writable VkPhysicalDeviceClusterAccelerationStructurePropertiesNV.
pub unsafe fn write_properties(p: *mut c_void) {
    // SAFETY: the caller's promise; write_keep_chain keeps pNext.
    unsafe { util::write_keep_chain(p, properties()) }
}

/// The op input's bounds, read through the union member opType selects.
///
/// # Safety
/// `info.op_input` points to the struct its opType names (or is null).
unsafe fn size_input(info: &ClusterAccelerationStructureInputInfoNV) -> Option<SizeInput> {
    let op = OpType::from_vk(info.op_type)?;
    let mode = OpMode::from_vk(info.op_mode)?;
    let mut s = SizeInput {
        op,
        mode,
        max_count: info.max_acceleration_structure_count,
        max_cluster_triangles: 0,
        max_total_triangles: 0,
        max_total_clusters: 0,
        max_clusters_per_blas: 0,
        max_moved_bytes: 0,
        move_type: ObjectType::TriangleCluster,
    };
    if info.op_input.is_null() {
        return None;
    }
    // SAFETY: (each arm) the union member opType names, per the caller's promise.
    unsafe {
        match op {
            OpType::BuildClustersBottomLevel => {
                let b = &*(info.op_input as *const ClusterAccelerationStructureClustersBottomLevelInputNV);
                s.max_total_clusters = b.max_total_cluster_count;
                s.max_clusters_per_blas = b.max_cluster_count_per_acceleration_structure;
            }
            OpType::MoveObjects => {
                let m = &*(info.op_input as *const ClusterAccelerationStructureMoveObjectsInputNV);
                s.max_moved_bytes = m.max_moved_bytes;
                s.move_type = ObjectType::from_vk(m.ty)?;
            }
            _ => {
                let t = &*(info.op_input as *const ClusterAccelerationStructureTriangleClusterInputNV);
                s.max_cluster_triangles = t.max_cluster_triangle_count;
                s.max_total_triangles = t.max_total_triangle_count;
            }
        }
    }
    Some(s)
}

/// The rules of VkClusterAccelerationStructureTriangleClusterInputNV (10439-10442), broken or
/// not; the command checks the same on its copy when it runs.
///
/// # Safety
/// `info.op_input` points to the struct its opType names (or is null).
unsafe fn triangle_input_violation(info: &ClusterAccelerationStructureInputInfoNV) -> Option<(&'static str, String)> {
    let op = OpType::from_vk(info.op_type)?;
    if matches!(op, OpType::MoveObjects | OpType::BuildClustersBottomLevel) || info.op_input.is_null() {
        return None;
    }
    // SAFETY: the union member opType names, per the caller's promise.
    let t = unsafe { &*(info.op_input as *const ClusterAccelerationStructureTriangleClusterInputNV) };
    if VertexFormat::from_vk(t.vertex_format.as_raw()).is_none() {
        return Some((concat!("VUID-VkClusterAccelerationStructureTriangleClusterInputNV-", "vertexFormat-10439"), format!("vertexFormat {:?} lacks ACCELERATION_STRUCTURE_VERTEX_BUFFER", t.vertex_format)));
    }
    if t.max_cluster_triangle_count > clas::MAX_TRIANGLES {
        let m = format!("maxClusterTriangleCount {} exceeds maxTrianglesPerCluster {}", t.max_cluster_triangle_count, clas::MAX_TRIANGLES);
        return Some((concat!("VUID-VkClusterAccelerationStructureTriangleClusterInputNV-", "maxClusterTriangleCount-10440"), m));
    }
    if t.max_cluster_vertex_count > clas::MAX_VERTICES {
        let m = format!("maxClusterVertexCount {} exceeds maxVerticesPerCluster {}", t.max_cluster_vertex_count, clas::MAX_VERTICES);
        return Some((concat!("VUID-VkClusterAccelerationStructureTriangleClusterInputNV-", "maxClusterVertexCount-10441"), m));
    }
    if t.min_position_truncate_bit_count > 32 {
        let m = format!("minPositionTruncateBitCount {} exceeds 32", t.min_position_truncate_bit_count);
        return Some((concat!("VUID-VkClusterAccelerationStructureTriangleClusterInputNV-", "minPositionTruncateBitCount-10442"), m));
    }
    None
}

/// `vkGetClusterAccelerationStructureBuildSizesNV`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer parameters.
unsafe extern "system" fn get_cluster_acceleration_structure_build_sizes_nv(
    device: vk::Device,
    p_info: *const ClusterAccelerationStructureInputInfoNV,
    p_size_info: *mut vk::AccelerationStructureBuildSizesInfoKHR,
) {
    const CMD: &str = "vkGetClusterAccelerationStructureBuildSizesNV";
    guard(CMD, (), || {
        if p_info.is_null() || p_size_info.is_null() {
            return;
        }
        // SAFETY: valid pointers per the spec; the op input matches opType.
        let Some(s) = (unsafe { size_input(&*p_info) }) else {
            diag::vuid("VUID-VkClusterAccelerationStructureInputInfoNV-opType-parameter", CMD, "unknown opType, opMode or move type, or no op input");
            return;
        };
        let vuid = "VUID-vkGetClusterAccelerationStructureBuildSizesNV-clusterAccelerationStructure-10438";
        match device::device_from(device).map(|d| d.features.cluster_acceleration_structure) {
            Some(Some(false)) => diag::vuid(vuid, CMD, "the clusterAccelerationStructure feature is not enabled"),
            Some(None) => crate::runtime::accel::clas::feature_struct_missing(vuid, CMD),
            _ => {}
        }
        // SAFETY: as for size_input.
        if let Some((vuid, message)) = unsafe { triangle_input_violation(&*p_info) } {
            diag::vuid(vuid, CMD, &message);
        }
        let sizes = clas::cluster_build_sizes(&s);
        // SAFETY: a valid output struct; its sType and pNext stay.
        let out = unsafe { &mut *p_size_info };
        out.acceleration_structure_size = sizes.acceleration_structure_size;
        out.build_scratch_size = sizes.build_scratch_size;
        out.update_scratch_size = sizes.update_scratch_size;
    })
}

fn strided(r: &vk::StridedDeviceAddressRegionKHR) -> Strided {
    Strided { address: r.device_address, stride: r.stride, size: r.size }
}

/// Lowers VkClusterAccelerationStructureCommandsInfoNV into an owned command.
///
/// # Safety
/// `info`'s op input points to the struct its opType names (or is null).
unsafe fn lower(info: &ClusterAccelerationStructureCommandsInfoNV) -> Result<ClusterCommand, &'static str> {
    let input = &info.input;
    let op = OpType::from_vk(input.op_type).ok_or("opType")?;
    let mode = OpMode::from_vk(input.op_mode).ok_or("opMode")?;
    let (mut vertex_format, mut move_type) = (None, ObjectType::TriangleCluster);
    let mut bounds = InputBounds::default();
    if input.op_input.is_null() {
        return Err("opInput");
    }
    // SAFETY: the union member opType names, per the caller's promise.
    unsafe {
        match op {
            OpType::MoveObjects => {
                let m = &*(input.op_input as *const ClusterAccelerationStructureMoveObjectsInputNV);
                move_type = ObjectType::from_vk(m.ty).ok_or("move type")?;
                bounds.max_moved_bytes = m.max_moved_bytes;
            }
            OpType::BuildClustersBottomLevel => {
                let b = &*(input.op_input as *const ClusterAccelerationStructureClustersBottomLevelInputNV);
                bounds.max_total_clusters = b.max_total_cluster_count;
                bounds.max_clusters_per_blas = b.max_cluster_count_per_acceleration_structure;
            }
            _ => {
                let t = &*(input.op_input as *const ClusterAccelerationStructureTriangleClusterInputNV);
                vertex_format = VertexFormat::from_vk(t.vertex_format.as_raw());
                bounds.vertex_format = t.vertex_format.as_raw();
                bounds.max_cluster_triangles = t.max_cluster_triangle_count;
                bounds.max_cluster_vertices = t.max_cluster_vertex_count;
                bounds.max_total_triangles = t.max_total_triangle_count;
                bounds.max_total_vertices = t.max_total_vertex_count;
                bounds.min_truncate_bits = t.min_position_truncate_bit_count;
            }
        }
    }
    Ok(ClusterCommand {
        op,
        mode,
        max_count: input.max_acceleration_structure_count,
        build_flags: input.flags.as_raw(),
        vertex_format,
        move_type,
        dst_implicit_data: info.dst_implicit_data,
        scratch_data: info.scratch_data,
        dst_addresses: strided(&info.dst_addresses_array),
        dst_sizes: strided(&info.dst_sizes_array),
        src_infos: strided(&info.src_infos_array),
        src_infos_count: info.src_infos_count,
        address_resolution: info.address_resolution_flags,
        bounds,
        // SAFETY: the same op input, per the caller's promise.
        queried_size: unsafe { size_input(input) }.map_or(0, |s| clas::cluster_build_sizes(&s).acceleration_structure_size),
    })
}

fn command_buffer_from(h: vk::CommandBuffer) -> Option<Arc<CommandBuffer>> {
    // SAFETY: a non-null VkCommandBuffer is a live handle we created (application obligation).
    unsafe { dispatchable::<CommandBuffer>(h.as_raw() as *mut handle::Dispatchable<CommandBuffer>) }
}

/// `vkCmdBuildClusterAccelerationStructureIndirectNV`: records the command; counts, argument
/// records and destination addresses are read from device memory when it executes.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters.
unsafe extern "system" fn cmd_build_cluster_acceleration_structure_indirect_nv(
    command_buffer: vk::CommandBuffer,
    p_command_infos: *const ClusterAccelerationStructureCommandsInfoNV,
) {
    const CMD: &str = "vkCmdBuildClusterAccelerationStructureIndirectNV";
    guard(CMD, (), || {
        let Some(cb) = command_buffer_from(command_buffer) else { return };
        if p_command_infos.is_null() {
            return;
        }
        // SAFETY: a valid struct per the spec, its op input matching opType.
        match unsafe { lower(&*p_command_infos) } {
            Ok(cmd) => cb.record_custom(Box::new(cmd)),
            Err(what) => diag::vuid("VUID-vkCmdBuildClusterAccelerationStructureIndirectNV-pCommandInfos-parameter", CMD, &format!("invalid {what}")),
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::{align_of, offset_of, size_of};

    #[test]
    fn host_struct_layouts_match_the_registry() {
        // nv-extensions.md B.4 (gcc offsetof on x86-64).
        assert_eq!((size_of::<PhysicalDeviceClusterAccelerationStructureFeaturesNV>(), align_of::<PhysicalDeviceClusterAccelerationStructureFeaturesNV>()), (24, 8));
        assert_eq!(size_of::<PhysicalDeviceClusterAccelerationStructurePropertiesNV>(), 48);
        assert_eq!(offset_of!(PhysicalDeviceClusterAccelerationStructurePropertiesNV, max_cluster_geometry_index), 44);
        assert_eq!(size_of::<RayTracingPipelineClusterAccelerationStructureCreateInfoNV>(), 24);
        assert_eq!(size_of::<ClusterAccelerationStructureInputInfoNV>(), 40);
        assert_eq!(offset_of!(ClusterAccelerationStructureInputInfoNV, op_input), 32);
        assert_eq!(size_of::<ClusterAccelerationStructureClustersBottomLevelInputNV>(), 24);
        assert_eq!(size_of::<ClusterAccelerationStructureTriangleClusterInputNV>(), 48);
        assert_eq!(offset_of!(ClusterAccelerationStructureTriangleClusterInputNV, min_position_truncate_bit_count), 44);
        assert_eq!(size_of::<ClusterAccelerationStructureMoveObjectsInputNV>(), 32);
        assert_eq!(offset_of!(ClusterAccelerationStructureMoveObjectsInputNV, max_moved_bytes), 24);
        assert_eq!(size_of::<ClusterAccelerationStructureCommandsInfoNV>(), 160);
        let o = [
            offset_of!(ClusterAccelerationStructureCommandsInfoNV, input),
            offset_of!(ClusterAccelerationStructureCommandsInfoNV, dst_implicit_data),
            offset_of!(ClusterAccelerationStructureCommandsInfoNV, scratch_data),
            offset_of!(ClusterAccelerationStructureCommandsInfoNV, dst_addresses_array),
            offset_of!(ClusterAccelerationStructureCommandsInfoNV, dst_sizes_array),
            offset_of!(ClusterAccelerationStructureCommandsInfoNV, src_infos_array),
            offset_of!(ClusterAccelerationStructureCommandsInfoNV, src_infos_count),
            offset_of!(ClusterAccelerationStructureCommandsInfoNV, address_resolution_flags),
        ];
        assert_eq!(o, [16, 56, 64, 72, 96, 120, 144, 152]);
    }

    #[test]
    fn reported_limits_meet_the_spec() {
        let p = properties();
        assert!(p.max_vertices_per_cluster >= 256 && p.max_triangles_per_cluster >= 256);
        assert!(p.cluster_scratch_byte_alignment <= 256 && p.cluster_byte_alignment <= 128);
        assert!(p.cluster_template_byte_alignment <= 32 && p.cluster_bottom_level_byte_alignment <= 256);
        assert!(p.cluster_template_bounds_byte_alignment <= 32 && p.max_cluster_geometry_index >= (1 << 24) - 1);
    }
}

//! VK_NV_cluster_acceleration_structure for API tests: its host structs (written from the
//! registry, not imported from the driver; ash 0.38 lacks them), the two commands resolved
//! through the loader, and builders for the structs with every field at a valid default.
use std::ffi::c_void;

use arbor::accel::clas::args::{OpMode, OpType};
use ash::vk;

pub const EXT: &str = "VK_NV_cluster_acceleration_structure";
pub const CMD: &str = "vkCmdBuildClusterAccelerationStructureIndirectNV";

#[repr(C)]
#[derive(Clone, Copy)]
pub struct InputInfo {
    pub s_type: i32,
    pub p_next: *mut c_void,
    pub max_acceleration_structure_count: u32,
    pub flags: u32,
    pub op_type: i32,
    pub op_mode: i32,
    pub op_input: *const c_void,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct TriangleInput {
    pub s_type: i32,
    pub p_next: *mut c_void,
    pub vertex_format: i32,
    pub max_geometry_index_value: u32,
    pub max_cluster_unique_geometry_count: u32,
    pub max_cluster_triangle_count: u32,
    pub max_cluster_vertex_count: u32,
    pub max_total_triangle_count: u32,
    pub max_total_vertex_count: u32,
    pub min_position_truncate_bit_count: u32,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct BottomLevelInput {
    pub s_type: i32,
    pub p_next: *mut c_void,
    pub max_total_cluster_count: u32,
    pub max_cluster_count_per_acceleration_structure: u32,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct MoveInput {
    pub s_type: i32,
    pub p_next: *mut c_void,
    pub ty: i32,
    pub no_move_overlap: u32,
    pub max_moved_bytes: u64,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct CommandsInfo {
    pub s_type: i32,
    pub p_next: *mut c_void,
    pub input: InputInfo,
    pub dst_implicit_data: u64,
    pub scratch_data: u64,
    pub dst_addresses_array: vk::StridedDeviceAddressRegionKHR,
    pub dst_sizes_array: vk::StridedDeviceAddressRegionKHR,
    pub src_infos_array: vk::StridedDeviceAddressRegionKHR,
    pub src_infos_count: u64,
    pub address_resolution_flags: u32,
}

pub type GetSizes = unsafe extern "system" fn(vk::Device, *const InputInfo, *mut vk::AccelerationStructureBuildSizesInfoKHR);
pub type CmdBuild = unsafe extern "system" fn(vk::CommandBuffer, *const CommandsInfo);

pub struct Nv {
    pub get_sizes: GetSizes,
    pub cmd_build: CmdBuild,
}

pub fn nv(ctx: &super::Context) -> Nv {
    let f = |name: &std::ffi::CStr| {
        // SAFETY: a device-level command name.
        unsafe { ctx.instance.get_device_proc_addr(ctx.device.handle(), name.as_ptr()) }.expect("the command resolves when the extension is enabled")
    };
    // SAFETY: the PFN types of these commands (vk.xml).
    unsafe {
        Nv {
            get_sizes: std::mem::transmute::<unsafe extern "system" fn(), GetSizes>(f(c"vkGetClusterAccelerationStructureBuildSizesNV")),
            cmd_build: std::mem::transmute::<unsafe extern "system" fn(), CmdBuild>(f(c"vkCmdBuildClusterAccelerationStructureIndirectNV")),
        }
    }
}

impl Nv {
    pub fn sizes(&self, ctx: &super::Context, input: &InputInfo) -> vk::AccelerationStructureBuildSizesInfoKHR<'static> {
        let mut s = vk::AccelerationStructureBuildSizesInfoKHR::default();
        // SAFETY: valid structs.
        unsafe { (self.get_sizes)(ctx.device.handle(), input, &mut s) };
        s
    }
}

pub fn region(address: u64, stride: u64, size: u64) -> vk::StridedDeviceAddressRegionKHR {
    vk::StridedDeviceAddressRegionKHR { device_address: address, stride, size }
}

pub fn input(op: OpType, mode: OpMode, count: u32, op_input: *const c_void) -> InputInfo {
    InputInfo { s_type: 1_000_569_005, p_next: std::ptr::null_mut(), max_acceleration_structure_count: count, flags: 0, op_type: op as i32, op_mode: mode as i32, op_input }
}

pub fn commands(input: InputInfo) -> CommandsInfo {
    CommandsInfo {
        s_type: 1_000_569_006,
        p_next: std::ptr::null_mut(),
        input,
        dst_implicit_data: 0,
        scratch_data: 0,
        dst_addresses_array: region(0, 0, 0),
        dst_sizes_array: region(0, 0, 0),
        src_infos_array: region(0, 0, 0),
        src_infos_count: 0,
        address_resolution_flags: 0,
    }
}

/// R32G32B32_SFLOAT clusters of up to `triangles` triangles and vertices, `total` in all.
pub fn triangle_input(triangles: u32, total: u32, min_truncate: u32) -> TriangleInput {
    TriangleInput {
        s_type: 1_000_569_003,
        p_next: std::ptr::null_mut(),
        vertex_format: vk::Format::R32G32B32_SFLOAT.as_raw(),
        max_geometry_index_value: 1 << 20,
        max_cluster_unique_geometry_count: triangles,
        max_cluster_triangle_count: triangles,
        max_cluster_vertex_count: triangles,
        max_total_triangle_count: total,
        max_total_vertex_count: total,
        min_position_truncate_bit_count: min_truncate,
    }
}

pub fn bottom_level_input(total: u32, per_blas: u32) -> BottomLevelInput {
    BottomLevelInput { s_type: 1_000_569_002, p_next: std::ptr::null_mut(), max_total_cluster_count: total, max_cluster_count_per_acceleration_structure: per_blas }
}

pub fn move_input(ty: i32, max_moved_bytes: u64) -> MoveInput {
    MoveInput { s_type: 1_000_569_004, p_next: std::ptr::null_mut(), ty, no_move_overlap: 0, max_moved_bytes }
}

pub fn bytes_of<T: bytemuck::Pod>(v: &[T]) -> Vec<u8> {
    bytemuck::cast_slice(v).to_vec()
}

/// Little-endian values read back from bytes.
pub fn collect<T: bytemuck::Pod>(bytes: &[u8]) -> Vec<T> {
    bytes.chunks_exact(std::mem::size_of::<T>()).map(bytemuck::pod_read_unaligned).collect()
}

/// A small cluster: an n × n grid of quads (2 n² triangles, (n + 1)² vertices) over
/// [x0, x0 + 1] × [0, 1] at height z, as R32G32B32_SFLOAT vertices and 16-bit indices.
pub fn grid_cluster(n: u32, x0: f32, z: f32) -> (Vec<[f32; 3]>, Vec<u16>) {
    let mut v = Vec::new();
    for y in 0..=n {
        for x in 0..=n {
            v.push([x0 + x as f32 / n as f32, y as f32 / n as f32, z]);
        }
    }
    let mut i = Vec::new();
    for y in 0..n {
        for x in 0..n {
            let k = (y * (n + 1) + x) as u16;
            let w = (n + 1) as u16;
            i.extend([k, k + 1, k + w, k + 1, k + w + 1, k + w]);
        }
    }
    (v, i)
}

//! VK_KHR_acceleration_structure (with its host commands, which may defer) and the query types of
//! VK_KHR_ray_tracing_maintenance1: entry points. Raw pointers are lowered here into owned
//! descriptions (`runtime::accel::BuildInfo`, `Copy`) that commands keep until they execute;
//! host addresses of host commands are vouched for here (`memory::region::HostMemory`).
//!
//! Nothing here executes a command or decides where it runs: that is `runtime::accel`'s.
use std::ffi::c_void;
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::device::device_from;
use super::handle::{self, dispatchable};
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::accel;
use crate::diag;
use crate::memory::region::HostMemory;
use crate::memory::Buffer;
use crate::runtime::accel::command::Deferral;
use crate::runtime::accel::{
    self as rt, AccelerationStructure, BuildCommand, BuildInfo, BuildKind, CopyCommand, GeometryDesc, GeometryInfo, RangeInfo, Ranges,
    WritePropertiesCommand,
};
use crate::runtime::command::CommandBuffer;
use crate::runtime::deferred::DeferredOperation;
use crate::runtime::in_use;
use crate::runtime::query::QueryPool;

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCreateAccelerationStructureKHR => create_acceleration_structure_khr),
        imp!(PFN_vkDestroyAccelerationStructureKHR => destroy_acceleration_structure_khr),
        imp!(PFN_vkGetAccelerationStructureDeviceAddressKHR => get_acceleration_structure_device_address_khr),
        imp!(PFN_vkGetAccelerationStructureBuildSizesKHR => get_acceleration_structure_build_sizes_khr),
        imp!(PFN_vkGetDeviceAccelerationStructureCompatibilityKHR => get_device_acceleration_structure_compatibility_khr),
        imp!(PFN_vkCmdBuildAccelerationStructuresKHR => cmd_build_acceleration_structures_khr),
        imp!(PFN_vkCmdBuildAccelerationStructuresIndirectKHR => cmd_build_acceleration_structures_indirect_khr),
        imp!(PFN_vkBuildAccelerationStructuresKHR => build_acceleration_structures_khr),
        imp!(PFN_vkCmdCopyAccelerationStructureKHR => cmd_copy_acceleration_structure_khr),
        imp!(PFN_vkCopyAccelerationStructureKHR => copy_acceleration_structure_khr),
        imp!(PFN_vkCmdCopyAccelerationStructureToMemoryKHR => cmd_copy_acceleration_structure_to_memory_khr),
        imp!(PFN_vkCopyAccelerationStructureToMemoryKHR => copy_acceleration_structure_to_memory_khr),
        imp!(PFN_vkCmdCopyMemoryToAccelerationStructureKHR => cmd_copy_memory_to_acceleration_structure_khr),
        imp!(PFN_vkCopyMemoryToAccelerationStructureKHR => copy_memory_to_acceleration_structure_khr),
        imp!(PFN_vkCmdWriteAccelerationStructuresPropertiesKHR => cmd_write_acceleration_structures_properties_khr),
        imp!(PFN_vkWriteAccelerationStructuresPropertiesKHR => write_acceleration_structures_properties_khr),
    ]
}

pub fn structure_from(h: vk::AccelerationStructureKHR) -> Option<Arc<AccelerationStructure>> {
    handle::get::<AccelerationStructure>(h.as_raw())
}

/// The structure a handle value names (what host builds' instances reference).
fn structure_from_raw(handle: u64) -> Option<Arc<AccelerationStructure>> {
    handle::get::<AccelerationStructure>(handle)
}

/// A host command's `deferredOperation` argument.
fn deferral_from(op: vk::DeferredOperationKHR) -> Deferral {
    if op == vk::DeferredOperationKHR::null() {
        return Deferral::Now;
    }
    handle::get::<DeferredOperation>(op.as_raw()).map_or(Deferral::Unknown, Deferral::On)
}

/// Vouches for the host addresses of a host command.
fn host_memory() -> HostMemory {
    // SAFETY: host addresses given to a host command are valid for the lengths the spec
    // derives from its parameters, and untouched by the application, until the command (or its
    // deferred operation) completes (VUID-vkBuildAccelerationStructuresKHR-pInfos-03725 and the
    // other host-address rules): the application's obligation. The runtime drops the value
    // when the command completes.
    unsafe { HostMemory::new() }
}

fn command_buffer_from(h: vk::CommandBuffer) -> Option<Arc<CommandBuffer>> {
    // SAFETY: a non-null VkCommandBuffer is a live handle we created (application obligation).
    unsafe { dispatchable::<CommandBuffer>(h.as_raw() as *mut handle::Dispatchable<CommandBuffer>) }
}

// ---------------------------------------------------------------------------------------------
// Objects

/// `vkCreateAccelerationStructureKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn create_acceleration_structure_khr(
    device: vk::Device,
    p_info: *const vk::AccelerationStructureCreateInfoKHR,
    _p_allocator: *const vk::AllocationCallbacks,
    p_as: *mut vk::AccelerationStructureKHR,
) -> vk::Result {
    const CMD: &str = "vkCreateAccelerationStructureKHR";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_INITIALIZATION_FAILED };
        if p_info.is_null() || p_as.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid create info per the spec.
        let info = unsafe { &*p_info };
        let lowered = rt::CreateInfo {
            buffer: handle::get::<Buffer>(info.buffer.as_raw()),
            offset: info.offset,
            size: info.size,
            ty: info.ty,
            create_flags: info.create_flags,
            device_address: info.device_address,
        };
        let s = match AccelerationStructure::create(&dev, lowered) {
            Ok(s) => s,
            Err(e) => return e,
        };
        // SAFETY: checked non-null.
        unsafe { *p_as = vk::AccelerationStructureKHR::from_raw(handle::register(Arc::new(s))) };
        vk::Result::SUCCESS
    })
}

/// `vkDestroyAccelerationStructureKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn destroy_acceleration_structure_khr(
    device: vk::Device,
    h: vk::AccelerationStructureKHR,
    _p_allocator: *const vk::AllocationCallbacks,
) {
    const CMD: &str = "vkDestroyAccelerationStructureKHR";
    guard(CMD, (), || {
        if h == vk::AccelerationStructureKHR::null() {
            return;
        }
        match handle::unregister::<AccelerationStructure>(h.as_raw()) {
            None => diag::vuid("VUID-vkDestroyAccelerationStructureKHR-accelerationStructure-parameter", CMD, "not a valid acceleration structure"),
            Some(s) => in_use::check_destroy(
                device_from(device).as_deref(),
                &*s,
                CMD,
                "VUID-vkDestroyAccelerationStructureKHR-accelerationStructure-02442",
                &format!("acceleration structure {:#x}", h.as_raw()),
                "the pending commands keep the structure's view and finish",
            ),
        }
    })
}

/// `vkGetAccelerationStructureDeviceAddressKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn get_acceleration_structure_device_address_khr(
    _device: vk::Device,
    p_info: *const vk::AccelerationStructureDeviceAddressInfoKHR,
) -> vk::DeviceAddress {
    guard("vkGetAccelerationStructureDeviceAddressKHR", 0, || {
        if p_info.is_null() {
            return 0;
        }
        // SAFETY: valid info per the spec.
        let info = unsafe { &*p_info };
        match structure_from(info.acceleration_structure).and_then(|s| s.address()) {
            Some(a) => a,
            None => {
                diag::vuid(
                    "VUID-vkGetAccelerationStructureDeviceAddressKHR-pInfo-09541",
                    "vkGetAccelerationStructureDeviceAddressKHR",
                    "the structure is invalid or its buffer is not bound to memory",
                );
                0
            }
        }
    })
}

/// Lower one `VkAccelerationStructureGeometryKHR`.
///
/// # Safety
/// `g` is a valid geometry struct.
unsafe fn lower_geometry(g: &vk::AccelerationStructureGeometryKHR) -> GeometryInfo {
    // SAFETY: the union member read is the one geometryType names.
    let desc = unsafe {
        match g.geometry_type {
            vk::GeometryTypeKHR::TRIANGLES => {
                let t = &g.geometry.triangles;
                GeometryDesc::Triangles {
                    vertex_format: t.vertex_format,
                    vertex_data: t.vertex_data.device_address,
                    vertex_stride: t.vertex_stride,
                    max_vertex: t.max_vertex,
                    index_type: t.index_type,
                    index_data: t.index_data.device_address,
                    transform_data: t.transform_data.device_address,
                }
            }
            vk::GeometryTypeKHR::AABBS => {
                let a = &g.geometry.aabbs;
                GeometryDesc::Aabbs { data: a.data.device_address, stride: a.stride }
            }
            vk::GeometryTypeKHR::INSTANCES => {
                let i = &g.geometry.instances;
                GeometryDesc::Instances { array_of_pointers: i.array_of_pointers != 0, data: i.data.device_address }
            }
            other => GeometryDesc::Unsupported(other),
        }
    };
    GeometryInfo { desc, flags: g.flags }
}

/// The geometries of a build info (pGeometries or ppGeometries).
///
/// # Safety
/// `info` is a valid build-geometry info.
unsafe fn lower_geometries(info: &vk::AccelerationStructureBuildGeometryInfoKHR) -> Vec<GeometryInfo> {
    let n = info.geometry_count as usize;
    // SAFETY: exactly one of the arrays is valid for geometryCount elements (spec).
    unsafe {
        if !info.p_geometries.is_null() {
            (0..n).map(|j| lower_geometry(&*info.p_geometries.add(j))).collect()
        } else if !info.pp_geometries.is_null() {
            (0..n).map(|j| lower_geometry(&**info.pp_geometries.add(j))).collect()
        } else {
            Vec::new()
        }
    }
}

/// # Safety
/// `info` is a valid build-geometry info.
unsafe fn lower_info(info: &vk::AccelerationStructureBuildGeometryInfoKHR, ranges: Ranges) -> BuildInfo {
    BuildInfo {
        ty: info.ty,
        flags: info.flags,
        mode: info.mode,
        src: structure_from(info.src_acceleration_structure),
        src_handle: info.src_acceleration_structure.as_raw(),
        dst: structure_from(info.dst_acceleration_structure),
        dst_handle: info.dst_acceleration_structure.as_raw(),
        // SAFETY: valid info; the union is read as an address (device) or pointer value (host).
        scratch: unsafe { info.scratch_data.device_address },
        geometry_count: info.geometry_count,
        // SAFETY: valid info.
        geometries: unsafe { lower_geometries(info) },
        ranges,
    }
}

/// `vkGetAccelerationStructureBuildSizesKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn get_acceleration_structure_build_sizes_khr(
    _device: vk::Device,
    build_type: vk::AccelerationStructureBuildTypeKHR,
    p_build_info: *const vk::AccelerationStructureBuildGeometryInfoKHR,
    p_max_primitive_counts: *const u32,
    p_size_info: *mut vk::AccelerationStructureBuildSizesInfoKHR,
) {
    const CMD: &str = "vkGetAccelerationStructureBuildSizesKHR";
    guard(CMD, (), || {
        if p_build_info.is_null() || p_size_info.is_null() {
            return;
        }
        // SAFETY: valid info per the spec.
        let info = unsafe { &*p_build_info };
        // SAFETY: valid info.
        let geometries = unsafe { lower_geometries(info) };
        if info.geometry_count > 0 && p_max_primitive_counts.is_null() {
            diag::vuid("VUID-vkGetAccelerationStructureBuildSizesKHR-pBuildInfo-03619", CMD, "pMaxPrimitiveCounts is NULL");
            return;
        }
        // SAFETY: geometryCount elements per the spec.
        let counts = unsafe { util::slice(p_max_primitive_counts, info.geometry_count) };
        let _ = build_type; // host and device builds use the same format and sizes
        match rt::build_sizes(info.ty, info.flags, &geometries, counts) {
            Some(s) => {
                // SAFETY: valid output struct; sType/pNext kept.
                unsafe {
                    (*p_size_info).acceleration_structure_size = s.acceleration_structure_size;
                    (*p_size_info).build_scratch_size = s.build_scratch_size;
                    (*p_size_info).update_scratch_size = s.update_scratch_size;
                }
            }
            None => diag::vuid(
                "VUID-vkGetAccelerationStructureBuildSizesKHR-pBuildInfo-parameter",
                CMD,
                "type, geometry type, vertex format or index type not supported",
            ),
        }
    })
}

/// `vkGetDeviceAccelerationStructureCompatibilityKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn get_device_acceleration_structure_compatibility_khr(
    _device: vk::Device,
    p_version: *const vk::AccelerationStructureVersionInfoKHR,
    p_compat: *mut vk::AccelerationStructureCompatibilityKHR,
) {
    guard("vkGetDeviceAccelerationStructureCompatibilityKHR", (), || {
        if p_version.is_null() || p_compat.is_null() {
            return;
        }
        // SAFETY: pVersionData points to 2*VK_UUID_SIZE bytes (spec).
        let data: &[u8; 32] = unsafe { &*(*p_version).p_version_data };
        let ok = accel::compatible(data, crate::DRIVER_UUID);
        // SAFETY: valid output pointer.
        unsafe {
            *p_compat = if ok {
                vk::AccelerationStructureCompatibilityKHR::COMPATIBLE
            } else {
                vk::AccelerationStructureCompatibilityKHR::INCOMPATIBLE
            }
        };
    })
}

// ---------------------------------------------------------------------------------------------
// Builds

/// `vkCmdBuildAccelerationStructuresKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn cmd_build_acceleration_structures_khr(
    command_buffer: vk::CommandBuffer,
    info_count: u32,
    p_infos: *const vk::AccelerationStructureBuildGeometryInfoKHR,
    pp_ranges: *const *const vk::AccelerationStructureBuildRangeInfoKHR,
) {
    const CMD: &str = "vkCmdBuildAccelerationStructuresKHR";
    guard(CMD, (), || {
        let Some(cb) = command_buffer_from(command_buffer) else { return };
        // SAFETY: the command's pInfos and ppBuildRangeInfos (spec).
        let out = unsafe { lower_direct(p_infos, info_count, pp_ranges) };
        cb.record_custom(Box::new(BuildCommand { kind: BuildKind::Direct, infos: out }));
    })
}

/// The build infos of a direct or host build with their range records.
///
/// # Safety
/// `p_infos` holds `info_count` valid build-geometry infos, and `pp_ranges` (when not null) as
/// many pointers to `geometryCount` range records each.
unsafe fn lower_direct(
    p_infos: *const vk::AccelerationStructureBuildGeometryInfoKHR,
    info_count: u32,
    pp_ranges: *const *const vk::AccelerationStructureBuildRangeInfoKHR,
) -> Vec<BuildInfo> {
    // SAFETY: infoCount elements (this function's contract).
    let infos = unsafe { util::slice(p_infos, info_count) };
    let mut out = Vec::with_capacity(infos.len());
    for (i, info) in infos.iter().enumerate() {
        // SAFETY: ppBuildRangeInfos[i] points to geometryCount records (this function's contract).
        let ranges = unsafe {
            let p = if pp_ranges.is_null() { std::ptr::null() } else { *pp_ranges.add(i) };
            util::slice(p, info.geometry_count).iter().map(range_from_vk).collect()
        };
        // SAFETY: a valid info (this function's contract).
        out.push(unsafe { lower_info(info, Ranges::Direct(ranges)) });
    }
    out
}

fn range_from_vk(r: &vk::AccelerationStructureBuildRangeInfoKHR) -> RangeInfo {
    RangeInfo {
        primitive_count: r.primitive_count,
        primitive_offset: r.primitive_offset,
        first_vertex: r.first_vertex,
        transform_offset: r.transform_offset,
    }
}

/// `vkCmdBuildAccelerationStructuresIndirectKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn cmd_build_acceleration_structures_indirect_khr(
    command_buffer: vk::CommandBuffer,
    info_count: u32,
    p_infos: *const vk::AccelerationStructureBuildGeometryInfoKHR,
    p_addresses: *const vk::DeviceAddress,
    p_strides: *const u32,
    pp_max_counts: *const *const u32,
) {
    const CMD: &str = "vkCmdBuildAccelerationStructuresIndirectKHR";
    guard(CMD, (), || {
        let Some(cb) = command_buffer_from(command_buffer) else { return };
        // SAFETY: infoCount elements each (spec).
        let (infos, addrs, strides) = unsafe {
            (util::slice(p_infos, info_count), util::slice(p_addresses, info_count), util::slice(p_strides, info_count))
        };
        if addrs.len() != infos.len() || strides.len() != infos.len() || pp_max_counts.is_null() {
            diag::vuid("VUID-vkCmdBuildAccelerationStructuresIndirectKHR-pIndirectDeviceAddresses-parameter", CMD, "missing arrays");
            return;
        }
        let mut out = Vec::with_capacity(infos.len());
        for (i, info) in infos.iter().enumerate() {
            // SAFETY: ppMaxPrimitiveCounts[i] points to geometryCount values (spec).
            let max = unsafe { util::slice(*pp_max_counts.add(i), info.geometry_count).to_vec() };
            let ranges = Ranges::Indirect { address: addrs[i], stride: strides[i], max_primitive_counts: max };
            // SAFETY: valid info.
            out.push(unsafe { lower_info(info, ranges) });
        }
        cb.record_custom(Box::new(BuildCommand { kind: BuildKind::Indirect, infos: out }));
    })
}

/// `vkBuildAccelerationStructuresKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn build_acceleration_structures_khr(
    device: vk::Device,
    deferred: vk::DeferredOperationKHR,
    info_count: u32,
    p_infos: *const vk::AccelerationStructureBuildGeometryInfoKHR,
    pp_ranges: *const *const vk::AccelerationStructureBuildRangeInfoKHR,
) -> vk::Result {
    const CMD: &str = "vkBuildAccelerationStructuresKHR";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_INITIALIZATION_FAILED };
        // SAFETY: the command's pInfos and ppBuildRangeInfos (spec).
        let out = unsafe { lower_direct(p_infos, info_count, pp_ranges) };
        rt::command::build_on_host(&dev, deferral_from(deferred), host_memory(), structure_from_raw, out)
    })
}

// ---------------------------------------------------------------------------------------------
// Copies

/// `vkCmdCopyAccelerationStructureKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn cmd_copy_acceleration_structure_khr(command_buffer: vk::CommandBuffer, p_info: *const vk::CopyAccelerationStructureInfoKHR) {
    const CMD: &str = "vkCmdCopyAccelerationStructureKHR";
    guard(CMD, (), || {
        let Some(cb) = command_buffer_from(command_buffer) else { return };
        if p_info.is_null() {
            return;
        }
        // SAFETY: valid info (spec).
        let i = unsafe { &*p_info };
        let op = rt::Copy::Structure { src: structure_from(i.src), dst: structure_from(i.dst), mode: i.mode };
        cb.record_custom(Box::new(CopyCommand { op }));
    })
}

/// `vkCmdCopyAccelerationStructureToMemoryKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn cmd_copy_acceleration_structure_to_memory_khr(
    command_buffer: vk::CommandBuffer,
    p_info: *const vk::CopyAccelerationStructureToMemoryInfoKHR,
) {
    const CMD: &str = "vkCmdCopyAccelerationStructureToMemoryKHR";
    guard(CMD, (), || {
        let Some(cb) = command_buffer_from(command_buffer) else { return };
        if p_info.is_null() {
            return;
        }
        // SAFETY: valid info (spec); the union is read as a device address.
        let (src, dst_address, mode) = unsafe { ((*p_info).src, (*p_info).dst.device_address, (*p_info).mode) };
        let op = rt::Copy::ToMemory { src: structure_from(src), dst: dst_address, mode };
        cb.record_custom(Box::new(CopyCommand { op }));
    })
}

/// `vkCmdCopyMemoryToAccelerationStructureKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn cmd_copy_memory_to_acceleration_structure_khr(
    command_buffer: vk::CommandBuffer,
    p_info: *const vk::CopyMemoryToAccelerationStructureInfoKHR,
) {
    const CMD: &str = "vkCmdCopyMemoryToAccelerationStructureKHR";
    guard(CMD, (), || {
        let Some(cb) = command_buffer_from(command_buffer) else { return };
        if p_info.is_null() {
            return;
        }
        // SAFETY: valid info (spec); the union is read as a device address.
        let (src_address, dst, mode) = unsafe { ((*p_info).src.device_address, (*p_info).dst, (*p_info).mode) };
        let op = rt::Copy::FromMemory { src: src_address, dst: structure_from(dst), mode };
        cb.record_custom(Box::new(CopyCommand { op }));
    })
}

fn host_copy(device: vk::Device, deferred: vk::DeferredOperationKHR, op: rt::Copy) -> vk::Result {
    let Some(dev) = device_from(device) else { return vk::Result::ERROR_INITIALIZATION_FAILED };
    rt::command::copy_on_host(&dev, deferral_from(deferred), host_memory(), structure_from_raw, op)
}

/// `vkCopyAccelerationStructureKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn copy_acceleration_structure_khr(
    device: vk::Device,
    deferred: vk::DeferredOperationKHR,
    p_info: *const vk::CopyAccelerationStructureInfoKHR,
) -> vk::Result {
    const CMD: &str = "vkCopyAccelerationStructureKHR";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if p_info.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid info (spec).
        let i = unsafe { &*p_info };
        host_copy(device, deferred, rt::Copy::Structure { src: structure_from(i.src), dst: structure_from(i.dst), mode: i.mode })
    })
}

/// `vkCopyAccelerationStructureToMemoryKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn copy_acceleration_structure_to_memory_khr(
    device: vk::Device,
    deferred: vk::DeferredOperationKHR,
    p_info: *const vk::CopyAccelerationStructureToMemoryInfoKHR,
) -> vk::Result {
    const CMD: &str = "vkCopyAccelerationStructureToMemoryKHR";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if p_info.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid info (spec); the union is read as a host pointer value.
        let (src, dst, mode) = unsafe { ((*p_info).src, (*p_info).dst.host_address as u64, (*p_info).mode) };
        host_copy(device, deferred, rt::Copy::ToMemory { src: structure_from(src), dst, mode })
    })
}

/// `vkCopyMemoryToAccelerationStructureKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn copy_memory_to_acceleration_structure_khr(
    device: vk::Device,
    deferred: vk::DeferredOperationKHR,
    p_info: *const vk::CopyMemoryToAccelerationStructureInfoKHR,
) -> vk::Result {
    const CMD: &str = "vkCopyMemoryToAccelerationStructureKHR";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if p_info.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid info (spec); the union is read as a host pointer value.
        let (src, dst, mode) = unsafe { ((*p_info).src.host_address as u64, (*p_info).dst, (*p_info).mode) };
        host_copy(device, deferred, rt::Copy::FromMemory { src, dst: structure_from(dst), mode })
    })
}

// ---------------------------------------------------------------------------------------------
// Properties

/// `vkCmdWriteAccelerationStructuresPropertiesKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn cmd_write_acceleration_structures_properties_khr(
    command_buffer: vk::CommandBuffer,
    count: u32,
    p_structures: *const vk::AccelerationStructureKHR,
    query_type: vk::QueryType,
    query_pool: vk::QueryPool,
    first_query: u32,
) {
    const CMD: &str = "vkCmdWriteAccelerationStructuresPropertiesKHR";
    guard(CMD, (), || {
        let Some(cb) = command_buffer_from(command_buffer) else { return };
        let pool = handle::get::<QueryPool>(query_pool.as_raw());
        // SAFETY: count handles (spec).
        let structures = unsafe { util::slice(p_structures, count) }.iter().map(|h| structure_from(*h)).collect();
        WritePropertiesCommand::record(&cb, structures, query_type, pool, (first_query, count));
    })
}

/// `vkWriteAccelerationStructuresPropertiesKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn write_acceleration_structures_properties_khr(
    device: vk::Device,
    count: u32,
    p_structures: *const vk::AccelerationStructureKHR,
    query_type: vk::QueryType,
    data_size: usize,
    p_data: *mut c_void,
    stride: usize,
) -> vk::Result {
    const CMD: &str = "vkWriteAccelerationStructuresPropertiesKHR";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_INITIALIZATION_FAILED };
        if !dev.features.acceleration_structure_host_commands {
            diag::vuid(&format!("VUID-{CMD}-accelerationStructureHostCommands-03585"), CMD, "host commands are not enabled");
        }
        if !stride.is_multiple_of(8) {
            diag::vuid(&format!("VUID-{CMD}-queryType-03448"), CMD, "stride must be a multiple of 8");
            return vk::Result::ERROR_UNKNOWN;
        }
        // The last value ends at (count - 1) * stride + 8, past count * stride when stride is 0.
        let last_end = (count as usize).checked_sub(1).map_or(Some(0), |n| n.checked_mul(stride).and_then(|o| o.checked_add(8)));
        let too_small = |end: Option<usize>| end.is_none_or(|n| n > data_size);
        if too_small((count as usize).checked_mul(stride)) || too_small(last_end) || p_data.is_null() {
            diag::vuid(&format!("VUID-{CMD}-dataSize-03452"), CMD, "dataSize is smaller than accelerationStructureCount * stride");
            return vk::Result::ERROR_UNKNOWN;
        }
        // SAFETY: count handles (spec).
        let structures: Vec<_> = unsafe { util::slice(p_structures, count) }.iter().map(|h| structure_from(*h)).collect();
        for (i, v) in rt::properties(&structures, query_type, CMD).into_iter().enumerate() {
            if let Some(v) = v {
                // SAFETY: i * stride + 8 <= (count - 1) * stride + 8 <= dataSize, checked above;
                // unaligned-safe write.
                unsafe { (p_data as *mut u8).add(i * stride).cast::<u64>().write_unaligned(v) };
            }
        }
        vk::Result::SUCCESS
    })
}

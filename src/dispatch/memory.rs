//! Device memory and buffers: allocation (with device addresses and capture/replay), host
//! mapping, memory requirements, binding, buffer device addresses. Buffer views are answered
//! here too: no format supports texel-buffer access, so every buffer view is invalid usage.
//!
//! The objects are `crate::memory::{Memory, Buffer}`; the checks that need the device's
//! enabled features are made here, range arithmetic lives in `crate::memory`.
use std::ffi::c_void;
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::device::device_from;
use super::handle::{get, register, unregister};
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::diag;
use crate::memory::{AllocError, BindError, Buffer, MapError, Memory};
use crate::runtime::in_use;
use crate::runtime::Device;

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkAllocateMemory => allocate_memory),
        imp!(PFN_vkFreeMemory => free_memory),
        imp!(PFN_vkMapMemory => map_memory),
        imp!(PFN_vkUnmapMemory => unmap_memory),
        imp!(PFN_vkFlushMappedMemoryRanges => flush_mapped_memory_ranges),
        imp!(PFN_vkInvalidateMappedMemoryRanges => invalidate_mapped_memory_ranges),
        imp!(PFN_vkGetDeviceMemoryCommitment => get_device_memory_commitment),
        imp!(PFN_vkGetDeviceMemoryOpaqueCaptureAddress => get_device_memory_opaque_capture_address),
        imp!(PFN_vkCreateBuffer => create_buffer),
        imp!(PFN_vkDestroyBuffer => destroy_buffer),
        imp!(PFN_vkGetBufferMemoryRequirements => get_buffer_memory_requirements),
        imp!(PFN_vkGetBufferMemoryRequirements2 => get_buffer_memory_requirements2),
        imp!(PFN_vkBindBufferMemory => bind_buffer_memory),
        imp!(PFN_vkBindBufferMemory2 => bind_buffer_memory2),
        imp!(PFN_vkGetBufferDeviceAddress => get_buffer_device_address),
        imp!(PFN_vkGetBufferOpaqueCaptureAddress => get_buffer_opaque_capture_address),
    ]
}

/// Arbor's memory types: 0 for everything, 1 the shareable memory sparse buffers bind
/// (`memory::sparse`); both of the one heap.
pub(super) const MEMORY_TYPE_COUNT: u32 = 2;
pub(super) const SPARSE_MEMORY_TYPE: u32 = 1;

/// Report a valid-usage violation and return the code Vulkan 1.4 defines for invalid usage
/// detected by the implementation.
fn invalid(vuid: &str, command: &str, message: &str) -> vk::Result {
    diag::vuid(vuid, command, message);
    vk::Result::ERROR_VALIDATION_FAILED_EXT
}

fn unknown_device(command: &str) -> vk::Result {
    report_unknown_device(command);
    vk::Result::ERROR_VALIDATION_FAILED_EXT
}

fn report_unknown_device(command: &str) {
    diag::vuid(&format!("VUID-{command}-device-parameter"), command, "device is not a valid VkDevice");
}

pub fn memory_from(h: vk::DeviceMemory) -> Option<Arc<Memory>> {
    get::<Memory>(h.as_raw())
}

pub fn buffer_from(h: vk::Buffer) -> Option<Arc<Buffer>> {
    get::<Buffer>(h.as_raw())
}

/// What the pNext chain of VkMemoryAllocateInfo asks for.
#[derive(Default)]
struct AllocateRequest {
    flags: vk::MemoryAllocateFlags,
    capture_address: u64,
}

/// # Safety
/// `p_next` is a valid VkMemoryAllocateInfo pNext chain.
unsafe fn allocate_request(p_next: *const c_void) -> AllocateRequest {
    let mut r = AllocateRequest::default();
    // SAFETY: valid chain; each struct is read as the type its sType names.
    unsafe {
        if let Some(f) = util::find_in::<vk::MemoryAllocateFlagsInfo>(p_next, vk::StructureType::MEMORY_ALLOCATE_FLAGS_INFO) {
            r.flags = f.flags;
        }
        if let Some(c) = util::find_in::<vk::MemoryOpaqueCaptureAddressAllocateInfo>(
            p_next,
            vk::StructureType::MEMORY_OPAQUE_CAPTURE_ADDRESS_ALLOCATE_INFO,
        ) {
            r.capture_address = c.opaque_capture_address;
        }
    }
    // VkMemoryDedicatedAllocateInfo is accepted: every allocation is as good as dedicated.
    r
}

unsafe extern "system" fn allocate_memory(
    device: vk::Device,
    p_allocate_info: *const vk::MemoryAllocateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_memory: *mut vk::DeviceMemory,
) -> vk::Result {
    const CMD: &str = "vkAllocateMemory";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        let Some(dev) = device_from(device) else { return unknown_device(CMD) };
        if p_allocate_info.is_null() || p_memory.is_null() {
            return invalid("VUID-vkAllocateMemory-pAllocateInfo-parameter", CMD, "null pointer argument");
        }
        // SAFETY: valid allocate info per the spec.
        let info = unsafe { &*p_allocate_info };
        // SAFETY: valid chain per the spec.
        let req = unsafe { allocate_request(info.p_next) };
        // SAFETY: checked non-null.
        unsafe { *p_memory = vk::DeviceMemory::null() };
        match allocate(&dev, info.allocation_size, info.memory_type_index, &req) {
            Ok(memory) => {
                // SAFETY: checked non-null.
                unsafe { *p_memory = vk::DeviceMemory::from_raw(register(memory)) };
                vk::Result::SUCCESS
            }
            Err(e) => e,
        }
    })
}

fn allocate(dev: &Device, size: u64, type_index: u32, req: &AllocateRequest) -> Result<Arc<Memory>, vk::Result> {
    const CMD: &str = "vkAllocateMemory";
    if type_index >= MEMORY_TYPE_COUNT {
        return Err(invalid(
            "VUID-vkAllocateMemory-pAllocateInfo-01714",
            CMD,
            &format!("memoryTypeIndex {type_index} is not a memory type of this device (there is {MEMORY_TYPE_COUNT})"),
        ));
    }
    if size == 0 {
        return Err(invalid("VUID-VkMemoryAllocateInfo-allocationSize-00638", CMD, "allocationSize is 0"));
    }
    if size > dev.memory.heap_size {
        // Invalid usage, but the answer an application can handle is the honest one.
        diag::vuid(
            "VUID-vkAllocateMemory-pAllocateInfo-01713",
            CMD,
            &format!("allocationSize {size} exceeds the heap size {}", dev.memory.heap_size),
        );
        return Err(vk::Result::ERROR_OUT_OF_DEVICE_MEMORY);
    }
    let device_address = req.flags.contains(vk::MemoryAllocateFlags::DEVICE_ADDRESS);
    let capture_replay = req.flags.contains(vk::MemoryAllocateFlags::DEVICE_ADDRESS_CAPTURE_REPLAY);
    if device_address && !dev.features.buffer_device_address {
        return Err(invalid(
            "VUID-VkMemoryAllocateInfo-flags-03331",
            CMD,
            "VK_MEMORY_ALLOCATE_DEVICE_ADDRESS_BIT without the bufferDeviceAddress feature",
        ));
    }
    if capture_replay && !dev.features.buffer_device_address_capture_replay {
        return Err(invalid(
            "VUID-VkMemoryAllocateInfo-flags-03330",
            CMD,
            "VK_MEMORY_ALLOCATE_DEVICE_ADDRESS_CAPTURE_REPLAY_BIT without the bufferDeviceAddressCaptureReplay feature",
        ));
    }
    if req.capture_address != 0 && !capture_replay {
        return Err(invalid(
            "VUID-VkMemoryAllocateInfo-opaqueCaptureAddress-03329",
            CMD,
            "an opaque capture address was given without VK_MEMORY_ALLOCATE_DEVICE_ADDRESS_CAPTURE_REPLAY_BIT",
        ));
    }
    let capture = (req.capture_address != 0).then_some(req.capture_address);
    let allocation = if type_index == SPARSE_MEMORY_TYPE {
        dev.memory.allocate_shareable_with(size, device_address, capture_replay, capture)
    } else {
        dev.memory.allocate_with(size, device_address, capture_replay, capture)
    };
    allocation.map_err(|e| match e {
        AllocError::OutOfDeviceMemory => vk::Result::ERROR_OUT_OF_DEVICE_MEMORY,
        AllocError::OutOfHostMemory => vk::Result::ERROR_OUT_OF_HOST_MEMORY,
        AllocError::InvalidCaptureAddress => {
            diag::report(
                diag::Level::Warn,
                CMD,
                &format!("opaque capture address {:#x} cannot be honoured (taken or not one Arbor hands out)", req.capture_address),
            );
            vk::Result::ERROR_INVALID_OPAQUE_CAPTURE_ADDRESS
        }
    })
}

unsafe extern "system" fn free_memory(device: vk::Device, memory: vk::DeviceMemory, _p_allocator: *const vk::AllocationCallbacks) {
    const CMD: &str = "vkFreeMemory";
    guard(CMD, (), || {
        let Some(dev) = device_from(device) else {
            report_unknown_device(CMD);
            return;
        };
        if memory == vk::DeviceMemory::null() {
            return;
        }
        match unregister::<Memory>(memory.as_raw()) {
            Some(m) => {
                in_use::check_destroy(
                    Some(&dev),
                    &*m,
                    CMD,
                    "VUID-vkFreeMemory-memory-00677",
                    &format!("memory {:#x}", memory.as_raw()),
                    "its addresses stop resolving now, so the pending work touching it is reported and skipped",
                );
                dev.memory.free(&m)
            }
            None => diag::vuid("VUID-vkFreeMemory-memory-parameter", CMD, "memory is not a live VkDeviceMemory"),
        }
    })
}

unsafe extern "system" fn map_memory(
    device: vk::Device,
    memory: vk::DeviceMemory,
    offset: vk::DeviceSize,
    size: vk::DeviceSize,
    flags: vk::MemoryMapFlags,
    pp_data: *mut *mut c_void,
) -> vk::Result {
    const CMD: &str = "vkMapMemory";
    guard(CMD, vk::Result::ERROR_MEMORY_MAP_FAILED, || {
        if device_from(device).is_none() {
            return unknown_device(CMD);
        }
        // SAFETY: valid output pointer per the spec.
        unsafe { util::out(pp_data, std::ptr::null_mut()) };
        let Some(m) = memory_from(memory) else {
            return invalid("VUID-vkMapMemory-memory-parameter", CMD, "memory is not a live VkDeviceMemory");
        };
        if !flags.is_empty() {
            return invalid("VUID-vkMapMemory-flags-zerobitmask", CMD, "flags must be 0");
        }
        if offset >= m.size {
            diag::vuid("VUID-vkMapMemory-offset-00679", CMD, &format!("offset {offset} is not less than the memory size {}", m.size));
            return vk::Result::ERROR_MEMORY_MAP_FAILED;
        }
        let len = if size == vk::WHOLE_SIZE { m.size - offset } else { size };
        if len == 0 {
            diag::vuid("VUID-vkMapMemory-size-00680", CMD, "size is 0");
            return vk::Result::ERROR_MEMORY_MAP_FAILED;
        }
        if len > m.size - offset {
            diag::vuid(
                "VUID-vkMapMemory-size-00681",
                CMD,
                &format!("offset {offset} + size {len} exceeds the memory size {}", m.size),
            );
            return vk::Result::ERROR_MEMORY_MAP_FAILED;
        }
        match m.map(offset, len) {
            Ok(p) => {
                // SAFETY: valid output pointer per the spec.
                unsafe { util::out(pp_data, p as *mut c_void) };
                vk::Result::SUCCESS
            }
            Err(MapError::AlreadyMapped) => {
                diag::vuid("VUID-vkMapMemory-memory-00678", CMD, "memory is already host mapped");
                vk::Result::ERROR_MEMORY_MAP_FAILED
            }
            Err(MapError::Range | MapError::Freed) => {
                diag::report(diag::Level::Error, CMD, "the memory cannot be mapped (freed or out of range)");
                vk::Result::ERROR_MEMORY_MAP_FAILED
            }
        }
    })
}

unsafe extern "system" fn unmap_memory(device: vk::Device, memory: vk::DeviceMemory) {
    const CMD: &str = "vkUnmapMemory";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_unknown_device(CMD);
            return;
        }
        match memory_from(memory) {
            Some(m) => {
                if !m.unmap() {
                    diag::vuid("VUID-vkUnmapMemory-memory-00689", CMD, "memory is not host mapped");
                }
            }
            None => diag::vuid("VUID-vkUnmapMemory-memory-parameter", CMD, "memory is not a live VkDeviceMemory"),
        }
    })
}

/// Check one VkMappedMemoryRange. Memory is coherent, so a valid range needs no work.
fn check_mapped_range(command: &str, range: &vk::MappedMemoryRange) -> bool {
    let Some(m) = memory_from(range.memory) else {
        diag::vuid("VUID-VkMappedMemoryRange-memory-parameter", command, "memory is not a live VkDeviceMemory");
        return false;
    };
    let Some((map_offset, map_size)) = m.mapped_range() else {
        diag::vuid("VUID-VkMappedMemoryRange-memory-00684", command, "memory is not currently host mapped");
        return false;
    };
    let map_end = map_offset + map_size;
    if range.size == vk::WHOLE_SIZE {
        if range.offset < map_offset || range.offset >= map_end {
            diag::vuid(
                "VUID-VkMappedMemoryRange-size-00686",
                command,
                &format!("offset {} is outside the mapped range [{map_offset}, {map_end})", range.offset),
            );
            return false;
        }
    } else {
        let inside = range.offset >= map_offset && range.offset.checked_add(range.size).is_some_and(|e| e <= map_end);
        if !inside {
            diag::vuid(
                "VUID-VkMappedMemoryRange-size-00685",
                command,
                &format!("range [{}, +{}) is not inside the mapped range [{map_offset}, {map_end})", range.offset, range.size),
            );
            return false;
        }
    }
    // nonCoherentAtomSize is 1: the alignment rules (offset-00687, size-01389, size-01390) always hold.
    true
}

fn mapped_ranges(command: &str, device: vk::Device, count: u32, p_ranges: *const vk::MappedMemoryRange) -> vk::Result {
    if device_from(device).is_none() {
        return unknown_device(command);
    }
    // SAFETY: valid array per the spec.
    let ranges = unsafe { util::slice(p_ranges, count) };
    // Every range is checked (and every problem reported), not just up to the first.
    let mut all_valid = true;
    for r in ranges {
        all_valid &= check_mapped_range(command, r);
    }
    if all_valid {
        vk::Result::SUCCESS
    } else {
        vk::Result::ERROR_VALIDATION_FAILED_EXT
    }
}

unsafe extern "system" fn flush_mapped_memory_ranges(device: vk::Device, count: u32, p_ranges: *const vk::MappedMemoryRange) -> vk::Result {
    const CMD: &str = "vkFlushMappedMemoryRanges";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || mapped_ranges(CMD, device, count, p_ranges))
}

unsafe extern "system" fn invalidate_mapped_memory_ranges(
    device: vk::Device,
    count: u32,
    p_ranges: *const vk::MappedMemoryRange,
) -> vk::Result {
    const CMD: &str = "vkInvalidateMappedMemoryRanges";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || mapped_ranges(CMD, device, count, p_ranges))
}

unsafe extern "system" fn get_device_memory_commitment(device: vk::Device, memory: vk::DeviceMemory, p_committed: *mut vk::DeviceSize) {
    const CMD: &str = "vkGetDeviceMemoryCommitment";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_unknown_device(CMD);
            return;
        }
        let Some(m) = memory_from(memory) else {
            diag::vuid("VUID-vkGetDeviceMemoryCommitment-memory-parameter", CMD, "memory is not a live VkDeviceMemory");
            return;
        };
        // Arbor's one memory type is not lazily allocated, so the query is invalid usage; the
        // answer is still the truth: the whole allocation is committed.
        diag::vuid(
            "VUID-vkGetDeviceMemoryCommitment-memory-00690",
            CMD,
            "memory was not allocated from a VK_MEMORY_PROPERTY_LAZILY_ALLOCATED_BIT memory type",
        );
        // SAFETY: valid output pointer per the spec.
        unsafe { util::out(p_committed, m.size) };
    })
}

unsafe extern "system" fn get_device_memory_opaque_capture_address(
    device: vk::Device,
    p_info: *const vk::DeviceMemoryOpaqueCaptureAddressInfo,
) -> u64 {
    const CMD: &str = "vkGetDeviceMemoryOpaqueCaptureAddress";
    guard(CMD, 0, || {
        let Some(dev) = device_from(device) else {
            report_unknown_device(CMD);
            return 0;
        };
        if p_info.is_null() {
            diag::vuid("VUID-vkGetDeviceMemoryOpaqueCaptureAddress-pInfo-parameter", CMD, "pInfo is null");
            return 0;
        }
        // SAFETY: valid info per the spec.
        let info = unsafe { &*p_info };
        let Some(m) = memory_from(info.memory) else {
            diag::vuid("VUID-VkDeviceMemoryOpaqueCaptureAddressInfo-memory-parameter", CMD, "memory is not a live VkDeviceMemory");
            return 0;
        };
        if !dev.features.buffer_device_address {
            diag::vuid("VUID-vkGetDeviceMemoryOpaqueCaptureAddress-None-03334", CMD, "the bufferDeviceAddress feature is not enabled");
        }
        if !m.device_address_flag {
            diag::vuid(
                "VUID-VkDeviceMemoryOpaqueCaptureAddressInfo-memory-03336",
                CMD,
                "memory was not allocated with VK_MEMORY_ALLOCATE_DEVICE_ADDRESS_BIT",
            );
        }
        // The opaque capture address is the allocation's device address: allocating with it
        // on replay places the memory, and so every buffer bound to it, where it was.
        m.address
    })
}

/// Buffer creation flags Arbor supports (sparse binding, but no sparse residency or aliasing,
/// no protected memory).
const SUPPORTED_BUFFER_FLAGS: vk::BufferCreateFlags =
    vk::BufferCreateFlags::from_raw(vk::BufferCreateFlags::DEVICE_ADDRESS_CAPTURE_REPLAY.as_raw() | vk::BufferCreateFlags::SPARSE_BINDING.as_raw());

unsafe extern "system" fn create_buffer(
    device: vk::Device,
    p_create_info: *const vk::BufferCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_buffer: *mut vk::Buffer,
) -> vk::Result {
    const CMD: &str = "vkCreateBuffer";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        let Some(dev) = device_from(device) else { return unknown_device(CMD) };
        if p_create_info.is_null() || p_buffer.is_null() {
            return invalid("VUID-vkCreateBuffer-pCreateInfo-parameter", CMD, "null pointer argument");
        }
        // SAFETY: valid create info per the spec.
        let info = unsafe { &*p_create_info };
        // SAFETY: checked non-null.
        unsafe { *p_buffer = vk::Buffer::null() };
        // SAFETY: valid chain per the spec.
        let capture = unsafe {
            util::find_in::<vk::BufferOpaqueCaptureAddressCreateInfo>(
                info.p_next,
                vk::StructureType::BUFFER_OPAQUE_CAPTURE_ADDRESS_CREATE_INFO,
            )
        }
        .map_or(0, |c| c.opaque_capture_address);
        if info.size == 0 {
            return invalid("VUID-VkBufferCreateInfo-size-00912", CMD, "size is 0");
        }
        if info.usage.is_empty() {
            return invalid("VUID-VkBufferCreateInfo-usage-requiredbitmask", CMD, "usage is 0");
        }
        let unsupported = info.flags & !SUPPORTED_BUFFER_FLAGS;
        if !unsupported.is_empty() {
            return invalid(
                "VUID-VkBufferCreateInfo-flags-00915",
                CMD,
                &format!("flags {unsupported:?} need features Arbor does not offer (sparse residency or aliasing, protected memory)"),
            );
        }
        if info.flags.contains(vk::BufferCreateFlags::DEVICE_ADDRESS_CAPTURE_REPLAY) && !dev.features.buffer_device_address_capture_replay {
            return invalid(
                "VUID-VkBufferCreateInfo-flags-03338",
                CMD,
                "VK_BUFFER_CREATE_DEVICE_ADDRESS_CAPTURE_REPLAY_BIT without the bufferDeviceAddressCaptureReplay feature",
            );
        }
        if capture != 0 && !info.flags.contains(vk::BufferCreateFlags::DEVICE_ADDRESS_CAPTURE_REPLAY) {
            return invalid(
                "VUID-VkBufferCreateInfo-opaqueCaptureAddress-03337",
                CMD,
                "an opaque capture address was given without VK_BUFFER_CREATE_DEVICE_ADDRESS_CAPTURE_REPLAY_BIT",
            );
        }
        let mut buffer = Buffer::new(info.size, info.usage, info.flags);
        buffer.capture_address = capture;
        let buffer = Arc::new(buffer);
        if info.flags.contains(vk::BufferCreateFlags::SPARSE_BINDING) {
            if let Err(e) = super::queue::reserve_sparse_range(&dev, &buffer, CMD) {
                return e;
            }
        }
        // SAFETY: checked non-null.
        unsafe { *p_buffer = vk::Buffer::from_raw(register(buffer)) };
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn destroy_buffer(device: vk::Device, buffer: vk::Buffer, _p_allocator: *const vk::AllocationCallbacks) {
    const CMD: &str = "vkDestroyBuffer";
    guard(CMD, (), || {
        let Some(dev) = device_from(device) else {
            report_unknown_device(CMD);
            return;
        };
        if buffer == vk::Buffer::null() {
            return;
        }
        match unregister::<Buffer>(buffer.as_raw()) {
            None => diag::vuid("VUID-vkDestroyBuffer-buffer-parameter", CMD, "buffer is not a live VkBuffer"),
            Some(b) => {
                in_use::check_destroy(
                    Some(&dev),
                    &*b,
                    CMD,
                    "VUID-vkDestroyBuffer-buffer-00922",
                    &format!("buffer {:#x}", buffer.as_raw()),
                    "the pending commands keep the buffer alive and finish",
                );
                // A sparse buffer's range is its own: its addresses go with it.
                if let Some((range, _)) = b.memory().filter(|(m, _)| m.is_sparse()) {
                    dev.memory.free(range);
                }
            }
        }
    })
}

/// A sparse buffer binds pages of the sparse memory type only; other buffers take the
/// ordinary type, so their memory keeps its huge-page backing.
pub(super) fn requirements(buffer: &Buffer) -> vk::MemoryRequirements {
    if buffer.flags.contains(vk::BufferCreateFlags::SPARSE_BINDING) {
        let page = crate::memory::sparse::SPARSE_PAGE;
        let size = buffer.size.checked_next_multiple_of(page).unwrap_or(buffer.size);
        return vk::MemoryRequirements { size, alignment: page, memory_type_bits: 1 << SPARSE_MEMORY_TYPE };
    }
    let (size, alignment) = buffer.requirements();
    vk::MemoryRequirements { size, alignment, memory_type_bits: 1 }
}

/// Writes `reqs` into a `VkMemoryRequirements2` and answers the structs chained to it (buffers
/// and images alike): a dedicated allocation gains nothing on a CPU device.
///
/// # Safety
/// `p_req` is a valid `VkMemoryRequirements2` whose pNext chain is valid (the spec's rule).
pub(super) unsafe fn write_requirements2(p_req: *mut vk::MemoryRequirements2, reqs: vk::MemoryRequirements) {
    // SAFETY: the caller's contract; write_keep_chain keeps pNext.
    unsafe {
        (*p_req).memory_requirements = reqs;
        util::for_each_out((*p_req).p_next, |s, p| {
            if s == vk::StructureType::MEMORY_DEDICATED_REQUIREMENTS {
                util::write_keep_chain(p, vk::MemoryDedicatedRequirements::default());
            }
        });
    }
}

unsafe extern "system" fn get_buffer_memory_requirements(device: vk::Device, buffer: vk::Buffer, p_req: *mut vk::MemoryRequirements) {
    const CMD: &str = "vkGetBufferMemoryRequirements";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_unknown_device(CMD);
            return;
        }
        let Some(b) = buffer_from(buffer) else {
            diag::vuid("VUID-vkGetBufferMemoryRequirements-buffer-parameter", CMD, "buffer is not a live VkBuffer");
            return;
        };
        // SAFETY: valid output pointer per the spec.
        unsafe { util::out(p_req, requirements(&b)) };
    })
}

unsafe extern "system" fn get_buffer_memory_requirements2(
    device: vk::Device,
    p_info: *const vk::BufferMemoryRequirementsInfo2,
    p_req: *mut vk::MemoryRequirements2,
) {
    const CMD: &str = "vkGetBufferMemoryRequirements2";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_unknown_device(CMD);
            return;
        }
        if p_info.is_null() || p_req.is_null() {
            diag::vuid("VUID-vkGetBufferMemoryRequirements2-pInfo-parameter", CMD, "null pointer argument");
            return;
        }
        // SAFETY: valid info per the spec.
        let Some(b) = buffer_from(unsafe { (*p_info).buffer }) else {
            diag::vuid("VUID-VkBufferMemoryRequirementsInfo2-buffer-parameter", CMD, "buffer is not a live VkBuffer");
            return;
        };
        // SAFETY: valid output struct and chain per the spec.
        unsafe { write_requirements2(p_req, requirements(&b)) };
    })
}

/// Bind one buffer. `prefix` is the VUID prefix of the command or struct ("vkBindBufferMemory"
/// or "VkBindBufferMemoryInfo").
fn bind_one(command: &str, prefix: &str, buffer: vk::Buffer, memory: vk::DeviceMemory, offset: u64) -> vk::Result {
    let Some(b) = buffer_from(buffer) else {
        return invalid(&format!("VUID-{prefix}-buffer-parameter"), command, "buffer is not a live VkBuffer");
    };
    let Some(m) = memory_from(memory) else {
        return invalid(&format!("VUID-{prefix}-memory-parameter"), command, "memory is not a live VkDeviceMemory");
    };
    if b.flags.contains(vk::BufferCreateFlags::SPARSE_BINDING) {
        return invalid(&format!("VUID-{prefix}-buffer-01030"), command, "the buffer was created sparse: bind its pages with vkQueueBindSparse");
    }
    if m.is_shareable() {
        return invalid(
            &format!("VUID-{prefix}-memory-01035"),
            command,
            "the memory is of the sparse memory type, which is not in the buffer's memoryTypeBits",
        );
    }
    if offset >= m.size {
        return invalid(
            &format!("VUID-{prefix}-memoryOffset-01031"),
            command,
            &format!("memoryOffset {offset} is not less than the memory size {}", m.size),
        );
    }
    let (req_size, alignment) = b.requirements();
    if !offset.is_multiple_of(alignment) {
        return invalid(
            &format!("VUID-{prefix}-memoryOffset-01036"),
            command,
            &format!("memoryOffset {offset} is not a multiple of the required alignment {alignment}"),
        );
    }
    if m.size - offset < req_size {
        return invalid(
            &format!("VUID-{prefix}-size-01037"),
            command,
            &format!("the memory has {} bytes after memoryOffset {offset}, the buffer requires {req_size}", m.size - offset),
        );
    }
    if b.usage.contains(vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS) && !m.device_address_flag {
        return invalid(
            &format!("VUID-{prefix}-bufferDeviceAddress-03339"),
            command,
            "the buffer has VK_BUFFER_USAGE_SHADER_DEVICE_ADDRESS_BIT but the memory was not allocated with VK_MEMORY_ALLOCATE_DEVICE_ADDRESS_BIT",
        );
    }
    match b.bind(m, offset) {
        Ok(()) => {
            let address = b.device_address().unwrap_or(0);
            if b.capture_address != 0 && b.capture_address != address {
                diag::report(
                    diag::Level::Warn,
                    command,
                    &format!(
                        "buffer created with opaque capture address {:#x} is bound at {address:#x}: allocate its memory with the captured memory address",
                        b.capture_address
                    ),
                );
            }
            vk::Result::SUCCESS
        }
        Err(BindError::AlreadyBound) => invalid(&format!("VUID-{prefix}-buffer-07459"), command, "the buffer is already bound to memory"),
        Err(BindError::Misaligned) => invalid(&format!("VUID-{prefix}-memoryOffset-01036"), command, "memoryOffset is misaligned"),
        Err(BindError::Access(e)) => invalid(&format!("VUID-{prefix}-size-01037"), command, &e.to_string()),
    }
}

unsafe extern "system" fn bind_buffer_memory(device: vk::Device, buffer: vk::Buffer, memory: vk::DeviceMemory, offset: vk::DeviceSize) -> vk::Result {
    const CMD: &str = "vkBindBufferMemory";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return unknown_device(CMD);
        }
        bind_one(CMD, CMD, buffer, memory, offset)
    })
}

unsafe extern "system" fn bind_buffer_memory2(device: vk::Device, count: u32, p_infos: *const vk::BindBufferMemoryInfo) -> vk::Result {
    const CMD: &str = "vkBindBufferMemory2";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return unknown_device(CMD);
        }
        // SAFETY: valid array per the spec.
        let infos = unsafe { util::slice(p_infos, count) };
        // VkBindBufferMemoryDeviceGroupInfo is ignored: one physical device per group.
        infos.iter().fold(vk::Result::SUCCESS, |result, i| {
            let r = bind_one(CMD, "VkBindBufferMemoryInfo", i.buffer, i.memory, i.memory_offset);
            if result == vk::Result::SUCCESS {
                r
            } else {
                result
            }
        })
    })
}

unsafe extern "system" fn get_buffer_device_address(device: vk::Device, p_info: *const vk::BufferDeviceAddressInfo) -> vk::DeviceAddress {
    const CMD: &str = "vkGetBufferDeviceAddress";
    guard(CMD, 0, || {
        let Some(dev) = device_from(device) else {
            report_unknown_device(CMD);
            return 0;
        };
        if p_info.is_null() {
            diag::vuid("VUID-vkGetBufferDeviceAddress-pInfo-parameter", CMD, "pInfo is null");
            return 0;
        }
        // SAFETY: valid info per the spec.
        let Some(b) = buffer_from(unsafe { (*p_info).buffer }) else {
            diag::vuid("VUID-VkBufferDeviceAddressInfo-buffer-parameter", CMD, "buffer is not a live VkBuffer");
            return 0;
        };
        if !dev.features.buffer_device_address {
            diag::vuid("VUID-vkGetBufferDeviceAddress-bufferDeviceAddress-03324", CMD, "the bufferDeviceAddress feature is not enabled");
        }
        if !b.usage.contains(vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS) {
            diag::vuid(
                "VUID-VkBufferDeviceAddressInfo-buffer-02601",
                CMD,
                "the buffer was not created with VK_BUFFER_USAGE_SHADER_DEVICE_ADDRESS_BIT",
            );
        }
        match b.device_address() {
            Some(a) => a,
            None => {
                diag::vuid("VUID-VkBufferDeviceAddressInfo-buffer-02600", CMD, "the buffer is not bound to memory");
                0
            }
        }
    })
}

unsafe extern "system" fn get_buffer_opaque_capture_address(device: vk::Device, p_info: *const vk::BufferDeviceAddressInfo) -> u64 {
    const CMD: &str = "vkGetBufferOpaqueCaptureAddress";
    guard(CMD, 0, || {
        let Some(dev) = device_from(device) else {
            report_unknown_device(CMD);
            return 0;
        };
        if p_info.is_null() {
            diag::vuid("VUID-vkGetBufferOpaqueCaptureAddress-pInfo-parameter", CMD, "pInfo is null");
            return 0;
        }
        // SAFETY: valid info per the spec.
        let Some(b) = buffer_from(unsafe { (*p_info).buffer }) else {
            diag::vuid("VUID-VkBufferDeviceAddressInfo-buffer-parameter", CMD, "buffer is not a live VkBuffer");
            return 0;
        };
        if !dev.features.buffer_device_address_capture_replay {
            diag::vuid(
                "VUID-vkGetBufferOpaqueCaptureAddress-None-03326",
                CMD,
                "the bufferDeviceAddressCaptureReplay feature is not enabled",
            );
        }
        // A buffer's address is its memory's address plus the bind offset: replaying the
        // memory at its captured address reproduces it, so the address is the capture data.
        b.device_address().unwrap_or(b.capture_address)
    })
}


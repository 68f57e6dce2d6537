//! Command pools, command buffers and the vkCmd* commands of the transfer/sync/query areas:
//! handles and raw arrays → checked Rust values → one call into `runtime::command`.
use std::ffi::c_void;
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::device::device_from;
use super::handle::{self, dispatchable, free_dispatchable, new_dispatchable, Dispatchable};
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::memory::Buffer;
use crate::runtime::command::{CommandBuffer, CommandPool, CopyRegion, COPY_BUFFER2_VUIDS, COPY_BUFFER_VUIDS};
use crate::runtime::query::QueryPool;
use crate::runtime::sync::Event;

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCreateCommandPool => create_command_pool),
        imp!(PFN_vkDestroyCommandPool => destroy_command_pool),
        imp!(PFN_vkResetCommandPool => reset_command_pool),
        imp!(PFN_vkTrimCommandPool => trim_command_pool),
        imp!(PFN_vkAllocateCommandBuffers => allocate_command_buffers),
        imp!(PFN_vkFreeCommandBuffers => free_command_buffers),
        imp!(PFN_vkBeginCommandBuffer => begin_command_buffer),
        imp!(PFN_vkEndCommandBuffer => end_command_buffer),
        imp!(PFN_vkResetCommandBuffer => reset_command_buffer),
        imp!(PFN_vkCmdCopyBuffer => cmd_copy_buffer),
        imp!(PFN_vkCmdCopyBuffer2 => cmd_copy_buffer2),
        imp!(PFN_vkCmdFillBuffer => cmd_fill_buffer),
        imp!(PFN_vkCmdUpdateBuffer => cmd_update_buffer),
        imp!(PFN_vkCmdPipelineBarrier => cmd_pipeline_barrier),
        imp!(PFN_vkCmdPipelineBarrier2 => cmd_pipeline_barrier2),
        imp!(PFN_vkCmdSetEvent => cmd_set_event),
        imp!(PFN_vkCmdSetEvent2 => cmd_set_event2),
        imp!(PFN_vkCmdResetEvent => cmd_reset_event),
        imp!(PFN_vkCmdResetEvent2 => cmd_reset_event2),
        imp!(PFN_vkCmdWaitEvents => cmd_wait_events),
        imp!(PFN_vkCmdWaitEvents2 => cmd_wait_events2),
        imp!(PFN_vkCmdWriteTimestamp => cmd_write_timestamp),
        imp!(PFN_vkCmdWriteTimestamp2 => cmd_write_timestamp2),
        imp!(PFN_vkCmdResetQueryPool => cmd_reset_query_pool),
        imp!(PFN_vkCmdCopyQueryPoolResults => cmd_copy_query_pool_results),
        imp!(PFN_vkCmdBeginQuery => cmd_begin_query),
        imp!(PFN_vkCmdEndQuery => cmd_end_query),
        imp!(PFN_vkCmdExecuteCommands => cmd_execute_commands),
    ]
}

pub type CommandBufferHandle = *mut Dispatchable<CommandBuffer>;

/// Resolve a VkCommandBuffer.
pub fn command_buffer_from(h: vk::CommandBuffer) -> Option<Arc<CommandBuffer>> {
    // SAFETY: a non-null VkCommandBuffer is a live handle we created (application obligation).
    unsafe { dispatchable::<CommandBuffer>(h.as_raw() as CommandBufferHandle) }
}

/// Look up a non-dispatchable object, reporting an unknown handle against `command`.
fn lookup<T: Send + Sync + 'static>(raw: u64, command: &str, what: &str) -> Option<Arc<T>> {
    let r = handle::get::<T>(raw);
    if r.is_none() {
        crate::diag::report(crate::diag::Level::Error, command, &format!("{what} is not a valid handle ({raw:#x}); command ignored"));
    }
    r
}

fn buffer(b: vk::Buffer, command: &str, what: &str) -> Option<Arc<Buffer>> {
    lookup::<Buffer>(b.as_raw(), command, what)
}

unsafe extern "system" fn create_command_pool(
    device: vk::Device,
    p_create_info: *const vk::CommandPoolCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_pool: *mut vk::CommandPool,
) -> vk::Result {
    guard("vkCreateCommandPool", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() || p_create_info.is_null() || p_pool.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid create info per the spec.
        let info = unsafe { &*p_create_info };
        if info.queue_family_index >= super::physical_device::QUEUE_FAMILY_COUNT {
            crate::diag::vuid("VUID-vkCreateCommandPool-queueFamilyIndex-01937", "vkCreateCommandPool", "no such queue family");
        }
        let pool = Arc::new(CommandPool::new(info.flags, info.queue_family_index));
        // SAFETY: checked non-null.
        unsafe { *p_pool = vk::CommandPool::from_raw(handle::register(pool)) };
        vk::Result::SUCCESS
    })
}

/// Free dispatchable command buffer handles.
fn free_handles(handles: Vec<usize>) {
    for h in handles {
        // SAFETY: the pool only stores handles it allocated and releases each once.
        unsafe { free_dispatchable::<CommandBuffer>(h as CommandBufferHandle) };
    }
}

unsafe extern "system" fn destroy_command_pool(device: vk::Device, pool: vk::CommandPool, _p_allocator: *const vk::AllocationCallbacks) {
    guard("vkDestroyCommandPool", (), || {
        if device_from(device).is_none() || pool == vk::CommandPool::null() {
            return;
        }
        if let Some(p) = handle::unregister::<CommandPool>(pool.as_raw()) {
            free_handles(p.take_all());
        }
    })
}

unsafe extern "system" fn reset_command_pool(device: vk::Device, pool: vk::CommandPool, flags: vk::CommandPoolResetFlags) -> vk::Result {
    guard("vkResetCommandPool", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        let (Some(_), Some(p)) = (device_from(device), lookup::<CommandPool>(pool.as_raw(), "vkResetCommandPool", "commandPool")) else {
            return vk::Result::SUCCESS;
        };
        p.reset(flags.contains(vk::CommandPoolResetFlags::RELEASE_RESOURCES));
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn trim_command_pool(device: vk::Device, pool: vk::CommandPool, _flags: vk::CommandPoolTrimFlags) {
    guard("vkTrimCommandPool", (), || {
        if let (Some(_), Some(p)) = (device_from(device), lookup::<CommandPool>(pool.as_raw(), "vkTrimCommandPool", "commandPool")) {
            p.trim();
        }
    })
}

unsafe extern "system" fn allocate_command_buffers(
    device: vk::Device,
    p_info: *const vk::CommandBufferAllocateInfo,
    p_buffers: *mut vk::CommandBuffer,
) -> vk::Result {
    guard("vkAllocateCommandBuffers", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() || p_info.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid allocate info per the spec.
        let info = unsafe { &*p_info };
        let n = info.command_buffer_count as usize;
        if n > 0 && p_buffers.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        let Some(pool) = lookup::<CommandPool>(info.command_pool.as_raw(), "vkAllocateCommandBuffers", "commandPool") else {
            // SAFETY: p_buffers is valid for n writes; on failure every element is set to null.
            unsafe { (0..n).for_each(|i| *p_buffers.add(i) = vk::CommandBuffer::null()) };
            return vk::Result::ERROR_OUT_OF_HOST_MEMORY;
        };
        if info.level != vk::CommandBufferLevel::PRIMARY && info.level != vk::CommandBufferLevel::SECONDARY {
            crate::diag::vuid("VUID-VkCommandBufferAllocateInfo-level-parameter", "vkAllocateCommandBuffers", "invalid level");
        }
        for i in 0..n {
            let cb = pool.allocate(info.level);
            let h = new_dispatchable(cb.clone());
            pool.adopt(h as usize, cb);
            // SAFETY: p_buffers is valid for n writes.
            unsafe { *p_buffers.add(i) = vk::CommandBuffer::from_raw(h as u64) };
        }
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn free_command_buffers(device: vk::Device, pool: vk::CommandPool, count: u32, p_buffers: *const vk::CommandBuffer) {
    guard("vkFreeCommandBuffers", (), || {
        let (Some(_), Some(p)) = (device_from(device), lookup::<CommandPool>(pool.as_raw(), "vkFreeCommandBuffers", "commandPool")) else {
            return;
        };
        // SAFETY: valid array of count handles per the spec.
        let handles = unsafe { util::slice(p_buffers, count) };
        let mut freed = Vec::new();
        for h in handles.iter().filter(|h| !h.is_null()) {
            if p.release(h.as_raw() as usize, "vkFreeCommandBuffers") {
                freed.push(h.as_raw() as usize);
            } else {
                crate::diag::vuid("VUID-vkFreeCommandBuffers-pCommandBuffers-parent", "vkFreeCommandBuffers", "a command buffer was not allocated from commandPool; not freed");
            }
        }
        free_handles(freed);
    })
}

unsafe extern "system" fn begin_command_buffer(cb: vk::CommandBuffer, p_info: *const vk::CommandBufferBeginInfo) -> vk::Result {
    guard("vkBeginCommandBuffer", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        let Some(c) = command_buffer_from(cb) else { return vk::Result::ERROR_INITIALIZATION_FAILED };
        if p_info.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid begin info per the spec.
        let info = unsafe { &*p_info };
        c.begin(info.flags, !info.p_inheritance_info.is_null());
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn end_command_buffer(cb: vk::CommandBuffer) -> vk::Result {
    guard("vkEndCommandBuffer", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || match command_buffer_from(cb) {
        Some(c) => c.end(),
        None => vk::Result::ERROR_INITIALIZATION_FAILED,
    })
}

unsafe extern "system" fn reset_command_buffer(cb: vk::CommandBuffer, flags: vk::CommandBufferResetFlags) -> vk::Result {
    guard("vkResetCommandBuffer", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if let Some(c) = command_buffer_from(cb) {
            c.reset(flags.contains(vk::CommandBufferResetFlags::RELEASE_RESOURCES));
        }
        vk::Result::SUCCESS
    })
}

// --- transfer ---------------------------------------------------------------------------------

unsafe extern "system" fn cmd_copy_buffer(cb: vk::CommandBuffer, src: vk::Buffer, dst: vk::Buffer, count: u32, p_regions: *const vk::BufferCopy) {
    guard("vkCmdCopyBuffer", (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        let (Some(s), Some(d)) = (buffer(src, "vkCmdCopyBuffer", "srcBuffer"), buffer(dst, "vkCmdCopyBuffer", "dstBuffer")) else {
            return c.violation("VUID-vkCmdCopyBuffer-srcBuffer-parameter", "vkCmdCopyBuffer", "invalid buffer handle");
        };
        // SAFETY: valid array of count regions per the spec.
        let regions = unsafe { util::slice(p_regions, count) }
            .iter()
            .map(|r| CopyRegion { src_offset: r.src_offset, dst_offset: r.dst_offset, size: r.size })
            .collect();
        c.cmd_copy_buffer(&COPY_BUFFER_VUIDS, s, d, regions);
    })
}

unsafe extern "system" fn cmd_copy_buffer2(cb: vk::CommandBuffer, p_info: *const vk::CopyBufferInfo2) {
    guard("vkCmdCopyBuffer2", (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        if p_info.is_null() {
            return;
        }
        // SAFETY: valid info per the spec.
        let info = unsafe { &*p_info };
        let (Some(s), Some(d)) = (buffer(info.src_buffer, "vkCmdCopyBuffer2", "srcBuffer"), buffer(info.dst_buffer, "vkCmdCopyBuffer2", "dstBuffer")) else {
            return c.violation("VUID-VkCopyBufferInfo2-srcBuffer-parameter", "vkCmdCopyBuffer2", "invalid buffer handle");
        };
        // SAFETY: valid array of regionCount regions per the spec.
        let regions = unsafe { util::slice(info.p_regions, info.region_count) }
            .iter()
            .map(|r| CopyRegion { src_offset: r.src_offset, dst_offset: r.dst_offset, size: r.size })
            .collect();
        c.cmd_copy_buffer(&COPY_BUFFER2_VUIDS, s, d, regions);
    })
}

unsafe extern "system" fn cmd_fill_buffer(cb: vk::CommandBuffer, dst: vk::Buffer, offset: vk::DeviceSize, size: vk::DeviceSize, data: u32) {
    guard("vkCmdFillBuffer", (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        match buffer(dst, "vkCmdFillBuffer", "dstBuffer") {
            Some(d) => c.cmd_fill_buffer(d, offset, size, data),
            None => c.violation("VUID-vkCmdFillBuffer-dstBuffer-parameter", "vkCmdFillBuffer", "invalid buffer handle"),
        }
    })
}

unsafe extern "system" fn cmd_update_buffer(cb: vk::CommandBuffer, dst: vk::Buffer, offset: vk::DeviceSize, size: vk::DeviceSize, p_data: *const c_void) {
    guard("vkCmdUpdateBuffer", (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        let Some(d) = buffer(dst, "vkCmdUpdateBuffer", "dstBuffer") else {
            return c.violation("VUID-vkCmdUpdateBuffer-dstBuffer-parameter", "vkCmdUpdateBuffer", "invalid buffer handle");
        };
        if size > 65536 || (size > 0 && p_data.is_null()) {
            return c.violation("VUID-vkCmdUpdateBuffer-dataSize-00037", "vkCmdUpdateBuffer", &format!("dataSize {size} must be in 1..=65536 with valid pData"));
        }
        // SAFETY: pData is valid for dataSize bytes per the spec (size checked ≤ 65536).
        let data = unsafe { util::slice(p_data as *const u8, size as u32) }.to_vec();
        c.cmd_update_buffer(d, offset, data);
    })
}

// --- barriers and events --------------------------------------------------------------------

unsafe extern "system" fn cmd_pipeline_barrier(
    cb: vk::CommandBuffer,
    _src: vk::PipelineStageFlags,
    _dst: vk::PipelineStageFlags,
    _dependency: vk::DependencyFlags,
    _memory_count: u32,
    _p_memory: *const vk::MemoryBarrier,
    _buffer_count: u32,
    _p_buffer: *const vk::BufferMemoryBarrier,
    _image_count: u32,
    _p_image: *const vk::ImageMemoryBarrier,
) {
    guard("vkCmdPipelineBarrier", (), || {
        if let Some(c) = command_buffer_from(cb) {
            c.cmd_barrier("vkCmdPipelineBarrier");
        }
    })
}

unsafe extern "system" fn cmd_pipeline_barrier2(cb: vk::CommandBuffer, _p_dependency: *const vk::DependencyInfo) {
    guard("vkCmdPipelineBarrier2", (), || {
        if let Some(c) = command_buffer_from(cb) {
            c.cmd_barrier("vkCmdPipelineBarrier2");
        }
    })
}

fn set_event(cb: vk::CommandBuffer, event: vk::Event, command: &str, set: bool) {
    let Some(c) = command_buffer_from(cb) else { return };
    match lookup::<Event>(event.as_raw(), command, "event") {
        Some(e) => c.cmd_set_event(command, e, set),
        None => c.violation("VUID-vkCmdSetEvent-event-parameter", command, "invalid event handle"),
    }
}

unsafe extern "system" fn cmd_set_event(cb: vk::CommandBuffer, event: vk::Event, _stage: vk::PipelineStageFlags) {
    guard("vkCmdSetEvent", (), || set_event(cb, event, "vkCmdSetEvent", true))
}

unsafe extern "system" fn cmd_set_event2(cb: vk::CommandBuffer, event: vk::Event, _p_dependency: *const vk::DependencyInfo) {
    guard("vkCmdSetEvent2", (), || set_event(cb, event, "vkCmdSetEvent2", true))
}

unsafe extern "system" fn cmd_reset_event(cb: vk::CommandBuffer, event: vk::Event, _stage: vk::PipelineStageFlags) {
    guard("vkCmdResetEvent", (), || set_event(cb, event, "vkCmdResetEvent", false))
}

unsafe extern "system" fn cmd_reset_event2(cb: vk::CommandBuffer, event: vk::Event, _stage: vk::PipelineStageFlags2) {
    guard("vkCmdResetEvent2", (), || set_event(cb, event, "vkCmdResetEvent2", false))
}

/// # Safety
/// `p_events` is null or valid for `count` handles.
unsafe fn wait_events(cb: vk::CommandBuffer, count: u32, p_events: *const vk::Event, command: &str) {
    let Some(c) = command_buffer_from(cb) else { return };
    // SAFETY: caller contract.
    let handles = unsafe { util::slice(p_events, count) };
    let mut events = Vec::with_capacity(handles.len());
    for h in handles {
        match lookup::<Event>(h.as_raw(), command, "pEvents[i]") {
            Some(e) => events.push(e),
            None => return c.violation("VUID-vkCmdWaitEvents-pEvents-parameter", command, "invalid event handle"),
        }
    }
    c.cmd_wait_events(command, events);
}

unsafe extern "system" fn cmd_wait_events(
    cb: vk::CommandBuffer,
    count: u32,
    p_events: *const vk::Event,
    _src: vk::PipelineStageFlags,
    _dst: vk::PipelineStageFlags,
    _memory_count: u32,
    _p_memory: *const vk::MemoryBarrier,
    _buffer_count: u32,
    _p_buffer: *const vk::BufferMemoryBarrier,
    _image_count: u32,
    _p_image: *const vk::ImageMemoryBarrier,
) {
    // SAFETY: valid array per the spec.
    guard("vkCmdWaitEvents", (), || unsafe { wait_events(cb, count, p_events, "vkCmdWaitEvents") })
}

unsafe extern "system" fn cmd_wait_events2(cb: vk::CommandBuffer, count: u32, p_events: *const vk::Event, _p_dependencies: *const vk::DependencyInfo) {
    // SAFETY: valid array per the spec.
    guard("vkCmdWaitEvents2", (), || unsafe { wait_events(cb, count, p_events, "vkCmdWaitEvents2") })
}

// --- queries ----------------------------------------------------------------------------------

fn query_pool(pool: vk::QueryPool, command: &str) -> Option<Arc<QueryPool>> {
    lookup::<QueryPool>(pool.as_raw(), command, "queryPool")
}

fn write_timestamp(cb: vk::CommandBuffer, pool: vk::QueryPool, query: u32, command: &'static str) {
    let Some(c) = command_buffer_from(cb) else { return };
    match query_pool(pool, command) {
        Some(p) => c.cmd_write_timestamp(command, p, query),
        None => c.violation("VUID-vkCmdWriteTimestamp-queryPool-parameter", command, "invalid query pool handle"),
    }
}

unsafe extern "system" fn cmd_write_timestamp(cb: vk::CommandBuffer, _stage: vk::PipelineStageFlags, pool: vk::QueryPool, query: u32) {
    guard("vkCmdWriteTimestamp", (), || write_timestamp(cb, pool, query, "vkCmdWriteTimestamp"))
}

unsafe extern "system" fn cmd_write_timestamp2(cb: vk::CommandBuffer, _stage: vk::PipelineStageFlags2, pool: vk::QueryPool, query: u32) {
    guard("vkCmdWriteTimestamp2", (), || write_timestamp(cb, pool, query, "vkCmdWriteTimestamp2"))
}

unsafe extern "system" fn cmd_reset_query_pool(cb: vk::CommandBuffer, pool: vk::QueryPool, first: u32, count: u32) {
    guard("vkCmdResetQueryPool", (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        match query_pool(pool, "vkCmdResetQueryPool") {
            Some(p) => c.cmd_reset_query_pool(p, first, count),
            None => c.violation("VUID-vkCmdResetQueryPool-queryPool-parameter", "vkCmdResetQueryPool", "invalid query pool handle"),
        }
    })
}

unsafe extern "system" fn cmd_copy_query_pool_results(
    cb: vk::CommandBuffer,
    pool: vk::QueryPool,
    first: u32,
    count: u32,
    dst: vk::Buffer,
    offset: vk::DeviceSize,
    stride: vk::DeviceSize,
    flags: vk::QueryResultFlags,
) {
    const CMD: &str = "vkCmdCopyQueryPoolResults";
    guard(CMD, (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        let (Some(p), Some(d)) = (query_pool(pool, CMD), buffer(dst, CMD, "dstBuffer")) else {
            return c.violation("VUID-vkCmdCopyQueryPoolResults-queryPool-parameter", CMD, "invalid handle");
        };
        c.cmd_copy_query_pool_results(p, first, count, d, offset, stride, flags);
    })
}

fn begin_end_query(cb: vk::CommandBuffer, pool: vk::QueryPool, query: u32, command: &str) {
    let Some(c) = command_buffer_from(cb) else { return };
    if let Some(p) = query_pool(pool, command) {
        c.cmd_begin_end_query(command, p, query);
    }
}

unsafe extern "system" fn cmd_begin_query(cb: vk::CommandBuffer, pool: vk::QueryPool, query: u32, _flags: vk::QueryControlFlags) {
    guard("vkCmdBeginQuery", (), || begin_end_query(cb, pool, query, "vkCmdBeginQuery"))
}

unsafe extern "system" fn cmd_end_query(cb: vk::CommandBuffer, pool: vk::QueryPool, query: u32) {
    guard("vkCmdEndQuery", (), || begin_end_query(cb, pool, query, "vkCmdEndQuery"))
}

// --- secondaries ------------------------------------------------------------------------------

unsafe extern "system" fn cmd_execute_commands(cb: vk::CommandBuffer, count: u32, p_buffers: *const vk::CommandBuffer) {
    guard("vkCmdExecuteCommands", (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        // SAFETY: valid array of count handles per the spec.
        let handles = unsafe { util::slice(p_buffers, count) };
        let mut secondaries = Vec::with_capacity(handles.len());
        for h in handles {
            match command_buffer_from(*h) {
                Some(s) => secondaries.push(s),
                None => return c.violation("VUID-vkCmdExecuteCommands-pCommandBuffers-parameter", "vkCmdExecuteCommands", "invalid command buffer handle"),
            }
        }
        c.cmd_execute_commands(secondaries);
    })
}

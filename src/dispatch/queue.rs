//! Queue submission, sparse binding and idle waits: submit and bind-sparse infos →
//! `runtime::queue::{BatchDesc, BindBatchDesc}`s → one call into the queue (which enqueues to
//! its worker and returns at once). Also the range a sparse buffer gets at creation.
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::command::command_buffer_from;
use super::device::{device_from, queue_from, QueueHandle};
use super::handle::{self, dispatchable};
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::diag;
use crate::runtime::command::CommandBuffer;
use crate::memory::sparse::SPARSE_PAGE;
use crate::memory::{AllocError, Buffer};
use crate::runtime::queue::{BatchDesc, BindBatchDesc, SparseBind};
use crate::runtime::Device;
use crate::runtime::sync::{Fence, Semaphore, SemaphoreKind};
use crate::runtime::Queue;

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkQueueSubmit => queue_submit),
        imp!(PFN_vkQueueSubmit2 => queue_submit2),
        imp!(PFN_vkQueueBindSparse => queue_bind_sparse),
        imp!(PFN_vkQueueWaitIdle => queue_wait_idle),
        imp!(PFN_vkDeviceWaitIdle => device_wait_idle),
    ]
}

fn semaphore(h: vk::Semaphore, command: &str) -> Option<Arc<Semaphore>> {
    let s = handle::get::<Semaphore>(h.as_raw());
    if s.is_none() {
        diag::report(diag::Level::Error, command, &format!("semaphore {:#x} is not a valid handle; ignored", h.as_raw()));
    }
    s
}

fn command_buffers(handles: impl Iterator<Item = vk::CommandBuffer>, command: &str) -> Vec<Arc<CommandBuffer>> {
    handles
        .filter_map(|h| {
            let c = command_buffer_from(h);
            if c.is_none() {
                diag::report(diag::Level::Error, command, "a command buffer handle is not valid; left out");
            }
            c
        })
        .collect()
}

fn fence(h: vk::Fence, command: &str) -> Option<Arc<Fence>> {
    if h == vk::Fence::null() {
        return None;
    }
    let f = handle::get::<Fence>(h.as_raw());
    if f.is_none() {
        diag::report(diag::Level::Error, command, "fence is not a valid handle; ignored");
    }
    f
}

/// Pair semaphores with their timeline values (binary semaphores ignore theirs).
fn with_values(sems: &[vk::Semaphore], values: Option<&[u64]>, command: &str, vuid: &str) -> Vec<(Arc<Semaphore>, u64)> {
    let mut out = Vec::with_capacity(sems.len());
    for (i, h) in sems.iter().enumerate() {
        let Some(s) = semaphore(*h, command) else { continue };
        let v = values.and_then(|v| v.get(i).copied());
        if s.kind == SemaphoreKind::Timeline && v.is_none() {
            diag::vuid(vuid, command, &format!("timeline semaphore #{i} has no value (VkTimelineSemaphoreSubmitInfo missing or too short); ignored"));
            continue;
        }
        out.push((s, v.unwrap_or(0)));
    }
    out
}

/// The wait and signal value arrays of a VkTimelineSemaphoreSubmitInfo (vkQueueSubmit and
/// vkQueueBindSparse both take one).
///
/// # Safety
/// `tl`, when present, is a valid VkTimelineSemaphoreSubmitInfo whose arrays hold their counts.
unsafe fn timeline_values<'a>(tl: Option<&'a vk::TimelineSemaphoreSubmitInfo<'a>>) -> (Option<&'a [u64]>, Option<&'a [u64]>) {
    match tl {
        // SAFETY: the caller's promise.
        Some(t) => unsafe {
            (
                Some(util::slice(t.p_wait_semaphore_values, t.wait_semaphore_value_count)),
                Some(util::slice(t.p_signal_semaphore_values, t.signal_semaphore_value_count)),
            )
        },
        None => (None, None),
    }
}

unsafe extern "system" fn queue_submit(queue: vk::Queue, count: u32, p_submits: *const vk::SubmitInfo, fence_h: vk::Fence) -> vk::Result {
    const CMD: &str = "vkQueueSubmit";
    guard(CMD, vk::Result::ERROR_DEVICE_LOST, || {
        let Some(q) = queue_from(queue) else { return vk::Result::ERROR_DEVICE_LOST };
        // SAFETY: valid array of count submit infos per the spec.
        let submits = unsafe { util::slice(p_submits, count) };
        let mut batches = Vec::with_capacity(submits.len());
        for s in submits {
            // SAFETY: valid pNext chain and arrays per the spec.
            let (tl, waits, cbs, signals) = unsafe {
                (
                    util::find_in::<vk::TimelineSemaphoreSubmitInfo>(s.p_next, vk::StructureType::TIMELINE_SEMAPHORE_SUBMIT_INFO),
                    util::slice(s.p_wait_semaphores, s.wait_semaphore_count),
                    util::slice(s.p_command_buffers, s.command_buffer_count),
                    util::slice(s.p_signal_semaphores, s.signal_semaphore_count),
                )
            };
            // SAFETY: `tl` is a valid VkTimelineSemaphoreSubmitInfo from the application's chain.
            let (wait_values, signal_values) = unsafe { timeline_values(tl) };
            batches.push(BatchDesc {
                waits: with_values(waits, wait_values, CMD, "VUID-VkSubmitInfo-pWaitSemaphores-03239"),
                command_buffers: command_buffers(cbs.iter().copied(), CMD),
                signals: with_values(signals, signal_values, CMD, "VUID-VkSubmitInfo-pNext-03241"),
            });
        }
        q.submit(CMD, batches, fence(fence_h, CMD))
    })
}

unsafe extern "system" fn queue_submit2(queue: vk::Queue, count: u32, p_submits: *const vk::SubmitInfo2, fence_h: vk::Fence) -> vk::Result {
    const CMD: &str = "vkQueueSubmit2";
    guard(CMD, vk::Result::ERROR_DEVICE_LOST, || {
        let Some(q) = queue_from(queue) else { return vk::Result::ERROR_DEVICE_LOST };
        // SAFETY: valid array of count submit infos per the spec.
        let submits = unsafe { util::slice(p_submits, count) };
        let mut batches = Vec::with_capacity(submits.len());
        for s in submits {
            // SAFETY: valid arrays per the spec.
            let (waits, cbs, signals) = unsafe {
                (
                    util::slice(s.p_wait_semaphore_infos, s.wait_semaphore_info_count),
                    util::slice(s.p_command_buffer_infos, s.command_buffer_info_count),
                    util::slice(s.p_signal_semaphore_infos, s.signal_semaphore_info_count),
                )
            };
            let lower = |infos: &[vk::SemaphoreSubmitInfo]| -> Vec<(Arc<Semaphore>, u64)> {
                infos.iter().filter_map(|i| semaphore(i.semaphore, CMD).map(|s| (s, i.value))).collect()
            };
            batches.push(BatchDesc {
                waits: lower(waits),
                command_buffers: command_buffers(cbs.iter().map(|c| c.command_buffer), CMD),
                signals: lower(signals),
            });
        }
        q.submit(CMD, batches, fence(fence_h, CMD))
    })
}

unsafe extern "system" fn queue_wait_idle(queue: vk::Queue) -> vk::Result {
    guard("vkQueueWaitIdle", vk::Result::ERROR_DEVICE_LOST, || match queue_from(queue) {
        Some(q) => q.wait_idle("vkQueueWaitIdle"),
        None => vk::Result::ERROR_DEVICE_LOST,
    })
}

unsafe extern "system" fn device_wait_idle(device: vk::Device) -> vk::Result {
    guard("vkDeviceWaitIdle", vk::Result::ERROR_DEVICE_LOST, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_DEVICE_LOST };
        let mut result = vk::Result::SUCCESS;
        for (_, _, h) in dev.queues.get().map(|v| v.as_slice()).unwrap_or(&[]) {
            // SAFETY: queue handles live as long as their device.
            if let Some(q) = unsafe { dispatchable::<Queue>(*h as QueueHandle) } {
                let r = q.wait_idle("vkDeviceWaitIdle");
                if r != vk::Result::SUCCESS {
                    result = r;
                }
            }
        }
        if dev.is_lost() {
            result = vk::Result::ERROR_DEVICE_LOST;
        }
        result
    })
}

/// vkCreateBuffer with VK_BUFFER_CREATE_SPARSE_BINDING_BIT: the buffer is bound once, to a
/// range of its own (every page unbound), registered in the address space like an allocation
/// so device addresses into it resolve as any buffer's do.
pub(super) fn reserve_sparse_range(dev: &Device, buffer: &Arc<Buffer>, command: &str) -> Result<(), vk::Result> {
    let range = dev.memory.reserve_sparse(buffer.size).map_err(|e| match e {
        AllocError::OutOfHostMemory => vk::Result::ERROR_OUT_OF_HOST_MEMORY,
        _ => vk::Result::ERROR_OUT_OF_DEVICE_MEMORY,
    })?;
    if buffer.capture_address != 0 {
        diag::report(diag::Level::Warn, command, "opaque capture addresses are not honoured for sparse buffers; the buffer gets a new address");
    }
    buffer.bind(range.clone(), 0).map_err(|_| {
        dev.memory.free(&range);
        vk::Result::ERROR_OUT_OF_HOST_MEMORY
    })
}

unsafe extern "system" fn queue_bind_sparse(queue: vk::Queue, count: u32, p_bind_info: *const vk::BindSparseInfo, fence_h: vk::Fence) -> vk::Result {
    const CMD: &str = "vkQueueBindSparse";
    guard(CMD, vk::Result::ERROR_DEVICE_LOST, || {
        let Some(q) = queue_from(queue) else { return vk::Result::ERROR_DEVICE_LOST };
        // SAFETY: valid array of count bind infos per the spec.
        let infos = unsafe { util::slice(p_bind_info, count) };
        let mut batches = Vec::with_capacity(infos.len());
        for info in infos {
            // SAFETY: valid pNext chain and arrays per the spec.
            let (tl, waits, signals, buffer_binds) = unsafe {
                (
                    util::find_in::<vk::TimelineSemaphoreSubmitInfo>(info.p_next, vk::StructureType::TIMELINE_SEMAPHORE_SUBMIT_INFO),
                    util::slice(info.p_wait_semaphores, info.wait_semaphore_count),
                    util::slice(info.p_signal_semaphores, info.signal_semaphore_count),
                    util::slice(info.p_buffer_binds, info.buffer_bind_count),
                )
            };
            // SAFETY: `tl` is a valid VkTimelineSemaphoreSubmitInfo from the application's chain.
            let (wait_values, signal_values) = unsafe { timeline_values(tl) };
            if info.image_opaque_bind_count > 0 || info.image_bind_count > 0 {
                diag::report(
                    diag::Level::Error,
                    CMD,
                    "sparse images are not supported (sparseResidencyImage2D/3D and sparse image creation are off): the image binds are refused; the buffer binds, waits and signals of the batch go ahead",
                );
            }
            let mut binds = Vec::new();
            for b in buffer_binds {
                // SAFETY: valid array per the spec.
                let list = unsafe { util::slice(b.p_binds, b.bind_count) };
                lower_buffer_binds(b.buffer, list, &mut binds);
            }
            batches.push(BindBatchDesc {
                waits: with_values(waits, wait_values, CMD, "VUID-VkBindSparseInfo-pWaitSemaphores-03246"),
                binds,
                signals: with_values(signals, signal_values, CMD, "VUID-VkBindSparseInfo-pNext-03248"),
            });
        }
        q.bind_sparse(CMD, batches, fence(fence_h, CMD))
    })
}

/// Check the binds of one VkSparseBufferMemoryBindInfo and lower the valid ones; an invalid
/// bind is reported by VUID and left out (the rest of the batch goes ahead, so its semaphores
/// and fence still signal).
fn lower_buffer_binds(buffer: vk::Buffer, list: &[vk::SparseMemoryBind], out: &mut Vec<SparseBind>) {
    const CMD: &str = "vkQueueBindSparse";
    let Some(b) = super::memory::buffer_from(buffer) else {
        diag::vuid("VUID-VkSparseBufferMemoryBindInfo-buffer-parameter", CMD, "buffer is not a live VkBuffer; its binds are left out");
        return;
    };
    if !b.flags.contains(vk::BufferCreateFlags::SPARSE_BINDING) || b.memory().is_none_or(|(m, _)| !m.is_sparse()) {
        diag::report(diag::Level::Error, CMD, "the buffer was not created with VK_BUFFER_CREATE_SPARSE_BINDING_BIT; its binds are left out");
        return;
    }
    let resource_size = super::memory::requirements(&b).size;
    for (i, bind) in list.iter().enumerate() {
        if let Some(lowered) = check_bind(&b, resource_size, i, bind) {
            out.push(lowered);
        }
    }
}

/// The valid-usage checks of one VkSparseMemoryBind of a buffer (`resource_size`: its size
/// rounded up to the page, as its memory requirements say).
fn check_bind(buffer: &Arc<Buffer>, resource_size: u64, i: usize, bind: &vk::SparseMemoryBind) -> Option<SparseBind> {
    const CMD: &str = "vkQueueBindSparse";
    let refuse = |vuid: &str, why: String| {
        diag::vuid(vuid, CMD, &format!("bind #{i} (resourceOffset {}, size {}): {why}; left out", bind.resource_offset, bind.size));
        None
    };
    if bind.size == 0 {
        return refuse("VUID-VkSparseMemoryBind-size-01098", "size is 0".into());
    }
    let aligned = |v: u64| v.is_multiple_of(SPARSE_PAGE);
    if !aligned(bind.resource_offset) || !aligned(bind.size) || !aligned(bind.memory_offset) {
        return refuse(
            "VUID-VkSparseMemoryBind-resourceOffset-09491",
            format!("resourceOffset, memoryOffset ({}) and size must be multiples of the sparse page, {SPARSE_PAGE} bytes", bind.memory_offset),
        );
    }
    if bind.resource_offset >= resource_size {
        return refuse("VUID-VkSparseMemoryBind-resourceOffset-01099", format!("resourceOffset is not less than the buffer's size {resource_size}"));
    }
    if bind.size > resource_size - bind.resource_offset {
        return refuse("VUID-VkSparseMemoryBind-size-01100", format!("the range runs past the buffer's size {resource_size}"));
    }
    let memory = if bind.memory == vk::DeviceMemory::null() {
        None
    } else {
        let Some(m) = super::memory::memory_from(bind.memory) else {
            return refuse("VUID-VkSparseMemoryBind-memory-parameter", "memory is not a live VkDeviceMemory".into());
        };
        if !m.is_shareable() {
            return refuse(
                "VUID-VkSparseMemoryBind-memory-01096",
                "the memory is not of the sparse memory type, the only one in the buffer's memoryTypeBits".into(),
            );
        }
        let size = m.size;
        if bind.memory_offset >= size {
            return refuse("VUID-VkSparseMemoryBind-memoryOffset-01101", format!("memoryOffset is not less than the memory size {size}"));
        }
        if bind.size > size - bind.memory_offset {
            return refuse("VUID-VkSparseMemoryBind-size-01102", format!("the range runs past the memory size {size} after memoryOffset"));
        }
        Some((m, bind.memory_offset))
    };
    Some(SparseBind { buffer: buffer.clone(), offset: bind.resource_offset, size: bind.size, memory })
}

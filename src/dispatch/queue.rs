//! Queue submission and idle waits: submit infos → `runtime::queue::BatchDesc`s → one call
//! into the queue (which enqueues to its worker and returns at once).
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
use crate::runtime::queue::BatchDesc;
use crate::runtime::sync::{Fence, Semaphore, SemaphoreKind};
use crate::runtime::Queue;

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkQueueSubmit => queue_submit),
        imp!(PFN_vkQueueSubmit2 => queue_submit2),
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
            // SAFETY: the value arrays of a valid VkTimelineSemaphoreSubmitInfo.
            let (wait_values, signal_values) = unsafe {
                match tl {
                    Some(t) => (
                        Some(util::slice(t.p_wait_semaphore_values, t.wait_semaphore_value_count)),
                        Some(util::slice(t.p_signal_semaphore_values, t.signal_semaphore_value_count)),
                    ),
                    None => (None, None),
                }
            };
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

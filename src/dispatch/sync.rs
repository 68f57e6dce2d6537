//! Fences, semaphores (binary and timeline) and events: handles → `runtime::sync`.
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::device::device_from;
use super::handle;
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::diag;
use crate::runtime::stall;
use crate::runtime::sync::{self, Deadline, Event, Fence, Semaphore, SemaphoreKind, WaitOutcome};
use crate::runtime::Device;

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCreateFence => create_fence),
        imp!(PFN_vkDestroyFence => destroy_fence),
        imp!(PFN_vkGetFenceStatus => get_fence_status),
        imp!(PFN_vkResetFences => reset_fences),
        imp!(PFN_vkWaitForFences => wait_for_fences),
        imp!(PFN_vkCreateSemaphore => create_semaphore),
        imp!(PFN_vkDestroySemaphore => destroy_semaphore),
        imp!(PFN_vkGetSemaphoreCounterValue => get_semaphore_counter_value),
        imp!(PFN_vkWaitSemaphores => wait_semaphores),
        imp!(PFN_vkSignalSemaphore => signal_semaphore),
        imp!(PFN_vkCreateEvent => create_event),
        imp!(PFN_vkDestroyEvent => destroy_event),
        imp!(PFN_vkGetEventStatus => get_event_status),
        imp!(PFN_vkSetEvent => set_event),
        imp!(PFN_vkResetEvent => reset_event),
    ]
}

/// The result of a host wait. A stall (`runtime::stall`: nothing pending can end the wait) is
/// reported with `what` and answered as a timeout would be, or device lost in strict mode.
fn wait_result(dev: &Device, command: &str, outcome: WaitOutcome, what: impl FnOnce() -> String) -> vk::Result {
    if dev.is_lost() {
        return vk::Result::ERROR_DEVICE_LOST;
    }
    match outcome {
        WaitOutcome::Ready => vk::Result::SUCCESS,
        WaitOutcome::TimedOut => vk::Result::TIMEOUT,
        WaitOutcome::Cancelled => vk::Result::ERROR_DEVICE_LOST,
        WaitOutcome::Stalled if stall::report(dev, command, &what()) => vk::Result::ERROR_DEVICE_LOST,
        WaitOutcome::Stalled => vk::Result::TIMEOUT,
    }
}

fn get<T: Send + Sync + 'static>(raw: u64, command: &str, what: &str) -> Option<Arc<T>> {
    let r = handle::get::<T>(raw);
    if r.is_none() {
        diag::report(diag::Level::Error, command, &format!("{what} {raw:#x} is not a valid handle"));
    }
    r
}

// --- fences -----------------------------------------------------------------------------------

unsafe extern "system" fn create_fence(
    device: vk::Device,
    p_info: *const vk::FenceCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_fence: *mut vk::Fence,
) -> vk::Result {
    guard("vkCreateFence", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() || p_info.is_null() || p_fence.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid create info per the spec.
        let info = unsafe { &*p_info };
        let f = Arc::new(Fence::new(info.flags.contains(vk::FenceCreateFlags::SIGNALED)));
        // SAFETY: checked non-null.
        unsafe { *p_fence = vk::Fence::from_raw(handle::register(f)) };
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn destroy_fence(device: vk::Device, fence: vk::Fence, _p_allocator: *const vk::AllocationCallbacks) {
    guard("vkDestroyFence", (), || {
        if device_from(device).is_none() || fence == vk::Fence::null() {
            return;
        }
        if let Some(f) = handle::unregister::<Fence>(fence.as_raw()) {
            if f.is_pending() {
                diag::vuid("VUID-vkDestroyFence-fence-01120", "vkDestroyFence", "the fence is still associated with an unfinished submission");
            }
        }
    })
}

unsafe extern "system" fn get_fence_status(device: vk::Device, fence: vk::Fence) -> vk::Result {
    guard("vkGetFenceStatus", vk::Result::ERROR_DEVICE_LOST, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_DEVICE_LOST };
        let Some(f) = get::<Fence>(fence.as_raw(), "vkGetFenceStatus", "fence") else { return vk::Result::ERROR_DEVICE_LOST };
        if dev.is_lost() {
            vk::Result::ERROR_DEVICE_LOST
        } else if f.is_signalled() {
            vk::Result::SUCCESS
        } else {
            vk::Result::NOT_READY
        }
    })
}

unsafe extern "system" fn reset_fences(device: vk::Device, count: u32, p_fences: *const vk::Fence) -> vk::Result {
    guard("vkResetFences", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return vk::Result::ERROR_OUT_OF_HOST_MEMORY;
        }
        // SAFETY: valid array of count fences per the spec.
        for h in unsafe { util::slice(p_fences, count) } {
            if let Some(f) = get::<Fence>(h.as_raw(), "vkResetFences", "fence") {
                if f.is_pending() {
                    diag::vuid("VUID-vkResetFences-pFences-01123", "vkResetFences", "the fence is associated with an unfinished submission");
                }
                f.reset();
            }
        }
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn wait_for_fences(device: vk::Device, count: u32, p_fences: *const vk::Fence, wait_all: vk::Bool32, timeout: u64) -> vk::Result {
    guard("vkWaitForFences", vk::Result::ERROR_DEVICE_LOST, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_DEVICE_LOST };
        // SAFETY: valid array of count fences per the spec.
        let fences: Vec<(u64, Arc<Fence>)> = unsafe { util::slice(p_fences, count) }
            .iter()
            .filter_map(|h| get::<Fence>(h.as_raw(), "vkWaitForFences", "fence").map(|f| (h.as_raw(), f)))
            .collect();
        let objects: Vec<Arc<Fence>> = fences.iter().map(|(_, f)| f.clone()).collect();
        let outcome = if objects.is_empty() { WaitOutcome::Ready } else { sync::wait_fences(&objects, wait_all != 0, Deadline::from_timeout_ns(timeout)) };
        wait_result(&dev, "vkWaitForFences", outcome, || {
            let unsignalled: Vec<String> = fences
                .iter()
                .filter(|(_, f)| !f.is_signalled())
                .map(|(h, f)| format!("{h:#x} ({})", if f.is_pending() { "its submission is blocked" } else { "never submitted" }))
                .collect();
            format!("fences not signalled: {}", unsignalled.join(", "))
        })
    })
}

// --- semaphores -------------------------------------------------------------------------------

unsafe extern "system" fn create_semaphore(
    device: vk::Device,
    p_info: *const vk::SemaphoreCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_semaphore: *mut vk::Semaphore,
) -> vk::Result {
    guard("vkCreateSemaphore", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_INITIALIZATION_FAILED };
        if p_info.is_null() || p_semaphore.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid create info and pNext chain per the spec.
        let info = unsafe { &*p_info };
        // SAFETY: as above.
        let ty = unsafe { util::find_in::<vk::SemaphoreTypeCreateInfo>(info.p_next, vk::StructureType::SEMAPHORE_TYPE_CREATE_INFO) };
        let (kind, initial) = match ty {
            Some(t) if t.semaphore_type == vk::SemaphoreType::TIMELINE => {
                if !dev.features.timeline_semaphore {
                    diag::vuid("VUID-VkSemaphoreTypeCreateInfo-timelineSemaphore-03252", "vkCreateSemaphore", "the timelineSemaphore feature is not enabled");
                }
                (SemaphoreKind::Timeline, t.initial_value)
            }
            Some(t) => {
                if t.initial_value != 0 {
                    diag::vuid("VUID-VkSemaphoreTypeCreateInfo-semaphoreType-03279", "vkCreateSemaphore", "a binary semaphore's initialValue must be 0");
                }
                (SemaphoreKind::Binary, 0)
            }
            None => (SemaphoreKind::Binary, 0),
        };
        let s = Arc::new(Semaphore::new(kind, initial));
        // SAFETY: checked non-null.
        unsafe { *p_semaphore = vk::Semaphore::from_raw(handle::register(s)) };
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn destroy_semaphore(device: vk::Device, semaphore: vk::Semaphore, _p_allocator: *const vk::AllocationCallbacks) {
    guard("vkDestroySemaphore", (), || {
        if device_from(device).is_some() && semaphore != vk::Semaphore::null() {
            // Queued waits and signals hold their own reference.
            handle::unregister::<Semaphore>(semaphore.as_raw());
        }
    })
}

unsafe extern "system" fn get_semaphore_counter_value(device: vk::Device, semaphore: vk::Semaphore, p_value: *mut u64) -> vk::Result {
    const CMD: &str = "vkGetSemaphoreCounterValue";
    guard(CMD, vk::Result::ERROR_DEVICE_LOST, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_DEVICE_LOST };
        let Some(s) = get::<Semaphore>(semaphore.as_raw(), CMD, "semaphore") else { return vk::Result::ERROR_DEVICE_LOST };
        if s.kind != SemaphoreKind::Timeline {
            diag::vuid("VUID-vkGetSemaphoreCounterValue-semaphore-03255", CMD, "semaphore is not a timeline semaphore");
        }
        // SAFETY: valid output pointer per the spec.
        unsafe { util::out(p_value, s.value()) };
        if dev.is_lost() {
            vk::Result::ERROR_DEVICE_LOST
        } else {
            vk::Result::SUCCESS
        }
    })
}

unsafe extern "system" fn wait_semaphores(device: vk::Device, p_info: *const vk::SemaphoreWaitInfo, timeout: u64) -> vk::Result {
    const CMD: &str = "vkWaitSemaphores";
    guard(CMD, vk::Result::ERROR_DEVICE_LOST, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_DEVICE_LOST };
        if p_info.is_null() {
            return vk::Result::ERROR_DEVICE_LOST;
        }
        // SAFETY: valid wait info per the spec.
        let info = unsafe { &*p_info };
        // SAFETY: valid arrays of semaphoreCount elements per the spec.
        let (sems, values) = unsafe { (util::slice(info.p_semaphores, info.semaphore_count), util::slice(info.p_values, info.semaphore_count)) };
        let mut waits = Vec::with_capacity(sems.len());
        let mut handles = Vec::with_capacity(sems.len());
        for (h, v) in sems.iter().zip(values) {
            let Some(s) = get::<Semaphore>(h.as_raw(), CMD, "semaphore") else { continue };
            if s.kind != SemaphoreKind::Timeline {
                diag::vuid("VUID-VkSemaphoreWaitInfo-pSemaphores-03256", CMD, "every semaphore must be a timeline semaphore; a binary one is ignored");
                continue;
            }
            waits.push((s, *v));
            handles.push(h.as_raw());
        }
        let all = !info.flags.contains(vk::SemaphoreWaitFlags::ANY);
        let outcome = if waits.is_empty() { WaitOutcome::Ready } else { sync::wait_semaphores(&waits, all, Deadline::from_timeout_ns(timeout)) };
        wait_result(&dev, CMD, outcome, || {
            let short: Vec<String> = handles
                .iter()
                .zip(&waits)
                .filter(|(_, (s, v))| !s.reached(*v))
                .map(|(h, (s, v))| format!("{h:#x} at {} waiting for {v}", s.value()))
                .collect();
            format!("timeline semaphores short of their values: {}", short.join(", "))
        })
    })
}

unsafe extern "system" fn signal_semaphore(device: vk::Device, p_info: *const vk::SemaphoreSignalInfo) -> vk::Result {
    const CMD: &str = "vkSignalSemaphore";
    guard(CMD, vk::Result::ERROR_DEVICE_LOST, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_DEVICE_LOST };
        if p_info.is_null() {
            return vk::Result::ERROR_DEVICE_LOST;
        }
        // SAFETY: valid signal info per the spec.
        let info = unsafe { &*p_info };
        let Some(s) = get::<Semaphore>(info.semaphore.as_raw(), CMD, "semaphore") else { return vk::Result::ERROR_DEVICE_LOST };
        if s.kind != SemaphoreKind::Timeline {
            diag::vuid("VUID-VkSemaphoreSignalInfo-semaphore-03257", CMD, "semaphore is not a timeline semaphore; not signalled");
            return vk::Result::SUCCESS;
        }
        if info.value <= s.value() {
            diag::vuid(
                "VUID-VkSemaphoreSignalInfo-value-03258",
                CMD,
                &format!("value {} is not greater than the current value {}", info.value, s.value()),
            );
        }
        s.signal(info.value);
        if dev.is_lost() {
            vk::Result::ERROR_DEVICE_LOST
        } else {
            vk::Result::SUCCESS
        }
    })
}

// --- events -----------------------------------------------------------------------------------

unsafe extern "system" fn create_event(
    device: vk::Device,
    p_info: *const vk::EventCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_event: *mut vk::Event,
) -> vk::Result {
    guard("vkCreateEvent", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() || p_info.is_null() || p_event.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid create info per the spec.
        let info = unsafe { &*p_info };
        let e = Arc::new(Event::new(info.flags));
        // SAFETY: checked non-null.
        unsafe { *p_event = vk::Event::from_raw(handle::register(e)) };
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn destroy_event(device: vk::Device, event: vk::Event, _p_allocator: *const vk::AllocationCallbacks) {
    guard("vkDestroyEvent", (), || {
        if device_from(device).is_some() && event != vk::Event::null() {
            handle::unregister::<Event>(event.as_raw());
        }
    })
}

unsafe extern "system" fn get_event_status(device: vk::Device, event: vk::Event) -> vk::Result {
    guard("vkGetEventStatus", vk::Result::ERROR_DEVICE_LOST, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_DEVICE_LOST };
        let Some(e) = get::<Event>(event.as_raw(), "vkGetEventStatus", "event") else { return vk::Result::ERROR_DEVICE_LOST };
        if e.device_only() {
            diag::vuid("VUID-vkGetEventStatus-event-03940", "vkGetEventStatus", "the event was created with DEVICE_ONLY");
        }
        if dev.is_lost() {
            vk::Result::ERROR_DEVICE_LOST
        } else if e.is_set() {
            vk::Result::EVENT_SET
        } else {
            vk::Result::EVENT_RESET
        }
    })
}

fn host_set_event(device: vk::Device, event: vk::Event, set: bool) -> vk::Result {
    let command = if set { "vkSetEvent" } else { "vkResetEvent" };
    if device_from(device).is_none() {
        return vk::Result::ERROR_OUT_OF_HOST_MEMORY;
    }
    let Some(e) = get::<Event>(event.as_raw(), command, "event") else { return vk::Result::SUCCESS };
    if e.device_only() {
        let vuid = if set { "VUID-vkSetEvent-event-03941" } else { "VUID-vkResetEvent-event-03823" };
        diag::vuid(vuid, command, "the event was created with DEVICE_ONLY");
    }
    if set {
        e.set();
    } else {
        e.reset();
    }
    vk::Result::SUCCESS
}

unsafe extern "system" fn set_event(device: vk::Device, event: vk::Event) -> vk::Result {
    guard("vkSetEvent", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || host_set_event(device, event, true))
}

unsafe extern "system" fn reset_event(device: vk::Device, event: vk::Event) -> vk::Result {
    guard("vkResetEvent", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || host_set_event(device, event, false))
}

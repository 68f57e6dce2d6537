//! Synchronisation objects: fences, semaphores (binary and timeline) and events, and the one
//! wait/notify hub every blocking wait in the driver goes through.
//!
//! State lives in atomics; a change is published by [`notify`] after the store. A waiter holds
//! the hub's lock while it checks its condition and while it goes to sleep, so a change made
//! between the check and the sleep cannot be missed (the notifier needs the same lock). Host
//! waits (vkWaitForFences, vkWaitSemaphores, vkQueueWaitIdle, WAIT query results) and queue
//! workers (semaphore waits, vkCmdWaitEvents) share it, so "wait for any of several objects"
//! is one predicate, and cancelling a blocked worker at device destruction is one flag.
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use ash::vk;

struct Hub {
    lock: Mutex<()>,
    changed: Condvar,
}

fn hub() -> &'static Hub {
    static HUB: Hub = Hub { lock: Mutex::new(()), changed: Condvar::new() };
    &HUB
}

fn hub_lock() -> MutexGuard<'static, ()> {
    hub().lock.lock().unwrap_or_else(|e| e.into_inner())
}

/// Publish a state change (call after the atomic store): wakes every waiter to re-check.
pub fn notify() {
    super::stall::advance();
    let _g = hub_lock();
    hub().changed.notify_all();
}

/// When a wait gives up.
#[derive(Clone, Copy, Debug)]
pub enum Deadline {
    /// Check once (timeout 0).
    Now,
    At(Instant),
    Never,
}

impl Deadline {
    /// From a Vulkan timeout in nanoseconds (0: poll; UINT64_MAX or too far to represent: never).
    pub fn from_timeout_ns(ns: u64) -> Deadline {
        match ns {
            0 => Deadline::Now,
            u64::MAX => Deadline::Never,
            ns => Instant::now().checked_add(Duration::from_nanos(ns)).map_or(Deadline::Never, Deadline::At),
        }
    }
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum WaitOutcome {
    Ready,
    TimedOut,
    /// The `cancel` flag was raised (device destruction stops blocked queue workers).
    Cancelled,
    /// Nothing can complete the wait (`stall`); only from [`wait_or_stall`].
    Stalled,
}

/// Block until `ready()` holds, the deadline passes or `cancel` is raised.
/// `ready` must only read state (atomics, short-lived locks); it runs with the hub's lock held.
pub fn wait_until(deadline: Deadline, cancel: Option<&AtomicBool>, ready: impl FnMut() -> bool) -> WaitOutcome {
    wait_inner(deadline, cancel, None, ready)
}

/// [`wait_until`] for a host wait that must not outlast a stall: also returns
/// [`WaitOutcome::Stalled`] once nothing in the driver can make `ready()` hold (`stall`).
pub fn wait_or_stall(deadline: Deadline, cancel: Option<&AtomicBool>, ready: impl FnMut() -> bool) -> WaitOutcome {
    wait_inner(deadline, cancel, Some(super::stall::Watch::new()), ready)
}

fn wait_inner(deadline: Deadline, cancel: Option<&AtomicBool>, mut watch: Option<super::stall::Watch>, mut ready: impl FnMut() -> bool) -> WaitOutcome {
    let mut guard = hub_lock();
    loop {
        if ready() {
            return WaitOutcome::Ready;
        }
        if cancel.is_some_and(|c| c.load(Ordering::Acquire)) {
            return WaitOutcome::Cancelled;
        }
        if watch.as_mut().is_some_and(|w| w.stalled()) {
            return WaitOutcome::Stalled;
        }
        // A stall-aware wait wakes up now and then to look at the driver's activity.
        let poll = watch.as_ref().and_then(|w| w.poll_interval());
        let until = match (deadline, poll) {
            (Deadline::Now, _) => return WaitOutcome::TimedOut,
            (Deadline::Never, None) => None,
            (Deadline::Never, Some(p)) => Some((Instant::now() + p, false)),
            (Deadline::At(t), None) => Some((t, true)),
            (Deadline::At(t), Some(p)) => {
                let wake = Instant::now() + p;
                Some(if wake < t { (wake, false) } else { (t, true) })
            }
        };
        guard = match until {
            None => hub().changed.wait(guard).unwrap_or_else(|e| e.into_inner()),
            Some((t, is_deadline)) => {
                let now = Instant::now();
                if now >= t {
                    if is_deadline {
                        return WaitOutcome::TimedOut;
                    }
                    continue;
                }
                hub().changed.wait_timeout(guard, t - now).unwrap_or_else(|e| e.into_inner()).0
            }
        };
    }
}

/// One `VkFence`.
pub struct Fence {
    signalled: AtomicBool,
    /// Submissions that will signal this fence and have not yet (VUID checks on reuse).
    pending: AtomicU64,
}

impl Fence {
    pub fn new(signalled: bool) -> Fence {
        Fence { signalled: AtomicBool::new(signalled), pending: AtomicU64::new(0) }
    }

    pub fn is_signalled(&self) -> bool {
        self.signalled.load(Ordering::Acquire)
    }

    pub fn is_pending(&self) -> bool {
        self.pending.load(Ordering::Acquire) > 0
    }

    /// A queue operation will signal this fence.
    pub fn mark_pending(&self) {
        self.pending.fetch_add(1, Ordering::AcqRel);
    }

    /// The queue signals the fence (its submission completed).
    pub fn signal_from_queue(&self) {
        self.signalled.store(true, Ordering::Release);
        self.pending.fetch_sub(1, Ordering::AcqRel);
        notify();
    }

    pub fn reset(&self) {
        self.signalled.store(false, Ordering::Release);
    }
}

/// Wait for fences: all of them or any of them.
pub fn wait_fences(fences: &[std::sync::Arc<Fence>], all: bool, deadline: Deadline) -> WaitOutcome {
    wait_or_stall(deadline, None, || {
        if all {
            fences.iter().all(|f| f.is_signalled())
        } else {
            fences.iter().any(|f| f.is_signalled())
        }
    })
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum SemaphoreKind {
    Binary,
    Timeline,
}

/// One `VkSemaphore`. A binary semaphore's payload is 0 (unsignalled) or 1 (signalled); a
/// timeline semaphore's is its counter, which only grows.
pub struct Semaphore {
    pub kind: SemaphoreKind,
    value: AtomicU64,
}

impl Semaphore {
    pub fn new(kind: SemaphoreKind, initial: u64) -> Semaphore {
        let initial = if kind == SemaphoreKind::Binary { 0 } else { initial };
        Semaphore { kind, value: AtomicU64::new(initial) }
    }

    /// Current counter (timeline) or 0/1 (binary).
    pub fn value(&self) -> u64 {
        self.value.load(Ordering::Acquire)
    }

    /// Signal: binary → signalled; timeline → counter raised to `value` (never lowered).
    pub fn signal(&self, value: u64) {
        match self.kind {
            SemaphoreKind::Binary => self.value.store(1, Ordering::Release),
            SemaphoreKind::Timeline => {
                self.value.fetch_max(value, Ordering::AcqRel);
            }
        }
        notify();
    }

    /// Whether a wait for `value` would be satisfied now (timeline: counter ≥ value).
    pub fn reached(&self, value: u64) -> bool {
        match self.kind {
            SemaphoreKind::Binary => self.value() == 1,
            SemaphoreKind::Timeline => self.value() >= value,
        }
    }

    /// A queue's wait operation: binary waits consume the signal, timeline waits leave it.
    /// Runs inside the hub lock (from `wait_until`), so two binary waiters cannot both consume.
    pub fn try_consume(&self, value: u64) -> bool {
        match self.kind {
            SemaphoreKind::Binary => self.value.compare_exchange(1, 0, Ordering::AcqRel, Ordering::Acquire).is_ok(),
            SemaphoreKind::Timeline => self.value() >= value,
        }
    }
}

/// Host wait on timeline semaphores (vkWaitSemaphores): all or any reach their values.
pub fn wait_semaphores(waits: &[(std::sync::Arc<Semaphore>, u64)], all: bool, deadline: Deadline) -> WaitOutcome {
    wait_or_stall(deadline, None, || {
        if all {
            waits.iter().all(|(s, v)| s.reached(*v))
        } else {
            waits.iter().any(|(s, v)| s.reached(*v))
        }
    })
}

/// One `VkEvent`.
pub struct Event {
    pub flags: vk::EventCreateFlags,
    set: AtomicBool,
}

impl Event {
    pub fn new(flags: vk::EventCreateFlags) -> Event {
        Event { flags, set: AtomicBool::new(false) }
    }

    pub fn device_only(&self) -> bool {
        self.flags.contains(vk::EventCreateFlags::DEVICE_ONLY)
    }

    pub fn is_set(&self) -> bool {
        self.set.load(Ordering::Acquire)
    }

    pub fn set(&self) {
        self.set.store(true, Ordering::Release);
        notify();
    }

    pub fn reset(&self) {
        self.set.store(false, Ordering::Release);
        notify();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn fence_wait_timeouts() {
        let f = Arc::new(Fence::new(false));
        assert_eq!(wait_fences(std::slice::from_ref(&f), true, Deadline::Now), WaitOutcome::TimedOut);
        assert_eq!(wait_fences(std::slice::from_ref(&f), true, Deadline::from_timeout_ns(1_000_000)), WaitOutcome::TimedOut);
        let f2 = f.clone();
        let t = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(20));
            f2.mark_pending();
            f2.signal_from_queue();
        });
        assert_eq!(wait_fences(std::slice::from_ref(&f), true, Deadline::Never), WaitOutcome::Ready);
        t.join().unwrap();
        f.reset();
        assert!(!f.is_signalled());
    }

    #[test]
    fn any_versus_all() {
        let a = Arc::new(Fence::new(true));
        let b = Arc::new(Fence::new(false));
        assert_eq!(wait_fences(&[a.clone(), b.clone()], false, Deadline::Now), WaitOutcome::Ready);
        assert_eq!(wait_fences(&[a, b], true, Deadline::Now), WaitOutcome::TimedOut);
    }

    #[test]
    fn timeline_only_grows_and_binary_is_consumed() {
        let t = Semaphore::new(SemaphoreKind::Timeline, 5);
        t.signal(3);
        assert_eq!(t.value(), 5);
        t.signal(9);
        assert!(t.reached(9) && !t.reached(10));
        let b = Semaphore::new(SemaphoreKind::Binary, 7);
        assert_eq!(b.value(), 0);
        b.signal(0);
        assert!(b.try_consume(0));
        assert!(!b.try_consume(0));
    }

    #[test]
    fn cancel_stops_a_blocked_wait() {
        let cancel = Arc::new(AtomicBool::new(false));
        let c2 = cancel.clone();
        let t = std::thread::spawn(move || wait_until(Deadline::Never, Some(&c2), || false));
        std::thread::sleep(Duration::from_millis(10));
        cancel.store(true, Ordering::Release);
        notify();
        assert_eq!(t.join().unwrap(), WaitOutcome::Cancelled);
    }
}

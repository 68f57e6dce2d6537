//! Stall detection: how a blocking wait learns that nothing can end it, and the one rule every
//! wait of the driver follows.
//!
//! The driver cannot know whether another application thread will still submit, signal or set
//! something, so "nothing can complete this wait" is decided by observation: the wait is
//! *stalled* when, for the grace period, no queue worker or host command of Arbor was executing
//! (workers blocked in a semaphore or event wait do not count) and no synchronisation state
//! changed (every fence, semaphore, event, query and queue change goes through
//! [`super::sync::notify`], which advances [`epoch`]). The grace period is `ARBOR_STALL_MS`
//! (default 5000 ms, so a slow but legal producer thread is not cut off; 0 turns detection off
//! and every wait blocks as long as the spec lets it). Activity on any device of the process
//! postpones detection: stalls are rare, and a false report is worse than a late one.
//!
//! The rule, per wait (normal mode / `ARBOR_STRICT=1`; a stall is always reported first):
//!
//! | wait | bounded by | on a stall |
//! | --- | --- | --- |
//! | `vkWaitForFences` | its timeout | `VK_TIMEOUT` / device lost |
//! | `vkWaitSemaphores` | its timeout | `VK_TIMEOUT` / device lost |
//! | `vkGetQueryPoolResults` with `WAIT` | nothing in the spec | `VK_NOT_READY` / device lost |
//! | `vkQueueWaitIdle`, `vkDeviceWaitIdle` | the queue's work | the blocked submission is abandoned (its command buffers skipped, its signals and fence fired), then `VK_SUCCESS` / device lost |
//! | queue worker: semaphore waits, `vkCmdWaitEvents`, `vkCmdCopyQueryPoolResults` with `WAIT` | nothing: wait-before-signal is legal | blocks until signalled, abandoned by a stalled `vkQueueWaitIdle`/`vkDeviceWaitIdle`, or cancelled by `vkDestroyDevice` |
//! | `vkDeferredOperationJoinKHR` | the deferred work itself (it depends on no other object) | not needed |
//! | `vkDestroyDevice` | cancels every worker wait, abandons what is queued | not needed |
//!
//! This module only observes; what a wait returns is decided where the wait is (`dispatch`
//! for host waits, `queue` for idle waits).
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use super::Device;
use crate::diag;

static EPOCH: AtomicU64 = AtomicU64::new(0);
static RUNNING: AtomicUsize = AtomicUsize::new(0);

/// The grace period, or None when detection is off (`ARBOR_STALL_MS=0`).
pub fn grace() -> Option<Duration> {
    static GRACE: OnceLock<Option<Duration>> = OnceLock::new();
    *GRACE.get_or_init(|| {
        let ms = std::env::var("ARBOR_STALL_MS").ok().and_then(|v| v.trim().parse::<u64>().ok()).unwrap_or(5000);
        (ms > 0).then(|| Duration::from_millis(ms))
    })
}

/// Called by `sync::notify` on every state change.
pub(super) fn advance() {
    EPOCH.fetch_add(1, Ordering::AcqRel);
}

/// Marks the current thread as executing driver work (a submission, a host command) while alive.
pub struct Running(());

/// Start counting the current thread as executing until the guard drops.
pub fn running() -> Running {
    RUNNING.fetch_add(1, Ordering::AcqRel);
    advance();
    Running(())
}

impl Drop for Running {
    fn drop(&mut self) {
        RUNNING.fetch_sub(1, Ordering::AcqRel);
        advance();
    }
}

/// Run a blocking wait of an executing thread (a queue worker): it does not count as executing
/// meanwhile, since what it waits for has to come from elsewhere.
pub fn blocked<R>(f: impl FnOnce() -> R) -> R {
    RUNNING.fetch_sub(1, Ordering::AcqRel);
    let r = f();
    RUNNING.fetch_add(1, Ordering::AcqRel);
    r
}

/// One waiter's view: when the driver last showed activity.
pub struct Watch {
    epoch: u64,
    since: Instant,
}

impl Watch {
    pub fn new() -> Watch {
        Watch { epoch: EPOCH.load(Ordering::Acquire), since: Instant::now() }
    }

    /// Whether the driver has been quiet for the grace period (never when detection is off).
    pub fn stalled(&mut self) -> bool {
        let Some(grace) = grace() else { return false };
        let e = EPOCH.load(Ordering::Acquire);
        if e != self.epoch || RUNNING.load(Ordering::Acquire) > 0 {
            self.epoch = e;
            self.since = Instant::now();
            return false;
        }
        self.since.elapsed() >= grace
    }

    /// How long to sleep before checking again.
    pub fn poll_interval(&self) -> Option<Duration> {
        grace().map(|g| (g / 4).max(Duration::from_millis(5)))
    }
}

impl Default for Watch {
    fn default() -> Self {
        Watch::new()
    }
}

/// Report a stalled wait of `command` (`what`: which objects it waited for). In strict mode the
/// device is lost; returns whether it is.
pub fn report(device: &Device, command: &str, what: &str) -> bool {
    let quiet = grace().map_or(0, |g| g.as_millis());
    diag::report(
        diag::Level::Error,
        command,
        &format!("[stall] {what}: nothing pending can complete this wait (no queue or host command executing, no state change for {quiet} ms)"),
    );
    if diag::strict() {
        diag::report(diag::Level::Error, command, "strict mode: device lost");
        device.mark_lost();
    }
    device.is_lost()
}

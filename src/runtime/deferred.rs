//! Deferred host operations (VK_KHR_deferred_host_operations): the operation object, whose
//! joining threads do the work ([`DeferredOperation`] explains how).
//!
//! This module owns the scheduling of deferred work only; what the work is (a host build or
//! copy) is `runtime::accel::command`'s, and the worker count is `threads`'.
use std::sync::{Arc, Condvar, Mutex};

use ash::vk;

enum State {
    /// Created, or never used: complete with VK_SUCCESS.
    Idle,
    Pending { slots: Vec<rayon::ThreadBuilder>, pool: Option<rayon::ThreadPool> },
    Complete(vk::Result),
}

/// One `VkDeferredOperationKHR`, and how its work is scheduled.
///
/// [`defer`](Self::defer) builds a rayon thread pool without threads of its own: its N worker
/// slots (`rayon::ThreadBuilder`s, N = `threads::configured_threads()`) wait in the operation,
/// and the work is spawned on that pool as one job. Each application thread that calls
/// `vkDeferredOperationJoinKHR` ([`join`](Self::join)) takes a slot (the first joiner slot 0)
/// and runs rayon's worker loop itself: one joiner picks up the job, and the job's parallel
/// parts (`rayon::join`, parallel iterators; `threads::run_parallel` keeps them on the pool the
/// calling thread works for, whatever `runtime::accel::build::Placement` says) are split into
/// tasks the joined threads steal from each other. So deferred work runs only on joining
/// threads, on the same scheduler and with the same task decomposition as every other build:
/// the structures are byte-identical whatever the number of joiners, and with no joiner nothing
/// runs (the application must join). When the job finishes it records its result and drops the
/// pool; every joined worker then leaves its loop once idle, waits until the result is
/// recorded and returns VK_SUCCESS, and unclaimed slots are dropped. A join that finds no free
/// slot returns VK_THREAD_DONE_KHR: nothing more can be handed to it, and the slots already
/// taken guarantee progress. [`max_concurrency`](Self::max_concurrency) is the number of free
/// slots. Where no pool can be made, `defer` runs the work at once and returns
/// VK_OPERATION_NOT_DEFERRED_KHR.
///
/// `threads::run_as_inline_worker` uses the same slot hand-over to make a queue worker the one
/// worker of a private pool.
pub struct DeferredOperation {
    state: Mutex<State>,
    done: Condvar,
}

impl Default for DeferredOperation {
    fn default() -> Self {
        DeferredOperation { state: Mutex::new(State::Idle), done: Condvar::new() }
    }
}

impl DeferredOperation {
    pub fn new() -> Arc<Self> {
        Arc::new(Self::default())
    }

    /// Whether an earlier operation on this object is still pending (VUID ...-03678).
    pub fn is_pending(&self) -> bool {
        matches!(*self.state.lock().unwrap_or_else(|e| e.into_inner()), State::Pending { .. })
    }

    /// Defer `work`: it runs when threads join. Returns VK_OPERATION_DEFERRED_KHR, or runs it at
    /// once and returns VK_OPERATION_NOT_DEFERRED_KHR when no pool can be made.
    pub fn defer(self: &Arc<Self>, threads: usize, work: Box<dyn FnOnce() -> vk::Result + Send>) -> vk::Result {
        let slots = Arc::new(Mutex::new(Vec::new()));
        let sink = slots.clone();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .spawn_handler(move |builder| {
                sink.lock().unwrap_or_else(|e| e.into_inner()).push(builder);
                Ok(())
            })
            .build();
        let pool = match pool {
            Ok(p) => p,
            Err(_) => {
                let r = work();
                *self.state.lock().unwrap_or_else(|e| e.into_inner()) = State::Complete(r);
                return vk::Result::OPERATION_NOT_DEFERRED_KHR;
            }
        };
        let mut slots = std::mem::take(&mut *slots.lock().unwrap_or_else(|e| e.into_inner()));
        // Joiners take slots from the end: keep slot 0 (the first joiner) first.
        slots.reverse();
        let me = self.clone();
        pool.spawn(move || {
            let r = work();
            me.complete(r);
        });
        *self.state.lock().unwrap_or_else(|e| e.into_inner()) = State::Pending { slots, pool: Some(pool) };
        vk::Result::OPERATION_DEFERRED_KHR
    }

    fn complete(&self, result: vk::Result) {
        let pool = {
            let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
            let pool = match &mut *st {
                State::Pending { pool, .. } => pool.take(),
                _ => None,
            };
            // Unclaimed slots are dropped with the state: nobody will run them.
            *st = State::Complete(result);
            pool
        };
        self.done.notify_all();
        // Dropping the pool terminates it: joined workers leave their loops once idle.
        drop(pool);
    }

    /// vkDeferredOperationJoinKHR.
    pub fn join(&self) -> vk::Result {
        let slot = {
            let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
            match &mut *st {
                State::Idle | State::Complete(_) => return vk::Result::SUCCESS,
                State::Pending { slots, .. } => slots.pop(),
            }
        };
        match slot {
            Some(worker) => {
                // Runs rayon's worker loop on this thread until the pool terminates, which
                // happens only after the work completed.
                worker.run();
                let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
                while matches!(*st, State::Pending { .. }) {
                    st = self.done.wait(st).unwrap_or_else(|e| e.into_inner());
                }
                vk::Result::SUCCESS
            }
            None => vk::Result::THREAD_DONE_KHR,
        }
    }

    /// vkGetDeferredOperationMaxConcurrencyKHR: how many more threads could help.
    pub fn max_concurrency(&self) -> u32 {
        match &*self.state.lock().unwrap_or_else(|e| e.into_inner()) {
            State::Pending { slots, .. } => slots.len() as u32,
            _ => 0,
        }
    }

    /// vkGetDeferredOperationResultKHR.
    pub fn result(&self) -> vk::Result {
        match &*self.state.lock().unwrap_or_else(|e| e.into_inner()) {
            State::Idle => vk::Result::SUCCESS,
            State::Pending { .. } => vk::Result::NOT_READY,
            State::Complete(r) => *r,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;
    use std::sync::Mutex as StdMutex;
    use std::time::Duration;

    #[test]
    fn a_single_joiner_runs_the_work_itself() {
        let op = DeferredOperation::new();
        assert_eq!(op.result(), vk::Result::SUCCESS, "a new operation is complete");
        let ran_on = Arc::new(StdMutex::new(None));
        let r = ran_on.clone();
        assert_eq!(
            op.defer(4, Box::new(move || {
                *r.lock().unwrap() = Some(std::thread::current().id());
                vk::Result::SUCCESS
            })),
            vk::Result::OPERATION_DEFERRED_KHR
        );
        assert_eq!(op.result(), vk::Result::NOT_READY);
        assert_eq!(op.max_concurrency(), 4);
        assert_eq!(op.join(), vk::Result::SUCCESS);
        assert_eq!(*ran_on.lock().unwrap(), Some(std::thread::current().id()), "the joining thread ran the work");
        assert_eq!(op.result(), vk::Result::SUCCESS);
        assert_eq!(op.max_concurrency(), 0);
        assert_eq!(op.join(), vk::Result::SUCCESS, "joining a complete operation");
    }

    #[test]
    fn parallel_parts_are_shared_by_the_joiners() {
        let op = DeferredOperation::new();
        let threads = Arc::new(StdMutex::new(HashSet::new()));
        let t = threads.clone();
        let _ = op.defer(
            2,
            Box::new(move || {
                // Two halves, each long enough that an idle joiner steals one.
                let work = |t: &StdMutex<HashSet<_>>| {
                    for _ in 0..20 {
                        t.lock().unwrap().insert(std::thread::current().id());
                        std::thread::sleep(Duration::from_millis(5));
                    }
                };
                rayon::join(|| work(&t), || work(&t));
                vk::Result::SUCCESS
            }),
        );
        let joiners: Vec<_> = std::thread::scope(|s| {
            let hs: Vec<_> = (0..3).map(|_| s.spawn(|| (std::thread::current().id(), op.join()))).collect();
            hs.into_iter().map(|h| h.join().unwrap()).collect()
        });
        let results: Vec<_> = joiners.iter().map(|(_, r)| *r).collect();
        assert!(results.contains(&vk::Result::SUCCESS));
        assert_eq!(results.iter().filter(|r| **r == vk::Result::THREAD_DONE_KHR).count(), 1, "two slots for three joiners: {results:?}");
        let ran: HashSet<_> = threads.lock().unwrap().clone();
        let joined: HashSet<_> = joiners.iter().map(|(id, _)| *id).collect();
        assert!(ran.is_subset(&joined), "only joining threads ran the work");
        assert_eq!(ran.len(), 2, "both worker slots' joiners took part");
        assert_eq!(op.result(), vk::Result::SUCCESS);
    }

    #[test]
    fn the_result_is_the_work_s_result() {
        let op = DeferredOperation::new();
        let _ = op.defer(1, Box::new(|| vk::Result::ERROR_DEVICE_LOST));
        assert_eq!(op.join(), vk::Result::SUCCESS);
        assert_eq!(op.result(), vk::Result::ERROR_DEVICE_LOST);
    }
}

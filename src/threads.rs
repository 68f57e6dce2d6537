//! The one worker pool of the process and the thread contexts work runs in: Arbor's pool,
//! a queue worker or application thread made the one worker of a private pool (small work
//! stays there), or a deferred operation's pool, whose workers are the application threads
//! that join it (how joiners run tasks: `runtime::deferred::DeferredOperation`).
//!
//! Sized by `ARBOR_THREADS` (default: all cores), read once. This module decides nothing about
//! what runs where; callers say (`runtime::accel::build::Placement` for builds).
#![forbid(unsafe_code)]
use std::sync::OnceLock;

/// The worker count: `ARBOR_THREADS` if set to a positive number, else all cores. Read on
/// first use and kept, so the pool and every deferred operation agree on it.
pub fn configured_threads() -> usize {
    static THREADS: OnceLock<usize> = OnceLock::new();
    *THREADS.get_or_init(|| {
        std::env::var("ARBOR_THREADS")
            .ok()
            .and_then(|s| s.trim().parse::<usize>().ok())
            .filter(|&n| n > 0)
            .unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1))
    })
}

/// The process-wide pool (created on first use).
pub fn pool() -> &'static rayon::ThreadPool {
    static POOL: OnceLock<rayon::ThreadPool> = OnceLock::new();
    POOL.get_or_init(|| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(configured_threads())
            .thread_name(|i| format!("arbor-worker-{i}"))
            .build()
            .expect("creating the worker pool")
    })
}

thread_local! {
    /// Whether this thread is an Arbor queue worker running as its own pool's worker
    /// (`run_as_inline_worker`).
    static INLINE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f` on the calling thread (an Arbor queue worker) as the one worker of a private
/// one-thread rayon pool, so that small work can run right here: rayon calls made inside `f`
/// stay on this thread, with no hand-off to the worker pool and back (on a virtual machine
/// each such wake-up can cost a quarter of a millisecond). The pool's only worker slot is taken
/// by this thread (as deferred operations hand theirs to joiners, see `runtime::deferred`);
/// `f` is its one job, and the pool ends when `f` returns, so nothing outlives the thread.
/// Without a pool, `f` just runs.
pub fn run_as_inline_worker(f: impl FnOnce() + Send + 'static) {
    use std::sync::{Arc, Mutex};
    let slot: Arc<Mutex<Option<rayon::ThreadBuilder>>> = Arc::new(Mutex::new(None));
    let sink = slot.clone();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .spawn_handler(move |b| {
            *sink.lock().unwrap_or_else(|e| e.into_inner()) = Some(b);
            Ok(())
        })
        .build();
    let builder = slot.lock().unwrap_or_else(|e| e.into_inner()).take();
    let (Ok(pool), Some(builder)) = (pool, builder) else {
        f();
        return;
    };
    // The job drops the pool when `f` is done, which ends `builder.run()` below. A panic in
    // `f` is carried out of the job (rayon would abort on it) and resumed on this thread, which
    // then ends as it would have without the pool.
    type Panic = Box<dyn std::any::Any + Send>;
    // The job cannot start before `builder.run()`: this thread is the pool's only worker.
    let handle: Arc<Mutex<Option<rayon::ThreadPool>>> = Arc::new(Mutex::new(None));
    let panicked: Arc<Mutex<Option<Panic>>> = Arc::new(Mutex::new(None));
    let (own, report) = (handle.clone(), panicked.clone());
    pool.spawn(move || {
        INLINE.with(|c| c.set(true));
        if let Err(e) = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
            *report.lock().unwrap_or_else(|e| e.into_inner()) = Some(e);
        }
        INLINE.with(|c| c.set(false));
        drop(own.lock().unwrap_or_else(|e| e.into_inner()).take());
    });
    *handle.lock().unwrap_or_else(|e| e.into_inner()) = Some(pool);
    builder.run();
    let payload = panicked.lock().unwrap_or_else(|e| e.into_inner()).take();
    if let Some(e) = payload {
        std::panic::resume_unwind(e);
    }
}

/// Runs `f` on the calling application thread (a non-deferred host build) as the one worker of
/// a private pool (`run_as_inline_worker`), so that the small work in it (`runs_inline`) keeps
/// its rayon calls here instead of waking Arbor's worker pool, as queue threads do with small
/// builds; large work goes to Arbor's pool from here (`run_parallel`). On a thread that already
/// works for a rayon pool (an Arbor thread, or an application's own rayon worker) `f` just
/// runs: its rayon calls go to that pool, as `run_parallel` would send them.
pub fn run_here<R: Send + 'static>(f: impl FnOnce() -> R + Send + 'static) -> R {
    if INLINE.with(|c| c.get()) || rayon::current_thread_index().is_some() {
        return f();
    }
    let (tx, rx) = std::sync::mpsc::sync_channel(1);
    run_as_inline_worker(move || {
        let _ = tx.send(f());
    });
    // `run_as_inline_worker` returns after `f` has run, or resumes its panic.
    rx.try_recv().expect("run_as_inline_worker ran the job")
}

/// The largest work, in primitives × worker-pool threads, that a command's builds may have and
/// still run on the calling queue or application thread (`runs_inline`). Below it the hand-off
/// to the pool and back (about a quarter of a millisecond on these virtual machines) costs
/// more than the pool's threads save. With 2 threads that allows builds of up to 4,096
/// primitives: the 3,674-triangle bunny was 7–10 % faster inline on the 2-vCPU box. With 16
/// threads it allows up to 512: the bunny builds 1.5–2.5× faster on the pool of the 16-core
/// machine (both recorded with commit ae1f3bb of 2026-11-22).
pub const INLINE_WORK: u64 = 8192;

/// Whether builds of `primitives` in all run on the calling thread (see `INLINE_WORK`).
pub fn runs_inline(primitives: u64) -> bool {
    inline_for(primitives, pool().current_num_threads())
}

fn inline_for(primitives: u64, threads: usize) -> bool {
    primitives.saturating_mul(threads.max(1) as u64) <= INLINE_WORK
}

/// Runs `f` where parallel work belongs: on the pool the calling thread already works for (a
/// deferred operation's pool, whose workers are the application threads that joined it, see
/// `runtime::deferred::DeferredOperation`); on the calling queue worker's or host command's own
/// thread when the caller says the work is small (`small`); otherwise on Arbor's worker pool.
pub fn run_parallel<R: Send>(small: bool, f: impl FnOnce() -> R + Send) -> R {
    if INLINE.with(|c| c.get()) {
        if small {
            f()
        } else {
            pool().install(f)
        }
    } else if rayon::current_thread_index().is_some() {
        f()
    } else {
        pool().install(f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;
    use std::thread::{self, ThreadId};

    #[test]
    fn inline_worker_keeps_small_work_on_its_thread_and_leaves_no_pool_behind() {
        let outer = thread::current().id();
        let (tx, rx) = std::sync::mpsc::channel::<(ThreadId, usize, Vec<ThreadId>, ThreadId, ThreadId)>();
        run_as_inline_worker(move || {
            let here = thread::current().id();
            // Parallel iterators inside run on this thread: a one-thread pool.
            let ids: Vec<ThreadId> = (0..64).into_par_iter().map(|_| thread::current().id()).collect();
            let small = run_parallel(true, || thread::current().id());
            let large = run_parallel(false, || thread::current().id());
            tx.send((here, rayon::current_num_threads(), ids, small, large)).unwrap();
        });
        let (here, n, ids, small, large) = rx.recv().unwrap();
        assert_eq!(here, outer, "f runs on the calling thread");
        assert_eq!(n, 1);
        assert!(ids.iter().all(|&t| t == outer), "parallel work stayed on the thread");
        assert_eq!(small, outer, "small work runs inline");
        assert_ne!(large, outer, "large work goes to the worker pool");
        // Afterwards the thread is nobody's worker again, and not marked inline.
        assert!(rayon::current_thread_index().is_none());
        assert!(!INLINE.with(|c| c.get()));
    }

    #[test]
    fn run_here_keeps_work_on_an_application_thread_and_defers_to_a_pool_it_works_for() {
        // A plain thread (an application calling a host command): the work and its parallel
        // iterators run right here, and the thread is nobody's worker afterwards.
        let outer = thread::current().id();
        let (here, n, ids) = run_here(|| {
            let ids: Vec<ThreadId> = (0..64).into_par_iter().map(|_| thread::current().id()).collect();
            (thread::current().id(), rayon::current_num_threads(), ids)
        });
        assert_eq!(here, outer);
        assert_eq!(n, 1);
        assert!(ids.iter().all(|&t| t == outer), "parallel work stayed on the thread");
        assert!(rayon::current_thread_index().is_none());
        assert_eq!(run_here(|| 7), 7, "and again on the same thread");
        // A thread of an application's own 3-thread pool keeps working for that pool.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let n = pool.install(|| run_here(rayon::current_num_threads));
        assert_eq!(n, 3);
        // A panic comes out on the calling thread.
        let r = std::panic::catch_unwind(|| run_here(|| -> u32 { panic!("inside") }));
        assert_eq!(r.expect_err("the panic reaches the caller").downcast_ref::<&str>().copied(), Some("inside"));
        assert!(rayon::current_thread_index().is_none());
    }

    #[test]
    fn small_work_stays_inline_by_primitives_times_threads() {
        assert!(inline_for(4096, 2) && !inline_for(4097, 2));
        assert!(inline_for(512, 16) && !inline_for(3674, 16));
        assert!(inline_for(8192, 1) && !inline_for(8193, 1));
        assert!(inline_for(0, 0) && !inline_for(u64::MAX, 3));
    }

    #[test]
    fn inline_worker_carries_a_panic_out() {
        let r = std::panic::catch_unwind(|| run_as_inline_worker(|| panic!("inside")));
        let e = r.expect_err("the panic reaches the caller");
        assert_eq!(e.downcast_ref::<&str>().copied(), Some("inside"));
        assert!(rayon::current_thread_index().is_none());
    }
}

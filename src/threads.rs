//! The one worker pool of the process. Builds run on it; deferred operations draw from it.
//! Sized by `ARBOR_THREADS` (default: all cores).
use std::sync::OnceLock;

pub fn configured_threads() -> usize {
    std::env::var("ARBOR_THREADS")
        .ok()
        .and_then(|s| s.trim().parse::<usize>().ok())
        .filter(|&n| n > 0)
        .unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1))
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
    /// This thread's own one-thread pool, if it is an Arbor queue worker (see `become_inline_worker`).
    static INLINE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Makes the calling thread (an Arbor queue worker, which lives as long as its queue) the one
/// worker of a private one-thread pool, so that small work can run right here: rayon calls
/// made on this thread then stay on it, with no hand-off to the worker pool and back (on a
/// virtual machine each such wake-up can cost a quarter of a millisecond). rayon cannot undo
/// this for a thread, so only threads Arbor owns do it. Returns the pool, which the caller
/// keeps for the thread's lifetime; None (nothing changed) if the thread is already some
/// pool's worker or the pool cannot be made.
pub fn become_inline_worker() -> Option<rayon::ThreadPool> {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).use_current_thread().build().ok()?;
    INLINE.with(|c| c.set(true));
    Some(pool)
}

/// Builds of at most this many primitives in all run on the queue thread: below it the builder
/// splits little across threads (most of its parallel cutoffs are 4096 references), and the
/// hand-off to the pool and back costs more than it buys (docs/BENCHMARKS.md, session 5).
pub const INLINE_PRIMITIVES: u64 = 4096;

/// Runs `f` where parallel work belongs: on the pool the calling thread already works for (a
/// deferred operation's pool, whose workers are the application threads that joined it); on a
/// queue worker's own thread when the work is small (`small`); otherwise on Arbor's worker pool
/// (queue workers and non-deferred host commands).
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

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

//! Queues: each has a worker thread (started on the first submission) that executes
//! submissions in order: wait semaphores → sparse binds or command buffers → signal
//! semaphores, batch after batch, then the fence. vkQueueSubmit and vkQueueBindSparse only
//! enqueue, so binds are ordered with command buffers on the same queue.
//!
//! Stopping: [`Queue::shutdown`] (vkDestroyDevice) raises the cancel flag, which ends any wait
//! the worker is blocked in, closes the channel and joins the thread. Submissions still queued
//! are abandoned (their buffers leave the pending state; nothing executes).
//!
//! Unblocking: a `vkQueueWaitIdle` that finds the queue stalled (`stall`: blocked in a wait
//! nothing pending can satisfy) raises the interrupt flag, which ends the blocked wait and
//! skips the rest of that one submission (its signals and fence still fire).
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex, Weak};
use std::thread::JoinHandle;

use ash::vk;

use super::command::{execute_recording, CommandBuffer, ExecContext, Flow, SubmittedBuffer};
use super::in_use::{Collector, Held};
use super::stall;
use super::sync::{self, Deadline, Fence, Semaphore, SemaphoreKind, WaitOutcome};
use super::Device;
use crate::diag;
use crate::memory::{Buffer, Memory};

/// One batch of a submission, as the dispatch layer lowered it.
pub struct BatchDesc {
    pub waits: Vec<(Arc<Semaphore>, u64)>,
    pub command_buffers: Vec<Arc<CommandBuffer>>,
    pub signals: Vec<(Arc<Semaphore>, u64)>,
}

/// One page-aligned bind of a sparse buffer's range: `[offset, offset + size)` of the buffer
/// onto `memory` at its offset, or unbound (zero pages) when `memory` is `None`. Checked by
/// the dispatch layer before it is enqueued.
pub struct SparseBind {
    pub buffer: Arc<Buffer>,
    pub offset: u64,
    pub size: u64,
    pub memory: Option<(Arc<Memory>, u64)>,
}

/// One batch of vkQueueBindSparse, as the dispatch layer lowered it.
pub struct BindBatchDesc {
    pub waits: Vec<(Arc<Semaphore>, u64)>,
    pub binds: Vec<SparseBind>,
    pub signals: Vec<(Arc<Semaphore>, u64)>,
}

struct Batch {
    waits: Vec<(Arc<Semaphore>, u64)>,
    /// Applied in order after the waits (a vkQueueBindSparse batch has no command buffers).
    binds: Vec<SparseBind>,
    command_buffers: Vec<SubmittedBuffer>,
    signals: Vec<(Arc<Semaphore>, u64)>,
    /// What the command buffers use (`in_use`); released before the signals.
    uses: Held,
}

struct Submission {
    batches: Vec<Batch>,
    fence: Option<Arc<Fence>>,
}

impl Submission {
    /// Nothing executes; buffers leave the pending state, signals and fence fire so that no
    /// host wait hangs on a stopped queue.
    fn abandon(self) {
        for b in self.batches {
            for cb in &b.command_buffers {
                cb.complete();
            }
            drop(b.uses);
            for (s, v) in &b.signals {
                s.signal(*v);
            }
        }
        if let Some(f) = self.fence {
            f.signal_from_queue();
        }
    }
}

/// State shared with the worker thread.
struct Shared {
    submitted: AtomicU64,
    completed: AtomicU64,
    stop: AtomicBool,
    /// Raised with `stop`, or to abandon the submission the worker is blocked in; ends the
    /// worker's waits and the current submission. Lowered by the worker when it starts the
    /// next submission, unless the queue is stopping.
    interrupt: AtomicBool,
}

struct Worker {
    tx: mpsc::Sender<Submission>,
    thread: JoinHandle<()>,
}

pub struct Queue {
    pub device: Weak<Device>,
    pub family: u32,
    pub index: u32,
    shared: Arc<Shared>,
    worker: Mutex<Option<Worker>>,
}

impl Queue {
    pub fn new(device: Weak<Device>, family: u32, index: u32) -> Queue {
        Queue {
            device,
            family,
            index,
            shared: Arc::new(Shared {
                submitted: AtomicU64::new(0),
                completed: AtomicU64::new(0),
                stop: AtomicBool::new(false),
                interrupt: AtomicBool::new(false),
            }),
            worker: Mutex::new(None),
        }
    }

    /// vkQueueSubmit / vkQueueSubmit2 after lowering: validate, mark pending, enqueue.
    pub fn submit(&self, command: &str, batches: Vec<BatchDesc>, fence: Option<Arc<Fence>>) -> vk::Result {
        let Some(device) = self.device.upgrade() else { return vk::Result::ERROR_DEVICE_LOST };
        if device.is_lost() {
            return vk::Result::ERROR_DEVICE_LOST;
        }
        if let Some(f) = &fence {
            if f.is_signalled() {
                diag::vuid("VUID-vkQueueSubmit-fence-00063", command, "the fence is already signalled (reset it before submitting)");
            }
            if f.is_pending() {
                diag::vuid("VUID-vkQueueSubmit-fence-00064", command, "the fence is already associated with an unfinished submission");
            }
        }
        let mut lowered = Vec::with_capacity(batches.len());
        for b in batches {
            for (s, v) in &b.signals {
                if s.kind == SemaphoreKind::Timeline && *v <= s.value() {
                    diag::vuid(
                        "VUID-VkSubmitInfo-pSignalSemaphores-03242",
                        command,
                        &format!("signal value {v} is not greater than the timeline semaphore's current value {}", s.value()),
                    );
                }
            }
            let command_buffers: Vec<SubmittedBuffer> = b.command_buffers.iter().filter_map(|cb| cb.prepare_submit(command)).collect();
            let mut uses = Collector::new(&device.memory);
            for c in command_buffers.iter().flat_map(|cb| &cb.recording.commands) {
                c.uses(&mut uses);
            }
            lowered.push(Batch { waits: b.waits, binds: Vec::new(), command_buffers, signals: b.signals, uses: uses.hold() });
        }
        self.enqueue(Submission { batches: lowered, fence })
    }

    /// vkQueueBindSparse after lowering and checks: enqueue the binds as a submission.
    pub fn bind_sparse(&self, command: &str, batches: Vec<BindBatchDesc>, fence: Option<Arc<Fence>>) -> vk::Result {
        let Some(device) = self.device.upgrade() else { return vk::Result::ERROR_DEVICE_LOST };
        if device.is_lost() {
            return vk::Result::ERROR_DEVICE_LOST;
        }
        if let Some(f) = &fence {
            if f.is_signalled() {
                diag::vuid("VUID-vkQueueBindSparse-fence-01113", command, "the fence is already signalled (reset it before submitting)");
            }
            if f.is_pending() {
                diag::vuid("VUID-vkQueueBindSparse-fence-01114", command, "the fence is already associated with an unfinished submission");
            }
        }
        let lowered = batches
            .into_iter()
            .map(|b| {
                let mut uses = Collector::new(&device.memory);
                for bind in &b.binds {
                    uses.buffer(&bind.buffer);
                }
                Batch { waits: b.waits, binds: b.binds, command_buffers: Vec::new(), signals: b.signals, uses: uses.hold() }
            })
            .collect();
        self.enqueue(Submission { batches: lowered, fence })
    }

    /// Mark the fence pending and hand the submission to the worker (started if need be).
    fn enqueue(&self, submission: Submission) -> vk::Result {
        if let Some(f) = &submission.fence {
            f.mark_pending();
        }
        let mut w = self.worker.lock().unwrap_or_else(|e| e.into_inner());
        if self.shared.stop.load(Ordering::Acquire) {
            drop(w);
            submission.abandon();
            return vk::Result::ERROR_DEVICE_LOST;
        }
        if w.is_none() {
            match self.start_worker() {
                Some(worker) => *w = Some(worker),
                None => {
                    drop(w);
                    submission.abandon();
                    return vk::Result::ERROR_OUT_OF_HOST_MEMORY;
                }
            }
        }
        self.shared.submitted.fetch_add(1, Ordering::AcqRel);
        if let Some(Worker { tx, .. }) = w.as_ref() {
            if let Err(mpsc::SendError(s)) = tx.send(submission) {
                self.shared.completed.fetch_add(1, Ordering::AcqRel);
                s.abandon();
                return vk::Result::ERROR_DEVICE_LOST;
            }
        }
        vk::Result::SUCCESS
    }

    fn start_worker(&self) -> Option<Worker> {
        let (tx, rx) = mpsc::channel::<Submission>();
        let shared = self.shared.clone();
        let device = self.device.clone();
        let thread = std::thread::Builder::new()
            .name(format!("arbor-queue-{}-{}", self.family, self.index))
            // Small builds run on this thread itself (`runtime::accel::build::Placement`).
            .spawn(move || crate::threads::run_as_inline_worker(move || worker_loop(rx, shared, device)))
            .ok()?;
        Some(Worker { tx, thread })
    }

    /// vkQueueWaitIdle (and each queue of vkDeviceWaitIdle, `command`): wait for everything
    /// submitted so far. A stalled queue (`stall`) is reported and its blocked submission
    /// abandoned, so the wait ends with the queue really idle; strict mode loses the device.
    pub fn wait_idle(&self, command: &str) -> vk::Result {
        let target = self.shared.submitted.load(Ordering::Acquire);
        let shared = &self.shared;
        loop {
            let r = sync::wait_or_stall(Deadline::Never, Some(&shared.stop), || shared.completed.load(Ordering::Acquire) >= target);
            if r != WaitOutcome::Stalled {
                break;
            }
            if let Some(d) = self.device.upgrade() {
                let what = format!(
                    "queue (family {}, index {}) is blocked in a semaphore or event wait; its submission is abandoned (command buffers skipped, signals and fence fired)",
                    self.family, self.index
                );
                stall::report(&d, command, &what);
            }
            shared.interrupt.store(true, Ordering::Release);
            sync::notify();
        }
        match self.device.upgrade() {
            Some(d) if !d.is_lost() => vk::Result::SUCCESS,
            _ => vk::Result::ERROR_DEVICE_LOST,
        }
    }

    /// vkDestroyDevice with submissions still pending: report them, then wait for them as
    /// vkQueueWaitIdle does (a stalled one is abandoned, so this returns).
    pub fn finish_before_destroy(&self) {
        let pending = self.shared.submitted.load(Ordering::Acquire).saturating_sub(self.shared.completed.load(Ordering::Acquire));
        if pending > 0 {
            diag::report(
                diag::Level::Error,
                "vkDestroyDevice",
                &format!("{pending} submission(s) still pending on queue (family {}, index {}); waiting for them (call vkDeviceWaitIdle before destroying the device)", self.family, self.index),
            );
            // The device goes either way; a lost device only ends the wait sooner. Marking it
            // lost stops a running dispatch at its next watchdog check (the watchdog reads the
            // flag) instead of at its deadline; waits still end by the stall rule.
            if let Some(d) = self.device.upgrade() {
                d.mark_lost();
            }
            let _ = self.wait_idle("vkDestroyDevice");
        }
    }

    /// Stop the worker (device destruction): cancel its waits, abandon what is queued, join.
    pub fn shutdown(&self) {
        self.shared.stop.store(true, Ordering::Release);
        self.shared.interrupt.store(true, Ordering::Release);
        sync::notify();
        let worker = self.worker.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(Worker { tx, thread }) = worker {
            drop(tx);
            if thread.join().is_err() {
                diag::report(diag::Level::Error, "vkDestroyDevice", "a queue worker panicked");
            }
        }
    }
}

impl Drop for Queue {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn worker_loop(rx: mpsc::Receiver<Submission>, shared: Arc<Shared>, device: Weak<Device>) {
    while let Ok(submission) = rx.recv() {
        let device = device.upgrade();
        match device {
            Some(d) if !shared.stop.load(Ordering::Acquire) => {
                // A panic in a command must not kill the queue: report it and go on.
                // An interrupt raised before this submission started was meant for an earlier
                // one that completed meanwhile.
                if !shared.stop.load(Ordering::Acquire) {
                    shared.interrupt.store(false, Ordering::Release);
                }
                let executing = stall::running();
                let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(&d, &shared, submission)));
                drop(executing);
                if r.is_err() {
                    diag::report(diag::Level::Error, "queue", "internal error (caught panic) while executing a submission");
                }
            }
            _ => submission.abandon(),
        }
        shared.completed.fetch_add(1, Ordering::AcqRel);
        sync::notify();
    }
}

fn run(device: &Arc<Device>, shared: &Shared, submission: Submission) {
    let ctx = ExecContext { device, cancel: &shared.interrupt };
    let mut stopped = false;
    for batch in submission.batches {
        if !stopped {
            for (s, v) in &batch.waits {
                let r = stall::blocked(|| sync::wait_until(Deadline::Never, Some(&shared.interrupt), || s.try_consume(*v)));
                if r != WaitOutcome::Ready {
                    stopped = true;
                    break;
                }
            }
        }
        if !stopped && !device.is_lost() {
            apply_binds(&batch.binds);
        }
        for cb in &batch.command_buffers {
            if !stopped && !device.is_lost() && execute_recording(&cb.recording, &ctx) == Flow::Stop {
                stopped = true;
            }
            cb.complete();
        }
        drop(batch.uses);
        for (s, v) in &batch.signals {
            s.signal(*v);
        }
    }
    if let Some(f) = &submission.fence {
        f.signal_from_queue();
    }
}

/// Apply a batch's sparse binds in order. The dispatch layer checked them; what can still
/// fail here (the memory freed meanwhile, the system refusing a mapping) is reported and that
/// bind skipped.
fn apply_binds(binds: &[SparseBind]) {
    for b in binds {
        let Some((range, base)) = b.buffer.memory() else {
            diag::report(diag::Level::Error, "vkQueueBindSparse", "the buffer has no sparse range; bind skipped");
            continue;
        };
        let target = b.memory.as_ref().map(|(m, o)| (m, *o));
        if let Err(e) = range.bind_sparse(base + b.offset, b.size, target) {
            diag::report(
                diag::Level::Error,
                "vkQueueBindSparse",
                &format!("bind of [{}, +{}) refused when applied ({e:?}); skipped", b.offset, b.size),
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicUsize;
    use std::sync::OnceLock;

    use super::*;
    use crate::memory::{AddressSpace, Buffer};
    use crate::runtime::command::{CommandPool, Exec, ExecError};
    use crate::runtime::PhysicalDevice;

    fn device() -> Arc<Device> {
        Arc::new(Device {
            physical: PhysicalDevice::new(),
            enabled_extensions: Default::default(),
            api_minor: 1,
            features: Default::default(),
            memory: Arc::new(AddressSpace::new(1 << 26)),
            queues: OnceLock::new(),
            epoch: std::time::Instant::now(),
            lost: Default::default(),
        })
    }

    fn buffer(dev: &Device, size: u64) -> Arc<Buffer> {
        let usage = vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST;
        let b = Arc::new(Buffer::new(size, usage, vk::BufferCreateFlags::empty()));
        b.bind(dev.memory.allocate(size, true, None).unwrap(), 0).unwrap();
        b
    }

    /// A custom command (the extension point): reads what the previous command wrote through a
    /// device address and writes its double after it.
    struct Double {
        address: u64,
        ran: Arc<AtomicUsize>,
    }

    impl Exec for Double {
        fn name(&self) -> &'static str {
            "vkCmdTestDouble"
        }
        fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError> {
            let mut v = [0u8; 4];
            ctx.memory().read(self.address, &mut v)?;
            let d = u32::from_le_bytes(v) * 2;
            ctx.memory().write(self.address + 4, &d.to_le_bytes())?;
            self.ran.fetch_add(1, Ordering::Relaxed);
            Ok(())
        }
    }

    #[test]
    fn custom_commands_run_in_order_with_the_built_in_ones() {
        let dev = device();
        let q = Queue::new(Arc::downgrade(&dev), 0, 0);
        let b = buffer(&dev, 64);
        let pool = Arc::new(CommandPool::new(vk::CommandPoolCreateFlags::empty(), 0));
        let cb = pool.allocate(vk::CommandBufferLevel::PRIMARY);
        let ran = Arc::new(AtomicUsize::new(0));
        cb.begin(vk::CommandBufferUsageFlags::empty(), false);
        cb.cmd_update_buffer(b.clone(), 0, 21u32.to_le_bytes().to_vec());
        cb.record_custom(Box::new(Double { address: b.device_address().unwrap(), ran: ran.clone() }));
        // A custom command whose access is refused: reported, skipped, the rest runs.
        cb.record_custom(Box::new(Double { address: 0x10, ran: ran.clone() }));
        cb.cmd_fill_buffer(b.clone(), 8, 4, 7);
        let _ = cb.end();
        let fence = Arc::new(sync::Fence::new(false));
        let batch = BatchDesc { waits: vec![], command_buffers: vec![cb.clone()], signals: vec![] };
        assert_eq!(q.submit("test", vec![batch], Some(fence.clone())), vk::Result::SUCCESS);
        assert_eq!(sync::wait_fences(&[fence], true, Deadline::Never), WaitOutcome::Ready);
        let mut out = [0u8; 12];
        b.read(0, &mut out).unwrap();
        assert_eq!(out, [21, 0, 0, 0, 42, 0, 0, 0, 7, 0, 0, 0]);
        assert_eq!(ran.load(Ordering::Relaxed), 1);
        assert!(!cb.is_pending());
        assert_eq!(q.wait_idle("test"), vk::Result::SUCCESS);
        q.shutdown();
    }

    #[test]
    fn sparse_binds_apply_after_their_waits_and_before_their_signals() {
        use crate::memory::sparse::SPARSE_PAGE;
        let dev = device();
        let q = Queue::new(Arc::downgrade(&dev), 0, 2);
        let memory = dev.memory.allocate_shareable(SPARSE_PAGE, true).unwrap();
        memory.write(0, &[9u8; 4]).unwrap();
        let b = Arc::new(Buffer::new(SPARSE_PAGE, vk::BufferUsageFlags::TRANSFER_SRC, vk::BufferCreateFlags::SPARSE_BINDING));
        b.bind(dev.memory.reserve_sparse(SPARSE_PAGE).unwrap(), 0).unwrap();
        let (gate, done) = (Arc::new(Semaphore::new(SemaphoreKind::Timeline, 0)), Arc::new(Semaphore::new(SemaphoreKind::Timeline, 0)));
        let fence = Arc::new(sync::Fence::new(false));
        let bind = SparseBind { buffer: b.clone(), offset: 0, size: SPARSE_PAGE, memory: Some((memory.clone(), 0)) };
        let batch = BindBatchDesc { waits: vec![(gate.clone(), 1)], binds: vec![bind], signals: vec![(done.clone(), 1)] };
        assert_eq!(q.bind_sparse("test", vec![batch], Some(fence.clone())), vk::Result::SUCCESS);
        let mut out = [0u8; 4];
        b.read(0, &mut out).unwrap();
        assert_eq!(out, [0; 4], "the bind waits for its semaphore: the page is still unbound");
        assert!(!fence.is_signalled() && done.value() == 0);
        gate.signal(1);
        assert_eq!(sync::wait_fences(&[fence], true, Deadline::Never), WaitOutcome::Ready);
        assert_eq!(done.value(), 1);
        b.read(0, &mut out).unwrap();
        assert_eq!(out, [9; 4], "bound: the buffer shows the memory");
        q.shutdown();
    }

    #[test]
    fn shutdown_cancels_a_blocked_worker_and_abandons_the_queue() {
        let dev = device();
        let q = Queue::new(Arc::downgrade(&dev), 0, 1);
        let sem = Arc::new(Semaphore::new(SemaphoreKind::Timeline, 0));
        let (f1, f2) = (Arc::new(sync::Fence::new(false)), Arc::new(sync::Fence::new(false)));
        let blocked = BatchDesc { waits: vec![(sem.clone(), 1)], command_buffers: vec![], signals: vec![] };
        assert_eq!(q.submit("test", vec![blocked], Some(f1.clone())), vk::Result::SUCCESS);
        assert_eq!(q.submit("test", vec![], Some(f2.clone())), vk::Result::SUCCESS);
        std::thread::sleep(std::time::Duration::from_millis(10));
        assert!(!f1.is_signalled());
        q.shutdown();
        assert!(f1.is_signalled() && f2.is_signalled(), "abandoned submissions still signal so no host wait hangs");
        assert_eq!(q.submit("test", vec![], None), vk::Result::ERROR_DEVICE_LOST);
    }
}

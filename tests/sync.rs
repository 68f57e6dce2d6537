//! Fences, events, binary and timeline semaphores, queue submission from several threads and
//! idle waits, through the real loader with validation on.
mod harness;

use std::sync::{Arc, Barrier, Mutex};
use std::time::{Duration, Instant};

use ash::vk;

fn command_pool(ctx: &harness::Context) -> vk::CommandPool {
    let info = vk::CommandPoolCreateInfo::default().queue_family_index(0).flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
    // SAFETY: valid create info.
    unsafe { ctx.device.create_command_pool(&info, None) }.unwrap()
}

fn command_buffer(device: &ash::Device, pool: vk::CommandPool) -> vk::CommandBuffer {
    let info = vk::CommandBufferAllocateInfo::default().command_pool(pool).level(vk::CommandBufferLevel::PRIMARY).command_buffer_count(1);
    // SAFETY: valid allocate info.
    unsafe { device.allocate_command_buffers(&info) }.unwrap()[0]
}

fn fence(device: &ash::Device, signalled: bool) -> vk::Fence {
    let flags = if signalled { vk::FenceCreateFlags::SIGNALED } else { vk::FenceCreateFlags::empty() };
    // SAFETY: valid create info.
    unsafe { device.create_fence(&vk::FenceCreateInfo::default().flags(flags), None) }.unwrap()
}

fn timeline(device: &ash::Device, initial: u64) -> vk::Semaphore {
    let mut ty = vk::SemaphoreTypeCreateInfo::default().semaphore_type(vk::SemaphoreType::TIMELINE).initial_value(initial);
    // SAFETY: valid create info.
    unsafe { device.create_semaphore(&vk::SemaphoreCreateInfo::default().push_next(&mut ty), None) }.unwrap()
}

fn begin(device: &ash::Device, cb: vk::CommandBuffer) {
    // SAFETY: cb is in the initial or executable state; its pool allows resets.
    unsafe { device.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()) }.unwrap();
}

/// A host-set event unblocks a vkCmdWaitEvents; the fence is not signalled before (timeout 0 →
/// VK_TIMEOUT) and is after.
#[test]
fn fence_timeouts_and_host_event_unblocks_wait_events() {
    let ctx = harness::context();
    let d = &ctx.device;
    let pool = command_pool(&ctx);
    let cb = command_buffer(d, pool);
    // SAFETY: objects created here; destroyed at the end after the queue is idle.
    unsafe {
        let event = d.create_event(&vk::EventCreateInfo::default(), None).unwrap();
        let f = fence(d, false);
        assert_eq!(d.wait_for_fences(&[f], true, 0), Err(vk::Result::TIMEOUT), "nothing submitted: timeout 0");
        assert_eq!(d.get_fence_status(f), Ok(false));
        let t = Instant::now();
        assert_eq!(d.wait_for_fences(&[f], true, 20_000_000), Err(vk::Result::TIMEOUT));
        assert!(t.elapsed() >= Duration::from_millis(19), "a 20 ms timeout waits about 20 ms");

        begin(d, cb);
        d.cmd_wait_events(cb, &[event], vk::PipelineStageFlags::HOST, vk::PipelineStageFlags::TRANSFER, &[], &[], &[]);
        d.end_command_buffer(cb).unwrap();
        let cbs = [cb];
        d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs)], f).unwrap();
        std::thread::sleep(Duration::from_millis(30));
        assert_eq!(d.wait_for_fences(&[f], true, 0), Err(vk::Result::TIMEOUT), "the queue waits for the event");
        assert_eq!(d.get_event_status(event), Ok(false));
        d.set_event(event).unwrap();
        assert_eq!(d.get_event_status(event), Ok(true));
        d.wait_for_fences(&[f], true, u64::MAX).unwrap();
        assert_eq!(d.get_fence_status(f), Ok(true));
        d.reset_fences(&[f]).unwrap();
        assert_eq!(d.get_fence_status(f), Ok(false));

        // waitAll versus waitAny.
        let s = fence(d, true);
        assert_eq!(d.wait_for_fences(&[s, f], true, 0), Err(vk::Result::TIMEOUT));
        d.wait_for_fences(&[s, f], false, 0).unwrap();
        d.wait_for_fences(&[s], true, u64::MAX).unwrap();

        d.destroy_fence(s, None);
        d.destroy_fence(f, None);
        d.destroy_event(event, None);
        d.destroy_command_pool(pool, None);
    }
    ctx.finish();
}

/// Events set and reset by commands (core and synchronization2), seen by the host.
#[test]
fn events_set_by_commands() {
    let ctx = harness::context();
    let d = &ctx.device;
    let sync2 = ash::khr::synchronization2::Device::new(&ctx.instance, d);
    let pool = command_pool(&ctx);
    let cb = command_buffer(d, pool);
    // SAFETY: objects created here; destroyed at the end after the queue is idle.
    unsafe {
        let a = d.create_event(&vk::EventCreateInfo::default(), None).unwrap();
        let b = d.create_event(&vk::EventCreateInfo::default(), None).unwrap();
        let device_only = d.create_event(&vk::EventCreateInfo::default().flags(vk::EventCreateFlags::DEVICE_ONLY), None).unwrap();
        let f = fence(d, false);
        begin(d, cb);
        d.cmd_set_event(cb, a, vk::PipelineStageFlags::TRANSFER);
        d.cmd_wait_events(cb, &[a], vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::TRANSFER, &[], &[], &[]);
        let mb = [vk::MemoryBarrier2::default()
            .src_stage_mask(vk::PipelineStageFlags2::TRANSFER)
            .src_access_mask(vk::AccessFlags2::TRANSFER_WRITE)
            .dst_stage_mask(vk::PipelineStageFlags2::TRANSFER)
            .dst_access_mask(vk::AccessFlags2::TRANSFER_READ)];
        let dep = vk::DependencyInfo::default().memory_barriers(&mb);
        sync2.cmd_set_event2(cb, b, &dep);
        sync2.cmd_wait_events2(cb, &[b], std::slice::from_ref(&dep));
        sync2.cmd_pipeline_barrier2(cb, &dep);
        sync2.cmd_reset_event2(cb, b, vk::PipelineStageFlags2::TRANSFER);
        // A DEVICE_ONLY event: set and waited on by the queue only.
        sync2.cmd_set_event2(cb, device_only, &dep);
        sync2.cmd_wait_events2(cb, &[device_only], std::slice::from_ref(&dep));
        d.end_command_buffer(cb).unwrap();
        let cbs = [cb];
        d.queue_submit(ctx.queues[1], &[vk::SubmitInfo::default().command_buffers(&cbs)], f).unwrap();
        d.wait_for_fences(&[f], true, u64::MAX).unwrap();
        assert_eq!(d.get_event_status(a), Ok(true), "set by vkCmdSetEvent");
        assert_eq!(d.get_event_status(b), Ok(false), "set then reset by the sync2 commands");
        d.reset_event(a).unwrap();
        assert_eq!(d.get_event_status(a), Ok(false));
        d.destroy_fence(f, None);
        d.destroy_event(a, None);
        d.destroy_event(b, None);
        d.destroy_event(device_only, None);
        d.destroy_command_pool(pool, None);
    }
    ctx.finish();
}

/// A queue waits on a timeline value that another thread signals from the host; the host
/// waits (all/any, timeouts) for the value the queue signals. Submit and Submit2 both.
#[test]
fn timeline_semaphores_across_threads() {
    let ctx = harness::context();
    let d = ctx.device.clone();
    let tl = ash::khr::timeline_semaphore::Device::new(&ctx.instance, &d);
    let sync2 = ash::khr::synchronization2::Device::new(&ctx.instance, &d);
    // SAFETY: objects created here; destroyed at the end after the queue is idle.
    unsafe {
        let sem = timeline(&d, 0);
        assert_eq!(tl.get_semaphore_counter_value(sem), Ok(0));
        let f = fence(&d, false);
        // vkQueueSubmit: wait 1 (from the host thread), signal 2.
        let waits = [sem];
        let stages = [vk::PipelineStageFlags::ALL_COMMANDS];
        let signals = [sem];
        let (wv, sv) = ([1u64], [2u64]);
        let mut tsi = vk::TimelineSemaphoreSubmitInfo::default().wait_semaphore_values(&wv).signal_semaphore_values(&sv);
        let submit = vk::SubmitInfo::default().wait_semaphores(&waits).wait_dst_stage_mask(&stages).signal_semaphores(&signals).push_next(&mut tsi);
        d.queue_submit(ctx.queues[2], &[submit], f).unwrap();
        // vkQueueSubmit2 on another queue: wait 2, signal 3.
        let w2 = [vk::SemaphoreSubmitInfo::default().semaphore(sem).value(2).stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
        let s2 = [vk::SemaphoreSubmitInfo::default().semaphore(sem).value(3).stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
        sync2.queue_submit2(ctx.queues[3], &[vk::SubmitInfo2::default().wait_semaphore_infos(&w2).signal_semaphore_infos(&s2)], vk::Fence::null()).unwrap();

        let sems = [sem];
        let v3 = [3u64];
        assert_eq!(tl.wait_semaphores(&vk::SemaphoreWaitInfo::default().semaphores(&sems).values(&v3), 0), Err(vk::Result::TIMEOUT));
        assert_eq!(d.wait_for_fences(&[f], true, 10_000_000), Err(vk::Result::TIMEOUT), "the queue waits for the host signal");

        let signaller = {
            let d = d.clone();
            let tl = ash::khr::timeline_semaphore::Device::new(&ctx.instance, &d);
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(20));
                tl.signal_semaphore(&vk::SemaphoreSignalInfo::default().semaphore(sem).value(1)).unwrap();
            })
        };
        // Host wait on another thread too.
        let waiter = {
            let tl = ash::khr::timeline_semaphore::Device::new(&ctx.instance, &d);
            std::thread::spawn(move || {
                let sems = [sem];
                let v = [3u64];
                tl.wait_semaphores(&vk::SemaphoreWaitInfo::default().semaphores(&sems).values(&v), u64::MAX)
            })
        };
        tl.wait_semaphores(&vk::SemaphoreWaitInfo::default().semaphores(&sems).values(&v3), u64::MAX).unwrap();
        assert_eq!(waiter.join().unwrap(), Ok(()));
        signaller.join().unwrap();
        assert_eq!(tl.get_semaphore_counter_value(sem), Ok(3));
        d.wait_for_fences(&[f], true, u64::MAX).unwrap();

        // waitAny: one of two values reached.
        let other = timeline(&d, 5);
        let two = [sem, other];
        let vals = [100u64, 5];
        let any = vk::SemaphoreWaitInfo::default().flags(vk::SemaphoreWaitFlags::ANY).semaphores(&two).values(&vals);
        tl.wait_semaphores(&any, 0).unwrap();
        let all = vk::SemaphoreWaitInfo::default().semaphores(&two).values(&vals);
        assert_eq!(tl.wait_semaphores(&all, 1_000_000), Err(vk::Result::TIMEOUT));

        d.device_wait_idle().unwrap();
        d.destroy_semaphore(other, None);
        d.destroy_semaphore(sem, None);
        d.destroy_fence(f, None);
    }
    ctx.finish();
}

/// A binary semaphore orders two queues: queue 1 waits for what queue 0 signals.
#[test]
fn binary_semaphore_between_queues() {
    let ctx = harness::context();
    let d = &ctx.device;
    // SAFETY: objects created here; destroyed at the end after the device is idle.
    unsafe {
        let sem = d.create_semaphore(&vk::SemaphoreCreateInfo::default(), None).unwrap();
        let event = d.create_event(&vk::EventCreateInfo::default(), None).unwrap();
        let pool = command_pool(&ctx);
        let cb = command_buffer(d, pool);
        begin(d, cb);
        d.cmd_wait_events(cb, &[event], vk::PipelineStageFlags::HOST, vk::PipelineStageFlags::TRANSFER, &[], &[], &[]);
        d.end_command_buffer(cb).unwrap();
        let (f0, f1) = (fence(d, false), fence(d, false));
        let cbs = [cb];
        let sems = [sem];
        let stages = [vk::PipelineStageFlags::ALL_COMMANDS];
        // Queue 0: blocked on the event, then signals the semaphore.
        d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs).signal_semaphores(&sems)], f0).unwrap();
        // Queue 1: waits for the semaphore.
        d.queue_submit(ctx.queues[1], &[vk::SubmitInfo::default().wait_semaphores(&sems).wait_dst_stage_mask(&stages)], f1).unwrap();
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(d.get_fence_status(f1), Ok(false), "queue 1 waits for queue 0");
        d.set_event(event).unwrap();
        d.wait_for_fences(&[f0, f1], true, u64::MAX).unwrap();
        d.device_wait_idle().unwrap();
        d.destroy_fence(f0, None);
        d.destroy_fence(f1, None);
        d.destroy_semaphore(sem, None);
        d.destroy_event(event, None);
        d.destroy_command_pool(pool, None);
    }
    ctx.finish();
}

#[derive(Clone, Copy)]
struct Mapped(usize);

/// A thread's work: re-record a fill of its own buffer with `value`, submit, wait, check.
fn fill_and_check(d: &ash::Device, queue: impl Fn(&dyn Fn(vk::Queue)), cb: vk::CommandBuffer, f: vk::Fence, buffer: vk::Buffer, mapped: Mapped, value: u32) {
    // SAFETY: the command buffer, fence and buffer belong to this thread; the queue is used
    // under the caller's external synchronisation.
    unsafe {
        d.reset_command_buffer(cb, vk::CommandBufferResetFlags::empty()).unwrap();
        begin(d, cb);
        d.cmd_fill_buffer(cb, buffer, 0, vk::WHOLE_SIZE, value);
        d.end_command_buffer(cb).unwrap();
        let cbs = [cb];
        queue(&|q| d.queue_submit(q, &[vk::SubmitInfo::default().command_buffers(&cbs)], f).unwrap());
        d.wait_for_fences(&[f], true, u64::MAX).unwrap();
        d.reset_fences(&[f]).unwrap();
        let words = std::slice::from_raw_parts(mapped.0 as *const u32, 64);
        assert!(words.iter().all(|w| *w == value), "fill of {value:#x} visible after the fence");
    }
}

struct ThreadObjects {
    pool: vk::CommandPool,
    cb: vk::CommandBuffer,
    fence: vk::Fence,
    buffer: vk::Buffer,
    memory: vk::DeviceMemory,
    mapped: Mapped,
}

fn thread_objects(ctx: &harness::Context, n: usize) -> Vec<ThreadObjects> {
    (0..n)
        .map(|_| {
            let pool = command_pool(ctx);
            let (buffer, memory, ptr) = ctx.host_buffer(256, vk::BufferUsageFlags::TRANSFER_DST);
            ThreadObjects { pool, cb: command_buffer(&ctx.device, pool), fence: fence(&ctx.device, false), buffer, memory, mapped: Mapped(ptr as usize) }
        })
        .collect()
}

fn destroy_thread_objects(ctx: &harness::Context, objs: Vec<ThreadObjects>) {
    for o in objs {
        // SAFETY: the device is idle; each object is destroyed once.
        unsafe {
            ctx.device.destroy_fence(o.fence, None);
            ctx.device.destroy_command_pool(o.pool, None);
            ctx.device.destroy_buffer(o.buffer, None);
            ctx.device.free_memory(o.memory, None);
        }
    }
}

/// Four threads, each submitting to its own queue, many times.
#[test]
fn many_threads_each_with_its_own_queue() {
    let ctx = harness::context();
    let objs = thread_objects(&ctx, 4);
    let start = Arc::new(Barrier::new(4));
    std::thread::scope(|s| {
        for (i, o) in objs.iter().enumerate() {
            let d = ctx.device.clone();
            let q = ctx.queues[i];
            let start = start.clone();
            let (cb, f, buffer, mapped) = (o.cb, o.fence, o.buffer, o.mapped);
            s.spawn(move || {
                start.wait();
                for n in 0..40u32 {
                    fill_and_check(&d, |submit| submit(q), cb, f, buffer, mapped, (i as u32) << 16 | n);
                }
            });
        }
    });
    // SAFETY: plain idle waits.
    unsafe {
        for q in &ctx.queues {
            ctx.device.queue_wait_idle(*q).unwrap();
        }
        ctx.device.device_wait_idle().unwrap();
    }
    destroy_thread_objects(&ctx, objs);
    ctx.finish();
}

/// Four threads sharing one queue under a Mutex (the application's external synchronisation).
#[test]
fn many_threads_one_queue_under_a_mutex() {
    let ctx = harness::context();
    let objs = thread_objects(&ctx, 4);
    let queue = Arc::new(Mutex::new(ctx.queues[0]));
    std::thread::scope(|s| {
        for (i, o) in objs.iter().enumerate() {
            let d = ctx.device.clone();
            let queue = queue.clone();
            let (cb, f, buffer, mapped) = (o.cb, o.fence, o.buffer, o.mapped);
            s.spawn(move || {
                for n in 0..40u32 {
                    fill_and_check(&d, |submit| submit(*queue.lock().unwrap()), cb, f, buffer, mapped, 0xA000_0000 | (i as u32) << 16 | n);
                }
            });
        }
    });
    // SAFETY: plain idle wait.
    unsafe { ctx.device.queue_wait_idle(ctx.queues[0]).unwrap() };
    destroy_thread_objects(&ctx, objs);
    ctx.finish();
}

/// vkQueueWaitIdle returns only after the queue's work is done (the work is held by an event).
#[test]
fn queue_wait_idle_waits_for_the_work() {
    let ctx = harness::context();
    let d = &ctx.device;
    // SAFETY: objects created here; destroyed after the device is idle.
    unsafe {
        let event = d.create_event(&vk::EventCreateInfo::default(), None).unwrap();
        let pool = command_pool(&ctx);
        let cb = command_buffer(d, pool);
        begin(d, cb);
        d.cmd_wait_events(cb, &[event], vk::PipelineStageFlags::HOST, vk::PipelineStageFlags::TRANSFER, &[], &[], &[]);
        d.end_command_buffer(cb).unwrap();
        let cbs = [cb];
        d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs)], vk::Fence::null()).unwrap();
        let setter = {
            let d = d.clone();
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(50));
                d.set_event(event).unwrap();
            })
        };
        let t = Instant::now();
        d.queue_wait_idle(ctx.queues[0]).unwrap();
        assert!(t.elapsed() >= Duration::from_millis(40), "returned before the event was set");
        setter.join().unwrap();
        d.device_wait_idle().unwrap();
        d.destroy_event(event, None);
        d.destroy_command_pool(pool, None);
    }
    ctx.finish();
}

/// Destroying a device whose queue is blocked (a wait that will never be satisfied) stops the
/// worker instead of hanging. Deliberately invalid usage, so without the validation layer.
#[test]
fn destroying_a_device_with_a_blocked_queue_does_not_hang() {
    let ctx = harness::Context::new(harness::Options { validation: false, ..Default::default() });
    let d = ctx.device.clone();
    // SAFETY: deliberately destroys a device with pending work (the driver must cope); the
    // context is then forgotten so it does not touch the destroyed device.
    unsafe {
        let sem = timeline(&d, 0);
        let waits = [sem];
        let stages = [vk::PipelineStageFlags::ALL_COMMANDS];
        let wv = [1u64];
        let mut tsi = vk::TimelineSemaphoreSubmitInfo::default().wait_semaphore_values(&wv);
        let submit = vk::SubmitInfo::default().wait_semaphores(&waits).wait_dst_stage_mask(&stages).push_next(&mut tsi);
        d.queue_submit(ctx.queues[0], &[submit], vk::Fence::null()).unwrap();
        d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default()], vk::Fence::null()).unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        let d2 = d.clone();
        std::thread::spawn(move || {
            d2.destroy_semaphore(sem, None);
            d2.destroy_device(None);
            let _ = tx.send(());
        });
        assert!(rx.recv_timeout(Duration::from_secs(10)).is_ok(), "vkDestroyDevice hung on a blocked queue");
    }
    std::mem::forget(ctx);
}

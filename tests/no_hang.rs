//! No host wait outlasts a stall: each test here hung before the stall rule (`runtime::stall`),
//! and runs under `harness::bounded` so a regression fails instead of hanging the run.
//!
//! The validation layer is off (these uses are invalid on purpose); Arbor's diagnostics are
//! checked instead. The grace period is shortened to 300 ms (`ARBOR_STALL_MS`, read once per
//! process: every test sets the same value before its first Vulkan call).
mod harness;

use std::time::{Duration, Instant};

use ash::vk;
use harness::vuid::*;
use harness::{bounded, diagnostics};

/// Longest any test may take; a hang fails the test after this.
const BOUND_S: u64 = 20;
/// What a stalled wait may take at most (the grace period is 300 ms).
const PROMPT: Duration = Duration::from_secs(5);

fn stall_ms() {
    std::env::set_var("ARBOR_STALL_MS", "300");
}

/// Diagnostics reported while `f` ran (the tests hold `serial()`).
fn reported_by<R>(f: impl FnOnce() -> R) -> (R, String) {
    let mark = diagnostics().len();
    let r = f();
    (r, diagnostics()[mark..].to_string())
}

fn timeline(d: &ash::Device, initial: u64) -> vk::Semaphore {
    let mut ty = vk::SemaphoreTypeCreateInfo::default().semaphore_type(vk::SemaphoreType::TIMELINE).initial_value(initial);
    // SAFETY: valid create info; the caller destroys it.
    unsafe { d.create_semaphore(&vk::SemaphoreCreateInfo::default().push_next(&mut ty), None) }.unwrap()
}

fn fence(d: &ash::Device) -> vk::Fence {
    // SAFETY: valid create info; the caller destroys it.
    unsafe { d.create_fence(&vk::FenceCreateInfo::default(), None) }.unwrap()
}

/// A command buffer of `a.pool`, recorded by `f`.
fn recorded(a: &Accel, f: impl FnOnce(vk::CommandBuffer)) -> vk::CommandBuffer {
    let d = &a.ctx.device;
    // SAFETY: valid pool; the command buffer is freed with the pool.
    unsafe {
        let cb = d.allocate_command_buffers(&vk::CommandBufferAllocateInfo::default().command_pool(a.pool).command_buffer_count(1)).unwrap()[0];
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        f(cb);
        d.end_command_buffer(cb).unwrap();
        cb
    }
}

/// The device still builds and traverses after the test's stall.
fn still_works(a: &Accel, m: &Mesh) {
    valid_blas(a, m, vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE);
}

#[test]
fn property_query_after_a_rejected_build_becomes_available() {
    bounded(BOUND_S, || {
        let _s = serial();
        stall_ms();
        let ctx = context();
        let a = Accel::new(&ctx);
        let m = upload_grid(&a);
        let d = &ctx.device;
        let (victim, scratch) = valid_blas(&a, &m, NO_FLAGS);
        // Misaligned scratch (03710): the build is rejected and its destination marked invalid.
        let geoms = [mesh_geom(&a, &m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(&a) + 64));
        cmd_build(&a, &[inf], &[&[range(m.count)]]);
        assert!(header_of(&a, &victim).is_none());
        let ty = vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR;
        // SAFETY: valid create info; destroyed below.
        let pool = unsafe { d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(ty).query_count(1), None) }.unwrap();
        let (_, said) = reported_by(|| {
            a.submit(|cb| {
                // SAFETY: recording command buffer, valid pool and structure.
                unsafe {
                    d.cmd_reset_query_pool(cb, pool, 0, 1);
                    a.ext.cmd_write_acceleration_structures_properties(cb, &[victim.s], ty, pool, 0);
                }
            })
        });
        assert!(said.contains("pAccelerationStructures-04964"), "the query of the invalid structure is reported:\n{said}");
        let mut out = [[0xA5A5u64; 2]; 1];
        let flags = vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT | vk::QueryResultFlags::WITH_AVAILABILITY;
        // SAFETY: valid pool; one query of two u64.
        let r = unsafe { d.get_query_pool_results(pool, 0, &mut out, flags) };
        assert_eq!(r, Ok(()), "WAIT returns: the command executed, so its query is available");
        assert_eq!(out[0], [0, 1], "value 0, available");
        // SAFETY: the pool is idle.
        unsafe { d.destroy_query_pool(pool, None) };
        still_works(&a, &m);
        a.destroy();
        ctx.finish();
    });
}

#[test]
fn wait_on_queries_nothing_writes_returns_not_ready() {
    bounded(BOUND_S, || {
        let _s = serial();
        stall_ms();
        let ctx = context();
        let a = Accel::new(&ctx);
        let m = upload_grid(&a);
        let d = &ctx.device;
        // SAFETY: valid create info; destroyed below.
        let pool = unsafe { d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(3), None) }.unwrap();
        a.submit(|cb| {
            // SAFETY: recording command buffer; query 0 is written, 1 and 2 never are.
            unsafe {
                d.cmd_reset_query_pool(cb, pool, 0, 3);
                d.cmd_write_timestamp(cb, vk::PipelineStageFlags::ALL_COMMANDS, pool, 0);
            }
        });
        let mut out = [0u64; 3];
        let t = Instant::now();
        // SAFETY: valid pool.
        let (r, said) = reported_by(|| unsafe { d.get_query_pool_results(pool, 0, &mut out, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT) });
        assert_eq!(r, Err(vk::Result::NOT_READY));
        assert!(t.elapsed() < PROMPT, "took {:?}", t.elapsed());
        assert!(said.contains("vkGetQueryPoolResults: [stall] WAIT on queries 1, 2 of query pool"), "the stall names the queries:\n{said}");
        // SAFETY: the pool is idle.
        unsafe { d.destroy_query_pool(pool, None) };
        still_works(&a, &m);
        a.destroy();
        ctx.finish();
    });
}

#[test]
fn fence_and_semaphore_waits_that_nothing_can_end_time_out() {
    bounded(BOUND_S, || {
        let _s = serial();
        stall_ms();
        let ctx = context();
        let a = Accel::new(&ctx);
        let m = upload_grid(&a);
        let d = &ctx.device;
        let tl = ash::khr::timeline_semaphore::Device::new(&ctx.instance, d);
        let (f, sem) = (fence(d), timeline(d, 2));
        let t = Instant::now();
        // SAFETY: a fence never submitted, waited on with an infinite timeout.
        let (r, said) = reported_by(|| unsafe { d.wait_for_fences(&[f], true, u64::MAX) });
        assert_eq!(r, Err(vk::Result::TIMEOUT));
        assert!(said.contains("vkWaitForFences: [stall] fences not signalled:") && said.contains("never submitted"), "{said}");
        let sems = [sem];
        let values = [5u64];
        // SAFETY: a timeline value no pending signal reaches.
        let (r, said) = reported_by(|| unsafe { tl.wait_semaphores(&vk::SemaphoreWaitInfo::default().semaphores(&sems).values(&values), u64::MAX) });
        assert_eq!(r, Err(vk::Result::TIMEOUT));
        assert!(said.contains("vkWaitSemaphores: [stall] timeline semaphores short of their values:") && said.contains("at 2 waiting for 5"), "{said}");
        assert!(t.elapsed() < 2 * PROMPT, "took {:?}", t.elapsed());
        // A value the host signals in time is not a stall.
        let signaller = {
            let tl = tl.clone();
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(20));
                // SAFETY: live semaphore.
                unsafe { tl.signal_semaphore(&vk::SemaphoreSignalInfo::default().semaphore(sem).value(5)) }.unwrap();
            })
        };
        // SAFETY: as above.
        let (r, said) = reported_by(|| unsafe { tl.wait_semaphores(&vk::SemaphoreWaitInfo::default().semaphores(&sems).values(&values), u64::MAX) });
        assert_eq!(r, Ok(()));
        assert!(!said.contains("[stall]"), "{said}");
        signaller.join().unwrap();
        // SAFETY: nothing pending uses them.
        unsafe {
            d.destroy_fence(f, None);
            d.destroy_semaphore(sem, None);
        }
        still_works(&a, &m);
        a.destroy();
        ctx.finish();
    });
}

#[test]
fn queue_blocked_on_a_semaphore_nobody_signals() {
    bounded(BOUND_S, || {
        let _s = serial();
        stall_ms();
        let ctx = context();
        let a = Accel::new(&ctx);
        let m = upload_grid(&a);
        let d = &ctx.device;
        let (f, sem) = (fence(d), timeline(d, 0));
        let marker = guarded(&a, 4);
        let (buf, off) = (a.buf(marker.buf).buffer, marker.offset);
        // SAFETY: valid objects; the submission waits for value 1, which nobody signals.
        let cb = recorded(&a, |cb| unsafe { d.cmd_fill_buffer(cb, buf, off, 4, 0x1234_5678) });
        let (waits, stages, cbs, wv) = ([sem], [vk::PipelineStageFlags::ALL_COMMANDS], [cb], [1u64]);
        let mut tsi = vk::TimelineSemaphoreSubmitInfo::default().wait_semaphore_values(&wv);
        let submit = vk::SubmitInfo::default().wait_semaphores(&waits).wait_dst_stage_mask(&stages).command_buffers(&cbs).push_next(&mut tsi);
        // SAFETY: as above.
        unsafe { d.queue_submit(ctx.queues[0], &[submit], f) }.unwrap();
        // SAFETY: the fence of that submission.
        let (r, said) = reported_by(|| unsafe { d.wait_for_fences(&[f], true, u64::MAX) });
        assert_eq!(r, Err(vk::Result::TIMEOUT));
        assert!(said.contains("its submission is blocked"), "{said}");
        // vkQueueWaitIdle abandons the blocked submission: its fence fires, its commands don't run.
        // SAFETY: valid queue.
        let (r, said) = reported_by(|| unsafe { d.queue_wait_idle(ctx.queues[0]) });
        assert_eq!(r, Ok(()));
        assert!(said.contains("vkQueueWaitIdle: [stall] queue (family 0, index 0) is blocked"), "{said}");
        // SAFETY: as above.
        assert_eq!(unsafe { d.get_fence_status(f) }, Ok(true));
        assert_eq!(marker.read(&a), vec![FILL; 4], "the abandoned command did not run");
        // The same blocked state reached through vkCmdWaitEvents and vkDeviceWaitIdle.
        // SAFETY: valid create info; destroyed below.
        let event = unsafe { d.create_event(&vk::EventCreateInfo::default(), None) }.unwrap();
        let stage = vk::PipelineStageFlags::ALL_COMMANDS;
        // SAFETY: an event nobody sets.
        let cb2 = recorded(&a, |cb| unsafe { d.cmd_wait_events(cb, &[event], stage, stage, &[], &[], &[]) });
        let cbs2 = [cb2];
        // SAFETY: as above.
        unsafe { d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs2)], vk::Fence::null()) }.unwrap();
        // SAFETY: valid device.
        let (r, said) = reported_by(|| unsafe { d.device_wait_idle() });
        assert_eq!(r, Ok(()));
        assert!(said.contains("vkDeviceWaitIdle: [stall] queue (family 0, index 0) is blocked"), "{said}");
        // SAFETY: the queue is idle.
        unsafe {
            d.destroy_event(event, None);
            d.destroy_fence(f, None);
            d.destroy_semaphore(sem, None);
        }
        still_works(&a, &m);
        a.destroy();
        ctx.finish();
    });
}

const STRICT_CHILD: &str = "strict_child_stalled_waits_lose_the_device";

#[test]
fn strict_mode_turns_a_stalled_wait_into_device_lost() {
    bounded(BOUND_S, || {
        stall_ms();
        let text = harness::child::run_child_test(STRICT_CHILD, &[("ARBOR_STRICT", "1")]);
        assert!(text.contains("strict child: device lost as expected"), "the strict-mode child skipped its checks:\n{text}");
    });
}

#[test]
#[ignore = "run by strict_mode_turns_a_stalled_wait_into_device_lost in a child process with ARBOR_STRICT=1"]
fn strict_child_stalled_waits_lose_the_device() {
    if std::env::var("ARBOR_STRICT").as_deref() != Ok("1") {
        return;
    }
    stall_ms();
    let ctx = context();
    let d = &ctx.device;
    // SAFETY: valid create info.
    let pool = unsafe { d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(1), None) }.unwrap();
    let a = Accel::new(&ctx);
    // SAFETY: recording command buffer, valid pool.
    a.submit(|cb| unsafe { d.cmd_reset_query_pool(cb, pool, 0, 1) });
    let mut out = [0u64; 1];
    // SAFETY: valid pool.
    let r = unsafe { d.get_query_pool_results(pool, 0, &mut out, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT) };
    assert_eq!(r, Err(vk::Result::ERROR_DEVICE_LOST));
    let f = fence(d);
    // SAFETY: a fence never submitted, on a lost device.
    assert_eq!(unsafe { d.wait_for_fences(&[f], true, u64::MAX) }, Err(vk::Result::ERROR_DEVICE_LOST));
    // SAFETY: nothing pending.
    unsafe {
        d.destroy_fence(f, None);
        d.destroy_query_pool(pool, None);
    }
    println!("strict child: device lost as expected");
}

//! Timestamp query pools through the real loader with validation on: timestamps in order,
//! vkGetQueryPoolResults with every flag combination, vkCmdCopyQueryPoolResults, host reset.
mod harness;

use ash::vk;
use ash::vk::Handle;

fn timestamp_pool(ctx: &harness::Context, count: u32) -> vk::QueryPool {
    let info = vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(count);
    // SAFETY: valid create info.
    unsafe { ctx.device.create_query_pool(&info, None) }.unwrap()
}

fn host_reset(ctx: &harness::Context) -> vk::PFN_vkResetQueryPool {
    // SAFETY: VK_EXT_host_query_reset is enabled by the harness; the name resolves to vkResetQueryPool's type.
    unsafe {
        let f = ctx.instance.get_device_proc_addr(ctx.device.handle(), c"vkResetQueryPoolEXT".as_ptr()).expect("vkResetQueryPoolEXT");
        std::mem::transmute::<unsafe extern "system" fn(), vk::PFN_vkResetQueryPool>(f)
    }
}

fn one_command_buffer(ctx: &harness::Context) -> (vk::CommandPool, vk::CommandBuffer) {
    // SAFETY: valid create/allocate infos.
    unsafe {
        let pool = ctx
            .device
            .create_command_pool(&vk::CommandPoolCreateInfo::default().queue_family_index(0).flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER), None)
            .unwrap();
        let info = vk::CommandBufferAllocateInfo::default().command_pool(pool).level(vk::CommandBufferLevel::PRIMARY).command_buffer_count(1);
        (pool, ctx.device.allocate_command_buffers(&info).unwrap()[0])
    }
}

fn submit_wait(ctx: &harness::Context, cb: vk::CommandBuffer) {
    // SAFETY: valid submission; the fence is destroyed after it signalled.
    unsafe {
        let f = ctx.device.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        let cbs = [cb];
        ctx.device.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs)], f).unwrap();
        ctx.device.wait_for_fences(&[f], true, u64::MAX).unwrap();
        ctx.device.destroy_fence(f, None);
    }
}

/// Raw vkGetQueryPoolResults with an explicit stride.
fn raw_results(ctx: &harness::Context, pool: vk::QueryPool, first: u32, count: u32, out: &mut [u8], stride: u64, flags: vk::QueryResultFlags) -> vk::Result {
    // SAFETY: `out` is valid for out.len() bytes.
    unsafe { (ctx.device.fp_v1_0().get_query_pool_results)(ctx.device.handle(), pool, first, count, out.len(), out.as_mut_ptr().cast(), stride, flags) }
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

#[test]
fn timestamps_increase_within_and_across_submissions() {
    let ctx = harness::context();
    let sync2 = ash::khr::synchronization2::Device::new(&ctx.instance, &ctx.device);
    let qp = timestamp_pool(&ctx, 6);
    let (pool, cb) = one_command_buffer(&ctx);
    let d = &ctx.device;
    // SAFETY: recording valid commands; the queue is idle between uses.
    unsafe {
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        d.cmd_reset_query_pool(cb, qp, 0, 6);
        d.cmd_write_timestamp(cb, vk::PipelineStageFlags::TOP_OF_PIPE, qp, 0);
        d.cmd_write_timestamp(cb, vk::PipelineStageFlags::BOTTOM_OF_PIPE, qp, 1);
        sync2.cmd_write_timestamp2(cb, vk::PipelineStageFlags2::ALL_COMMANDS, qp, 2);
        d.end_command_buffer(cb).unwrap();
    }
    submit_wait(&ctx, cb);
    // SAFETY: as above.
    unsafe {
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        d.cmd_write_timestamp(cb, vk::PipelineStageFlags::BOTTOM_OF_PIPE, qp, 3);
        sync2.cmd_write_timestamp2(cb, vk::PipelineStageFlags2::ALL_COMMANDS, qp, 4);
        d.end_command_buffer(cb).unwrap();
    }
    std::thread::sleep(std::time::Duration::from_millis(1));
    submit_wait(&ctx, cb);
    let mut ts = [0u64; 5];
    // SAFETY: reading results of written queries.
    unsafe { d.get_query_pool_results(qp, 0, &mut ts, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT) }.unwrap();
    assert!(ts[0] > 0);
    assert!(ts[0] <= ts[1] && ts[1] <= ts[2], "in order within a command buffer: {ts:?}");
    assert!(ts[2] < ts[3] && ts[3] <= ts[4], "later submissions read later times: {ts:?}");
    assert!(ts[3] - ts[2] >= 1_000_000, "the 1 ms sleep shows in ns (timestampPeriod = 1): {ts:?}");
    // SAFETY: the device is idle.
    unsafe {
        d.destroy_command_pool(pool, None);
        d.destroy_query_pool(qp, None);
    }
    ctx.finish();
}

#[test]
fn query_results_with_every_flag_combination() {
    let ctx = harness::context();
    let reset = host_reset(&ctx);
    let qp = timestamp_pool(&ctx, 4);
    let d = &ctx.device;
    // SAFETY: valid host reset of the whole pool.
    unsafe { reset(d.handle(), qp, 0, 4) };

    // Nothing written yet: NOT_READY, values untouched, availability 0.
    let mut out = vec![0xABu8; 64];
    assert_eq!(raw_results(&ctx, qp, 0, 4, &mut out[..32], 8, vk::QueryResultFlags::TYPE_64), vk::Result::NOT_READY);
    assert!(out.iter().all(|b| *b == 0xAB), "no value written for unavailable queries");
    assert_eq!(raw_results(&ctx, qp, 0, 4, &mut out, 16, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WITH_AVAILABILITY), vk::Result::NOT_READY);
    for q in 0..4 {
        assert_eq!(u64_at(&out, q * 16), 0xABAB_ABAB_ABAB_ABAB);
        assert_eq!(u64_at(&out, q * 16 + 8), 0, "availability 0");
    }

    // Write queries 0 and 2.
    let (pool, cb) = one_command_buffer(&ctx);
    // SAFETY: recording valid commands.
    unsafe {
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        d.cmd_write_timestamp(cb, vk::PipelineStageFlags::BOTTOM_OF_PIPE, qp, 0);
        d.cmd_write_timestamp(cb, vk::PipelineStageFlags::BOTTOM_OF_PIPE, qp, 2);
        d.end_command_buffer(cb).unwrap();
    }
    submit_wait(&ctx, cb);
    let mut t = [0u64; 1];
    // SAFETY: query 0 is written.
    unsafe { d.get_query_pool_results(qp, 0, &mut t, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT) }.unwrap();
    let t0 = t[0];

    // 64-bit with availability, stride 24 (larger than needed): 0 and 2 available.
    let mut out = vec![0xCDu8; 24 * 3 + 16];
    assert_eq!(raw_results(&ctx, qp, 0, 4, &mut out, 24, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WITH_AVAILABILITY), vk::Result::NOT_READY);
    assert_eq!(u64_at(&out, 0), t0);
    assert_eq!(u64_at(&out, 8), 1);
    assert_eq!(u64_at(&out, 16), 0xCDCD_CDCD_CDCD_CDCD, "the gap of the stride is untouched");
    assert_eq!(u64_at(&out, 24), 0xCDCD_CDCD_CDCD_CDCD, "unavailable value untouched");
    assert_eq!(u64_at(&out, 32), 0);
    assert_ne!(u64_at(&out, 48), 0xCDCD_CDCD_CDCD_CDCD);
    assert_eq!(u64_at(&out, 56), 1);
    assert_eq!(u64_at(&out, 80), 0);

    // 32-bit values (low bits of the 64-bit time), with and without availability.
    let mut out = vec![0u8; 8];
    assert_eq!(raw_results(&ctx, qp, 0, 1, &mut out[..4], 4, vk::QueryResultFlags::empty()), vk::Result::SUCCESS);
    assert_eq!(u32_at(&out, 0), t0 as u32);
    assert_eq!(raw_results(&ctx, qp, 0, 1, &mut out, 8, vk::QueryResultFlags::WITH_AVAILABILITY), vk::Result::SUCCESS);
    assert_eq!((u32_at(&out, 0), u32_at(&out, 4)), (t0 as u32, 1));
    let mut out = vec![0u8; 16];
    assert_eq!(raw_results(&ctx, qp, 1, 2, &mut out, 8, vk::QueryResultFlags::WITH_AVAILABILITY), vk::Result::NOT_READY);
    assert_eq!(u32_at(&out, 4), 0);
    assert_eq!(u32_at(&out, 12), 1);
    // WAIT on available queries returns at once with SUCCESS.
    let mut out = vec![0u8; 8];
    assert_eq!(raw_results(&ctx, qp, 2, 1, &mut out, 8, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT), vk::Result::SUCCESS);

    // Host reset: unavailable again.
    // SAFETY: the queue is idle.
    unsafe { reset(d.handle(), qp, 0, 4) };
    let mut out = vec![0u8; 16];
    assert_eq!(raw_results(&ctx, qp, 0, 1, &mut out, 16, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WITH_AVAILABILITY), vk::Result::NOT_READY);
    assert_eq!(u64_at(&out, 8), 0);
    // SAFETY: the device is idle.
    unsafe {
        d.destroy_command_pool(pool, None);
        d.destroy_query_pool(qp, None);
    }
    ctx.finish();
}

/// WAIT blocks until the queue writes the query (the queue is held by an event).
#[test]
fn wait_flag_blocks_until_the_query_is_written() {
    let ctx = harness::context();
    let reset = host_reset(&ctx);
    let qp = timestamp_pool(&ctx, 1);
    let d = &ctx.device;
    let (pool, cb) = one_command_buffer(&ctx);
    // SAFETY: objects created here; destroyed after the device is idle.
    unsafe {
        reset(d.handle(), qp, 0, 1);
        let event = d.create_event(&vk::EventCreateInfo::default(), None).unwrap();
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        d.cmd_wait_events(cb, &[event], vk::PipelineStageFlags::HOST, vk::PipelineStageFlags::TRANSFER, &[], &[], &[]);
        d.cmd_write_timestamp(cb, vk::PipelineStageFlags::BOTTOM_OF_PIPE, qp, 0);
        d.end_command_buffer(cb).unwrap();
        let cbs = [cb];
        d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs)], vk::Fence::null()).unwrap();
        let mut t = [0u64; 1];
        assert_eq!(d.get_query_pool_results(qp, 0, &mut t, vk::QueryResultFlags::TYPE_64), Err(vk::Result::NOT_READY));
        let setter = {
            let d = d.clone();
            let raw = event.as_raw();
            std::thread::spawn(move || {
                std::thread::sleep(std::time::Duration::from_millis(20));
                d.set_event(vk::Event::from_raw(raw)).unwrap();
            })
        };
        d.get_query_pool_results(qp, 0, &mut t, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT).unwrap();
        assert!(t[0] > 0);
        setter.join().unwrap();
        d.device_wait_idle().unwrap();
        d.destroy_event(event, None);
        d.destroy_command_pool(pool, None);
        d.destroy_query_pool(qp, None);
    }
    ctx.finish();
}

#[test]
fn copy_query_pool_results_into_a_buffer() {
    let ctx = harness::context();
    let qp = timestamp_pool(&ctx, 3);
    let d = &ctx.device;
    let (buffer, memory, ptr) = ctx.host_buffer(256, vk::BufferUsageFlags::TRANSFER_DST);
    // SAFETY: the mapping covers the buffer; read only while the queue is idle.
    let bytes = unsafe { std::slice::from_raw_parts_mut(ptr, 256) };
    bytes.fill(0xEE);
    let (pool, cb) = one_command_buffer(&ctx);
    // SAFETY: recording valid commands.
    unsafe {
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        d.cmd_reset_query_pool(cb, qp, 0, 3);
        d.cmd_write_timestamp(cb, vk::PipelineStageFlags::BOTTOM_OF_PIPE, qp, 0);
        d.cmd_write_timestamp(cb, vk::PipelineStageFlags::BOTTOM_OF_PIPE, qp, 1);
        // [0, 48): 64-bit + availability, stride 16, all three (query 2 unavailable).
        d.cmd_copy_query_pool_results(cb, qp, 0, 3, buffer, 0, 16, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WITH_AVAILABILITY);
        // [64, 72): 32-bit, stride 4, queries 0 and 1, waiting for them.
        d.cmd_copy_query_pool_results(cb, qp, 0, 2, buffer, 64, 4, vk::QueryResultFlags::WAIT);
        // [128, 144): 64-bit, stride 8, queries 0 and 1.
        d.cmd_copy_query_pool_results(cb, qp, 0, 2, buffer, 128, 8, vk::QueryResultFlags::TYPE_64);
        d.end_command_buffer(cb).unwrap();
    }
    submit_wait(&ctx, cb);
    let mut ts = [0u64; 2];
    // SAFETY: queries 0 and 1 are written.
    unsafe { d.get_query_pool_results(qp, 0, &mut ts, vk::QueryResultFlags::TYPE_64) }.unwrap();
    assert_eq!([u64_at(bytes, 0), u64_at(bytes, 8)], [ts[0], 1]);
    assert_eq!([u64_at(bytes, 16), u64_at(bytes, 24)], [ts[1], 1]);
    assert_eq!(u64_at(bytes, 32), 0xEEEE_EEEE_EEEE_EEEE, "unavailable value not written");
    assert_eq!(u64_at(bytes, 40), 0, "availability 0");
    assert_eq!([u32_at(bytes, 64), u32_at(bytes, 68)], [ts[0] as u32, ts[1] as u32]);
    assert_eq!(u32_at(bytes, 72), 0xEEEE_EEEE);
    assert_eq!([u64_at(bytes, 128), u64_at(bytes, 136)], ts);
    assert_eq!(u64_at(bytes, 144), 0xEEEE_EEEE_EEEE_EEEE);
    // SAFETY: the device is idle.
    unsafe {
        d.destroy_command_pool(pool, None);
        d.destroy_query_pool(qp, None);
        d.destroy_buffer(buffer, None);
        d.free_memory(memory, None);
    }
    ctx.finish();
}

//! Command buffers through the real loader with validation on: transfer commands verified byte
//! for byte (including ordering inside one command buffer), secondary command buffers,
//! reset/re-record, ONE_TIME_SUBMIT and SIMULTANEOUS_USE.
mod harness;

use ash::vk;

const USAGE: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(vk::BufferUsageFlags::TRANSFER_SRC.as_raw() | vk::BufferUsageFlags::TRANSFER_DST.as_raw());

struct Buf {
    buffer: vk::Buffer,
    memory: vk::DeviceMemory,
    ptr: *mut u8,
    size: usize,
}

impl Buf {
    fn new(ctx: &harness::Context, size: usize) -> Buf {
        let (buffer, memory, ptr) = ctx.host_buffer(size as u64, USAGE);
        Buf { buffer, memory, ptr, size }
    }

    fn bytes(&self) -> &[u8] {
        // SAFETY: the mapping covers the whole buffer; tests touch it only while the queue is idle.
        unsafe { std::slice::from_raw_parts(self.ptr, self.size) }
    }

    fn bytes_mut(&mut self) -> &mut [u8] {
        // SAFETY: as for `bytes`; `&mut self` keeps this the only view the test holds.
        unsafe { std::slice::from_raw_parts_mut(self.ptr, self.size) }
    }

    fn destroy(self, ctx: &harness::Context) {
        // SAFETY: the device is idle; destroyed once.
        unsafe {
            ctx.device.destroy_buffer(self.buffer, None);
            ctx.device.free_memory(self.memory, None);
        }
    }
}

fn pool(ctx: &harness::Context, flags: vk::CommandPoolCreateFlags) -> vk::CommandPool {
    // SAFETY: valid create info.
    unsafe { ctx.device.create_command_pool(&vk::CommandPoolCreateInfo::default().queue_family_index(0).flags(flags), None) }.unwrap()
}

fn allocate(ctx: &harness::Context, pool: vk::CommandPool, level: vk::CommandBufferLevel, n: u32) -> Vec<vk::CommandBuffer> {
    let info = vk::CommandBufferAllocateInfo::default().command_pool(pool).level(level).command_buffer_count(n);
    // SAFETY: valid allocate info.
    unsafe { ctx.device.allocate_command_buffers(&info) }.unwrap()
}

fn begin(ctx: &harness::Context, cb: vk::CommandBuffer, flags: vk::CommandBufferUsageFlags) {
    // SAFETY: cb may be begun (initial state, or its pool allows implicit reset).
    unsafe { ctx.device.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default().flags(flags)) }.unwrap();
}

/// Submit and wait with a fresh fence.
fn submit_wait(ctx: &harness::Context, queue: vk::Queue, cbs: &[vk::CommandBuffer]) {
    // SAFETY: valid submission of executable command buffers; the fence is destroyed after it signalled.
    unsafe {
        let f = ctx.device.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        ctx.device.queue_submit(queue, &[vk::SubmitInfo::default().command_buffers(cbs)], f).unwrap();
        ctx.device.wait_for_fences(&[f], true, u64::MAX).unwrap();
        ctx.device.destroy_fence(f, None);
    }
}

fn transfer_barrier(ctx: &harness::Context, cb: vk::CommandBuffer) {
    let mb = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::TRANSFER_WRITE).dst_access_mask(vk::AccessFlags::TRANSFER_READ | vk::AccessFlags::TRANSFER_WRITE)];
    // SAFETY: recording command buffer.
    unsafe { ctx.device.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::TRANSFER, vk::DependencyFlags::empty(), &mb, &[], &[]) };
}

fn pattern(n: usize, seed: u8) -> Vec<u8> {
    (0..n).map(|i| (i as u8).wrapping_mul(31).wrapping_add(seed)).collect()
}

#[test]
fn copy_fill_update_byte_for_byte() {
    let ctx = harness::context();
    let mut a = Buf::new(&ctx, 4096);
    let mut b = Buf::new(&ctx, 1034);
    a.bytes_mut().copy_from_slice(&pattern(4096, 7));
    b.bytes_mut().fill(0xEE);
    let p = pool(&ctx, vk::CommandPoolCreateFlags::empty());
    let cb = allocate(&ctx, p, vk::CommandBufferLevel::PRIMARY, 1)[0];
    let update: Vec<u8> = (100..116).collect();
    begin(&ctx, cb, vk::CommandBufferUsageFlags::empty());
    // SAFETY: recording valid transfer commands on live buffers.
    unsafe {
        let d = &ctx.device;
        d.cmd_update_buffer(cb, b.buffer, 0, &update);
        d.cmd_copy_buffer(
            cb,
            a.buffer,
            b.buffer,
            &[vk::BufferCopy { src_offset: 64, dst_offset: 256, size: 128 }, vk::BufferCopy { src_offset: 4000, dst_offset: 16, size: 96 }],
        );
        d.cmd_fill_buffer(cb, b.buffer, 512, 256, 0xDEAD_BEEF);
        // VK_WHOLE_SIZE: from 1024 to the end (10 bytes) rounded down to a multiple of 4 → 8 bytes.
        d.cmd_fill_buffer(cb, b.buffer, 1024, vk::WHOLE_SIZE, 0x0403_0201);
        d.end_command_buffer(cb).unwrap();
    }
    submit_wait(&ctx, ctx.queues[0], &[cb]);

    let mut expect = vec![0xEEu8; 1034];
    expect[0..16].copy_from_slice(&update);
    expect[16..112].copy_from_slice(&a.bytes()[4000..4096]);
    expect[256..384].copy_from_slice(&a.bytes()[64..192]);
    for w in expect[512..768].chunks_mut(4) {
        w.copy_from_slice(&0xDEAD_BEEFu32.to_le_bytes());
    }
    for w in expect[1024..1032].chunks_mut(4) {
        w.copy_from_slice(&[1, 2, 3, 4]);
    }
    assert_eq!(b.bytes(), &expect[..]);
    assert_eq!(a.bytes(), &pattern(4096, 7)[..], "the source is untouched");
    // SAFETY: the device is idle.
    unsafe { ctx.device.destroy_command_pool(p, None) };
    a.destroy(&ctx);
    b.destroy(&ctx);
    ctx.finish();
}

/// Commands see what earlier commands of the same command buffer wrote (update → copy,
/// fill → copy → copy), and submissions see earlier submissions.
#[test]
fn later_commands_see_earlier_writes() {
    let ctx = harness::context();
    let mut a = Buf::new(&ctx, 1024);
    let mut b = Buf::new(&ctx, 1024);
    a.bytes_mut().fill(0);
    b.bytes_mut().fill(0);
    let p = pool(&ctx, vk::CommandPoolCreateFlags::TRANSIENT);
    let cbs = allocate(&ctx, p, vk::CommandBufferLevel::PRIMARY, 2);
    let data: Vec<u8> = (1..=64).collect();
    // SAFETY: recording valid transfer commands on live buffers.
    unsafe {
        let d = &ctx.device;
        begin(&ctx, cbs[0], vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        d.cmd_update_buffer(cbs[0], a.buffer, 0, &data);
        transfer_barrier(&ctx, cbs[0]);
        d.cmd_copy_buffer(cbs[0], a.buffer, b.buffer, &[vk::BufferCopy { src_offset: 0, dst_offset: 128, size: 64 }]);
        transfer_barrier(&ctx, cbs[0]);
        d.cmd_fill_buffer(cbs[0], a.buffer, 0, 32, 0x1111_1111);
        transfer_barrier(&ctx, cbs[0]);
        d.cmd_copy_buffer(cbs[0], a.buffer, b.buffer, &[vk::BufferCopy { src_offset: 0, dst_offset: 256, size: 64 }]);
        d.end_command_buffer(cbs[0]).unwrap();
        // The second command buffer of the same submission copies what the first wrote.
        begin(&ctx, cbs[1], vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        d.cmd_copy_buffer(cbs[1], b.buffer, a.buffer, &[vk::BufferCopy { src_offset: 256, dst_offset: 512, size: 64 }]);
        d.end_command_buffer(cbs[1]).unwrap();
    }
    submit_wait(&ctx, ctx.queues[1], &cbs);
    assert_eq!(&b.bytes()[128..192], &data[..]);
    let mut second = vec![0x11u8; 32];
    second.extend_from_slice(&data[32..]);
    assert_eq!(&b.bytes()[256..320], &second[..]);
    assert_eq!(&a.bytes()[512..576], &second[..]);
    assert!(b.bytes()[..128].iter().all(|x| *x == 0));
    // SAFETY: the device is idle.
    unsafe { ctx.device.destroy_command_pool(p, None) };
    a.destroy(&ctx);
    b.destroy(&ctx);
    ctx.finish();
}

#[test]
fn copy_buffer2_and_large_copies() {
    let ctx = harness::context();
    let copy2 = ash::khr::copy_commands2::Device::new(&ctx.instance, &ctx.device);
    let n = 9 << 20; // larger than the executor's staging chunk
    let mut a = Buf::new(&ctx, n);
    let mut b = Buf::new(&ctx, n);
    let src = pattern(n, 3);
    a.bytes_mut().copy_from_slice(&src);
    b.bytes_mut().fill(0);
    let p = pool(&ctx, vk::CommandPoolCreateFlags::empty());
    let cb = allocate(&ctx, p, vk::CommandBufferLevel::PRIMARY, 1)[0];
    begin(&ctx, cb, vk::CommandBufferUsageFlags::empty());
    let regions = [vk::BufferCopy2::default().src_offset(0).dst_offset(0).size(n as u64 - 16), vk::BufferCopy2::default().src_offset(n as u64 - 16).dst_offset(n as u64 - 16).size(16)];
    // SAFETY: recording a valid copy.
    unsafe {
        copy2.cmd_copy_buffer2(cb, &vk::CopyBufferInfo2::default().src_buffer(a.buffer).dst_buffer(b.buffer).regions(&regions));
        ctx.device.end_command_buffer(cb).unwrap();
    }
    submit_wait(&ctx, ctx.queues[2], &[cb]);
    assert!(b.bytes() == &src[..], "9 MiB copied byte for byte");
    // SAFETY: the device is idle.
    unsafe { ctx.device.destroy_command_pool(p, None) };
    a.destroy(&ctx);
    b.destroy(&ctx);
    ctx.finish();
}

#[test]
fn secondary_command_buffers_execute_inline() {
    let ctx = harness::context();
    let mut a = Buf::new(&ctx, 256);
    a.bytes_mut().fill(0);
    let p = pool(&ctx, vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
    let primary = allocate(&ctx, p, vk::CommandBufferLevel::PRIMARY, 1)[0];
    let secondaries = allocate(&ctx, p, vk::CommandBufferLevel::SECONDARY, 2);
    let inheritance = vk::CommandBufferInheritanceInfo::default();
    // SAFETY: recording valid commands; secondaries begun with inheritance info.
    unsafe {
        let d = &ctx.device;
        for (i, s) in secondaries.iter().enumerate() {
            d.begin_command_buffer(*s, &vk::CommandBufferBeginInfo::default().inheritance_info(&inheritance)).unwrap();
            d.cmd_fill_buffer(*s, a.buffer, 64 * i as u64, 64, 0x0101_0101 * (i as u32 + 1));
            transfer_barrier(&ctx, *s);
            d.cmd_copy_buffer(*s, a.buffer, a.buffer, &[vk::BufferCopy { src_offset: 0, dst_offset: 128 + 64 * i as u64, size: 64 }]);
            d.end_command_buffer(*s).unwrap();
        }
        begin(&ctx, primary, vk::CommandBufferUsageFlags::empty());
        d.cmd_update_buffer(primary, a.buffer, 0, &[9u8; 64]);
        transfer_barrier(&ctx, primary);
        // Secondary 0 fills [0, 64) with 1s then copies it to [128, 192): sees its own fill.
        // Secondary 1 fills [64, 128) with 2s then copies [0, 64) (1s) to [192, 256).
        d.cmd_execute_commands(primary, &secondaries);
        transfer_barrier(&ctx, primary);
        d.cmd_fill_buffer(primary, a.buffer, 60, 4, 0xFFFF_FFFF);
        d.end_command_buffer(primary).unwrap();
    }
    submit_wait(&ctx, ctx.queues[0], &[primary]);
    let mut expect = vec![1u8; 256];
    expect[64..128].fill(2);
    expect[60..64].fill(0xFF);
    assert_eq!(a.bytes(), &expect[..]);

    // Re-record a secondary and the primary: the new contents run.
    // SAFETY: the queue is idle; the pool allows resets.
    unsafe {
        let d = &ctx.device;
        d.reset_command_buffer(secondaries[0], vk::CommandBufferResetFlags::RELEASE_RESOURCES).unwrap();
        d.begin_command_buffer(secondaries[0], &vk::CommandBufferBeginInfo::default().inheritance_info(&inheritance)).unwrap();
        d.cmd_fill_buffer(secondaries[0], a.buffer, 0, vk::WHOLE_SIZE, 0x7777_7777);
        d.end_command_buffer(secondaries[0]).unwrap();
        begin(&ctx, primary, vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        d.cmd_execute_commands(primary, &secondaries[..1]);
        d.end_command_buffer(primary).unwrap();
    }
    submit_wait(&ctx, ctx.queues[0], &[primary]);
    assert!(a.bytes().iter().all(|x| *x == 0x77));
    // SAFETY: the device is idle.
    unsafe {
        ctx.device.free_command_buffers(p, &secondaries);
        ctx.device.destroy_command_pool(p, None);
    }
    a.destroy(&ctx);
    ctx.finish();
}

/// Reset and re-record: explicit vkResetCommandBuffer, implicit reset by vkBeginCommandBuffer,
/// vkResetCommandPool, ONE_TIME_SUBMIT recordings re-recorded, trim, free.
#[test]
fn reset_and_rerecord() {
    let ctx = harness::context();
    let mut a = Buf::new(&ctx, 64);
    let buffer = a.buffer;
    let record_fill = |cb: vk::CommandBuffer, value: u32, flags: vk::CommandBufferUsageFlags| {
        begin(&ctx, cb, flags);
        // SAFETY: recording a valid fill.
        unsafe {
            ctx.device.cmd_fill_buffer(cb, buffer, 0, 64, value);
            ctx.device.end_command_buffer(cb).unwrap();
        }
    };
    let check = |a: &Buf, value: u32| {
        assert!(a.bytes().chunks(4).all(|w| w == value.to_le_bytes()), "buffer holds {value:#x}");
    };
    let p = pool(&ctx, vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
    let cb = allocate(&ctx, p, vk::CommandBufferLevel::PRIMARY, 1)[0];
    record_fill(cb, 1, vk::CommandBufferUsageFlags::empty());
    submit_wait(&ctx, ctx.queues[0], &[cb]);
    check(&a, 1);
    a.bytes_mut().fill(0);
    submit_wait(&ctx, ctx.queues[1], &[cb]);
    check(&a, 1);
    // SAFETY: not pending; the pool allows resets.
    unsafe { ctx.device.reset_command_buffer(cb, vk::CommandBufferResetFlags::empty()) }.unwrap();
    record_fill(cb, 2, vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
    submit_wait(&ctx, ctx.queues[0], &[cb]);
    check(&a, 2);
    // Invalid after its one submission: begin resets it implicitly.
    record_fill(cb, 3, vk::CommandBufferUsageFlags::empty());
    submit_wait(&ctx, ctx.queues[0], &[cb]);
    check(&a, 3);

    // A pool without RESET_COMMAND_BUFFER: reset through the pool.
    let p2 = pool(&ctx, vk::CommandPoolCreateFlags::TRANSIENT);
    let cbs = allocate(&ctx, p2, vk::CommandBufferLevel::PRIMARY, 3);
    record_fill(cbs[0], 4, vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
    submit_wait(&ctx, ctx.queues[3], &cbs[..1]);
    check(&a, 4);
    // SAFETY: nothing pending.
    unsafe {
        ctx.device.reset_command_pool(p2, vk::CommandPoolResetFlags::RELEASE_RESOURCES).unwrap();
        ctx.device.trim_command_pool(p2, vk::CommandPoolTrimFlags::empty());
    }
    record_fill(cbs[0], 5, vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
    record_fill(cbs[1], 6, vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
    submit_wait(&ctx, ctx.queues[3], &cbs[..2]);
    check(&a, 6);
    // SAFETY: nothing pending; the remaining buffers go with their pools.
    unsafe {
        ctx.device.free_command_buffers(p2, &cbs[..1]);
        ctx.device.destroy_command_pool(p2, None);
        ctx.device.destroy_command_pool(p, None);
    }
    a.destroy(&ctx);
    ctx.finish();
}

/// SIMULTANEOUS_USE: one recording pending on two queues at once (held by an event).
#[test]
fn simultaneous_use_on_two_queues() {
    let ctx = harness::context();
    let mut a = Buf::new(&ctx, 64);
    a.bytes_mut().fill(0);
    let p = pool(&ctx, vk::CommandPoolCreateFlags::empty());
    let cb = allocate(&ctx, p, vk::CommandBufferLevel::PRIMARY, 1)[0];
    // SAFETY: objects created here; destroyed after the device is idle.
    unsafe {
        let d = &ctx.device;
        let event = d.create_event(&vk::EventCreateInfo::default(), None).unwrap();
        begin(&ctx, cb, vk::CommandBufferUsageFlags::SIMULTANEOUS_USE);
        d.cmd_wait_events(cb, &[event], vk::PipelineStageFlags::HOST, vk::PipelineStageFlags::TRANSFER, &[], &[], &[]);
        d.cmd_fill_buffer(cb, a.buffer, 0, 64, 0x5555_5555);
        d.end_command_buffer(cb).unwrap();
        let cbs = [cb];
        d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs)], vk::Fence::null()).unwrap();
        d.queue_submit(ctx.queues[1], &[vk::SubmitInfo::default().command_buffers(&cbs)], vk::Fence::null()).unwrap();
        d.set_event(event).unwrap();
        d.device_wait_idle().unwrap();
        assert!(a.bytes().iter().all(|x| *x == 0x55));
        d.destroy_event(event, None);
        d.destroy_command_pool(p, None);
    }
    a.destroy(&ctx);
    ctx.finish();
}

/// A command that fails when executed (its source memory was freed after recording) is
/// reported and skipped; the rest of the command buffer still runs. Deliberately invalid
/// usage, so without the validation layer.
#[test]
fn a_failing_command_is_skipped_and_the_rest_runs() {
    let ctx = harness::Context::new(harness::Options { validation: false, ..Default::default() });
    let mut a = Buf::new(&ctx, 256);
    let mut b = Buf::new(&ctx, 256);
    a.bytes_mut().fill(0x99);
    b.bytes_mut().fill(0);
    let p = pool(&ctx, vk::CommandPoolCreateFlags::empty());
    let cb = allocate(&ctx, p, vk::CommandBufferLevel::PRIMARY, 1)[0];
    begin(&ctx, cb, vk::CommandBufferUsageFlags::empty());
    // SAFETY: recording valid commands; the source is then freed before execution (the test).
    unsafe {
        ctx.device.cmd_copy_buffer(cb, a.buffer, b.buffer, &[vk::BufferCopy { src_offset: 0, dst_offset: 0, size: 128 }]);
        ctx.device.cmd_fill_buffer(cb, b.buffer, 128, 128, 0x2222_2222);
        ctx.device.end_command_buffer(cb).unwrap();
    }
    a.destroy(&ctx);
    submit_wait(&ctx, ctx.queues[0], &[cb]);
    assert!(b.bytes()[..128].iter().all(|x| *x == 0), "the failed copy wrote nothing");
    assert!(b.bytes()[128..].iter().all(|x| *x == 0x22), "the fill after it ran");
    assert!(harness::diagnostics().contains("vkCmdCopyBuffer: device-memory access refused: the memory was freed"), "reported");
    // SAFETY: the device is idle.
    unsafe { ctx.device.destroy_command_pool(p, None) };
    b.destroy(&ctx);
    ctx.finish();
}

/// Strict mode (ARBOR_STRICT=1, read once per process): run in a child process.
#[test]
fn strict_mode_loses_the_device() {
    harness::child::run_child_test("strict_mode_child", &[("ARBOR_STRICT", "1"), ("ARBOR_DIAG", "off")]);
}

#[test]
#[ignore = "run by strict_mode_loses_the_device with ARBOR_STRICT=1"]
fn strict_mode_child() {
    let ctx = harness::Context::new(harness::Options { validation: false, ..Default::default() });
    let b = Buf::new(&ctx, 64);
    let p = pool(&ctx, vk::CommandPoolCreateFlags::empty());
    let cb = allocate(&ctx, p, vk::CommandBufferLevel::PRIMARY, 1)[0];
    begin(&ctx, cb, vk::CommandBufferUsageFlags::empty());
    // SAFETY: a deliberately invalid fill (unaligned offset): strict mode loses the device.
    unsafe {
        ctx.device.cmd_fill_buffer(cb, b.buffer, 2, 4, 1);
        ctx.device.end_command_buffer(cb).unwrap();
        let f = ctx.device.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        let cbs = [cb];
        ctx.device.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs)], f).unwrap();
        assert_eq!(ctx.device.wait_for_fences(&[f], true, u64::MAX), Err(vk::Result::ERROR_DEVICE_LOST));
        assert_eq!(ctx.device.queue_submit(ctx.queues[1], &[], vk::Fence::null()), Err(vk::Result::ERROR_DEVICE_LOST));
        assert_eq!(ctx.device.device_wait_idle(), Err(vk::Result::ERROR_DEVICE_LOST));
        ctx.device.destroy_fence(f, None);
        ctx.device.destroy_command_pool(p, None);
    }
    b.destroy(&ctx);
    ctx.finish();
}

/// Lifecycle misuse and invalid arguments are reported with their VUIDs; invalid commands are
/// not recorded (guard bytes stay), the process goes on. Without the validation layer.
#[test]
fn misuse_is_diagnosed() {
    let ctx = harness::Context::new(harness::Options { validation: false, ..Default::default() });
    let mut b = Buf::new(&ctx, 64);
    b.bytes_mut().fill(0xAA);
    let p = pool(&ctx, vk::CommandPoolCreateFlags::empty());
    let cbs = allocate(&ctx, p, vk::CommandBufferLevel::PRIMARY, 2);
    let d = &ctx.device;
    // SAFETY: deliberately invalid usage the driver must diagnose without crashing.
    unsafe {
        let event = d.create_event(&vk::EventCreateInfo::default(), None).unwrap();
        let qp = d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(1), None).unwrap();
        // Submitting a buffer that was never recorded.
        let f = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs[..1])], f).unwrap();
        d.wait_for_fences(&[f], true, u64::MAX).unwrap();
        // Invalid arguments: not recorded.
        begin(&ctx, cbs[0], vk::CommandBufferUsageFlags::empty());
        d.cmd_fill_buffer(cbs[0], b.buffer, 2, 4, 0);
        d.cmd_fill_buffer(cbs[0], b.buffer, 0, 128, 0);
        d.cmd_update_buffer(cbs[0], b.buffer, 60, &[0u8; 8]);
        d.cmd_copy_buffer(cbs[0], b.buffer, b.buffer, &[vk::BufferCopy { src_offset: 0, dst_offset: 8, size: 16 }]);
        d.cmd_begin_query(cbs[0], qp, 0, vk::QueryControlFlags::empty());
        d.cmd_write_timestamp(cbs[0], vk::PipelineStageFlags::TRANSFER, qp, 1);
        d.cmd_wait_events(cbs[0], &[event], vk::PipelineStageFlags::HOST, vk::PipelineStageFlags::TRANSFER, &[], &[], &[]);
        d.end_command_buffer(cbs[0]).unwrap();
        // Pending: reset, re-begin and resubmit are diagnosed.
        d.reset_fences(&[f]).unwrap();
        d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&cbs[..1])], f).unwrap();
        d.queue_submit(ctx.queues[1], &[vk::SubmitInfo::default().command_buffers(&cbs[..1])], vk::Fence::null()).unwrap();
        d.reset_fences(&[f]).unwrap();
        d.set_event(event).unwrap();
        d.device_wait_idle().unwrap();
        // Executable, pool without RESET_COMMAND_BUFFER: begin is diagnosed (and resets anyway).
        begin(&ctx, cbs[0], vk::CommandBufferUsageFlags::empty());
        d.end_command_buffer(cbs[0]).unwrap();
        d.end_command_buffer(cbs[1]).unwrap();
        d.reset_command_buffer(cbs[1], vk::CommandBufferResetFlags::empty()).unwrap();
        d.destroy_fence(f, None);
        d.destroy_event(event, None);
        d.destroy_query_pool(qp, None);
        d.destroy_command_pool(p, None);
    }
    assert!(b.bytes().iter().all(|x| *x == 0xAA), "no invalid command was executed");
    let log = harness::diagnostics();
    for vuid in [
        "VUID-vkQueueSubmit-pCommandBuffers-00070",
        "VUID-vkCmdFillBuffer-dstOffset-00025",
        "VUID-vkCmdFillBuffer-size-00027",
        "VUID-vkCmdUpdateBuffer-dataSize-00033",
        "VUID-vkCmdCopyBuffer-pRegions-00117",
        "VUID-vkCmdBeginQuery-queryType-02804",
        "VUID-vkCmdWriteTimestamp-query-04904",
        "VUID-vkQueueSubmit-pCommandBuffers-00071",
        "VUID-vkResetFences-pFences-01123",
        "VUID-vkBeginCommandBuffer-commandBuffer-00050",
        "VUID-vkEndCommandBuffer-commandBuffer-00059",
        "VUID-vkResetCommandBuffer-commandBuffer-00046",
    ] {
        assert!(log.contains(vuid), "{vuid} not reported; diagnostics:\n{log}");
    }
    b.destroy(&ctx);
    ctx.finish();
}

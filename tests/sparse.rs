//! Sparse binding of buffers through the loader (docs/ROBUSTNESS.md, section 4): a sparse
//! buffer's pages bound to pages of memory objects with vkQueueBindSparse show those memories'
//! bytes, both ways; unbound pages read zero; rebinding changes what is seen; acceleration
//! structures built from and into sparse buffers equal those of ordinary buffers byte for byte;
//! binds are ordered with submissions by semaphores (binary and timeline) and fences. The
//! reference for every byte is the memory objects' own contents, read through their mappings.
//!
//! The positive tests run with the validation layer on and fail on any message; the negative
//! ones (one per valid-usage check of vkQueueBindSparse) run with it off and read Arbor's
//! diagnostics. Every test holds `SERIAL`, so the diagnostics appended while it runs are its own.

mod harness;

use std::sync::{Mutex, MutexGuard};

use ash::vk;
use harness::accel::{payload, triangles, Accel, ALL_USAGE};
use harness::{Context, Options};

const PAGE: u64 = 64 << 10;
const COPY_USAGE: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(
    vk::BufferUsageFlags::TRANSFER_SRC.as_raw() | vk::BufferUsageFlags::TRANSFER_DST.as_raw() | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS.as_raw(),
);

static SERIAL: Mutex<()> = Mutex::new(());

fn serial() -> MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

fn context(validation: bool) -> Context {
    Context::new(Options { validation, sparse_binding: true, acceleration_structure: true, ..Default::default() })
}

/// A memory object of the type sparse buffers bind, mapped, with a device address.
struct SparseMemory {
    memory: vk::DeviceMemory,
    ptr: *mut u8,
    size: u64,
}

impl SparseMemory {
    fn bytes(&self, offset: u64, len: u64) -> Vec<u8> {
        assert!(offset + len <= self.size);
        // SAFETY: mapped memory of `size` bytes.
        unsafe { std::slice::from_raw_parts(self.ptr.add(offset as usize), len as usize).to_vec() }
    }
    fn write(&self, offset: u64, data: &[u8]) {
        assert!(offset + data.len() as u64 <= self.size);
        // SAFETY: mapped memory of `size` bytes.
        unsafe { std::ptr::copy_nonoverlapping(data.as_ptr(), self.ptr.add(offset as usize), data.len()) };
    }
}

/// A sparse buffer of `size` bytes (nothing bound).
fn sparse_buffer(ctx: &Context, size: u64, usage: vk::BufferUsageFlags) -> vk::Buffer {
    let info = vk::BufferCreateInfo::default().size(size).usage(usage).flags(vk::BufferCreateFlags::SPARSE_BINDING);
    // SAFETY: valid create info; sparseBinding is enabled.
    unsafe { ctx.device.create_buffer(&info, None) }.expect("vkCreateBuffer (sparse)")
}

/// `pages` pages of the memory type `buffer` reports, each byte `fill(offset)`.
fn sparse_memory(ctx: &Context, buffer: vk::Buffer, pages: u64, fill: impl Fn(u64) -> u8) -> SparseMemory {
    // SAFETY: live buffer; valid allocate info; the memory is freed by the test.
    unsafe {
        let req = ctx.device.get_buffer_memory_requirements(buffer);
        let mut flags = vk::MemoryAllocateFlagsInfo::default().flags(vk::MemoryAllocateFlags::DEVICE_ADDRESS);
        let ai = vk::MemoryAllocateInfo::default()
            .allocation_size(pages * req.alignment)
            .memory_type_index(ctx.memory_type(req.memory_type_bits, vk::MemoryPropertyFlags::HOST_VISIBLE))
            .push_next(&mut flags);
        let memory = ctx.device.allocate_memory(&ai, None).expect("vkAllocateMemory (sparse type)");
        let ptr = ctx.device.map_memory(memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()).unwrap() as *mut u8;
        let m = SparseMemory { memory, ptr, size: pages * req.alignment };
        m.write(0, &(0..m.size).map(fill).collect::<Vec<u8>>());
        m
    }
}

/// One page bind: (page of the buffer, memory and page in it; None unbinds).
type PageBind = (u64, Option<(vk::DeviceMemory, u64)>);

fn memory_binds(binds: &[PageBind]) -> Vec<vk::SparseMemoryBind> {
    binds
        .iter()
        .map(|&(page, target)| {
            let (memory, memory_offset) = target.map_or((vk::DeviceMemory::null(), 0), |(m, p)| (m, p * PAGE));
            vk::SparseMemoryBind { resource_offset: page * PAGE, size: PAGE, memory, memory_offset, flags: vk::SparseMemoryBindFlags::empty() }
        })
        .collect()
}

/// vkQueueBindSparse of `binds` on queue `q`, then wait for its fence.
fn bind_and_wait(ctx: &Context, q: usize, buffer: vk::Buffer, binds: &[PageBind]) {
    let list = memory_binds(binds);
    let buffer_binds = [vk::SparseBufferMemoryBindInfo::default().buffer(buffer).binds(&list)];
    // SAFETY: valid bind info; the fence is waited for and destroyed.
    unsafe {
        let fence = ctx.device.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        ctx.device.queue_bind_sparse(ctx.queues[q], &[vk::BindSparseInfo::default().buffer_binds(&buffer_binds)], fence).unwrap();
        ctx.device.wait_for_fences(&[fence], true, u64::MAX).unwrap();
        ctx.device.destroy_fence(fence, None);
    }
}

/// Record `f` into a fresh command buffer of a fresh pool, submit it to queue 0 after waiting
/// `waits` (semaphore, timeline value) and wait for its fence.
fn submit(ctx: &Context, waits: &[(vk::Semaphore, u64)], f: impl FnOnce(vk::CommandBuffer)) {
    let d = &ctx.device;
    // SAFETY: valid create infos; everything is destroyed after the wait.
    unsafe {
        let pool = d.create_command_pool(&vk::CommandPoolCreateInfo::default(), None).unwrap();
        let cb = d.allocate_command_buffers(&vk::CommandBufferAllocateInfo::default().command_pool(pool).command_buffer_count(1)).unwrap()[0];
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        f(cb);
        d.end_command_buffer(cb).unwrap();
        let fence = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        let sems: Vec<vk::Semaphore> = waits.iter().map(|w| w.0).collect();
        let values: Vec<u64> = waits.iter().map(|w| w.1).collect();
        let stages = vec![vk::PipelineStageFlags::TRANSFER; waits.len()];
        let mut tl = vk::TimelineSemaphoreSubmitInfo::default().wait_semaphore_values(&values);
        let cbs = [cb];
        let si = vk::SubmitInfo::default().wait_semaphores(&sems).wait_dst_stage_mask(&stages).command_buffers(&cbs).push_next(&mut tl);
        d.queue_submit(ctx.queues[0], &[si], fence).unwrap();
        d.wait_for_fences(&[fence], true, u64::MAX).unwrap();
        d.destroy_fence(fence, None);
        d.destroy_command_pool(pool, None);
    }
}

/// The first `len` bytes of `buffer`, copied on the device (vkCmdCopyBuffer) into a host buffer.
fn read_back(ctx: &Context, buffer: vk::Buffer, len: u64, waits: &[(vk::Semaphore, u64)]) -> Vec<u8> {
    let (dst, memory, ptr) = ctx.host_buffer(len, COPY_USAGE);
    // SAFETY: 0xEE marks bytes the copy did not write.
    unsafe { std::ptr::write_bytes(ptr, 0xEE, len as usize) };
    // SAFETY: both buffers hold `len` bytes; recording command buffer.
    submit(ctx, waits, |cb| unsafe { ctx.device.cmd_copy_buffer(cb, buffer, dst, &[vk::BufferCopy { src_offset: 0, dst_offset: 0, size: len }]) });
    // SAFETY: mapped host buffer of `len` bytes; destroyed once.
    unsafe {
        let out = std::slice::from_raw_parts(ptr, len as usize).to_vec();
        ctx.device.destroy_buffer(dst, None);
        ctx.device.free_memory(memory, None);
        out
    }
}

/// Copy `data` on the device into `buffer` at `offset`.
fn write_through(ctx: &Context, buffer: vk::Buffer, offset: u64, data: &[u8]) {
    let (src, memory, ptr) = ctx.host_buffer(data.len() as u64, COPY_USAGE);
    // SAFETY: mapped host buffer of data.len() bytes.
    unsafe { std::ptr::copy_nonoverlapping(data.as_ptr(), ptr, data.len()) };
    let region = vk::BufferCopy { src_offset: 0, dst_offset: offset, size: data.len() as u64 };
    // SAFETY: recording command buffer; the region lies inside both buffers.
    submit(ctx, &[], |cb| unsafe { ctx.device.cmd_copy_buffer(cb, src, buffer, &[region]) });
    // SAFETY: destroyed once, after the submission's fence.
    unsafe {
        ctx.device.destroy_buffer(src, None);
        ctx.device.free_memory(memory, None);
    }
}

fn free(ctx: &Context, buffer: vk::Buffer, memories: &[&SparseMemory]) {
    // SAFETY: the device is idle for these objects (every submission was waited for).
    unsafe {
        ctx.device.destroy_buffer(buffer, None);
        for m in memories {
            ctx.device.free_memory(m.memory, None);
        }
    }
}

fn page(bytes: &[u8], p: u64) -> &[u8] {
    &bytes[(p * PAGE) as usize..((p + 1) * PAGE) as usize]
}

#[test]
fn sparse_buffers_report_the_sparse_page_and_their_own_memory_type() {
    let _serial = serial();
    let ctx = context(true);
    let buffer = sparse_buffer(&ctx, 3 * PAGE - 100, COPY_USAGE);
    let ordinary = ctx.host_buffer(1000, COPY_USAGE);
    // SAFETY: live buffers.
    let (req, ord) = unsafe { (ctx.device.get_buffer_memory_requirements(buffer), ctx.device.get_buffer_memory_requirements(ordinary.0)) };
    assert_eq!((req.size, req.alignment), (3 * PAGE, PAGE), "size rounded up to the sparse page, which is the alignment");
    assert_eq!(req.memory_type_bits.count_ones(), 1, "sparse buffers bind one memory type");
    assert_eq!(req.memory_type_bits & ord.memory_type_bits, 0, "and ordinary buffers another");
    // SAFETY: live buffer with SHADER_DEVICE_ADDRESS usage.
    let address = unsafe { ctx.device.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(buffer)) };
    assert!(address != 0 && address.is_multiple_of(PAGE));
    // SAFETY: objects created above, destroyed once.
    unsafe {
        ctx.device.destroy_buffer(ordinary.0, None);
        ctx.device.free_memory(ordinary.1, None);
    }
    free(&ctx, buffer, &[]);
    ctx.finish();
}

#[test]
fn pages_show_their_memory_both_ways_unbound_read_zero_and_rebinding_changes_them() {
    let _serial = serial();
    let ctx = context(true);
    let size = 4 * PAGE;
    let buffer = sparse_buffer(&ctx, size, COPY_USAGE);
    let a = sparse_memory(&ctx, buffer, 2, |i| (i * 7 % 251) as u8 | 1);
    let b = sparse_memory(&ctx, buffer, 2, |i| (i * 13 % 241) as u8 | 1);
    // Pages out of order and across two memories; page 2 unbound.
    bind_and_wait(&ctx, 1, buffer, &[(0, Some((a.memory, 1))), (1, Some((b.memory, 0))), (3, Some((a.memory, 0)))]);
    let seen = read_back(&ctx, buffer, size, &[]);
    assert!(page(&seen, 0) == a.bytes(PAGE, PAGE), "page 0 shows page 1 of memory a");
    assert!(page(&seen, 1) == b.bytes(0, PAGE), "page 1 shows page 0 of memory b");
    assert!(page(&seen, 2).iter().all(|&x| x == 0), "the unbound page reads zero");
    assert!(page(&seen, 3) == a.bytes(0, PAGE), "page 3 shows page 0 of memory a");

    // Host writes through a memory's mapping show through the buffer.
    a.write(PAGE + 10, b"through the mapping");
    let seen = read_back(&ctx, buffer, size, &[]);
    assert_eq!(&seen[10..29], b"through the mapping");
    // Device writes to the buffer land in the bound memory, across a page boundary; the 2000
    // bytes written into the unbound page reach no memory.
    let (a_before, mut b_expected) = (a.bytes(0, 2 * PAGE), b.bytes(0, 2 * PAGE));
    let data: Vec<u8> = (0..3000u32).map(|i| (i % 200) as u8 + 20).collect();
    write_through(&ctx, buffer, 2 * PAGE - 1000, &data);
    b_expected[(PAGE - 1000) as usize..PAGE as usize].copy_from_slice(&data[..1000]);
    assert!(b.bytes(0, 2 * PAGE) == b_expected, "the end of page 1 is memory b, and nothing else of b changed");
    assert!(a.bytes(0, 2 * PAGE) == a_before, "memory a is not bound there");

    // Rebinding: page 1 now shows memory a's page 0; unbinding page 0 makes it read zero.
    bind_and_wait(&ctx, 1, buffer, &[(1, Some((a.memory, 0))), (0, None)]);
    let seen = read_back(&ctx, buffer, size, &[]);
    assert!(page(&seen, 0).iter().all(|&x| x == 0), "an unbound page reads zero");
    assert!(page(&seen, 1) == a.bytes(0, PAGE), "the rebound page shows its new memory");
    assert!(page(&seen, 3) == a.bytes(0, PAGE), "two pages may show the same memory");
    assert_eq!(b.bytes(PAGE - 1000, 1000), data[..1000], "memory b keeps its bytes after the unbind");
    free(&ctx, buffer, &[&a, &b]);
    ctx.finish();
}

#[test]
fn binds_are_ordered_with_submissions_by_semaphores_and_fences() {
    let _serial = serial();
    let ctx = context(true);
    let d = &ctx.device;
    let buffer = sparse_buffer(&ctx, PAGE, COPY_USAGE);
    let first = sparse_memory(&ctx, buffer, 1, |i| (i % 97) as u8 + 1);
    let second = sparse_memory(&ctx, buffer, 1, |i| (i % 89) as u8 + 100);
    // SAFETY: valid create infos; semaphores and fences destroyed at the end.
    let (binary, timeline, fence) = unsafe {
        let mut ty = vk::SemaphoreTypeCreateInfo::default().semaphore_type(vk::SemaphoreType::TIMELINE);
        (
            d.create_semaphore(&vk::SemaphoreCreateInfo::default(), None).unwrap(),
            d.create_semaphore(&vk::SemaphoreCreateInfo::default().push_next(&mut ty), None).unwrap(),
            d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap(),
        )
    };
    // Bind, then a copy on the same queue that waits the binary semaphore the bind signals.
    let list = memory_binds(&[(0, Some((first.memory, 0)))]);
    let binds = [vk::SparseBufferMemoryBindInfo::default().buffer(buffer).binds(&list)];
    let signal = [binary];
    // SAFETY: valid bind info.
    unsafe { d.queue_bind_sparse(ctx.queues[0], &[vk::BindSparseInfo::default().buffer_binds(&binds).signal_semaphores(&signal)], vk::Fence::null()) }.unwrap();
    assert!(read_back(&ctx, buffer, PAGE, &[(binary, 0)]) == first.bytes(0, PAGE));

    // A rebind on another queue that waits a timeline value the host has not signalled: it
    // cannot have run, so its fence is not signalled; after the host signals, the copy that
    // waits the bind's own timeline signal sees the new memory.
    let list = memory_binds(&[(0, Some((second.memory, 0)))]);
    let binds = [vk::SparseBufferMemoryBindInfo::default().buffer(buffer).binds(&list)];
    let (sems, wait_values, signal_values) = ([timeline], [1u64], [2u64]);
    let mut tl = vk::TimelineSemaphoreSubmitInfo::default().wait_semaphore_values(&wait_values).signal_semaphore_values(&signal_values);
    let info = vk::BindSparseInfo::default().wait_semaphores(&sems).buffer_binds(&binds).signal_semaphores(&sems).push_next(&mut tl);
    // SAFETY: valid bind info, semaphores and fence.
    unsafe {
        d.queue_bind_sparse(ctx.queues[1], &[info], fence).unwrap();
        assert_eq!(d.get_fence_status(fence), Ok(false), "the bind waits for timeline value 1");
        d.signal_semaphore(&vk::SemaphoreSignalInfo::default().semaphore(timeline).value(1)).unwrap();
    }
    assert!(read_back(&ctx, buffer, PAGE, &[(timeline, 2)]) == second.bytes(0, PAGE), "the copy after the rebind sees the new memory");
    // SAFETY: the fence's bind has signalled value 2, which the copy waited for.
    unsafe {
        d.wait_for_fences(&[fence], true, u64::MAX).unwrap();
        assert_eq!(d.get_semaphore_counter_value(timeline), Ok(2));
        d.destroy_fence(fence, None);
        d.destroy_semaphore(binary, None);
        d.destroy_semaphore(timeline, None);
    }
    free(&ctx, buffer, &[&first, &second]);
    ctx.finish();
}

/// A height field of `n` x `n` vertices (two triangles per quad): vertex bytes, index bytes.
fn terrain(n: u32) -> (Vec<u8>, Vec<u8>, u32) {
    let mut v = Vec::new();
    for y in 0..n {
        for x in 0..n {
            let (fx, fy) = (x as f32 / n as f32, y as f32 / n as f32);
            for c in [fx, fy, (fx * 9.0).sin() * (fy * 7.0).cos() * 0.1] {
                v.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
    let mut i = Vec::new();
    for y in 0..n - 1 {
        for x in 0..n - 1 {
            let k = y * n + x;
            for t in [k, k + 1, k + n, k + 1, k + n + 1, k + n] {
                i.extend_from_slice(&t.to_le_bytes());
            }
        }
    }
    (v, i, 2 * (n - 1) * (n - 1))
}

#[test]
fn structures_built_from_and_into_sparse_buffers_equal_ordinary_ones() {
    let _serial = serial();
    let ctx = context(true);
    let a = Accel::new(&ctx);
    let (vertices, indices, count) = terrain(80);
    assert!(vertices.len() as u64 > PAGE, "the vertex data spans pages");
    let (vi, ii) = (a.upload(&vertices), a.upload(&indices));
    let geometry = |vertex: u64| [triangles(vertex, a.buf(ii).address, 80 * 80 - 1)];
    let flags = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION;
    let blas = vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL;
    let g = geometry(a.buf(vi).address);
    let probe = vk::AccelerationStructureBuildGeometryInfoKHR::default().ty(blas).flags(flags).geometries(&g);
    let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &probe, &[count]);
    let scratch = a.buffer(sizes.build_scratch_size);
    let build = |dst: vk::AccelerationStructureKHR, vertex: u64| {
        let g = geometry(vertex);
        let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
            .ty(blas)
            .flags(flags)
            .geometries(&g)
            .dst_acceleration_structure(dst)
            .scratch_data(vk::DeviceOrHostAddressKHR { device_address: a.buf(scratch).address });
        let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(count)];
        // SAFETY: valid build info and ranges; recording command buffer.
        a.submit(|cb| unsafe { a.ext.cmd_build_acceleration_structures(cb, &[info], &[&range[..]]) });
    };
    // Both destinations start as 0xA5: what a build leaves unwritten must match too.
    let (ordinary, ordinary_buf) = a.structure(blas, sizes.acceleration_structure_size);
    a.fill(ordinary_buf, 0xA5);
    build(ordinary, a.buf(vi).address);

    // The same vertices in a sparse buffer whose two pages are bound in reverse order to two
    // memories, written through the memories' mappings; the destination sparse too.
    let vb = sparse_buffer(&ctx, vertices.len() as u64, ALL_USAGE);
    let lo = sparse_memory(&ctx, vb, 1, |_| 0);
    let hi = sparse_memory(&ctx, vb, 1, |_| 0);
    bind_and_wait(&ctx, 0, vb, &[(0, Some((hi.memory, 0))), (1, Some((lo.memory, 0)))]);
    hi.write(0, &vertices[..PAGE as usize]);
    lo.write(0, &vertices[PAGE as usize..]);
    let dst_pages = sizes.acceleration_structure_size.div_ceil(PAGE);
    let db = sparse_buffer(&ctx, sizes.acceleration_structure_size, ALL_USAGE);
    let dm: Vec<SparseMemory> = (0..2).map(|_| sparse_memory(&ctx, db, dst_pages.div_ceil(2), |_| 0xA5)).collect();
    let dst_binds: Vec<PageBind> = (0..dst_pages).map(|p| (p, Some((dm[(p % 2) as usize].memory, p / 2)))).collect();
    bind_and_wait(&ctx, 0, db, &dst_binds);
    // SAFETY: live buffers with device-address usage; valid create info.
    let (vb_address, sparse) = unsafe {
        let info = vk::AccelerationStructureCreateInfoKHR::default().buffer(db).size(sizes.acceleration_structure_size).ty(blas);
        (
            ctx.device.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(vb)),
            a.ext.create_acceleration_structure(&info, None).unwrap(),
        )
    };
    build(sparse, vb_address);

    // Byte for byte: the structures' bytes (the sparse one read through its memories, page by
    // page), their serialized payloads and their compacted sizes.
    let size = sizes.acceleration_structure_size;
    let ordinary_bytes = a.buf(ordinary_buf).read(0, size as usize);
    let sparse_bytes: Vec<u8> = (0..dst_pages).flat_map(|p| dm[(p % 2) as usize].bytes(p / 2 * PAGE, PAGE)).take(size as usize).collect();
    assert!(ordinary_bytes == sparse_bytes, "the structure built into the sparse buffer differs from the ordinary one");
    assert!(payload(&a.serialize(ordinary)) == payload(&a.serialize(sparse)), "serialized payloads differ");
    let compacted = vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR;
    assert_eq!(a.query(ordinary, compacted), a.query(sparse, compacted));
    // SAFETY: the helper's queue is idle; objects destroyed once.
    unsafe {
        ctx.device.queue_wait_idle(ctx.queues[0]).unwrap();
        a.ext.destroy_acceleration_structure(sparse, None);
    }
    free(&ctx, vb, &[&lo, &hi]);
    free(&ctx, db, &dm.iter().collect::<Vec<_>>());
    a.destroy();
    ctx.finish();
}

/// One invalid bind (validation layer off): Arbor names `vuid`, leaves the bind out (the page
/// stays as it was: bound to `good`), and the batch's fence still signals.
fn expect_refused(vuid: &str, bind: impl FnOnce(&Context, vk::Buffer, &SparseMemory, vk::DeviceMemory) -> vk::SparseMemoryBind) {
    let _serial = serial();
    let ctx = context(false);
    let buffer = sparse_buffer(&ctx, 2 * PAGE, COPY_USAGE);
    let good = sparse_memory(&ctx, buffer, 2, |i| (i % 101) as u8 + 1);
    let other = sparse_memory(&ctx, buffer, 2, |_| 0x33);
    bind_and_wait(&ctx, 0, buffer, &[(0, Some((good.memory, 0))), (1, Some((good.memory, 1)))]);
    let mark = harness::diagnostics().len();
    let list = [bind(&ctx, buffer, &other, other.memory)];
    let binds = [vk::SparseBufferMemoryBindInfo::default().buffer(buffer).binds(&list)];
    // SAFETY: the bind info is invalid on purpose in one way; the fence is valid.
    unsafe {
        let fence = ctx.device.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        ctx.device.queue_bind_sparse(ctx.queues[0], &[vk::BindSparseInfo::default().buffer_binds(&binds)], fence).unwrap();
        ctx.device.wait_for_fences(&[fence], true, u64::MAX).unwrap();
        ctx.device.destroy_fence(fence, None);
    }
    let tail = harness::diagnostics()[mark..].to_string();
    let line = format!("arbor: error: vkQueueBindSparse: [{vuid}] ");
    assert!(tail.lines().any(|l| l.starts_with(&line)), "expected a line starting with {line:?}; the driver reported:\n{tail}");
    assert!(tail.lines().filter(|l| l.starts_with("arbor: error:")).all(|l| l.starts_with(&line)), "other errors besides {vuid}:\n{tail}");
    assert!(read_back(&ctx, buffer, 2 * PAGE, &[]) == good.bytes(0, 2 * PAGE), "the refused bind changed what the buffer shows");
    free(&ctx, buffer, &[&good, &other]);
    ctx.finish();
}

fn page_bind(resource_offset: u64, size: u64, memory: vk::DeviceMemory, memory_offset: u64) -> vk::SparseMemoryBind {
    vk::SparseMemoryBind { resource_offset, size, memory, memory_offset, flags: vk::SparseMemoryBindFlags::empty() }
}

#[test]
fn misaligned_resource_offset_is_refused() {
    expect_refused("VUID-VkSparseMemoryBind-resourceOffset-09491", |_, _, _, m| page_bind(4096, PAGE, m, 0));
}

#[test]
fn misaligned_memory_offset_is_refused() {
    expect_refused("VUID-VkSparseMemoryBind-resourceOffset-09491", |_, _, _, m| page_bind(0, PAGE, m, 256));
}

#[test]
fn misaligned_size_is_refused() {
    expect_refused("VUID-VkSparseMemoryBind-resourceOffset-09491", |_, _, _, m| page_bind(0, PAGE / 2, m, 0));
}

#[test]
fn zero_size_is_refused() {
    expect_refused("VUID-VkSparseMemoryBind-size-01098", |_, _, _, m| page_bind(0, 0, m, 0));
}

#[test]
fn resource_offset_past_the_buffer_is_refused() {
    expect_refused("VUID-VkSparseMemoryBind-resourceOffset-01099", |_, _, _, m| page_bind(2 * PAGE, PAGE, m, 0));
}

#[test]
fn range_past_the_buffer_is_refused() {
    expect_refused("VUID-VkSparseMemoryBind-size-01100", |_, _, _, m| page_bind(PAGE, 2 * PAGE, m, 0));
}

#[test]
fn memory_offset_past_the_memory_is_refused() {
    expect_refused("VUID-VkSparseMemoryBind-memoryOffset-01101", |_, _, _, m| page_bind(0, PAGE, m, 2 * PAGE));
}

#[test]
fn range_past_the_memory_is_refused() {
    expect_refused("VUID-VkSparseMemoryBind-size-01102", |_, _, _, m| page_bind(0, 2 * PAGE, m, PAGE));
}

#[test]
fn memory_of_the_ordinary_type_is_refused() {
    expect_refused("VUID-VkSparseMemoryBind-memory-01096", |ctx, _, _, _| {
        // Leaked on purpose: the test's device goes at its end.
        let (_, memory, _) = ctx.host_buffer(2 * PAGE, COPY_USAGE);
        page_bind(0, PAGE, memory, 0)
    });
}

#[test]
fn binding_a_sparse_buffer_with_vk_bind_buffer_memory_is_refused() {
    let _serial = serial();
    let ctx = context(false);
    let buffer = sparse_buffer(&ctx, PAGE, COPY_USAGE);
    let m = sparse_memory(&ctx, buffer, 1, |_| 1);
    let mark = harness::diagnostics().len();
    // SAFETY: invalid on purpose (the buffer is sparse); live objects.
    let r = unsafe { ctx.device.bind_buffer_memory(buffer, m.memory, 0) };
    assert_eq!(r, Err(vk::Result::ERROR_VALIDATION_FAILED_EXT));
    let tail = harness::diagnostics()[mark..].to_string();
    assert!(tail.contains("[VUID-vkBindBufferMemory-buffer-01030]"), "the driver reported:\n{tail}");
    free(&ctx, buffer, &[&m]);
    ctx.finish();
}

#[test]
fn image_binds_are_refused_by_name_and_the_batch_still_signals() {
    let _serial = serial();
    let ctx = context(false);
    let mark = harness::diagnostics().len();
    let binds = [vk::SparseMemoryBind::default()];
    let opaque = [vk::SparseImageOpaqueMemoryBindInfo::default().binds(&binds)];
    // SAFETY: invalid on purpose (no sparse image exists); the fence is valid.
    unsafe {
        let fence = ctx.device.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        ctx.device.queue_bind_sparse(ctx.queues[0], &[vk::BindSparseInfo::default().image_opaque_binds(&opaque)], fence).unwrap();
        ctx.device.wait_for_fences(&[fence], true, u64::MAX).unwrap();
        ctx.device.destroy_fence(fence, None);
    }
    let tail = harness::diagnostics()[mark..].to_string();
    assert!(tail.contains("vkQueueBindSparse: sparse images are not supported"), "the driver reported:\n{tail}");
    ctx.finish();
}

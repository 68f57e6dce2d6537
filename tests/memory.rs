//! Device memory and buffers through the real loader with validation on: allocation, device
//! addresses, capture/replay, mapping, flush/invalidate, out-of-memory, requirements.
mod harness;

use ash::vk;

const STORAGE_ADDR: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(
    vk::BufferUsageFlags::STORAGE_BUFFER.as_raw() | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS.as_raw(),
);

fn bda(ctx: &harness::Context) -> ash::khr::buffer_device_address::Device {
    ash::khr::buffer_device_address::Device::new(&ctx.instance, &ctx.device)
}

#[test]
fn device_addresses_distinct_aligned_stable() {
    let ctx = harness::context();
    let bda = bda(&ctx);
    let mut made = Vec::new();
    let mut addrs = Vec::new();
    for size in [4u64, 256, 1000, 4096, 65536, 1 << 20] {
        let (b, m, _) = ctx.host_buffer(size, STORAGE_ADDR);
        // SAFETY: live buffer with SHADER_DEVICE_ADDRESS usage bound to DEVICE_ADDRESS memory.
        let a = unsafe { bda.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(b)) };
        assert_ne!(a, 0);
        assert_eq!(a % 256, 0, "address {a:#x} not 256-aligned");
        // Stable across calls, and the opaque capture address is the address.
        // SAFETY: as above.
        unsafe {
            assert_eq!(bda.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(b)), a);
            assert_eq!(bda.get_buffer_opaque_capture_address(&vk::BufferDeviceAddressInfo::default().buffer(b)), a);
        }
        assert!(!addrs.contains(&a));
        addrs.push(a);
        made.push((b, m, size));
    }
    // Non-overlapping ranges.
    let mut ranges: Vec<(u64, u64)> = addrs.iter().zip(&made).map(|(a, (_, _, s))| (*a, *a + *s)).collect();
    ranges.sort();
    assert!(ranges.windows(2).all(|w| w[0].1 <= w[1].0));
    // SAFETY: objects created above, destroyed once.
    unsafe {
        for (b, m, _) in made {
            ctx.device.destroy_buffer(b, None);
            ctx.device.free_memory(m, None);
        }
    }
    ctx.finish();
}

#[test]
fn two_buffers_in_one_allocation() {
    let ctx = harness::context();
    let bda = bda(&ctx);
    // SAFETY: valid create infos; everything destroyed below.
    unsafe {
        let ci = vk::BufferCreateInfo::default().size(300).usage(STORAGE_ADDR);
        let b0 = ctx.device.create_buffer(&ci, None).unwrap();
        let b1 = ctx.device.create_buffer(&ci, None).unwrap();
        let req = ctx.device.get_buffer_memory_requirements(b0);
        assert_eq!(req.alignment, 256);
        assert_eq!(req.size, 512);
        let mut flags = vk::MemoryAllocateFlagsInfo::default().flags(vk::MemoryAllocateFlags::DEVICE_ADDRESS);
        let ai = vk::MemoryAllocateInfo::default().allocation_size(2 * req.size).memory_type_index(0).push_next(&mut flags);
        let m = ctx.device.allocate_memory(&ai, None).unwrap();
        let binds = [
            vk::BindBufferMemoryInfo::default().buffer(b0).memory(m).memory_offset(0),
            vk::BindBufferMemoryInfo::default().buffer(b1).memory(m).memory_offset(req.size),
        ];
        ctx.device.bind_buffer_memory2(&binds).unwrap();
        let a0 = bda.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(b0));
        let a1 = bda.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(b1));
        assert_eq!(a1, a0 + req.size);
        assert_eq!(
            bda.get_device_memory_opaque_capture_address(&vk::DeviceMemoryOpaqueCaptureAddressInfo::default().memory(m)),
            a0
        );
        ctx.device.destroy_buffer(b0, None);
        ctx.device.destroy_buffer(b1, None);
        ctx.device.free_memory(m, None);
    }
    ctx.finish();
}

#[test]
fn memory_requirements() {
    let ctx = harness::context();
    // SAFETY: valid create infos; everything destroyed below.
    unsafe {
        for (size, usage) in [
            (1u64, vk::BufferUsageFlags::TRANSFER_SRC),
            (257, vk::BufferUsageFlags::STORAGE_BUFFER),
            (4096, vk::BufferUsageFlags::UNIFORM_BUFFER),
            (12345, STORAGE_ADDR),
        ] {
            let b = ctx.device.create_buffer(&vk::BufferCreateInfo::default().size(size).usage(usage), None).unwrap();
            let r = ctx.device.get_buffer_memory_requirements(b);
            assert_eq!(r.alignment, 256);
            assert_eq!(r.size, size.next_multiple_of(256));
            assert_eq!(r.memory_type_bits, 1);
            let mut dedicated = vk::MemoryDedicatedRequirements::default();
            let mut r2 = vk::MemoryRequirements2::default().push_next(&mut dedicated);
            ctx.device.get_buffer_memory_requirements2(&vk::BufferMemoryRequirementsInfo2::default().buffer(b), &mut r2);
            assert_eq!(r2.memory_requirements.size, r.size);
            assert_eq!(r2.memory_requirements.alignment, 256);
            assert_eq!(dedicated.requires_dedicated_allocation, vk::FALSE);
            assert_eq!(dedicated.prefers_dedicated_allocation, vk::FALSE);
            ctx.device.destroy_buffer(b, None);
        }
        // A dedicated allocation (VkMemoryDedicatedAllocateInfo) is accepted.
        let b = ctx.device.create_buffer(&vk::BufferCreateInfo::default().size(1000).usage(STORAGE_ADDR), None).unwrap();
        let r = ctx.device.get_buffer_memory_requirements(b);
        let mut dedicated = vk::MemoryDedicatedAllocateInfo::default().buffer(b);
        let mut flags = vk::MemoryAllocateFlagsInfo::default().flags(vk::MemoryAllocateFlags::DEVICE_ADDRESS);
        let ai = vk::MemoryAllocateInfo::default().allocation_size(r.size).memory_type_index(0).push_next(&mut dedicated).push_next(&mut flags);
        let m = ctx.device.allocate_memory(&ai, None).unwrap();
        ctx.device.bind_buffer_memory2(&[vk::BindBufferMemoryInfo::default().buffer(b).memory(m)]).unwrap();
        ctx.device.destroy_buffer(b, None);
        ctx.device.free_memory(m, None);
        // Both memory types (ordinary, and the one sparse buffers bind) are device-local,
        // host-visible and coherent.
        let mp = ctx.instance.get_physical_device_memory_properties(ctx.physical);
        assert_eq!(mp.memory_type_count, 2);
        for t in &mp.memory_types[..2] {
            assert!(t
                .property_flags
                .contains(vk::MemoryPropertyFlags::DEVICE_LOCAL | vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT));
        }
    }
    ctx.finish();
}

#[test]
fn map_write_read_back_flush_invalidate() {
    let ctx = harness::context();
    let (b, m, p) = ctx.host_buffer(8192, vk::BufferUsageFlags::STORAGE_BUFFER);
    assert_eq!(p as usize % 64, 0, "minMemoryMapAlignment");
    // SAFETY: the mapping covers 8192 bytes; objects destroyed below.
    unsafe {
        let src: Vec<u8> = (0..8192u32).map(|i| (i * 7 + 3) as u8).collect();
        std::ptr::copy_nonoverlapping(src.as_ptr(), p, src.len());
        let ranges = [
            vk::MappedMemoryRange::default().memory(m).offset(0).size(vk::WHOLE_SIZE),
            vk::MappedMemoryRange::default().memory(m).offset(100).size(200),
        ];
        ctx.device.flush_mapped_memory_ranges(&ranges).unwrap();
        ctx.device.invalidate_mapped_memory_ranges(&ranges).unwrap();
        ctx.device.unmap_memory(m);
        // Map again at an offset: the same bytes are there.
        let q = ctx.device.map_memory(m, 4096, 1024, vk::MemoryMapFlags::empty()).unwrap() as *const u8;
        let back = std::slice::from_raw_parts(q, 1024);
        assert_eq!(back, &src[4096..5120]);
        let r = [vk::MappedMemoryRange::default().memory(m).offset(4096).size(1024)];
        ctx.device.invalidate_mapped_memory_ranges(&r).unwrap();
        ctx.device.unmap_memory(m);
        // And a whole-size map at an offset ends at the allocation's end.
        let q = ctx.device.map_memory(m, 8000, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()).unwrap() as *const u8;
        assert_eq!(std::slice::from_raw_parts(q, 192), &src[8000..8192]);
        ctx.device.unmap_memory(m);
        ctx.device.destroy_buffer(b, None);
        ctx.device.free_memory(m, None);
    }
    ctx.finish();
}

#[test]
fn new_memory_is_zeroed() {
    let ctx = harness::context();
    let (b, m, p) = ctx.host_buffer(1 << 16, vk::BufferUsageFlags::STORAGE_BUFFER);
    // SAFETY: mapping covers the buffer; objects destroyed below.
    unsafe {
        assert!(std::slice::from_raw_parts(p, 1 << 16).iter().all(|&x| x == 0));
        ctx.device.destroy_buffer(b, None);
        ctx.device.free_memory(m, None);
    }
    ctx.finish();
}

#[test]
fn out_of_device_memory_and_recovery() {
    let ctx = harness::context();
    // SAFETY: valid allocate infos; memory freed below.
    unsafe {
        let heap = ctx.instance.get_physical_device_memory_properties(ctx.physical).memory_heaps[0].size;
        let half = heap / 2 + (1 << 20);
        let ai = vk::MemoryAllocateInfo::default().allocation_size(half).memory_type_index(0);
        // Host memory is committed only as it is touched, so this costs no RAM.
        let first = ctx.device.allocate_memory(&ai, None).expect("half the heap");
        assert_eq!(ctx.device.allocate_memory(&ai, None), Err(vk::Result::ERROR_OUT_OF_DEVICE_MEMORY));
        // Small allocations still work, and freeing gives the space back.
        let small = ctx.device.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(4096).memory_type_index(0), None).unwrap();
        ctx.device.free_memory(first, None);
        let again = ctx.device.allocate_memory(&ai, None).expect("space given back");
        ctx.device.free_memory(again, None);
        ctx.device.free_memory(small, None);
        // Freeing VK_NULL_HANDLE is allowed.
        ctx.device.free_memory(vk::DeviceMemory::null(), None);
    }
    ctx.finish();
}

/// Device addresses recorded on one device are reproduced on another (opaque capture/replay).
// One function: one scenario, the replay on a second device needs the addresses the capture returned.
#[test]
fn capture_replay_reproduces_buffer_address() {
    let usage = STORAGE_ADDR;
    let capture_flags = vk::MemoryAllocateFlags::DEVICE_ADDRESS | vk::MemoryAllocateFlags::DEVICE_ADDRESS_CAPTURE_REPLAY;
    let size = 3 * 4096u64;

    // Capture: a few ordinary allocations first, then the captured buffer at offset 512.
    let ctx = harness::context();
    let bda1 = bda(&ctx);
    let (buffer_address, memory_address) = {
        // SAFETY: valid create infos; everything destroyed below.
        unsafe {
            let fillers: Vec<_> = (0..3)
                .map(|_| ctx.device.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(1 << 20).memory_type_index(0), None).unwrap())
                .collect();
            let b = ctx
                .device
                .create_buffer(
                    &vk::BufferCreateInfo::default().size(size).usage(usage).flags(vk::BufferCreateFlags::DEVICE_ADDRESS_CAPTURE_REPLAY),
                    None,
                )
                .unwrap();
            let mut flags = vk::MemoryAllocateFlagsInfo::default().flags(capture_flags);
            let m = ctx
                .device
                .allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(size + 512).memory_type_index(0).push_next(&mut flags), None)
                .unwrap();
            ctx.device.bind_buffer_memory(b, m, 512).unwrap();
            let info = vk::BufferDeviceAddressInfo::default().buffer(b);
            let a = bda1.get_buffer_device_address(&info);
            assert_eq!(bda1.get_buffer_opaque_capture_address(&info), a);
            let ma = bda1.get_device_memory_opaque_capture_address(&vk::DeviceMemoryOpaqueCaptureAddressInfo::default().memory(m));
            assert_eq!(a, ma + 512);
            ctx.device.destroy_buffer(b, None);
            ctx.device.free_memory(m, None);
            for f in fillers {
                ctx.device.free_memory(f, None);
            }
            (a, ma)
        }
    };
    ctx.finish();

    // Replay on a second device: other allocations happen in a different order, the captured
    // memory address is requested explicitly, and the buffer lands where it was.
    let ctx = harness::context();
    let bda2 = bda(&ctx);
    // SAFETY: valid create infos; everything destroyed below.
    unsafe {
        let ordinary = ctx.device.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(5 << 20).memory_type_index(0), None).unwrap();
        let mut capture_info = vk::BufferOpaqueCaptureAddressCreateInfo::default().opaque_capture_address(buffer_address);
        let b = ctx
            .device
            .create_buffer(
                &vk::BufferCreateInfo::default()
                    .size(size)
                    .usage(usage)
                    .flags(vk::BufferCreateFlags::DEVICE_ADDRESS_CAPTURE_REPLAY)
                    .push_next(&mut capture_info),
                None,
            )
            .unwrap();
        let mut flags = vk::MemoryAllocateFlagsInfo::default().flags(capture_flags);
        let mut opaque = vk::MemoryOpaqueCaptureAddressAllocateInfo::default().opaque_capture_address(memory_address);
        let ai = vk::MemoryAllocateInfo::default()
            .allocation_size(size + 512)
            .memory_type_index(0)
            .push_next(&mut flags)
            .push_next(&mut opaque);
        let m = ctx.device.allocate_memory(&ai, None).unwrap();
        ctx.device.bind_buffer_memory(b, m, 512).unwrap();
        assert_eq!(bda2.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(b)), buffer_address);
        // The address is taken now: asking for it again cannot be honoured.
        let mut flags2 = vk::MemoryAllocateFlagsInfo::default().flags(capture_flags);
        let mut opaque2 = vk::MemoryOpaqueCaptureAddressAllocateInfo::default().opaque_capture_address(memory_address);
        let ai2 = vk::MemoryAllocateInfo::default()
            .allocation_size(4096)
            .memory_type_index(0)
            .push_next(&mut flags2)
            .push_next(&mut opaque2);
        assert_eq!(ctx.device.allocate_memory(&ai2, None), Err(vk::Result::ERROR_INVALID_OPAQUE_CAPTURE_ADDRESS));
        ctx.device.destroy_buffer(b, None);
        ctx.device.free_memory(m, None);
        ctx.device.free_memory(ordinary, None);
    }
    ctx.finish();
}

#[test]
fn khr_aliases_resolve_to_the_same_commands() {
    let ctx = harness::context();
    // SAFETY: plain lookups.
    unsafe {
        for name in [c"vkGetBufferDeviceAddressKHR", c"vkGetBufferOpaqueCaptureAddressKHR", c"vkGetDeviceMemoryOpaqueCaptureAddressKHR"] {
            assert!(ctx.instance.get_device_proc_addr(ctx.device.handle(), name.as_ptr()).is_some(), "{name:?}");
        }
    }
    ctx.finish();
}

/// With the validation layer off, Arbor's own checks report invalid memory usage with VUIDs and
/// return errors; the process survives.
#[test]
fn invalid_usage_is_reported() {
    let ctx = harness::Context::new(harness::Options { validation: false, ..Default::default() });
    let d = &ctx.device;
    let bda = bda(&ctx);
    const FAILED: Option<vk::Result> = Some(vk::Result::ERROR_VALIDATION_FAILED_EXT);
    // SAFETY: deliberately invalid usage Arbor must survive; objects destroyed below.
    unsafe {
        assert_eq!(d.create_buffer(&vk::BufferCreateInfo::default().size(0).usage(vk::BufferUsageFlags::STORAGE_BUFFER), None).err(), FAILED);
        assert_eq!(d.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(4096).memory_type_index(3), None).err(), FAILED);
        // More than the whole heap: invalid usage, answered honestly.
        let heap = ctx.instance.get_physical_device_memory_properties(ctx.physical).memory_heaps[0].size;
        assert_eq!(
            d.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(heap + 1).memory_type_index(0), None),
            Err(vk::Result::ERROR_OUT_OF_DEVICE_MEMORY)
        );

        // host_buffer leaves the memory mapped: a second map fails.
        let (b, m, _) = ctx.host_buffer(1024, vk::BufferUsageFlags::STORAGE_BUFFER);
        assert_eq!(d.map_memory(m, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()), Err(vk::Result::ERROR_MEMORY_MAP_FAILED));
        d.unmap_memory(m);
        d.unmap_memory(m);
        let range = [vk::MappedMemoryRange::default().memory(m).offset(0).size(vk::WHOLE_SIZE)];
        assert_eq!(d.flush_mapped_memory_ranges(&range).err(), FAILED);
        assert_eq!(d.map_memory(m, 512, 1024, vk::MemoryMapFlags::empty()), Err(vk::Result::ERROR_MEMORY_MAP_FAILED));
        // Bound twice; misaligned; too small.
        assert_eq!(d.bind_buffer_memory(b, m, 0).err(), FAILED);
        let b2 = d.create_buffer(&vk::BufferCreateInfo::default().size(512).usage(vk::BufferUsageFlags::STORAGE_BUFFER), None).unwrap();
        assert_eq!(d.bind_buffer_memory(b2, m, 100).err(), FAILED);
        assert_eq!(d.bind_buffer_memory(b2, m, 768).err(), FAILED);
        // An address of a buffer without SHADER_DEVICE_ADDRESS usage is reported (and given).
        assert_ne!(bda.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(b)), 0);
        // A view of a buffer without texel-buffer usage is refused.
        let view = vk::BufferViewCreateInfo::default().buffer(b).format(vk::Format::R32_UINT).range(vk::WHOLE_SIZE);
        assert_eq!(d.create_buffer_view(&view, None).err(), FAILED);
        // Memory is not lazily allocated: the query is reported, and answered with the size.
        assert_eq!(d.get_device_memory_commitment(m), 1024);
        d.destroy_buffer(b2, None);
        d.destroy_buffer(b, None);
        d.free_memory(m, None);
    }
    ctx.finish();
    let diag = harness::diagnostics();
    for vuid in [
        "VUID-vkAllocateMemory-pAllocateInfo-01713",
        "VUID-vkGetDeviceMemoryCommitment-memory-00690",
        "VUID-VkBufferCreateInfo-size-00912",
        "VUID-vkAllocateMemory-pAllocateInfo-01714",
        "VUID-vkMapMemory-memory-00678",
        "VUID-vkUnmapMemory-memory-00689",
        "VUID-VkMappedMemoryRange-memory-00684",
        "VUID-vkMapMemory-size-00681",
        "VUID-vkBindBufferMemory-buffer-07459",
        "VUID-vkBindBufferMemory-memoryOffset-01036",
        "VUID-vkBindBufferMemory-size-01037",
        "VUID-VkBufferDeviceAddressInfo-buffer-02601",
        "VUID-VkBufferViewCreateInfo-buffer-00932",
    ] {
        assert!(diag.contains(vuid), "{vuid} not reported:\n{diag}");
    }
}

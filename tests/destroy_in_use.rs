//! Destroying what pending work uses: an acceleration structure, its buffer or its memory while
//! a submitted build into it is pending, and vkDestroyDevice with work pending or children
//! alive. Each is reported at destroy time with its VUID; the process lives, guard bytes hold,
//! and the device still builds afterwards (`runtime::in_use`).
//!
//! The pending build is held back by a timeline semaphore the test signals from the host once
//! the objects are destroyed. The validation layer is off (the uses are invalid on purpose).
mod harness;

use std::time::Duration;

use ash::vk;
use harness::vuid::*;
use harness::{bounded, diagnostics};

const BOUND_S: u64 = 30;

/// A short grace period for stalled waits (`ARBOR_STALL_MS`, read once per process: every test
/// sets the same value before its first Vulkan call).
fn stall_ms() {
    std::env::set_var("ARBOR_STALL_MS", "300");
}

fn reported_by<R>(f: impl FnOnce() -> R) -> (R, String) {
    let mark = diagnostics().len();
    let r = f();
    (r, diagnostics()[mark..].to_string())
}

fn timeline(d: &ash::Device) -> vk::Semaphore {
    let mut ty = vk::SemaphoreTypeCreateInfo::default().semaphore_type(vk::SemaphoreType::TIMELINE).initial_value(0);
    // SAFETY: valid create info; the caller destroys it.
    unsafe { d.create_semaphore(&vk::SemaphoreCreateInfo::default().push_next(&mut ty), None) }.unwrap()
}

/// A structure of the test's own (not the helper's, which destroys its objects itself): a
/// buffer of its own memory, the structure at offset GUARD with GUARD bytes of 0xA5 around it.
struct Own {
    buffer: vk::Buffer,
    memory: vk::DeviceMemory,
    ptr: *mut u8,
    size: u64,
    s: vk::AccelerationStructureKHR,
}

impl Own {
    fn new(a: &Accel, size: u64) -> Own {
        let (buffer, memory, ptr) = a.ctx.host_buffer(size + 2 * GUARD, ALL_USAGE);
        // SAFETY: mapped memory of size + 2 * GUARD bytes.
        unsafe { std::ptr::write_bytes(ptr, FILL, (size + 2 * GUARD) as usize) };
        let info = vk::AccelerationStructureCreateInfoKHR::default().buffer(buffer).offset(GUARD).size(size).ty(BLAS);
        // SAFETY: valid create info.
        let s = unsafe { a.ext.create_acceleration_structure(&info, None) }.unwrap();
        Own { buffer, memory, ptr, size, s }
    }

    fn bytes(&self) -> Vec<u8> {
        // SAFETY: the memory is still mapped (not freed).
        unsafe { std::slice::from_raw_parts(self.ptr, (self.size + 2 * GUARD) as usize).to_vec() }
    }
}

/// Record a grid build into `dst` and submit it behind timeline value 1 of `sem`.
fn pending_build(a: &Accel, m: &Mesh, dst: vk::AccelerationStructureKHR, scratch: &Region, sem: vk::Semaphore) -> vk::Fence {
    let d = &a.ctx.device;
    let geoms = [mesh_geom(a, m)];
    let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(dst).scratch_data(madr(scratch.address(a)));
    let ranges = [range(m.count)];
    // SAFETY: valid objects; the command buffer is freed with the helper's pool.
    unsafe {
        let cb = d.allocate_command_buffers(&vk::CommandBufferAllocateInfo::default().command_pool(a.pool).command_buffer_count(1)).unwrap()[0];
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        a.ext.cmd_build_acceleration_structures(cb, &[inf], &[&ranges]);
        d.end_command_buffer(cb).unwrap();
        let f = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        let (waits, stages, cbs, wv) = ([sem], [vk::PipelineStageFlags::ALL_COMMANDS], [cb], [1u64]);
        let mut tsi = vk::TimelineSemaphoreSubmitInfo::default().wait_semaphore_values(&wv);
        let submit = vk::SubmitInfo::default().wait_semaphores(&waits).wait_dst_stage_mask(&stages).command_buffers(&cbs).push_next(&mut tsi);
        d.queue_submit(a.ctx.queues[a.queue], &[submit], f).unwrap();
        f
    }
}

/// Release the pending build and wait for its fence.
fn release(a: &Accel, sem: vk::Semaphore, fence: vk::Fence) {
    let d = &a.ctx.device;
    let tl = ash::khr::timeline_semaphore::Device::new(&a.ctx.instance, d);
    // SAFETY: live semaphore and fence.
    unsafe {
        tl.signal_semaphore(&vk::SemaphoreSignalInfo::default().semaphore(sem).value(1)).unwrap();
        d.wait_for_fences(&[fence], true, u64::MAX).unwrap();
        d.destroy_fence(fence, None);
        d.destroy_semaphore(sem, None);
    }
}

fn sizes_of_grid(a: &Accel, m: &Mesh) -> (u64, u64) {
    let geoms = [mesh_geom(a, m)];
    let s = a.sizes(DEVICE, &info(BLAS, NO_FLAGS, &geoms), &[m.count]);
    (s.acceleration_structure_size, s.build_scratch_size)
}

#[test]
fn destroying_a_structure_and_its_buffer_while_a_build_is_pending() {
    bounded(BOUND_S, || {
        stall_ms();
        scenario(|a, m| {
            let d = &a.ctx.device;
            let (size, scratch_size) = sizes_of_grid(a, m);
            let own = Own::new(a, size);
            let scratch = guarded(a, scratch_size);
            let sem = timeline(d);
            let fence = pending_build(a, m, own.s, &scratch, sem);
            // SAFETY: destroyed while the build into them is pending, on purpose.
            let (_, said) = reported_by(|| unsafe {
                a.ext.destroy_acceleration_structure(own.s, None);
                d.destroy_buffer(own.buffer, None);
            });
            assert!(said.contains("[VUID-vkDestroyAccelerationStructureKHR-accelerationStructure-02442] acceleration structure"), "{said}");
            assert!(said.contains("[VUID-vkDestroyBuffer-buffer-00922] buffer"), "{said}");
            let (_, said) = reported_by(|| release(a, sem, fence));
            assert!(!said.contains("arbor: error"), "the build finishes without a complaint:\n{said}");
            // The structures' Arcs kept the view: the build finished into the memory.
            let bytes = own.bytes();
            let g = GUARD as usize;
            assert!(bytes[..g].iter().chain(&bytes[g + size as usize..]).all(|&b| b == FILL), "guard bytes changed");
            let h = arbor::accel::header(&bytes[g..g + size as usize]).expect("the pending build finished");
            assert_eq!(h.primitive_count, m.count);
            assert_guards(a, scratch);
            // SAFETY: nothing uses the memory any more: no report.
            let (_, said) = reported_by(|| unsafe { d.free_memory(own.memory, None) });
            assert!(!said.contains("arbor: error"), "{said}");
        });
    });
}

#[test]
fn freeing_the_memory_of_a_pending_build() {
    bounded(BOUND_S, || {
        stall_ms();
        scenario(|a, m| {
            let d = &a.ctx.device;
            let (size, scratch_size) = sizes_of_grid(a, m);
            let own = Own::new(a, size);
            let scratch = guarded(a, scratch_size);
            let sem = timeline(d);
            let fence = pending_build(a, m, own.s, &scratch, sem);
            // SAFETY: freed while the build into it is pending, on purpose.
            let (_, said) = reported_by(|| unsafe {
                a.ext.destroy_acceleration_structure(own.s, None);
                d.destroy_buffer(own.buffer, None);
                d.free_memory(own.memory, None);
            });
            assert!(said.contains("[VUID-vkFreeMemory-memory-00677] memory"), "{said}");
            // The build is skipped (its destination no longer resolves) and says so.
            let (_, said) = reported_by(|| release(a, sem, fence));
            assert!(said.contains("arbor: error: vkCmdBuildAccelerationStructuresKHR"), "the skipped build is reported:\n{said}");
            assert!(!said.contains("panic") && !said.contains("internal error"), "{said}");
            assert_guards(a, scratch);
        });
    });
}

#[test]
fn destroying_a_device_with_children_alive_reports_them_once() {
    bounded(BOUND_S, || {
        stall_ms();
        let _s = serial();
        let ctx = context();
        let d = &ctx.device;
        // SAFETY: objects left alive on purpose.
        unsafe {
            let _ = ctx.host_buffer(256, ALL_USAGE);
            let _ = ctx.host_buffer(256, ALL_USAGE);
            let _ = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        }
        let (_, said) = reported_by(|| ctx.finish());
        let lines: Vec<&str> = said.lines().filter(|l| l.contains("VUID-vkDestroyDevice-device-05137")).collect();
        assert_eq!(lines.len(), 1, "{said}");
        assert!(lines[0].contains("child objects not destroyed: 2 VkBuffer, 2 VkDeviceMemory, 1 VkFence"), "{said}");
    });
}

#[test]
fn destroying_a_device_with_work_pending() {
    bounded(BOUND_S, || {
        stall_ms();
        let _s = serial();
        let ctx = context();
        let d = ctx.device.clone();
        let sem = timeline(&d);
        let (waits, stages, wv) = ([sem], [vk::PipelineStageFlags::ALL_COMMANDS], [1u64]);
        let mut tsi = vk::TimelineSemaphoreSubmitInfo::default().wait_semaphore_values(&wv);
        let submit = vk::SubmitInfo::default().wait_semaphores(&waits).wait_dst_stage_mask(&stages).push_next(&mut tsi);
        // SAFETY: a submission waiting for a value nobody signals; the device is destroyed
        // while it is pending, on purpose.
        unsafe { d.queue_submit(ctx.queues[1], &[submit], vk::Fence::null()) }.unwrap();
        std::thread::sleep(Duration::from_millis(20));
        // SAFETY: as above.
        unsafe { d.destroy_semaphore(sem, None) };
        let (_, said) = reported_by(|| ctx.finish_without_wait());
        assert!(said.contains("vkDestroyDevice: 1 submission(s) still pending on queue (family 0, index 1)"), "{said}");
        assert!(said.contains("vkDestroyDevice: [stall] queue (family 0, index 1) is blocked"), "{said}");
    });
}

const STRICT_CHILD: &str = "strict_child_destroying_in_use_loses_the_device";

#[test]
fn strict_mode_turns_destroying_in_use_into_device_lost() {
    bounded(BOUND_S, || {
        stall_ms();
        let text = harness::child::run_child_test(STRICT_CHILD, &[("ARBOR_STRICT", "1")]);
        assert!(text.contains("strict child: device lost as expected"), "the strict-mode child skipped its checks:\n{text}");
    });
}

#[test]
#[ignore = "run by strict_mode_turns_destroying_in_use_into_device_lost in a child process with ARBOR_STRICT=1"]
fn strict_child_destroying_in_use_loses_the_device() {
    if std::env::var("ARBOR_STRICT").as_deref() != Ok("1") {
        return;
    }
    stall_ms();
    let ctx = context();
    let a = Accel::new(&ctx);
    let m = upload_grid(&a);
    let d = &ctx.device;
    let (size, scratch_size) = sizes_of_grid(&a, &m);
    let own = Own::new(&a, size);
    let scratch = guarded(&a, scratch_size);
    let sem = timeline(d);
    let fence = pending_build(&a, &m, own.s, &scratch, sem);
    // SAFETY: destroyed while the build into it is pending, on purpose.
    unsafe { a.ext.destroy_acceleration_structure(own.s, None) };
    let tl = ash::khr::timeline_semaphore::Device::new(&ctx.instance, d);
    // SAFETY: live semaphore and fence.
    unsafe {
        let _ = tl.signal_semaphore(&vk::SemaphoreSignalInfo::default().semaphore(sem).value(1));
        assert_eq!(d.wait_for_fences(&[fence], true, u64::MAX), Err(vk::Result::ERROR_DEVICE_LOST));
    }
    println!("strict child: device lost as expected");
}

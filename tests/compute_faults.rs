//! Compute shaders that go wrong, through the loader with validation on: a module Arbor cannot
//! run fails at pipeline creation naming what it rejects; out-of-bounds accesses and a null
//! device address are reported once and contained, and the device stays usable; a shader that
//! never ends is stopped by the watchdog, which loses the device (in a child process, because
//! ARBOR_WATCHDOG_SECONDS is read once per process); destroying the device while such a shader
//! runs stops it at once, long before the watchdog's deadline (validation off there: that use is
//! invalid on purpose).
mod harness;

use ash::vk;
use harness::compute::*;

#[test]
fn an_unsupported_instruction_fails_pipeline_creation_with_its_name_and_offset() {
    let gpu = Gpu::arbor();
    let job = Job::new(glsl("vk_reject.comp"), vec![Binding::storage(vec![0; 16])], Size::Direct([1, 1, 1]));
    assert_eq!(run(&gpu, &job).err(), Some(JobError::Pipeline(vk::Result::ERROR_UNKNOWN)));
    let diag = harness::diagnostics();
    let line = diag.lines().find(|l| l.contains("vkCreateComputePipelines") && l.contains("GLSL.std.450 instruction 58 at word"));
    assert!(line.is_some(), "no diagnostic naming PackHalf2x16 (GLSL.std.450 58) and its word offset:\n{diag}");
    // The device is fine: a good shader runs afterwards.
    let ok = Job::new(glsl("vk_dispatch.comp"), vec![Binding::storage(vec![0; 512 * 8 * 16])], Size::Direct([1, 1, 1]));
    assert_eq!(as_u32(&run(&gpu, &ok).unwrap()[0])[0], 1);
    gpu.assert_quiet();
}

#[test]
fn out_of_bounds_accesses_are_contained_and_reported_once() {
    let gpu = Gpu::arbor();
    // Both descriptors cover 64 bytes (16 words) of 256-byte buffers; invocations 8..16 go
    // past the range by `offset` = 8.
    let src: Vec<u32> = (0..64).map(|i| 100 + i).collect();
    let mut dst = Binding::storage(u32s(&[0xDEAD_BEEF; 64]));
    dst.range = 64;
    let mut input = Binding::storage(u32s(&src));
    input.range = 64;
    let mut job = Job::new(glsl("vk_oob.comp"), vec![dst, input], Size::Direct([1, 1, 1]));
    job.push = u32s(&[8]);
    let out = as_u32(&run(&gpu, &job).expect("the dispatch completes")[0]);
    for (i, &v) in out.iter().enumerate() {
        let want = if (8..16).contains(&i) { src[i] + 1 } else { 0xDEAD_BEEF };
        assert_eq!(v, want, "word {i}: only in-range writes land; nothing outside the descriptor's range changes");
    }
    let diag = harness::diagnostics();
    let lines: Vec<&str> = diag.lines().filter(|l| l.contains("robustBufferAccess") && l.contains("contained memory fault")).collect();
    assert_eq!(lines.len(), 1, "one diagnostic per dispatch:\n{diag}");
    assert!(lines[0].contains("Binding { set: 0, binding: 0 }") || lines[0].contains("Binding { set: 0, binding: 1 }"), "{}", lines[0]);
    // Not lost: the next dispatch runs.
    job.push = u32s(&[0]);
    assert!(run(&gpu, &job).is_ok());
    gpu.assert_quiet();
}

#[test]
fn a_null_device_address_is_contained_and_reported() {
    let gpu = Gpu::arbor();
    // No address patch: the header pointer in the push constants is null.
    let mut job = Job::new(glsl("vk_bda.comp"), vec![Binding::storage(u32s(&[7; 64]))], Size::Direct([2, 1, 1]));
    job.push = vec![0; 8];
    let out = as_u32(&run(&gpu, &job).expect("the dispatch completes")[0]);
    assert!(out.iter().all(|&v| v == 7), "nothing is written when the header cannot be read");
    let diag = harness::diagnostics();
    assert!(
        diag.lines().any(|l| l.contains("PhysicalStorageBuffer") && l.contains("Unmapped") && l.contains("DeviceAddress")),
        "no diagnostic for the null address:\n{diag}"
    );
    assert!(run(&gpu, &job).is_ok(), "the device is not lost");
    gpu.assert_quiet();
}

const WATCHDOG_CHILD: &str = "watchdog_child_endless_shader_loses_the_device";

#[test]
fn the_watchdog_stops_an_endless_shader_and_loses_the_device() {
    let out = std::process::Command::new(std::env::current_exe().unwrap())
        .args([WATCHDOG_CHILD, "--exact", "--ignored", "--nocapture", "--test-threads=1"])
        .env("ARBOR_WATCHDOG_SECONDS", "1")
        .output()
        .expect("run the test binary as a child");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the watchdog child failed:\n{text}");
    assert!(text.contains("1 passed"), "the watchdog child did not run:\n{text}");
    assert!(text.contains("watchdog child: device lost as expected"), "the watchdog child skipped its checks:\n{text}");
}

#[test]
#[ignore = "run by the_watchdog_stops_an_endless_shader_and_loses_the_device in a child process with ARBOR_WATCHDOG_SECONDS=1"]
fn watchdog_child_endless_shader_loses_the_device() {
    if std::env::var("ARBOR_WATCHDOG_SECONDS").as_deref() != Ok("1") {
        return;
    }
    let gpu = Gpu::arbor();
    let start = std::time::Instant::now();
    let job = Job::new(glsl("vk_spin.comp"), vec![Binding::storage(vec![0; 8])], Size::Direct([4, 1, 1]));
    let r = run(&gpu, &job);
    assert!(start.elapsed().as_secs() < 30, "the queue hung for {:?}", start.elapsed());
    assert_eq!(r.err(), Some(JobError::Submit(vk::Result::ERROR_DEVICE_LOST)), "the fence wait reports the lost device");
    // Later submissions report it too, at once.
    let ok = Job::new(glsl("vk_dispatch.comp"), vec![Binding::storage(vec![0; 512 * 8 * 16])], Size::Direct([1, 1, 1]));
    assert_eq!(run(&gpu, &ok).err(), Some(JobError::Submit(vk::Result::ERROR_DEVICE_LOST)));
    let diag = harness::diagnostics();
    assert!(diag.contains("did not finish within 1 s (ARBOR_WATCHDOG_SECONDS)"), "no watchdog diagnostic:\n{diag}");
    // The layer keeps the lost submissions' fence and command buffer "in use" (their waits
    // returned DEVICE_LOST, not SUCCESS), so destroying them is reported; nothing else may be.
    let lost_only = ["VUID-vkDestroyFence-fence-01120", "VUID-vkDestroyCommandPool-commandPool-00041"];
    let other: Vec<String> = gpu.messages().into_iter().filter(|m| !lost_only.iter().any(|v| m.contains(v))).collect();
    assert!(other.is_empty(), "validation messages:\n{}", other.join("\n"));
    println!("watchdog child: device lost as expected");
}

const DESTROY_CHILD: &str = "destroy_child_endless_shader_stops_when_the_device_is_destroyed";

#[test]
fn destroying_the_device_stops_an_endless_shader_long_before_the_watchdog() {
    let out = std::process::Command::new(std::env::current_exe().unwrap())
        .args([DESTROY_CHILD, "--exact", "--ignored", "--nocapture", "--test-threads=1"])
        .env("ARBOR_WATCHDOG_SECONDS", "600")
        .output()
        .expect("run the test binary as a child");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the destroy child failed:\n{text}");
    assert!(text.contains("1 passed"), "the destroy child did not run:\n{text}");
    assert!(text.contains("destroy child: the dispatch was stopped"), "the destroy child skipped its checks:\n{text}");
}

#[test]
#[ignore = "run by destroying_the_device_stops_an_endless_shader_long_before_the_watchdog in a child process with ARBOR_WATCHDOG_SECONDS=600"]
fn destroy_child_endless_shader_stops_when_the_device_is_destroyed() {
    if std::env::var("ARBOR_WATCHDOG_SECONDS").as_deref() != Ok("600") {
        return;
    }
    harness::use_arbor_manifest();
    let spirv = glsl("vk_spin.comp");
    // Without the cancel flag vkDestroyDevice waits for the 600 s watchdog: the bound fails it.
    harness::bounded(60, move || destroy_while_spinning(&spirv));
    let diag = harness::diagnostics();
    assert!(diag.contains("dispatch stopped before it finished"), "no diagnostic for the stopped dispatch:\n{diag}");
    assert!(!diag.contains("ARBOR_WATCHDOG_SECONDS"), "the deadline fired instead:\n{diag}");
    println!("destroy child: the dispatch was stopped");
}

/// Submit the endless shader, see it still running, then destroy the device with the work
/// pending (invalid on purpose, so no validation layer here).
fn destroy_while_spinning(spirv: &[u32]) {
    // SAFETY: valid create infos on live objects; the device is destroyed with its work pending
    // on purpose, the other children are left to the driver's teardown.
    unsafe {
        let entry = ash::Entry::load().expect("libvulkan.so.1");
        let app = vk::ApplicationInfo::default().api_version(vk::API_VERSION_1_2);
        let instance = entry.create_instance(&vk::InstanceCreateInfo::default().application_info(&app), None).unwrap();
        let pd = instance.enumerate_physical_devices().unwrap()[0];
        let prio = [1.0f32];
        let qci = [vk::DeviceQueueCreateInfo::default().queue_family_index(0).queue_priorities(&prio)];
        let d = instance.create_device(pd, &vk::DeviceCreateInfo::default().queue_create_infos(&qci), None).unwrap();
        let buffer = d.create_buffer(&vk::BufferCreateInfo::default().size(8).usage(vk::BufferUsageFlags::STORAGE_BUFFER), None).unwrap();
        let req = d.get_buffer_memory_requirements(buffer);
        let mp = instance.get_physical_device_memory_properties(pd);
        let host = vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT;
        let ty = (0..mp.memory_type_count).find(|&i| req.memory_type_bits & (1 << i) != 0 && mp.memory_types[i as usize].property_flags.contains(host)).unwrap();
        let memory = d.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(req.size).memory_type_index(ty), None).unwrap();
        d.bind_buffer_memory(buffer, memory, 0).unwrap();
        let p = d.map_memory(memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()).unwrap() as *mut u8;
        std::ptr::write_bytes(p, 0, 8); // flag = 0: the loop never ends
        let slot = [vk::DescriptorSetLayoutBinding::default()
            .binding(0)
            .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
            .descriptor_count(1)
            .stage_flags(vk::ShaderStageFlags::COMPUTE)];
        let dsl = [d.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&slot), None).unwrap()];
        let layout = d.create_pipeline_layout(&vk::PipelineLayoutCreateInfo::default().set_layouts(&dsl), None).unwrap();
        let module = d.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(spirv), None).unwrap();
        let stage = vk::PipelineShaderStageCreateInfo::default().stage(vk::ShaderStageFlags::COMPUTE).module(module).name(c"main");
        let pipeline = d.create_compute_pipelines(vk::PipelineCache::null(), &[vk::ComputePipelineCreateInfo::default().stage(stage).layout(layout)], None).unwrap()[0];
        let sizes = [vk::DescriptorPoolSize::default().ty(vk::DescriptorType::STORAGE_BUFFER).descriptor_count(1)];
        let pool = d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(1).pool_sizes(&sizes), None).unwrap();
        let set = d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&dsl)).unwrap()[0];
        let info = [vk::DescriptorBufferInfo::default().buffer(buffer).range(vk::WHOLE_SIZE)];
        d.update_descriptor_sets(&[vk::WriteDescriptorSet::default().dst_set(set).descriptor_type(vk::DescriptorType::STORAGE_BUFFER).buffer_info(&info)], &[]);
        let cmd_pool = d.create_command_pool(&vk::CommandPoolCreateInfo::default().queue_family_index(0), None).unwrap();
        let cb = d.allocate_command_buffers(&vk::CommandBufferAllocateInfo::default().command_pool(cmd_pool).command_buffer_count(1)).unwrap()[0];
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        d.cmd_bind_pipeline(cb, vk::PipelineBindPoint::COMPUTE, pipeline);
        d.cmd_bind_descriptor_sets(cb, vk::PipelineBindPoint::COMPUTE, layout, 0, &[set], &[]);
        d.cmd_dispatch(cb, 4, 1, 1);
        d.end_command_buffer(cb).unwrap();
        let fence = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        d.queue_submit(d.get_device_queue(0, 0), &[vk::SubmitInfo::default().command_buffers(&[cb])], fence).unwrap();
        assert_eq!(d.wait_for_fences(&[fence], true, 300_000_000), Err(vk::Result::TIMEOUT), "the endless shader finished");
        d.destroy_device(None);
        instance.destroy_instance(None);
    }
}

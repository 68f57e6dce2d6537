//! Compute shaders that go wrong, through the loader with validation on: a module Arbor cannot
//! run fails at pipeline creation naming what it rejects; out-of-bounds accesses and a null
//! device address are reported once and contained, and the device stays usable; a shader that
//! never ends is stopped by the watchdog, which loses the device (in a child process, because
//! ARBOR_WATCHDOG_SECONDS is read once per process).
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

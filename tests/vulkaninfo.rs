//! Debian's vulkaninfo (vulkan-tools) shows Arbor through the loader, cleanly.
mod harness;

use std::process::Command;

fn run_vulkaninfo(args: &[&str]) -> (bool, String, String) {
    let manifest = harness::use_arbor_manifest();
    let out = Command::new("vulkaninfo")
        .args(args)
        .env("VK_ICD_FILENAMES", &manifest)
        .env("VK_DRIVER_FILES", &manifest)
        .env("VK_LOADER_DEBUG", "error,warn")
        .env("NODEVICE_SELECT", "1")
        .output()
        .expect("vulkaninfo not found: install vulkan-tools (the README's test command does)");
    (out.status.success(), String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned())
}

/// Lines that report a problem from the loader or from Arbor's diagnostics channel.
fn problems(text: &str) -> Vec<&str> {
    text.lines()
        .filter(|l| l.contains("Loader Message") || l.starts_with("arbor:") || l.contains("ERROR") || l.contains("WARNING"))
        .collect()
}

#[test]
fn vulkaninfo_summary_shows_arbor() {
    let (ok, stdout, stderr) = run_vulkaninfo(&["--summary"]);
    assert!(ok, "vulkaninfo --summary failed:\n{stdout}\n{stderr}");
    assert!(
        stdout.lines().any(|l| l.trim().starts_with("deviceName") && l.contains("= Arbor (software)")),
        "no Arbor device line:\n{stdout}"
    );
    assert!(stdout.contains("PHYSICAL_DEVICE_TYPE_CPU"));
    let p: Vec<_> = problems(&stdout).into_iter().chain(problems(&stderr)).collect();
    assert!(p.is_empty(), "problems reported: {p:#?}");
}

#[test]
fn vulkaninfo_full_report_is_clean() {
    let (ok, stdout, stderr) = run_vulkaninfo(&[]);
    assert!(ok, "vulkaninfo failed:\n{stderr}");
    assert!(stdout.contains("Arbor (software)"));
    assert!(stdout.contains("VK_KHR_buffer_device_address"));
    let p: Vec<_> = problems(&stdout).into_iter().chain(problems(&stderr)).collect();
    assert!(p.is_empty(), "problems reported: {p:#?}");
}

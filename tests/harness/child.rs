//! Settings Arbor reads once per process (`ARBOR_STRICT`, `ARBOR_WATCHDOG_SECONDS`, …) are tested
//! in a child process: the parent test runs one ignored test of its own binary with the setting.

/// Runs the ignored test `name` of this test binary in a child process with `env`; fails unless
/// it ran and passed. Returns the child's stdout and stderr.
pub fn run_child_test(name: &str, env: &[(&str, &str)]) -> String {
    let out = std::process::Command::new(std::env::current_exe().expect("test executable path"))
        .args([name, "--exact", "--ignored", "--nocapture", "--test-threads=1"])
        .envs(env.iter().copied())
        .output()
        .expect("run the test binary as a child");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the child test {name} failed:\n{text}");
    assert!(text.contains("1 passed"), "the child test {name} did not run:\n{text}");
    text
}

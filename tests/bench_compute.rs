//! arbor-bench's compute workloads (target/release/arbor-bench, built by `cargo build --release
//! --workspace`) on tiny sizes: each runs on Arbor (and on lavapipe when installed), reports a
//! positive rate and says its output matched the CPU computation (the harness fails the row
//! otherwise). And the committed SPIR-V of bench/shaders is what glslang makes of the GLSL
//! beside it, when glslangValidator is installed.
use std::path::PathBuf;
use std::process::Command;

const COMPUTE: [&str; 4] = ["compute-alu", "compute-memory", "compute-divergent", "compute-first-dispatch"];

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn bench_exe() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    let profile_dir = exe.parent().and_then(|d| d.parent()).expect("target/<profile>");
    let release = profile_dir.parent().map(|t| t.join("release").join("arbor-bench"));
    for c in [release, Some(profile_dir.join("arbor-bench"))].into_iter().flatten() {
        if c.exists() && c.parent().map(|d| d.join("libvulkan_arbor.so").exists()).unwrap_or(false) {
            return c;
        }
    }
    panic!("target/release/arbor-bench with libvulkan_arbor.so beside it is missing: run `cargo build --release --workspace` first");
}

/// The value of `"key": value` in one JSON result line (the harness writes one object a line).
fn field<'a>(line: &'a str, key: &str) -> &'a str {
    let pat = format!("\"{key}\": ");
    let at = line.find(&pat).unwrap_or_else(|| panic!("{key} missing in {line}")) + pat.len();
    let rest = &line[at..];
    if let Some(s) = rest.strip_prefix('"') {
        let mut end = 0;
        let b = s.as_bytes();
        while b[end] != b'"' {
            end += if b[end] == b'\\' { 2 } else { 1 };
        }
        &s[..end]
    } else {
        rest[..rest.find([',', '}']).unwrap_or(rest.len())].trim()
    }
}

/// Runs the compute workloads on `driver`; returns (stdout, one JSON result line per workload).
fn run(driver: &str, threads: &str) -> Option<(String, Vec<String>)> {
    let dir = std::env::temp_dir().join(format!("arbor-bench-compute-{}-{driver}-{threads}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("out.json");
    let out = Command::new(bench_exe())
        .args(["--driver", driver, "--threads", threads, "--workloads", "compute", "--invocations", "700", "--memory-mib", "1"])
        .args(["--repeat", "2", "--warmup", "0", "--json"])
        .arg(&json)
        .env("NODEVICE_SELECT", "1")
        .output()
        .expect("run arbor-bench");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    if stderr.contains(&format!("skipping {driver}")) {
        println!("{driver} is not installed: its compute rows are skipped ({stderr})");
        return None;
    }
    assert!(out.status.success(), "arbor-bench --driver {driver} failed ({}):\n{stdout}\n{stderr}", out.status);
    let text = std::fs::read_to_string(&json).unwrap();
    let rows: Vec<String> = text.lines().filter(|l| l.contains("\"workload\": \"compute-")).map(str::to_string).collect();
    Some((stdout, rows))
}

fn check(driver: &str, stdout: &str, rows: &[String]) {
    assert_eq!(rows.len(), COMPUTE.len(), "one row per compute workload:\n{stdout}");
    for (row, w) in rows.iter().zip(COMPUTE) {
        assert_eq!(field(row, "driver"), driver);
        assert_eq!(field(row, "workload"), w);
        assert_eq!(field(row, "status"), "ok", "{row}");
        let rate: f64 = field(row, "mprims_per_s").parse().unwrap_or_else(|_| panic!("no rate: {row}"));
        assert!(rate > 0.0, "{row}");
        let median: f64 = field(row, "median_ms").parse().unwrap();
        assert!(median > 0.0, "{row}");
        let expected = match w {
            "compute-memory" => 65536.0,
            "compute-first-dispatch" => 256.0,
            _ => 700.0,
        };
        assert_eq!(field(row, "primitives").parse::<f64>().unwrap(), expected, "{row}");
        // The harness writes "verified" only after comparing every output with the CPU's; a
        // mismatch fails the row instead.
        assert!(field(row, "note").contains("verified"), "{row}");
        let line = format!("{driver} (threads ");
        assert!(stdout.lines().any(|l| l.starts_with(&line) && l.contains(w) && l.contains("verified")), "{w} missing below the table:\n{stdout}");
    }
}

#[test]
fn compute_workloads_run_and_verify_on_arbor() {
    for threads in ["1", "2"] {
        let (stdout, rows) = run("arbor", threads).expect("Arbor is always there");
        check("arbor", &stdout, &rows);
        assert!(rows.iter().all(|r| field(r, "threads") == threads), "{rows:?}");
    }
}

#[test]
fn compute_workloads_run_and_verify_on_lavapipe() {
    if let Some((stdout, rows)) = run("lavapipe", "1") {
        check("lavapipe", &stdout, &rows);
    }
}

#[test]
fn committed_spirv_matches_the_glsl() {
    let dir = root().join("bench/shaders");
    let mut shaders: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        // compute_*.comp only: trace.comp targets Vulkan 1.2 and tests/bench_harness.rs checks it.
        .filter(|p| p.extension().is_some_and(|e| e == "comp") && p.file_name().is_some_and(|n| n.to_string_lossy().starts_with("compute_")))
        .collect();
    shaders.sort();
    assert!(shaders.len() >= 3, "bench/shaders/compute_*.comp missing");
    let tmp = std::env::temp_dir().join(format!("arbor-bench-spv-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    for src in shaders {
        let committed = src.with_extension("spv");
        assert!(committed.exists(), "{} has no committed SPIR-V beside it", src.display());
        let out = tmp.join(committed.file_name().unwrap());
        let r = match Command::new("glslangValidator").args(["-V", "--target-env", "vulkan1.1", "-o"]).arg(&out).arg(&src).output() {
            Ok(r) => r,
            Err(_) => {
                println!("glslangValidator is not installed: the committed SPIR-V is not rechecked");
                return;
            }
        };
        assert!(r.status.success(), "glslang failed on {}:\n{}", src.display(), String::from_utf8_lossy(&r.stdout));
        assert!(
            std::fs::read(&out).unwrap() == std::fs::read(&committed).unwrap(),
            "{} is stale: regenerate it with `glslangValidator -V --target-env vulkan1.1 -o {} {}`",
            committed.display(),
            committed.display(),
            src.display()
        );
    }
}

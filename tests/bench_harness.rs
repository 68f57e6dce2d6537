//! Runs the built harness (target/release/arbor-bench, built by `cargo build --release
//! --workspace`) on a small scene and checks the table, the JSON and the CSV: every column,
//! one row per workload, sane values (times > 0, sizes > 0, compacted ≤ size, SAH and node counts
//! for Arbor). Then the same against lavapipe when it is installed (skipped with a message when
//! not), where host and indirect builds must read "not supported", not fail. The trace workloads
//! (ray queries from a compute shader) on Arbor, and `--compare lavapipe` on the same rays; the
//! committed SPIR-V of the trace shader against a fresh compile.
use std::path::PathBuf;
use std::process::Command;

const WORKLOADS: [&str; 7] = ["fast-trace", "fast-build", "update", "compact", "indirect", "host", "host-deferred"];
const TABLE_COLUMNS: [&str; 19] = [
    "driver", "threads", "scene", "workload", "prims", "timing", "median ms", "min ms", "max ms", "wall ms", "Mprim/s", "AS size",
    "compacted", "scratch", "B/prim", "SAH", "nodes", "leaves", "Mray/s",
];
const FIELDS: [&str; 27] = [
    "driver", "device", "threads", "scene", "workload", "primitives", "status", "reason", "timing", "repeat", "median_ms", "min_ms",
    "max_ms", "wall_median_ms", "wall_min_ms", "wall_max_ms", "mprims_per_s", "as_size", "compacted_size", "scratch_size",
    "bytes_per_prim", "sah_cost", "node_count", "leaf_count", "note", "rays", "mrays_per_s",
];

fn bench_exe() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    let profile_dir = exe.parent().and_then(|d| d.parent()).expect("target/<profile>");
    // The README's test command builds the release workspace; prefer that binary.
    let release = profile_dir.parent().map(|t| t.join("release").join("arbor-bench"));
    let candidates = [release, Some(profile_dir.join("arbor-bench"))];
    for c in candidates.into_iter().flatten() {
        if c.exists() && c.parent().map(|d| d.join("libvulkan_arbor.so").exists()).unwrap_or(false) {
            return c;
        }
    }
    panic!("target/release/arbor-bench with libvulkan_arbor.so beside it is missing: run `cargo build --release --workspace` first");
}

fn out_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("arbor-bench-test-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A flat JSON object's fields (the harness writes one result object per line, no nesting).
fn fields(obj: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let b = obj.trim().trim_start_matches('{').trim_end_matches(',').trim_end_matches('}');
    let mut rest = b;
    while let Some(start) = rest.find('"') {
        let after = &rest[start + 1..];
        let end = after.find('"').unwrap();
        let key = after[..end].to_string();
        let after = after[end + 1..].trim_start().strip_prefix(':').unwrap().trim_start();
        let (value, tail) = if let Some(s) = after.strip_prefix('"') {
            let mut i = 0;
            let bytes = s.as_bytes();
            while bytes[i] != b'"' {
                i += if bytes[i] == b'\\' { 2 } else { 1 };
            }
            (s[..i].to_string(), &s[i + 1..])
        } else {
            let e = after.find(',').unwrap_or(after.len());
            (after[..e].trim().to_string(), &after[e..])
        };
        out.push((key, value));
        rest = tail.trim_start().trim_start_matches(',');
    }
    out
}

fn get<'a>(f: &'a [(String, String)], k: &str) -> &'a str {
    &f.iter().find(|(key, _)| key == k).unwrap_or_else(|| panic!("field {k} missing in {f:?}")).1
}

fn num(f: &[(String, String)], k: &str) -> f64 {
    get(f, k).parse().unwrap_or_else(|_| panic!("{k} = {:?} is not a number in {f:?}", get(f, k)))
}

struct Run {
    stdout: String,
    results: Vec<Vec<(String, String)>>,
    csv: String,
    /// The JSON's "compare" objects (--compare), one per line.
    compare: Vec<String>,
}

fn run(driver: &str, extra: &[&str]) -> Run {
    run_in(driver, driver, extra)
}

/// `run` with its files in out_dir(`tag`) (tests running at the same time use their own).
fn run_in(tag: &str, driver: &str, extra: &[&str]) -> Run {
    let dir = out_dir(tag);
    let json = dir.join(format!("{driver}.json"));
    let csv = dir.join(format!("{driver}.csv"));
    let svg = dir.join(format!("{driver}.svg"));
    let mut cmd = Command::new(bench_exe());
    cmd.args(["--driver", driver, "--scene", "bunny", "--repeat", "2", "--joiners", "2"])
        .arg("--json")
        .arg(&json)
        .arg("--csv")
        .arg(&csv)
        .arg("--svg")
        .arg(&svg)
        .args(extra)
        .env("NODEVICE_SELECT", "1");
    let out = cmd.output().expect("run arbor-bench");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "arbor-bench --driver {driver} failed ({}):\n{stdout}\n{stderr}", out.status);
    assert!(stderr.contains("[1/"), "no progress indicator on stderr:\n{stderr}");
    let text = std::fs::read_to_string(&json).unwrap();
    let results: Vec<Vec<(String, String)>> = text
        .lines()
        .skip_while(|l| !l.contains("\"results\""))
        .skip(1)
        .take_while(|l| l.trim_start().starts_with('{'))
        .map(fields)
        .collect();
    for k in ["\"tool\": \"arbor-bench\"", "\"command\"", "\"drivers\"", "\"scenes\"", "\"results\""] {
        assert!(text.contains(k), "{k} missing from the JSON:\n{text}");
    }
    let svg_text = std::fs::read_to_string(&svg).unwrap();
    assert!(svg_text.starts_with("<svg") && svg_text.trim_end().ends_with("</svg>") && svg_text.contains("<rect"), "{svg_text}");
    let compare = text
        .lines()
        .skip_while(|l| !l.contains("\"compare\""))
        .skip(1)
        .take_while(|l| l.trim_start().starts_with('{'))
        .map(|l| l.trim().trim_end_matches(',').to_string())
        .collect();
    Run { stdout, results, csv: std::fs::read_to_string(&csv).unwrap(), compare }
}

fn check_common(r: &Run, driver: &str) {
    let header = r.stdout.lines().next().expect("a table");
    for c in TABLE_COLUMNS {
        assert!(header.contains(c), "table column {c:?} missing:\n{}", r.stdout);
    }
    let csv_header = r.csv.lines().next().unwrap();
    assert_eq!(csv_header, FIELDS.join(","));
    assert_eq!(r.csv.lines().count(), 1 + WORKLOADS.len());
    assert_eq!(r.results.len(), WORKLOADS.len(), "one result per workload:\n{}", r.stdout);
    for (res, w) in r.results.iter().zip(WORKLOADS) {
        let keys: Vec<&str> = res.iter().map(|(k, _)| k.as_str()).collect();
        assert_eq!(keys, FIELDS, "JSON fields");
        assert_eq!(get(res, "driver"), driver);
        assert_eq!(get(res, "workload"), w);
        assert_eq!(get(res, "scene"), "bunny");
        assert!(num(res, "primitives") > 1000.0);
        let line = r.stdout.lines().find(|l| l.starts_with(driver) && l.split_whitespace().nth(3) == Some(w)).unwrap_or_else(|| {
            panic!("no table line for {driver} {w}:\n{}", r.stdout);
        });
        if get(res, "status") != "ok" {
            assert_eq!(get(res, "status"), "not supported", "{res:?}");
            assert!(line.contains("not supported"), "{line}");
            continue;
        }
        for k in ["median_ms", "min_ms", "max_ms", "wall_median_ms", "mprims_per_s"] {
            assert!(num(res, k) > 0.0, "{k} must be > 0: {res:?}");
        }
        assert!(num(res, "min_ms") <= num(res, "median_ms") && num(res, "median_ms") <= num(res, "max_ms"), "{res:?}");
        assert_eq!(num(res, "repeat"), 2.0);
        assert!(num(res, "as_size") > 0.0, "{res:?}");
        if w != "compact" {
            assert!(num(res, "scratch_size") > 0.0, "{res:?}");
        }
        if w != "update" {
            let c = num(res, "compacted_size");
            assert!(c > 0.0 && c <= num(res, "as_size"), "compacted {c} vs size: {res:?}");
        }
        assert!(["timestamp", "fence", "host"].contains(&get(res, "timing")), "{res:?}");
    }
}

#[test]
fn harness_against_arbor_reports_every_column_with_sane_values() {
    let dir = out_dir("arbor");
    let png = dir.join("bunny.png");
    let r = run("arbor", &["--render", png.to_str().unwrap(), "--render-size", "64x48"]);
    check_common(&r, "arbor");
    for res in &r.results {
        assert_eq!(get(res, "status"), "ok", "Arbor supports every workload: {res:?}");
        if ["fast-trace", "fast-build"].contains(&get(res, "workload")) {
            let sah = num(res, "sah_cost");
            assert!(sah > 1.0 && sah < 1000.0, "SAH {sah}");
            assert!(num(res, "node_count") > 0.0 && num(res, "leaf_count") > 0.0, "{res:?}");
        }
    }
    let host = r.results.iter().find(|f| get(f, "workload") == "host-deferred").unwrap();
    assert_eq!(get(host, "timing"), "host");
    // The PNG: signature, IHDR of the asked size, ends with IEND.
    let p = std::fs::read(&png).unwrap();
    assert_eq!(&p[..8], b"\x89PNG\r\n\x1a\n");
    assert_eq!(&p[12..16], b"IHDR");
    assert_eq!(u32::from_be_bytes(p[16..20].try_into().unwrap()), 64);
    assert_eq!(u32::from_be_bytes(p[20..24].try_into().unwrap()), 48);
    assert_eq!(&p[p.len() - 8..p.len() - 4], b"IEND");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn harness_against_lavapipe_when_installed() {
    let manifest = ["/usr/share/vulkan/icd.d/lvp_icd.json", "/usr/share/vulkan/icd.d/lvp_icd.x86_64.json"]
        .into_iter()
        .find(|p| std::path::Path::new(p).exists());
    let Some(manifest) = manifest else {
        eprintln!("SKIPPED: lavapipe is not installed (apt-get install -y -t bookworm-backports mesa-vulkan-drivers)");
        return;
    };
    // Debian 12's own Mesa (22.3) has no VK_KHR_acceleration_structure: then every row must say so.
    let r = run("lavapipe", &[]);
    check_common(&r, "lavapipe");
    let supported: Vec<&str> = r.results.iter().filter(|f| get(f, "status") == "ok").map(|f| get(f, "workload")).collect();
    if supported.is_empty() {
        eprintln!("NOTE: {manifest}: this lavapipe has no VK_KHR_acceleration_structure (Mesa 25 from bookworm-backports has)");
        assert!(r.results.iter().all(|f| get(f, "reason").contains("VK_KHR_acceleration_structure")), "{:?}", r.results);
        return;
    }
    for w in ["fast-trace", "fast-build", "update", "compact"] {
        assert!(supported.contains(&w), "lavapipe should run {w}: {:?}", r.results);
    }
    for w in ["host", "host-deferred", "indirect"] {
        let f = r.results.iter().find(|f| get(f, "workload") == w).unwrap();
        assert_eq!(get(f, "status"), "not supported", "lavapipe has no {w} builds: {f:?}");
    }
    assert!(r.stdout.contains("not supported"));
}

/// `--efficiency` on the library rows: the note carries the parallel efficiency against as many
/// concurrent 1-thread builds as the pool has threads, with their timings.
#[test]
fn harness_efficiency_against_concurrent_single_thread_builds() {
    let r = run_in("efficiency", "arbor", &["--workloads", "lib-fast-build", "--threads", "2", "--efficiency", "--no-metrics"]);
    assert_eq!(r.results.len(), 1, "{}", r.stdout);
    let res = &r.results[0];
    assert_eq!(get(res, "status"), "ok", "{res:?}");
    let note = get(res, "note");
    let pct: f64 = note
        .split("efficiency ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no efficiency in the note: {note}"));
    assert!(pct > 0.0 && pct < 1000.0, "efficiency {pct} %: {note}");
    assert!(note.contains("against 2 concurrent 1-thread builds"), "{note}");
    let base: f64 = note.split("median of their medians ").nth(1).and_then(|s| s.split(' ').next()).and_then(|v| v.parse().ok()).expect("baseline median");
    assert!(base > 0.0, "{note}");
    let _ = std::fs::remove_dir_all(out_dir("efficiency"));
}

const TRACE_RAYS: &str = "16384";

/// The trace workloads on Arbor: one row each, with the rays asked for, a positive rate in the
/// table and the JSON, and hits (the bunny fills a good part of the primary camera's view).
#[test]
fn harness_trace_workloads_on_arbor_report_a_positive_rate() {
    let r = run_in("trace", "arbor", &["--workloads", "trace-primary,trace-random", "--rays", TRACE_RAYS, "--threads", "2"]);
    assert!(r.stdout.lines().next().unwrap().contains("Mray/s"), "{}", r.stdout);
    assert_eq!(r.results.len(), 2, "{}", r.stdout);
    for (res, w) in r.results.iter().zip(["trace-primary", "trace-random"]) {
        assert_eq!(get(res, "workload"), w);
        assert_eq!(get(res, "status"), "ok", "{res:?}");
        assert_eq!(get(res, "rays"), TRACE_RAYS, "{res:?}");
        assert!(num(res, "mrays_per_s") > 0.0 && num(res, "median_ms") > 0.0, "{res:?}");
        assert_eq!(get(res, "mprims_per_s"), "null", "a trace row has no build rate: {res:?}");
        let pct: f64 = get(res, "note").split("rays, ").nth(1).and_then(|s| s.split('%').next()).and_then(|v| v.parse().ok()).expect("hit rate");
        assert!(pct > 5.0 && pct < 100.0, "hit rate {pct} %: {res:?}");
        let line = r.stdout.lines().find(|l| l.split_whitespace().nth(3) == Some(w)).expect("table line");
        let rate: f64 = line.split_whitespace().last().unwrap().parse().unwrap_or_else(|_| panic!("no Mray/s in {line}"));
        assert!(rate > 0.0, "{line}");
    }
    let _ = std::fs::remove_dir_all(out_dir("trace"));
}

/// `--compare lavapipe`: the same rays on Arbor and on lavapipe agree hit by hit (exit status 0,
/// every category 0 in the JSON), on the bunny and on a TLAS of 200 instances (instance indices
/// and custom indices); skipped when lavapipe or its ray queries are missing.
#[test]
fn harness_compare_with_lavapipe_finds_no_mismatch() {
    if !std::path::Path::new("/usr/share/vulkan/icd.d/lvp_icd.json").exists() {
        eprintln!("SKIPPED: lavapipe is not installed (apt-get install -y -t bookworm-backports mesa-vulkan-drivers)");
        return;
    }
    let args = ["--compare", "lavapipe", "--scene", "instances", "--instances", "200", "--rays", TRACE_RAYS, "--repeat", "1", "--warmup", "0", "--threads", "2"];
    let r = run_in("compare", "arbor", &args);
    let lvp: Vec<_> = r.results.iter().filter(|f| get(f, "driver") == "lavapipe").collect();
    assert_eq!(lvp.len(), 4, "{}", r.stdout);
    if lvp.iter().any(|f| get(f, "status") == "not supported") {
        eprintln!("SKIPPED: this lavapipe has no VK_KHR_ray_query (Mesa 25 from bookworm-backports has): {:?}", lvp);
        return;
    }
    assert_eq!(r.compare.len(), 4, "one comparison per scene and trace workload:\n{}", r.stdout);
    for c in &r.compare {
        let f = fields_of_compare(c);
        assert_eq!(get(&f, "other"), "lavapipe");
        assert_eq!(get(&f, "rays"), TRACE_RAYS);
        assert!(num(&f, "hits_arbor") > 0.0 && num(&f, "hits_arbor") == num(&f, "hits_other"), "{c}");
        for k in ["mismatches", "hit_miss", "primitive", "instance", "geometry", "t", "barycentrics"] {
            assert_eq!(num(&f, k), 0.0, "{k}: {c}\n{}", r.stdout);
        }
    }
    assert!(r.stdout.contains("compare arbor vs lavapipe on bunny trace-primary"), "{}", r.stdout);
    let inst = r.compare.iter().find(|c| c.contains("\"scene\": \"instances\"")).expect("instances compared");
    assert!(num(&fields_of_compare(inst), "hits_arbor") > 100.0, "{inst}");
    let _ = std::fs::remove_dir_all(out_dir("compare"));
}

/// The flat fields of a comparison object (before its nested "first" list).
fn fields_of_compare(obj: &str) -> Vec<(String, String)> {
    let flat = obj.split(", \"first\"").next().unwrap();
    fields(&format!("{flat}}}"))
}

/// bench/shaders/trace.spv is what glslang makes of trace.comp today (when the glslang recorded
/// in bench/shaders/README.md is installed; another version may emit other, equally valid words).
#[test]
fn trace_shader_spirv_matches_its_source() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("bench/shaders");
    let Ok(v) = Command::new("glslangValidator").arg("--version").output() else {
        eprintln!("SKIPPED: glslangValidator is not installed");
        return;
    };
    let version = String::from_utf8_lossy(&v.stdout).lines().next().unwrap_or("").trim().to_string();
    let out = out_dir("spirv").join("trace.spv");
    let r = Command::new("glslangValidator").args(["-V", "--target-env", "vulkan1.2", "-o"]).arg(&out).arg(dir.join("trace.comp")).output().unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stdout));
    let fresh = std::fs::read(&out).unwrap();
    let committed = std::fs::read(dir.join("trace.spv")).unwrap();
    let recorded = std::fs::read_to_string(dir.join("README.md")).unwrap();
    if fresh != committed {
        assert!(
            !recorded.contains(&format!("glslang: {version}")),
            "bench/shaders/trace.spv is stale: regenerate it (bench/shaders/README.md)"
        );
        eprintln!("SKIPPED: {version} differs from the glslang recorded in bench/shaders/README.md");
    }
    assert_eq!(u32::from_le_bytes(committed[..4].try_into().unwrap()), 0x0723_0203, "SPIR-V magic");
    let _ = std::fs::remove_dir_all(out_dir("spirv"));
}

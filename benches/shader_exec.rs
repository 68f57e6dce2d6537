//! Invocations per second of the shader library's lane interpreter on an ALU-heavy loop with
//! divergent trip counts (tests/shaders/alu_loop.comp, compiled here by glslang and run as
//! glslang emits it and after `spirv-opt -O`), on 1 thread and on all threads.
//!
//!   cargo bench --bench shader_exec
//!   ARBOR_BENCH_SECS=N   measurement time per benchmark (default 3)
//!
//! Needs glslangValidator and spirv-opt (Debian: glslang-tools, spirv-tools).

use arbor::shader::{dispatch, HostMemory, Module, Pipeline, Watchdog};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use std::path::PathBuf;
use std::process::Command;
use std::time::Duration;

const GROUPS: u32 = 256;
const LOCAL: u32 = 64;

fn spirv(optimise: bool) -> Vec<u32> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let dir = std::env::temp_dir().join(format!("arbor-shader-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let spv = dir.join("alu_loop.spv");
    let status = Command::new("glslangValidator")
        .args(["-V", "--target-env", "vulkan1.2", "-o"])
        .arg(&spv)
        .arg(root.join("tests/shaders/alu_loop.comp"))
        .output()
        .expect("glslangValidator (Debian package glslang-tools)");
    assert!(status.status.success());
    let path = if optimise {
        let opt = dir.join("alu_loop.opt.spv");
        let s = Command::new("spirv-opt").arg("-O").arg(&spv).arg("-o").arg(&opt).status().expect("spirv-opt (spirv-tools)");
        assert!(s.success());
        opt
    } else {
        spv
    };
    std::fs::read(path).unwrap().chunks(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

fn bench(c: &mut Criterion) {
    let secs = std::env::var("ARBOR_BENCH_SECS").ok().and_then(|s| s.parse().ok()).unwrap_or(3);
    let mut g = c.benchmark_group("shader_alu_loop");
    g.measurement_time(Duration::from_secs(secs)).sample_size(10);
    g.throughput(Throughput::Elements((GROUPS * LOCAL) as u64));
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    for (name, optimise) in [("glslang", false), ("spirv-opt", true)] {
        let module = Module::parse(&spirv(optimise)).unwrap();
        let pipeline = Pipeline::compute(&module, "main", &[]).unwrap();
        let mut mem = HostMemory::new();
        let out = mem.add_buffer(&vec![0; (GROUPS * LOCAL * 4) as usize]);
        mem.bind(0, 0, out);
        let run = || assert!(dispatch(&pipeline, &mem, &[], [GROUPS, 1, 1], [0; 3], &Watchdog::default()).is_clean());
        g.bench_function(format!("{name}/1-thread"), |b| b.iter(|| one.install(run)));
        g.bench_function(format!("{name}/all-threads"), |b| b.iter(run));
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

//! Library tests: GLSL shaders from tests/shaders compiled at test time by glslang (and each
//! also through `spirv-opt -O`), run by the lane executor over `HostMemory`, and checked
//! against a CPU reference computed here — never against Arbor's own output.
use std::path::PathBuf;
use std::process::Command;

use super::*;

/// The SPIR-V of tests/shaders/`name`: [glslang's, spirv-opt -O's].
fn compile(name: &str) -> Vec<(String, Vec<u32>)> {
    compile_with(name, &[])
}

fn compile_with(name: &str, defines: &[&str]) -> Vec<(String, Vec<u32>)> {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/shaders").join(name);
    let dir = std::env::temp_dir().join(format!("arbor-shader-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let tag: String = defines.join("_").chars().filter(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
    let spv = dir.join(format!("{name}{tag}.spv"));
    let opt = dir.join(format!("{name}{tag}.opt.spv"));
    let mut cmd = Command::new("glslangValidator");
    cmd.args(["-V", "--target-env", "vulkan1.2"]);
    for d in defines {
        cmd.arg(format!("-D{d}"));
    }
    let out = cmd.arg("-o").arg(&spv).arg(&src).output().unwrap_or_else(|e| {
        panic!("glslangValidator not found ({e}): install the Debian package glslang-tools (scripts/deps.sh does)")
    });
    assert!(out.status.success(), "glslang failed on {name}: {}", String::from_utf8_lossy(&out.stdout));
    let out = Command::new("spirv-opt").arg("-O").arg(&spv).arg("-o").arg(&opt).output().unwrap_or_else(|e| {
        panic!("spirv-opt not found ({e}): install the Debian package spirv-tools (scripts/deps.sh does)")
    });
    assert!(out.status.success(), "spirv-opt failed on {name}: {}", String::from_utf8_lossy(&out.stderr));
    [("glslang", spv), ("spirv-opt -O", opt)]
        .into_iter()
        .map(|(what, p)| {
            let bytes = std::fs::read(&p).unwrap();
            let words = bytes.chunks(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            (format!("{name} ({what})"), words)
        })
        .collect()
}

fn pipeline(words: &[u32], spec: &[(u32, Vec<u8>)]) -> Pipeline {
    let module = Module::parse(words).unwrap_or_else(|e| panic!("parse: {e}"));
    Pipeline::compute(&module, "main", spec).unwrap_or_else(|e| panic!("pipeline: {e}"))
}

/// Runs `words` with `buffers` bound at set 0, bindings 0.. and returns their final contents.
fn run(words: &[u32], buffers: &[Vec<u8>], push: &[u8], groups: [u32; 3]) -> Vec<Vec<u8>> {
    run_spec(words, &[], buffers, push, groups)
}

fn run_spec(words: &[u32], spec: &[(u32, Vec<u8>)], buffers: &[Vec<u8>], push: &[u8], groups: [u32; 3]) -> Vec<Vec<u8>> {
    let p = pipeline(words, spec);
    let mut mem = HostMemory::new();
    for (i, b) in buffers.iter().enumerate() {
        let idx = mem.add_buffer(b);
        mem.bind(0, i as u32, idx);
    }
    let report = dispatch(&p, &mem, push, groups, [0; 3], &Watchdog::default());
    assert!(report.is_clean(), "dispatch report: {report:?}");
    (0..buffers.len()).map(|i| mem.bytes(i)).collect()
}

fn u32s(b: &[u8]) -> Vec<u32> {
    b.chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect()
}

fn f32s(b: &[u8]) -> Vec<f32> {
    u32s(b).into_iter().map(f32::from_bits).collect()
}

fn bytes_u32(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Deterministic test inputs.
fn inputs(n: usize, seed: u32) -> Vec<u32> {
    let mut s = seed.wrapping_mul(2654435761).max(1);
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            s
        })
        .collect()
}

#[test]
fn arith_matches_cpu_reference() {
    let n = 256;
    let a: Vec<u32> = inputs(n, 1).into_iter().map(|x| x % 100_000).collect();
    for (what, words) in compile("arith.comp") {
        let out = run(&words, &[bytes_u32(&a), vec![0; n * 4], vec![0; n * 4]], &[], [4, 1, 1]);
        let (u, g) = (u32s(&out[1]), f32s(&out[2]));
        for i in 0..n {
            let x = a[i];
            let want = x.wrapping_mul(3).wrapping_add(x >> 2).wrapping_sub(x ^ 0x55).wrapping_add(i as u32);
            assert_eq!(u[i], want, "{what}: u[{i}]");
            let wf = x as f32 * 0.5 + 1.25 / (i as f32 + 1.0);
            assert_eq!(g[i], wf, "{what}: g[{i}]");
        }
    }
}

fn collatz(mut x: u32) -> u32 {
    let mut steps = 0;
    while x != 1 && steps < 1000 {
        x = if x & 1 == 0 { x / 2 } else { x.wrapping_mul(3).wrapping_add(1) };
        steps += 1;
    }
    steps
}

fn weird(x: u32) -> f32 {
    let mut acc = 0.0f32;
    for k in 0..16u32 {
        if k == x % 7 {
            continue;
        }
        if k > 4 + x % 9 {
            break;
        }
        acc += k as f32 * 0.25;
    }
    acc
}

fn pick(x: u32) -> u32 {
    match x % 5 {
        0 => 10,
        1 => 20,
        3 => x.wrapping_mul(2),
        _ => x.wrapping_add(7),
    }
}

#[test]
fn control_flow_calls_and_composites() {
    let n = 96;
    let input: Vec<u32> = inputs(n, 7).into_iter().map(|x| x % 5000).collect();
    for (what, words) in compile("control.comp") {
        let out = run(&words, &[bytes_u32(&input), vec![0; n * 16]], &[], [3, 1, 1]);
        let p = u32s(&out[1]);
        for i in 0..n {
            let x = input[i];
            let arr = [x, x + 1, x + 2, x + 3];
            let s: u32 = (0..4).map(|k| arr[((k + x as i32) & 3) as usize] * (k as u32 + 1)).sum();
            assert_eq!(p[4 * i], collatz(x + 1) + s, "{what}: a[{i}]");
            assert_eq!(f32::from_bits(p[4 * i + 1]), weird(x), "{what}: b[{i}]");
            assert_eq!([p[4 * i + 2], p[4 * i + 3]], [pick(x + 1), pick(x)], "{what}: v[{i}]");
        }
    }
}

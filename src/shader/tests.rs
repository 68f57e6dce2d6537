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

fn close(got: f32, want: f32) -> bool {
    got == want || (got - want).abs() <= 1e-4 * want.abs().max(1.0) || (got.is_nan() && want.is_nan())
}

fn msb(v: u32) -> u32 {
    if v == 0 { u32::MAX } else { 31 - v.leading_zeros() }
}

/// Reference for math.comp: (exact 32-bit results, approximate ones by slot, 64-bit results).
fn math_reference(i: u32, x: f32, y: f32, u: u32) -> ([u32; 32], Vec<(usize, f32)>, [u64; 4]) {
    let s = u as i32;
    let mut o = [0u32; 32];
    let fb = f32::to_bits;
    o[0] = fb(x.abs().sqrt());
    o[1] = fb(x.floor() + y.ceil() * 2.0);
    o[2] = fb(x - x.floor());
    o[3] = fb(x.clamp(-1.0, 1.0) + x.min(y) - x.max(y));
    o[4] = fb(x.mul_add(y, 0.5));
    o[6] = fb(x.trunc() + y.round() + (x * 3.0).round_ties_even());
    let approx = vec![
        (5, x * 0.75 + y * 0.25 + if x < 0.0 { 0.0 } else { 1.0 } + if y > 0.0 { 1.0 } else if y < 0.0 { -1.0 } else { 0.0 }),
        (7, x - 1.5 * (x / 1.5).floor() + y.abs()),
        (8, (x * 0.1).exp() + (y.abs() + 1.0).ln()),
        (9, x.sin() * y.cos() + y.atan2(x) + (x.abs() + 1.0).powf(1.5)),
        (10, {
            let p = [x, y * 0.5, 1.0];
            let q = [y, 1.0, x];
            let len = |v: [f32; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            len(p) + (p[0] * q[0] + p[1] * q[1] + p[2] * q[2]) + len([p[0] - q[0], p[1] - q[1], p[2] - q[2]])
        }),
        (11, {
            let p = [x, y * 0.5, 1.0];
            let q = [y, 1.0, x];
            let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            let n = [p[0] / l, p[1] / l, p[2] / l];
            let c = [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]];
            let d = n[0] * q[0] + n[1] * q[1] + n[2] * q[2];
            let r = [q[0] - 2.0 * d * n[0], q[2] - 2.0 * d * n[2]];
            n[0] + n[1] * 2.0 + c[0] * 3.0 + c[1] + c[2] * 0.5 + r[0] + r[1]
        }),
        (12, {
            let t = ((x + 1.0) / 3.0).clamp(0.0, 1.0);
            t * t * (3.0 - 2.0 * t) + 1.0 / (y.abs() + 1.0).sqrt()
        }),
    ];
    let smsb = if s < 0 { msb(!s as u32) } else { msb(s as u32) };
    let lsb = if u == 0 { u32::MAX } else { u.trailing_zeros() };
    o[13] = lsb.wrapping_add(msb(u).wrapping_mul(100)).wrapping_add(smsb.wrapping_mul(10000));
    o[14] = u.count_ones().wrapping_add(u.reverse_bits());
    o[15] = ((u >> 3) & 0x1FF).wrapping_add((((s >> 5) << 25) >> 25) as u32);
    let mask = ((1u32 << 13) - 1) << 4;
    o[16] = (u & !mask) | ((0x1234 << 4) & mask);
    let prod = u as u64 * 0x9E37_79B9;
    o[17] = (prod >> 32) as u32 ^ prod as u32;
    let (sum, carry) = u.overflowing_add(0xF000_0000);
    o[18] = sum.wrapping_add(carry as u32);
    o[19] = (s.min(-5).wrapping_add(s.max(7)).wrapping_add(s.clamp(-100, 100)) as u32)
        .wrapping_add(u.min(77))
        .wrapping_add(u.clamp(5, 9));
    o[20] = (s.wrapping_abs().wrapping_add(s.signum()) as u32).wrapping_add(u % 7).wrapping_add(u / 13);
    o[21] = ((s >> 3) as u32) ^ (u << 5) ^ !u;
    o[22] = ((x * 100.0) as i32 as u32).wrapping_add((y.abs() * 10.0) as u32);
    o[23] = fb(s as f32 + u as f32);
    o[24] = (x < y) as u32 + (x >= y) as u32 * 2 + ((x / 0.0).is_nan() as u32) * 4 + ((y / 0.0).is_infinite() as u32) * 8;
    let big = (u as u64).wrapping_mul(0x1_0000_0001).wrapping_add(i as u64);
    let sb = s as i64 * -3;
    let d = x as f64 * y as f64 + 1.0 / 3.0;
    let w = [
        big ^ (big >> 17) ^ (big << 9),
        (sb / 7 + sb.rem_euclid(5)) as u64,
        (d + d.abs().sqrt()).to_bits(),
        ((d * 1000.0) as i64 as u64).wrapping_add((big >> 32) as u32 as u64),
    ];
    (o, approx, w)
}

#[test]
fn glsl_std450_conversions_bits_and_64bit() {
    let n = 64;
    let r = inputs(3 * n, 11);
    let mut v = Vec::new();
    for i in 0..n {
        let x = (r[3 * i] % 20000) as f32 / 1000.0 - 10.0;
        let y = (r[3 * i + 1] % 20000) as f32 / 1000.0 - 10.0;
        let z = if i % 9 == 0 { 0 } else { r[3 * i + 2] };
        v.extend([x.to_bits(), y.to_bits(), z, 0]);
    }
    for (what, words) in compile("math.comp") {
        let out = run(&words, &[bytes_u32(&v), vec![0; n * 128], vec![0; n * 32]], &[], [4, 1, 1]);
        let o = u32s(&out[1]);
        let w: Vec<u64> = out[2].chunks(8).map(|c| u64::from_le_bytes(c.try_into().unwrap())).collect();
        for i in 0..n {
            let (x, y, u) = (f32::from_bits(v[4 * i]), f32::from_bits(v[4 * i + 1]), v[4 * i + 2]);
            let (exact, approx, wide) = math_reference(i as u32, x, y, u);
            for k in (0..25).filter(|k| !approx.iter().any(|a| a.0 == *k)) {
                assert_eq!(o[32 * i + k], exact[k], "{what}: invocation {i} slot {k} (x={x}, y={y}, u={u:#x})");
            }
            for &(k, want) in &approx {
                let got = f32::from_bits(o[32 * i + k]);
                assert!(close(got, want), "{what}: invocation {i} slot {k}: {got} vs {want} (x={x}, y={y})");
            }
            assert_eq!(&w[4 * i..4 * i + 4], &wide, "{what}: 64-bit results of invocation {i}");
        }
    }
}

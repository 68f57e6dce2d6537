//! Library tests: GLSL shaders from tests/shaders compiled at test time by glslang (assembly
//! by spirv-as), each also through `spirv-opt -O`, run by the lane executor over `HostMemory`, and checked
//! against a CPU reference computed here — never against Arbor's own output.
use std::path::PathBuf;
use std::process::Command;

use super::*;

/// The SPIR-V of tests/shaders/`name`: [glslang's, spirv-opt -O's].
fn compile(name: &str) -> Vec<(String, Vec<u32>)> {
    compile_with(name, &[])
}

pub(super) fn compile_with(name: &str, defines: &[&str]) -> Vec<(String, Vec<u32>)> {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/shaders").join(name);
    let dir = std::env::temp_dir().join(format!("arbor-shader-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let tag: String = defines.join("_").chars().filter(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
    // Tests run in parallel and some compile the same shader: every call gets its own files.
    static CALLS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let call = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let spv = dir.join(format!("{name}{tag}.{call}.spv"));
    let opt = dir.join(format!("{name}{tag}.{call}.opt.spv"));
    // Hand-written assembly goes through spirv-as; GLSL through glslang.
    let out = if name.ends_with(".spvasm") {
        Command::new("spirv-as").args(["--target-env", "vulkan1.2", "-o"]).arg(&spv).arg(&src).output().unwrap_or_else(|e| {
            panic!("spirv-as not found ({e}): install the Debian package spirv-tools (scripts/deps.sh does)")
        })
    } else {
        let mut cmd = Command::new("glslangValidator");
        cmd.args(["-V", "--target-env", "vulkan1.2"]);
        for d in defines {
            cmd.arg(format!("-D{d}"));
        }
        cmd.arg("-o").arg(&spv).arg(&src).output().unwrap_or_else(|e| {
            panic!("glslangValidator not found ({e}): install the Debian package glslang-tools (scripts/deps.sh does)")
        })
    };
    let log = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "compiling {name} failed: {log}");
    let out = Command::new("spirv-opt").arg("-O").arg(&spv).arg("-o").arg(&opt).output().unwrap_or_else(|e| {
        panic!("spirv-opt not found ({e}): install the Debian package spirv-tools (scripts/deps.sh does)")
    });
    assert!(out.status.success(), "spirv-opt failed on {name}: {}", String::from_utf8_lossy(&out.stderr));
    [("glslang", spv), ("spirv-opt -O", opt)]
        .into_iter()
        .map(|(what, p)| {
            let bytes = std::fs::read(&p).unwrap();
            let _ = std::fs::remove_file(&p);
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

#[test]
fn shared_memory_barriers_and_atomics() {
    let (groups, n) = (3usize, 192usize);
    let v: Vec<u32> = inputs(n, 3);
    let global_init = bytes_u32(&[0, 0, u32::MAX, 0, 0, i32::MAX as u32]);
    for (what, words) in compile("shared.comp") {
        let out = run(&words, &[bytes_u32(&v), vec![0; n * 4], vec![0; groups * 12], global_init.clone()], &[], [3, 1, 1]);
        let (rev, sums, glob) = (u32s(&out[1]), u32s(&out[2]), u32s(&out[3]));
        for g in 0..n {
            assert_eq!(rev[g], v[g / 64 * 64 + 63 - g % 64], "{what}: reversed[{g}]");
        }
        for w in 0..groups {
            let part = &v[w * 64..w * 64 + 64];
            let sum = part.iter().fold(0u32, |a, &x| a.wrapping_add(x));
            let low = part.iter().fold(0u32, |a, &x| a.wrapping_add(x & 0xFF));
            let bits = part.iter().fold(0u32, |a, &x| a | 1 << (x % 32));
            assert_eq!(&sums[3 * w..3 * w + 3], &[sum, low, bits], "{what}: workgroup {w}");
        }
        assert_eq!(glob[0], v.iter().fold(0u32, |a, &x| a.wrapping_add(x & 0xFFF)), "{what}: total");
        assert_eq!(glob[1], *v.iter().max().unwrap(), "{what}: max");
        assert_eq!(glob[2], *v.iter().min().unwrap(), "{what}: min");
        assert_eq!(glob[3], v.iter().fold(0, |a, &x| a | (x & 0xF0F0)), "{what}: or");
        // Racy by design: some invocation won the compare-exchange.
        assert!((1..=n as u32).contains(&glob[4]), "{what}: compare-exchange winner {}", glob[4]);
        assert_eq!(glob[5] as i32, v.iter().map(|&x| x as i32).min().unwrap(), "{what}: signed min");
    }
}

fn push_ubo_reference(i: u32, k: u32, flag: bool, wgx: u32, push: (u32, f32), ubo: &[u32]) -> (u32, f32) {
    let f = |w: usize| f32::from_bits(ubo[w]);
    let t = ubo[4 + 4 * (i as usize % 4)];
    let (c0, c1) = ((f(20), f(21)), (f(24), f(25)));
    let mv = (c0.0 * i as f32 + c1.0, c0.1 * i as f32 + c1.1);
    let fv = f(1) * i as f32 + push.1 + mv.0 + mv.1 * 0.5;
    let u = i * push.0 + t * (k * 2 + 1) + if flag { 1000 } else { 0 } + wgx * 100_000;
    (u, fv)
}

#[test]
fn push_constants_uniform_buffer_and_specialization() {
    let count = 50u32;
    let mut ubo = vec![0u32; 28];
    for (k, x) in ubo.iter_mut().enumerate() {
        *x = match k {
            0..=3 => (k as f32 * 0.75 + 0.5).to_bits(),
            20..=27 => (k as f32 * 0.125 - 2.0).to_bits(),
            _ => 3 * k as u32 + 1,
        };
    }
    let push: Vec<u8> = [5u32, 1.5f32.to_bits(), count].iter().flat_map(|x| x.to_le_bytes()).collect();
    // (specialization data, then the values it gives the shader).
    type Case = (Vec<(u32, Vec<u8>)>, u32, bool, u32);
    let cases: [Case; 2] = [
        (vec![], 3, false, 1),
        (vec![(0, 5u32.to_le_bytes().to_vec()), (1, 1u32.to_le_bytes().to_vec()), (2, 16u32.to_le_bytes().to_vec())], 5, true, 16),
    ];
    for (what, words) in compile("push_ubo_spec.comp") {
        for (spec, k, flag, wgx) in &cases {
            let p = pipeline(&words, spec);
            assert_eq!(p.local_size, [*wgx, 1, 1], "{what}");
            assert_eq!(p.push_constant_size, 12, "{what}");
            let groups = count.div_ceil(*wgx) + 1; // one extra group exercises the early return
            let out = run_spec(&words, spec, &[bytes_u32(&ubo), vec![0; 8 * 64]], &push, [groups, 1, 1]);
            let o = u32s(&out[1]);
            for i in 0..count {
                let (u, f) = push_ubo_reference(i, *k, *flag, *wgx, (5, 1.5), &ubo);
                assert_eq!(o[2 * i as usize], u, "{what} spec {spec:?}: o[{i}]");
                assert!(close(f32::from_bits(o[2 * i as usize + 1]), f), "{what} spec {spec:?}: f[{i}]");
            }
            assert!(o[2 * count as usize..].iter().all(|&x| x == 0), "{what}: writes past count");
        }
    }
}

/// Memory for bda.comp: (memory, vals, table, out_words, raw) buffer indices.
fn bda_memory(n: u32) -> (HostMemory, Vec<f32>, [usize; 4]) {
    let mut mem = HostMemory::new();
    let vals: Vec<f32> = (0..2 * n).map(|k| k as f32 * 0.5 - 3.0).collect();
    let mut vb = bytes_u32(&[2.5f32.to_bits(), 0]);
    vb.extend(vals.iter().flat_map(|x| x.to_le_bytes()));
    let vi = mem.add_buffer(&vb);
    let mut tb = mem.device_address(vi).to_le_bytes().to_vec();
    tb.extend(bytes_u32(&[n, 0]));
    let ti = mem.add_buffer(&tb);
    let oi = mem.add_buffer(&vec![0; 64 * 4]);
    let ri = mem.add_buffer(&vec![0; 64 * 8]);
    (mem, vals, [vi, ti, oi, ri])
}

#[test]
fn buffer_device_address() {
    let n = 40u32;
    for (what, words) in compile("bda.comp") {
        let p = pipeline(&words, &[]);
        let (mem, vals, [vi, ti, oi, ri]) = bda_memory(n);
        let push: Vec<u8> = [mem.device_address(ti), mem.device_address(oi), mem.device_address(ri)]
            .iter()
            .flat_map(|a| a.to_le_bytes())
            .collect();
        let report = dispatch(&p, &mem, &push, [2, 1, 1], [0; 3], &Watchdog::default());
        assert!(report.is_clean(), "{what}: {report:?}");
        let (o, raw) = (u32s(&mem.bytes(oi)), u32s(&mem.bytes(ri)));
        let va = mem.device_address(vi);
        for i in 0..64usize {
            let live = (i as u32) < n;
            let want = if live { (vals[2 * i] * 2.5 + vals[2 * i + 1]).to_bits() } else { 0 };
            assert_eq!(raw[2 * i], want, "{what}: raw[{i}]");
            assert_eq!(raw[2 * i + 1], if live { 7 * i as u32 } else { 0 }, "{what}: raw[{i}]+1");
            assert_eq!(o[i], if live { (va & 0xFFFF) as u32 + i as u32 } else { 0 }, "{what}: out[{i}]");
        }
    }
}

fn subgroup_reference(x: &[u32]) -> Vec<[u32; 16]> {
    let lanes = LANES;
    let mut out = vec![[0u32; 16]; x.len()];
    for s in (0..x.len()).step_by(lanes) {
        let g = &x[s..s + lanes];
        let ballot = (0..lanes).filter(|&l| g[l] & 1 == 1).fold(0u32, |a, l| a | 1 << l);
        let sum = g.iter().fold(0u32, |a, &v| a.wrapping_add(v));
        let then: Vec<usize> = (0..lanes).filter(|&l| g[l].is_multiple_of(3)).collect();
        let then_ballot = then.iter().fold(0u32, |a, &l| a | 1 << l);
        let then_sum = then.iter().fold(0u32, |a, &l| a.wrapping_add(g[l]));
        let others: Vec<usize> = (0..lanes).filter(|&l| !g[l].is_multiple_of(3)).collect();
        let prod = others.iter().fold(1u32, |a, &l| a.wrapping_mul(g[l] % 4 + 1));
        let fsum = g.iter().fold(0f32, |a, &v| a + v as f32 * 0.5);
        for l in 0..lanes {
            let below = (1u32 << l) - 1;
            let o = &mut out[s + l];
            o[0] = lanes as u32 * 1000 + l as u32 * 10 + (l == 0) as u32;
            o[1] = g.iter().all(|&v| v > 5) as u32 + 2 * g.iter().any(|&v| v > 90) as u32
                + 4 * g.iter().all(|&v| v / 1000 == g[0] / 1000) as u32;
            o[2] = g[3].wrapping_add(g[0] * 2);
            o[3] = ballot;
            o[4] = ballot.count_ones() + 100 * (ballot & ((2 << l) - 1)).count_ones() + 10000 * (ballot & below).count_ones();
            let (lsb, msb) = if ballot == 0 { (u32::MAX, u32::MAX) } else { (ballot.trailing_zeros(), 31 - ballot.leading_zeros()) };
            o[5] = lsb.wrapping_add(msb.wrapping_mul(100)).wrapping_add(if ballot & 4 != 0 { 10000 } else { 0 });
            o[6] = sum;
            o[7] = g.iter().min().unwrap() + g.iter().max().unwrap() * 3;
            o[8] = g.iter().fold(!0u32, |a, &v| a & (v | 0x100)) ^ g.iter().fold(0, |a, &v| a | v) ^ g.iter().fold(0, |a, &v| a ^ v);
            o[9] = g[..=l].iter().fold(0u32, |a, &v| a.wrapping_add(v));
            o[10] = g[..l].iter().fold(0u32, |a, &v| a.wrapping_add(v));
            o[11] = fsum.to_bits();
            if g[l].is_multiple_of(3) {
                o[12] = then_sum + (then[0] == l) as u32;
                o[13] = then_ballot;
            } else {
                o[12] = prod;
                o[13] = others.iter().filter(|&&k| k < l).count() as u32;
            }
            o[14] = (g.iter().map(|&v| v as i32 - 50).min().unwrap()) as u32;
            o[15] = (1 << l) | (below << 8);
        }
    }
    out
}

#[test]
fn subgroup_basic_vote_ballot_arithmetic() {
    let n = 64usize;
    let x: Vec<u32> = inputs(n, 5)
        .into_iter()
        .enumerate()
        .map(|(g, r)| match g / LANES {
            1 => 2000 + r % 100,
            2 => 10 + r % 80,
            _ => r % 100,
        })
        .collect();
    let want = subgroup_reference(&x);
    for (what, words) in compile("subgroup.comp") {
        let out = run(&words, &[bytes_u32(&x), vec![0; n * 64]], &[], [2, 1, 1]);
        let o = u32s(&out[1]);
        for g in 0..n {
            assert_eq!(&o[16 * g..16 * g + 16], &want[g], "{what}: invocation {g} (x = {:?})", &x[g / LANES * LANES..][..LANES]);
        }
    }
}

/// The word at `offset` must be the instruction the error names.
fn opcode_at(words: &[u32], offset: usize) -> u32 {
    words[offset] & 0xFFFF
}

#[test]
fn unsupported_modules_fail_at_parse_naming_what_and_where() {
    for (what, words) in compile("int8.comp") {
        match Module::parse(&words) {
            Err(ShaderError::UnsupportedCapability { capability, offset }) => {
                assert!(capability.contains("Int8"), "{what}: {capability}");
                assert_eq!(opcode_at(&words, offset), spirv::Op::Capability as u32, "{what}");
            }
            other => panic!("{what}: expected an unsupported capability, got {other:?}"),
        }
    }
    for (what, words) in compile("image.comp") {
        match Module::parse(&words) {
            Err(ShaderError::UnsupportedOpcode { opcode, offset }) => {
                assert_eq!(opcode, "OpTypeSampledImage", "{what}");
                assert_eq!(opcode_at(&words, offset), spirv::Op::TypeSampledImage as u32, "{what}");
            }
            other => panic!("{what}: expected an unsupported opcode, got {other:?}"),
        }
    }
    let garbage = [0x0723_0203u32, 0x0001_0500, 0, 10, 0, 0x0005_0000];
    assert!(matches!(Module::parse(&garbage), Err(ShaderError::Malformed { .. })));
    assert!(matches!(Module::parse(&[1, 2, 3]), Err(ShaderError::Malformed { offset: 0, .. })));
    let words = &compile("arith.comp")[0].1;
    let module = Module::parse(words).unwrap();
    assert!(matches!(Pipeline::compute(&module, "nope", &[]), Err(ShaderError::NoEntryPoint { .. })));
}

#[test]
fn out_of_bounds_and_unbound_accesses_are_contained_and_reported() {
    for (what, words) in compile("oob.comp") {
        let p = pipeline(&words, &[]);
        let mut mem = HostMemory::new();
        let input = mem.add_buffer(&bytes_u32(&(0..24).collect::<Vec<u32>>()));
        let out = mem.add_buffer(&[0; 24 * 4]);
        mem.bind(0, 0, input);
        mem.bind(0, 1, out);
        // Invocations 0..16 at shift 10: indices 10..26, of which 24 and 25 are past both buffers.
        let push = 10u32.to_le_bytes();
        let report = dispatch(&p, &mem, &push, [1, 1, 1], [0; 3], &Watchdog::default());
        assert_eq!(report.fault_count, 4, "{what}: {report:?}");
        let f = report.faults[0];
        assert_eq!((f.kind, f.space, f.at, f.write), (FaultKind::OutOfBounds, FaultSpace::Binding { set: 0, binding: 0 }, 96, false), "{what}");
        assert_eq!(f.invocation, 14, "{what}");
        assert!(report.faults.iter().any(|f| f.write && f.space == FaultSpace::Binding { set: 0, binding: 1 }), "{what}");
        let o = u32s(&mem.bytes(out));
        for (i, &x) in o.iter().enumerate() {
            assert_eq!(x, if i >= 10 { i as u32 + 1 } else { 0 }, "{what}: o[{i}]");
        }
        // Nothing bound at binding 1: every store is an Unbound fault, loads still work.
        let mut mem = HostMemory::new();
        let input = mem.add_buffer(&bytes_u32(&[0; 16]));
        mem.bind(0, 0, input);
        let report = dispatch(&p, &mem, &0u32.to_le_bytes(), [1, 1, 1], [0; 3], &Watchdog::default());
        assert_eq!(report.fault_count, 16, "{what}");
        assert_eq!(report.faults[0].kind, FaultKind::Unbound, "{what}");
    }
    for (what, words) in compile("bda.comp") {
        let p = pipeline(&words, &[]);
        let (mem, _, [_, ti, oi, _]) = bda_memory(8);
        let bad = 0xDEAD_0000u64;
        let push: Vec<u8> = [mem.device_address(ti), mem.device_address(oi), bad].iter().flat_map(|a| a.to_le_bytes()).collect();
        let report = dispatch(&p, &mem, &push, [1, 1, 1], [0; 3], &Watchdog::default());
        assert_eq!(report.fault_count, 16, "{what}: two unmapped stores for each of 8 invocations");
        assert_eq!((report.faults[0].kind, report.faults[0].at), (FaultKind::Unmapped, bad), "{what}");
        let va = mem.device_address(0) & 0xFFFF;
        let want: Vec<u32> = (0..8).map(|i| va as u32 + i).collect();
        assert_eq!(&u32s(&mem.bytes(oi))[..8], &want[..], "{what}: good stores still land");
    }
}

#[test]
fn watchdog_stops_a_shader_that_does_not_terminate() {
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;
    for (what, words) in compile("spin.comp") {
        let p = pipeline(&words, &[]);
        let mut mem = HostMemory::new();
        let b = mem.add_buffer(&[0; 8]);
        mem.bind(0, 0, b);
        let budget = Watchdog { step_budget: Some(100_000), ..Watchdog::default() };
        let report = dispatch(&p, &mem, &[], [4, 1, 1], [0; 3], &budget);
        assert_eq!(report.stopped, Some(Stop::StepBudget), "{what}");
        let deadline = Watchdog { deadline: Some(std::time::Instant::now() + std::time::Duration::from_millis(50)), ..Watchdog::default() };
        assert_eq!(dispatch(&p, &mem, &[], [2, 1, 1], [0; 3], &deadline).stopped, Some(Stop::Deadline), "{what}");
        let cancel = Watchdog { cancel: Some(Arc::new(AtomicBool::new(true))), ..Watchdog::default() };
        assert_eq!(dispatch(&p, &mem, &[], [2, 1, 1], [0; 3], &cancel).stopped, Some(Stop::Cancelled), "{what}");
        // With the magic value in place the same shader terminates.
        let mut mem = HostMemory::new();
        let b = mem.add_buffer(&bytes_u32(&[12345, 0]));
        mem.bind(0, 0, b);
        assert!(dispatch(&p, &mem, &[], [2, 1, 1], [0; 3], &budget).is_clean(), "{what}");
    }
}

#[test]
fn results_do_not_depend_on_thread_count_or_dispatch_base() {
    let n = 96;
    let input: Vec<u32> = inputs(n, 9).into_iter().map(|x| x % 5000).collect();
    let (_, words) = &compile("control.comp")[1];
    let p = pipeline(words, &[]);
    let run_on = |threads: usize, base: u32| {
        let mut mem = HostMemory::new();
        let i = mem.add_buffer(&bytes_u32(&input));
        let o = mem.add_buffer(&vec![0; n * 16]);
        mem.bind(0, 0, i);
        mem.bind(0, 1, o);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        // Two dispatches split at `base` cover the same workgroups as one.
        pool.install(|| {
            assert!(dispatch(&p, &mem, &[], [base, 1, 1], [0; 3], &Watchdog::default()).is_clean());
            assert!(dispatch(&p, &mem, &[], [3 - base, 1, 1], [base, 0, 0], &Watchdog::default()).is_clean());
        });
        mem.bytes(o)
    };
    let one = run_on(1, 0);
    assert!(one.iter().any(|&b| b != 0));
    assert_eq!(run_on(4, 0), one);
    assert_eq!(run_on(3, 1), one);
    assert_eq!(run_on(2, 2), one);
}

/// Reference for misc.comp: the eight words of invocation `li` of workgroup `wg`, the Item it
/// stores, and its flat index.
fn misc_reference(wg: [u32; 3], nwg: [u32; 3], li: u32) -> (u32, [u32; 8], [u32; 4]) {
    let flat = |li: u32| (wg[0] + nwg[0] * (wg[1] + nwg[1] * wg[2])) * 16 + li;
    let g = flat(li);
    let lid = [li % 4, (li / 4) % 2, li / 8];
    let gid = [wg[0] * 4 + lid[0], wg[1] * 2 + lid[1], wg[2] * 2 + lid[2]];
    let mut o = [0u32; 8];
    o[0] = gid[0] + 100 * gid[1] + 10000 * gid[2];
    o[1] = lid[0] + 10 * lid[1] + 100 * lid[2] + 1000 * li;
    let m = [[1.0f32, 2.0, 3.0], [0.5, li as f32, 1.0], [-1.0, 0.0, 2.0]];
    let v = [g as f32, 1.0, 2.0];
    let mv: Vec<f32> = (0..3).map(|i| m[0][i] * v[0] + m[1][i] * v[1] + m[2][i] * v[2]).collect();
    let vm: Vec<f32> = (0..3).map(|j| v[0] * m[j][0] + v[1] * m[j][1] + v[2] * m[j][2]).collect();
    let mm = |j: usize, i: usize| (0..3).map(|k| m[k][i] * m[k][j]).sum::<f32>();
    o[2] = (mv[0] + mv[1] * 2.0 + mv[2] * 3.0 + vm[0] + vm[1] * 5.0 + vm[2] * 7.0 + mm(1, 2) + mm(2, 0)).to_bits();
    let mut q = [g, g * 2, g * 3, g * 4];
    q[(li % 4) as usize] = 77;
    o[3] = q[((li + 1) % 4) as usize] + q[(li % 4) as usize] * 1000 + [3, 1, 4, 1, 5][(g % 5) as usize] * 100_000;
    let mut seed = 17u32;
    o[4] = (0..3).fold(0u32, |r, _| {
        seed = seed.wrapping_mul(1_103_515_245).wrapping_add(12345);
        r.wrapping_add(seed >> 8)
    });
    let (mut steps, mut x) = (0u32, g);
    loop {
        x = x / 2 + (x & 1);
        steps += 1;
        if !(x > 1 && steps < 50) {
            break;
        }
    }
    'outer: for i in 0..6u32 {
        for j in 0..6u32 {
            if i * j == g % 17 {
                steps += 100 * i + 10 * j;
                break 'outer;
            }
        }
    }
    o[5] = steps;
    let other = flat(15 - li);
    o[6] = other + 15 - li;
    o[7] = (if li > 7 { g } else { !g }).wrapping_add([g, 2, 3, 4][(li % 4) as usize] * 2);
    (g, o, [other, 15 - li, (other as f32 * 0.25).to_bits(), 0])
}

#[test]
fn workgroup_builtins_matrices_private_globals_and_64bit_atomics() {
    let (count, base) = ([2u32, 2, 1], [1u32, 0, 1]);
    let slots = 160usize;
    for (what, words) in compile("misc.comp") {
        let p = pipeline(&words, &[]);
        assert_eq!(p.local_size, [4, 2, 2]);
        let mut mem = HostMemory::new();
        let o = mem.add_buffer(&vec![0; slots * 32]);
        let acc = mem.add_buffer(&vec![0; 16 + slots * 16]);
        mem.bind(0, 0, o);
        mem.bind(0, 1, acc);
        let report = dispatch(&p, &mem, &[], count, base, &Watchdog::default());
        assert!(report.is_clean(), "{what}: {report:?}");
        let (out, accb) = (u32s(&mem.bytes(o)), u32s(&mem.bytes(acc)));
        let (mut sum, mut max) = (0u64, 0u64);
        for z in 0..count[2] {
            for y in 0..count[1] {
                for x in 0..count[0] {
                    let wg = [base[0] + x, base[1] + y, base[2] + z];
                    for li in 0..16 {
                        let (g, want, item) = misc_reference(wg, count, li);
                        let got = &out[8 * g as usize..8 * g as usize + 8];
                        for k in (0..8).filter(|&k| k != 2) {
                            assert_eq!(got[k], want[k], "{what}: workgroup {wg:?} invocation {li} word {k}");
                        }
                        assert!(close(f32::from_bits(got[2]), f32::from_bits(want[2])), "{what}: matrices, invocation {g}");
                        assert_eq!(&accb[4 + 4 * g as usize..4 + 4 * g as usize + 3], &item[..3], "{what}: items[{g}]");
                        sum = sum.wrapping_add((g as u64) << 32 | g as u64);
                        max = max.max((g as u64) << 32);
                    }
                }
            }
        }
        let word64 = |k: usize| accb[2 * k] as u64 | (accb[2 * k + 1] as u64) << 32;
        assert_eq!((word64(0), word64(1)), (sum, max), "{what}: 64-bit atomics");
    }
}

#[test]
fn subgroup_shuffles() {
    let n = 64usize;
    let x = inputs(n, 13);
    for (what, words) in compile("shuffle.comp") {
        let o = u32s(&run(&words, &[bytes_u32(&x), vec![0; n * 16]], &[], [2, 1, 1])[1]);
        for g in 0..n {
            let (base, l) = (g / LANES * LANES, g % LANES);
            let at = |k: usize| x[base + k];
            assert_eq!(o[4 * g], at((l + 3) % LANES), "{what}: shuffle at {g}");
            assert_eq!(o[4 * g + 1], at(l ^ 5), "{what}: shuffle xor at {g}");
            // Up/down past the subgroup's edge are undefined: only the defined lanes are checked.
            if l >= 1 {
                assert_eq!(o[4 * g + 2], at(l - 1), "{what}: shuffle up at {g}");
            }
            if l + 2 < LANES {
                assert_eq!(o[4 * g + 3], at(l + 2), "{what}: shuffle down at {g}");
            }
        }
    }
}

#[test]
fn handwritten_remainders_dynamic_vectors_copy_memory_spec_composites_switch64_ptr_access_chain() {
    for (spec, k) in [(vec![], 5u32), (vec![(0u32, 9u32.to_le_bytes().to_vec())], 9)] {
        for (what, words) in compile("handwritten.spvasm") {
            let p = pipeline(&words, &spec);
            let mut mem = HostMemory::new();
            let o = mem.add_buffer(&[0; 16 * 32]);
            let raw = mem.add_buffer(&[0; 16 * 4]);
            mem.bind(0, 0, o);
            let push = mem.device_address(raw).to_le_bytes();
            let report = dispatch(&p, &mem, &push, [2, 1, 1], [0; 3], &Watchdog::default());
            assert!(report.is_clean(), "{what}: {report:?}");
            let (out, raw) = (u32s(&mem.bytes(o)), u32s(&mem.bytes(raw)));
            for g in 0..16u32 {
                let w = &out[8 * g as usize..8 * g as usize + 6];
                let neg = -7 - g as i32;
                let x = -7.5f32 - g as f32;
                let mut v = [k, 7, 2, 3];
                v[(g % 4) as usize] = g;
                let sw = match g { 3 => 30, 5 => 50, _ => 7 };
                let want = [
                    (neg % 3) as u32,
                    neg.rem_euclid(3) as u32,
                    (x % 2.0).to_bits(),
                    (x - 2.0 * (x / 2.0).floor()).to_bits(),
                    v[((g + 1) % 4) as usize] + (k + 8) * 1000,
                    sw,
                ];
                assert_eq!(w, &want, "{what} (K = {k}): invocation {g}");
                assert_eq!(raw[g as usize], 3 * g + 1, "{what}: OpPtrAccessChain store {g}");
            }
        }
    }
}

#[test]
fn spec_constant_vector_swizzles() {
    let spec = |x: u32, y: u32, k: u32| vec![(0, x.to_le_bytes().to_vec()), (1, y.to_le_bytes().to_vec()), (2, k.to_le_bytes().to_vec())];
    for (what, words) in compile("spec_swizzle.comp") {
        for (sp, size, k) in [(vec![], [1, 1], 3u32), (spec(4, 2, 10), [4, 2], 10)] {
            let out = run_spec(&words, &sp, &[vec![0; 64]], &[], [1, 1, 1]);
            let want = size[1] * 100 + size[0] + (2 + k * 10) * 1000;
            let o = u32s(&out[0]);
            for (i, &v) in o.iter().enumerate() {
                let live = i < (size[0] * size[1]) as usize;
                assert_eq!(v, if live { want } else { 0 }, "{what} with {size:?}, K = {k}: o[{i}]");
            }
        }
    }
}

/// A hand-built test program over buffers (0, 0) and (0, 1): no images, structures or
/// workgroup memory.
pub(super) fn two_buffer_program(blocks: Vec<ir::Block>, reg_count: u32, consts: Vec<(ir::Reg, u64)>, frame: usize) -> ir::Program {
    ir::Program {
        blocks,
        reg_count,
        consts,
        lane_frame: vec![0; frame],
        workgroup_bytes: 0,
        bindings: vec![(0, 0), (0, 1)],
        binding_counts: vec![1, 1],
        images: vec![],
        image_counts: vec![],
        accel_arrays: vec![],
        accel_bindings: vec![],
    }
}

/// Frames get only what the program reads: gl_GlobalInvocationID's words for a shader that
/// reads nothing else, more for one that does, and every word and the variables past the
/// built-ins once an address into the frame is computed.
#[test]
fn lane_frames_get_what_the_program_reads() {
    use super::exec::frame_use;
    use ir::{Op, Sc, Space};
    let all = (1u64 << (ir::builtin_offset::END / 4)) - 1;
    for (what, words) in compile("arith.comp") {
        let used = frame_use(&pipeline(&words, &[]).program);
        assert!(used.builtins != 0 && used.builtins & !0b111 == 0, "{what}: {used:?}");
    }
    for (what, words) in compile("misc.comp") {
        let used = frame_use(&pipeline(&words, &[]).program);
        assert!(used.builtins & !0b111 != 0 && used.tail, "{what}: {used:?}");
    }
    let (addr, gid, var) = (0, 1, 3);
    let ops = vec![Op::Load { ty: Sc::I32, space: Space::Lane, dst: gid, addr }, Op::Load { ty: Sc::I32, space: Space::Lane, dst: 2, addr: var }];
    let konsts = vec![(addr, 0), (var, ir::builtin_offset::END as u64)];
    let prog = two_buffer_program(vec![ir::Block { ops: ops.clone(), term: ir::Term::Exit, phi_in: vec![], edge_moves: vec![] }], 4, konsts, 168);
    assert_eq!(frame_use(&prog), super::exec::FrameUse { builtins: 1, tail: true });
    let ops = vec![ops[0].clone(), Op::Load { ty: Sc::I32, space: Space::Lane, dst: 2, addr: gid }];
    let prog = two_buffer_program(vec![ir::Block { ops, term: ir::Term::Exit, phi_in: vec![], edge_moves: vec![] }], 3, vec![(addr, 0)], 160);
    assert_eq!(frame_use(&prog), super::exec::FrameUse { builtins: all, tail: true });
}

//! Compute shaders through the loader (validation on, zero messages): SSBO arithmetic, each
//! shader as glslang compiled it, after `spirv-opt -O`, and (where a twin exists) from WGSL by
//! naga; results checked against a CPU reference computed here, and the same jobs on lavapipe
//! when it is installed.
mod harness;

use harness::compute::*;

/// The SPIR-V variants of a shader: glslang's, spirv-opt's, and naga's for a WGSL twin.
fn variants(glsl_name: &str, wgsl_name: Option<&str>) -> Vec<(String, Vec<u32>)> {
    let g = glsl(glsl_name);
    let mut v = vec![(format!("{glsl_name} (glslang)"), g.clone()), (format!("{glsl_name} (spirv-opt -O)"), optimized(&g))];
    if let Some(w) = wgsl_name {
        v.push((format!("{w} (naga)"), wgsl(w)));
    }
    v
}

/// Run `check` on Arbor and, when installed, lavapipe; both must be quiet.
fn on_every_driver(check: impl Fn(&Gpu)) {
    let arbor = Gpu::arbor();
    check(&arbor);
    arbor.assert_quiet();
    if let Some(lvp) = Gpu::lavapipe() {
        check(&lvp);
        lvp.assert_quiet();
    }
}

fn close(a: f32, b: f32) -> bool {
    (a - b).abs() <= 1e-5 * a.abs().max(b.abs()).max(1.0)
}

#[test]
fn integer_arithmetic_matches_the_cpu() {
    let n = 256u32;
    let input: Vec<u32> = (0..n).map(|i| i.wrapping_mul(0x9E37_79B9) ^ (i << 7)).collect();
    let want_u: Vec<u32> = input.iter().enumerate().map(|(i, &x)| x.wrapping_mul(2654435761).wrapping_add(x >> 3).wrapping_sub(x ^ 0xA5A5).wrapping_add(i as u32)).collect();
    let want_w: Vec<u64> = input.iter().enumerate().map(|(i, &x)| (x as u64).wrapping_mul(0x1_0000_0001).wrapping_add(i as u64)).collect();
    let shaders = variants("vk_arith.comp", None);
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let job = Job::new(
                spirv.clone(),
                vec![Binding::storage(u32s(&input)), Binding::storage(vec![0; 4 * n as usize]), Binding::storage(vec![0; 8 * n as usize])],
                Size::Direct([n / 64, 1, 1]),
            );
            let out = run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
            assert_eq!(as_u32(&out[1]), want_u, "{name} on {:?}", gpu.driver);
            let w: Vec<u64> = out[2].chunks(8).map(|c| u64::from_le_bytes(c.try_into().unwrap())).collect();
            assert_eq!(w, want_w, "{name} on {:?}", gpu.driver);
        }
    });
}

#[test]
fn float_arithmetic_matches_the_cpu_for_glsl_and_wgsl() {
    let n = 128u32;
    let input: Vec<f32> = (0..n).map(|i| (i as f32 - 60.0) * 0.37).collect();
    let want: Vec<f32> = input
        .iter()
        .enumerate()
        .map(|(i, &x)| {
            let y = x * 1.5 + i as f32 / 4.0;
            y.abs().sqrt() + x.floor() - x.min(2.0) * y.max(-1.0)
        })
        .collect();
    let shaders = variants("vk_arith_f.comp", Some("vk_arith_f.wgsl"));
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let job = Job::new(spirv.clone(), vec![Binding::storage(f32s(&input)), Binding::storage(vec![0; 4 * n as usize])], Size::Direct([n / 32, 1, 1]));
            let out = as_f32(&run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver))[1]);
            for (i, (g, w)) in out.iter().zip(&want).enumerate() {
                assert!(close(*g, *w), "{name} on {:?}: [{i}] = {g}, expected {w}", gpu.driver);
            }
        }
    });
}

fn collatz(mut x: u32) -> u32 {
    let mut steps = 0;
    while x != 1 && steps < 500 {
        x = if x & 1 == 1 { x.wrapping_mul(3).wrapping_add(1) } else { x / 2 };
        steps += 1;
    }
    steps
}

#[test]
fn control_flow_matches_the_cpu_for_glsl_and_wgsl() {
    let n = 256u32;
    let input: Vec<u32> = (0..n).map(|i| i.wrapping_mul(2_654_435_761) >> 7).collect();
    let want: Vec<u32> = input
        .iter()
        .map(|&x| {
            let mut acc = 0u32;
            for k in 0..(x & 31) {
                if k % 3 == 0 {
                    continue;
                }
                if acc > 1000 {
                    break;
                }
                acc += k * k;
            }
            match x % 4 {
                0 => acc + 7,
                1 => acc ^ 0xFF,
                2 => acc * 3,
                _ => acc + collatz(x + 1),
            }
        })
        .collect();
    let shaders = variants("vk_control.comp", Some("vk_control.wgsl"));
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let job = Job::new(spirv.clone(), vec![Binding::storage(u32s(&input)), Binding::storage(vec![0; 4 * n as usize])], Size::Direct([n / 64, 1, 1]));
            let out = run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
            assert_eq!(as_u32(&out[1]), want, "{name} on {:?}", gpu.driver);
        }
    });
}

#[test]
fn shared_memory_and_barriers_match_the_cpu_for_glsl_and_wgsl() {
    let groups = 6u32;
    let n = groups * 128;
    let input: Vec<u32> = (0..n).map(|i| i.wrapping_mul(7919) % 100_003).collect();
    let sums: Vec<u32> = input.chunks(128).map(|c| c.iter().fold(0u32, |a, &x| a.wrapping_add(x))).collect();
    let rot: Vec<u32> = (0..n as usize).map(|i| input[i / 128 * 128 + (i % 128 + 1) % 128]).collect();
    let shaders = variants("vk_shared.comp", Some("vk_shared.wgsl"));
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let job = Job::new(
                spirv.clone(),
                vec![Binding::storage(u32s(&input)), Binding::storage(vec![0; 4 * groups as usize]), Binding::storage(vec![0; 4 * n as usize])],
                Size::Direct([groups, 1, 1]),
            );
            let out = run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
            assert_eq!(as_u32(&out[1]), sums, "{name} on {:?}: workgroup sums", gpu.driver);
            assert_eq!(as_u32(&out[2]), rot, "{name} on {:?}: neighbour reads after the barrier", gpu.driver);
        }
    });
}

#[test]
fn atomics_on_buffers_and_shared_memory_match_the_cpu() {
    let groups = 8u32;
    let n = groups * 64;
    let input: Vec<u32> = (0..n).map(|i| i.wrapping_mul(0x2545_F491) ^ (i >> 3)).collect();
    // count, max, min (starts at u32::MAX), or, sum64 (two words), 16 bins.
    let mut counters = vec![0u32; 6 + 16];
    counters[2] = u32::MAX;
    let mut want = counters.clone();
    let mut sum64 = 0u64;
    for &x in &input {
        want[0] += 1;
        want[1] = want[1].max(x);
        want[2] = want[2].min(x);
        want[3] |= 1 << (x % 32);
        sum64 = sum64.wrapping_add((x as u64) << 8);
        want[6 + (x % 16) as usize] += 1;
    }
    want[4] = sum64 as u32;
    want[5] = (sum64 >> 32) as u32;
    let group_sums: Vec<u32> = input.chunks(64).map(|c| c.iter().map(|x| x & 0xFFFF).sum()).collect();
    let shaders = variants("vk_atomics.comp", None);
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let job = Job::new(
                spirv.clone(),
                vec![Binding::storage(u32s(&input)), Binding::storage(u32s(&counters)), Binding::storage(vec![0; 4 * groups as usize])],
                Size::Direct([groups, 1, 1]),
            );
            let out = run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
            assert_eq!(as_u32(&out[1]), want, "{name} on {:?}: buffer atomics", gpu.driver);
            assert_eq!(as_u32(&out[2]), group_sums, "{name} on {:?}: shared-memory atomics", gpu.driver);
        }
    });
}

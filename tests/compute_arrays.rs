//! Arrays of buffer descriptors through the loader (validation on, zero messages): a storage
//! array written through a non-uniform index, a uniform array read with constant and
//! dynamically uniform indices, a runtime array read non-uniformly, each element a separate
//! descriptor range (dstArrayElement writes) of one buffer; results checked against a CPU
//! reference computed here, on Arbor and (when installed) lavapipe. An index past the array's
//! end is reported once and contained.
mod harness;

use harness::compute::*;

/// Bytes of one array element's range (a multiple of every offset alignment in use).
const PART: usize = 256;

fn on_every_driver(check: impl Fn(&Gpu)) {
    let arbor = Gpu::arbor();
    check(&arbor);
    arbor.assert_quiet();
    if let Some(lvp) = Gpu::lavapipe() {
        check(&lvp);
        lvp.assert_quiet();
    }
}

/// `parts` equal parts of PART bytes, part p holding `f(p, k)` at word k.
fn parts(parts: usize, f: impl Fn(usize, usize) -> u32) -> Vec<u8> {
    (0..parts).flat_map(|p| u32s(&(0..PART / 4).map(|k| f(p, k)).collect::<Vec<_>>())).collect()
}

#[test]
fn buffer_arrays_with_constant_uniform_and_non_uniform_indices() {
    let n = 64usize;
    let ins = parts(3, |p, k| (p as u32 + 1) * 1000 + k as u32 * 7);
    // params[p].k = (10 + p, 100 * (p + 1), junk, junk).
    let params = parts(3, |p, k| match k {
        0 => 10 + p as u32,
        1 => 100 * (p as u32 + 1),
        _ => 0xABCD,
    });
    let glsl = glsl("vk_arrays.comp");
    let shaders = [("vk_arrays.comp (glslang)", glsl.clone()), ("vk_arrays.comp (spirv-opt -O)", optimized(&glsl))];
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            for (pick, shift) in [(0u32, 0u32), (1, 2)] {
                let bindings = vec![
                    Binding::storage(vec![0xFF; 4 * PART]).array(4),
                    Binding::uniform(params.clone()).array(3),
                    Binding::storage(ins.clone()).array(3),
                ];
                let mut job = Job::new(spirv.clone(), bindings, Size::Direct([n as u32 / 16, 1, 1]));
                job.push = u32s(&[pick, shift]);
                let out = run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
                let out = as_u32(&out[0]);
                let mut want = as_u32(&vec![0xFF; 4 * PART]);
                for i in 0..n {
                    let j = (i + shift as usize) % 3;
                    let v = (j as u32 + 1) * 1000 + i as u32 * 7;
                    let (e, k) = (i % 4, i / 4);
                    want[e * PART / 4 + k] = v * 3 + 12 + 100 * (pick + 1) * j as u32;
                }
                assert_eq!(out, want, "{name} on {:?}, pick {pick}, shift {shift}", gpu.driver);
            }
        }
    });
}

#[test]
fn an_array_index_past_the_end_is_reported_once_and_contained() {
    let gpu = Gpu::arbor();
    let mut job = Job::new(glsl("vk_arrays_oob.comp"), vec![Binding::storage(vec![0; 2 * PART]).array(2)], Size::Direct([2, 1, 1]));
    job.push = u32s(&[5]);
    let out = as_u32(&run(&gpu, &job).expect("the dispatch completes")[0]);
    assert!(out.iter().all(|&v| v == 0), "nothing is written through an index past the array");
    let diag = harness::diagnostics();
    let lines: Vec<&str> = diag.lines().filter(|l| l.contains("contained memory fault")).collect();
    assert_eq!(lines.len(), 1, "one diagnostic per dispatch:\n{diag}");
    assert!(lines[0].contains("VUID-vkCmdDispatch-None-10068") && lines[0].contains("element: 5"), "{}", lines[0]);
    // In range, element 1 gets every write: the device is fine.
    job.push = u32s(&[1]);
    let out = as_u32(&run(&gpu, &job).unwrap()[0]);
    let want: Vec<u32> = (0..2 * PART / 4).map(|w| if w >= PART / 4 && w - PART / 4 < 32 { (w - PART / 4) as u32 + 7 } else { 0 }).collect();
    assert_eq!(out, want);
    gpu.assert_quiet();
}

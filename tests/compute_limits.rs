//! The compute limits Arbor reports are what its executor runs: a workgroup of
//! maxComputeWorkGroupInvocations (1024) invocations using maxComputeSharedMemorySize (32 KiB)
//! of shared memory with barriers between phases, checked against a CPU computation, through
//! the loader with validation on (which checks the shader against the reported limits), and
//! the same job on lavapipe when it is installed.
mod harness;

use harness::compute::*;

const GROUPS: usize = 2;
const PER_GROUP: usize = 8192;

#[test]
fn a_1024_invocation_workgroup_with_32_kib_of_shared_memory_and_barriers_matches_the_cpu() {
    let input: Vec<u32> = (0..GROUPS * PER_GROUP).map(|i| (i as u32).wrapping_mul(0x9E37_79B9) >> 7).collect();
    let mut want_dst = vec![0u32; input.len()];
    let mut want_sums = vec![0u32; GROUPS];
    for g in 0..GROUPS {
        let s = &input[g * PER_GROUP..(g + 1) * PER_GROUP];
        for i in 0..PER_GROUP {
            want_dst[g * PER_GROUP + i] = s[PER_GROUP - 1 - i].wrapping_mul(3).wrapping_add((i % 1024) as u32);
        }
        want_sums[g] = s.iter().fold(0u32, |a, &v| a.wrapping_add(v));
    }
    let g = glsl("vk_big_group.comp");
    let shaders = [("glslang", g.clone()), ("spirv-opt -O", optimized(&g))];
    let mut gpus = vec![Gpu::arbor()];
    gpus.extend(Gpu::lavapipe());
    for gpu in &gpus {
        // SAFETY: plain query on a live instance and physical device.
        let limits = unsafe { gpu.instance.get_physical_device_properties(gpu.physical) }.limits;
        if limits.max_compute_work_group_invocations < 1024 || limits.max_compute_shared_memory_size < 32768 {
            println!("{:?} reports smaller compute limits: skipped there", gpu.driver);
            continue;
        }
        for (name, spirv) in &shaders {
            let job = Job::new(
                spirv.clone(),
                vec![Binding::storage(u32s(&input)), Binding::storage(vec![0; 4 * input.len()]), Binding::storage(vec![0; 4 * GROUPS])],
                Size::Direct([GROUPS as u32, 1, 1]),
            );
            let out = run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
            assert!(as_u32(&out[1]) == want_dst, "{name} on {:?}: shared-memory exchange differs from the CPU's", gpu.driver);
            assert_eq!(as_u32(&out[2]), want_sums, "{name} on {:?}: reduction", gpu.driver);
        }
        gpu.assert_quiet();
    }
}

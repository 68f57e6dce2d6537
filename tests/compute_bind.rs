//! Compute state through the loader (validation on, zero messages): push constants, uniform
//! buffers and dynamic offsets (uniform and storage), specialization constants, buffer device
//! address, subgroups, vkCmdDispatchBase and vkCmdDispatchIndirect; every result checked
//! against a CPU reference computed here, on Arbor and (when installed) lavapipe.
mod harness;

use ash::vk;
use harness::compute::*;

fn on_every_driver(check: impl Fn(&Gpu)) {
    let arbor = Gpu::arbor();
    check(&arbor);
    arbor.assert_quiet();
    if let Some(lvp) = Gpu::lavapipe() {
        check(&lvp);
        lvp.assert_quiet();
    }
}

fn both_compilers(name: &str) -> Vec<(String, Vec<u32>)> {
    let g = glsl(name);
    vec![(format!("{name} (glslang)"), g.clone()), (format!("{name} (spirv-opt -O)"), optimized(&g))]
}

#[test]
fn push_constants_dynamic_uniform_and_storage_offsets_and_spec_constants() {
    let (local, groups) = (16u32, 4u32);
    let n = local * groups;
    // The parameters sit 256 bytes into the uniform buffer (a dynamic offset), after junk.
    let mut ubo = vec![0xEEu8; 256];
    ubo.extend(u32s(&[10, 20, 30, 40]));
    ubo.extend(f32s(&[0.5, 1.5, 2.5, 3.5]));
    // The output starts 512 bytes into its buffer (a dynamic storage offset): a different
    // offset from the uniform's, so the order in which dynamic offsets apply is checked too.
    let out_len = 512 + 8 * n as usize;
    let mut push = u32s(&[5]);
    push.extend(f32s(&[0.5]));
    let mut want = vec![0u32; 2 * n as usize];
    for i in 0..n {
        want[i as usize] = !(i * 3 + 5 + [10, 20, 30, 40][(i % 4) as usize]);
        want[(n + i) as usize] = (i as f32 * 0.5 + [0.5, 1.5, 2.5, 3.5][(i % 4) as usize]).to_bits();
    }
    let shaders = both_compilers("vk_push_ubo.comp");
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let mut job = Job::new(
                spirv.clone(),
                vec![Binding::uniform(ubo.clone()).dynamic(256, 32), Binding::storage(vec![0; out_len]).dynamic(512, 8 * n as u64)],
                Size::Direct([groups, 1, 1]),
            );
            job.push = push.clone();
            job.spec = vec![(0, u32s(&[local])), (1, u32s(&[3])), (2, u32s(&[1]))];
            let out = run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
            assert!(out[1][..512].iter().all(|&b| b == 0), "{name} on {:?}: wrote before the dynamic offset", gpu.driver);
            assert_eq!(as_u32(&out[1][512..]), want, "{name} on {:?}", gpu.driver);
        }
    });
}

#[test]
fn buffer_device_address_reads_and_writes_through_pointers() {
    let n = 64u32;
    let count = n - 5;
    let values: Vec<u32> = (0..n).map(|i| i * 11 + 3).collect();
    let mut header = vec![0u8; 16];
    header[8..12].copy_from_slice(&count.to_le_bytes());
    let want_values: Vec<u32> = values.iter().enumerate().map(|(i, &x)| if (i as u32) < count { x * 2 + 1 } else { x }).collect();
    let want_out: Vec<u32> = values.iter().enumerate().map(|(i, &x)| if (i as u32) < count { x + count } else { 0 }).collect();
    let shaders = both_compilers("vk_bda.comp");
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let mut job = Job::new(
                spirv.clone(),
                vec![Binding::storage(vec![0; 4 * n as usize]), Binding::storage(header.clone()), Binding::storage(u32s(&values))],
                Size::Direct([n / 32, 1, 1]),
            );
            job.push = vec![0; 8];
            // Push constants → header; header.values → the values buffer.
            job.addresses = vec![AddressPatch { into: None, at: 0, of: 1, plus: 0 }, AddressPatch { into: Some(1), at: 0, of: 2, plus: 0 }];
            let out = run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
            assert_eq!(as_u32(&out[0]), want_out, "{name} on {:?}: reads", gpu.driver);
            assert_eq!(as_u32(&out[2]), want_values, "{name} on {:?}: writes through the pointer", gpu.driver);
        }
    });
}

/// What vk_subgroup.comp must write, from the subgroup membership the driver reported.
fn subgroup_reference(input: &[u32], ids: &[(u32, u32)]) -> Vec<u32> {
    let mut out = vec![0u32; input.len() * 10];
    for (i, &(sg, lane)) in ids.iter().enumerate() {
        let members: Vec<usize> = (0..input.len()).filter(|&j| ids[j].0 == sg).collect();
        let of = |l: u32| members.iter().find(|&&j| ids[j].1 == l).map(|&j| input[j]).unwrap_or(0);
        let r = &mut out[i * 10..i * 10 + 10];
        r[0] = sg;
        r[1] = lane;
        r[2] = members.iter().fold(0u32, |a, &j| a.wrapping_add(input[j]));
        r[3] = members.iter().filter(|&&j| ids[j].1 <= lane).fold(0u32, |a, &j| a.wrapping_add(input[j]));
        r[4] = members.iter().map(|&j| input[j]).max().unwrap();
        r[5] = members.iter().filter(|&&j| input[j] & 1 == 1).count() as u32;
        r[6] = members.iter().all(|&j| input[j] / 1000 == input[i] / 1000) as u32;
        r[7] = (lane == members.iter().map(|&j| ids[j].1).min().unwrap()) as u32;
        r[8] = of(0);
        r[9] = of(lane ^ 1);
    }
    out
}

#[test]
fn subgroup_operations_match_the_cpu_for_the_reported_subgroup_size() {
    let n = 256u32;
    // Blocks of 16 invocations share x / 1000, so all-equal is true for subgroups of up to 16.
    let input: Vec<u32> = (0..n).map(|i| (i / 16) * 1000 + (i.wrapping_mul(37) % 997)).collect();
    let shaders = both_compilers("vk_subgroup.comp");
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let job = Job::new(spirv.clone(), vec![Binding::storage(u32s(&input)), Binding::storage(vec![0; 40 * n as usize])], Size::Direct([n / 64, 1, 1]));
            let out = as_u32(&run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver))[1]);
            let ids: Vec<(u32, u32)> = out.chunks(10).map(|r| (r[0], r[1])).collect();
            for (sg, lanes) in ids.chunk_by(|a, b| a.0 == b.0).map(|c| (c[0].0, c.len())) {
                assert_eq!(lanes as u32, gpu.subgroup_size, "{name} on {:?}: subgroup {sg} has {lanes} lanes", gpu.driver);
            }
            assert_eq!(out, subgroup_reference(&input, &ids), "{name} on {:?}", gpu.driver);
        }
    });
}

/// What vk_dispatch.comp writes for `groups` workgroups from `base` (slots of 4 per invocation).
fn dispatch_reference(base: [u32; 3], groups: [u32; 3]) -> Vec<u32> {
    let mut out = vec![0u32; 512 * 8 * 4];
    for gz in base[2]..base[2] + groups[2] {
        for gy in base[1]..base[1] + groups[1] {
            for gx in base[0]..base[0] + groups[0] {
                let group = gx + 8 * (gy + 8 * gz);
                for ly in 0..2 {
                    for lx in 0..4 {
                        let local = lx + 4 * ly;
                        let (x, y, z) = (gx * 4 + lx, gy * 2 + ly, gz);
                        let slot = ((group * 8 + local) * 4) as usize;
                        out[slot] = 1 + x + 100 * y + 10000 * z;
                        out[slot + 1] = groups[0] + 100 * groups[1] + 10000 * groups[2];
                        out[slot + 2] = local;
                        out[slot + 3] = group;
                    }
                }
            }
        }
    }
    out
}

#[test]
fn dispatch_direct_base_and_indirect_cover_exactly_their_workgroups() {
    let cases = [
        ("vkCmdDispatch", Size::Direct([3, 2, 2]), [0; 3], [3, 2, 2]),
        ("vkCmdDispatchBase", Size::Base { base: [2, 1, 3], groups: [3, 2, 2] }, [2, 1, 3], [3, 2, 2]),
        ("vkCmdDispatchIndirect", Size::Indirect([2, 3, 1]), [0; 3], [2, 3, 1]),
        ("vkCmdDispatchIndirect of zero groups", Size::Indirect([4, 0, 1]), [0; 3], [0, 0, 0]),
    ];
    let shaders = both_compilers("vk_dispatch.comp");
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            for (what, size, base, groups) in cases {
                let job = Job::new(spirv.clone(), vec![Binding::storage(vec![0; 512 * 8 * 16])], size);
                let out = as_u32(&run(gpu, &job).unwrap_or_else(|e| panic!("{name} {what} on {:?}: {e:?}", gpu.driver))[0]);
                assert!(out == dispatch_reference(base, groups), "{name}: {what} on {:?} wrote other workgroups or values", gpu.driver);
            }
        }
    });
}

#[test]
fn pipeline_cache_data_is_a_valid_header() {
    let gpu = Gpu::arbor();
    // SAFETY: valid create info; the cache is destroyed below.
    unsafe {
        let cache = gpu.device.create_pipeline_cache(&vk::PipelineCacheCreateInfo::default(), None).unwrap();
        let data = gpu.device.get_pipeline_cache_data(cache).unwrap();
        let p = gpu.instance.get_physical_device_properties(gpu.physical);
        assert_eq!(data.len(), 32);
        assert_eq!(u32::from_le_bytes(data[0..4].try_into().unwrap()), 32, "headerSize");
        assert_eq!(u32::from_le_bytes(data[4..8].try_into().unwrap()), 1, "VK_PIPELINE_CACHE_HEADER_VERSION_ONE");
        assert_eq!(u32::from_le_bytes(data[8..12].try_into().unwrap()), p.vendor_id);
        assert_eq!(u32::from_le_bytes(data[12..16].try_into().unwrap()), p.device_id);
        assert_eq!(data[16..32], p.pipeline_cache_uuid);
        let other = gpu.device.create_pipeline_cache(&vk::PipelineCacheCreateInfo::default().initial_data(&data), None).unwrap();
        gpu.device.merge_pipeline_caches(cache, &[other]).unwrap();
        gpu.device.destroy_pipeline_cache(other, None);
        gpu.device.destroy_pipeline_cache(cache, None);
    }
    gpu.assert_quiet();
}

#[test]
fn subgroup_operations_on_64_bit_integers_and_doubles_match_the_cpu() {
    let n = 128usize;
    let input: Vec<u64> = (0..n as u64).map(|i| i.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 9).collect();
    let bytes: Vec<u8> = input.iter().flat_map(|x| x.to_le_bytes()).collect();
    let shaders = both_compilers("vk_subgroup64.comp");
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let job = Job::new(spirv.clone(), vec![Binding::storage(bytes.clone()), Binding::storage(vec![0; 40 * n])], Size::Direct([n as u32 / 32, 1, 1]));
            let out = run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
            let r: Vec<u64> = out[1].chunks(8).map(|c| u64::from_le_bytes(c.try_into().unwrap())).collect();
            for i in 0..n {
                let members: Vec<usize> = (0..n).filter(|&j| r[j * 5] == r[i * 5]).collect();
                let sum = members.iter().fold(0u64, |a, &j| a.wrapping_add(input[j]));
                let max = members.iter().map(|&j| input[j]).max().unwrap();
                // Doubles of 20-bit integers halved: every partial sum is exact.
                let dsum: f64 = members.iter().map(|&j| (input[j] & 0xFFFFF) as f64 * 0.5).sum();
                assert_eq!(r[i * 5 + 1], sum, "{name} on {:?}: subgroupAdd(uint64) at {i}", gpu.driver);
                assert_eq!(r[i * 5 + 2], max, "{name} on {:?}: subgroupMax(uint64) at {i}", gpu.driver);
                assert!(members.iter().any(|&j| input[j] == r[i * 5 + 3]), "{name} on {:?}: subgroupBroadcastFirst at {i}", gpu.driver);
                assert_eq!(r[i * 5 + 4], (dsum * 2.0) as u64, "{name} on {:?}: subgroupAdd(double) at {i}", gpu.driver);
            }
        }
    });
}

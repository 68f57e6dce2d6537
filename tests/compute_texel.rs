//! Texel buffers through the loader (validation on, zero messages): vkCreateBufferView, a
//! uniform texel buffer read with texelFetch (OpImageFetch), R32_SFLOAT and RGBA8_UNORM storage
//! texel buffers written and read back, their sizes queried; every result checked against a
//! CPU reference computed here, on Arbor and (when installed) lavapipe, with glslang's and
//! `spirv-opt -O`'s SPIR-V (WGSL has no texel buffers: no naga twin). A texel coordinate past
//! the view is reported once and contained. Image atomics (OpImageTexelPointer) on an
//! R32_UINT storage image and an R32_SINT texel buffer. The format query answers texel-buffer
//! and atomic support for exactly the formats that run.
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

#[test]
fn uniform_and_storage_texel_buffers_match_the_cpu_reference() {
    let n = 64u32;
    let src: Vec<u32> = (0..n).map(|i| i * 13 + 5).collect();
    let rgba: Vec<u8> = (0..n).flat_map(|i| [i as u8, (2 * i) as u8, 255 - i as u8, 7]).collect();
    let want_dst: Vec<f32> = src.iter().map(|&v| v as f32 * 0.5 + 0.25).collect();
    // c.wzyx of a UNORM8 texel stores its bytes reversed (conversion round-trips exactly).
    let want_io: Vec<u8> = rgba.chunks(4).flat_map(|t| [t[3], t[2], t[1], t[0]]).collect();
    let g = glsl("vk_texel.comp");
    let shaders = [("vk_texel.comp (glslang)", g.clone()), ("vk_texel.comp (spirv-opt -O)", optimized(&g))];
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let bindings = vec![
                Binding::uniform_texels(vk::Format::R32_UINT, u32s(&src)),
                Binding::storage_texels(vk::Format::R32_SFLOAT, vec![0; 4 * n as usize]),
                Binding::storage_texels(vk::Format::R8G8B8A8_UNORM, rgba.clone()),
                Binding::storage(vec![0; 8]),
            ];
            let out = run(gpu, &Job::new(spirv.clone(), bindings, Size::Direct([n / 16, 1, 1]))).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
            assert_eq!(as_f32(&out[1]), want_dst, "{name} on {:?}: float storage texels", gpu.driver);
            assert_eq!(out[2], want_io, "{name} on {:?}: RGBA8 storage texels", gpu.driver);
            assert_eq!(as_u32(&out[3]), [n, n], "{name} on {:?}: textureSize / imageSize", gpu.driver);
        }
    });
}

#[test]
fn image_atomics_on_storage_images_and_texel_buffers_match_the_cpu_reference() {
    let n = 256usize;
    let mut x = 0x2545_F491u32;
    let values: Vec<i32> = (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x % 2001) as i32 - 1000
        })
        .collect();
    let bin = |v: i32| (v as u32 & 15) as usize;
    let mut hist = [0u32; 4 * 6];
    let mut minmax: Vec<i32> = (0..32).map(|k| if k % 2 == 0 { i32::MAX } else { i32::MIN }).collect();
    for (i, &v) in values.iter().enumerate() {
        let b = bin(v);
        hist[b] += 1;
        hist[16 + b % 4] |= 1 << (i % 32);
        minmax[2 * b] = minmax[2 * b].min(v);
        minmax[2 * b + 1] = minmax[2 * b + 1].max(v);
    }
    let g = glsl("vk_image_atomics.comp");
    let shaders = [("vk_image_atomics.comp (glslang)", g.clone()), ("vk_image_atomics.comp (spirv-opt -O)", optimized(&g))];
    let initial: Vec<i32> = (0..32).map(|k| if k % 2 == 0 { i32::MAX } else { i32::MIN }).collect();
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            let bindings = vec![
                Binding::storage_image(vk::Format::R32_UINT, [4, 6], vec![0; 4 * 4 * 6]),
                Binding::storage_texels(vk::Format::R32_SINT, initial.iter().flat_map(|v| v.to_le_bytes()).collect()),
                Binding::storage(values.iter().flat_map(|v| v.to_le_bytes()).collect()),
                Binding::storage(vec![0xEE; 4 * n]),
            ];
            let out = run(gpu, &Job::new(spirv.clone(), bindings, Size::Direct([n as u32 / 64, 1, 1]))).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
            let (img, old) = (as_u32(&out[0]), as_u32(&out[3]));
            let ctx = format!("{name} on {:?}", gpu.driver);
            assert_eq!(img[..20], hist[..20], "{ctx}: histogram and OR masks");
            let got_minmax: Vec<i32> = as_u32(&out[1]).iter().map(|&w| w as i32).collect();
            assert_eq!(got_minmax, minmax, "{ctx}: min/max texel buffer");
            // One invocation claims texel (0, 5); every other one sees its id + 1.
            let winners: Vec<usize> = (0..n).filter(|&i| old[i] == 0).collect();
            assert_eq!(winners.len(), 1, "{ctx}: exactly one compare-exchange succeeds");
            let w = winners[0] as u32 + 1;
            assert!(old.iter().all(|&o| o == 0 || o == w), "{ctx}: the others return the winner's value");
            assert_eq!(img[20..], [w, 0, 0, 0], "{ctx}: the claimed texel");
        }
    });
}

#[test]
fn arrays_of_texel_buffers_with_uniform_constant_and_non_uniform_indices() {
    let (n, texels) = (64usize, 64usize);
    let srcs: Vec<u32> = (0..3 * texels).map(|k| (k / texels) as u32 * 1000 + (k % texels) as u32).collect();
    let g = glsl("vk_texel_arrays.comp");
    let shaders = [("vk_texel_arrays.comp (glslang)", g.clone()), ("vk_texel_arrays.comp (spirv-opt -O)", optimized(&g))];
    on_every_driver(|gpu| {
        for (name, spirv) in &shaders {
            for pick in [0u32, 1] {
                let bindings = vec![
                    Binding::uniform_texels(vk::Format::R32_UINT, u32s(&srcs)).array(3),
                    Binding::storage_texels(vk::Format::R32_UINT, vec![0; 4 * 4 * texels]).array(4),
                    Binding::storage(vec![0; 32]),
                ];
                let mut job = Job::new(spirv.clone(), bindings, Size::Direct([n as u32 / 16, 1, 1]));
                job.push = u32s(&[pick]);
                let out = run(gpu, &job).unwrap_or_else(|e| panic!("{name} on {:?}: {e:?}", gpu.driver));
                let mut want = vec![0u32; 4 * texels];
                for i in 0..n {
                    let (a, b) = (srcs[pick as usize * texels + i], srcs[2 * texels + i]);
                    want[(i % 4) * texels + i / 4] = a * 10 + b;
                }
                for e in 0..4 {
                    want[e * texels + 60 + e] = (n / 4) as u32;
                }
                let ctx = format!("{name} on {:?}, pick {pick}", gpu.driver);
                assert_eq!(as_u32(&out[1]), want, "{ctx}: storage texel buffer elements");
                assert_eq!(as_u32(&out[2]), [64, 64, 64, 64, 64, 64, 64, 0], "{ctx}: element sizes");
            }
        }
    });
}

#[test]
fn a_texel_coordinate_past_the_view_is_reported_once_and_contained() {
    let gpu = Gpu::arbor();
    let texels: Vec<u32> = (0..32).map(|i| 1000 + i).collect();
    let mut job = Job::new(glsl("vk_texel_oob.comp"), vec![Binding::storage_texels(vk::Format::R32_UINT, u32s(&texels)), Binding::storage(vec![0xEE; 4 * 32])], Size::Direct([2, 1, 1]));
    job.push = u32s(&[8]);
    let out = run(&gpu, &job).expect("the dispatch completes");
    let (t, o) = (as_u32(&out[0]), as_u32(&out[1]));
    for i in 0..32usize {
        // Invocation i reads and writes texel i + 8: those past texel 31 read zero and write nothing.
        assert_eq!(o[i], if i + 8 < 32 { texels[i + 8] } else { 0 }, "read by invocation {i}");
        assert_eq!(t[i], if i >= 8 { (i - 8) as u32 + 100 } else { texels[i] }, "texel {i}");
    }
    let diag = harness::diagnostics();
    let lines: Vec<&str> = diag.lines().filter(|l| l.contains("contained memory fault")).collect();
    assert_eq!(lines.len(), 1, "one diagnostic per dispatch:\n{diag}");
    assert!(lines[0].contains("Binding { set: 0, binding: 0 }") && lines[0].contains("OutOfBounds"), "{}", lines[0]);
    gpu.assert_quiet();
}

#[test]
fn format_properties_report_texel_buffers_for_the_formats_that_run() {
    let gpu = Gpu::arbor();
    let texel = vk::FormatFeatureFlags::UNIFORM_TEXEL_BUFFER | vk::FormatFeatureFlags::STORAGE_TEXEL_BUFFER;
    for format in [vk::Format::R32_UINT, vk::Format::R32_SINT, vk::Format::R32_SFLOAT, vk::Format::R32G32B32A32_UINT, vk::Format::R32G32B32A32_SINT, vk::Format::R32G32B32A32_SFLOAT, vk::Format::R8G8B8A8_UNORM] {
        // SAFETY: plain query.
        let p = unsafe { gpu.instance.get_physical_device_format_properties(gpu.physical, format) };
        assert!(p.buffer_features.contains(texel), "{format:?}: {:?}", p.buffer_features);
    }
    // Atomics: exactly the 32-bit integer formats.
    for format in [vk::Format::R32_UINT, vk::Format::R32_SINT, vk::Format::R32_SFLOAT, vk::Format::R8G8B8A8_UNORM] {
        // SAFETY: plain query.
        let p = unsafe { gpu.instance.get_physical_device_format_properties(gpu.physical, format) };
        let int = matches!(format, vk::Format::R32_UINT | vk::Format::R32_SINT);
        assert_eq!(p.optimal_tiling_features.contains(vk::FormatFeatureFlags::STORAGE_IMAGE_ATOMIC), int, "{format:?}");
        assert_eq!(p.buffer_features.contains(vk::FormatFeatureFlags::STORAGE_TEXEL_BUFFER_ATOMIC), int, "{format:?}");
    }
    for format in [vk::Format::R8_UNORM, vk::Format::R16G16B16A16_SFLOAT, vk::Format::B8G8R8A8_UNORM] {
        // SAFETY: plain query.
        let p = unsafe { gpu.instance.get_physical_device_format_properties(gpu.physical, format) };
        assert!(!p.buffer_features.intersects(texel), "{format:?} claims texel buffers: {:?}", p.buffer_features);
    }
    gpu.assert_quiet();
}

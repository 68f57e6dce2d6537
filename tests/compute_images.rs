//! Storage images in compute dispatches through the loader (validation on, zero messages):
//! imageSize, imageLoad and imageStore on a 2D R32_UINT and a 2D RGBA8 image, checked against
//! a CPU reference computed here, on Arbor and (when installed) lavapipe.
mod harness;

use ash::vk;
use harness::compute::*;

#[test]
fn image_load_store_and_size_on_r32ui_and_rgba8() {
    let (counts_extent, colors_extent) = ([12u32, 8], [10u32, 5]);
    let counts: Vec<u32> = (0..counts_extent[0] * counts_extent[1]).map(|i| i.wrapping_mul(2654435761) >> 20).collect();
    let colors: Vec<u8> = (0..4 * colors_extent[0] * colors_extent[1]).map(|i| (i.wrapping_mul(2654435761) >> 13) as u8).collect();
    let want_counts: Vec<u32> = counts.iter().enumerate().map(|(i, &v)| {
        let (x, y) = (i as u32 % counts_extent[0], i as u32 / counts_extent[0]);
        v.wrapping_mul(3) + x + 100 * y
    }).collect();
    // (g, r, 1 - b, a): swaps and 1 - b are exact in UNORM8, whatever the rounding.
    let want_colors: Vec<u8> = colors.chunks(4).flat_map(|c| [c[1], c[0], 255 - c[2], c[3]]).collect();
    let spirv = glsl("vk_images.comp");
    let check = |gpu: &Gpu| {
        let job = Job::new(
            spirv.clone(),
            vec![
                Binding::storage_image(vk::Format::R32_UINT, counts_extent, u32s(&counts)),
                Binding::storage_image(vk::Format::R8G8B8A8_UNORM, colors_extent, colors.clone()),
                Binding::storage(vec![0; 16]),
            ],
            Size::Direct([3, 2, 1]),
        );
        let out = run(gpu, &job).unwrap_or_else(|e| panic!("{:?}: {e:?}", gpu.driver));
        assert_eq!(as_u32(&out[2]), [12, 8, 10, 5], "{:?}: imageSize", gpu.driver);
        assert_eq!(as_u32(&out[0]), want_counts, "{:?}: R32_UINT", gpu.driver);
        assert_eq!(out[1], want_colors, "{:?}: RGBA8", gpu.driver);
    };
    let arbor = Gpu::arbor();
    check(&arbor);
    arbor.assert_quiet();
    if let Some(lvp) = Gpu::lavapipe() {
        check(&lvp);
        lvp.assert_quiet();
    }
}

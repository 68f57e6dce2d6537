//! Images through the real loader with validation on (zero messages): format queries answer
//! exactly what works; clear / buffer → image / image → image / image → buffer round trips for
//! every format, 1D/2D/3D, arrays and mip levels, both tilings, checked against a CPU model of
//! the image; the linear subresource layout is where the texels really are; storage-image
//! descriptors are accepted; and invalid use is reported with its VUID and not executed.
mod harness;

use ash::vk;

const FORMATS: &[(vk::Format, usize)] = &[
    (vk::Format::R32_UINT, 4),
    (vk::Format::R32_SINT, 4),
    (vk::Format::R32_SFLOAT, 4),
    (vk::Format::R32G32B32A32_UINT, 16),
    (vk::Format::R32G32B32A32_SINT, 16),
    (vk::Format::R32G32B32A32_SFLOAT, 16),
    (vk::Format::R8G8B8A8_UNORM, 4),
];

const ALL_USAGE: vk::ImageUsageFlags = vk::ImageUsageFlags::from_raw(
    vk::ImageUsageFlags::STORAGE.as_raw() | vk::ImageUsageFlags::TRANSFER_SRC.as_raw() | vk::ImageUsageFlags::TRANSFER_DST.as_raw(),
);
const BUF_USAGE: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(vk::BufferUsageFlags::TRANSFER_SRC.as_raw() | vk::BufferUsageFlags::TRANSFER_DST.as_raw());

struct Img {
    image: vk::Image,
    memory: vk::DeviceMemory,
}

#[allow(clippy::too_many_arguments)] // one VkImageCreateInfo's worth of parameters
fn image(ctx: &harness::Context, format: vk::Format, ty: vk::ImageType, extent: [u32; 3], levels: u32, layers: u32, tiling: vk::ImageTiling, usage: vk::ImageUsageFlags) -> Img {
    let info = vk::ImageCreateInfo::default()
        .image_type(ty)
        .format(format)
        .extent(vk::Extent3D { width: extent[0], height: extent[1], depth: extent[2] })
        .mip_levels(levels)
        .array_layers(layers)
        .samples(vk::SampleCountFlags::TYPE_1)
        .tiling(tiling)
        .usage(usage)
        .initial_layout(if tiling == vk::ImageTiling::LINEAR { vk::ImageLayout::PREINITIALIZED } else { vk::ImageLayout::UNDEFINED });
    // SAFETY: valid create info; the test destroys the objects.
    unsafe {
        let image = ctx.device.create_image(&info, None).expect("vkCreateImage");
        let req = ctx.device.get_image_memory_requirements(image);
        let ai = vk::MemoryAllocateInfo::default()
            .allocation_size(req.size)
            .memory_type_index(ctx.memory_type(req.memory_type_bits, vk::MemoryPropertyFlags::HOST_VISIBLE));
        let memory = ctx.device.allocate_memory(&ai, None).expect("vkAllocateMemory");
        ctx.device.bind_image_memory(image, memory, 0).expect("vkBindImageMemory");
        Img { image, memory }
    }
}

fn destroy(ctx: &harness::Context, i: Img) {
    // SAFETY: the device is idle; destroyed once.
    unsafe {
        ctx.device.destroy_image(i.image, None);
        ctx.device.free_memory(i.memory, None);
    }
}

fn layers_of(level: u32, layers: u32) -> vk::ImageSubresourceLayers {
    vk::ImageSubresourceLayers { aspect_mask: vk::ImageAspectFlags::COLOR, mip_level: level, base_array_layer: 0, layer_count: layers }
}

fn whole(levels: u32, layers: u32) -> vk::ImageSubresourceRange {
    vk::ImageSubresourceRange { aspect_mask: vk::ImageAspectFlags::COLOR, base_mip_level: 0, level_count: levels, base_array_layer: 0, layer_count: layers }
}

/// Records into a fresh command buffer, submits, waits.
fn run(ctx: &harness::Context, record: impl FnOnce(vk::CommandBuffer)) {
    // SAFETY: valid objects, destroyed after the fence signalled.
    unsafe {
        let d = &ctx.device;
        let pool = d.create_command_pool(&vk::CommandPoolCreateInfo::default().queue_family_index(0), None).unwrap();
        let info = vk::CommandBufferAllocateInfo::default().command_pool(pool).level(vk::CommandBufferLevel::PRIMARY).command_buffer_count(1);
        let cb = d.allocate_command_buffers(&info).unwrap()[0];
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        record(cb);
        d.end_command_buffer(cb).unwrap();
        let f = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        d.queue_submit(ctx.queues[0], &[vk::SubmitInfo::default().command_buffers(&[cb])], f).unwrap();
        d.wait_for_fences(&[f], true, u64::MAX).unwrap();
        d.destroy_fence(f, None);
        d.destroy_command_pool(pool, None);
    }
}

/// A barrier between transfers, with layout transitions (from, to) for the listed images.
fn barrier(ctx: &harness::Context, cb: vk::CommandBuffer, images: &[(vk::Image, vk::ImageLayout, vk::ImageLayout)], levels: u32, layers: u32) {
    let ib: Vec<vk::ImageMemoryBarrier> = images
        .iter()
        .map(|&(image, from, to)| {
            vk::ImageMemoryBarrier::default()
                .src_access_mask(vk::AccessFlags::TRANSFER_WRITE)
                .dst_access_mask(vk::AccessFlags::TRANSFER_READ | vk::AccessFlags::TRANSFER_WRITE)
                .old_layout(from)
                .new_layout(to)
                .src_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
                .dst_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
                .image(image)
                .subresource_range(whole(levels, layers))
        })
        .collect();
    let mb = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::TRANSFER_WRITE).dst_access_mask(vk::AccessFlags::TRANSFER_READ | vk::AccessFlags::TRANSFER_WRITE)];
    // SAFETY: recording command buffer.
    unsafe { ctx.device.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::TRANSFER, vk::DependencyFlags::empty(), &mb, &[], &ib) };
}

/// Host-visible buffer holding `bytes` (or zeros), and a way to read it back.
struct Buf {
    buffer: vk::Buffer,
    memory: vk::DeviceMemory,
    ptr: *mut u8,
    len: usize,
}

impl Buf {
    fn new(ctx: &harness::Context, bytes: &[u8]) -> Buf {
        let (buffer, memory, ptr) = ctx.host_buffer(bytes.len() as u64, BUF_USAGE);
        // SAFETY: the mapping covers the buffer.
        unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), ptr, bytes.len()) };
        Buf { buffer, memory, ptr, len: bytes.len() }
    }
    fn bytes(&self) -> Vec<u8> {
        // SAFETY: the mapping covers the buffer; the queue is idle.
        unsafe { std::slice::from_raw_parts(self.ptr, self.len) }.to_vec()
    }
    fn destroy(self, ctx: &harness::Context) {
        // SAFETY: idle device; destroyed once.
        unsafe {
            ctx.device.destroy_buffer(self.buffer, None);
            ctx.device.free_memory(self.memory, None);
        }
    }
}

/// The texel a clear of (1.0, 0.5, 0.25, 0.0) or (7, -3, 9, 11) writes, from the spec's rules.
fn clear_value(format: vk::Format) -> (vk::ClearColorValue, Vec<u8>) {
    let f = [1.0f32, 0.5, 0.25, 0.0];
    let i = [7i32, -3, 9, 11];
    let words = |w: &[u32]| w.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    match format {
        vk::Format::R8G8B8A8_UNORM => (vk::ClearColorValue { float32: f }, vec![255, 128, 64, 0]),
        vk::Format::R32_SFLOAT => (vk::ClearColorValue { float32: f }, words(&[f[0].to_bits()])),
        vk::Format::R32G32B32A32_SFLOAT => (vk::ClearColorValue { float32: f }, words(&f.map(f32::to_bits))),
        vk::Format::R32_UINT | vk::Format::R32_SINT => (vk::ClearColorValue { int32: i }, words(&[i[0] as u32])),
        _ => (vk::ClearColorValue { int32: i }, words(&i.map(|x| x as u32))),
    }
}

fn pattern(n: usize, seed: u32) -> Vec<u8> {
    (0..n as u32).map(|i| (i.wrapping_mul(2654435761).wrapping_add(seed) >> 13) as u8).collect()
}

/// (image type, extent, layers, levels)
const SHAPES: &[(vk::ImageType, [u32; 3], u32, u32)] = &[
    (vk::ImageType::TYPE_1D, [19, 1, 1], 1, 1),
    (vk::ImageType::TYPE_1D, [8, 1, 1], 3, 2),
    (vk::ImageType::TYPE_2D, [7, 5, 1], 1, 2),
    (vk::ImageType::TYPE_2D, [6, 4, 1], 3, 1),
    (vk::ImageType::TYPE_3D, [5, 4, 3], 1, 2),
];

/// The box a round trip uploads into level 0: offset 1 in every dimension the image has, the
/// rest of the extent, from a buffer with padded rows (the copy must honour bufferRowLength).
struct Upload {
    offset: [u32; 3],
    extent: [u32; 3],
    row_length: u32,
    texel: usize,
    image_extent: [u32; 3],
    layers: u32,
    bytes: Vec<u8>,
}

impl Upload {
    fn of(format: vk::Format, texel: usize, image_extent: [u32; 3], layers: u32) -> Upload {
        let offset: [u32; 3] = std::array::from_fn(|k| u32::from(image_extent[k] > 1));
        let extent: [u32; 3] = std::array::from_fn(|k| image_extent[k] - offset[k]);
        let row_length = extent[0] + 2;
        let bytes = pattern((row_length * extent[1] * extent[2] * layers) as usize * texel, format.as_raw() as u32);
        Upload { offset, extent, row_length, texel, image_extent, layers, bytes }
    }

    /// The CPU model after clear + upload: per level, layers × depth × height × width texels.
    fn model(&self, clear_texel: &[u8], levels: u32) -> Vec<Vec<u8>> {
        let (e, o, b, t) = (self.image_extent, self.offset, self.extent, self.texel);
        let mut model: Vec<Vec<u8>> = (0..levels)
            .map(|l| {
                let le = e.map(|x| (x >> l).max(1));
                clear_texel.repeat((le[0] * le[1] * le[2] * self.layers) as usize)
            })
            .collect();
        for layer in 0..self.layers {
            for z in 0..b[2] {
                for y in 0..b[1] {
                    let src = ((((layer * b[2] + z) * b[1] + y) * self.row_length) as usize) * t;
                    let dst = ((((layer * e[2] + o[2] + z) * e[1] + o[1] + y) * e[0] + o[0]) as usize) * t;
                    let n = b[0] as usize * t;
                    model[0][dst..dst + n].copy_from_slice(&self.bytes[src..src + n]);
                }
            }
        }
        model
    }
}

/// Clear everything, upload a box of level 0 at an offset (padded buffer rows), copy the
/// image to a second one, read every level of that back; compare with the CPU model.
fn round_trip(ctx: &harness::Context, format: vk::Format, texel: usize, shape: (vk::ImageType, [u32; 3], u32, u32), tiling: vk::ImageTiling) {
    let (ty, extent, layers, levels) = shape;
    let a = image(ctx, format, ty, extent, levels, layers, tiling, ALL_USAGE);
    let b = image(ctx, format, ty, extent, levels, layers, vk::ImageTiling::OPTIMAL, ALL_USAGE);
    let (clear, clear_texel) = clear_value(format);
    let level_extent = |l: u32| extent.map(|e| (e >> l).max(1));
    let upload = Upload::of(format, texel, extent, layers);
    let model = upload.model(&clear_texel, levels);
    let (off, bx, row_length, upload) = (upload.offset, upload.extent, upload.row_length, upload.bytes);
    let up = Buf::new(ctx, &upload);
    let total: usize = model.iter().map(Vec::len).sum();
    let down = Buf::new(ctx, &vec![0u8; total]);
    run(ctx, |cb| {
        let d = &ctx.device;
        let (undef, src, dst) = (vk::ImageLayout::UNDEFINED, vk::ImageLayout::TRANSFER_SRC_OPTIMAL, vk::ImageLayout::TRANSFER_DST_OPTIMAL);
        barrier(ctx, cb, &[(a.image, undef, dst), (b.image, undef, dst)], levels, layers);
        // SAFETY: recording; every region lies inside the objects.
        unsafe {
            d.cmd_clear_color_image(cb, a.image, dst, &clear, &[whole(levels, layers)]);
            barrier(ctx, cb, &[], levels, layers);
            let region = vk::BufferImageCopy {
                buffer_offset: 0,
                buffer_row_length: row_length,
                buffer_image_height: 0,
                image_subresource: layers_of(0, layers),
                image_offset: vk::Offset3D { x: off[0] as i32, y: off[1] as i32, z: off[2] as i32 },
                image_extent: vk::Extent3D { width: bx[0], height: bx[1], depth: bx[2] },
            };
            d.cmd_copy_buffer_to_image(cb, up.buffer, a.image, dst, &[region]);
            barrier(ctx, cb, &[(a.image, dst, src)], levels, layers);
            let copies: Vec<vk::ImageCopy> = (0..levels)
                .map(|l| {
                    let e = level_extent(l);
                    vk::ImageCopy {
                        src_subresource: layers_of(l, layers),
                        src_offset: vk::Offset3D::default(),
                        dst_subresource: layers_of(l, layers),
                        dst_offset: vk::Offset3D::default(),
                        extent: vk::Extent3D { width: e[0], height: e[1], depth: e[2] },
                    }
                })
                .collect();
            d.cmd_copy_image(cb, a.image, src, b.image, dst, &copies);
            barrier(ctx, cb, &[(b.image, dst, src)], levels, layers);
            let mut at = 0u64;
            let back: Vec<vk::BufferImageCopy> = (0..levels)
                .map(|l| {
                    let e = level_extent(l);
                    let r = vk::BufferImageCopy {
                        buffer_offset: at,
                        buffer_row_length: 0,
                        buffer_image_height: 0,
                        image_subresource: layers_of(l, layers),
                        image_offset: vk::Offset3D::default(),
                        image_extent: vk::Extent3D { width: e[0], height: e[1], depth: e[2] },
                    };
                    at += model[l as usize].len() as u64;
                    r
                })
                .collect();
            d.cmd_copy_image_to_buffer(cb, b.image, src, down.buffer, &back);
        }
    });
    assert_eq!(down.bytes(), model.concat(), "{format:?} {ty:?} {extent:?} x{layers} layers, {levels} levels, {tiling:?}");
    up.destroy(ctx);
    down.destroy(ctx);
    destroy(ctx, a);
    destroy(ctx, b);
}

#[test]
fn clear_and_copy_round_trips_every_format_shape_and_tiling() {
    let ctx = harness::context();
    for &(format, texel) in FORMATS {
        for &shape in SHAPES {
            for tiling in [vk::ImageTiling::OPTIMAL, vk::ImageTiling::LINEAR] {
                round_trip(&ctx, format, texel, shape, tiling);
            }
        }
    }
    ctx.finish();
}

#[test]
fn format_queries_match_what_works() {
    let ctx = harness::context();
    let i = &ctx.instance;
    let want = vk::FormatFeatureFlags::STORAGE_IMAGE | vk::FormatFeatureFlags::TRANSFER_SRC | vk::FormatFeatureFlags::TRANSFER_DST;
    // SAFETY: plain queries on a live physical device.
    unsafe {
        for &(format, _) in FORMATS {
            // Image atomics run on the 32-bit integer formats only.
            let atomic = matches!(format, vk::Format::R32_UINT | vk::Format::R32_SINT);
            let want = if atomic { want | vk::FormatFeatureFlags::STORAGE_IMAGE_ATOMIC } else { want };
            let p = i.get_physical_device_format_properties(ctx.physical, format);
            assert_eq!((p.optimal_tiling_features, p.linear_tiling_features), (want, want), "{format:?}");
            let mut p3 = vk::FormatProperties3::default();
            let mut p2 = vk::FormatProperties2::default().push_next(&mut p3);
            i.get_physical_device_format_properties2(ctx.physical, format, &mut p2);
            assert_eq!(p2.format_properties.optimal_tiling_features, want);
            assert!(p3.optimal_tiling_features.contains(vk::FormatFeatureFlags2::STORAGE_IMAGE | vk::FormatFeatureFlags2::STORAGE_WRITE_WITHOUT_FORMAT));
            assert!(!p3.optimal_tiling_features.contains(vk::FormatFeatureFlags2::SAMPLED_IMAGE));
            for (ty, max) in [(vk::ImageType::TYPE_1D, [4096, 1, 1]), (vk::ImageType::TYPE_2D, [4096, 4096, 1]), (vk::ImageType::TYPE_3D, [256, 256, 256])] {
                for tiling in [vk::ImageTiling::OPTIMAL, vk::ImageTiling::LINEAR] {
                    let r = i.get_physical_device_image_format_properties(ctx.physical, format, ty, tiling, ALL_USAGE, vk::ImageCreateFlags::empty()).unwrap();
                    assert_eq!([r.max_extent.width, r.max_extent.height, r.max_extent.depth], max, "{format:?} {ty:?}");
                    assert_eq!(r.sample_counts, vk::SampleCountFlags::TYPE_1);
                    assert_eq!(r.max_array_layers, if ty == vk::ImageType::TYPE_3D { 1 } else { 256 });
                    let info = vk::PhysicalDeviceImageFormatInfo2::default().format(format).ty(ty).tiling(tiling).usage(vk::ImageUsageFlags::STORAGE);
                    let mut out = vk::ImageFormatProperties2::default();
                    i.get_physical_device_image_format_properties2(ctx.physical, &info, &mut out).unwrap();
                    assert_eq!(format!("{:?}", out.image_format_properties), format!("{r:?}"));
                }
                // Sampling, attachments and sparse/mutable flags are not offered.
                for usage in [vk::ImageUsageFlags::SAMPLED, vk::ImageUsageFlags::COLOR_ATTACHMENT, vk::ImageUsageFlags::STORAGE | vk::ImageUsageFlags::SAMPLED] {
                    let r = i.get_physical_device_image_format_properties(ctx.physical, format, ty, vk::ImageTiling::OPTIMAL, usage, vk::ImageCreateFlags::empty());
                    assert_eq!(r.err(), Some(vk::Result::ERROR_FORMAT_NOT_SUPPORTED), "{format:?} {usage:?}");
                }
                let r = i.get_physical_device_image_format_properties(ctx.physical, format, ty, vk::ImageTiling::OPTIMAL, ALL_USAGE, vk::ImageCreateFlags::MUTABLE_FORMAT);
                assert_eq!(r.err(), Some(vk::Result::ERROR_FORMAT_NOT_SUPPORTED));
            }
        }
        // Formats without image support: no image features, image queries refused; vertex
        // formats keep their acceleration-structure feature.
        for format in [vk::Format::R16_UINT, vk::Format::R8G8B8A8_SRGB, vk::Format::D32_SFLOAT, vk::Format::R32G32_SFLOAT] {
            let p = i.get_physical_device_format_properties(ctx.physical, format);
            assert!(p.optimal_tiling_features.is_empty() && p.linear_tiling_features.is_empty(), "{format:?}");
            let r = i.get_physical_device_image_format_properties(ctx.physical, format, vk::ImageType::TYPE_2D, vk::ImageTiling::OPTIMAL, vk::ImageUsageFlags::TRANSFER_DST, vk::ImageCreateFlags::empty());
            assert_eq!(r.err(), Some(vk::Result::ERROR_FORMAT_NOT_SUPPORTED), "{format:?}");
        }
        let v = i.get_physical_device_format_properties(ctx.physical, vk::Format::R32G32_SFLOAT);
        assert_eq!(v.buffer_features, vk::FormatFeatureFlags::ACCELERATION_STRUCTURE_VERTEX_BUFFER_KHR);
    }
    ctx.finish();
}

#[test]
fn linear_subresource_layout_is_where_the_texels_are() {
    let ctx = harness::context();
    let (w, h, layers, levels) = (6u32, 4u32, 2u32, 2u32);
    let img = image(&ctx, vk::Format::R32_UINT, vk::ImageType::TYPE_2D, [w, h, 1], levels, layers, vk::ImageTiling::LINEAR, ALL_USAGE);
    // SAFETY: linear image, plain queries; the memory is host-visible and mapped while idle.
    let ptr = unsafe { ctx.device.map_memory(img.memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()) }.unwrap() as *mut u8;
    let mut want = Vec::new();
    for level in 0..levels {
        let (lw, lh) = ((w >> level).max(1), (h >> level).max(1));
        for layer in 0..layers {
            let sub = vk::ImageSubresource { aspect_mask: vk::ImageAspectFlags::COLOR, mip_level: level, array_layer: layer };
            // SAFETY: plain query on a linear image.
            let l = unsafe { ctx.device.get_image_subresource_layout(img.image, sub) };
            assert!(l.row_pitch >= lw as u64 * 4 && l.size >= l.row_pitch * lh as u64, "{l:?}");
            for y in 0..lh {
                for x in 0..lw {
                    let v = level * 1_000_000 + layer * 10_000 + y * 100 + x;
                    let at = l.offset + y as u64 * l.row_pitch + x as u64 * 4;
                    // SAFETY: inside the mapped allocation (the layout says so; the size check above).
                    unsafe { std::ptr::copy_nonoverlapping(v.to_le_bytes().as_ptr(), ptr.add(at as usize), 4) };
                    want.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
    }
    // SAFETY: mapped above.
    unsafe { ctx.device.unmap_memory(img.memory) };
    let down = Buf::new(&ctx, &vec![0u8; want.len()]);
    run(&ctx, |cb| {
        barrier(&ctx, cb, &[(img.image, vk::ImageLayout::PREINITIALIZED, vk::ImageLayout::TRANSFER_SRC_OPTIMAL)], levels, layers);
        let mut at = 0;
        let regions: Vec<vk::BufferImageCopy> = (0..levels)
            .map(|l| {
                let (lw, lh) = ((w >> l).max(1), (h >> l).max(1));
                let r = vk::BufferImageCopy {
                    buffer_offset: at,
                    image_subresource: layers_of(l, layers),
                    image_extent: vk::Extent3D { width: lw, height: lh, depth: 1 },
                    ..Default::default()
                };
                at += (lw * lh * layers * 4) as u64;
                r
            })
            .collect();
        // SAFETY: recording; regions inside both objects.
        unsafe { ctx.device.cmd_copy_image_to_buffer(cb, img.image, vk::ImageLayout::TRANSFER_SRC_OPTIMAL, down.buffer, &regions) };
    });
    assert_eq!(down.bytes(), want);
    down.destroy(&ctx);
    destroy(&ctx, img);
    ctx.finish();
}

#[test]
fn storage_image_views_and_descriptors() {
    let ctx = harness::context();
    let d = &ctx.device;
    let img = image(&ctx, vk::Format::R32G32B32A32_SFLOAT, vk::ImageType::TYPE_2D, [8, 8, 1], 2, 4, vk::ImageTiling::OPTIMAL, ALL_USAGE);
    // SAFETY: valid create infos; objects destroyed below.
    unsafe {
        let view_info = |ty, base_layer, layers, level| {
            vk::ImageViewCreateInfo::default()
                .image(img.image)
                .view_type(ty)
                .format(vk::Format::R32G32B32A32_SFLOAT)
                .subresource_range(vk::ImageSubresourceRange { aspect_mask: vk::ImageAspectFlags::COLOR, base_mip_level: level, level_count: 1, base_array_layer: base_layer, layer_count: layers })
        };
        let v2d = d.create_image_view(&view_info(vk::ImageViewType::TYPE_2D, 2, 1, 1), None).unwrap();
        let varr = d.create_image_view(&view_info(vk::ImageViewType::TYPE_2D_ARRAY, 0, 4, 0), None).unwrap();
        let bindings = [vk::DescriptorSetLayoutBinding::default()
            .binding(0)
            .descriptor_type(vk::DescriptorType::STORAGE_IMAGE)
            .descriptor_count(2)
            .stage_flags(vk::ShaderStageFlags::COMPUTE)];
        let layout = d.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings), None).unwrap();
        let sizes = [vk::DescriptorPoolSize { ty: vk::DescriptorType::STORAGE_IMAGE, descriptor_count: 4 }];
        let pool = d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(2).pool_sizes(&sizes), None).unwrap();
        let sets = d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&[layout, layout])).unwrap();
        let infos = [
            vk::DescriptorImageInfo { sampler: vk::Sampler::null(), image_view: v2d, image_layout: vk::ImageLayout::GENERAL },
            vk::DescriptorImageInfo { sampler: vk::Sampler::null(), image_view: varr, image_layout: vk::ImageLayout::GENERAL },
        ];
        let write = vk::WriteDescriptorSet::default().dst_set(sets[0]).dst_binding(0).descriptor_type(vk::DescriptorType::STORAGE_IMAGE).image_info(&infos);
        let copy = vk::CopyDescriptorSet::default().src_set(sets[0]).dst_set(sets[1]).descriptor_count(2);
        d.update_descriptor_sets(&[write], &[]);
        d.update_descriptor_sets(&[], &[copy]);
        d.destroy_descriptor_pool(pool, None);
        d.destroy_descriptor_set_layout(layout, None);
        d.destroy_image_view(v2d, None);
        d.destroy_image_view(varr, None);
    }
    let log = harness::diagnostics();
    assert!(!log.contains("VUID-VkWriteDescriptorSet"), "{log}");
    destroy(&ctx, img);
    ctx.finish();
}

#[test]
fn invalid_use_is_reported_and_not_executed() {
    let ctx = harness::Context::new(harness::Options { validation: false, ..Default::default() });
    let d = &ctx.device;
    let info = |format, usage| {
        vk::ImageCreateInfo::default()
            .image_type(vk::ImageType::TYPE_2D)
            .format(format)
            .extent(vk::Extent3D { width: 4, height: 4, depth: 1 })
            .mip_levels(1)
            .array_layers(1)
            .samples(vk::SampleCountFlags::TYPE_1)
            .usage(usage)
    };
    // SAFETY: deliberately invalid calls that Arbor must reject without crashing.
    unsafe {
        assert_eq!(d.create_image(&info(vk::Format::R16_UINT, vk::ImageUsageFlags::STORAGE), None), Err(vk::Result::ERROR_VALIDATION_FAILED_EXT));
        assert_eq!(d.create_image(&info(vk::Format::R32_UINT, vk::ImageUsageFlags::SAMPLED), None), Err(vk::Result::ERROR_VALIDATION_FAILED_EXT));
        assert_eq!(d.create_image(&info(vk::Format::R32_UINT, vk::ImageUsageFlags::STORAGE).mip_levels(4), None), Err(vk::Result::ERROR_VALIDATION_FAILED_EXT));
    }
    // An image without TRANSFER_DST: clear and upload are dropped; an out-of-range upload too.
    let src = image(&ctx, vk::Format::R32_UINT, vk::ImageType::TYPE_2D, [4, 4, 1], 1, 1, vk::ImageTiling::LINEAR, vk::ImageUsageFlags::TRANSFER_SRC);
    let dst = image(&ctx, vk::Format::R32_UINT, vk::ImageType::TYPE_2D, [4, 4, 1], 1, 1, vk::ImageTiling::LINEAR, ALL_USAGE);
    let up = Buf::new(&ctx, &[0xABu8; 256]);
    let down = Buf::new(&ctx, &[0x5Au8; 64]);
    // SAFETY: deliberately invalid view creation.
    unsafe {
        let v = vk::ImageViewCreateInfo::default()
            .image(dst.image)
            .view_type(vk::ImageViewType::TYPE_2D)
            .format(vk::Format::R32_SFLOAT)
            .subresource_range(whole(1, 1));
        assert_eq!(d.create_image_view(&v, None), Err(vk::Result::ERROR_VALIDATION_FAILED_EXT));
    }
    // SAFETY: valid create info; the image stays unbound on purpose.
    let unbound = unsafe { d.create_image(&info(vk::Format::R32_UINT, ALL_USAGE), None) }.unwrap();
    run(&ctx, |cb| {
        let clear = vk::ClearColorValue { uint32: [1, 2, 3, 4] };
        let full = vk::BufferImageCopy { image_subresource: layers_of(0, 1), image_extent: vk::Extent3D { width: 4, height: 4, depth: 1 }, ..Default::default() };
        let outside = vk::BufferImageCopy { image_offset: vk::Offset3D { x: 2, y: 0, z: 0 }, ..full };
        // SAFETY: recording; the invalid commands are what is tested.
        unsafe {
            d.cmd_clear_color_image(cb, src.image, vk::ImageLayout::GENERAL, &clear, &[whole(1, 1)]);
            d.cmd_copy_buffer_to_image(cb, up.buffer, src.image, vk::ImageLayout::GENERAL, &[full]);
            d.cmd_copy_buffer_to_image(cb, up.buffer, dst.image, vk::ImageLayout::GENERAL, &[outside]);
            d.cmd_copy_image_to_buffer(cb, dst.image, vk::ImageLayout::GENERAL, down.buffer, &[vk::BufferImageCopy { image_offset: vk::Offset3D { x: 0, y: 3, z: 0 }, ..full }]);
            let r = vk::ImageCopy { src_subresource: layers_of(1, 1), dst_subresource: layers_of(0, 1), extent: vk::Extent3D { width: 1, height: 1, depth: 1 }, ..Default::default() };
            d.cmd_copy_image(cb, src.image, vk::ImageLayout::GENERAL, dst.image, vk::ImageLayout::GENERAL, &[r]);
            d.cmd_copy_image_to_buffer(cb, unbound, vk::ImageLayout::GENERAL, down.buffer, &[full]);
        }
    });
    assert!(down.bytes().iter().all(|&b| b == 0x5A), "an invalid copy was executed");
    let log = harness::diagnostics();
    for vuid in [
        "VUID-VkImageCreateInfo-imageCreateMaxMipLevels-02251",
        "VUID-VkImageCreateInfo-mipLevels-00958",
        "VUID-VkImageViewCreateInfo-image-01762",
        "VUID-vkCmdClearColorImage-image-00002",
        "VUID-vkCmdCopyBufferToImage-dstImage-00177",
        "VUID-vkCmdCopyBufferToImage-pRegions-06218",
        "VUID-vkCmdCopyImageToBuffer-pRegions-06221",
        "VUID-vkCmdCopyImage-srcSubresource-07967",
        "VUID-vkCmdCopyImageToBuffer-srcImage-07966",
    ] {
        assert!(log.contains(vuid), "{vuid} not reported; diagnostics:\n{log}");
    }
    assert!(log.contains("R16_UINT"), "the unsupported format is named:\n{log}");
    // SAFETY: idle device; destroyed once.
    unsafe { d.destroy_image(unbound, None) };
    up.destroy(&ctx);
    down.destroy(&ctx);
    destroy(&ctx, src);
    destroy(&ctx, dst);
    ctx.finish();
}

#[test]
fn copy_commands2_round_trip() {
    let ctx = harness::context();
    let (w, h, layers) = (5u32, 3u32, 2u32);
    let a = image(&ctx, vk::Format::R32G32B32A32_SINT, vk::ImageType::TYPE_2D, [w, h, 1], 1, layers, vk::ImageTiling::OPTIMAL, ALL_USAGE);
    let b = image(&ctx, vk::Format::R32G32B32A32_UINT, vk::ImageType::TYPE_2D, [w, h, 1], 1, layers, vk::ImageTiling::OPTIMAL, ALL_USAGE);
    let data = pattern((w * h * layers * 16) as usize, 99);
    let up = Buf::new(&ctx, &data);
    let down = Buf::new(&ctx, &vec![0u8; data.len()]);
    let extent = vk::Extent3D { width: w, height: h, depth: 1 };
    run(&ctx, |cb| {
        let (undef, src, dst) = (vk::ImageLayout::UNDEFINED, vk::ImageLayout::TRANSFER_SRC_OPTIMAL, vk::ImageLayout::TRANSFER_DST_OPTIMAL);
        let region = [vk::BufferImageCopy2::default().image_subresource(layers_of(0, layers)).image_extent(extent)];
        let copy = [vk::ImageCopy2::default().src_subresource(layers_of(0, layers)).dst_subresource(layers_of(0, layers)).extent(extent)];
        barrier(&ctx, cb, &[(a.image, undef, dst), (b.image, undef, dst)], 1, layers);
        // SAFETY: recording; regions inside the objects.
        unsafe {
            let d = ash::khr::copy_commands2::Device::new(&ctx.instance, &ctx.device);
            d.cmd_copy_buffer_to_image2(cb, &vk::CopyBufferToImageInfo2::default().src_buffer(up.buffer).dst_image(a.image).dst_image_layout(dst).regions(&region));
            barrier(&ctx, cb, &[(a.image, dst, src)], 1, layers);
            // Size-compatible formats copy bit for bit.
            d.cmd_copy_image2(cb, &vk::CopyImageInfo2::default().src_image(a.image).src_image_layout(src).dst_image(b.image).dst_image_layout(dst).regions(&copy));
            barrier(&ctx, cb, &[(b.image, dst, src)], 1, layers);
            d.cmd_copy_image_to_buffer2(cb, &vk::CopyImageToBufferInfo2::default().src_image(b.image).src_image_layout(src).dst_buffer(down.buffer).regions(&region));
        }
    });
    assert_eq!(down.bytes(), data);
    up.destroy(&ctx);
    down.destroy(&ctx);
    destroy(&ctx, a);
    destroy(&ctx, b);
    ctx.finish();
}

//! Running a compute [`Job`](super::compute::Job): every Vulkan object it needs is created,
//! used once and destroyed here, so a test reads as data in, buffers out. A storage-image
//! binding is an image plus a staging buffer: texels are copied in before the dispatch and out
//! after it, so the staging buffer is what the job returns for that binding.
use ash::vk;

use super::compute::{Binding, Gpu, Job, JobError, Size};

struct Buffer {
    buffer: vk::Buffer,
    memory: vk::DeviceMemory,
    ptr: *mut u8,
    size: u64,
}

fn buffer(gpu: &Gpu, data: &[u8], usage: vk::BufferUsageFlags) -> Buffer {
    let size = data.len().max(16) as u64;
    let d = &gpu.device;
    // SAFETY: valid create infos; destroyed by `run`.
    unsafe {
        let usage = usage | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS;
        let buffer = d.create_buffer(&vk::BufferCreateInfo::default().size(size).usage(usage), None).unwrap();
        let req = d.get_buffer_memory_requirements(buffer);
        let mut flags = vk::MemoryAllocateFlagsInfo::default().flags(vk::MemoryAllocateFlags::DEVICE_ADDRESS);
        let ai = vk::MemoryAllocateInfo::default().allocation_size(req.size).memory_type_index(gpu_memory_type(gpu, req.memory_type_bits)).push_next(&mut flags);
        let memory = d.allocate_memory(&ai, None).unwrap();
        d.bind_buffer_memory(buffer, memory, 0).unwrap();
        let ptr = d.map_memory(memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()).unwrap() as *mut u8;
        std::ptr::write_bytes(ptr, 0, size as usize);
        std::ptr::copy_nonoverlapping(data.as_ptr(), ptr, data.len());
        Buffer { buffer, memory, ptr, size }
    }
}

/// A storage-image binding's image, its memory and its view.
struct Image {
    image: vk::Image,
    memory: vk::DeviceMemory,
    view: vk::ImageView,
    extent: [u32; 2],
}

/// A 2D single-level storage image (optimal tiling) with a view of the whole of it.
pub fn storage_image(gpu: &Gpu, format: vk::Format, extent: [u32; 2]) -> (vk::Image, vk::DeviceMemory, vk::ImageView) {
    let d = &gpu.device;
    let usage = vk::ImageUsageFlags::STORAGE | vk::ImageUsageFlags::TRANSFER_SRC | vk::ImageUsageFlags::TRANSFER_DST;
    let info = vk::ImageCreateInfo::default()
        .image_type(vk::ImageType::TYPE_2D)
        .format(format)
        .extent(vk::Extent3D { width: extent[0], height: extent[1], depth: 1 })
        .mip_levels(1)
        .array_layers(1)
        .samples(vk::SampleCountFlags::TYPE_1)
        .tiling(vk::ImageTiling::OPTIMAL)
        .usage(usage)
        .initial_layout(vk::ImageLayout::UNDEFINED);
    // SAFETY: valid create infos; the caller destroys all three.
    unsafe {
        let image = d.create_image(&info, None).unwrap();
        let req = d.get_image_memory_requirements(image);
        let ai = vk::MemoryAllocateInfo::default().allocation_size(req.size).memory_type_index(gpu_memory_type(gpu, req.memory_type_bits));
        let memory = d.allocate_memory(&ai, None).unwrap();
        d.bind_image_memory(image, memory, 0).unwrap();
        let vi = vk::ImageViewCreateInfo::default().image(image).view_type(vk::ImageViewType::TYPE_2D).format(format).subresource_range(color_range());
        let view = d.create_image_view(&vi, None).unwrap();
        (image, memory, view)
    }
}

fn color_range() -> vk::ImageSubresourceRange {
    vk::ImageSubresourceRange { aspect_mask: vk::ImageAspectFlags::COLOR, base_mip_level: 0, level_count: 1, base_array_layer: 0, layer_count: 1 }
}

/// A layout transition of a whole single-level color image.
pub fn image_barrier(image: vk::Image, from: (vk::ImageLayout, vk::AccessFlags), to: (vk::ImageLayout, vk::AccessFlags)) -> vk::ImageMemoryBarrier<'static> {
    vk::ImageMemoryBarrier::default()
        .old_layout(from.0)
        .src_access_mask(from.1)
        .new_layout(to.0)
        .dst_access_mask(to.1)
        .src_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
        .dst_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
        .image(image)
        .subresource_range(color_range())
}

/// The buffer ↔ image copy region of a whole, tightly packed 2D image.
pub fn whole_image_copy(extent: [u32; 2]) -> vk::BufferImageCopy {
    vk::BufferImageCopy {
        buffer_offset: 0,
        buffer_row_length: 0,
        buffer_image_height: 0,
        image_subresource: vk::ImageSubresourceLayers { aspect_mask: vk::ImageAspectFlags::COLOR, mip_level: 0, base_array_layer: 0, layer_count: 1 },
        image_offset: vk::Offset3D::default(),
        image_extent: vk::Extent3D { width: extent[0], height: extent[1], depth: 1 },
    }
}

fn gpu_memory_type(gpu: &Gpu, bits: u32) -> u32 {
    let want = vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT;
    // SAFETY: plain query.
    let mp = unsafe { gpu.instance.get_physical_device_memory_properties(gpu.physical) };
    (0..mp.memory_type_count).find(|&i| bits & (1 << i) != 0 && mp.memory_types[i as usize].property_flags.contains(want)).expect("host-visible memory")
}

/// The descriptor objects and the pipeline of a job.
struct Objects {
    set_layout: vk::DescriptorSetLayout,
    pool: vk::DescriptorPool,
    set: vk::DescriptorSet,
    layout: vk::PipelineLayout,
    module: vk::ShaderModule,
    pipeline: vk::Pipeline,
    /// Buffer views of the texel-buffer bindings (null for the others).
    views: Vec<vk::BufferView>,
}

fn objects(gpu: &Gpu, job: &Job, buffers: &[Buffer], images: &[Option<Image>]) -> Result<Objects, JobError> {
    let d = &gpu.device;
    let lb: Vec<_> = job
        .bindings
        .iter()
        .enumerate()
        .map(|(i, b)| vk::DescriptorSetLayoutBinding::default().binding(i as u32).descriptor_type(b.kind).descriptor_count(b.elements).stage_flags(vk::ShaderStageFlags::COMPUTE))
        .collect();
    // SAFETY: valid create infos; every object is destroyed by `destroy`.
    unsafe {
        let set_layout = d.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&lb), None).unwrap();
        let sizes: Vec<_> = job.bindings.iter().map(|b| vk::DescriptorPoolSize { ty: b.kind, descriptor_count: b.elements }).collect();
        let pool = if sizes.is_empty() {
            vk::DescriptorPool::null()
        } else {
            d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(1).pool_sizes(&sizes), None).unwrap()
        };
        let set = if sizes.is_empty() {
            vk::DescriptorSet::null()
        } else {
            let layouts = [set_layout];
            d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&layouts)).unwrap()[0]
        };
        let infos: Vec<Vec<vk::DescriptorBufferInfo>> = job.bindings.iter().zip(buffers).map(|(b, buf)| buffer_infos(b, buf.buffer)).collect();
        let image_infos: Vec<[vk::DescriptorImageInfo; 1]> = images
            .iter()
            .map(|i| [vk::DescriptorImageInfo { sampler: vk::Sampler::null(), image_view: i.as_ref().map_or(vk::ImageView::null(), |i| i.view), image_layout: vk::ImageLayout::GENERAL }])
            .collect();
        let view_infos: Vec<Vec<vk::BufferView>> = job.bindings.iter().zip(buffers).map(|(b, buf)| texel_views(gpu, b, buf.buffer)).collect();
        let views: Vec<vk::BufferView> = view_infos.iter().flatten().copied().collect();
        let writes: Vec<_> = job
            .bindings
            .iter()
            .zip(infos.iter().zip(&image_infos))
            .zip(&view_infos)
            .enumerate()
            .map(|(i, ((b, (info, image_info)), view))| {
                let w = vk::WriteDescriptorSet::default().dst_set(set).dst_binding(i as u32).descriptor_type(b.kind);
                if b.texel.is_some() {
                    w.texel_buffer_view(view)
                } else if b.image.is_some() {
                    w.image_info(image_info)
                } else {
                    w.buffer_info(info)
                }
            })
            .collect();
        d.update_descriptor_sets(&writes, &[]);
        let push_size = (job.push.len() as u32).next_multiple_of(4);
        let ranges = [vk::PushConstantRange { stage_flags: vk::ShaderStageFlags::COMPUTE, offset: 0, size: push_size }];
        let set_layouts = [set_layout];
        let mut lci = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
        if push_size > 0 {
            lci = lci.push_constant_ranges(&ranges);
        }
        let layout = d.create_pipeline_layout(&lci, None).unwrap();
        let module = d.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&job.spirv), None).unwrap();
        let mut data = Vec::new();
        let mut entries = Vec::new();
        for (id, bytes) in &job.spec {
            entries.push(vk::SpecializationMapEntry { constant_id: *id, offset: data.len() as u32, size: bytes.len() });
            data.extend_from_slice(bytes);
        }
        let spec = vk::SpecializationInfo::default().map_entries(&entries).data(&data);
        let name = c"main";
        let stage = vk::PipelineShaderStageCreateInfo::default().stage(vk::ShaderStageFlags::COMPUTE).module(module).name(name).specialization_info(&spec);
        let flags = if matches!(job.size, Size::Base { .. }) { vk::PipelineCreateFlags::DISPATCH_BASE } else { vk::PipelineCreateFlags::empty() };
        let ci = [vk::ComputePipelineCreateInfo::default().flags(flags).stage(stage).layout(layout)];
        let o = |pipeline| Objects { set_layout, pool, set, layout, module, pipeline, views: views.clone() };
        match d.create_compute_pipelines(vk::PipelineCache::null(), &ci, None) {
            Ok(p) => Ok(o(p[0])),
            Err((_, e)) => {
                destroy(gpu, &o(vk::Pipeline::null()));
                Err(JobError::Pipeline(e))
            }
        }
    }
}

/// The buffer views of a texel-buffer binding: the whole buffer, or one per array element
/// over its part; none for other bindings.
fn texel_views(gpu: &Gpu, b: &Binding, buffer: vk::Buffer) -> Vec<vk::BufferView> {
    let Some(format) = b.texel else { return Vec::new() };
    let part = (b.data.len() / b.elements as usize) as u64;
    (0..b.elements as u64)
        .map(|e| {
            let range = if b.elements == 1 { vk::WHOLE_SIZE } else { part };
            let ci = vk::BufferViewCreateInfo::default().buffer(buffer).format(format).offset(e * part).range(range);
            // SAFETY: a live buffer with texel-buffer usage; the view is destroyed with the objects.
            unsafe { gpu.device.create_buffer_view(&ci, None) }.expect("vkCreateBufferView")
        })
        .collect()
}

/// The descriptors of one buffer binding: the whole range, or one part per array element.
fn buffer_infos(b: &Binding, buffer: vk::Buffer) -> Vec<vk::DescriptorBufferInfo> {
    if b.elements == 1 {
        return vec![vk::DescriptorBufferInfo { buffer, offset: 0, range: b.range }];
    }
    let part = (b.data.len() / b.elements as usize) as u64;
    (0..b.elements as u64).map(|e| vk::DescriptorBufferInfo { buffer, offset: e * part, range: if b.range == vk::WHOLE_SIZE { part } else { b.range } }).collect()
}

fn destroy(gpu: &Gpu, o: &Objects) {
    let d = &gpu.device;
    // SAFETY: the objects are idle (the fence was waited on) and not used again.
    unsafe {
        d.destroy_pipeline(o.pipeline, None);
        d.destroy_shader_module(o.module, None);
        d.destroy_pipeline_layout(o.layout, None);
        d.destroy_descriptor_pool(o.pool, None);
        d.destroy_descriptor_set_layout(o.set_layout, None);
        for &v in &o.views {
            d.destroy_buffer_view(v, None);
        }
    }
}

/// Record and submit the dispatch; wait for its fence.
fn submit(gpu: &Gpu, job: &Job, o: &Objects, indirect: &Buffer, buffers: &[Buffer], images: &[Option<Image>]) -> Result<(), JobError> {
    let d = &gpu.device;
    // SAFETY: valid objects; the command pool and fence are destroyed before returning.
    unsafe {
        let cmd_pool = d.create_command_pool(&vk::CommandPoolCreateInfo::default().queue_family_index(0), None).unwrap();
        let cb = d.allocate_command_buffers(&vk::CommandBufferAllocateInfo::default().command_pool(cmd_pool).command_buffer_count(1)).unwrap()[0];
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        let staged = || images.iter().zip(buffers).filter_map(|(i, b)| Some((i.as_ref()?, b)));
        for (image, staging) in staged() {
            let (none, dst, general) = (vk::AccessFlags::empty(), vk::AccessFlags::TRANSFER_WRITE, vk::AccessFlags::SHADER_READ | vk::AccessFlags::SHADER_WRITE);
            let to_dst = [image_barrier(image.image, (vk::ImageLayout::UNDEFINED, none), (vk::ImageLayout::TRANSFER_DST_OPTIMAL, dst))];
            d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TOP_OF_PIPE, vk::PipelineStageFlags::TRANSFER, vk::DependencyFlags::empty(), &[], &[], &to_dst);
            d.cmd_copy_buffer_to_image(cb, staging.buffer, image.image, vk::ImageLayout::TRANSFER_DST_OPTIMAL, &[whole_image_copy(image.extent)]);
            let to_general = [image_barrier(image.image, (vk::ImageLayout::TRANSFER_DST_OPTIMAL, dst), (vk::ImageLayout::GENERAL, general))];
            d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::COMPUTE_SHADER, vk::DependencyFlags::empty(), &[], &[], &to_general);
        }
        d.cmd_bind_pipeline(cb, vk::PipelineBindPoint::COMPUTE, o.pipeline);
        if o.set != vk::DescriptorSet::null() {
            let dynamic: Vec<u32> = job.bindings.iter().filter(|b| b.kind == vk::DescriptorType::UNIFORM_BUFFER_DYNAMIC || b.kind == vk::DescriptorType::STORAGE_BUFFER_DYNAMIC).flat_map(|b| vec![b.dynamic_offset; b.elements as usize]).collect();
            d.cmd_bind_descriptor_sets(cb, vk::PipelineBindPoint::COMPUTE, o.layout, 0, &[o.set], &dynamic);
        }
        if !job.push.is_empty() {
            let mut push = job.push.clone();
            push.resize(push.len().next_multiple_of(4), 0);
            d.cmd_push_constants(cb, o.layout, vk::ShaderStageFlags::COMPUTE, 0, &push);
        }
        match job.size {
            Size::Direct([x, y, z]) => d.cmd_dispatch(cb, x, y, z),
            Size::Base { base, groups } => d.cmd_dispatch_base(cb, base[0], base[1], base[2], groups[0], groups[1], groups[2]),
            Size::Indirect(_) => d.cmd_dispatch_indirect(cb, indirect.buffer, 16),
        }
        for (image, staging) in staged() {
            let general = (vk::ImageLayout::GENERAL, vk::AccessFlags::SHADER_WRITE);
            let to_src = [image_barrier(image.image, general, (vk::ImageLayout::TRANSFER_SRC_OPTIMAL, vk::AccessFlags::TRANSFER_READ))];
            d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::COMPUTE_SHADER, vk::PipelineStageFlags::TRANSFER, vk::DependencyFlags::empty(), &[], &[], &to_src);
            d.cmd_copy_image_to_buffer(cb, image.image, vk::ImageLayout::TRANSFER_SRC_OPTIMAL, staging.buffer, &[whole_image_copy(image.extent)]);
        }
        let barrier = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE).dst_access_mask(vk::AccessFlags::HOST_READ)];
        let from = vk::PipelineStageFlags::COMPUTE_SHADER | vk::PipelineStageFlags::TRANSFER;
        d.cmd_pipeline_barrier(cb, from, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &barrier, &[], &[]);
        d.end_command_buffer(cb).unwrap();
        let fence = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
        let cbs = [cb];
        let submitted = d.queue_submit(gpu.queue, &[vk::SubmitInfo::default().command_buffers(&cbs)], fence);
        let r = submitted.and_then(|_| d.wait_for_fences(&[fence], true, 60_000_000_000));
        // A lost device still signals the fence of a submission it accepted; make sure it did,
        // so nothing is pending when the objects are destroyed.
        if submitted.is_ok() && r.is_err() {
            let _ = d.wait_for_fences(&[fence], true, 60_000_000_000);
        }
        d.destroy_fence(fence, None);
        d.destroy_command_pool(cmd_pool, None);
        r.map_err(JobError::Submit)
    }
}

/// Run `job` on `gpu`; returns every binding's bytes afterwards.
pub fn run(gpu: &Gpu, job: &Job) -> Result<Vec<Vec<u8>>, JobError> {
    let usage = vk::BufferUsageFlags::STORAGE_BUFFER
        | vk::BufferUsageFlags::UNIFORM_BUFFER
        | vk::BufferUsageFlags::UNIFORM_TEXEL_BUFFER
        | vk::BufferUsageFlags::STORAGE_TEXEL_BUFFER;
    let staging = vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST;
    let buffers: Vec<Buffer> = job.bindings.iter().map(|b| buffer(gpu, &b.data, if b.image.is_some() { staging } else { usage })).collect();
    let images: Vec<Option<Image>> = job
        .bindings
        .iter()
        .map(|b| {
            let (format, extent) = b.image?;
            let (image, memory, view) = storage_image(gpu, format, extent);
            Some(Image { image, memory, view, extent })
        })
        .collect();
    let mut record = vec![0u8; 32];
    if let Size::Indirect(g) = job.size {
        for (i, v) in g.iter().enumerate() {
            record[16 + 4 * i..20 + 4 * i].copy_from_slice(&v.to_le_bytes());
        }
    }
    let indirect = buffer(gpu, &record, vk::BufferUsageFlags::INDIRECT_BUFFER);
    let mut job = job.clone();
    for p in &job.addresses {
        // SAFETY: a live buffer created with SHADER_DEVICE_ADDRESS usage.
        let address = unsafe { gpu.device.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(buffers[p.of].buffer)) } + p.plus;
        match p.into {
            None => job.push[p.at..p.at + 8].copy_from_slice(&address.to_le_bytes()),
            Some(b) => {
                assert!(p.at + 8 <= buffers[b].size as usize);
                // SAFETY: mapped memory of a live buffer, inside its size (asserted).
                unsafe { std::ptr::copy_nonoverlapping(address.to_le_bytes().as_ptr(), buffers[b].ptr.add(p.at), 8) };
            }
        }
    }
    let result = objects(gpu, &job, &buffers, &images).and_then(|o| {
        let r = submit(gpu, &job, &o, &indirect, &buffers, &images);
        destroy(gpu, &o);
        r
    });
    let out = buffers
        .iter()
        .zip(&job.bindings)
        // SAFETY: mapped, coherent, and the dispatch finished (fence waited).
        .map(|(b, j)| unsafe { std::slice::from_raw_parts(b.ptr, b.size as usize)[..j.data.len()].to_vec() })
        .collect();
    for i in images.iter().flatten() {
        // SAFETY: idle and not used again.
        unsafe {
            gpu.device.destroy_image_view(i.view, None);
            gpu.device.destroy_image(i.image, None);
            gpu.device.free_memory(i.memory, None);
        }
    }
    for b in buffers.iter().chain([&indirect]) {
        // SAFETY: idle and not used again.
        unsafe {
            gpu.device.destroy_buffer(b.buffer, None);
            gpu.device.free_memory(b.memory, None);
        }
    }
    result.map(|_| out)
}

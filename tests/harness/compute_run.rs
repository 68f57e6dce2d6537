//! Running a compute [`Job`](super::compute::Job): every Vulkan object it needs is created,
//! used once and destroyed here, so a test reads as data in, buffers out.
use ash::vk;

use super::compute::{Gpu, Job, JobError, Size};

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
}

fn objects(gpu: &Gpu, job: &Job, buffers: &[Buffer]) -> Result<Objects, JobError> {
    let d = &gpu.device;
    let lb: Vec<_> = job
        .bindings
        .iter()
        .enumerate()
        .map(|(i, b)| vk::DescriptorSetLayoutBinding::default().binding(i as u32).descriptor_type(b.kind).descriptor_count(1).stage_flags(vk::ShaderStageFlags::COMPUTE))
        .collect();
    // SAFETY: valid create infos; every object is destroyed by `destroy`.
    unsafe {
        let set_layout = d.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&lb), None).unwrap();
        let sizes: Vec<_> = job.bindings.iter().map(|b| vk::DescriptorPoolSize { ty: b.kind, descriptor_count: 1 }).collect();
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
        let infos: Vec<[vk::DescriptorBufferInfo; 1]> =
            job.bindings.iter().zip(buffers).map(|(b, buf)| [vk::DescriptorBufferInfo { buffer: buf.buffer, offset: 0, range: b.range }]).collect();
        let writes: Vec<_> = job
            .bindings
            .iter()
            .zip(&infos)
            .enumerate()
            .map(|(i, (b, info))| vk::WriteDescriptorSet::default().dst_set(set).dst_binding(i as u32).descriptor_type(b.kind).buffer_info(info))
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
        let o = |pipeline| Objects { set_layout, pool, set, layout, module, pipeline };
        match d.create_compute_pipelines(vk::PipelineCache::null(), &ci, None) {
            Ok(p) => Ok(o(p[0])),
            Err((_, e)) => {
                destroy(gpu, &o(vk::Pipeline::null()));
                Err(JobError::Pipeline(e))
            }
        }
    }
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
    }
}

/// Record and submit the dispatch; wait for its fence.
fn submit(gpu: &Gpu, job: &Job, o: &Objects, indirect: &Buffer) -> Result<(), JobError> {
    let d = &gpu.device;
    // SAFETY: valid objects; the command pool and fence are destroyed before returning.
    unsafe {
        let cmd_pool = d.create_command_pool(&vk::CommandPoolCreateInfo::default().queue_family_index(0), None).unwrap();
        let cb = d.allocate_command_buffers(&vk::CommandBufferAllocateInfo::default().command_pool(cmd_pool).command_buffer_count(1)).unwrap()[0];
        d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).unwrap();
        d.cmd_bind_pipeline(cb, vk::PipelineBindPoint::COMPUTE, o.pipeline);
        if o.set != vk::DescriptorSet::null() {
            let dynamic: Vec<u32> = job.bindings.iter().filter(|b| b.kind == vk::DescriptorType::UNIFORM_BUFFER_DYNAMIC || b.kind == vk::DescriptorType::STORAGE_BUFFER_DYNAMIC).map(|b| b.dynamic_offset).collect();
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
        let barrier = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::SHADER_WRITE).dst_access_mask(vk::AccessFlags::HOST_READ)];
        d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::COMPUTE_SHADER, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &barrier, &[], &[]);
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
    let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::UNIFORM_BUFFER;
    let buffers: Vec<Buffer> = job.bindings.iter().map(|b| buffer(gpu, &b.data, usage)).collect();
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
    let result = objects(gpu, &job, &buffers).and_then(|o| {
        let r = submit(gpu, &job, &o, &indirect);
        destroy(gpu, &o);
        r
    });
    let out = buffers
        .iter()
        .zip(&job.bindings)
        // SAFETY: mapped, coherent, and the dispatch finished (fence waited).
        .map(|(b, j)| unsafe { std::slice::from_raw_parts(b.ptr, b.size as usize)[..j.data.len()].to_vec() })
        .collect();
    for b in buffers.iter().chain([&indirect]) {
        // SAFETY: idle and not used again.
        unsafe {
            gpu.device.destroy_buffer(b.buffer, None);
            gpu.device.free_memory(b.memory, None);
        }
    }
    result.map(|_| out)
}

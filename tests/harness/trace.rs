//! One compute dispatch of a ray-query shader on an [`Accel`] device, for the tests that trace
//! structures they built through the API (tests/ray_query.rs, clas_rq.rs, ptlas_api.rs,
//! ptlas_rq.rs): the pipeline of a SPIR-V module, its dispatch recorded after the builds and
//! read back by the host, and the common descriptor set of a TLAS and storage buffers. A test
//! whose set is unusual (PTLAS descriptors, copied sets, `rq::RqGpu`) writes its own and uses
//! [`Pipeline`].
use arbor::accel::Ray;
use ash::vk;

use super::accel::Accel;

const STAGE: vk::ShaderStageFlags = vk::ShaderStageFlags::COMPUTE;

/// The bytes of `rays` as the shaders read them: [origin, tmin, direction, tmax], f32 each.
pub fn ray_bytes(rays: &[Ray]) -> Vec<u8> {
    rays.iter().flat_map(|r| [r.origin.x, r.origin.y, r.origin.z, r.tmin, r.direction.x, r.direction.y, r.direction.z, r.tmax]).flat_map(f32::to_le_bytes).collect()
}

/// A compute pipeline of `main` in one module over one set layout.
pub struct Pipeline {
    pub layout: vk::PipelineLayout,
    pub module: vk::ShaderModule,
    pub pipeline: vk::Pipeline,
}

impl Pipeline {
    /// `spirv` over `set_layout`, with `push_size` bytes of push constants (no range when 0).
    pub fn new(d: &ash::Device, spirv: &[u32], set_layout: vk::DescriptorSetLayout, push_size: u32) -> Pipeline {
        let layouts = [set_layout];
        let ranges = [vk::PushConstantRange { stage_flags: STAGE, offset: 0, size: push_size }];
        let mut lci = vk::PipelineLayoutCreateInfo::default().set_layouts(&layouts);
        if push_size > 0 {
            lci = lci.push_constant_ranges(&ranges);
        }
        // SAFETY: valid create infos; the objects are destroyed by `destroy`.
        unsafe {
            let layout = d.create_pipeline_layout(&lci, None).unwrap();
            let module = d.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(spirv), None).unwrap();
            let ci = [vk::ComputePipelineCreateInfo::default().stage(vk::PipelineShaderStageCreateInfo::default().stage(STAGE).module(module).name(c"main")).layout(layout)];
            let pipeline = d.create_compute_pipelines(vk::PipelineCache::null(), &ci, None).map_err(|(_, e)| e).expect("vkCreateComputePipelines")[0];
            Pipeline { layout, module, pipeline }
        }
    }

    /// Records the dispatch of `groups` workgroups with `set` bound and `push` (skipped when
    /// empty), then a barrier that makes the shader's writes visible to the host.
    pub fn record(&self, d: &ash::Device, cb: vk::CommandBuffer, set: vk::DescriptorSet, push: &[u8], groups: u32) {
        // SAFETY: a command buffer in the recording state; the pipeline, layout and set are live.
        unsafe {
            d.cmd_bind_pipeline(cb, vk::PipelineBindPoint::COMPUTE, self.pipeline);
            d.cmd_bind_descriptor_sets(cb, vk::PipelineBindPoint::COMPUTE, self.layout, 0, &[set], &[]);
            if !push.is_empty() {
                d.cmd_push_constants(cb, self.layout, STAGE, 0, push);
            }
            d.cmd_dispatch(cb, groups, 1, 1);
            let barrier = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::SHADER_WRITE).dst_access_mask(vk::AccessFlags::HOST_READ)];
            d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::COMPUTE_SHADER, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &barrier, &[], &[]);
        }
    }

    pub fn destroy(self, d: &ash::Device) {
        // SAFETY: the work that used them has completed (the submissions waited).
        unsafe {
            d.destroy_pipeline(self.pipeline, None);
            d.destroy_shader_module(self.module, None);
            d.destroy_pipeline_layout(self.layout, None);
        }
    }
}

/// Records the barrier between acceleration-structure builds and a compute shader reading them.
pub fn after_builds(d: &ash::Device, cb: vk::CommandBuffer) {
    let barrier = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::ACCELERATION_STRUCTURE_WRITE_KHR).dst_access_mask(vk::AccessFlags::ACCELERATION_STRUCTURE_READ_KHR)];
    // SAFETY: a command buffer in the recording state.
    unsafe { d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::ACCELERATION_STRUCTURE_BUILD_KHR, vk::PipelineStageFlags::COMPUTE_SHADER, vk::DependencyFlags::empty(), &barrier, &[], &[]) };
}

/// Dispatches `spirv` once, after a barrier on earlier builds: `tlas`, when given, at binding 0
/// of set 0, then the [`Accel`] buffers `buffers` as storage buffers at the following bindings;
/// `push` as push constants, `groups` workgroups in x. The caller reads the buffers back.
// One function: descriptor set, pipeline, dispatch and teardown of one trace.
pub fn dispatch(a: &Accel, spirv: &[u32], tlas: Option<vk::AccelerationStructureKHR>, buffers: &[usize], push: &[u8], groups: u32) {
    let d = &a.ctx.device;
    let first = tlas.is_some() as u32;
    let binding = |b: u32, ty| vk::DescriptorSetLayoutBinding::default().binding(b).descriptor_type(ty).descriptor_count(1).stage_flags(STAGE);
    let mut bindings: Vec<_> = tlas.iter().map(|_| binding(0, vk::DescriptorType::ACCELERATION_STRUCTURE_KHR)).collect();
    bindings.extend((0..buffers.len() as u32).map(|k| binding(first + k, vk::DescriptorType::STORAGE_BUFFER)));
    let mut sizes = vec![vk::DescriptorPoolSize { ty: vk::DescriptorType::STORAGE_BUFFER, descriptor_count: buffers.len() as u32 }];
    if tlas.is_some() {
        sizes.insert(0, vk::DescriptorPoolSize { ty: vk::DescriptorType::ACCELERATION_STRUCTURE_KHR, descriptor_count: 1 });
    }
    // SAFETY: valid create infos; everything is destroyed before returning, after the wait.
    unsafe {
        let set_layout = d.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings), None).unwrap();
        let pool = d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(1).pool_sizes(&sizes), None).unwrap();
        let layouts = [set_layout];
        let set = d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&layouts)).unwrap()[0];
        let structures: Vec<_> = tlas.into_iter().collect();
        let mut as_info = vk::WriteDescriptorSetAccelerationStructureKHR::default().acceleration_structures(&structures);
        let infos: Vec<_> = buffers.iter().map(|&b| [vk::DescriptorBufferInfo { buffer: a.buf(b).buffer, offset: 0, range: vk::WHOLE_SIZE }]).collect();
        let mut writes: Vec<_> = (infos.iter().zip(first..)).map(|(info, b)| vk::WriteDescriptorSet::default().dst_set(set).dst_binding(b).descriptor_type(vk::DescriptorType::STORAGE_BUFFER).buffer_info(info)).collect();
        if tlas.is_some() {
            writes.insert(0, vk::WriteDescriptorSet::default().dst_set(set).dst_binding(0).descriptor_count(1).descriptor_type(vk::DescriptorType::ACCELERATION_STRUCTURE_KHR).push_next(&mut as_info));
        }
        d.update_descriptor_sets(&writes, &[]);
        let pipeline = Pipeline::new(d, spirv, set_layout, push.len() as u32);
        a.submit(|cb| {
            after_builds(d, cb);
            pipeline.record(d, cb, set, push, groups);
        });
        pipeline.destroy(d);
        d.destroy_descriptor_pool(pool, None);
        d.destroy_descriptor_set_layout(set_layout, None);
    }
}

/// The usual trace: `spirv` over `tlas` at binding 0, `rays` at 1 and a zeroed hits buffer of
/// `hit_size` bytes a ray at 2, push constants [ray count, 0], 64 rays a workgroup; the hits.
pub fn trace_tlas(a: &Accel, spirv: &[u32], tlas: vk::AccelerationStructureKHR, rays: &[u8], ray_count: usize, hit_size: usize) -> Vec<u8> {
    let (rb, hb) = (a.upload(rays), a.buffer((hit_size * ray_count) as u64));
    let push: Vec<u8> = [ray_count as u32, 0].iter().flat_map(|x| x.to_le_bytes()).collect();
    dispatch(a, spirv, Some(tlas), &[rb, hb], &push, (ray_count as u32).div_ceil(64));
    a.buf(hb).read(0, hit_size * ray_count)
}

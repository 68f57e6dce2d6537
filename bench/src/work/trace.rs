//! Trace workloads: seeded rays (primary camera rays, or random rays) through a ray-query compute
//! shader (bench/shaders/trace.comp, closest hit) over the scene's TLAS, built on the same driver
//! through the API with PREFER_FAST_TRACE. Timed per dispatch (submit + fence wait), the build
//! excluded; the hits are read back for the hit rate and, for --compare, kept in the row.
use std::sync::Arc;

use arbor_scene::{InstanceRecord, Rng};
use ash::vk;

use super::inputs::{build_sizes, dev, instances, Inputs};
use super::{Options, Row, Scene, SceneKind, Stats, Workload};
use crate::compare::{Hit, TraceRay};
use crate::vkctx::{Arena, Gpu, Place};

/// bench/shaders/trace.comp compiled by `glslangValidator -V --target-env vulkan1.2` (SPIR-V 1.5);
/// committed, so that running the benchmark needs no compiler. tests/bench_harness.rs checks it
/// against a fresh compile.
const TRACE_SPV: &[u8] = include_bytes!("../../shaders/trace.spv");

/// Invocations per workgroup (local_size_x of the shader).
const LOCAL_SIZE: u32 = 64;

/// Seed of the random rays (the same as benches/accel_trace.rs).
const RANDOM_SEED: u64 = 7;

/// The rays and the hits of one trace workload on one driver, for --compare.
pub struct Capture {
    pub rays: Vec<TraceRay>,
    pub hits: Vec<Hit>,
}

impl std::fmt::Debug for Capture {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Capture({} rays, {} hits)", self.rays.len(), self.hits.len())
    }
}

/// The scene's bounds: the mesh's, or the union of the instances' transformed BLAS bounds.
fn scene_bounds(scene: &Scene, inp: &Inputs) -> [f32; 6] {
    let (blases, records) = match &scene.kind {
        SceneKind::Mesh(m) => return m.bounds(),
        SceneKind::Instances { blases, .. } => (blases, &inp.records),
    };
    let mut b = [f32::INFINITY, f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY];
    for r in records {
        let Some(k) = inp.blas_addresses.iter().position(|&a| a == r.reference) else { continue };
        let m = blases[k].bounds();
        for corner in 0..8 {
            let p = [m[if corner & 1 == 0 { 0 } else { 3 }], m[if corner & 2 == 0 { 1 } else { 4 }], m[if corner & 4 == 0 { 2 } else { 5 }]];
            for row in 0..3 {
                let t = &r.transform[4 * row..4 * row + 4];
                let v = t[0] * p[0] + t[1] * p[1] + t[2] * p[2] + t[3];
                b[row] = b[row].min(v);
                b[row + 3] = b[row + 3].max(v);
            }
        }
    }
    b
}

/// `n` primary rays: a pinhole camera framing the bounds (arbor_scene::primary_rays), on a
/// near-square image of at least `n` pixels, cut to `n`.
pub fn primary_rays(b: [f32; 6], n: usize) -> Vec<TraceRay> {
    let w = (n as f64).sqrt().ceil().max(1.0) as usize;
    let h = n.div_ceil(w);
    let mut rays: Vec<TraceRay> = arbor_scene::primary_rays(b, w, h)
        .into_iter()
        .map(|r| TraceRay { origin: r.origin.into(), tmin: 0.0, dir: r.direction.into(), tmax: f32::INFINITY })
        .collect();
    rays.truncate(n);
    rays
}

/// `n` random rays, deterministic from `seed`: even ones from outside the bounds towards a
/// random point inside, odd ones from a random point inside in a random direction (the recipe of
/// benches/accel_trace.rs).
pub fn random_rays(b: [f32; 6], n: usize, seed: u64) -> Vec<TraceRay> {
    let mut rng = Rng::new(seed);
    let lo = glam::Vec3::new(b[0], b[1], b[2]);
    let ext = glam::Vec3::new(b[3] - b[0], b[4] - b[1], b[5] - b[2]);
    (0..n)
        .map(|i| {
            let p = lo + ext * glam::Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            let (o, d) = if i % 2 == 0 {
                let o = lo + ext * 0.5 + glam::Vec3::from(rng.unit_vector()) * ext.length();
                (o, (p - o).normalize())
            } else {
                (p, glam::Vec3::from(rng.unit_vector()))
            };
            TraceRay { origin: o.into(), tmin: 0.0, dir: d.into(), tmax: f32::INFINITY }
        })
        .collect()
}

/// Builds one structure on the device (PREFER_FAST_TRACE) from `geom`; returns it and its size.
fn build(a: &Arena, ty: vk::AccelerationStructureTypeKHR, geom: vk::AccelerationStructureGeometryKHR, count: u32) -> Result<(vk::AccelerationStructureKHR, u64), String> {
    let geoms = [geom];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(ty)
        .flags(vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let sizes = build_sizes(a.gpu, vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, count);
    let (s, _) = a.structure(ty, sizes.acceleration_structure_size, Place::Device)?;
    let scratch = a.buffer(sizes.build_scratch_size, Place::Device)?;
    let info = info.dst_acceleration_structure(s).scratch_data(vk::DeviceOrHostAddressKHR { device_address: scratch.address });
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(count)];
    a.gpu.submit(|cb| {
        // SAFETY: valid infos; the buffers live until the wait inside submit.
        unsafe { a.gpu.ext.cmd_build_acceleration_structures(cb, &[info], &[&range]) };
    })?;
    Ok((s, sizes.acceleration_structure_size))
}

/// The scene's TLAS: over the scene's instances, or over one identity instance of the mesh's BLAS.
fn build_tlas(a: &Arena, inp: &Inputs) -> Result<(vk::AccelerationStructureKHR, u64), String> {
    let tlas = vk::AccelerationStructureTypeKHR::TOP_LEVEL;
    if inp.ty == tlas {
        return build(a, tlas, inp.geom, inp.count);
    }
    let (blas, _) = build(a, vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, inp.geom, inp.count)?;
    let record = InstanceRecord { transform: InstanceRecord::IDENTITY, custom_index: 0, mask: 0xFF, sbt_offset: 0, flags: 0, reference: a.address_of(blas) };
    let records = a.upload(&record.to_bytes())?;
    build(a, tlas, instances(dev(records.address)), 1)
}

/// The compute pipeline of trace.comp with its descriptor set (TLAS, rays, hits).
struct Pipeline<'g> {
    gpu: &'g Gpu,
    set_layout: vk::DescriptorSetLayout,
    pool: vk::DescriptorPool,
    set: vk::DescriptorSet,
    layout: vk::PipelineLayout,
    module: vk::ShaderModule,
    pipeline: vk::Pipeline,
}

fn vk_err(what: &'static str) -> impl Fn(vk::Result) -> String {
    move |e| format!("{what}: {e}")
}

impl<'g> Pipeline<'g> {
    // One function: the objects are created in dependency order, each destroyed by Drop.
    fn new(gpu: &'g Gpu, tlas: vk::AccelerationStructureKHR, rays: vk::Buffer, hits: vk::Buffer) -> Result<Pipeline<'g>, String> {
        let d = &gpu.device;
        let stage = vk::ShaderStageFlags::COMPUTE;
        let binding = |b: u32, ty: vk::DescriptorType| vk::DescriptorSetLayoutBinding::default().binding(b).descriptor_type(ty).descriptor_count(1).stage_flags(stage);
        let bindings = [
            binding(0, vk::DescriptorType::ACCELERATION_STRUCTURE_KHR),
            binding(1, vk::DescriptorType::STORAGE_BUFFER),
            binding(2, vk::DescriptorType::STORAGE_BUFFER),
        ];
        let words: Vec<u32> = TRACE_SPV.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let mut p = Pipeline {
            gpu,
            set_layout: vk::DescriptorSetLayout::null(),
            pool: vk::DescriptorPool::null(),
            set: vk::DescriptorSet::null(),
            layout: vk::PipelineLayout::null(),
            module: vk::ShaderModule::null(),
            pipeline: vk::Pipeline::null(),
        };
        // SAFETY: valid create infos on a live device; every object is destroyed by Drop, after
        // the caller's submissions have completed.
        unsafe {
            p.set_layout = d.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings), None).map_err(vk_err("vkCreateDescriptorSetLayout"))?;
            let sizes = [
                vk::DescriptorPoolSize { ty: vk::DescriptorType::ACCELERATION_STRUCTURE_KHR, descriptor_count: 1 },
                vk::DescriptorPoolSize { ty: vk::DescriptorType::STORAGE_BUFFER, descriptor_count: 2 },
            ];
            p.pool = d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(1).pool_sizes(&sizes), None).map_err(vk_err("vkCreateDescriptorPool"))?;
            let layouts = [p.set_layout];
            p.set = d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(p.pool).set_layouts(&layouts)).map_err(vk_err("vkAllocateDescriptorSets"))?[0];
            let structures = [tlas];
            let mut as_info = vk::WriteDescriptorSetAccelerationStructureKHR::default().acceleration_structures(&structures);
            let infos = [rays, hits].map(|buffer| [vk::DescriptorBufferInfo { buffer, offset: 0, range: vk::WHOLE_SIZE }]);
            let write = |b: u32| vk::WriteDescriptorSet::default().dst_set(p.set).dst_binding(b);
            let writes = [
                write(0).descriptor_count(1).descriptor_type(vk::DescriptorType::ACCELERATION_STRUCTURE_KHR).push_next(&mut as_info),
                write(1).descriptor_type(vk::DescriptorType::STORAGE_BUFFER).buffer_info(&infos[0]),
                write(2).descriptor_type(vk::DescriptorType::STORAGE_BUFFER).buffer_info(&infos[1]),
            ];
            d.update_descriptor_sets(&writes, &[]);
            let ranges = [vk::PushConstantRange { stage_flags: stage, offset: 0, size: 8 }];
            p.layout = d
                .create_pipeline_layout(&vk::PipelineLayoutCreateInfo::default().set_layouts(&layouts).push_constant_ranges(&ranges), None)
                .map_err(vk_err("vkCreatePipelineLayout"))?;
            p.module = d.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&words), None).map_err(vk_err("vkCreateShaderModule"))?;
            let ci = [vk::ComputePipelineCreateInfo::default().stage(vk::PipelineShaderStageCreateInfo::default().stage(stage).module(p.module).name(c"main")).layout(p.layout)];
            p.pipeline = d.create_compute_pipelines(vk::PipelineCache::null(), &ci, None).map_err(|(_, e)| format!("vkCreateComputePipelines: {e}"))?[0];
        }
        Ok(p)
    }

    /// Records the dispatch of `n` rays.
    fn record(&self, cb: vk::CommandBuffer, n: u32) {
        let d = &self.gpu.device;
        let push: Vec<u8> = [n, 0].iter().flat_map(|x| x.to_le_bytes()).collect();
        // SAFETY: a recording command buffer; the pipeline, layout and set are live.
        unsafe {
            d.cmd_bind_pipeline(cb, vk::PipelineBindPoint::COMPUTE, self.pipeline);
            d.cmd_bind_descriptor_sets(cb, vk::PipelineBindPoint::COMPUTE, self.layout, 0, &[self.set], &[]);
            d.cmd_push_constants(cb, self.layout, vk::ShaderStageFlags::COMPUTE, 0, &push);
            d.cmd_dispatch(cb, n.div_ceil(LOCAL_SIZE), 1, 1);
        }
    }
}

impl Drop for Pipeline<'_> {
    fn drop(&mut self) {
        let d = &self.gpu.device;
        // SAFETY: the queue is idle first; each object is destroyed once (null handles are ignored).
        unsafe {
            let _ = d.queue_wait_idle(self.gpu.queue);
            d.destroy_pipeline(self.pipeline, None);
            d.destroy_shader_module(self.module, None);
            d.destroy_pipeline_layout(self.layout, None);
            d.destroy_descriptor_pool(self.pool, None);
            d.destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}

/// The hits buffer copied into host memory (after the shader's writes) and decoded.
fn read_hits(a: &Arena, hits: vk::Buffer, n: usize) -> Result<Vec<Hit>, String> {
    let len = (n * Hit::SIZE) as u64;
    let host = a.buffer(len, Place::Host)?;
    let d = &a.gpu.device;
    a.gpu.submit(|cb| {
        let before = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::SHADER_WRITE).dst_access_mask(vk::AccessFlags::TRANSFER_READ)];
        let after = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::TRANSFER_WRITE).dst_access_mask(vk::AccessFlags::HOST_READ)];
        // SAFETY: a recording command buffer; both buffers hold `len` bytes.
        unsafe {
            d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::COMPUTE_SHADER, vk::PipelineStageFlags::TRANSFER, vk::DependencyFlags::empty(), &before, &[], &[]);
            d.cmd_copy_buffer(cb, hits, host.buffer, &[vk::BufferCopy::default().size(len)]);
            d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &after, &[], &[]);
        }
    })?;
    Ok(host.read(0, len as usize).chunks_exact(Hit::SIZE).map(Hit::from_bytes).collect())
}

/// The rays of a trace workload over this scene.
pub(super) fn rays_for(scene: &Scene, inp: &Inputs, w: Workload, n: usize) -> Vec<TraceRay> {
    let b = scene_bounds(scene, inp);
    match w {
        Workload::TracePrimary => primary_rays(b, n),
        _ => random_rays(b, n, RANDOM_SEED),
    }
}

/// A trace workload (`TracePrimary` or `TraceRandom`) into `row`.
pub(super) fn trace(gpu: &Gpu, inp: &Inputs, scene: &Scene, w: Workload, opts: &Options, row: &mut Row) -> Result<(), String> {
    if !gpu.caps.ray_query {
        row.status = super::Status::NotSupported("no VK_KHR_ray_query (rayQuery) on a Vulkan 1.2 device".into());
        return Ok(());
    }
    let a = Arena::new(gpu);
    let (tlas, size) = build_tlas(&a, inp)?;
    let rays = rays_for(scene, inp, w, opts.rays);
    let n = rays.len();
    let rb = a.upload(&rays.iter().flat_map(|r| r.to_bytes()).collect::<Vec<u8>>())?;
    let hb = a.buffer((n * Hit::SIZE) as u64, Place::Device)?;
    let times = {
        let p = Pipeline::new(gpu, tlas, rb.buffer, hb.buffer)?;
        gpu.timed(opts.warmup, opts.repeat, |cb| p.record(cb, n as u32))?
    };
    let wall: Vec<f64> = times.iter().map(|t| t.1).collect();
    row.wall = Stats::of(&wall);
    row.time = row.wall;
    row.timing = "fence";
    row.rays = n as u64;
    row.as_size = size;
    let hits = read_hits(&a, hb.buffer, n)?;
    let hit = hits.iter().filter(|h| h.kind != 0).count();
    row.note = format!("{n} rays, {:.1}% hit; TLAS built on the driver, not timed", 100.0 * hit as f64 / n.max(1) as f64);
    if opts.keep_hits {
        row.hits = Some(Arc::new(Capture { rays, hits }));
    }
    Ok(())
}

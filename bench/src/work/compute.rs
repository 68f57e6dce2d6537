//! Compute-shader workloads: an ALU-bound kernel, a memory-bound streaming read-modify-write, a
//! divergent one (Collatz step counts), each reported as invocations per second (median of the
//! timed repeats of one dispatch), and the wall time from vkCreateShaderModule of a new pipeline
//! to its first dispatch's fence. Every workload checks its output against a CPU computation
//! once, outside the timing, so a fast wrong answer fails instead of being reported.
//!
//! The shaders are bench/shaders/compute_*.comp; their SPIR-V is committed beside them
//! (`glslangValidator -V --target-env vulkan1.1`), so the harness needs no compiler.
use std::time::Instant;

use ash::vk;

use super::{Options, Row, Stats, Status, Workload};
use crate::vkctx::{Arena, Buf, Gpu, Place};

const ALU_SPV: &[u8] = include_bytes!("../../shaders/compute_alu.spv");
const MEMORY_SPV: &[u8] = include_bytes!("../../shaders/compute_memory.spv");
const DIVERGENT_SPV: &[u8] = include_bytes!("../../shaders/compute_divergent.spv");

/// local_size_x of every shader.
const GROUP: u64 = 64;
/// Workgroups per row of the dispatch (the shaders index rows by gl_NumWorkGroups.x); within
/// the spec minimum of maxComputeWorkGroupCount.
const ROW_GROUPS: u64 = 32768;
/// Rounds of the ALU kernel's loop: 6 FMAs and 4 transcendentals each.
const ALU_ITERS: u32 = 32;
/// Step cap of the Collatz kernel (no start value below 2^20 needs more than 524).
const COLLATZ_CAP: u32 = 1000;
/// Invocations of the first-dispatch workload: small, so the pipeline's creation dominates.
const FIRST_DISPATCH_INVOCATIONS: u64 = 256;
/// Largest |GPU − CPU| accepted for the float kernel: drivers' sin/cos/exp/sqrt/fma precision
/// differs from the CPU's by far less; a missing or wrong operation by far more.
const ALU_TOLERANCE: f32 = 1e-2;

fn spirv(bytes: &[u8]) -> Vec<u32> {
    bytes.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

fn vk_err(what: &'static str) -> impl Fn(vk::Result) -> String {
    move |e| format!("{what}: {e}")
}

/// Group counts covering `n` invocations in rows of ROW_GROUPS workgroups.
fn groups_for(n: u64) -> [u32; 3] {
    let total = n.div_ceil(GROUP).max(1);
    if total <= ROW_GROUPS {
        [total as u32, 1, 1]
    } else {
        [ROW_GROUPS as u32, total.div_ceil(ROW_GROUPS) as u32, 1]
    }
}

/// The descriptor side every kernel shares: one storage buffer at set 0 binding 0, 16 bytes of
/// push constants.
struct Binding<'g> {
    gpu: &'g Gpu,
    set_layout: vk::DescriptorSetLayout,
    layout: vk::PipelineLayout,
    pool: vk::DescriptorPool,
    set: vk::DescriptorSet,
}

impl<'g> Binding<'g> {
    fn new(gpu: &'g Gpu, buf: &Buf) -> Result<Binding<'g>, String> {
        let d = &gpu.device;
        let slot = [vk::DescriptorSetLayoutBinding::default()
            .binding(0)
            .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
            .descriptor_count(1)
            .stage_flags(vk::ShaderStageFlags::COMPUTE)];
        let push = [vk::PushConstantRange::default().stage_flags(vk::ShaderStageFlags::COMPUTE).offset(0).size(16)];
        let sizes = [vk::DescriptorPoolSize::default().ty(vk::DescriptorType::STORAGE_BUFFER).descriptor_count(1)];
        // SAFETY: valid create infos; Drop destroys everything made here.
        unsafe {
            let set_layout = d
                .create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&slot), None)
                .map_err(vk_err("vkCreateDescriptorSetLayout"))?;
            let mut b = Binding { gpu, set_layout, layout: vk::PipelineLayout::null(), pool: vk::DescriptorPool::null(), set: vk::DescriptorSet::null() };
            let layouts = [set_layout];
            b.layout = d
                .create_pipeline_layout(&vk::PipelineLayoutCreateInfo::default().set_layouts(&layouts).push_constant_ranges(&push), None)
                .map_err(vk_err("vkCreatePipelineLayout"))?;
            b.pool = d
                .create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(1).pool_sizes(&sizes), None)
                .map_err(vk_err("vkCreateDescriptorPool"))?;
            b.set = d
                .allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(b.pool).set_layouts(&layouts))
                .map_err(vk_err("vkAllocateDescriptorSets"))?[0];
            let info = [vk::DescriptorBufferInfo::default().buffer(buf.buffer).offset(0).range(vk::WHOLE_SIZE)];
            let write = vk::WriteDescriptorSet::default()
                .dst_set(b.set)
                .dst_binding(0)
                .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                .buffer_info(&info);
            d.update_descriptor_sets(&[write], &[]);
            Ok(b)
        }
    }

    /// vkCreateShaderModule + vkCreateComputePipelines; `salt` is specialization constant 0.
    fn pipeline(&self, words: &[u32], salt: u32) -> Result<Kernel<'_>, String> {
        let d = &self.gpu.device;
        // SAFETY: valid create infos; the Kernel destroys both objects.
        unsafe {
            let module = d.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(words), None).map_err(vk_err("vkCreateShaderModule"))?;
            let entries = [vk::SpecializationMapEntry { constant_id: 0, offset: 0, size: 4 }];
            let data = salt.to_le_bytes();
            let spec = vk::SpecializationInfo::default().map_entries(&entries).data(&data);
            let stage = vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::COMPUTE)
                .module(module)
                .name(c"main")
                .specialization_info(&spec);
            let info = [vk::ComputePipelineCreateInfo::default().stage(stage).layout(self.layout)];
            match d.create_compute_pipelines(vk::PipelineCache::null(), &info, None) {
                Ok(p) => Ok(Kernel { binding: self, module, pipeline: p[0] }),
                Err((_, e)) => {
                    d.destroy_shader_module(module, None);
                    Err(format!("vkCreateComputePipelines: {e}"))
                }
            }
        }
    }
}

impl Drop for Binding<'_> {
    fn drop(&mut self) {
        let d = &self.gpu.device;
        // SAFETY: no pending work uses these (every submission was waited for).
        unsafe {
            d.destroy_descriptor_pool(self.pool, None);
            d.destroy_pipeline_layout(self.layout, None);
            d.destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}

/// One compute pipeline over a [`Binding`].
struct Kernel<'b> {
    binding: &'b Binding<'b>,
    module: vk::ShaderModule,
    pipeline: vk::Pipeline,
}

impl Kernel<'_> {
    /// Bind, push `push` and dispatch enough groups for `n` invocations.
    fn record(&self, cb: vk::CommandBuffer, push: [u32; 4], n: u64) {
        let d = &self.binding.gpu.device;
        let bytes: Vec<u8> = push.iter().flat_map(|w| w.to_le_bytes()).collect();
        let [x, y, z] = groups_for(n);
        // SAFETY: a recording command buffer; every object is live.
        unsafe {
            d.cmd_bind_pipeline(cb, vk::PipelineBindPoint::COMPUTE, self.pipeline);
            d.cmd_bind_descriptor_sets(cb, vk::PipelineBindPoint::COMPUTE, self.binding.layout, 0, &[self.binding.set], &[]);
            d.cmd_push_constants(cb, self.binding.layout, vk::ShaderStageFlags::COMPUTE, 0, &bytes);
            d.cmd_dispatch(cb, x, y, z);
        }
    }
}

impl Drop for Kernel<'_> {
    fn drop(&mut self) {
        let d = &self.binding.gpu.device;
        // SAFETY: no pending work uses the pipeline (every submission was waited for).
        unsafe {
            d.destroy_pipeline(self.pipeline, None);
            d.destroy_shader_module(self.module, None);
        }
    }
}

/// `words` 32-bit words of `buf`, read directly when mapped, else through a host copy.
fn read_words(arena: &Arena, buf: &Buf, words: usize) -> Result<Vec<u32>, String> {
    let bytes = if !buf.ptr.is_null() {
        buf.read(0, 4 * words)
    } else {
        let host = arena.buffer(4 * words as u64, Place::Host)?;
        arena.gpu.submit(|cb| {
            let region = [vk::BufferCopy::default().size(4 * words as u64)];
            // SAFETY: recording command buffer, live buffers.
            unsafe { arena.gpu.device.cmd_copy_buffer(cb, buf.buffer, host.buffer, &region) };
        })?;
        host.read(0, 4 * words)
    };
    Ok(bytes.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
}

/// The ALU kernel on the CPU, for invocation `i` (the shader's operations in the same order).
pub fn alu_reference(i: u32, iters: u32, salt: u32) -> f32 {
    let mut x = (i & 1023) as f32 * (1.0 / 1024.0);
    let mut y = 0.25f32;
    for _ in 0..iters {
        x = x.mul_add(0.75, y * 0.125) + 0.0625;
        y = y.mul_add(0.5, x * 0.25);
        let s = x.sin();
        let c = y.cos();
        x = s.mul_add(0.5, x * 0.25);
        y = c.mul_add(0.25, y * 0.5);
        x = (x * x + 1.0).sqrt().mul_add(0.25, (-y).exp() * 0.125);
        y = y.mul_add(0.75, x * -0.125);
    }
    x + y + salt as f32 * (1.0 / 65536.0)
}

/// The Collatz step count of `x`, capped, with wrapping arithmetic (the shader's uint).
pub fn collatz_reference(mut x: u32, cap: u32) -> u32 {
    let mut s = 0;
    while x > 1 && s < cap {
        x = if x & 1 != 0 { x.wrapping_mul(3).wrapping_add(1) } else { x >> 1 };
        s += 1;
    }
    s
}

/// The ALU output against the CPU: the largest difference, or the first value out of tolerance.
fn check_alu(got: &[u32], salt: u32) -> Result<f32, String> {
    let mut worst = 0f32;
    for (i, &w) in got.iter().enumerate() {
        let (g, r) = (f32::from_bits(w), alu_reference(i as u32, ALU_ITERS, salt));
        let err = (g - r).abs();
        if err.is_nan() || err > ALU_TOLERANCE {
            return Err(format!("wrong result: invocation {i} wrote {g}, the CPU computes {r}"));
        }
        worst = worst.max(err);
    }
    Ok(worst)
}

/// Runs one compute workload on `gpu` into `row`: its rate, its verification in the note.
pub fn run(gpu: &Gpu, w: Workload, opts: &Options, row: &mut Row) -> Result<(), String> {
    let arena = Arena::new(gpu);
    let n = match w {
        Workload::ComputeMemory => (opts.compute_memory_bytes / 16).max(1),
        Workload::ComputeFirstDispatch => FIRST_DISPATCH_INVOCATIONS,
        _ => opts.compute_invocations.max(1),
    };
    row.primitives = n;
    if n.div_ceil(GROUP).div_ceil(ROW_GROUPS) > 65535 {
        return Err(format!("{n} invocations are more than the harness dispatches"));
    }
    match w {
        Workload::ComputeAlu => alu(&arena, n, opts, row),
        Workload::ComputeMemory => memory(&arena, n, opts, row),
        Workload::ComputeDivergent => divergent(&arena, n, opts, row),
        Workload::ComputeFirstDispatch => first_dispatch(&arena, n, opts, row),
        _ => Err(format!("{} is not a compute workload", w.name())),
    }
}

/// The timed repeats of `kernel` over `n` invocations into `row` (time and wall, ms).
fn time_kernel(arena: &Arena, kernel: &Kernel, push: [u32; 4], n: u64, opts: &Options, row: &mut Row) -> Result<(), String> {
    let runs = arena.gpu.timed(opts.warmup, opts.repeat, |cb| kernel.record(cb, push, n))?;
    let stamped = runs.iter().all(|(ts, _)| ts.is_some());
    row.timing = if stamped { "timestamp" } else { "fence" };
    let time: Vec<f64> = runs.iter().map(|(ts, wall)| if stamped { ts.unwrap_or(*wall) } else { *wall }).collect();
    let wall: Vec<f64> = runs.iter().map(|(_, wall)| *wall).collect();
    row.time = Stats::of(&time);
    row.wall = Stats::of(&wall);
    if row.time.is_none_or(|t| t.median <= 0.0) {
        return Err("no positive time measured".into());
    }
    Ok(())
}

fn rate_note(row: &Row) -> String {
    let rate = row.mprims_per_s().unwrap_or(0.0);
    format!("{rate:.2} M invocations/s")
}

fn alu(arena: &Arena, n: u64, opts: &Options, row: &mut Row) -> Result<(), String> {
    let out = arena.buffer(4 * n, Place::Device)?;
    let binding = Binding::new(arena.gpu, &out)?;
    let kernel = binding.pipeline(&spirv(ALU_SPV), 0)?;
    let push = [n as u32, ALU_ITERS, 0, 0];
    arena.gpu.submit(|cb| kernel.record(cb, push, n))?;
    let worst = check_alu(&read_words(arena, &out, n as usize)?, 0)?;
    time_kernel(arena, &kernel, push, n, opts, row)?;
    row.note = format!("{}; verified: {n} results within {worst:.1e} of the CPU's; {ALU_ITERS} rounds of 6 FMA + 4 transcendentals", rate_note(row));
    Ok(())
}

fn memory(arena: &Arena, n: u64, opts: &Options, row: &mut Row) -> Result<(), String> {
    let init: Vec<u32> = (0..4 * n as u32).map(|i| i.wrapping_mul(2654435761)).collect();
    let data = arena.upload(&init.iter().flat_map(|w| w.to_le_bytes()).collect::<Vec<u8>>())?;
    let binding = Binding::new(arena.gpu, &data)?;
    let kernel = binding.pipeline(&spirv(MEMORY_SPV), 0)?;
    let push = [n as u32, 0, 0, 0];
    arena.gpu.submit(|cb| kernel.record(cb, push, n))?;
    let got = read_words(arena, &data, 4 * n as usize)?;
    if let Some(i) = (0..got.len()).find(|&i| got[i] != init[i].wrapping_mul(1664525).wrapping_add(1013904223)) {
        return Err(format!("wrong result: word {i} is {:#x}, the CPU computes {:#x}", got[i], init[i].wrapping_mul(1664525).wrapping_add(1013904223)));
    }
    time_kernel(arena, &kernel, push, n, opts, row)?;
    let gbs = row.time.map(|t| 2.0 * 16.0 * n as f64 / (t.median * 1e-3) / 1e9).unwrap_or(0.0);
    row.note = format!("{}; {gbs:.2} GB/s read+write of {} MiB; verified: all {} words exact", rate_note(row), (16 * n) >> 20, 4 * n);
    Ok(())
}

fn divergent(arena: &Arena, n: u64, opts: &Options, row: &mut Row) -> Result<(), String> {
    let out = arena.buffer(4 * n, Place::Device)?;
    let binding = Binding::new(arena.gpu, &out)?;
    let kernel = binding.pipeline(&spirv(DIVERGENT_SPV), 0)?;
    let first = 1u32;
    let push = [n as u32, COLLATZ_CAP, first, 0];
    arena.gpu.submit(|cb| kernel.record(cb, push, n))?;
    let got = read_words(arena, &out, n as usize)?;
    let mut steps = 0u64;
    for (i, &g) in got.iter().enumerate() {
        let r = collatz_reference(first.wrapping_add(i as u32), COLLATZ_CAP);
        if g != r {
            return Err(format!("wrong result: invocation {i} counted {g} steps, the CPU counts {r}"));
        }
        steps += r as u64;
    }
    time_kernel(arena, &kernel, push, n, opts, row)?;
    row.note = format!("{}; verified: all {n} step counts exact (mean {:.1} loop rounds)", rate_note(row), steps as f64 / n as f64);
    Ok(())
}

/// Each repeat: a new module and pipeline (a salt no earlier pipeline had, so no driver cache
/// can answer), then one dispatch; the wall time from vkCreateShaderModule to its fence.
fn first_dispatch(arena: &Arena, n: u64, opts: &Options, row: &mut Row) -> Result<(), String> {
    let out = arena.buffer(4 * n, Place::Device)?;
    let binding = Binding::new(arena.gpu, &out)?;
    let words = spirv(ALU_SPV);
    let push = [n as u32, ALU_ITERS, 0, 0];
    // Salts differ between runs of the harness too (drivers may keep a cache on disk).
    let base = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.subsec_nanos() % 4096).unwrap_or(0) * 64;
    let (mut total, mut create) = (Vec::new(), Vec::new());
    let mut worst = 0f32;
    // No warm-up: the first pipeline a process creates is the cold case this measures.
    for k in 0..opts.repeat {
        let salt = base + 1 + k as u32;
        let t0 = Instant::now();
        let kernel = binding.pipeline(&words, salt)?;
        let created = t0.elapsed().as_secs_f64() * 1e3;
        arena.gpu.submit(|cb| kernel.record(cb, push, n))?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        worst = worst.max(check_alu(&read_words(arena, &out, n as usize)?, salt)?);
        total.push(ms);
        create.push(created);
    }
    row.timing = "fence";
    row.time = Stats::of(&total);
    row.wall = row.time;
    let c = Stats::of(&create).map(|s| s.median).unwrap_or(0.0);
    row.note = format!("new pipeline to first fence: median {:.2} ms, the process's first {:.2} ms (vkCreateComputePipelines {c:.2} ms of the median); verified: each dispatch within {worst:.1e} of the CPU's", row.time.map(|t| t.median).unwrap_or(0.0), total[0]);
    Ok(())
}

/// The row of a compute workload that cannot run on this device.
pub fn unsupported(gpu: &Gpu) -> Option<Status> {
    // The harness's buffers are made with device addresses (vkctx), which the driver enables
    // only with the acceleration-structure extensions.
    gpu.caps.missing.as_ref().map(|m| Status::NotSupported(format!("the harness needs bufferDeviceAddress ({m})")))
}

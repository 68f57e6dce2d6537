//! Shader modules, compute pipelines, pipeline caches and the compute commands (bind pipeline,
//! bind descriptor sets, push constants, dispatch, dispatch base, dispatch indirect): raw
//! structs → owned values → one call into `runtime::shader`. A module Arbor cannot run fails
//! here, at pipeline creation, with the library's diagnostic (what and at which word).
use std::ffi::c_void;
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::command::command_buffer_from;
use super::device::device_from;
use super::handle::{get, register, unregister};
use super::memory::buffer_from;
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::diag;
use crate::runtime::command::CommandBuffer;
use crate::runtime::descriptor::{DescriptorSet, PipelineLayout};
use crate::runtime::shader::{ComputeLimits, ComputePipeline, Dispatch, DispatchSize, PipelineCache, PipelineError, ShaderModule};

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCreateShaderModule => create_shader_module),
        imp!(PFN_vkDestroyShaderModule => destroy_shader_module),
        imp!(PFN_vkCreateComputePipelines => create_compute_pipelines),
        imp!(PFN_vkDestroyPipeline => destroy_pipeline),
        imp!(PFN_vkCreatePipelineCache => create_pipeline_cache),
        imp!(PFN_vkDestroyPipelineCache => destroy_pipeline_cache),
        imp!(PFN_vkGetPipelineCacheData => get_pipeline_cache_data),
        imp!(PFN_vkMergePipelineCaches => merge_pipeline_caches),
        imp!(PFN_vkCmdBindPipeline => cmd_bind_pipeline),
        imp!(PFN_vkCmdBindDescriptorSets => cmd_bind_descriptor_sets),
        imp!(PFN_vkCmdPushConstants => cmd_push_constants),
        imp!(PFN_vkCmdDispatch => cmd_dispatch),
        imp!(PFN_vkCmdDispatchBase => cmd_dispatch_base),
        imp!(PFN_vkCmdDispatchIndirect => cmd_dispatch_indirect),
    ]
}

fn no_device(command: &str) -> vk::Result {
    diag::vuid(&format!("VUID-{command}-device-parameter"), command, "device is not a valid VkDevice");
    vk::Result::ERROR_VALIDATION_FAILED_EXT
}

/// The SPIR-V words of a VkShaderModuleCreateInfo (copied: the application's array is only
/// valid during the call).
///
/// # Safety
/// `info` is a valid VkShaderModuleCreateInfo.
unsafe fn words(info: &vk::ShaderModuleCreateInfo) -> Vec<u32> {
    // SAFETY: pCode is valid for codeSize bytes, a multiple of 4, per the spec.
    unsafe { util::slice(info.p_code, (info.code_size / 4) as u32) }.to_vec()
}

unsafe extern "system" fn create_shader_module(
    device: vk::Device,
    p_create_info: *const vk::ShaderModuleCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_module: *mut vk::ShaderModule,
) -> vk::Result {
    const CMD: &str = "vkCreateShaderModule";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device(CMD);
        }
        if p_create_info.is_null() || p_module.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid create info per the spec.
        let module = ShaderModule::new(&unsafe { words(&*p_create_info) });
        // SAFETY: checked non-null.
        unsafe { *p_module = vk::ShaderModule::from_raw(register(Arc::new(module))) };
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn destroy_shader_module(device: vk::Device, module: vk::ShaderModule, _p_allocator: *const vk::AllocationCallbacks) {
    guard("vkDestroyShaderModule", (), || {
        if device_from(device).is_some() && module != vk::ShaderModule::null() && unregister::<ShaderModule>(module.as_raw()).is_none() {
            diag::vuid("VUID-vkDestroyShaderModule-shaderModule-parameter", "vkDestroyShaderModule", "shaderModule is not a live handle");
        }
    })
}

/// (SpecId, bytes) pairs of a VkSpecializationInfo.
///
/// # Safety
/// `info` is null or a valid VkSpecializationInfo.
unsafe fn specialization(info: *const vk::SpecializationInfo) -> Vec<(u32, Vec<u8>)> {
    if info.is_null() {
        return Vec::new();
    }
    // SAFETY: valid per the caller.
    let info = unsafe { &*info };
    // SAFETY: pMapEntries and pData are valid for their counts per the spec.
    let (entries, data) = unsafe { (util::slice(info.p_map_entries, info.map_entry_count), util::slice(info.p_data as *const u8, info.data_size as u32)) };
    entries
        .iter()
        .filter_map(|e| {
            let end = (e.offset as usize).checked_add(e.size)?;
            data.get(e.offset as usize..end).map(|b| (e.constant_id, b.to_vec()))
        })
        .collect()
}

fn compute_limits() -> ComputeLimits {
    let l = super::physical_device::limits();
    ComputeLimits {
        max_group_size: l.max_compute_work_group_size,
        max_group_invocations: l.max_compute_work_group_invocations,
        max_shared_memory: l.max_compute_shared_memory_size,
    }
}

/// Create one compute pipeline; errors are reported here, with the module's diagnostic.
///
/// # Safety
/// `info` is a valid VkComputePipelineCreateInfo.
unsafe fn create_one(info: &vk::ComputePipelineCreateInfo) -> Result<ComputePipeline, vk::Result> {
    const CMD: &str = "vkCreateComputePipelines";
    let stage = &info.stage;
    let chained;
    let module = if stage.module != vk::ShaderModule::null() {
        get::<ShaderModule>(stage.module.as_raw())
    } else {
        // maintenance5: the module's create info chained into the stage instead of a module.
        // SAFETY: a valid pNext chain per the spec.
        let ci = unsafe { util::find_in::<vk::ShaderModuleCreateInfo>(stage.p_next, vk::StructureType::SHADER_MODULE_CREATE_INFO) };
        // SAFETY: a valid create info per the spec.
        chained = ci.map(|ci| Arc::new(ShaderModule::new(&unsafe { words(ci) })));
        chained.clone()
    };
    let Some(module) = module else {
        diag::vuid("VUID-VkPipelineShaderStageCreateInfo-module-parameter", CMD, "stage.module is not a live shader module and no VkShaderModuleCreateInfo is chained");
        return Err(vk::Result::ERROR_VALIDATION_FAILED_EXT);
    };
    if stage.stage != vk::ShaderStageFlags::COMPUTE {
        diag::vuid("VUID-VkComputePipelineCreateInfo-stage-00701", CMD, &format!("stage.stage is {:?}, must be COMPUTE", stage.stage));
        return Err(vk::Result::ERROR_VALIDATION_FAILED_EXT);
    }
    let Some(layout) = get::<PipelineLayout>(info.layout.as_raw()) else {
        diag::vuid("VUID-VkComputePipelineCreateInfo-layout-parameter", CMD, "layout is not a live pipeline layout");
        return Err(vk::Result::ERROR_VALIDATION_FAILED_EXT);
    };
    // SAFETY: pName is a valid NUL-terminated string per the spec.
    let entry = unsafe { util::cstr(stage.p_name) }.unwrap_or("main");
    // SAFETY: valid specialization info (or null) per the spec.
    let spec = unsafe { specialization(stage.p_specialization_info) };
    ComputePipeline::new(&module, entry, &spec, layout, info.flags, &compute_limits()).map_err(|e| match e {
        PipelineError::Shader(e) => {
            diag::report(diag::Level::Error, CMD, &format!("the shader cannot run on Arbor: {e}"));
            vk::Result::ERROR_UNKNOWN
        }
        PipelineError::Invalid(v) => {
            diag::vuid(v.vuid, CMD, &v.message);
            vk::Result::ERROR_VALIDATION_FAILED_EXT
        }
    })
}

unsafe extern "system" fn create_compute_pipelines(
    device: vk::Device,
    _cache: vk::PipelineCache,
    count: u32,
    p_create_infos: *const vk::ComputePipelineCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_pipelines: *mut vk::Pipeline,
) -> vk::Result {
    const CMD: &str = "vkCreateComputePipelines";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device(CMD);
        }
        // SAFETY: valid arrays of `count` per the spec.
        let infos = unsafe { util::slice(p_create_infos, count) };
        let mut result = vk::Result::SUCCESS;
        for (i, info) in infos.iter().enumerate() {
            // SAFETY: a valid create info per the spec.
            let handle = match unsafe { create_one(info) } {
                Ok(p) => vk::Pipeline::from_raw(register(Arc::new(p))),
                Err(e) => {
                    result = e;
                    vk::Pipeline::null()
                }
            };
            // SAFETY: pPipelines is valid for `count` writes per the spec.
            unsafe { util::out(p_pipelines.add(i), handle) };
        }
        result
    })
}

unsafe extern "system" fn destroy_pipeline(device: vk::Device, pipeline: vk::Pipeline, _p_allocator: *const vk::AllocationCallbacks) {
    guard("vkDestroyPipeline", (), || {
        if device_from(device).is_some() && pipeline != vk::Pipeline::null() && unregister::<ComputePipeline>(pipeline.as_raw()).is_none() {
            diag::vuid("VUID-vkDestroyPipeline-pipeline-parameter", "vkDestroyPipeline", "pipeline is not a live handle");
        }
    })
}

unsafe extern "system" fn create_pipeline_cache(
    device: vk::Device,
    p_create_info: *const vk::PipelineCacheCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_cache: *mut vk::PipelineCache,
) -> vk::Result {
    guard("vkCreatePipelineCache", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device("vkCreatePipelineCache");
        }
        if p_create_info.is_null() || p_cache.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // Initial data is accepted and ignored: nothing Arbor makes is worth caching.
        // SAFETY: checked non-null.
        unsafe { *p_cache = vk::PipelineCache::from_raw(register(Arc::new(PipelineCache))) };
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn destroy_pipeline_cache(device: vk::Device, cache: vk::PipelineCache, _p_allocator: *const vk::AllocationCallbacks) {
    guard("vkDestroyPipelineCache", (), || {
        if device_from(device).is_some() && cache != vk::PipelineCache::null() && unregister::<PipelineCache>(cache.as_raw()).is_none() {
            diag::vuid("VUID-vkDestroyPipelineCache-pipelineCache-parameter", "vkDestroyPipelineCache", "pipelineCache is not a live handle");
        }
    })
}

unsafe extern "system" fn get_pipeline_cache_data(device: vk::Device, cache: vk::PipelineCache, p_size: *mut usize, p_data: *mut c_void) -> vk::Result {
    guard("vkGetPipelineCacheData", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() || get::<PipelineCache>(cache.as_raw()).is_none() || p_size.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        let p = super::physical_device::properties();
        let data = PipelineCache::data(p.vendor_id, p.device_id, p.pipeline_cache_uuid);
        // SAFETY: p_size is valid; p_data null or valid for *p_size bytes per the spec.
        unsafe {
            if p_data.is_null() {
                *p_size = data.len();
                return vk::Result::SUCCESS;
            }
            // The header is all or nothing: a shorter buffer gets no bytes (the spec's rule).
            if *p_size < data.len() {
                *p_size = 0;
                return vk::Result::INCOMPLETE;
            }
            std::ptr::copy_nonoverlapping(data.as_ptr(), p_data as *mut u8, data.len());
            *p_size = data.len();
        }
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn merge_pipeline_caches(device: vk::Device, _dst: vk::PipelineCache, _count: u32, _p_src: *const vk::PipelineCache) -> vk::Result {
    guard("vkMergePipelineCaches", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device("vkMergePipelineCaches");
        }
        vk::Result::SUCCESS
    })
}

// --- commands ---------------------------------------------------------------------------------

fn compute_bind_point(c: &CommandBuffer, bind_point: vk::PipelineBindPoint, command: &str, vuid: &str) -> bool {
    if bind_point != vk::PipelineBindPoint::COMPUTE {
        c.violation(vuid, command, &format!("bind point {bind_point:?}: Arbor has only compute pipelines"));
        return false;
    }
    true
}

unsafe extern "system" fn cmd_bind_pipeline(cb: vk::CommandBuffer, bind_point: vk::PipelineBindPoint, pipeline: vk::Pipeline) {
    const CMD: &str = "vkCmdBindPipeline";
    guard(CMD, (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        if !compute_bind_point(&c, bind_point, CMD, "VUID-vkCmdBindPipeline-pipelineBindPoint-00777") {
            return;
        }
        match get::<ComputePipeline>(pipeline.as_raw()) {
            Some(p) => {
                c.compute_state(CMD, |s| s.pipeline = Some(p));
            }
            None => c.violation("VUID-vkCmdBindPipeline-pipeline-parameter", CMD, "pipeline is not a live compute pipeline"),
        }
    })
}

unsafe extern "system" fn cmd_bind_descriptor_sets(
    cb: vk::CommandBuffer,
    bind_point: vk::PipelineBindPoint,
    _layout: vk::PipelineLayout,
    first_set: u32,
    count: u32,
    p_sets: *const vk::DescriptorSet,
    dynamic_count: u32,
    p_dynamic_offsets: *const u32,
) {
    const CMD: &str = "vkCmdBindDescriptorSets";
    guard(CMD, (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        if !compute_bind_point(&c, bind_point, CMD, "VUID-vkCmdBindDescriptorSets-pipelineBindPoint-00361") {
            return;
        }
        // SAFETY: valid arrays of their counts per the spec.
        let (handles, offsets) = unsafe { (util::slice(p_sets, count), util::slice(p_dynamic_offsets, dynamic_count)) };
        let mut sets = Vec::with_capacity(handles.len());
        for h in handles {
            match get::<DescriptorSet>(h.as_raw()) {
                Some(s) => sets.push(s),
                None => return c.violation("VUID-vkCmdBindDescriptorSets-pDescriptorSets-parameter", CMD, "pDescriptorSets[i] is not a live descriptor set"),
            }
        }
        if let Some(Err(v)) = c.compute_state(CMD, |s| s.bind_sets(first_set, sets, offsets)) {
            c.violation(v.vuid, CMD, &v.message);
        }
    })
}

unsafe extern "system" fn cmd_push_constants(
    cb: vk::CommandBuffer,
    layout: vk::PipelineLayout,
    stages: vk::ShaderStageFlags,
    offset: u32,
    size: u32,
    p_values: *const c_void,
) {
    const CMD: &str = "vkCmdPushConstants";
    guard(CMD, (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        let Some(l) = get::<PipelineLayout>(layout.as_raw()) else {
            return c.violation("VUID-vkCmdPushConstants-layout-parameter", CMD, "layout is not a live pipeline layout");
        };
        let end = offset as u64 + size as u64;
        let covered = l.push_constant_ranges.iter().any(|r| r.stage_flags.contains(stages) && r.offset <= offset && end <= (r.offset + r.size) as u64);
        if !covered {
            return c.violation("VUID-vkCmdPushConstants-offset-01795", CMD, &format!("bytes [{offset}, {end}) for {stages:?} are not inside one of the layout's push-constant ranges"));
        }
        // SAFETY: pValues is valid for `size` bytes per the spec.
        let data = unsafe { util::slice(p_values as *const u8, size) };
        c.compute_state(CMD, |s| s.push(offset, data));
    })
}

/// Snapshot the bound compute state into a recorded dispatch.
fn record_dispatch(cb: vk::CommandBuffer, name: &'static str, size: DispatchSize) {
    let Some(c) = command_buffer_from(cb) else { return };
    let Some(state) = c.compute_state(name, |s| s.clone()) else { return };
    let Some(pipeline) = state.pipeline else {
        let vuid = if name == "vkCmdDispatchIndirect" { "VUID-vkCmdDispatchIndirect-None-08606" } else { "VUID-vkCmdDispatch-None-08606" };
        return c.violation(vuid, name, "no compute pipeline is bound");
    };
    if let DispatchSize::Direct { base, .. } = &size {
        if *base != [0; 3] && !pipeline.dispatch_base {
            return c.violation("VUID-vkCmdDispatchBase-baseGroupX-00427", name, &format!("base {base:?} needs a pipeline created with VK_PIPELINE_CREATE_DISPATCH_BASE_BIT"));
        }
    }
    let max_groups = super::physical_device::limits().max_compute_work_group_count;
    c.record_custom(Box::new(Dispatch { name, pipeline, sets: state.sets, push_constants: state.push_constants, size, max_groups }));
}

fn check_groups(cb: vk::CommandBuffer, name: &'static str, groups: [u32; 3], base: [u32; 3]) -> bool {
    let max = super::physical_device::limits().max_compute_work_group_count;
    for i in 0..3 {
        if base[i] as u64 + groups[i] as u64 > max[i] as u64 {
            if let Some(c) = command_buffer_from(cb) {
                let vuid = ["VUID-vkCmdDispatch-groupCountX-00386", "VUID-vkCmdDispatch-groupCountY-00387", "VUID-vkCmdDispatch-groupCountZ-00388"][i];
                c.violation(vuid, name, &format!("{} + {} workgroups exceed maxComputeWorkGroupCount {}", base[i], groups[i], max[i]));
            }
            return false;
        }
    }
    true
}

unsafe extern "system" fn cmd_dispatch(cb: vk::CommandBuffer, x: u32, y: u32, z: u32) {
    guard("vkCmdDispatch", (), || {
        if check_groups(cb, "vkCmdDispatch", [x, y, z], [0; 3]) {
            record_dispatch(cb, "vkCmdDispatch", DispatchSize::Direct { groups: [x, y, z], base: [0; 3] });
        }
    })
}

unsafe extern "system" fn cmd_dispatch_base(cb: vk::CommandBuffer, bx: u32, by: u32, bz: u32, x: u32, y: u32, z: u32) {
    guard("vkCmdDispatchBase", (), || {
        if check_groups(cb, "vkCmdDispatchBase", [x, y, z], [bx, by, bz]) {
            record_dispatch(cb, "vkCmdDispatchBase", DispatchSize::Direct { groups: [x, y, z], base: [bx, by, bz] });
        }
    })
}

unsafe extern "system" fn cmd_dispatch_indirect(cb: vk::CommandBuffer, buffer: vk::Buffer, offset: vk::DeviceSize) {
    const CMD: &str = "vkCmdDispatchIndirect";
    guard(CMD, (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        let Some(b) = buffer_from(buffer) else {
            return c.violation("VUID-vkCmdDispatchIndirect-buffer-parameter", CMD, "buffer is not a live buffer");
        };
        if !b.usage.contains(vk::BufferUsageFlags::INDIRECT_BUFFER) {
            return c.violation("VUID-vkCmdDispatchIndirect-buffer-02709", CMD, "the buffer lacks INDIRECT_BUFFER usage");
        }
        if !offset.is_multiple_of(4) || offset.checked_add(12).is_none_or(|end| end > b.size) {
            return c.violation("VUID-vkCmdDispatchIndirect-offset-00407", CMD, &format!("offset {offset}: the 12-byte record must be 4-aligned and inside the buffer (size {})", b.size));
        }
        record_dispatch(cb, CMD, DispatchSize::Indirect { buffer: b, offset });
    })
}

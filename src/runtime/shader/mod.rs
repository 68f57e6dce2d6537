//! Compute pipelines on the Vulkan side: shader modules, compute pipelines and pipeline caches
//! as objects, the compute state a command buffer binds ([`BindState`]) and the dispatch
//! commands that run `crate::shader` on the queue worker (`dispatch`), with the library's
//! [`crate::shader::Memory`] implemented over `src/memory` (`memory`).
//!
//! Everything that can make a module unrunnable is found when the pipeline is created (the
//! library parses and lowers there); a dispatch only resolves descriptors and runs. This module
//! owns no handles and reads no application pointers (that is `dispatch::pipeline`).
use std::sync::Arc;

use ash::vk;

use crate::runtime::descriptor::{DescriptorSet, PipelineLayout, Violation};
use crate::shader::{self as lib, ShaderError};

mod dispatch;
pub mod memory;

pub use dispatch::{watchdog_seconds, Dispatch, DispatchSize};

/// One `VkShaderModule`: the words as parsed. A module the library cannot read is kept with
/// its error, which pipeline creation reports (the spec lets creation of the module succeed;
/// the failure belongs to the pipeline that uses it).
pub struct ShaderModule {
    pub parsed: Result<Arc<lib::Module>, ShaderError>,
}

impl ShaderModule {
    pub fn new(words: &[u32]) -> ShaderModule {
        ShaderModule { parsed: lib::Module::parse(words).map(Arc::new) }
    }
}

/// One compute `VkPipeline`: the specialised, lowered entry point and the layout it was made
/// with (bind-time checks compare against it).
pub struct ComputePipeline {
    pub pipeline: lib::Pipeline,
    pub layout: Arc<PipelineLayout>,
    /// Created with VK_PIPELINE_CREATE_DISPATCH_BASE_BIT (vkCmdDispatchBase may use a base).
    pub dispatch_base: bool,
}

/// Why a compute pipeline could not be created.
#[derive(Debug)]
pub enum PipelineError {
    /// The library cannot run the module (unsupported capability, opcode…): VK_ERROR_UNKNOWN.
    Shader(ShaderError),
    /// The create info breaks a valid-usage rule (layout does not match the shader…).
    Invalid(Violation),
}

/// Device limits a pipeline must respect.
#[derive(Clone, Copy, Debug)]
pub struct ComputeLimits {
    pub max_group_size: [u32; 3],
    pub max_group_invocations: u32,
    pub max_shared_memory: u32,
}

fn invalid(vuid: &'static str, message: String) -> PipelineError {
    PipelineError::Invalid(Violation { vuid, message })
}

impl ComputePipeline {
    /// vkCreateComputePipelines for one create info, after lowering: the module (or its parse
    /// error), the entry point, the specialization data (SpecId, bytes), the layout.
    pub fn new(
        module: &ShaderModule,
        entry_point: &str,
        specialization: &[(u32, Vec<u8>)],
        layout: Arc<PipelineLayout>,
        flags: vk::PipelineCreateFlags,
        limits: &ComputeLimits,
    ) -> Result<ComputePipeline, PipelineError> {
        let parsed = module.parsed.as_ref().map_err(|e| PipelineError::Shader(e.clone()))?;
        let pipeline = lib::Pipeline::compute(parsed, entry_point, specialization).map_err(PipelineError::Shader)?;
        for b in pipeline.bindings() {
            let found = layout.set_layouts.get(b.set as usize).and_then(|l| l.binding(b.binding));
            let Some(found) = found else {
                return Err(invalid(
                    "VUID-VkComputePipelineCreateInfo-layout-07988",
                    format!("the shader uses set {} binding {} which the pipeline layout does not declare", b.set, b.binding),
                ));
            };
            if found.count < b.count {
                return Err(invalid(
                    "VUID-VkComputePipelineCreateInfo-layout-07991",
                    format!("the shader declares set {} binding {} as an array of {} but the layout's descriptorCount is {}", b.set, b.binding, b.count, found.count),
                ));
            }
        }
        let push = pipeline.push_constant_size;
        if push > 0 {
            let covered = layout
                .push_constant_ranges
                .iter()
                .filter(|r| r.stage_flags.contains(vk::ShaderStageFlags::COMPUTE))
                .any(|r| r.offset + r.size >= push);
            if !covered {
                return Err(invalid(
                    "VUID-VkComputePipelineCreateInfo-layout-07987",
                    format!("the shader reads {push} bytes of push constants but the layout has no compute push-constant range for them"),
                ));
            }
        }
        let [x, y, z] = pipeline.local_size;
        let m = limits.max_group_size;
        if x > m[0] || y > m[1] || z > m[2] || x as u64 * y as u64 * z as u64 > limits.max_group_invocations as u64 {
            return Err(invalid(
                "VUID-RuntimeSpirv-x-06429",
                format!("workgroup size {x}×{y}×{z} exceeds maxComputeWorkGroupSize {m:?} / maxComputeWorkGroupInvocations {}", limits.max_group_invocations),
            ));
        }
        if pipeline.workgroup_memory_size() > limits.max_shared_memory {
            return Err(invalid(
                "VUID-RuntimeSpirv-Workgroup-06530",
                format!("{} bytes of shared memory exceed maxComputeSharedMemorySize {}", pipeline.workgroup_memory_size(), limits.max_shared_memory),
            ));
        }
        Ok(ComputePipeline { pipeline, layout, dispatch_base: flags.contains(vk::PipelineCreateFlags::DISPATCH_BASE) })
    }
}

/// One `VkPipelineCache`. Arbor's pipelines cost microseconds to create, so the cache keeps
/// nothing; its data is the header the spec requires, so applications can store and reload it.
pub struct PipelineCache;

impl PipelineCache {
    /// The cache's data: VkPipelineCacheHeaderVersionOne and nothing after it.
    pub fn data(vendor_id: u32, device_id: u32, uuid: [u8; 16]) -> Vec<u8> {
        let mut out = Vec::with_capacity(32);
        out.extend_from_slice(&32u32.to_le_bytes());
        out.extend_from_slice(&(vk::PipelineCacheHeaderVersion::ONE.as_raw() as u32).to_le_bytes());
        out.extend_from_slice(&vendor_id.to_le_bytes());
        out.extend_from_slice(&device_id.to_le_bytes());
        out.extend_from_slice(&uuid);
        out
    }
}

/// A descriptor set as bound: the set and the dynamic offsets that came with it.
#[derive(Clone)]
pub struct BoundSet {
    pub set: Arc<DescriptorSet>,
    pub dynamic_offsets: Vec<u32>,
}

/// The compute state of a command buffer: what vkCmdBindPipeline, vkCmdBindDescriptorSets and
/// vkCmdPushConstants set. A dispatch snapshots it (descriptor contents are read when the
/// dispatch executes, as the spec allows).
#[derive(Clone, Default)]
pub struct BindState {
    pub pipeline: Option<Arc<ComputePipeline>>,
    /// Indexed by set number.
    pub sets: Vec<Option<BoundSet>>,
    pub push_constants: Vec<u8>,
}

impl BindState {
    /// vkCmdBindDescriptorSets: bind `sets` from `first`. Each set takes its layout's dynamic
    /// count from `dynamic_offsets`, in order. Returns a violation when the counts disagree.
    pub fn bind_sets(&mut self, first: u32, sets: Vec<Arc<DescriptorSet>>, dynamic_offsets: &[u32]) -> Result<(), Violation> {
        let needed: u32 = sets.iter().map(|s| s.layout.dynamic_count()).sum();
        if needed as usize != dynamic_offsets.len() {
            return Err(Violation {
                vuid: "VUID-vkCmdBindDescriptorSets-dynamicOffsetCount-00359",
                message: format!("{} dynamic offsets given, the sets have {needed} dynamic descriptors", dynamic_offsets.len()),
            });
        }
        let mut offsets = dynamic_offsets;
        for (i, set) in sets.into_iter().enumerate() {
            let n = set.layout.dynamic_count() as usize;
            let slot = first as usize + i;
            if self.sets.len() <= slot {
                self.sets.resize(slot + 1, None);
            }
            self.sets[slot] = Some(BoundSet { set, dynamic_offsets: offsets[..n].to_vec() });
            offsets = &offsets[n..];
        }
        Ok(())
    }

    /// vkCmdPushConstants: bytes at `offset` (the caller checked the range against the layout).
    pub fn push(&mut self, offset: u32, data: &[u8]) {
        let end = offset as usize + data.len();
        if self.push_constants.len() < end {
            self.push_constants.resize(end, 0);
        }
        self.push_constants[offset as usize..end].copy_from_slice(data);
    }
}

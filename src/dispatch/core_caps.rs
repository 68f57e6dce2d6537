//! The Vulkan 1.1 and 1.2 feature and property structs (`VkPhysicalDeviceVulkan11/12*`) and the
//! promoted extension structs they summarise, answered from one place so the aggregate and the
//! individual structs can never disagree.
//!
//! Why Arbor reports Vulkan 1.2: every 1.2 requirement that applies to a device with only
//! compute and transfer queues is met — SPIR-V 1.5 modules (the shader library reads them),
//! timeline semaphores, host query reset, buffer device address, uniformBufferStandardLayout,
//! subgroupBroadcastDynamicId, shaderSubgroupExtendedTypes (the library's subgroup operations
//! work on every integer and float width it runs: 32 and 64 bits). The 1.2 requirements it does
//! not meet are graphics ones with nothing to apply to here: imagelessFramebuffer and
//! separateDepthStencilLayouts (no framebuffers, no depth images) and the render-pass-2 and
//! draw-indirect-count commands (resolved, reporting "not supported"). The README says what is
//! and is not conformant.
use std::ffi::c_void;

use ash::vk;

use super::physical_device::{MAX_ALLOCATION_SIZE, SUBGROUP_OPERATIONS};
use super::util;

/// What Arbor's Vulkan 1.2 features are; the individual promoted structs are derived from it.
pub fn vulkan12_features() -> vk::PhysicalDeviceVulkan12Features<'static> {
    vk::PhysicalDeviceVulkan12Features {
        // Atomics on 64-bit storage-buffer values (Int64Atomics); shared-memory 64-bit atomics
        // are not claimed until a test covers them.
        shader_buffer_int64_atomics: vk::TRUE,
        // Sub-features of descriptor indexing as VK_EXT_descriptor_indexing reports them; the
        // umbrella `descriptorIndexing` stays false because not all of them are supported.
        descriptor_binding_uniform_buffer_update_after_bind: vk::TRUE,
        descriptor_binding_storage_buffer_update_after_bind: vk::TRUE,
        descriptor_binding_update_unused_while_pending: vk::TRUE,
        descriptor_binding_partially_bound: vk::TRUE,
        descriptor_binding_variable_descriptor_count: vk::TRUE,
        // Arrays of storage and uniform buffers, storage images, texel buffers and
        // acceleration structures, sized or runtime, indexed by any value: the executor
        // resolves every element once per dispatch and picks one per lane.
        runtime_descriptor_array: vk::TRUE,
        shader_uniform_buffer_array_non_uniform_indexing: vk::TRUE,
        shader_storage_buffer_array_non_uniform_indexing: vk::TRUE,
        shader_storage_image_array_non_uniform_indexing: vk::TRUE,
        shader_uniform_texel_buffer_array_dynamic_indexing: vk::TRUE,
        shader_storage_texel_buffer_array_dynamic_indexing: vk::TRUE,
        shader_uniform_texel_buffer_array_non_uniform_indexing: vk::TRUE,
        shader_storage_texel_buffer_array_non_uniform_indexing: vk::TRUE,
        uniform_buffer_standard_layout: vk::TRUE,
        shader_subgroup_extended_types: vk::TRUE,
        host_query_reset: vk::TRUE,
        timeline_semaphore: vk::TRUE,
        buffer_device_address: vk::TRUE,
        buffer_device_address_capture_replay: vk::TRUE,
        vulkan_memory_model: vk::TRUE,
        vulkan_memory_model_device_scope: vk::TRUE,
        subgroup_broadcast_dynamic_id: vk::TRUE,
        ..Default::default()
    }
}

/// VkPhysicalDeviceDescriptorIndexingFeatures, derived from the Vulkan 1.2 features (they must
/// agree).
pub fn descriptor_indexing_features() -> vk::PhysicalDeviceDescriptorIndexingFeatures<'static> {
    let f = vulkan12_features();
    vk::PhysicalDeviceDescriptorIndexingFeatures {
        shader_uniform_buffer_array_non_uniform_indexing: f.shader_uniform_buffer_array_non_uniform_indexing,
        shader_storage_buffer_array_non_uniform_indexing: f.shader_storage_buffer_array_non_uniform_indexing,
        shader_storage_image_array_non_uniform_indexing: f.shader_storage_image_array_non_uniform_indexing,
        shader_uniform_texel_buffer_array_dynamic_indexing: f.shader_uniform_texel_buffer_array_dynamic_indexing,
        shader_storage_texel_buffer_array_dynamic_indexing: f.shader_storage_texel_buffer_array_dynamic_indexing,
        shader_uniform_texel_buffer_array_non_uniform_indexing: f.shader_uniform_texel_buffer_array_non_uniform_indexing,
        shader_storage_texel_buffer_array_non_uniform_indexing: f.shader_storage_texel_buffer_array_non_uniform_indexing,
        descriptor_binding_uniform_buffer_update_after_bind: f.descriptor_binding_uniform_buffer_update_after_bind,
        descriptor_binding_storage_buffer_update_after_bind: f.descriptor_binding_storage_buffer_update_after_bind,
        descriptor_binding_update_unused_while_pending: f.descriptor_binding_update_unused_while_pending,
        descriptor_binding_partially_bound: f.descriptor_binding_partially_bound,
        descriptor_binding_variable_descriptor_count: f.descriptor_binding_variable_descriptor_count,
        runtime_descriptor_array: f.runtime_descriptor_array,
        ..Default::default()
    }
}

/// Fill a Vulkan 1.1/1.2 feature struct (aggregate or promoted). False for other sTypes.
///
/// # Safety
/// `p` points to a writable struct of type `s_type`.
pub unsafe fn fill_feature_struct(s_type: vk::StructureType, p: *mut c_void) -> bool {
    let f = vulkan12_features();
    // SAFETY: (each arm) the sType identifies the struct; write_keep_chain preserves pNext.
    unsafe {
        match s_type {
            vk::StructureType::PHYSICAL_DEVICE_VULKAN_1_1_FEATURES => util::write_keep_chain(
                // multiview is required by Vulkan 1.1; without graphics queues it has no effect.
                p,
                vk::PhysicalDeviceVulkan11Features { multiview: vk::TRUE, ..Default::default() },
            ),
            vk::StructureType::PHYSICAL_DEVICE_VULKAN_1_2_FEATURES => util::write_keep_chain(p, f),
            vk::StructureType::PHYSICAL_DEVICE_SHADER_ATOMIC_INT64_FEATURES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceShaderAtomicInt64Features {
                    shader_buffer_int64_atomics: f.shader_buffer_int64_atomics,
                    shader_shared_int64_atomics: f.shader_shared_int64_atomics,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_UNIFORM_BUFFER_STANDARD_LAYOUT_FEATURES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceUniformBufferStandardLayoutFeatures { uniform_buffer_standard_layout: f.uniform_buffer_standard_layout, ..Default::default() },
            ),
            vk::StructureType::PHYSICAL_DEVICE_SHADER_SUBGROUP_EXTENDED_TYPES_FEATURES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceShaderSubgroupExtendedTypesFeatures { shader_subgroup_extended_types: f.shader_subgroup_extended_types, ..Default::default() },
            ),
            vk::StructureType::PHYSICAL_DEVICE_VULKAN_MEMORY_MODEL_FEATURES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceVulkanMemoryModelFeatures {
                    vulkan_memory_model: f.vulkan_memory_model,
                    vulkan_memory_model_device_scope: f.vulkan_memory_model_device_scope,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_SHADER_FLOAT16_INT8_FEATURES => {
                util::write_keep_chain(p, vk::PhysicalDeviceShaderFloat16Int8Features::default())
            }
            vk::StructureType::PHYSICAL_DEVICE_8BIT_STORAGE_FEATURES => util::write_keep_chain(p, vk::PhysicalDevice8BitStorageFeatures::default()),
            vk::StructureType::PHYSICAL_DEVICE_SCALAR_BLOCK_LAYOUT_FEATURES => {
                util::write_keep_chain(p, vk::PhysicalDeviceScalarBlockLayoutFeatures::default())
            }
            vk::StructureType::PHYSICAL_DEVICE_IMAGELESS_FRAMEBUFFER_FEATURES => {
                util::write_keep_chain(p, vk::PhysicalDeviceImagelessFramebufferFeatures::default())
            }
            vk::StructureType::PHYSICAL_DEVICE_SEPARATE_DEPTH_STENCIL_LAYOUTS_FEATURES => {
                util::write_keep_chain(p, vk::PhysicalDeviceSeparateDepthStencilLayoutsFeatures::default())
            }
            _ => return false,
        }
    }
    true
}

fn driver_name() -> [std::ffi::c_char; vk::MAX_DRIVER_NAME_SIZE] {
    let mut n = [0; vk::MAX_DRIVER_NAME_SIZE];
    util::write_name(&mut n, "Arbor");
    n
}

fn driver_info() -> [std::ffi::c_char; vk::MAX_DRIVER_INFO_SIZE] {
    let mut n = [0; vk::MAX_DRIVER_INFO_SIZE];
    util::write_name(&mut n, "CPU driver; compute shaders as native code (Cranelift) or through a SIMD-lane interpreter");
    n
}

/// Arbor has no registered VkDriverId; 0 is not one of the registered values, so no tool
/// mistakes Arbor for another driver. conformanceVersion is 0.0.0.0: not conformance-tested.
const DRIVER_ID: vk::DriverId = vk::DriverId::from_raw(0);

/// The Vulkan 1.1 properties.
pub fn vulkan11_properties() -> vk::PhysicalDeviceVulkan11Properties<'static> {
    vk::PhysicalDeviceVulkan11Properties {
        device_uuid: crate::DEVICE_UUID,
        driver_uuid: crate::DRIVER_UUID,
        subgroup_size: crate::shader::LANES as u32,
        subgroup_supported_stages: vk::ShaderStageFlags::COMPUTE,
        subgroup_supported_operations: SUBGROUP_OPERATIONS,
        point_clipping_behavior: vk::PointClippingBehavior::ALL_CLIP_PLANES,
        max_multiview_view_count: 6,
        max_multiview_instance_index: (1 << 27) - 1,
        max_per_set_descriptors: 1 << 20,
        max_memory_allocation_size: MAX_ALLOCATION_SIZE,
        ..Default::default()
    }
}

/// The Vulkan 1.2 properties (descriptor-indexing limits as VK_EXT_descriptor_indexing's).
pub fn vulkan12_properties() -> vk::PhysicalDeviceVulkan12Properties<'static> {
    vk::PhysicalDeviceVulkan12Properties {
        driver_id: DRIVER_ID,
        driver_name: driver_name(),
        driver_info: driver_info(),
        conformance_version: vk::ConformanceVersion::default(),
        denorm_behavior_independence: vk::ShaderFloatControlsIndependence::NONE,
        rounding_mode_independence: vk::ShaderFloatControlsIndependence::NONE,
        robust_buffer_access_update_after_bind: vk::TRUE,
        max_update_after_bind_descriptors_in_all_pools: 1 << 20,
        max_per_stage_descriptor_update_after_bind_samplers: 16,
        max_per_stage_descriptor_update_after_bind_uniform_buffers: 12,
        max_per_stage_descriptor_update_after_bind_storage_buffers: 500_000,
        max_per_stage_descriptor_update_after_bind_sampled_images: 16,
        max_per_stage_descriptor_update_after_bind_storage_images: 4,
        max_per_stage_descriptor_update_after_bind_input_attachments: 4,
        max_per_stage_update_after_bind_resources: 500_000,
        max_descriptor_set_update_after_bind_samplers: 96,
        max_descriptor_set_update_after_bind_uniform_buffers: 72,
        max_descriptor_set_update_after_bind_uniform_buffers_dynamic: 8,
        max_descriptor_set_update_after_bind_storage_buffers: 500_000,
        max_descriptor_set_update_after_bind_storage_buffers_dynamic: 8,
        max_descriptor_set_update_after_bind_sampled_images: 96,
        max_descriptor_set_update_after_bind_storage_images: 24,
        max_descriptor_set_update_after_bind_input_attachments: 4,
        max_timeline_semaphore_value_difference: u64::MAX >> 1,
        framebuffer_integer_color_sample_counts: vk::SampleCountFlags::TYPE_1,
        ..Default::default()
    }
}

/// Fill a Vulkan 1.1/1.2 property struct (aggregate, or promoted and not answered elsewhere).
/// False for other sTypes.
///
/// # Safety
/// `p` points to a writable struct of type `s_type`.
pub unsafe fn fill_property_struct(s_type: vk::StructureType, p: *mut c_void) -> bool {
    let v12 = vulkan12_properties();
    // SAFETY: (each arm) the sType identifies the struct; write_keep_chain preserves pNext.
    unsafe {
        match s_type {
            vk::StructureType::PHYSICAL_DEVICE_VULKAN_1_1_PROPERTIES => util::write_keep_chain(p, vulkan11_properties()),
            vk::StructureType::PHYSICAL_DEVICE_VULKAN_1_2_PROPERTIES => util::write_keep_chain(p, v12),
            vk::StructureType::PHYSICAL_DEVICE_DRIVER_PROPERTIES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceDriverProperties {
                    driver_id: v12.driver_id,
                    driver_name: v12.driver_name,
                    driver_info: v12.driver_info,
                    conformance_version: v12.conformance_version,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_FLOAT_CONTROLS_PROPERTIES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceFloatControlsProperties {
                    denorm_behavior_independence: v12.denorm_behavior_independence,
                    rounding_mode_independence: v12.rounding_mode_independence,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_DEPTH_STENCIL_RESOLVE_PROPERTIES => {
                util::write_keep_chain(p, vk::PhysicalDeviceDepthStencilResolveProperties::default())
            }
            vk::StructureType::PHYSICAL_DEVICE_SAMPLER_FILTER_MINMAX_PROPERTIES => {
                util::write_keep_chain(p, vk::PhysicalDeviceSamplerFilterMinmaxProperties::default())
            }
            _ => return false,
        }
    }
    true
}

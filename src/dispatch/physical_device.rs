//! Physical-device queries: features, properties, queues, memory, extensions (formats are
//! `format`'s).
//! Every `*2` query walks its pNext chain and fills the structs Arbor knows; unknown ones are
//! skipped untouched.
use std::ffi::{c_char, c_void};
use std::sync::Arc;

use ash::vk;

use super::handle::dispatchable;
use super::instance::PhysicalDeviceHandle;
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::runtime::PhysicalDevice;

/// Device extensions Arbor advertises, with spec versions. Only what works.
pub const DEVICE_EXTENSIONS: &[(&str, u32)] = &[
    ("VK_KHR_acceleration_structure", 13),
    ("VK_KHR_bind_memory2", 1),
    ("VK_KHR_buffer_device_address", 1),
    (super::nv_cluster::EXTENSION_NAME, super::nv_cluster::SPEC_VERSION),
    ("VK_KHR_copy_commands2", 1),
    ("VK_KHR_dedicated_allocation", 3),
    ("VK_KHR_deferred_host_operations", 4),
    ("VK_EXT_descriptor_indexing", 2),
    ("VK_KHR_get_memory_requirements2", 1),
    ("VK_EXT_host_query_reset", 1),
    ("VK_KHR_maintenance1", 2),
    ("VK_KHR_maintenance2", 1),
    ("VK_KHR_maintenance3", 1),
    ("VK_KHR_ray_query", 1),
    ("VK_KHR_ray_tracing_maintenance1", 1),
    ("VK_KHR_synchronization2", 1),
    ("VK_KHR_timeline_semaphore", 2),
    (super::nv_partitioned::EXTENSION_NAME, super::nv_partitioned::SPEC_VERSION),
];

pub const QUEUE_FAMILY_COUNT: u32 = 1;
pub const QUEUE_COUNT: u32 = 4;
pub const MEMORY_TYPE_FLAGS: vk::MemoryPropertyFlags = vk::MemoryPropertyFlags::from_raw(
    vk::MemoryPropertyFlags::DEVICE_LOCAL.as_raw()
        | vk::MemoryPropertyFlags::HOST_VISIBLE.as_raw()
        | vk::MemoryPropertyFlags::HOST_COHERENT.as_raw()
        | vk::MemoryPropertyFlags::HOST_CACHED.as_raw(),
);
/// Acceleration-structure limits: the spec's minimums or more (maxPrimitiveCount 2^29-1 is
/// required; the counts are 32-bit in the API and the format addresses up to 2^32-1 primitives).
pub const MAX_GEOMETRY_COUNT: u64 = (1 << 24) - 1;
pub const MAX_INSTANCE_COUNT: u64 = (1 << 24) - 1;
pub const MAX_PRIMITIVE_COUNT: u64 = (1 << 29) - 1;
/// Largest single allocation (also maxMemoryAllocationSize).
pub const MAX_ALLOCATION_SIZE: u64 = 1 << 40;

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkGetPhysicalDeviceFeatures => get_physical_device_features),
        imp!(PFN_vkGetPhysicalDeviceFeatures2 => get_physical_device_features2),
        imp!(PFN_vkGetPhysicalDeviceProperties => get_physical_device_properties),
        imp!(PFN_vkGetPhysicalDeviceProperties2 => get_physical_device_properties2),
        imp!(PFN_vkGetPhysicalDeviceQueueFamilyProperties => get_physical_device_queue_family_properties),
        imp!(PFN_vkGetPhysicalDeviceQueueFamilyProperties2 => get_physical_device_queue_family_properties2),
        imp!(PFN_vkGetPhysicalDeviceMemoryProperties => get_physical_device_memory_properties),
        imp!(PFN_vkGetPhysicalDeviceMemoryProperties2 => get_physical_device_memory_properties2),
        imp!(PFN_vkGetPhysicalDeviceExternalBufferProperties => get_physical_device_external_buffer_properties),
        imp!(PFN_vkGetPhysicalDeviceExternalFenceProperties => get_physical_device_external_fence_properties),
        imp!(PFN_vkGetPhysicalDeviceExternalSemaphoreProperties => get_physical_device_external_semaphore_properties),
        imp!(PFN_vkEnumerateDeviceExtensionProperties => enumerate_device_extension_properties),
        imp!(PFN_vkEnumerateDeviceLayerProperties => enumerate_device_layer_properties),
    ]
}

pub fn physical_from(h: vk::PhysicalDevice) -> Option<Arc<PhysicalDevice>> {
    // SAFETY: a non-null VkPhysicalDevice is a live handle we created (application obligation).
    unsafe { dispatchable::<PhysicalDevice>(vk::Handle::as_raw(h) as PhysicalDeviceHandle) }
}

/// Subgroup operations the shader library implements (not clustered, not quad).
pub const SUBGROUP_OPERATIONS: vk::SubgroupFeatureFlags = vk::SubgroupFeatureFlags::from_raw(
    vk::SubgroupFeatureFlags::BASIC.as_raw()
        | vk::SubgroupFeatureFlags::VOTE.as_raw()
        | vk::SubgroupFeatureFlags::BALLOT.as_raw()
        | vk::SubgroupFeatureFlags::ARITHMETIC.as_raw()
        | vk::SubgroupFeatureFlags::SHUFFLE.as_raw()
        | vk::SubgroupFeatureFlags::SHUFFLE_RELATIVE.as_raw(),
);

/// Core 1.0 features. Only what Arbor really does; robustBufferAccess is required by the spec
/// (the shader library contains out-of-range accesses); shaderInt64/shaderFloat64 are
/// capabilities the shader library runs; storage images without a declared format are read
/// and written through the view's format, which the library knows.
pub fn features() -> vk::PhysicalDeviceFeatures {
    vk::PhysicalDeviceFeatures {
        robust_buffer_access: vk::TRUE,
        // Arrays of buffers and storage images indexed by dynamically uniform values (the
        // library resolves each element per lane, so non-uniform indices work too).
        shader_uniform_buffer_array_dynamic_indexing: vk::TRUE,
        shader_storage_buffer_array_dynamic_indexing: vk::TRUE,
        shader_storage_image_array_dynamic_indexing: vk::TRUE,
        shader_storage_image_read_without_format: vk::TRUE,
        shader_storage_image_write_without_format: vk::TRUE,
        shader_int64: vk::TRUE,
        shader_float64: vk::TRUE,
        // Buffers only (docs/ROBUSTNESS.md, section 4): sparseResidency* and sparse images stay off.
        sparse_binding: vk::TRUE,
        ..Default::default()
    }
}

unsafe extern "system" fn get_physical_device_features(pd: vk::PhysicalDevice, p: *mut vk::PhysicalDeviceFeatures) {
    guard("vkGetPhysicalDeviceFeatures", (), || {
        if physical_from(pd).is_some() {
            // SAFETY: valid output pointer per the spec.
            unsafe { util::out(p, features()) };
        }
    })
}

/// Fill one extension feature struct of a pNext chain. Returns false for unknown sTypes.
///
/// # Safety
/// `p` points to a writable struct of type `s_type`.
// One function: a table, one match arm per feature struct of the chain.
pub unsafe fn fill_feature_struct(s_type: vk::StructureType, p: *mut c_void) -> bool {
    // SAFETY: (each arm) the sType identifies the struct; write_keep_chain preserves pNext.
    unsafe {
        match s_type {
            vk::StructureType::PHYSICAL_DEVICE_BUFFER_DEVICE_ADDRESS_FEATURES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceBufferDeviceAddressFeatures {
                    buffer_device_address: vk::TRUE,
                    buffer_device_address_capture_replay: vk::TRUE,
                    buffer_device_address_multi_device: vk::FALSE,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_DESCRIPTOR_INDEXING_FEATURES => util::write_keep_chain(
                p,
                super::core_caps::descriptor_indexing_features(),
            ),
            vk::StructureType::PHYSICAL_DEVICE_TIMELINE_SEMAPHORE_FEATURES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceTimelineSemaphoreFeatures { timeline_semaphore: vk::TRUE, ..Default::default() },
            ),
            vk::StructureType::PHYSICAL_DEVICE_SYNCHRONIZATION_2_FEATURES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceSynchronization2Features { synchronization2: vk::TRUE, ..Default::default() },
            ),
            vk::StructureType::PHYSICAL_DEVICE_ACCELERATION_STRUCTURE_FEATURES_KHR => util::write_keep_chain(
                p,
                vk::PhysicalDeviceAccelerationStructureFeaturesKHR {
                    acceleration_structure: vk::TRUE,
                    acceleration_structure_capture_replay: vk::TRUE,
                    acceleration_structure_indirect_build: vk::TRUE,
                    acceleration_structure_host_commands: vk::TRUE,
                    descriptor_binding_acceleration_structure_update_after_bind: vk::TRUE,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_RAY_QUERY_FEATURES_KHR => {
                util::write_keep_chain(p, vk::PhysicalDeviceRayQueryFeaturesKHR { ray_query: vk::TRUE, ..Default::default() })
            }
            vk::StructureType::PHYSICAL_DEVICE_RAY_TRACING_MAINTENANCE_1_FEATURES_KHR => util::write_keep_chain(
                // No ray-tracing pipelines, so no vkCmdTraceRaysIndirect2KHR.
                p,
                vk::PhysicalDeviceRayTracingMaintenance1FeaturesKHR {
                    ray_tracing_maintenance1: vk::TRUE,
                    ray_tracing_pipeline_trace_rays_indirect2: vk::FALSE,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_HOST_QUERY_RESET_FEATURES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceHostQueryResetFeatures { host_query_reset: vk::TRUE, ..Default::default() },
            ),
            // Vulkan 1.1 feature structs.
            vk::StructureType::PHYSICAL_DEVICE_MULTIVIEW_FEATURES => util::write_keep_chain(
                // multiview is required by Vulkan 1.1; without graphics queues it has no effect.
                p,
                vk::PhysicalDeviceMultiviewFeatures { multiview: vk::TRUE, ..Default::default() },
            ),
            vk::StructureType::PHYSICAL_DEVICE_16BIT_STORAGE_FEATURES => {
                util::write_keep_chain(p, vk::PhysicalDevice16BitStorageFeatures::default())
            }
            vk::StructureType::PHYSICAL_DEVICE_VARIABLE_POINTERS_FEATURES => {
                util::write_keep_chain(p, vk::PhysicalDeviceVariablePointersFeatures::default())
            }
            vk::StructureType::PHYSICAL_DEVICE_PROTECTED_MEMORY_FEATURES => {
                util::write_keep_chain(p, vk::PhysicalDeviceProtectedMemoryFeatures::default())
            }
            vk::StructureType::PHYSICAL_DEVICE_SAMPLER_YCBCR_CONVERSION_FEATURES => {
                util::write_keep_chain(p, vk::PhysicalDeviceSamplerYcbcrConversionFeatures::default())
            }
            vk::StructureType::PHYSICAL_DEVICE_SHADER_DRAW_PARAMETERS_FEATURES => {
                util::write_keep_chain(p, vk::PhysicalDeviceShaderDrawParametersFeatures::default())
            }
            s if s == super::nv_cluster::STYPE_FEATURES => super::nv_cluster::write_features(p),
            _ => return super::nv_partitioned::fill_feature_struct(s_type, p) || super::core_caps::fill_feature_struct(s_type, p),
        }
    }
    true
}

unsafe extern "system" fn get_physical_device_features2(pd: vk::PhysicalDevice, p: *mut vk::PhysicalDeviceFeatures2) {
    guard("vkGetPhysicalDeviceFeatures2", (), || {
        if physical_from(pd).is_none() || p.is_null() {
            return;
        }
        // SAFETY: valid output struct and chain per the spec.
        unsafe {
            (*p).features = features();
            util::for_each_out((*p).p_next, |s, q| {
                fill_feature_struct(s, q);
            });
        }
    })
}

// One function: a table, one line per limit.
pub fn limits() -> vk::PhysicalDeviceLimits {
    vk::PhysicalDeviceLimits {
        max_image_dimension1_d: 4096,
        max_image_dimension2_d: 4096,
        max_image_dimension3_d: 256,
        max_image_dimension_cube: 4096,
        max_image_array_layers: 256,
        max_texel_buffer_elements: 65536,
        max_uniform_buffer_range: 65536,
        max_storage_buffer_range: u32::MAX,
        max_push_constants_size: 128,
        max_memory_allocation_count: 1 << 20,
        max_sampler_allocation_count: 4000,
        buffer_image_granularity: 1,
        // Sparse ranges count against the heap like allocations, so the heap bounds them too.
        sparse_address_space_size: MAX_ALLOCATION_SIZE,
        max_bound_descriptor_sets: 8,
        max_per_stage_descriptor_samplers: 16,
        max_per_stage_descriptor_uniform_buffers: 12,
        max_per_stage_descriptor_storage_buffers: 1 << 20,
        max_per_stage_descriptor_sampled_images: 16,
        max_per_stage_descriptor_storage_images: 4,
        max_per_stage_descriptor_input_attachments: 4,
        max_per_stage_resources: 1 << 20,
        max_descriptor_set_samplers: 96,
        max_descriptor_set_uniform_buffers: 72,
        max_descriptor_set_uniform_buffers_dynamic: 8,
        max_descriptor_set_storage_buffers: 1 << 20,
        max_descriptor_set_storage_buffers_dynamic: 8,
        max_descriptor_set_sampled_images: 96,
        max_descriptor_set_storage_images: 24,
        max_descriptor_set_input_attachments: 4,
        max_vertex_input_attributes: 16,
        max_vertex_input_bindings: 16,
        max_vertex_input_attribute_offset: 2047,
        max_vertex_input_binding_stride: 2048,
        max_vertex_output_components: 64,
        max_fragment_input_components: 64,
        max_fragment_output_attachments: 4,
        max_fragment_combined_output_resources: 4,
        max_compute_shared_memory_size: 32768,
        max_compute_work_group_count: [65535, 65535, 65535],
        max_compute_work_group_invocations: 1024,
        max_compute_work_group_size: [1024, 1024, 64],
        sub_pixel_precision_bits: 4,
        sub_texel_precision_bits: 4,
        mipmap_precision_bits: 4,
        max_draw_indexed_index_value: u32::MAX,
        max_draw_indirect_count: 1,
        max_sampler_lod_bias: 2.0,
        max_sampler_anisotropy: 1.0,
        max_viewports: 1,
        max_viewport_dimensions: [4096, 4096],
        viewport_bounds_range: [-8192.0, 8191.0],
        viewport_sub_pixel_bits: 0,
        min_memory_map_alignment: 64,
        min_texel_buffer_offset_alignment: 16,
        min_uniform_buffer_offset_alignment: 16,
        min_storage_buffer_offset_alignment: 16,
        max_texel_offset: 7,
        min_texel_offset: -8,
        max_texel_gather_offset: 7,
        min_texel_gather_offset: -8,
        max_framebuffer_width: 4096,
        max_framebuffer_height: 4096,
        max_framebuffer_layers: 256,
        framebuffer_color_sample_counts: vk::SampleCountFlags::TYPE_1 | vk::SampleCountFlags::TYPE_4,
        framebuffer_depth_sample_counts: vk::SampleCountFlags::TYPE_1 | vk::SampleCountFlags::TYPE_4,
        framebuffer_stencil_sample_counts: vk::SampleCountFlags::TYPE_1 | vk::SampleCountFlags::TYPE_4,
        framebuffer_no_attachments_sample_counts: vk::SampleCountFlags::TYPE_1 | vk::SampleCountFlags::TYPE_4,
        max_color_attachments: 4,
        sampled_image_color_sample_counts: vk::SampleCountFlags::TYPE_1 | vk::SampleCountFlags::TYPE_4,
        sampled_image_integer_sample_counts: vk::SampleCountFlags::TYPE_1,
        sampled_image_depth_sample_counts: vk::SampleCountFlags::TYPE_1 | vk::SampleCountFlags::TYPE_4,
        sampled_image_stencil_sample_counts: vk::SampleCountFlags::TYPE_1 | vk::SampleCountFlags::TYPE_4,
        storage_image_sample_counts: vk::SampleCountFlags::TYPE_1,
        max_sample_mask_words: 1,
        timestamp_compute_and_graphics: vk::TRUE,
        timestamp_period: 1.0,
        max_clip_distances: 8,
        max_cull_distances: 8,
        max_combined_clip_and_cull_distances: 8,
        discrete_queue_priorities: 2,
        point_size_range: [1.0, 64.0],
        line_width_range: [1.0, 1.0],
        point_size_granularity: 1.0,
        line_width_granularity: 0.0,
        strict_lines: vk::FALSE,
        standard_sample_locations: vk::TRUE,
        optimal_buffer_copy_offset_alignment: 1,
        optimal_buffer_copy_row_pitch_alignment: 1,
        non_coherent_atom_size: 1,
        ..Default::default()
    }
}

pub fn properties() -> vk::PhysicalDeviceProperties {
    let mut p = vk::PhysicalDeviceProperties {
        api_version: crate::API_VERSION,
        driver_version: crate::DRIVER_VERSION,
        vendor_id: 0x10000, // VK_VENDOR_ID_KHRONOS: no PCI vendor; Khronos-registered software id space
        device_id: 0x4152, // "AR"
        device_type: vk::PhysicalDeviceType::CPU,
        limits: limits(),
        sparse_properties: vk::PhysicalDeviceSparseProperties::default(),
        pipeline_cache_uuid: crate::DRIVER_UUID,
        ..Default::default()
    };
    util::write_name(&mut p.device_name, crate::DEVICE_NAME);
    p
}

unsafe extern "system" fn get_physical_device_properties(pd: vk::PhysicalDevice, p: *mut vk::PhysicalDeviceProperties) {
    guard("vkGetPhysicalDeviceProperties", (), || {
        if physical_from(pd).is_some() {
            // SAFETY: valid output pointer per the spec.
            unsafe { util::out(p, properties()) };
        }
    })
}

/// Fill one extension property struct of a pNext chain. Returns false for unknown sTypes.
///
/// # Safety
/// `p` points to a writable struct of type `s_type`.
// One function: a table, one match arm per property struct of the chain.
pub unsafe fn fill_property_struct(s_type: vk::StructureType, p: *mut c_void) -> bool {
    // SAFETY: (each arm) the sType identifies the struct; write_keep_chain preserves pNext.
    unsafe {
        match s_type {
            vk::StructureType::PHYSICAL_DEVICE_ID_PROPERTIES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceIDProperties {
                    device_uuid: crate::DEVICE_UUID,
                    driver_uuid: crate::DRIVER_UUID,
                    device_luid_valid: vk::FALSE,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_MAINTENANCE_3_PROPERTIES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceMaintenance3Properties {
                    max_per_set_descriptors: 1 << 20,
                    max_memory_allocation_size: MAX_ALLOCATION_SIZE,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_SUBGROUP_PROPERTIES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceSubgroupProperties {
                    subgroup_size: crate::shader::LANES as u32,
                    supported_stages: vk::ShaderStageFlags::COMPUTE,
                    supported_operations: SUBGROUP_OPERATIONS,
                    quad_operations_in_all_stages: vk::FALSE,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_POINT_CLIPPING_PROPERTIES => util::write_keep_chain(
                p,
                vk::PhysicalDevicePointClippingProperties {
                    point_clipping_behavior: vk::PointClippingBehavior::ALL_CLIP_PLANES,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_MULTIVIEW_PROPERTIES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceMultiviewProperties {
                    max_multiview_view_count: 6,
                    max_multiview_instance_index: (1 << 27) - 1,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_PROTECTED_MEMORY_PROPERTIES => {
                util::write_keep_chain(p, vk::PhysicalDeviceProtectedMemoryProperties::default())
            }
            // The promoted struct answers what VkPhysicalDeviceVulkan12Properties says (one table).
            vk::StructureType::PHYSICAL_DEVICE_DESCRIPTOR_INDEXING_PROPERTIES => {
                let v12 = super::core_caps::vulkan12_properties();
                let q = vk::PhysicalDeviceDescriptorIndexingProperties {
                    max_update_after_bind_descriptors_in_all_pools: v12.max_update_after_bind_descriptors_in_all_pools,
                    shader_uniform_buffer_array_non_uniform_indexing_native: v12.shader_uniform_buffer_array_non_uniform_indexing_native,
                    shader_sampled_image_array_non_uniform_indexing_native: v12.shader_sampled_image_array_non_uniform_indexing_native,
                    shader_storage_buffer_array_non_uniform_indexing_native: v12.shader_storage_buffer_array_non_uniform_indexing_native,
                    shader_storage_image_array_non_uniform_indexing_native: v12.shader_storage_image_array_non_uniform_indexing_native,
                    shader_input_attachment_array_non_uniform_indexing_native: v12.shader_input_attachment_array_non_uniform_indexing_native,
                    robust_buffer_access_update_after_bind: v12.robust_buffer_access_update_after_bind,
                    quad_divergent_implicit_lod: v12.quad_divergent_implicit_lod,
                    max_per_stage_descriptor_update_after_bind_samplers: v12.max_per_stage_descriptor_update_after_bind_samplers,
                    max_per_stage_descriptor_update_after_bind_uniform_buffers: v12.max_per_stage_descriptor_update_after_bind_uniform_buffers,
                    max_per_stage_descriptor_update_after_bind_storage_buffers: v12.max_per_stage_descriptor_update_after_bind_storage_buffers,
                    max_per_stage_descriptor_update_after_bind_sampled_images: v12.max_per_stage_descriptor_update_after_bind_sampled_images,
                    max_per_stage_descriptor_update_after_bind_storage_images: v12.max_per_stage_descriptor_update_after_bind_storage_images,
                    max_per_stage_descriptor_update_after_bind_input_attachments: v12.max_per_stage_descriptor_update_after_bind_input_attachments,
                    max_per_stage_update_after_bind_resources: v12.max_per_stage_update_after_bind_resources,
                    max_descriptor_set_update_after_bind_samplers: v12.max_descriptor_set_update_after_bind_samplers,
                    max_descriptor_set_update_after_bind_uniform_buffers: v12.max_descriptor_set_update_after_bind_uniform_buffers,
                    max_descriptor_set_update_after_bind_uniform_buffers_dynamic: v12.max_descriptor_set_update_after_bind_uniform_buffers_dynamic,
                    max_descriptor_set_update_after_bind_storage_buffers: v12.max_descriptor_set_update_after_bind_storage_buffers,
                    max_descriptor_set_update_after_bind_storage_buffers_dynamic: v12.max_descriptor_set_update_after_bind_storage_buffers_dynamic,
                    max_descriptor_set_update_after_bind_sampled_images: v12.max_descriptor_set_update_after_bind_sampled_images,
                    max_descriptor_set_update_after_bind_storage_images: v12.max_descriptor_set_update_after_bind_storage_images,
                    max_descriptor_set_update_after_bind_input_attachments: v12.max_descriptor_set_update_after_bind_input_attachments,
                    ..Default::default()
                };
                util::write_keep_chain(p, q)
            }
            vk::StructureType::PHYSICAL_DEVICE_ACCELERATION_STRUCTURE_PROPERTIES_KHR => util::write_keep_chain(
                p,
                vk::PhysicalDeviceAccelerationStructurePropertiesKHR {
                    max_geometry_count: MAX_GEOMETRY_COUNT,
                    max_instance_count: MAX_INSTANCE_COUNT,
                    max_primitive_count: MAX_PRIMITIVE_COUNT,
                    max_per_stage_descriptor_acceleration_structures: 1 << 20,
                    max_per_stage_descriptor_update_after_bind_acceleration_structures: 1 << 20,
                    max_descriptor_set_acceleration_structures: 1 << 20,
                    max_descriptor_set_update_after_bind_acceleration_structures: 1 << 20,
                    min_acceleration_structure_scratch_offset_alignment: crate::runtime::accel::SCRATCH_ALIGNMENT as u32,
                    ..Default::default()
                },
            ),
            vk::StructureType::PHYSICAL_DEVICE_TIMELINE_SEMAPHORE_PROPERTIES => util::write_keep_chain(
                p,
                vk::PhysicalDeviceTimelineSemaphoreProperties {
                    max_timeline_semaphore_value_difference: u64::MAX >> 1,
                    ..Default::default()
                },
            ),
            s if s == super::nv_cluster::STYPE_PROPERTIES => super::nv_cluster::write_properties(p),
            _ => return super::nv_partitioned::fill_property_struct(s_type, p) || super::core_caps::fill_property_struct(s_type, p),
        }
    }
    true
}

unsafe extern "system" fn get_physical_device_properties2(pd: vk::PhysicalDevice, p: *mut vk::PhysicalDeviceProperties2) {
    guard("vkGetPhysicalDeviceProperties2", (), || {
        if physical_from(pd).is_none() || p.is_null() {
            return;
        }
        // SAFETY: valid output struct and chain per the spec.
        unsafe {
            (*p).properties = properties();
            util::for_each_out((*p).p_next, |s, q| {
                fill_property_struct(s, q);
            });
        }
    })
}

pub fn queue_family_properties() -> vk::QueueFamilyProperties {
    vk::QueueFamilyProperties {
        queue_flags: vk::QueueFlags::COMPUTE | vk::QueueFlags::TRANSFER | vk::QueueFlags::SPARSE_BINDING,
        queue_count: QUEUE_COUNT,
        timestamp_valid_bits: 64,
        min_image_transfer_granularity: vk::Extent3D { width: 1, height: 1, depth: 1 },
    }
}

unsafe extern "system" fn get_physical_device_queue_family_properties(
    pd: vk::PhysicalDevice,
    p_count: *mut u32,
    p_props: *mut vk::QueueFamilyProperties,
) {
    guard("vkGetPhysicalDeviceQueueFamilyProperties", (), || {
        if physical_from(pd).is_some() {
            // SAFETY: valid pointers per the spec.
            let _ = unsafe { util::enumerate(&[queue_family_properties()], p_count, p_props) };
        }
    })
}

unsafe extern "system" fn get_physical_device_queue_family_properties2(
    pd: vk::PhysicalDevice,
    p_count: *mut u32,
    p_props: *mut vk::QueueFamilyProperties2,
) {
    guard("vkGetPhysicalDeviceQueueFamilyProperties2", (), || {
        if physical_from(pd).is_none() || p_count.is_null() {
            return;
        }
        // SAFETY: valid pointers per the spec; the output structs keep sType/pNext.
        unsafe {
            if p_props.is_null() {
                *p_count = QUEUE_FAMILY_COUNT;
                return;
            }
            if *p_count >= 1 {
                (*p_props).queue_family_properties = queue_family_properties();
                *p_count = 1;
            }
        }
    })
}

pub fn memory_properties(pd: &PhysicalDevice) -> vk::PhysicalDeviceMemoryProperties {
    let mut m = vk::PhysicalDeviceMemoryProperties { memory_type_count: super::memory::MEMORY_TYPE_COUNT, memory_heap_count: 1, ..Default::default() };
    m.memory_types[0] = vk::MemoryType { property_flags: MEMORY_TYPE_FLAGS, heap_index: 0 };
    // The memory sparse buffers bind (shareable, `memory::sparse`): same properties, same heap.
    m.memory_types[1] = vk::MemoryType { property_flags: MEMORY_TYPE_FLAGS, heap_index: 0 };
    m.memory_heaps[0] = vk::MemoryHeap { size: pd.heap_size, flags: vk::MemoryHeapFlags::DEVICE_LOCAL };
    m
}

unsafe extern "system" fn get_physical_device_memory_properties(pd: vk::PhysicalDevice, p: *mut vk::PhysicalDeviceMemoryProperties) {
    guard("vkGetPhysicalDeviceMemoryProperties", (), || {
        if let Some(pd) = physical_from(pd) {
            // SAFETY: valid output pointer per the spec.
            unsafe { util::out(p, memory_properties(&pd)) };
        }
    })
}

unsafe extern "system" fn get_physical_device_memory_properties2(pd: vk::PhysicalDevice, p: *mut vk::PhysicalDeviceMemoryProperties2) {
    guard("vkGetPhysicalDeviceMemoryProperties2", (), || {
        if let Some(pd) = physical_from(pd) {
            if !p.is_null() {
                // SAFETY: valid output struct per the spec.
                unsafe { (*p).memory_properties = memory_properties(&pd) };
            }
        }
    })
}

unsafe extern "system" fn get_physical_device_external_buffer_properties(
    _pd: vk::PhysicalDevice,
    _info: *const vk::PhysicalDeviceExternalBufferInfo,
    p: *mut vk::ExternalBufferProperties,
) {
    if !p.is_null() {
        // SAFETY: valid output struct per the spec. No external memory handle types.
        unsafe { (*p).external_memory_properties = vk::ExternalMemoryProperties::default() };
    }
}

unsafe extern "system" fn get_physical_device_external_fence_properties(
    _pd: vk::PhysicalDevice,
    _info: *const vk::PhysicalDeviceExternalFenceInfo,
    p: *mut vk::ExternalFenceProperties,
) {
    if !p.is_null() {
        // SAFETY: valid output struct per the spec. No external fence handle types.
        unsafe {
            (*p).export_from_imported_handle_types = vk::ExternalFenceHandleTypeFlags::empty();
            (*p).compatible_handle_types = vk::ExternalFenceHandleTypeFlags::empty();
            (*p).external_fence_features = vk::ExternalFenceFeatureFlags::empty();
        }
    }
}

unsafe extern "system" fn get_physical_device_external_semaphore_properties(
    _pd: vk::PhysicalDevice,
    _info: *const vk::PhysicalDeviceExternalSemaphoreInfo,
    p: *mut vk::ExternalSemaphoreProperties,
) {
    if !p.is_null() {
        // SAFETY: valid output struct per the spec. No external semaphore handle types.
        unsafe {
            (*p).export_from_imported_handle_types = vk::ExternalSemaphoreHandleTypeFlags::empty();
            (*p).compatible_handle_types = vk::ExternalSemaphoreHandleTypeFlags::empty();
            (*p).external_semaphore_features = vk::ExternalSemaphoreFeatureFlags::empty();
        }
    }
}

unsafe extern "system" fn enumerate_device_extension_properties(
    _pd: vk::PhysicalDevice,
    p_layer_name: *const c_char,
    p_count: *mut u32,
    p_props: *mut vk::ExtensionProperties,
) -> vk::Result {
    guard("vkEnumerateDeviceExtensionProperties", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if !p_layer_name.is_null() {
            return vk::Result::ERROR_LAYER_NOT_PRESENT;
        }
        // SAFETY: valid pointers per the spec.
        unsafe { util::enumerate(&super::instance::device_extension_properties(), p_count, p_props) }
    })
}

unsafe extern "system" fn enumerate_device_layer_properties(
    _pd: vk::PhysicalDevice,
    p_count: *mut u32,
    p_props: *mut vk::LayerProperties,
) -> vk::Result {
    // SAFETY: valid pointers per the spec.
    unsafe { util::enumerate::<vk::LayerProperties>(&[], p_count, p_props) }
}

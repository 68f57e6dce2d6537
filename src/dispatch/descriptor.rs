//! Descriptor set layouts, pools, sets and their updates (direct and by template), and
//! pipeline layouts. The objects and their rules live in `runtime::descriptor`; this module
//! converts the application's structs into `Descriptor` values and reports violations.
use std::ffi::c_void;
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::device::device_from;
use super::handle::{get, register, unregister};
use super::memory::buffer_from;
use super::nv_partitioned::{WriteDescriptorSetPartitionedAccelerationStructureNV as PtlasWrite, STRUCTURE_TYPE_WRITE_DESCRIPTOR_SET_PARTITIONED_ACCELERATION_STRUCTURE_NV};
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::diag;
use crate::runtime::accel::AccelerationStructure;
use crate::runtime::image::{BufferView, ImageView};
use crate::runtime::descriptor::{
    acceleration_structure_descriptor, buffer_descriptor, storage_image_descriptor, texel_buffer_descriptor, type_class, AllocateError, BufferLimits, Descriptor, DescriptorPool, DescriptorSet, DescriptorSetLayout,
    DescriptorUpdateTemplate, LayoutBinding, PipelineLayout, TemplateEntry, TypeClass, Violation,
};

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCreateDescriptorSetLayout => create_descriptor_set_layout),
        imp!(PFN_vkDestroyDescriptorSetLayout => destroy_descriptor_set_layout),
        imp!(PFN_vkGetDescriptorSetLayoutSupport => get_descriptor_set_layout_support),
        imp!(PFN_vkCreateDescriptorPool => create_descriptor_pool),
        imp!(PFN_vkDestroyDescriptorPool => destroy_descriptor_pool),
        imp!(PFN_vkResetDescriptorPool => reset_descriptor_pool),
        imp!(PFN_vkAllocateDescriptorSets => allocate_descriptor_sets),
        imp!(PFN_vkFreeDescriptorSets => free_descriptor_sets),
        imp!(PFN_vkUpdateDescriptorSets => update_descriptor_sets),
        imp!(PFN_vkCreateDescriptorUpdateTemplate => create_descriptor_update_template),
        imp!(PFN_vkDestroyDescriptorUpdateTemplate => destroy_descriptor_update_template),
        imp!(PFN_vkUpdateDescriptorSetWithTemplate => update_descriptor_set_with_template),
        imp!(PFN_vkCreatePipelineLayout => create_pipeline_layout),
        imp!(PFN_vkDestroyPipelineLayout => destroy_pipeline_layout),
    ]
}

/// Descriptors one set may hold (maxPerSetDescriptors).
const MAX_PER_SET_DESCRIPTORS: u64 = 1 << 20;

fn report(command: &str, v: &Violation) {
    diag::vuid(v.vuid, command, &v.message);
}

fn invalid(command: &str, v: &Violation) -> vk::Result {
    report(command, v);
    vk::Result::ERROR_VALIDATION_FAILED_EXT
}

fn no_device(command: &str) -> vk::Result {
    report_no_device(command);
    vk::Result::ERROR_VALIDATION_FAILED_EXT
}

fn report_no_device(command: &str) {
    diag::vuid(&format!("VUID-{command}-device-parameter"), command, "device is not a valid VkDevice");
}

fn bad_handle(vuid: &'static str, what: &str) -> Violation {
    Violation { vuid, message: format!("{what} is not a live handle of its type") }
}

fn buffer_limits() -> BufferLimits {
    let l = super::physical_device::limits();
    BufferLimits {
        min_uniform_offset_alignment: l.min_uniform_buffer_offset_alignment,
        min_storage_offset_alignment: l.min_storage_buffer_offset_alignment,
        max_uniform_range: l.max_uniform_buffer_range as u64,
        max_storage_range: l.max_storage_buffer_range as u64,
    }
}

/// Lower a VkDescriptorSetLayoutCreateInfo into a checked layout.
///
/// # Safety
/// `info` is a valid VkDescriptorSetLayoutCreateInfo.
unsafe fn lower_layout(info: &vk::DescriptorSetLayoutCreateInfo) -> Result<DescriptorSetLayout, Violation> {
    // SAFETY: valid arrays and chain per the spec.
    let (bindings, flags_info) = unsafe {
        (
            util::slice(info.p_bindings, info.binding_count),
            util::find_in::<vk::DescriptorSetLayoutBindingFlagsCreateInfo>(
                info.p_next,
                vk::StructureType::DESCRIPTOR_SET_LAYOUT_BINDING_FLAGS_CREATE_INFO,
            ),
        )
    };
    // SAFETY: valid array per the spec.
    let binding_flags = flags_info.map_or(&[][..], |f| unsafe { util::slice(f.p_binding_flags, f.binding_count) });
    if !binding_flags.is_empty() && binding_flags.len() != bindings.len() {
        return Err(Violation {
            vuid: "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-bindingCount-03002",
            message: format!("{} binding flags for {} bindings", binding_flags.len(), bindings.len()),
        });
    }
    let lowered = bindings
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let samplers = matches!(b.descriptor_type, vk::DescriptorType::SAMPLER | vk::DescriptorType::COMBINED_IMAGE_SAMPLER)
                && !b.p_immutable_samplers.is_null();
            LayoutBinding {
                binding: b.binding,
                descriptor_type: b.descriptor_type,
                count: b.descriptor_count,
                stages: b.stage_flags,
                flags: binding_flags.get(i).copied().unwrap_or_default(),
                immutable_samplers: if samplers {
                    // SAFETY: valid array of descriptorCount samplers per the spec.
                    unsafe { util::slice(b.p_immutable_samplers, b.descriptor_count) }.iter().map(|s| s.as_raw()).collect()
                } else {
                    Vec::new()
                },
            }
        })
        .collect();
    DescriptorSetLayout::new(info.flags, lowered)
}

unsafe extern "system" fn create_descriptor_set_layout(
    device: vk::Device,
    p_create_info: *const vk::DescriptorSetLayoutCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_set_layout: *mut vk::DescriptorSetLayout,
) -> vk::Result {
    const CMD: &str = "vkCreateDescriptorSetLayout";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device(CMD);
        }
        if p_create_info.is_null() || p_set_layout.is_null() {
            return invalid(CMD, &Violation { vuid: "VUID-vkCreateDescriptorSetLayout-pCreateInfo-parameter", message: "null pointer".into() });
        }
        // SAFETY: checked non-null; valid per the spec.
        unsafe { *p_set_layout = vk::DescriptorSetLayout::null() };
        // SAFETY: valid create info per the spec.
        match unsafe { lower_layout(&*p_create_info) } {
            Ok(layout) => {
                // SAFETY: checked non-null.
                unsafe { *p_set_layout = vk::DescriptorSetLayout::from_raw(register(Arc::new(layout))) };
                vk::Result::SUCCESS
            }
            Err(v) => invalid(CMD, &v),
        }
    })
}

unsafe extern "system" fn destroy_descriptor_set_layout(
    device: vk::Device,
    layout: vk::DescriptorSetLayout,
    _p_allocator: *const vk::AllocationCallbacks,
) {
    const CMD: &str = "vkDestroyDescriptorSetLayout";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_no_device(CMD);
            return;
        }
        // Sets and pipeline layouts made from it keep their own reference.
        if layout != vk::DescriptorSetLayout::null() && unregister::<DescriptorSetLayout>(layout.as_raw()).is_none() {
            report(CMD, &bad_handle("VUID-vkDestroyDescriptorSetLayout-descriptorSetLayout-parameter", "descriptorSetLayout"));
        }
    })
}

unsafe extern "system" fn get_descriptor_set_layout_support(
    device: vk::Device,
    p_create_info: *const vk::DescriptorSetLayoutCreateInfo,
    p_support: *mut vk::DescriptorSetLayoutSupport,
) {
    const CMD: &str = "vkGetDescriptorSetLayoutSupport";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_no_device(CMD);
            return;
        }
        if p_create_info.is_null() || p_support.is_null() {
            return;
        }
        // SAFETY: valid create info per the spec.
        let layout = unsafe { lower_layout(&*p_create_info) };
        // An invalid layout is simply not supported; the query itself is not an error.
        let (supported, max_variable) = match &layout {
            Ok(l) => {
                let total = l.total_descriptors();
                let variable = l.variable_binding().map(|b| b.count as u64);
                let fixed = total - variable.unwrap_or(0);
                let max_variable = variable.map_or(0, |_| MAX_PER_SET_DESCRIPTORS.saturating_sub(fixed));
                (total <= MAX_PER_SET_DESCRIPTORS, max_variable.min(u32::MAX as u64) as u32)
            }
            Err(_) => (false, 0),
        };
        // SAFETY: valid output struct and chain per the spec; write_keep_chain keeps pNext.
        unsafe {
            (*p_support).supported = supported.into();
            util::for_each_out((*p_support).p_next, |s, p| {
                if s == vk::StructureType::DESCRIPTOR_SET_VARIABLE_DESCRIPTOR_COUNT_LAYOUT_SUPPORT {
                    util::write_keep_chain(
                        p,
                        vk::DescriptorSetVariableDescriptorCountLayoutSupport {
                            max_variable_descriptor_count: if supported { max_variable } else { 0 },
                            ..Default::default()
                        },
                    );
                }
            });
        }
    })
}

unsafe extern "system" fn create_descriptor_pool(
    device: vk::Device,
    p_create_info: *const vk::DescriptorPoolCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_pool: *mut vk::DescriptorPool,
) -> vk::Result {
    const CMD: &str = "vkCreateDescriptorPool";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device(CMD);
        }
        if p_create_info.is_null() || p_pool.is_null() {
            return invalid(CMD, &Violation { vuid: "VUID-vkCreateDescriptorPool-pCreateInfo-parameter", message: "null pointer".into() });
        }
        // SAFETY: checked non-null.
        unsafe { *p_pool = vk::DescriptorPool::null() };
        // SAFETY: valid create info per the spec.
        let info = unsafe { &*p_create_info };
        // SAFETY: valid array per the spec.
        let sizes: Vec<_> = unsafe { util::slice(info.p_pool_sizes, info.pool_size_count) }.iter().map(|s| (s.ty, s.descriptor_count)).collect();
        match DescriptorPool::new(info.flags, info.max_sets, &sizes) {
            Ok(pool) => {
                // SAFETY: checked non-null.
                unsafe { *p_pool = vk::DescriptorPool::from_raw(register(Arc::new(pool))) };
                vk::Result::SUCCESS
            }
            Err(v) => invalid(CMD, &v),
        }
    })
}

/// Retire the handles of sets a pool gave back.
fn retire(sets: Vec<Arc<DescriptorSet>>) {
    for s in sets {
        unregister::<DescriptorSet>(s.handle());
    }
}

unsafe extern "system" fn destroy_descriptor_pool(device: vk::Device, pool: vk::DescriptorPool, _p_allocator: *const vk::AllocationCallbacks) {
    const CMD: &str = "vkDestroyDescriptorPool";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_no_device(CMD);
            return;
        }
        if pool == vk::DescriptorPool::null() {
            return;
        }
        match unregister::<DescriptorPool>(pool.as_raw()) {
            // Destroying a pool frees its sets.
            Some(p) => retire(p.reset()),
            None => report(CMD, &bad_handle("VUID-vkDestroyDescriptorPool-descriptorPool-parameter", "descriptorPool")),
        }
    })
}

unsafe extern "system" fn reset_descriptor_pool(device: vk::Device, pool: vk::DescriptorPool, flags: vk::DescriptorPoolResetFlags) -> vk::Result {
    const CMD: &str = "vkResetDescriptorPool";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device(CMD);
        }
        if !flags.is_empty() {
            return invalid(CMD, &Violation { vuid: "VUID-vkResetDescriptorPool-flags-zerobitmask", message: "flags must be 0".into() });
        }
        match get::<DescriptorPool>(pool.as_raw()) {
            Some(p) => {
                retire(p.reset());
                vk::Result::SUCCESS
            }
            None => invalid(CMD, &bad_handle("VUID-vkResetDescriptorPool-descriptorPool-parameter", "descriptorPool")),
        }
    })
}

unsafe extern "system" fn allocate_descriptor_sets(
    device: vk::Device,
    p_allocate_info: *const vk::DescriptorSetAllocateInfo,
    p_sets: *mut vk::DescriptorSet,
) -> vk::Result {
    const CMD: &str = "vkAllocateDescriptorSets";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device(CMD);
        }
        if p_allocate_info.is_null() || p_sets.is_null() {
            return invalid(CMD, &Violation { vuid: "VUID-vkAllocateDescriptorSets-pAllocateInfo-parameter", message: "null pointer".into() });
        }
        // SAFETY: valid allocate info per the spec.
        let info = unsafe { &*p_allocate_info };
        let n = info.descriptor_set_count as usize;
        // SAFETY: pDescriptorSets has descriptorSetCount elements per the spec; on failure
        // every element is VK_NULL_HANDLE.
        let out = unsafe { std::slice::from_raw_parts_mut(p_sets, n) };
        out.fill(vk::DescriptorSet::null());
        // SAFETY: valid arrays and chain per the spec.
        let (layouts, variable) = unsafe {
            let variable = util::find_in::<vk::DescriptorSetVariableDescriptorCountAllocateInfo>(
                info.p_next,
                vk::StructureType::DESCRIPTOR_SET_VARIABLE_DESCRIPTOR_COUNT_ALLOCATE_INFO,
            );
            (
                util::slice(info.p_set_layouts, info.descriptor_set_count),
                variable.map_or(&[][..], |v| util::slice(v.p_descriptor_counts, v.descriptor_set_count)),
            )
        };
        if !variable.is_empty() && variable.len() != n {
            return invalid(
                CMD,
                &Violation {
                    vuid: "VUID-VkDescriptorSetVariableDescriptorCountAllocateInfo-descriptorSetCount-03045",
                    message: format!("{} variable counts for {n} sets", variable.len()),
                },
            );
        }
        let Some(pool) = get::<DescriptorPool>(info.descriptor_pool.as_raw()) else {
            return invalid(CMD, &bad_handle("VUID-VkDescriptorSetAllocateInfo-descriptorPool-parameter", "descriptorPool"));
        };
        let mut requests = Vec::with_capacity(n);
        for (i, l) in layouts.iter().enumerate() {
            let Some(layout) = get::<DescriptorSetLayout>(l.as_raw()) else {
                return invalid(CMD, &bad_handle("VUID-VkDescriptorSetAllocateInfo-pSetLayouts-parameter", "pSetLayouts[i]"));
            };
            requests.push((layout, variable.get(i).copied()));
        }
        match pool.allocate(&requests) {
            Ok(sets) => {
                for (o, s) in out.iter_mut().zip(sets) {
                    let h = register(s.clone());
                    s.set_handle(h);
                    *o = vk::DescriptorSet::from_raw(h);
                }
                vk::Result::SUCCESS
            }
            Err(AllocateError::OutOfPoolMemory) => vk::Result::ERROR_OUT_OF_POOL_MEMORY,
            Err(AllocateError::Invalid(v)) => invalid(CMD, &v),
        }
    })
}

unsafe extern "system" fn free_descriptor_sets(
    device: vk::Device,
    pool: vk::DescriptorPool,
    count: u32,
    p_sets: *const vk::DescriptorSet,
) -> vk::Result {
    const CMD: &str = "vkFreeDescriptorSets";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device(CMD);
        }
        let Some(pool) = get::<DescriptorPool>(pool.as_raw()) else {
            return invalid(CMD, &bad_handle("VUID-vkFreeDescriptorSets-descriptorPool-parameter", "descriptorPool"));
        };
        // SAFETY: valid array per the spec.
        let handles = unsafe { util::slice(p_sets, count) };
        let mut sets = Vec::with_capacity(handles.len());
        for h in handles.iter().filter(|h| **h != vk::DescriptorSet::null()) {
            match get::<DescriptorSet>(h.as_raw()) {
                Some(s) => sets.push(s),
                None => return invalid(CMD, &bad_handle("VUID-vkFreeDescriptorSets-pDescriptorSets-00310", "a descriptor set")),
            }
        }
        match pool.free(&sets) {
            Ok(()) => {
                retire(sets);
                vk::Result::SUCCESS
            }
            Err(v) => invalid(CMD, &v),
        }
    })
}

/// Convert `count` descriptors of type `t` whose source structs are at `at(i)`: the one place
/// raw descriptor info becomes [`Descriptor`] values (writes and templates both use it).
///
/// # Safety
/// `at(i)` must return a pointer valid for a read of the struct type `t` uses
/// (VkDescriptorBufferInfo, VkDescriptorImageInfo, VkBufferView, VkAccelerationStructureKHR, or
/// the VkDeviceAddress of a partitioned structure),
/// for i in 0..count.
unsafe fn convert(t: vk::DescriptorType, count: u32, at: impl Fn(usize) -> *const u8) -> Result<Vec<Descriptor>, Violation> {
    let limits = buffer_limits();
    (0..count as usize)
        .map(|i| {
            let p = at(i);
            // The caller guarantees a readable struct of the right type at `p`; template data
            // need not be aligned, hence read_unaligned.
            match type_class(t) {
                TypeClass::Buffer => {
                    // SAFETY: see above; a VkDescriptorBufferInfo.
                    let b = unsafe { std::ptr::read_unaligned(p as *const vk::DescriptorBufferInfo) };
                    buffer_descriptor(t, buffer_from(b.buffer), b.buffer.as_raw(), b.offset, b.range, &limits)
                }
                TypeClass::Image => {
                    // SAFETY: see above; a VkDescriptorImageInfo.
                    let im = unsafe { std::ptr::read_unaligned(p as *const vk::DescriptorImageInfo) };
                    if t == vk::DescriptorType::STORAGE_IMAGE {
                        let h = im.image_view.as_raw();
                        return storage_image_descriptor(get::<ImageView>(h), h, im.image_layout);
                    }
                    Ok(Descriptor::Image { sampler: im.sampler.as_raw(), image_view: im.image_view.as_raw(), layout: im.image_layout })
                }
                TypeClass::TexelBuffer => {
                    // SAFETY: see above; a VkBufferView.
                    let v = unsafe { std::ptr::read_unaligned(p as *const vk::BufferView) };
                    texel_buffer_descriptor(t, get::<BufferView>(v.as_raw()), v.as_raw())
                }
                TypeClass::AccelerationStructure => {
                    // SAFETY: see above; a VkAccelerationStructureKHR handle.
                    let h = unsafe { std::ptr::read_unaligned(p as *const vk::AccelerationStructureKHR) };
                    acceleration_structure_descriptor(get::<AccelerationStructure>(h.as_raw()), h.as_raw())
                }
                TypeClass::PartitionedAccelerationStructure => {
                    // SAFETY: see above; a VkDeviceAddress (0: the null descriptor).
                    let address = unsafe { std::ptr::read_unaligned(p as *const vk::DeviceAddress) };
                    Ok(Descriptor::PartitionedAccelerationStructure { address })
                }
                TypeClass::Unsupported => Err(Violation {
                    vuid: "VUID-VkWriteDescriptorSet-descriptorType-parameter",
                    message: format!("descriptor type {t:?} is not supported"),
                }),
            }
        })
        .collect()
}

/// Apply one VkWriteDescriptorSet.
///
/// # Safety
/// `w` is a valid VkWriteDescriptorSet.
unsafe fn apply_write(w: &vk::WriteDescriptorSet) -> Result<(), Violation> {
    let Some(set) = get::<DescriptorSet>(w.dst_set.as_raw()) else {
        return Err(Violation { vuid: "VUID-VkWriteDescriptorSet-dstSet-00320", message: "dstSet is not a live VkDescriptorSet".into() });
    };
    let t = w.descriptor_type;
    let (base, stride, vuid): (*const u8, usize, &'static str) = match type_class(t) {
        TypeClass::Buffer => (w.p_buffer_info.cast(), std::mem::size_of::<vk::DescriptorBufferInfo>(), "VUID-VkWriteDescriptorSet-descriptorType-00324"),
        TypeClass::Image => (w.p_image_info.cast(), std::mem::size_of::<vk::DescriptorImageInfo>(), "VUID-VkWriteDescriptorSet-descriptorType-00322"),
        TypeClass::TexelBuffer => (w.p_texel_buffer_view.cast(), std::mem::size_of::<vk::BufferView>(), "VUID-VkWriteDescriptorSet-descriptorType-02994"),
        TypeClass::AccelerationStructure => {
            // SAFETY: valid chain per the spec.
            let info = unsafe {
                util::find_in::<vk::WriteDescriptorSetAccelerationStructureKHR>(
                    w.p_next,
                    vk::StructureType::WRITE_DESCRIPTOR_SET_ACCELERATION_STRUCTURE_KHR,
                )
            };
            match info {
                Some(i) if i.acceleration_structure_count == w.descriptor_count => (
                    i.p_acceleration_structures.cast(),
                    std::mem::size_of::<vk::AccelerationStructureKHR>(),
                    "VUID-VkWriteDescriptorSetAccelerationStructureKHR-pAccelerationStructures-parameter",
                ),
                _ => {
                    return Err(Violation {
                        vuid: "VUID-VkWriteDescriptorSet-descriptorType-02382",
                        message: "no VkWriteDescriptorSetAccelerationStructureKHR with accelerationStructureCount == descriptorCount in pNext".into(),
                    })
                }
            }
        }
        TypeClass::PartitionedAccelerationStructure => {
            // SAFETY: valid chain per the spec.
            let info = unsafe { util::find_in::<PtlasWrite>(w.p_next, STRUCTURE_TYPE_WRITE_DESCRIPTOR_SET_PARTITIONED_ACCELERATION_STRUCTURE_NV) };
            match info {
                Some(i) if i.acceleration_structure_count == w.descriptor_count => {
                    (i.p_acceleration_structures.cast(), std::mem::size_of::<vk::DeviceAddress>(), "VkWriteDescriptorSetPartitionedAccelerationStructureNV-pAccelerationStructures")
                }
                // No numbered VUID names this rule; the struct's own text does.
                _ => {
                    return Err(Violation {
                        vuid: "VkWriteDescriptorSetPartitionedAccelerationStructureNV-accelerationStructureCount",
                        message: "no VkWriteDescriptorSetPartitionedAccelerationStructureNV with accelerationStructureCount == descriptorCount in pNext".into(),
                    })
                }
            }
        }
        TypeClass::Unsupported => (std::ptr::null(), 0, "VUID-VkWriteDescriptorSet-descriptorType-parameter"),
    };
    if base.is_null() && w.descriptor_count > 0 {
        return Err(Violation { vuid, message: format!("no descriptor info array for {t:?}") });
    }
    // SAFETY: the array for this type has descriptorCount elements per the spec.
    let descriptors = unsafe { convert(t, w.descriptor_count, |i| base.wrapping_add(i * stride)) }?;
    set.write(w.dst_binding, w.dst_array_element, t, descriptors)
}

fn apply_copy(c: &vk::CopyDescriptorSet) -> Result<(), Violation> {
    let (Some(src), Some(dst)) = (get::<DescriptorSet>(c.src_set.as_raw()), get::<DescriptorSet>(c.dst_set.as_raw())) else {
        return Err(Violation { vuid: "VUID-VkCopyDescriptorSet-srcSet-parameter", message: "srcSet or dstSet is not a live VkDescriptorSet".into() });
    };
    dst.copy_from(&src, c.src_binding, c.src_array_element, c.dst_binding, c.dst_array_element, c.descriptor_count)
}

unsafe extern "system" fn update_descriptor_sets(
    device: vk::Device,
    write_count: u32,
    p_writes: *const vk::WriteDescriptorSet,
    copy_count: u32,
    p_copies: *const vk::CopyDescriptorSet,
) {
    const CMD: &str = "vkUpdateDescriptorSets";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_no_device(CMD);
            return;
        }
        // Writes first, then copies, each in array order (the spec's order). An invalid one
        // is reported and skipped; the others still apply.
        // SAFETY: valid arrays per the spec.
        for w in unsafe { util::slice(p_writes, write_count) } {
            // SAFETY: a valid VkWriteDescriptorSet.
            if let Err(v) = unsafe { apply_write(w) } {
                report(CMD, &v);
            }
        }
        // SAFETY: valid array per the spec.
        for c in unsafe { util::slice(p_copies, copy_count) } {
            if let Err(v) = apply_copy(c) {
                report(CMD, &v);
            }
        }
    })
}

unsafe extern "system" fn create_descriptor_update_template(
    device: vk::Device,
    p_create_info: *const vk::DescriptorUpdateTemplateCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_template: *mut vk::DescriptorUpdateTemplate,
) -> vk::Result {
    const CMD: &str = "vkCreateDescriptorUpdateTemplate";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device(CMD);
        }
        if p_create_info.is_null() || p_template.is_null() {
            return invalid(CMD, &Violation { vuid: "VUID-vkCreateDescriptorUpdateTemplate-pCreateInfo-parameter", message: "null pointer".into() });
        }
        // SAFETY: checked non-null.
        unsafe { *p_template = vk::DescriptorUpdateTemplate::null() };
        // SAFETY: valid create info per the spec.
        let info = unsafe { &*p_create_info };
        if info.template_type != vk::DescriptorUpdateTemplateType::DESCRIPTOR_SET {
            return invalid(
                CMD,
                &Violation {
                    vuid: "VUID-VkDescriptorUpdateTemplateCreateInfo-templateType-parameter",
                    message: format!("template type {:?} is not supported (no push descriptors)", info.template_type),
                },
            );
        }
        let Some(layout) = get::<DescriptorSetLayout>(info.descriptor_set_layout.as_raw()) else {
            return invalid(CMD, &bad_handle("VUID-VkDescriptorUpdateTemplateCreateInfo-templateType-00350", "descriptorSetLayout"));
        };
        // SAFETY: valid array per the spec.
        let entries = unsafe { util::slice(info.p_descriptor_update_entries, info.descriptor_update_entry_count) }
            .iter()
            .map(|e| TemplateEntry {
                binding: e.dst_binding,
                element: e.dst_array_element,
                count: e.descriptor_count,
                descriptor_type: e.descriptor_type,
                offset: e.offset,
                stride: e.stride,
            })
            .collect();
        match DescriptorUpdateTemplate::new(layout, entries) {
            Ok(t) => {
                // SAFETY: checked non-null.
                unsafe { *p_template = vk::DescriptorUpdateTemplate::from_raw(register(Arc::new(t))) };
                vk::Result::SUCCESS
            }
            Err(v) => invalid(CMD, &v),
        }
    })
}

unsafe extern "system" fn destroy_descriptor_update_template(
    device: vk::Device,
    template: vk::DescriptorUpdateTemplate,
    _p_allocator: *const vk::AllocationCallbacks,
) {
    const CMD: &str = "vkDestroyDescriptorUpdateTemplate";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_no_device(CMD);
            return;
        }
        if template != vk::DescriptorUpdateTemplate::null() && unregister::<DescriptorUpdateTemplate>(template.as_raw()).is_none() {
            report(CMD, &bad_handle("VUID-vkDestroyDescriptorUpdateTemplate-descriptorUpdateTemplate-parameter", "descriptorUpdateTemplate"));
        }
    })
}

unsafe extern "system" fn update_descriptor_set_with_template(
    device: vk::Device,
    set: vk::DescriptorSet,
    template: vk::DescriptorUpdateTemplate,
    p_data: *const c_void,
) {
    const CMD: &str = "vkUpdateDescriptorSetWithTemplate";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_no_device(CMD);
            return;
        }
        let (Some(s), Some(t)) = (get::<DescriptorSet>(set.as_raw()), get::<DescriptorUpdateTemplate>(template.as_raw())) else {
            report(CMD, &bad_handle("VUID-vkUpdateDescriptorSetWithTemplate-descriptorSet-parameter", "descriptorSet or descriptorUpdateTemplate"));
            return;
        };
        if !Arc::ptr_eq(&s.layout, &t.layout) && s.layout.bindings != t.layout.bindings {
            report(
                CMD,
                &Violation {
                    vuid: "VUID-vkUpdateDescriptorSetWithTemplate-descriptorSet-parameter",
                    message: "the set's layout is not compatible with the template's".into(),
                },
            );
            return;
        }
        if p_data.is_null() && t.entries.iter().any(|e| e.count > 0) {
            report(CMD, &Violation { vuid: "VUID-vkUpdateDescriptorSetWithTemplate-pData-01685", message: "pData is null".into() });
            return;
        }
        let data = p_data as *const u8;
        for e in &t.entries {
            // SAFETY: pData holds, for every entry, descriptorCount structs at offset + i * stride
            // (the template's contract with the application).
            let converted = unsafe { convert(e.descriptor_type, e.count, |i| data.wrapping_add(e.offset + i * e.stride)) };
            if let Err(v) = converted.and_then(|d| s.write(e.binding, e.element, e.descriptor_type, d)) {
                report(CMD, &v);
            }
        }
    })
}

unsafe extern "system" fn create_pipeline_layout(
    device: vk::Device,
    p_create_info: *const vk::PipelineLayoutCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_layout: *mut vk::PipelineLayout,
) -> vk::Result {
    const CMD: &str = "vkCreatePipelineLayout";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return no_device(CMD);
        }
        if p_create_info.is_null() || p_layout.is_null() {
            return invalid(CMD, &Violation { vuid: "VUID-vkCreatePipelineLayout-pCreateInfo-parameter", message: "null pointer".into() });
        }
        // SAFETY: checked non-null.
        unsafe { *p_layout = vk::PipelineLayout::null() };
        // SAFETY: valid create info and arrays per the spec.
        let info = unsafe { &*p_create_info };
        // SAFETY: as above.
        let handles = unsafe { util::slice(info.p_set_layouts, info.set_layout_count) };
        let mut set_layouts = Vec::with_capacity(handles.len());
        for h in handles {
            match get::<DescriptorSetLayout>(h.as_raw()) {
                Some(l) => set_layouts.push(l),
                None => return invalid(CMD, &bad_handle("VUID-VkPipelineLayoutCreateInfo-pSetLayouts-parameter", "pSetLayouts[i]")),
            }
        }
        // SAFETY: valid array per the spec.
        let ranges = unsafe { util::slice(info.p_push_constant_ranges, info.push_constant_range_count) }.to_vec();
        let limits = super::physical_device::limits();
        match PipelineLayout::new(info.flags, set_layouts, ranges, limits.max_bound_descriptor_sets, limits.max_push_constants_size) {
            Ok(l) => {
                // SAFETY: checked non-null.
                unsafe { *p_layout = vk::PipelineLayout::from_raw(register(Arc::new(l))) };
                vk::Result::SUCCESS
            }
            Err(v) => invalid(CMD, &v),
        }
    })
}

unsafe extern "system" fn destroy_pipeline_layout(device: vk::Device, layout: vk::PipelineLayout, _p_allocator: *const vk::AllocationCallbacks) {
    const CMD: &str = "vkDestroyPipelineLayout";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_no_device(CMD);
            return;
        }
        if layout != vk::PipelineLayout::null() && unregister::<PipelineLayout>(layout.as_raw()).is_none() {
            report(CMD, &bad_handle("VUID-vkDestroyPipelineLayout-pipelineLayout-parameter", "pipelineLayout"));
        }
    })
}

//! Descriptor objects: set layouts, pools, sets (which store what was written), update
//! templates and pipeline layouts. Plain Rust values: the dispatch layer converts the
//! application's structs into [`Descriptor`]s and calls one method here. The descriptor values
//! and their checked construction are in `value` (re-exported here).
//!
//! A set stores one [`Descriptor`] per array element of each binding. Buffer descriptors keep a
//! weak reference to the buffer (a destroyed buffer makes the descriptor invalid, it does not
//! keep the memory alive) plus the handle for diagnostics; acceleration-structure descriptors
//! likewise hold the structure weakly. A new descriptor kind is one more [`Descriptor`] variant,
//! one [`TypeClass`] and one arm in [`type_class`].
use std::collections::HashMap;
use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};

use ash::vk;

mod value;

pub use value::{
    acceleration_structure_descriptor, buffer_descriptor, is_dynamic, storage_image_descriptor, texel_buffer_descriptor, type_class, BufferLimits, Descriptor, TypeClass, Violation,
    PARTITIONED_ACCELERATION_STRUCTURE_NV,
};
use value::violation;

/// One binding of a set layout.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LayoutBinding {
    pub binding: u32,
    pub descriptor_type: vk::DescriptorType,
    /// Array size; for a VARIABLE_DESCRIPTOR_COUNT binding, the upper bound.
    pub count: u32,
    pub stages: vk::ShaderStageFlags,
    pub flags: vk::DescriptorBindingFlags,
    /// Raw handles of immutable samplers (empty when none).
    pub immutable_samplers: Vec<u64>,
}

/// One `VkDescriptorSetLayout`.
#[derive(Debug)]
pub struct DescriptorSetLayout {
    pub flags: vk::DescriptorSetLayoutCreateFlags,
    /// Sorted by binding number.
    pub bindings: Vec<LayoutBinding>,
}

/// Layout creation flags Arbor supports.
const SUPPORTED_LAYOUT_FLAGS: vk::DescriptorSetLayoutCreateFlags = vk::DescriptorSetLayoutCreateFlags::UPDATE_AFTER_BIND_POOL;

impl DescriptorSetLayout {
    /// Check and build a layout. `bindings` in the application's order; binding flags are
    /// already attached (from VkDescriptorSetLayoutBindingFlagsCreateInfo).
    pub fn new(flags: vk::DescriptorSetLayoutCreateFlags, mut bindings: Vec<LayoutBinding>) -> Result<Self, Violation> {
        if !(flags & !SUPPORTED_LAYOUT_FLAGS).is_empty() {
            return Err(violation(
                "VUID-VkDescriptorSetLayoutCreateInfo-flags-parameter",
                format!("flags {flags:?} include ones Arbor does not support (push descriptors are not offered)"),
            ));
        }
        bindings.sort_by_key(|b| b.binding);
        if let Some(w) = bindings.windows(2).find(|w| w[0].binding == w[1].binding) {
            return Err(violation(
                "VUID-VkDescriptorSetLayoutCreateInfo-binding-00279",
                format!("binding number {} appears twice", w[0].binding),
            ));
        }
        for (i, b) in bindings.iter().enumerate() {
            if type_class(b.descriptor_type) == TypeClass::Unsupported {
                return Err(violation(
                    "VUID-VkDescriptorSetLayoutBinding-descriptorType-parameter",
                    format!("binding {}: descriptor type {:?} is not supported", b.binding, b.descriptor_type),
                ));
            }
            let uab = b.flags.contains(vk::DescriptorBindingFlags::UPDATE_AFTER_BIND);
            if uab && !flags.contains(vk::DescriptorSetLayoutCreateFlags::UPDATE_AFTER_BIND_POOL) {
                return Err(violation(
                    "VUID-VkDescriptorSetLayoutCreateInfo-flags-03000",
                    format!("binding {} is UPDATE_AFTER_BIND but the layout lacks UPDATE_AFTER_BIND_POOL", b.binding),
                ));
            }
            if uab && is_dynamic(b.descriptor_type) {
                return Err(violation(
                    "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-None-03011",
                    format!("binding {}: dynamic buffer descriptors cannot be UPDATE_AFTER_BIND", b.binding),
                ));
            }
            if uab
                && !matches!(
                    b.descriptor_type,
                    vk::DescriptorType::UNIFORM_BUFFER
                        | vk::DescriptorType::STORAGE_BUFFER
                        | vk::DescriptorType::ACCELERATION_STRUCTURE_KHR
                        | PARTITIONED_ACCELERATION_STRUCTURE_NV
                )
            {
                let vuid = match b.descriptor_type {
                    vk::DescriptorType::STORAGE_IMAGE => "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-descriptorBindingStorageImageUpdateAfterBind-03007",
                    vk::DescriptorType::UNIFORM_TEXEL_BUFFER => {
                        "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-descriptorBindingUniformTexelBufferUpdateAfterBind-03009"
                    }
                    vk::DescriptorType::STORAGE_TEXEL_BUFFER => {
                        "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-descriptorBindingStorageTexelBufferUpdateAfterBind-03010"
                    }
                    vk::DescriptorType::INPUT_ATTACHMENT => "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-None-03011",
                    _ => "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-descriptorBindingSampledImageUpdateAfterBind-03006",
                };
                return Err(violation(
                    vuid,
                    format!(
                        "binding {}: UPDATE_AFTER_BIND for {:?} needs a feature Arbor does not offer",
                        b.binding, b.descriptor_type
                    ),
                ));
            }
            let variable = b.flags.contains(vk::DescriptorBindingFlags::VARIABLE_DESCRIPTOR_COUNT);
            if variable && i + 1 != bindings.len() {
                return Err(violation(
                    "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-pBindingFlags-03004",
                    format!("binding {} has VARIABLE_DESCRIPTOR_COUNT but is not the highest binding", b.binding),
                ));
            }
            if variable && is_dynamic(b.descriptor_type) {
                return Err(violation(
                    "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-pBindingFlags-03015",
                    format!("binding {}: dynamic buffer descriptors cannot have a variable count", b.binding),
                ));
            }
        }
        Ok(DescriptorSetLayout { flags, bindings })
    }

    pub fn binding(&self, binding: u32) -> Option<&LayoutBinding> {
        self.bindings.binary_search_by_key(&binding, |b| b.binding).ok().map(|i| &self.bindings[i])
    }

    /// The variable-count binding, if the layout has one (always the last).
    pub fn variable_binding(&self) -> Option<&LayoutBinding> {
        self.bindings.last().filter(|b| b.flags.contains(vk::DescriptorBindingFlags::VARIABLE_DESCRIPTOR_COUNT))
    }

    /// Descriptor count of each binding for a set allocated with `variable_count`.
    fn counts(&self, variable_count: u32) -> Vec<u32> {
        let variable = self.variable_binding().map(|b| b.binding);
        self.bindings.iter().map(|b| if Some(b.binding) == variable { variable_count.min(b.count) } else { b.count }).collect()
    }

    /// Descriptors a set of this layout takes from a pool, by type.
    pub fn pool_usage(&self, variable_count: u32) -> HashMap<vk::DescriptorType, u64> {
        let mut usage = HashMap::new();
        for (b, n) in self.bindings.iter().zip(self.counts(variable_count)) {
            *usage.entry(b.descriptor_type).or_insert(0) += n as u64;
        }
        usage
    }

    /// Total descriptors (for vkGetDescriptorSetLayoutSupport).
    pub fn total_descriptors(&self) -> u64 {
        self.bindings.iter().map(|b| b.count as u64).sum()
    }

    /// Dynamic descriptors in binding order (the order dynamic offsets are consumed in).
    pub fn dynamic_count(&self) -> u32 {
        self.bindings.iter().filter(|b| is_dynamic(b.descriptor_type)).map(|b| b.count).sum()
    }
}

/// A pool allocation failure.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum AllocateError {
    /// maxSets or a pool size would be exceeded: VK_ERROR_OUT_OF_POOL_MEMORY.
    OutOfPoolMemory,
    Invalid(Violation),
}

struct PoolState {
    sets: Vec<Arc<DescriptorSet>>,
    used: HashMap<vk::DescriptorType, u64>,
}

/// One `VkDescriptorPool`: limits are enforced exactly (maxSets and every pool size).
pub struct DescriptorPool {
    pub flags: vk::DescriptorPoolCreateFlags,
    pub max_sets: u32,
    pub sizes: HashMap<vk::DescriptorType, u64>,
    state: Mutex<PoolState>,
}

const SUPPORTED_POOL_FLAGS: vk::DescriptorPoolCreateFlags = vk::DescriptorPoolCreateFlags::from_raw(
    vk::DescriptorPoolCreateFlags::FREE_DESCRIPTOR_SET.as_raw() | vk::DescriptorPoolCreateFlags::UPDATE_AFTER_BIND.as_raw(),
);

impl DescriptorPool {
    pub fn new(
        flags: vk::DescriptorPoolCreateFlags,
        max_sets: u32,
        sizes: &[(vk::DescriptorType, u32)],
    ) -> Result<Self, Violation> {
        if !(flags & !SUPPORTED_POOL_FLAGS).is_empty() {
            return Err(violation("VUID-VkDescriptorPoolCreateInfo-flags-parameter", format!("unsupported flags {flags:?}")));
        }
        if max_sets == 0 {
            return Err(violation("VUID-VkDescriptorPoolCreateInfo-maxSets-00301", "maxSets is 0"));
        }
        let mut map = HashMap::new();
        for &(t, n) in sizes {
            if n == 0 {
                return Err(violation("VUID-VkDescriptorPoolSize-descriptorCount-00302", format!("descriptorCount of {t:?} is 0")));
            }
            *map.entry(t).or_insert(0) += n as u64;
        }
        Ok(DescriptorPool { flags, max_sets, sizes: map, state: Mutex::new(PoolState { sets: Vec::new(), used: HashMap::new() }) })
    }

    fn state(&self) -> std::sync::MutexGuard<'_, PoolState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Allocate one set per (layout, variable count); all or nothing.
    pub fn allocate(self: &Arc<Self>, requests: &[(Arc<DescriptorSetLayout>, Option<u32>)]) -> Result<Vec<Arc<DescriptorSet>>, AllocateError> {
        let mut state = self.state();
        let mut used = state.used.clone();
        for (layout, variable) in requests {
            if layout.flags.contains(vk::DescriptorSetLayoutCreateFlags::UPDATE_AFTER_BIND_POOL)
                && !self.flags.contains(vk::DescriptorPoolCreateFlags::UPDATE_AFTER_BIND)
            {
                return Err(AllocateError::Invalid(violation(
                    "VUID-VkDescriptorSetAllocateInfo-pSetLayouts-03044",
                    "a layout with UPDATE_AFTER_BIND_POOL needs a pool created with UPDATE_AFTER_BIND",
                )));
            }
            if let (Some(v), Some(b)) = (variable, layout.variable_binding()) {
                if *v > b.count {
                    return Err(AllocateError::Invalid(violation(
                        "VUID-VkDescriptorSetVariableDescriptorCountAllocateInfo-pSetLayouts-03046",
                        format!("variable descriptor count {v} exceeds the binding's maximum {}", b.count),
                    )));
                }
            }
            for (t, n) in layout.pool_usage(variable.unwrap_or(0)) {
                *used.entry(t).or_insert(0) += n;
            }
        }
        if state.sets.len() + requests.len() > self.max_sets as usize
            || used.iter().any(|(t, n)| *n > self.sizes.get(t).copied().unwrap_or(0))
        {
            return Err(AllocateError::OutOfPoolMemory);
        }
        state.used = used;
        let sets: Vec<_> = requests
            .iter()
            .map(|(layout, variable)| Arc::new(DescriptorSet::new(layout.clone(), variable.unwrap_or(0), Arc::downgrade(self))))
            .collect();
        state.sets.extend(sets.iter().cloned());
        Ok(sets)
    }

    /// Return sets to the pool (vkFreeDescriptorSets). Sets of other pools are ignored and
    /// reported in the result.
    pub fn free(&self, sets: &[Arc<DescriptorSet>]) -> Result<(), Violation> {
        if !self.flags.contains(vk::DescriptorPoolCreateFlags::FREE_DESCRIPTOR_SET) {
            return Err(violation(
                "VUID-vkFreeDescriptorSets-descriptorPool-00312",
                "the pool was not created with VK_DESCRIPTOR_POOL_CREATE_FREE_DESCRIPTOR_SET_BIT",
            ));
        }
        let mut state = self.state();
        let mut foreign = false;
        for set in sets {
            match state.sets.iter().position(|s| Arc::ptr_eq(s, set)) {
                Some(i) => {
                    let s = state.sets.swap_remove(i);
                    for (t, n) in s.layout.pool_usage(s.variable_count) {
                        if let Some(u) = state.used.get_mut(&t) {
                            *u = u.saturating_sub(n);
                        }
                    }
                }
                None => foreign = true,
            }
        }
        if foreign {
            return Err(violation("VUID-vkFreeDescriptorSets-pDescriptorSets-parent", "a set was not allocated from this pool"));
        }
        Ok(())
    }

    /// Free every set (vkResetDescriptorPool, vkDestroyDescriptorPool); returns them so the
    /// caller can retire their handles.
    pub fn reset(&self) -> Vec<Arc<DescriptorSet>> {
        let mut state = self.state();
        state.used.clear();
        std::mem::take(&mut state.sets)
    }

    /// Sets currently allocated.
    pub fn allocated(&self) -> usize {
        self.state().sets.len()
    }

    /// Whether `set` was allocated from this pool and is still live.
    pub fn owns(&self, set: &Arc<DescriptorSet>) -> bool {
        self.state().sets.iter().any(|s| Arc::ptr_eq(s, set))
    }
}

/// One `VkDescriptorSet`: one [`Descriptor`] per array element of every binding.
pub struct DescriptorSet {
    pub layout: Arc<DescriptorSetLayout>,
    /// Count of the variable-count binding (0 when the layout has none).
    pub variable_count: u32,
    pub pool: Weak<DescriptorPool>,
    /// The handle the dispatch layer registered this set under (0 until set).
    handle: AtomicU64,
    /// Indexed like `layout.bindings`.
    slots: Mutex<Vec<Vec<Descriptor>>>,
}

impl fmt::Debug for DescriptorSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("DescriptorSet").field("handle", &self.handle()).field("slots", &*self.lock()).finish()
    }
}

impl DescriptorSet {
    fn new(layout: Arc<DescriptorSetLayout>, variable_count: u32, pool: Weak<DescriptorPool>) -> Self {
        let slots = layout.counts(variable_count).into_iter().map(|n| vec![Descriptor::Empty; n as usize]).collect();
        DescriptorSet { layout, variable_count, pool, handle: AtomicU64::new(0), slots: Mutex::new(slots) }
    }

    pub fn handle(&self) -> u64 {
        self.handle.load(Ordering::Relaxed)
    }

    pub fn set_handle(&self, handle: u64) {
        self.handle.store(handle, Ordering::Relaxed);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<Vec<Descriptor>>> {
        self.slots.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn index(&self, binding: u32) -> Option<usize> {
        self.layout.bindings.binary_search_by_key(&binding, |b| b.binding).ok()
    }

    /// What binding `binding` holds (one entry per array element); None if the layout has no
    /// such binding.
    pub fn binding(&self, binding: u32) -> Option<Vec<Descriptor>> {
        let i = self.index(binding)?;
        Some(self.lock()[i].clone())
    }

    /// One descriptor.
    pub fn descriptor(&self, binding: u32, element: u32) -> Option<Descriptor> {
        let i = self.index(binding)?;
        self.lock()[i].get(element as usize).cloned()
    }

    /// The (binding index, element) positions `count` consecutive descriptors starting at
    /// (binding, element) occupy, following the spec's roll-over into the next bindings.
    /// Every binding touched must match the first one's type, stages and flags.
    fn positions(&self, binding: u32, element: u32, count: u32, vuid_prefix: &'static str) -> Result<Vec<(usize, usize)>, Violation> {
        let Some(mut bi) = self.index(binding) else {
            return Err(violation(
                if vuid_prefix == "dst" { "VUID-VkWriteDescriptorSet-dstBinding-00315" } else { "VUID-VkCopyDescriptorSet-srcBinding-00345" },
                format!("the set layout has no binding {binding}"),
            ));
        };
        let slots = self.lock();
        let first = &self.layout.bindings[bi];
        let mut element = element as usize;
        let mut out = Vec::with_capacity(count as usize);
        while out.len() < count as usize {
            let b = &self.layout.bindings[bi];
            let len = slots[bi].len();
            if element < len {
                // Bindings with no descriptors are skipped; the others must match the first.
                if b.descriptor_type != first.descriptor_type || b.stages != first.stages || b.flags != first.flags {
                    return Err(violation(
                        "VUID-VkWriteDescriptorSet-descriptorCount-00317",
                        format!(
                            "the update rolls over from binding {} into binding {} which differs in type, stages or flags",
                            first.binding, b.binding
                        ),
                    ));
                }
                let take = (len - element).min(count as usize - out.len());
                out.extend((element..element + take).map(|e| (bi, e)));
                element = 0;
                if out.len() == count as usize {
                    break;
                }
            } else {
                element -= len;
            }
            bi += 1;
            if bi >= self.layout.bindings.len() {
                return Err(violation(
                    if vuid_prefix == "dst" { "VUID-VkWriteDescriptorSet-dstArrayElement-00321" } else { "VUID-VkCopyDescriptorSet-srcArrayElement-00346" },
                    format!("{count} descriptors from binding {binding} run past the last binding of the set"),
                ));
            }
        }
        Ok(out)
    }

    /// Write consecutive descriptors starting at (binding, element) (vkUpdateDescriptorSets,
    /// templates). `descriptor_type` must be the binding's type.
    pub fn write(&self, binding: u32, element: u32, descriptor_type: vk::DescriptorType, descriptors: Vec<Descriptor>) -> Result<(), Violation> {
        let Some(b) = self.layout.binding(binding) else {
            return Err(violation("VUID-VkWriteDescriptorSet-dstBinding-00315", format!("the set layout has no binding {binding}")));
        };
        if b.descriptor_type != descriptor_type {
            return Err(violation(
                "VUID-VkWriteDescriptorSet-descriptorType-00319",
                format!("binding {binding} is {:?}, the write is {descriptor_type:?}", b.descriptor_type),
            ));
        }
        let positions = self.positions(binding, element, descriptors.len() as u32, "dst")?;
        let mut slots = self.lock();
        for ((bi, e), d) in positions.into_iter().zip(descriptors) {
            slots[bi][e] = d;
        }
        Ok(())
    }

    /// Copy `count` descriptors (vkUpdateDescriptorSets' VkCopyDescriptorSet). `src` may be
    /// this set.
    pub fn copy_from(&self, src: &DescriptorSet, src_binding: u32, src_element: u32, dst_binding: u32, dst_element: u32, count: u32) -> Result<(), Violation> {
        let (Some(sb), Some(db)) = (src.layout.binding(src_binding), self.layout.binding(dst_binding)) else {
            return Err(violation(
                "VUID-VkCopyDescriptorSet-srcBinding-00345",
                format!("no binding {src_binding} in the source or no binding {dst_binding} in the destination"),
            ));
        };
        if sb.descriptor_type != db.descriptor_type {
            return Err(violation(
                "VUID-VkCopyDescriptorSet-dstBinding-02632",
                format!("source binding is {:?}, destination binding is {:?}", sb.descriptor_type, db.descriptor_type),
            ));
        }
        let from = src.positions(src_binding, src_element, count, "src")?;
        let to = self.positions(dst_binding, dst_element, count, "dst")?;
        // Read everything first: source and destination may be the same set (overlap is
        // invalid usage, but reading first keeps the result well defined).
        let values: Vec<Descriptor> = {
            let s = src.lock();
            from.iter().map(|&(bi, e)| s[bi][e].clone()).collect()
        };
        let mut d = self.lock();
        for ((bi, e), v) in to.into_iter().zip(values) {
            d[bi][e] = v;
        }
        Ok(())
    }
}

/// One entry of a descriptor update template: where the descriptors' source structs lie in the
/// application's data block.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TemplateEntry {
    pub binding: u32,
    pub element: u32,
    pub count: u32,
    pub descriptor_type: vk::DescriptorType,
    pub offset: usize,
    pub stride: usize,
}

/// One `VkDescriptorUpdateTemplate` (descriptor-set templates only: no push descriptors).
#[derive(Debug)]
pub struct DescriptorUpdateTemplate {
    pub layout: Arc<DescriptorSetLayout>,
    pub entries: Vec<TemplateEntry>,
}

impl DescriptorUpdateTemplate {
    pub fn new(layout: Arc<DescriptorSetLayout>, entries: Vec<TemplateEntry>) -> Result<Self, Violation> {
        for e in &entries {
            match layout.binding(e.binding) {
                None => {
                    return Err(violation(
                        "VUID-VkDescriptorUpdateTemplateCreateInfo-templateType-00350",
                        format!("entry for binding {} which the set layout does not have", e.binding),
                    ))
                }
                Some(b) if b.descriptor_type != e.descriptor_type => {
                    return Err(violation(
                        "VUID-VkDescriptorUpdateTemplateEntry-descriptorType-parameter",
                        format!("entry type {:?} differs from binding {}'s {:?}", e.descriptor_type, e.binding, b.descriptor_type),
                    ))
                }
                _ => {}
            }
        }
        Ok(DescriptorUpdateTemplate { layout, entries })
    }
}

/// One `VkPipelineLayout`.
#[derive(Debug)]
pub struct PipelineLayout {
    pub flags: vk::PipelineLayoutCreateFlags,
    pub set_layouts: Vec<Arc<DescriptorSetLayout>>,
    pub push_constant_ranges: Vec<vk::PushConstantRange>,
}

impl PipelineLayout {
    pub fn new(
        flags: vk::PipelineLayoutCreateFlags,
        set_layouts: Vec<Arc<DescriptorSetLayout>>,
        push_constant_ranges: Vec<vk::PushConstantRange>,
        max_bound_sets: u32,
        max_push_constants: u32,
    ) -> Result<Self, Violation> {
        if set_layouts.len() > max_bound_sets as usize {
            return Err(violation(
                "VUID-VkPipelineLayoutCreateInfo-setLayoutCount-00286",
                format!("{} set layouts exceed maxBoundDescriptorSets {max_bound_sets}", set_layouts.len()),
            ));
        }
        for (i, r) in push_constant_ranges.iter().enumerate() {
            if r.offset % 4 != 0 || r.offset >= max_push_constants {
                return Err(violation(
                    "VUID-VkPushConstantRange-offset-00294",
                    format!("push constant range {i}: offset {} must be a multiple of 4 below {max_push_constants}", r.offset),
                ));
            }
            if r.size == 0 || r.size % 4 != 0 || r.size > max_push_constants - r.offset {
                return Err(violation(
                    "VUID-VkPushConstantRange-size-00298",
                    format!("push constant range {i}: size {} must be a non-zero multiple of 4 within {max_push_constants} bytes", r.size),
                ));
            }
            if r.stage_flags.is_empty() {
                return Err(violation("VUID-VkPushConstantRange-stageFlags-requiredbitmask", format!("push constant range {i}: no stages")));
            }
            if push_constant_ranges[..i].iter().any(|p| !(p.stage_flags & r.stage_flags).is_empty()) {
                return Err(violation(
                    "VUID-VkPipelineLayoutCreateInfo-pPushConstantRanges-00292",
                    format!("push constant range {i} shares a stage with an earlier range"),
                ));
            }
        }
        Ok(PipelineLayout { flags, set_layouts, push_constant_ranges })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::memory::Buffer;
    use crate::runtime::accel::AccelerationStructure;
    use crate::memory::AddressSpace;

    const LIMITS: BufferLimits =
        BufferLimits { min_uniform_offset_alignment: 16, min_storage_offset_alignment: 16, max_uniform_range: 65536, max_storage_range: u32::MAX as u64 };

    fn binding(binding: u32, t: vk::DescriptorType, count: u32) -> LayoutBinding {
        LayoutBinding { binding, descriptor_type: t, count, stages: vk::ShaderStageFlags::COMPUTE, flags: vk::DescriptorBindingFlags::empty(), immutable_samplers: vec![] }
    }

    fn storage(space: &AddressSpace, size: u64, usage: vk::BufferUsageFlags) -> Arc<Buffer> {
        let m = space.allocate(size, false, None).unwrap();
        let b = Arc::new(Buffer::new(size, usage, vk::BufferCreateFlags::empty()));
        b.bind(m, 0).unwrap();
        b
    }

    fn pool(max_sets: u32, sizes: &[(vk::DescriptorType, u32)], flags: vk::DescriptorPoolCreateFlags) -> Arc<DescriptorPool> {
        Arc::new(DescriptorPool::new(flags, max_sets, sizes).unwrap())
    }

    #[test]
    fn writes_read_back() {
        let space = AddressSpace::new(1 << 24);
        let b = storage(&space, 4096, vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::UNIFORM_BUFFER);
        let layout = Arc::new(
            DescriptorSetLayout::new(
                vk::DescriptorSetLayoutCreateFlags::empty(),
                vec![binding(3, vk::DescriptorType::UNIFORM_BUFFER, 1), binding(0, vk::DescriptorType::STORAGE_BUFFER, 4)],
            )
            .unwrap(),
        );
        assert_eq!(layout.bindings[0].binding, 0, "bindings sorted");
        let p = pool(4, &[(vk::DescriptorType::STORAGE_BUFFER, 8), (vk::DescriptorType::UNIFORM_BUFFER, 2)], vk::DescriptorPoolCreateFlags::empty());
        let set = p.allocate(&[(layout.clone(), None)]).unwrap().remove(0);
        assert_eq!(set.binding(0).unwrap(), vec![Descriptor::Empty; 4]);
        assert_eq!(set.binding(1), None);

        let d = |off, range| buffer_descriptor(vk::DescriptorType::STORAGE_BUFFER, Some(b.clone()), 0x77, off, range, &LIMITS).unwrap();
        set.write(0, 1, vk::DescriptorType::STORAGE_BUFFER, vec![d(0, 64), d(256, vk::WHOLE_SIZE)]).unwrap();
        assert_eq!(set.descriptor(0, 0), Some(Descriptor::Empty));
        assert_eq!(set.descriptor(0, 1), Some(d(0, 64)));
        let (buf, off, len) = set.descriptor(0, 2).unwrap().buffer_range(0).unwrap();
        assert!(Arc::ptr_eq(&buf, &b));
        assert_eq!((off, len), (256, 4096 - 256));
        assert_eq!(set.descriptor(0, 2).unwrap().handle(), 0x77);

        // Wrong type, unknown binding, past the end.
        assert_eq!(set.write(3, 0, vk::DescriptorType::STORAGE_BUFFER, vec![d(0, 16)]).unwrap_err().vuid, "VUID-VkWriteDescriptorSet-descriptorType-00319");
        assert_eq!(set.write(1, 0, vk::DescriptorType::STORAGE_BUFFER, vec![d(0, 16)]).unwrap_err().vuid, "VUID-VkWriteDescriptorSet-dstBinding-00315");
        // Rolling over from binding 0 into binding 3 (a different type) is invalid, and
        // nothing is written.
        assert!(set.write(0, 3, vk::DescriptorType::STORAGE_BUFFER, vec![d(0, 16), d(16, 16)]).is_err());
        assert_eq!(set.descriptor(0, 3), Some(Descriptor::Empty));

        // A destroyed buffer leaves an invalid descriptor, not a dangling one.
        let b2 = storage(&space, 256, vk::BufferUsageFlags::STORAGE_BUFFER);
        set.write(0, 0, vk::DescriptorType::STORAGE_BUFFER, vec![buffer_descriptor(vk::DescriptorType::STORAGE_BUFFER, Some(b2.clone()), 1, 0, 256, &LIMITS).unwrap()]).unwrap();
        drop(b2);
        assert!(set.descriptor(0, 0).unwrap().buffer_range(0).is_none());
    }

    #[test]
    fn buffer_descriptor_checks() {
        let space = AddressSpace::new(1 << 24);
        let st = storage(&space, 1024, vk::BufferUsageFlags::STORAGE_BUFFER);
        let check = |t, b: &Arc<Buffer>, off, range| buffer_descriptor(t, Some(b.clone()), 1, off, range, &LIMITS).err().map(|v| v.vuid);
        let sb = vk::DescriptorType::STORAGE_BUFFER;
        assert_eq!(check(sb, &st, 0, 1024), None);
        assert_eq!(check(sb, &st, 1024, vk::WHOLE_SIZE), Some("VUID-VkDescriptorBufferInfo-offset-00340"));
        assert_eq!(check(sb, &st, 0, 0), Some("VUID-VkDescriptorBufferInfo-range-00341"));
        assert_eq!(check(sb, &st, 16, 1024), Some("VUID-VkDescriptorBufferInfo-range-00342"));
        assert_eq!(check(sb, &st, 8, 16), Some("VUID-VkWriteDescriptorSet-descriptorType-00328"));
        assert_eq!(check(vk::DescriptorType::UNIFORM_BUFFER, &st, 0, 16), Some("VUID-VkWriteDescriptorSet-descriptorType-00330"));
        let un = storage(&space, 1 << 17, vk::BufferUsageFlags::UNIFORM_BUFFER);
        assert_eq!(check(vk::DescriptorType::UNIFORM_BUFFER, &un, 0, vk::WHOLE_SIZE), Some("VUID-VkWriteDescriptorSet-descriptorType-00332"));
        // Dynamic: the range limit applies at bind time.
        assert_eq!(check(vk::DescriptorType::UNIFORM_BUFFER_DYNAMIC, &un, 0, vk::WHOLE_SIZE), None);
        let unbound = Arc::new(Buffer::new(64, vk::BufferUsageFlags::STORAGE_BUFFER, vk::BufferCreateFlags::empty()));
        assert_eq!(check(sb, &unbound, 0, 64), Some("VUID-VkWriteDescriptorSet-descriptorType-00329"));
        assert_eq!(buffer_descriptor(sb, None, 5, 0, 4, &LIMITS).unwrap_err().vuid, "VUID-VkDescriptorBufferInfo-buffer-02998");
    }

    #[test]
    fn roll_over_and_copies() {
        let space = AddressSpace::new(1 << 24);
        let b = storage(&space, 4096, vk::BufferUsageFlags::STORAGE_BUFFER);
        let t = vk::DescriptorType::STORAGE_BUFFER;
        // Binding 1 is empty and skipped by roll-over.
        let layout = Arc::new(
            DescriptorSetLayout::new(
                vk::DescriptorSetLayoutCreateFlags::empty(),
                vec![binding(0, t, 2), binding(1, vk::DescriptorType::UNIFORM_BUFFER, 0), binding(2, t, 3)],
            )
            .unwrap(),
        );
        let p = pool(2, &[(t, 10)], vk::DescriptorPoolCreateFlags::empty());
        let sets = p.allocate(&[(layout.clone(), None), (layout.clone(), None)]).unwrap();
        let d = |i: u64| buffer_descriptor(t, Some(b.clone()), 9, i * 16, 16, &LIMITS).unwrap();
        // Four descriptors from (0, 1): one into binding 0, three into binding 2.
        sets[0].write(0, 1, t, (0..4).map(d).collect()).unwrap();
        assert_eq!(sets[0].binding(0).unwrap(), vec![Descriptor::Empty, d(0)]);
        assert_eq!(sets[0].binding(2).unwrap(), vec![d(1), d(2), d(3)]);
        // Past the end of the last binding.
        assert_eq!(sets[0].write(2, 2, t, vec![d(0), d(1)]).unwrap_err().vuid, "VUID-VkWriteDescriptorSet-dstArrayElement-00321");
        // An element index past a binding's end continues in the next bindings.
        sets[1].write(0, 3, t, vec![d(7)]).unwrap();
        assert_eq!(sets[1].descriptor(2, 1), Some(d(7)));

        // Copies (with roll-over on both sides) and a copy within one set.
        sets[1].copy_from(&sets[0], 0, 1, 2, 0, 3).unwrap();
        assert_eq!(sets[1].binding(2).unwrap(), vec![d(0), d(1), d(2)]);
        sets[0].copy_from(&sets[0], 2, 2, 0, 0, 1).unwrap();
        assert_eq!(sets[0].descriptor(0, 0), Some(d(3)));
        assert!(sets[1].copy_from(&sets[0], 0, 0, 1, 0, 1).is_err(), "type mismatch");
    }

    #[test]
    fn pool_limits_free_and_reset() {
        let t = vk::DescriptorType::STORAGE_BUFFER;
        let layout = Arc::new(DescriptorSetLayout::new(vk::DescriptorSetLayoutCreateFlags::empty(), vec![binding(0, t, 2)]).unwrap());
        let p = pool(3, &[(t, 5)], vk::DescriptorPoolCreateFlags::FREE_DESCRIPTOR_SET);
        let a = p.allocate(&[(layout.clone(), None), (layout.clone(), None)]).unwrap();
        // 4 of 5 descriptors used: a third set needs 2 more.
        assert_eq!(p.allocate(&[(layout.clone(), None)]).unwrap_err(), AllocateError::OutOfPoolMemory);
        assert_eq!(p.allocated(), 2);
        p.free(&a[..1]).unwrap();
        assert!(!p.owns(&a[0]) && p.owns(&a[1]));
        let b = p.allocate(&[(layout.clone(), None)]).unwrap();
        assert_eq!(p.allocated(), 2);
        // maxSets: an empty layout uses no descriptors but still a set.
        let empty = Arc::new(DescriptorSetLayout::new(vk::DescriptorSetLayoutCreateFlags::empty(), vec![]).unwrap());
        p.allocate(&[(empty.clone(), None)]).unwrap();
        assert_eq!(p.allocate(&[(empty.clone(), None)]).unwrap_err(), AllocateError::OutOfPoolMemory);
        // All or nothing.
        assert_eq!(p.reset().len(), 3);
        assert_eq!(p.allocate(&[(layout.clone(), None), (layout.clone(), None), (layout.clone(), None)]).unwrap_err(), AllocateError::OutOfPoolMemory);
        assert_eq!(p.allocated(), 0);
        // Sets of another pool, and pools without FREE_DESCRIPTOR_SET.
        assert!(p.free(&b).is_err());
        let fixed = pool(1, &[(t, 2)], vk::DescriptorPoolCreateFlags::empty());
        let s = fixed.allocate(&[(layout.clone(), None)]).unwrap();
        assert_eq!(fixed.free(&s).unwrap_err().vuid, "VUID-vkFreeDescriptorSets-descriptorPool-00312");
    }

    #[test]
    fn binding_flags_and_variable_counts() {
        let t = vk::DescriptorType::STORAGE_BUFFER;
        let mut var = binding(1, t, 100);
        var.flags = vk::DescriptorBindingFlags::VARIABLE_DESCRIPTOR_COUNT | vk::DescriptorBindingFlags::PARTIALLY_BOUND;
        let mut uab = binding(0, t, 1);
        uab.flags = vk::DescriptorBindingFlags::UPDATE_AFTER_BIND;
        // UPDATE_AFTER_BIND needs the layout flag.
        assert_eq!(
            DescriptorSetLayout::new(vk::DescriptorSetLayoutCreateFlags::empty(), vec![uab.clone()]).unwrap_err().vuid,
            "VUID-VkDescriptorSetLayoutCreateInfo-flags-03000"
        );
        // The variable binding must be the last one.
        let mut early = var.clone();
        early.binding = 0;
        let mut after = binding(1, t, 1);
        after.binding = 5;
        assert!(DescriptorSetLayout::new(vk::DescriptorSetLayoutCreateFlags::empty(), vec![early, after]).is_err());
        let layout = Arc::new(
            DescriptorSetLayout::new(vk::DescriptorSetLayoutCreateFlags::UPDATE_AFTER_BIND_POOL, vec![var.clone(), uab.clone()]).unwrap(),
        );
        assert_eq!(layout.binding(1).unwrap().flags, var.flags);
        assert_eq!(layout.variable_binding().map(|b| b.binding), Some(1));
        // Needs an UPDATE_AFTER_BIND pool.
        let plain = pool(4, &[(t, 200)], vk::DescriptorPoolCreateFlags::empty());
        assert!(matches!(plain.allocate(&[(layout.clone(), Some(3))]), Err(AllocateError::Invalid(_))));
        let p = pool(4, &[(t, 20)], vk::DescriptorPoolCreateFlags::UPDATE_AFTER_BIND);
        let s = p.allocate(&[(layout.clone(), Some(7))]).unwrap().remove(0);
        assert_eq!(s.variable_count, 7);
        assert_eq!(s.binding(1).unwrap().len(), 7);
        // Without a count the variable binding is empty; counts above the maximum are invalid;
        // the pool counts the variable count, not the maximum.
        assert_eq!(p.allocate(&[(layout.clone(), None)]).unwrap()[0].binding(1).unwrap().len(), 0);
        assert!(matches!(p.allocate(&[(layout.clone(), Some(101))]), Err(AllocateError::Invalid(_))));
        assert!(p.allocate(&[(layout.clone(), Some(10))]).is_ok());
        assert_eq!(p.allocate(&[(layout.clone(), Some(2))]).unwrap_err(), AllocateError::OutOfPoolMemory);
    }

    #[test]
    fn acceleration_structure_descriptors() {
        let space = AddressSpace::new(1 << 24);
        let b = storage(&space, 4096, vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR);
        let make = |t| {
            Arc::new(AccelerationStructure {
                buffer: b.clone(),
                offset: 256,
                size: 1024,
                create_type: t,
                create_flags: vk::AccelerationStructureCreateFlagsKHR::empty(),
            })
        };
        let tlas = make(vk::AccelerationStructureTypeKHR::TOP_LEVEL);
        let blas = make(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL);
        let t = vk::DescriptorType::ACCELERATION_STRUCTURE_KHR;
        let mut asb = binding(0, t, 2);
        asb.flags = vk::DescriptorBindingFlags::UPDATE_AFTER_BIND;
        let layout = Arc::new(DescriptorSetLayout::new(vk::DescriptorSetLayoutCreateFlags::UPDATE_AFTER_BIND_POOL, vec![asb]).unwrap());
        let p = pool(1, &[(t, 2)], vk::DescriptorPoolCreateFlags::UPDATE_AFTER_BIND);
        let set = p.allocate(&[(layout, None)]).unwrap().remove(0);
        let d = acceleration_structure_descriptor(Some(tlas.clone()), 0x42).unwrap();
        set.write(0, 1, t, vec![d.clone()]).unwrap();
        assert_eq!(set.descriptor(0, 1), Some(d));
        let got = set.descriptor(0, 1).unwrap().acceleration_structure().unwrap();
        assert!(Arc::ptr_eq(&got, &tlas));
        assert_eq!(set.descriptor(0, 1).unwrap().handle(), 0x42);
        assert_eq!(
            acceleration_structure_descriptor(Some(blas), 1).unwrap_err().vuid,
            "VUID-VkWriteDescriptorSetAccelerationStructureKHR-pAccelerationStructures-03579"
        );
        assert!(acceleration_structure_descriptor(None, 0).is_err());
        drop((got, tlas));
        assert!(set.descriptor(0, 1).unwrap().acceleration_structure().is_none());
    }

    #[test]
    fn templates_and_pipeline_layouts() {
        let t = vk::DescriptorType::STORAGE_BUFFER;
        let layout = Arc::new(DescriptorSetLayout::new(vk::DescriptorSetLayoutCreateFlags::empty(), vec![binding(0, t, 2)]).unwrap());
        let entry = TemplateEntry { binding: 0, element: 0, count: 2, descriptor_type: t, offset: 0, stride: 24 };
        assert!(DescriptorUpdateTemplate::new(layout.clone(), vec![entry.clone()]).is_ok());
        assert!(DescriptorUpdateTemplate::new(layout.clone(), vec![TemplateEntry { binding: 4, ..entry.clone() }]).is_err());
        assert!(DescriptorUpdateTemplate::new(layout.clone(), vec![TemplateEntry { descriptor_type: vk::DescriptorType::UNIFORM_BUFFER, ..entry }]).is_err());

        let range = |stages, offset, size| vk::PushConstantRange { stage_flags: stages, offset, size };
        let ok = PipelineLayout::new(
            vk::PipelineLayoutCreateFlags::empty(),
            vec![layout.clone(), layout.clone()],
            vec![range(vk::ShaderStageFlags::COMPUTE, 0, 128)],
            8,
            128,
        )
        .unwrap();
        assert_eq!(ok.set_layouts.len(), 2);
        assert_eq!(ok.push_constant_ranges[0].size, 128);
        let bad = |ranges, sets: usize| PipelineLayout::new(vk::PipelineLayoutCreateFlags::empty(), vec![layout.clone(); sets], ranges, 8, 128).map(|_| ()).unwrap_err().vuid;
        assert_eq!(bad(vec![], 9), "VUID-VkPipelineLayoutCreateInfo-setLayoutCount-00286");
        assert_eq!(bad(vec![range(vk::ShaderStageFlags::COMPUTE, 2, 4)], 1), "VUID-VkPushConstantRange-offset-00294");
        assert_eq!(bad(vec![range(vk::ShaderStageFlags::COMPUTE, 64, 68)], 1), "VUID-VkPushConstantRange-size-00298");
        assert_eq!(
            bad(vec![range(vk::ShaderStageFlags::COMPUTE, 0, 4), range(vk::ShaderStageFlags::COMPUTE, 4, 4)], 1),
            "VUID-VkPipelineLayoutCreateInfo-pPushConstantRanges-00292"
        );
    }
}

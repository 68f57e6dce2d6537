//! Descriptor objects: set layouts, pools, sets (which store what was written), update
//! templates and pipeline layouts. Plain Rust values: the dispatch layer converts the
//! application's structs into [`Descriptor`]s and calls one method here.
//!
//! A set stores one [`Descriptor`] per array element of each binding. Buffer descriptors keep a
//! weak reference to the buffer (a destroyed buffer makes the descriptor invalid, it does not
//! keep the memory alive) plus the handle for diagnostics. A new descriptor kind (for example
//! acceleration structures) is one more [`Descriptor`] variant and one arm in [`type_class`].
use std::collections::HashMap;
use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};

use ash::vk;

use crate::memory::Buffer;

/// Descriptors Arbor can store. Types Arbor has no objects for yet (samplers, images, texel
/// buffers) are kept as raw handles so that writes and copies still round-trip.
#[derive(Clone)]
pub enum Descriptor {
    /// Never written (or written as null with nullDescriptor-like partially bound use).
    Empty,
    /// Uniform/storage buffer (also _DYNAMIC): `range` as written (may be VK_WHOLE_SIZE).
    Buffer { buffer: Weak<Buffer>, handle: u64, offset: u64, range: u64 },
    /// Sampler / image descriptors: raw handles and the layout.
    Image { sampler: u64, image_view: u64, layout: vk::ImageLayout },
    /// Uniform/storage texel buffer: the raw buffer-view handle.
    TexelBuffer { view: u64 },
}

impl Descriptor {
    /// The buffer and the effective byte range for a buffer descriptor (`dynamic_offset` added
    /// for the _DYNAMIC types). None for other kinds or when the buffer was destroyed.
    pub fn buffer_range(&self, dynamic_offset: u64) -> Option<(Arc<Buffer>, u64, u64)> {
        match self {
            Descriptor::Buffer { buffer, offset, range, .. } => {
                let b = buffer.upgrade()?;
                let start = offset.checked_add(dynamic_offset)?;
                let len = if *range == vk::WHOLE_SIZE { b.size.checked_sub(start)? } else { *range };
                Some((b, start, len))
            }
            _ => None,
        }
    }

    /// The raw handle of the object the descriptor refers to (0 for none).
    pub fn handle(&self) -> u64 {
        match self {
            Descriptor::Empty => 0,
            Descriptor::Buffer { handle, .. } => *handle,
            Descriptor::Image { image_view, sampler, .. } => {
                if *image_view != 0 {
                    *image_view
                } else {
                    *sampler
                }
            }
            Descriptor::TexelBuffer { view } => *view,
        }
    }
}

impl PartialEq for Descriptor {
    fn eq(&self, other: &Self) -> bool {
        match (self, other) {
            (Descriptor::Empty, Descriptor::Empty) => true,
            (
                Descriptor::Buffer { buffer: a, handle: ha, offset: oa, range: ra },
                Descriptor::Buffer { buffer: b, handle: hb, offset: ob, range: rb },
            ) => a.ptr_eq(b) && ha == hb && oa == ob && ra == rb,
            (
                Descriptor::Image { sampler: sa, image_view: va, layout: la },
                Descriptor::Image { sampler: sb, image_view: vb, layout: lb },
            ) => sa == sb && va == vb && la == lb,
            (Descriptor::TexelBuffer { view: a }, Descriptor::TexelBuffer { view: b }) => a == b,
            _ => false,
        }
    }
}

impl fmt::Debug for Descriptor {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Descriptor::Empty => write!(f, "Empty"),
            Descriptor::Buffer { handle, offset, range, buffer } => write!(
                f,
                "Buffer({handle:#x}, offset {offset}, range {range}{})",
                if buffer.strong_count() == 0 { ", destroyed" } else { "" }
            ),
            Descriptor::Image { sampler, image_view, layout } => {
                write!(f, "Image(sampler {sampler:#x}, view {image_view:#x}, {layout:?})")
            }
            Descriptor::TexelBuffer { view } => write!(f, "TexelBuffer({view:#x})"),
        }
    }
}

/// Which [`Descriptor`] kind a descriptor type stores.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum TypeClass {
    Buffer,
    Image,
    TexelBuffer,
    /// Types Arbor does not support (inline uniform blocks, mutable, …).
    Unsupported,
}

pub fn type_class(t: vk::DescriptorType) -> TypeClass {
    match t {
        vk::DescriptorType::UNIFORM_BUFFER
        | vk::DescriptorType::STORAGE_BUFFER
        | vk::DescriptorType::UNIFORM_BUFFER_DYNAMIC
        | vk::DescriptorType::STORAGE_BUFFER_DYNAMIC => TypeClass::Buffer,
        vk::DescriptorType::SAMPLER
        | vk::DescriptorType::COMBINED_IMAGE_SAMPLER
        | vk::DescriptorType::SAMPLED_IMAGE
        | vk::DescriptorType::STORAGE_IMAGE
        | vk::DescriptorType::INPUT_ATTACHMENT => TypeClass::Image,
        vk::DescriptorType::UNIFORM_TEXEL_BUFFER | vk::DescriptorType::STORAGE_TEXEL_BUFFER => TypeClass::TexelBuffer,
        _ => TypeClass::Unsupported,
    }
}

pub fn is_dynamic(t: vk::DescriptorType) -> bool {
    matches!(t, vk::DescriptorType::UNIFORM_BUFFER_DYNAMIC | vk::DescriptorType::STORAGE_BUFFER_DYNAMIC)
}

/// A valid-usage violation found by this module: the VUID and what is wrong. The dispatch
/// layer reports it with the command's name.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Violation {
    pub vuid: &'static str,
    pub message: String,
}

fn violation(vuid: &'static str, message: impl Into<String>) -> Violation {
    Violation { vuid, message: message.into() }
}

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
                    "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-None-03005",
                    format!("binding {}: dynamic buffer descriptors cannot be UPDATE_AFTER_BIND", b.binding),
                ));
            }
            if uab && !matches!(b.descriptor_type, vk::DescriptorType::UNIFORM_BUFFER | vk::DescriptorType::STORAGE_BUFFER) {
                return Err(violation(
                    "VUID-VkDescriptorSetLayoutBindingFlagsCreateInfo-descriptorBindingSampledImageUpdateAfterBind-03006",
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

/// Device limits the buffer-descriptor checks use (VkPhysicalDeviceLimits).
#[derive(Clone, Copy, Debug)]
pub struct BufferLimits {
    pub min_uniform_offset_alignment: u64,
    pub min_storage_offset_alignment: u64,
    pub max_uniform_range: u64,
    pub max_storage_range: u64,
}

/// Check and build a buffer descriptor of type `t` (VkDescriptorBufferInfo). `buffer` is the
/// looked-up buffer (None for a null or unknown handle).
pub fn buffer_descriptor(
    t: vk::DescriptorType,
    buffer: Option<Arc<Buffer>>,
    handle: u64,
    offset: u64,
    range: u64,
    limits: &BufferLimits,
) -> Result<Descriptor, Violation> {
    let Some(b) = buffer else {
        return Err(violation(
            "VUID-VkDescriptorBufferInfo-buffer-02998",
            format!("buffer {handle:#x} is not a live VkBuffer (the nullDescriptor feature is not offered)"),
        ));
    };
    if offset >= b.size {
        return Err(violation("VUID-VkDescriptorBufferInfo-offset-00340", format!("offset {offset} is not less than the buffer size {}", b.size)));
    }
    if range != vk::WHOLE_SIZE {
        if range == 0 {
            return Err(violation("VUID-VkDescriptorBufferInfo-range-00341", "range is 0"));
        }
        if range > b.size - offset {
            return Err(violation(
                "VUID-VkDescriptorBufferInfo-range-00342",
                format!("offset {offset} + range {range} exceeds the buffer size {}", b.size),
            ));
        }
    }
    let effective = if range == vk::WHOLE_SIZE { b.size - offset } else { range };
    let uniform = matches!(t, vk::DescriptorType::UNIFORM_BUFFER | vk::DescriptorType::UNIFORM_BUFFER_DYNAMIC);
    let (usage, usage_vuid, align, align_vuid, max, max_vuid) = if uniform {
        (
            vk::BufferUsageFlags::UNIFORM_BUFFER,
            "VUID-VkWriteDescriptorSet-descriptorType-00330",
            limits.min_uniform_offset_alignment,
            "VUID-VkWriteDescriptorSet-descriptorType-00327",
            limits.max_uniform_range,
            "VUID-VkWriteDescriptorSet-descriptorType-00332",
        )
    } else {
        (
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "VUID-VkWriteDescriptorSet-descriptorType-00331",
            limits.min_storage_offset_alignment,
            "VUID-VkWriteDescriptorSet-descriptorType-00328",
            limits.max_storage_range,
            "VUID-VkWriteDescriptorSet-descriptorType-00333",
        )
    };
    if !b.usage.contains(usage) {
        return Err(violation(usage_vuid, format!("{t:?} descriptor for a buffer without {usage:?} usage ({:?})", b.usage)));
    }
    if offset % align.max(1) != 0 {
        return Err(violation(align_vuid, format!("offset {offset} is not a multiple of {align}")));
    }
    // For the dynamic types the effective range is only known at bind time.
    if !is_dynamic(t) && effective > max {
        return Err(violation(max_vuid, format!("range {effective} exceeds the device limit {max}")));
    }
    if b.memory().is_none() {
        return Err(violation("VUID-VkWriteDescriptorSet-descriptorType-00329", "the buffer is not bound to memory"));
    }
    Ok(Descriptor::Buffer { buffer: Arc::downgrade(&b), handle, offset, range })
}

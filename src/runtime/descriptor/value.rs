//! Descriptor values: what a set stores per array element ([`Descriptor`]), the class of each
//! descriptor type, and the checked conversion of a written buffer or acceleration structure
//! into a descriptor, with the [`Violation`]s those checks find.
//!
//! This module holds no objects (layouts, pools, sets are the parent's) and reports nothing
//! itself: the dispatch layer reports violations with the command's name.
use std::fmt;
use std::sync::{Arc, Weak};

use ash::vk;

use crate::memory::Buffer;
use crate::runtime::accel::AccelerationStructure;
use crate::runtime::image::{BufferView, ImageView};

/// Descriptors Arbor can store. Types Arbor has no objects for yet (samplers, images, texel
/// buffers) are kept as raw handles so that writes and copies still round-trip.
#[derive(Clone)]
pub enum Descriptor {
    /// Never written (or written as null with nullDescriptor-like partially bound use).
    Empty,
    /// Uniform/storage buffer (also _DYNAMIC): `range` as written (may be VK_WHOLE_SIZE).
    Buffer { buffer: Weak<Buffer>, handle: u64, offset: u64, range: u64 },
    /// Sampler / sampled-image descriptors (not run): raw handles and the layout.
    Image { sampler: u64, image_view: u64, layout: vk::ImageLayout },
    /// VK_DESCRIPTOR_TYPE_STORAGE_IMAGE: the view, held weakly like buffers.
    StorageImage { view: Weak<ImageView>, handle: u64, layout: vk::ImageLayout },
    /// Uniform/storage texel buffer: the view, held weakly like buffers.
    TexelBuffer { view: Weak<BufferView>, handle: u64 },
    /// VK_DESCRIPTOR_TYPE_ACCELERATION_STRUCTURE_KHR.
    AccelerationStructure { structure: Weak<AccelerationStructure>, handle: u64 },
    /// VK_DESCRIPTOR_TYPE_PARTITIONED_ACCELERATION_STRUCTURE_NV: a PTLAS is no object, only
    /// bytes at a device address (0: the null descriptor, which the spec allows).
    PartitionedAccelerationStructure { address: u64 },
}

/// VK_DESCRIPTOR_TYPE_PARTITIONED_ACCELERATION_STRUCTURE_NV (vk.xml; ash 0.38 lacks it).
pub const PARTITIONED_ACCELERATION_STRUCTURE_NV: vk::DescriptorType = vk::DescriptorType::from_raw(1000570000);

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
            Descriptor::TexelBuffer { handle, .. } => *handle,
            Descriptor::AccelerationStructure { handle, .. } | Descriptor::StorageImage { handle, .. } => *handle,
            Descriptor::PartitionedAccelerationStructure { address } => *address,
        }
    }

    /// The view of a storage-image descriptor (None for other kinds or when it was destroyed).
    pub fn storage_image(&self) -> Option<Arc<ImageView>> {
        match self {
            Descriptor::StorageImage { view, .. } => view.upgrade(),
            _ => None,
        }
    }

    /// The view of a texel-buffer descriptor (None for other kinds or when it was destroyed).
    pub fn texel_buffer(&self) -> Option<Arc<BufferView>> {
        match self {
            Descriptor::TexelBuffer { view, .. } => view.upgrade(),
            _ => None,
        }
    }

    /// The acceleration structure of an acceleration-structure descriptor (None for other
    /// kinds or when it was destroyed).
    pub fn acceleration_structure(&self) -> Option<Arc<AccelerationStructure>> {
        match self {
            Descriptor::AccelerationStructure { structure, .. } => structure.upgrade(),
            _ => None,
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
            (Descriptor::TexelBuffer { view: a, handle: ha }, Descriptor::TexelBuffer { view: b, handle: hb }) => a.ptr_eq(b) && ha == hb,
            (
                Descriptor::StorageImage { view: a, handle: ha, layout: la },
                Descriptor::StorageImage { view: b, handle: hb, layout: lb },
            ) => a.ptr_eq(b) && ha == hb && la == lb,
            (
                Descriptor::AccelerationStructure { structure: a, handle: ha },
                Descriptor::AccelerationStructure { structure: b, handle: hb },
            ) => a.ptr_eq(b) && ha == hb,
            (Descriptor::PartitionedAccelerationStructure { address: a }, Descriptor::PartitionedAccelerationStructure { address: b }) => a == b,
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
            Descriptor::TexelBuffer { view, handle } => {
                write!(f, "TexelBuffer({handle:#x}{})", if view.strong_count() == 0 { ", destroyed" } else { "" })
            }
            Descriptor::StorageImage { view, handle, layout } => write!(
                f,
                "StorageImage({handle:#x}, {layout:?}{})",
                if view.strong_count() == 0 { ", destroyed" } else { "" }
            ),
            Descriptor::AccelerationStructure { handle, structure } => write!(
                f,
                "AccelerationStructure({handle:#x}{})",
                if structure.strong_count() == 0 { ", destroyed" } else { "" }
            ),
            Descriptor::PartitionedAccelerationStructure { address } => write!(f, "PartitionedAccelerationStructure({address:#x})"),
        }
    }
}

/// Which [`Descriptor`] kind a descriptor type stores.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum TypeClass {
    Buffer,
    Image,
    TexelBuffer,
    AccelerationStructure,
    /// A PTLAS by device address.
    PartitionedAccelerationStructure,
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
        vk::DescriptorType::ACCELERATION_STRUCTURE_KHR => TypeClass::AccelerationStructure,
        PARTITIONED_ACCELERATION_STRUCTURE_NV => TypeClass::PartitionedAccelerationStructure,
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

pub(super) fn violation(vuid: &'static str, message: impl Into<String>) -> Violation {
    Violation { vuid, message: message.into() }
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
    if !offset.is_multiple_of(align.max(1)) {
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

/// Check and build an acceleration-structure descriptor. `structure` is the looked-up object
/// (None for a null or unknown handle).
pub fn acceleration_structure_descriptor(structure: Option<Arc<AccelerationStructure>>, handle: u64) -> Result<Descriptor, Violation> {
    let Some(s) = structure else {
        return Err(violation(
            "VUID-VkWriteDescriptorSetAccelerationStructureKHR-pAccelerationStructures-03580",
            format!("{handle:#x} is not a live VkAccelerationStructureKHR (the nullDescriptor feature is not offered)"),
        ));
    };
    if s.create_type == vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL {
        return Err(violation(
            "VUID-VkWriteDescriptorSetAccelerationStructureKHR-pAccelerationStructures-03579",
            "a bottom-level acceleration structure cannot be written to a descriptor",
        ));
    }
    Ok(Descriptor::AccelerationStructure { structure: Arc::downgrade(&s), handle })
}

/// Check and build a storage-image descriptor. `view` is the looked-up object (None when the
/// handle is not a live view).
pub fn storage_image_descriptor(view: Option<Arc<ImageView>>, handle: u64, layout: vk::ImageLayout) -> Result<Descriptor, Violation> {
    let Some(v) = view else {
        return Err(violation("VUID-VkWriteDescriptorSet-descriptorType-02997", format!("imageView {handle:#x} is not a live VkImageView (nullDescriptor is not offered)")));
    };
    if !v.image.usage.contains(vk::ImageUsageFlags::STORAGE) {
        return Err(violation("VUID-VkWriteDescriptorSet-descriptorType-00339", "the view's image lacks VK_IMAGE_USAGE_STORAGE_BIT"));
    }
    if v.level_count != 1 {
        return Err(violation("VUID-VkWriteDescriptorSet-descriptorType-00336", format!("a storage-image view must select one mip level, not {}", v.level_count)));
    }
    if layout != vk::ImageLayout::GENERAL {
        return Err(violation("VUID-VkWriteDescriptorSet-descriptorType-04152", format!("imageLayout {layout:?}: storage images must be in VK_IMAGE_LAYOUT_GENERAL")));
    }
    Ok(Descriptor::StorageImage { view: Arc::downgrade(&v), handle, layout })
}

/// A uniform or storage texel-buffer descriptor (`t` says which) naming `view` (None when
/// `handle` is no live VkBufferView).
pub fn texel_buffer_descriptor(t: vk::DescriptorType, view: Option<Arc<BufferView>>, handle: u64) -> Result<Descriptor, Violation> {
    let Some(v) = view else {
        return Err(violation("VUID-VkWriteDescriptorSet-descriptorType-02994", format!("pTexelBufferView {handle:#x} is not a live VkBufferView (nullDescriptor is not offered)")));
    };
    let (usage, vuid) = if t == vk::DescriptorType::UNIFORM_TEXEL_BUFFER {
        (vk::BufferUsageFlags::UNIFORM_TEXEL_BUFFER, "VUID-VkWriteDescriptorSet-descriptorType-08765")
    } else {
        (vk::BufferUsageFlags::STORAGE_TEXEL_BUFFER, "VUID-VkWriteDescriptorSet-descriptorType-08766")
    };
    if !v.buffer.usage.contains(usage) {
        return Err(violation(vuid, format!("the view's buffer lacks {usage:?} usage")));
    }
    Ok(Descriptor::TexelBuffer { view: Arc::downgrade(&v), handle })
}

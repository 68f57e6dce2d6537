//! Images and image views: the storage-image formats Arbor runs (and nothing else), the
//! checks of image and view creation, and [`storage_image_binding`], which turns a bound
//! storage-image descriptor into what the shader library reads and writes. Texel storage and
//! range checks are `crate::memory::image`'s; the transfer commands are in `image_copy`.
use std::sync::Arc;

use ash::vk;

use crate::memory::image::Image as Storage;
use crate::runtime::descriptor::Descriptor;
use crate::shader::{ImageBinding, ImageFormat};

/// One format Arbor supports for images, and what a shader sees of it.
#[derive(Clone, Copy, Debug)]
pub struct FormatInfo {
    pub format: vk::Format,
    pub texel_size: u32,
    pub shader: ImageFormat,
}

/// Every image format Arbor offers: storage images and transfers, both tilings.
pub const FORMATS: &[FormatInfo] = &[
    FormatInfo { format: vk::Format::R32_UINT, texel_size: 4, shader: ImageFormat::R32Uint },
    FormatInfo { format: vk::Format::R32_SINT, texel_size: 4, shader: ImageFormat::R32Sint },
    FormatInfo { format: vk::Format::R32_SFLOAT, texel_size: 4, shader: ImageFormat::R32Sfloat },
    FormatInfo { format: vk::Format::R32G32B32A32_UINT, texel_size: 16, shader: ImageFormat::Rgba32Uint },
    FormatInfo { format: vk::Format::R32G32B32A32_SINT, texel_size: 16, shader: ImageFormat::Rgba32Sint },
    FormatInfo { format: vk::Format::R32G32B32A32_SFLOAT, texel_size: 16, shader: ImageFormat::Rgba32Sfloat },
    FormatInfo { format: vk::Format::R8G8B8A8_UNORM, texel_size: 4, shader: ImageFormat::Rgba8Unorm },
];

pub fn format_info(format: vk::Format) -> Option<&'static FormatInfo> {
    FORMATS.iter().find(|f| f.format == format)
}

/// Usages an image may have: storage and transfers (no sampling, no attachments).
pub const SUPPORTED_USAGE: vk::ImageUsageFlags =
    vk::ImageUsageFlags::from_raw(vk::ImageUsageFlags::STORAGE.as_raw() | vk::ImageUsageFlags::TRANSFER_SRC.as_raw() | vk::ImageUsageFlags::TRANSFER_DST.as_raw());

/// Largest extent per image type (the device limits maxImageDimension1D/2D/3D) and layers.
pub const MAX_DIMENSION_1D: u32 = 4096;
pub const MAX_DIMENSION_2D: u32 = 4096;
pub const MAX_DIMENSION_3D: u32 = 256;
pub const MAX_ARRAY_LAYERS: u32 = 256;

/// The largest extent of `ty` (None for image types Arbor does not know).
pub fn max_extent(ty: vk::ImageType) -> Option<[u32; 3]> {
    match ty {
        vk::ImageType::TYPE_1D => Some([MAX_DIMENSION_1D, 1, 1]),
        vk::ImageType::TYPE_2D => Some([MAX_DIMENSION_2D, MAX_DIMENSION_2D, 1]),
        vk::ImageType::TYPE_3D => Some([MAX_DIMENSION_3D; 3]),
        _ => None,
    }
}

/// Mip levels of a full chain for `extent`.
pub fn full_chain(extent: [u32; 3]) -> u32 {
    32 - extent.iter().copied().max().unwrap_or(1).max(1).leading_zeros()
}

/// One `VkImage`.
pub struct Image {
    pub format: vk::Format,
    pub image_type: vk::ImageType,
    pub tiling: vk::ImageTiling,
    pub usage: vk::ImageUsageFlags,
    pub flags: vk::ImageCreateFlags,
    pub info: FormatInfo,
    pub storage: Storage,
}

/// The parts of VkImageCreateInfo Arbor reads.
#[derive(Clone, Copy, Debug)]
pub struct ImageDesc {
    pub flags: vk::ImageCreateFlags,
    pub image_type: vk::ImageType,
    pub format: vk::Format,
    pub extent: [u32; 3],
    pub mip_levels: u32,
    pub array_layers: u32,
    pub samples: vk::SampleCountFlags,
    pub tiling: vk::ImageTiling,
    pub usage: vk::ImageUsageFlags,
    pub initial_layout: vk::ImageLayout,
}

/// Why an image or view cannot be created: invalid usage (reported with its VUID), or a valid
/// request Arbor does not support.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CreateError {
    Invalid { vuid: &'static str, message: String },
    /// VK_ERROR_FORMAT_NOT_SUPPORTED (with what is unsupported, for the diagnostic).
    Unsupported(String),
}

fn invalid(vuid: &'static str, message: impl Into<String>) -> CreateError {
    CreateError::Invalid { vuid, message: message.into() }
}

impl Image {
    /// Check `d` and create the image (unbound).
    pub fn new(d: &ImageDesc) -> Result<Image, CreateError> {
        if d.extent.contains(&0) {
            return Err(invalid("VUID-VkImageCreateInfo-extent-00944", format!("extent {:?} has a zero dimension", d.extent)));
        }
        if d.mip_levels == 0 || d.array_layers == 0 {
            return Err(invalid("VUID-VkImageCreateInfo-mipLevels-00947", "mipLevels and arrayLayers must be at least 1"));
        }
        if d.usage.is_empty() {
            return Err(invalid("VUID-VkImageCreateInfo-usage-requiredbitmask", "usage is 0"));
        }
        if d.mip_levels > full_chain(d.extent) {
            return Err(invalid("VUID-VkImageCreateInfo-mipLevels-00958", format!("mipLevels {} exceeds the full chain of {:?}", d.mip_levels, d.extent)));
        }
        if d.image_type == vk::ImageType::TYPE_1D && (d.extent[1] != 1 || d.extent[2] != 1) {
            return Err(invalid("VUID-VkImageCreateInfo-imageType-00956", "a 1D image must have height and depth 1"));
        }
        if d.image_type == vk::ImageType::TYPE_2D && d.extent[2] != 1 {
            return Err(invalid("VUID-VkImageCreateInfo-imageType-00957", "a 2D image must have depth 1"));
        }
        if d.image_type == vk::ImageType::TYPE_3D && d.array_layers != 1 {
            return Err(invalid("VUID-VkImageCreateInfo-imageType-00961", "a 3D image must have arrayLayers 1"));
        }
        if d.initial_layout != vk::ImageLayout::UNDEFINED && d.initial_layout != vk::ImageLayout::PREINITIALIZED {
            return Err(invalid("VUID-VkImageCreateInfo-initialLayout-00993", format!("initialLayout {:?}", d.initial_layout)));
        }
        let info = *format_info(d.format).ok_or_else(|| CreateError::Unsupported(format!("format {:?}", d.format)))?;
        // What vkGetPhysicalDeviceImageFormatProperties answers; creating anything else is
        // VUID-VkImageCreateInfo-imageCreateMaxMipLevels-02251 and its neighbours.
        let limits = "VUID-VkImageCreateInfo-imageCreateMaxMipLevels-02251";
        if !(d.usage & !SUPPORTED_USAGE).is_empty() {
            return Err(invalid(limits, format!("usage {:?} is not supported (storage and transfer only)", d.usage & !SUPPORTED_USAGE)));
        }
        if !d.flags.is_empty() {
            return Err(invalid(limits, format!("flags {:?} are not supported", d.flags)));
        }
        if d.samples != vk::SampleCountFlags::TYPE_1 {
            return Err(invalid(limits, format!("samples {:?}: only single-sampled images", d.samples)));
        }
        if !matches!(d.tiling, vk::ImageTiling::OPTIMAL | vk::ImageTiling::LINEAR) {
            return Err(invalid(limits, format!("tiling {:?}", d.tiling)));
        }
        let max = max_extent(d.image_type).ok_or_else(|| invalid("VUID-VkImageCreateInfo-imageType-parameter", format!("{:?}", d.image_type)))?;
        if d.extent.iter().zip(max).any(|(&e, m)| e > m) || d.array_layers > MAX_ARRAY_LAYERS {
            return Err(invalid("VUID-VkImageCreateInfo-extent-02252", format!("extent {:?} x {} layers exceeds {max:?} x {MAX_ARRAY_LAYERS}", d.extent, d.array_layers)));
        }
        let storage = Storage::new(info.texel_size, d.extent, d.mip_levels, d.array_layers)
            .ok_or_else(|| invalid("VUID-VkImageCreateInfo-extent-02252", "image size overflows"))?;
        Ok(Image { format: d.format, image_type: d.image_type, tiling: d.tiling, usage: d.usage, flags: d.flags, info, storage })
    }
}

/// One `VkImageView`: an image and the subresources it selects.
pub struct ImageView {
    pub image: Arc<Image>,
    pub view_type: vk::ImageViewType,
    pub format: vk::Format,
    pub base_level: u32,
    pub level_count: u32,
    pub base_layer: u32,
    pub layer_count: u32,
}

impl ImageView {
    /// Check and create a view of `image`. `range` counts may be VK_REMAINING_*.
    pub fn new(image: Arc<Image>, view_type: vk::ImageViewType, format: vk::Format, range: vk::ImageSubresourceRange) -> Result<ImageView, CreateError> {
        if range.aspect_mask != vk::ImageAspectFlags::COLOR {
            return Err(invalid("VUID-VkImageViewCreateInfo-subresourceRange-09594", format!("aspectMask {:?} (color images: COLOR only)", range.aspect_mask)));
        }
        let s = &image.storage;
        let level_count = if range.level_count == vk::REMAINING_MIP_LEVELS { s.levels.saturating_sub(range.base_mip_level) } else { range.level_count };
        let layer_count = if range.layer_count == vk::REMAINING_ARRAY_LAYERS { s.layers.saturating_sub(range.base_array_layer) } else { range.layer_count };
        if range.base_mip_level >= s.levels || level_count == 0 || range.base_mip_level as u64 + level_count as u64 > s.levels as u64 {
            return Err(invalid("VUID-VkImageViewCreateInfo-subresourceRange-01718", format!("levels {}+{level_count} outside the image's {}", range.base_mip_level, s.levels)));
        }
        if range.base_array_layer >= s.layers || layer_count == 0 || range.base_array_layer as u64 + layer_count as u64 > s.layers as u64 {
            return Err(invalid("VUID-VkImageViewCreateInfo-subresourceRange-06725", format!("layers {}+{layer_count} outside the image's {}", range.base_array_layer, s.layers)));
        }
        // Formats must match: MUTABLE_FORMAT (which would allow others) is not offered.
        if format != image.format {
            return Err(invalid("VUID-VkImageViewCreateInfo-image-01762", format!("view format {format:?} differs from the image's {:?}", image.format)));
        }
        let compatible = match image.image_type {
            vk::ImageType::TYPE_1D => matches!(view_type, vk::ImageViewType::TYPE_1D | vk::ImageViewType::TYPE_1D_ARRAY),
            vk::ImageType::TYPE_2D => matches!(view_type, vk::ImageViewType::TYPE_2D | vk::ImageViewType::TYPE_2D_ARRAY),
            _ => view_type == vk::ImageViewType::TYPE_3D,
        };
        if !compatible {
            return Err(invalid("VUID-VkImageViewCreateInfo-subResourceRange-01021", format!("view type {view_type:?} does not fit a {:?} image", image.image_type)));
        }
        if matches!(view_type, vk::ImageViewType::TYPE_1D | vk::ImageViewType::TYPE_2D | vk::ImageViewType::TYPE_3D) && layer_count != 1 {
            return Err(invalid("VUID-VkImageViewCreateInfo-imageViewType-04973", format!("a non-array view must have one layer, not {layer_count}")));
        }
        Ok(ImageView { image, view_type, format, base_level: range.base_mip_level, level_count, base_layer: range.base_array_layer, layer_count })
    }

    /// What a shader sees of this view as a storage image, with `id` as the name the caller's
    /// `shader::Memory` gives the image's memory (texel offsets are relative to the image's
    /// start: `crate::memory::image::Image::read`/`write` take them as they are).
    pub fn shader_binding(&self, id: u64) -> Option<ImageBinding> {
        let s = &self.image.storage;
        let sub = s.subresource(self.base_level, self.base_layer)?;
        let extent = s.level_extent(self.base_level);
        Some(ImageBinding {
            buffer: id,
            offset: sub.offset,
            format: self.image.info.shader,
            extent,
            layers: self.layer_count,
            row_pitch: sub.row_pitch,
            slice_pitch: sub.depth_pitch,
            layer_pitch: sub.array_pitch,
        })
    }
}

/// The storage image a descriptor names, for a dispatch: the image (whose `storage` serves
/// the library's `read`/`write` for id `id`, offsets relative to the image's start) and the
/// library's view of it. None when the descriptor is not a storage image, its view or image
/// was destroyed, the image has no memory bound, or the view selects several levels (which
/// VUID-VkWriteDescriptorSet-descriptorType-00336 forbids).
pub fn storage_image_binding(descriptor: &Descriptor, id: u64) -> Option<(Arc<Image>, ImageBinding)> {
    let view = descriptor.storage_image()?;
    if !view.image.storage.is_bound() || view.level_count != 1 {
        return None;
    }
    Some((view.image.clone(), view.shader_binding(id)?))
}

//! Images and image views: the storage-image formats Arbor runs (and nothing else), the
//! checks of image and view creation, and [`storage_image_binding`], which turns a bound
//! storage-image descriptor into what the shader library reads and writes. Texel storage and
//! range checks are `crate::memory::image`'s; the transfer commands are in `image_copy`.
use std::sync::Arc;

use ash::vk;

use crate::memory::image::Image as Storage;
use crate::memory::Buffer;
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

/// One `VkBufferView`: a range of a buffer read and written as texels of `format` (uniform
/// and storage texel buffers). The formats are the storage-image ones.
pub struct BufferView {
    pub buffer: Arc<Buffer>,
    pub info: FormatInfo,
    pub offset: u64,
    /// Bytes of the view (VK_WHOLE_SIZE resolved, rounded down to whole texels).
    pub range: u64,
}

/// Device limits a buffer view must respect.
#[derive(Clone, Copy, Debug)]
pub struct TexelBufferLimits {
    pub min_offset_alignment: u64,
    pub max_elements: u64,
}

impl BufferView {
    /// Check and create a view (vkCreateBufferView). `range` may be VK_WHOLE_SIZE.
    pub fn new(buffer: Arc<Buffer>, format: vk::Format, offset: u64, range: u64, limits: &TexelBufferLimits) -> Result<BufferView, CreateError> {
        let info = *format_info(format).ok_or_else(|| invalid("VUID-VkBufferViewCreateInfo-format-08778", format!("format {format:?} does not support texel-buffer access")))?;
        let texel = info.texel_size as u64;
        if !buffer.usage.intersects(vk::BufferUsageFlags::UNIFORM_TEXEL_BUFFER | vk::BufferUsageFlags::STORAGE_TEXEL_BUFFER) {
            return Err(invalid("VUID-VkBufferViewCreateInfo-buffer-00932", "the buffer has neither UNIFORM_TEXEL_BUFFER nor STORAGE_TEXEL_BUFFER usage"));
        }
        if buffer.memory().is_none() {
            return Err(invalid("VUID-VkBufferViewCreateInfo-buffer-00935", "the buffer has no memory bound"));
        }
        if offset >= buffer.size {
            return Err(invalid("VUID-VkBufferViewCreateInfo-offset-00925", format!("offset {offset} is not less than the buffer's size {}", buffer.size)));
        }
        if !offset.is_multiple_of(limits.min_offset_alignment) {
            return Err(invalid("VUID-VkBufferViewCreateInfo-offset-02749", format!("offset {offset} is not a multiple of minTexelBufferOffsetAlignment {}", limits.min_offset_alignment)));
        }
        let bytes = if range == vk::WHOLE_SIZE {
            (buffer.size - offset) / texel * texel
        } else {
            if range == 0 {
                return Err(invalid("VUID-VkBufferViewCreateInfo-range-00928", "range is 0"));
            }
            if !range.is_multiple_of(texel) {
                return Err(invalid("VUID-VkBufferViewCreateInfo-range-00929", format!("range {range} is not a multiple of the {texel}-byte texel")));
            }
            if offset.checked_add(range).is_none_or(|end| end > buffer.size) {
                return Err(invalid("VUID-VkBufferViewCreateInfo-offset-00931", format!("offset {offset} + range {range} exceeds the buffer's size {}", buffer.size)));
            }
            range
        };
        if bytes / texel > limits.max_elements {
            let vuid = if range == vk::WHOLE_SIZE { "VUID-VkBufferViewCreateInfo-range-04059" } else { "VUID-VkBufferViewCreateInfo-range-00930" };
            return Err(invalid(vuid, format!("{} texels exceed maxTexelBufferElements {}", bytes / texel, limits.max_elements)));
        }
        Ok(BufferView { buffer, info, offset, range: bytes })
    }

    /// What a shader sees of the view: a one-row image of `range / texel` texels in the memory
    /// the caller names `id` (the buffer), starting at the view's offset.
    pub fn shader_binding(&self, id: u64) -> ImageBinding {
        let n = (self.range / self.info.texel_size as u64) as u32;
        ImageBinding::packed(id, self.offset, self.info.shader, [n, 1, 1], 1)
    }
}

/// The texel buffer a descriptor names, for a dispatch: its buffer (serving `read`/`write` for
/// id `id`, offsets relative to the buffer's start) and the library's view. None when the
/// descriptor is no texel buffer or its view or buffer was destroyed.
pub fn texel_buffer_binding(descriptor: &Descriptor, id: u64) -> Option<(Arc<Buffer>, ImageBinding)> {
    let view = descriptor.texel_buffer()?;
    Some((view.buffer.clone(), view.shader_binding(id)))
}

#[cfg(test)]
mod tests {
    //! The path a compute dispatch takes to a storage image: descriptor → `storage_image_binding`
    //! → a `shader::Memory` that serves texels from the image's storage → the library's
    //! executor writing through it. Checked against the subresource layout, not the executor.
    use super::*;
    use crate::memory::AddressSpace;
    use crate::runtime::descriptor::storage_image_descriptor;
    use crate::shader::{dispatch, Memory, Module, Pipeline, Region, Watchdog};

    struct ImageMemory {
        image: Arc<Image>,
        binding: ImageBinding,
    }

    impl Memory for ImageMemory {
        fn binding(&self, _: u32, _: u32) -> Option<Region> {
            None
        }
        fn address(&self, _: u64, _: u64) -> Option<Region> {
            None
        }
        fn read(&self, _: u64, offset: u64, out: &mut [u8]) -> bool {
            self.image.storage.read(offset, out).is_ok()
        }
        fn write(&self, _: u64, offset: u64, data: &[u8]) -> bool {
            self.image.storage.write(offset, data).is_ok()
        }
        fn atomic(&self, _: u64, _: u64, _: usize, _: &dyn Fn(u64) -> u64) -> Option<u64> {
            None
        }
        fn image(&self, set: u32, binding: u32) -> Option<ImageBinding> {
            ((set, binding) == (0, 0)).then_some(self.binding)
        }
    }

    fn compile(src: &str) -> Vec<u32> {
        let dir = std::env::temp_dir().join(format!("arbor-runtime-image-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (glsl, spv) = (dir.join("w.comp"), dir.join("w.spv"));
        std::fs::write(&glsl, src).unwrap();
        let out = std::process::Command::new("glslangValidator").args(["-V", "--target-env", "vulkan1.2", "-o"]).arg(&spv).arg(&glsl).output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
        std::fs::read(&spv).unwrap().chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect()
    }

    #[test]
    fn a_storage_image_descriptor_serves_a_dispatch() {
        let desc = ImageDesc {
            flags: vk::ImageCreateFlags::empty(),
            image_type: vk::ImageType::TYPE_2D,
            format: vk::Format::R32_UINT,
            extent: [4, 4, 1],
            mip_levels: 2,
            array_layers: 3,
            samples: vk::SampleCountFlags::TYPE_1,
            tiling: vk::ImageTiling::OPTIMAL,
            usage: SUPPORTED_USAGE,
            initial_layout: vk::ImageLayout::UNDEFINED,
        };
        let image = Arc::new(Image::new(&desc).unwrap());
        let space = AddressSpace::new(1 << 24);
        let memory = space.allocate(image.storage.requirements().0, false, None).unwrap();
        image.storage.bind(memory, 0).unwrap();
        // Level 1 (2x2), layers 1 and 2.
        let range = vk::ImageSubresourceRange { aspect_mask: vk::ImageAspectFlags::COLOR, base_mip_level: 1, level_count: 1, base_array_layer: 1, layer_count: 2 };
        let view = Arc::new(ImageView::new(image.clone(), vk::ImageViewType::TYPE_2D_ARRAY, desc.format, range).unwrap());
        let d = storage_image_descriptor(Some(view.clone()), 0x10, vk::ImageLayout::GENERAL).unwrap();
        let (img, binding) = storage_image_binding(&d, 7).unwrap();
        assert_eq!((binding.buffer, binding.extent, binding.layers), (7, [2, 2, 1], 2));
        let words = compile(
            "#version 450\nlayout(local_size_x = 1) in;\nlayout(set = 0, binding = 0, r32ui) uniform writeonly uimage2DArray img;\n\
             void main() { uvec3 g = gl_GlobalInvocationID; imageStore(img, ivec3(g), uvec4(1 + g.x + 10 * g.y + 100 * g.z)); }\n",
        );
        let p = Pipeline::compute(&Module::parse(&words).unwrap(), "main", &[]).unwrap();
        let mem = ImageMemory { image: img, binding };
        let report = dispatch(&p, &mem, &[], [2, 2, 2], [0; 3], &Watchdog::default());
        assert!(report.is_clean(), "{report:?}");
        let read = |level, layer| {
            let s = image.storage.subresource(level, layer).unwrap();
            let mut b = vec![0u8; s.size as usize];
            image.storage.read(s.offset, &mut b).unwrap();
            b.chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect::<Vec<_>>()
        };
        for layer in 0..3 {
            assert_eq!(read(0, layer), vec![0; 16], "level 0 is outside the view");
        }
        assert_eq!(read(1, 0), vec![0; 4], "layer 0 is outside the view");
        assert_eq!(read(1, 1), vec![1, 2, 11, 12]);
        assert_eq!(read(1, 2), vec![101, 102, 111, 112]);
        // A destroyed view leaves nothing to bind.
        drop(view);
        assert!(storage_image_binding(&d, 7).is_none());
    }
}

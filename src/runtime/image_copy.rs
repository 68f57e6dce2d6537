//! Image transfer commands: vkCmdClearColorImage, vkCmdCopyBufferToImage,
//! vkCmdCopyImageToBuffer and vkCmdCopyImage (and their `2` forms). Recording checks what it
//! can see and records an [`Exec`] command that owns its regions and `Arc`s of the images and
//! buffers; execution moves rows through `crate::memory`'s checked reads and writes, in queue
//! order with the other commands. Layouts are accepted and ignored: storage is linear.
use std::sync::Arc;

use ash::vk;

use super::command::{CommandBuffer, Exec, ExecContext, ExecError};
use super::image::Image;
use crate::memory::Buffer;

/// One image subresource layer range and box of a copy.
#[derive(Clone, Copy, Debug)]
pub struct ImageRegion {
    pub level: u32,
    pub base_layer: u32,
    pub layer_count: u32,
    pub offset: [i32; 3],
    pub extent: [u32; 3],
}

/// A buffer ↔ image copy region (VkBufferImageCopy, lowered).
#[derive(Clone, Copy, Debug)]
pub struct BufferImageRegion {
    pub buffer_offset: u64,
    /// Texels per buffer row and rows per buffer image; 0 means tightly packed.
    pub row_length: u32,
    pub image_height: u32,
    pub image: ImageRegion,
}

/// An image → image copy region (VkImageCopy, lowered).
#[derive(Clone, Copy, Debug)]
pub struct ImageCopyRegion {
    pub src: ImageRegion,
    pub dst_level: u32,
    pub dst_base_layer: u32,
    pub dst_layer_count: u32,
    pub dst_offset: [i32; 3],
}

/// The VUIDs of one command name (the `2` forms name their structs).
pub struct Vuids {
    pub command: &'static str,
    pub usage: &'static str,
    pub buffer_usage: &'static str,
    pub subresource: &'static str,
    pub bounds: &'static str,
    pub buffer_range: &'static str,
    /// The image (for vkCmdCopyImage: the source; `unbound_dst` the destination) has no memory.
    pub unbound: &'static str,
    pub unbound_dst: &'static str,
}

/// Checks that `r` lies inside `image`; the message of the first failure.
fn region_inside(image: &Image, r: &ImageRegion) -> Result<(), (bool, String)> {
    let s = &image.storage;
    if r.level >= s.levels || r.layer_count == 0 || r.base_layer as u64 + r.layer_count as u64 > s.layers as u64 {
        return Err((true, format!("level {} layers {}+{} outside the image ({} levels, {} layers)", r.level, r.base_layer, r.layer_count, s.levels, s.layers)));
    }
    let e = s.level_extent(r.level);
    for k in 0..3 {
        let end = r.offset[k] as i64 + r.extent[k] as i64;
        if r.offset[k] < 0 || r.extent[k] == 0 || end > e[k] as i64 {
            return Err((false, format!("offset {:?} extent {:?} outside level {} of extent {e:?}", r.offset, r.extent, r.level)));
        }
    }
    if image.image_type == vk::ImageType::TYPE_3D && r.layer_count != 1 {
        return Err((true, "a 3D image has one layer".into()));
    }
    Ok(())
}

/// Bytes of buffer memory a buffer ↔ image region touches, from its buffer offset.
fn buffer_span(texel: u32, r: &BufferImageRegion) -> u64 {
    let (row, height) = pitches(r);
    let e = r.image.extent;
    let slices = e[2] as u64 * r.image.layer_count as u64;
    ((slices - 1) * height as u64 * row as u64 + (e[1] as u64 - 1) * row as u64 + e[0] as u64) * texel as u64
}

fn pitches(r: &BufferImageRegion) -> (u32, u32) {
    let row = if r.row_length == 0 { r.image.extent[0] } else { r.row_length };
    let height = if r.image_height == 0 { r.image.extent[1] } else { r.image_height };
    (row, height)
}

/// Byte offset of (x0, y, z) of layer `layer` of the region in the image.
fn image_row(image: &Image, r: &ImageRegion, layer: u32, y: u32, z: u32) -> u64 {
    let sub = image.storage.subresource(r.level, r.base_layer + layer).expect("region checked at record time");
    let x = r.offset[0] as u64 * image.info.texel_size as u64;
    sub.offset + (r.offset[2] as u64 + z as u64) * sub.depth_pitch + (r.offset[1] as u64 + y as u64) * sub.row_pitch + x
}

/// Calls `f(layer, y, z)` for every row of a region.
fn rows(r: &ImageRegion, mut f: impl FnMut(u32, u32, u32) -> Result<(), ExecError>) -> Result<(), ExecError> {
    for layer in 0..r.layer_count {
        for z in 0..r.extent[2] {
            for y in 0..r.extent[1] {
                f(layer, y, z)?;
            }
        }
    }
    Ok(())
}

struct BufferImageCopy {
    name: &'static str,
    buffer: Arc<Buffer>,
    image: Arc<Image>,
    to_image: bool,
    regions: Vec<BufferImageRegion>,
}

impl Exec for BufferImageCopy {
    fn name(&self) -> &'static str {
        self.name
    }

    fn execute(&self, _ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        let texel = self.image.info.texel_size as u64;
        for r in &self.regions {
            let (row_len, height) = pitches(r);
            let mut row = vec![0u8; (r.image.extent[0] as u64 * texel) as usize];
            rows(&r.image, |layer, y, z| {
                let slice = layer as u64 * r.image.extent[2] as u64 + z as u64;
                let b = r.buffer_offset + ((slice * height as u64 + y as u64) * row_len as u64) * texel;
                let i = image_row(&self.image, &r.image, layer, y, z);
                if self.to_image {
                    self.buffer.read(b, &mut row)?;
                    self.image.storage.write(i, &row)?;
                } else {
                    self.image.storage.read(i, &mut row)?;
                    self.buffer.write(b, &row)?;
                }
                Ok(())
            })?;
        }
        Ok(())
    }
}

/// Record vkCmdCopyBufferToImage(2) (`to_image`) or vkCmdCopyImageToBuffer(2).
pub fn cmd_copy_buffer_image(cb: &CommandBuffer, v: &Vuids, buffer: Arc<Buffer>, image: Arc<Image>, to_image: bool, regions: Vec<BufferImageRegion>) {
    let (cmd, need, buffer_need) = if to_image {
        (v.command, vk::ImageUsageFlags::TRANSFER_DST, vk::BufferUsageFlags::TRANSFER_SRC)
    } else {
        (v.command, vk::ImageUsageFlags::TRANSFER_SRC, vk::BufferUsageFlags::TRANSFER_DST)
    };
    if !image.usage.contains(need) {
        return cb.violation(v.usage, cmd, &format!("the image lacks {need:?} usage"));
    }
    if !image.storage.is_bound() {
        return cb.violation(v.unbound, cmd, "the image is not bound to memory");
    }
    if !buffer.usage.contains(buffer_need) {
        return cb.violation(v.buffer_usage, cmd, &format!("the buffer lacks {buffer_need:?} usage"));
    }
    for (i, r) in regions.iter().enumerate() {
        if let Err((sub, m)) = region_inside(&image, &r.image) {
            return cb.violation(if sub { v.subresource } else { v.bounds }, cmd, &format!("pRegions[{i}]: {m}"));
        }
        let (row, height) = pitches(r);
        if row < r.image.extent[0] || height < r.image.extent[1] {
            return cb.violation(v.buffer_range, cmd, &format!("pRegions[{i}]: bufferRowLength/bufferImageHeight smaller than the extent"));
        }
        let span = buffer_span(image.info.texel_size, r);
        if r.buffer_offset.checked_add(span).is_none_or(|end| end > buffer.size) {
            return cb.violation(v.buffer_range, cmd, &format!("pRegions[{i}] needs {span} bytes from bufferOffset {} of a {}-byte buffer", r.buffer_offset, buffer.size));
        }
    }
    cb.record_custom(Box::new(BufferImageCopy { name: v.command, buffer, image, to_image, regions }));
}

struct ImageCopy {
    name: &'static str,
    src: Arc<Image>,
    dst: Arc<Image>,
    regions: Vec<ImageCopyRegion>,
}

impl Exec for ImageCopy {
    fn name(&self) -> &'static str {
        self.name
    }

    fn execute(&self, _ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        for r in &self.regions {
            let d = dst_region(r);
            let mut row = vec![0u8; (r.src.extent[0] as u64 * self.src.info.texel_size as u64) as usize];
            rows(&r.src, |layer, y, z| {
                self.src.storage.read(image_row(&self.src, &r.src, layer, y, z), &mut row)?;
                self.dst.storage.write(image_row(&self.dst, &d, layer, y, z), &row)?;
                Ok(())
            })?;
        }
        Ok(())
    }
}

fn dst_region(r: &ImageCopyRegion) -> ImageRegion {
    ImageRegion { level: r.dst_level, base_layer: r.dst_base_layer, layer_count: r.dst_layer_count, offset: r.dst_offset, extent: r.src.extent }
}

/// Record vkCmdCopyImage(2). `v.usage` is the source's usage VUID, `v.buffer_usage` the
/// destination's (an image here).
pub fn cmd_copy_image(cb: &CommandBuffer, v: &Vuids, src: Arc<Image>, dst: Arc<Image>, regions: Vec<ImageCopyRegion>) {
    let cmd = v.command;
    if !src.usage.contains(vk::ImageUsageFlags::TRANSFER_SRC) {
        return cb.violation(v.usage, cmd, "srcImage lacks TRANSFER_SRC usage");
    }
    if !dst.usage.contains(vk::ImageUsageFlags::TRANSFER_DST) {
        return cb.violation(v.buffer_usage, cmd, "dstImage lacks TRANSFER_DST usage");
    }
    if !src.storage.is_bound() {
        return cb.violation(v.unbound, cmd, "srcImage is not bound to memory");
    }
    if !dst.storage.is_bound() {
        return cb.violation(v.unbound_dst, cmd, "dstImage is not bound to memory");
    }
    if src.info.texel_size != dst.info.texel_size {
        return cb.violation(v.buffer_range, cmd, &format!("formats {:?} and {:?} are not size-compatible", src.format, dst.format));
    }
    for (i, r) in regions.iter().enumerate() {
        for (which, image, region) in [("src", &src, r.src), ("dst", &dst, dst_region(r))] {
            if let Err((sub, m)) = region_inside(image, &region) {
                return cb.violation(if sub { v.subresource } else { v.bounds }, cmd, &format!("pRegions[{i}] {which}: {m}"));
            }
        }
        if r.src.layer_count != r.dst_layer_count {
            return cb.violation(v.subresource, cmd, &format!("pRegions[{i}]: source and destination layer counts differ"));
        }
    }
    cb.record_custom(Box::new(ImageCopy { name: v.command, src, dst, regions }));
}

struct ClearColor {
    image: Arc<Image>,
    texel: [u8; 16],
    ranges: Vec<ImageRegion>,
}

impl Exec for ClearColor {
    fn name(&self) -> &'static str {
        "vkCmdClearColorImage"
    }

    fn execute(&self, _ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        let t = self.image.info.texel_size as usize;
        for r in &self.ranges {
            let row: Vec<u8> = self.texel[..t].iter().copied().cycle().take(t * r.extent[0] as usize).collect();
            rows(r, |layer, y, z| Ok(self.image.storage.write(image_row(&self.image, r, layer, y, z), &row)?))?;
        }
        Ok(())
    }
}

/// The bytes of a clear value in the image's format. `color` is VkClearColorValue's 16
/// bytes as words: the `float32` member for float and UNORM formats, `int32`/`uint32` (the
/// same bits) for integer ones.
fn clear_texel(image: &Image, color: [u32; 4]) -> [u8; 16] {
    use crate::shader::ImageFormat as F;
    let words = match image.info.shader {
        F::Rgba8Unorm => {
            let b = color.map(|w| {
                let c = f32::from_bits(w);
                (if c.is_nan() { 0.0 } else { c.clamp(0.0, 1.0) } * 255.0).round() as u8
            });
            [u32::from_le_bytes(b), 0, 0, 0]
        }
        _ => color,
    };
    let mut out = [0u8; 16];
    for (k, w) in words.iter().enumerate() {
        out[4 * k..4 * k + 4].copy_from_slice(&w.to_le_bytes());
    }
    out
}

/// Record vkCmdClearColorImage (VK_REMAINING_* counts resolved here); `color` as for
/// [`clear_texel`].
pub fn cmd_clear_color_image(cb: &CommandBuffer, image: Arc<Image>, color: [u32; 4], ranges: &[vk::ImageSubresourceRange]) {
    const CMD: &str = "vkCmdClearColorImage";
    if !image.usage.contains(vk::ImageUsageFlags::TRANSFER_DST) {
        return cb.violation("VUID-vkCmdClearColorImage-image-00002", CMD, "image lacks TRANSFER_DST usage");
    }
    if !image.storage.is_bound() {
        return cb.violation("VUID-vkCmdClearColorImage-image-00003", CMD, "image is not bound to memory");
    }
    let s = &image.storage;
    let mut out = Vec::new();
    for (i, r) in ranges.iter().enumerate() {
        if r.aspect_mask != vk::ImageAspectFlags::COLOR {
            return cb.violation("VUID-vkCmdClearColorImage-aspectMask-02498", CMD, &format!("pRanges[{i}].aspectMask must be COLOR"));
        }
        let levels = if r.level_count == vk::REMAINING_MIP_LEVELS { s.levels.saturating_sub(r.base_mip_level) } else { r.level_count };
        let layers = if r.layer_count == vk::REMAINING_ARRAY_LAYERS { s.layers.saturating_sub(r.base_array_layer) } else { r.layer_count };
        if r.base_mip_level >= s.levels || levels == 0 || r.base_mip_level as u64 + levels as u64 > s.levels as u64 {
            return cb.violation("VUID-vkCmdClearColorImage-baseMipLevel-01470", CMD, &format!("pRanges[{i}] levels outside the image's {}", s.levels));
        }
        if r.base_array_layer >= s.layers || layers == 0 || r.base_array_layer as u64 + layers as u64 > s.layers as u64 {
            return cb.violation("VUID-vkCmdClearColorImage-baseArrayLayer-01472", CMD, &format!("pRanges[{i}] layers outside the image's {}", s.layers));
        }
        for level in r.base_mip_level..r.base_mip_level + levels {
            let extent = s.level_extent(level);
            out.push(ImageRegion { level, base_layer: r.base_array_layer, layer_count: layers, offset: [0; 3], extent });
        }
    }
    let texel = clear_texel(&image, color);
    cb.record_custom(Box::new(ClearColor { image, texel, ranges: out }));
}

//! The image transfer commands: vkCmdClearColorImage, vkCmdCopyBufferToImage(2),
//! vkCmdCopyImageToBuffer(2), vkCmdCopyImage(2). Raw regions → `runtime::image_copy`'s
//! lowered regions → one call that checks and records. Image layouts are accepted and
//! ignored (storage is linear); barriers with image layout transitions are in `command`.
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::command::command_buffer_from;
use super::handle::get;
use super::image::image_from;
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::memory::Buffer;
use crate::runtime::command::CommandBuffer;
use crate::runtime::image::Image;
use crate::runtime::image_copy::{self, BufferImageRegion, ImageCopyRegion, ImageRegion, Vuids};

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCmdClearColorImage => cmd_clear_color_image),
        imp!(PFN_vkCmdCopyBufferToImage => cmd_copy_buffer_to_image),
        imp!(PFN_vkCmdCopyBufferToImage2 => cmd_copy_buffer_to_image2),
        imp!(PFN_vkCmdCopyImageToBuffer => cmd_copy_image_to_buffer),
        imp!(PFN_vkCmdCopyImageToBuffer2 => cmd_copy_image_to_buffer2),
        imp!(PFN_vkCmdCopyImage => cmd_copy_image),
        imp!(PFN_vkCmdCopyImage2 => cmd_copy_image2),
    ]
}

const TO_IMAGE: Vuids = Vuids {
    command: "vkCmdCopyBufferToImage",
    usage: "VUID-vkCmdCopyBufferToImage-dstImage-00177",
    buffer_usage: "VUID-vkCmdCopyBufferToImage-srcBuffer-00174",
    subresource: "VUID-vkCmdCopyBufferToImage-imageSubresource-07967",
    bounds: "VUID-vkCmdCopyBufferToImage-pRegions-06218",
    buffer_range: "VUID-vkCmdCopyBufferToImage-pRegions-00171",
    unbound: "VUID-vkCmdCopyBufferToImage-dstImage-07966",
    unbound_dst: "VUID-vkCmdCopyBufferToImage-dstImage-07966",
};
const TO_IMAGE2: Vuids = Vuids {
    command: "vkCmdCopyBufferToImage2",
    usage: "VUID-VkCopyBufferToImageInfo2-dstImage-00177",
    buffer_usage: "VUID-VkCopyBufferToImageInfo2-srcBuffer-00174",
    subresource: "VUID-VkCopyBufferToImageInfo2-imageSubresource-07967",
    bounds: "VUID-VkCopyBufferToImageInfo2-pRegions-06223",
    buffer_range: "VUID-VkCopyBufferToImageInfo2-pRegions-00171",
    unbound: "VUID-VkCopyBufferToImageInfo2-dstImage-07966",
    unbound_dst: "VUID-VkCopyBufferToImageInfo2-dstImage-07966",
};
const TO_BUFFER: Vuids = Vuids {
    command: "vkCmdCopyImageToBuffer",
    usage: "VUID-vkCmdCopyImageToBuffer-srcImage-00186",
    buffer_usage: "VUID-vkCmdCopyImageToBuffer-dstBuffer-00191",
    subresource: "VUID-vkCmdCopyImageToBuffer-imageSubresource-07967",
    bounds: "VUID-vkCmdCopyImageToBuffer-pRegions-06221",
    buffer_range: "VUID-vkCmdCopyImageToBuffer-pRegions-00183",
    unbound: "VUID-vkCmdCopyImageToBuffer-srcImage-07966",
    unbound_dst: "VUID-vkCmdCopyImageToBuffer-srcImage-07966",
};
const TO_BUFFER2: Vuids = Vuids {
    command: "vkCmdCopyImageToBuffer2",
    usage: "VUID-VkCopyImageToBufferInfo2-srcImage-00186",
    buffer_usage: "VUID-VkCopyImageToBufferInfo2-dstBuffer-00191",
    subresource: "VUID-VkCopyImageToBufferInfo2-imageSubresource-07967",
    bounds: "VUID-VkCopyImageToBufferInfo2-pRegions-06224",
    buffer_range: "VUID-VkCopyImageToBufferInfo2-pRegions-00183",
    unbound: "VUID-VkCopyImageToBufferInfo2-srcImage-07966",
    unbound_dst: "VUID-VkCopyImageToBufferInfo2-srcImage-07966",
};
const COPY_IMAGE: Vuids = Vuids {
    command: "vkCmdCopyImage",
    usage: "VUID-vkCmdCopyImage-srcImage-00126",
    buffer_usage: "VUID-vkCmdCopyImage-dstImage-00131",
    subresource: "VUID-vkCmdCopyImage-srcSubresource-07967",
    bounds: "VUID-vkCmdCopyImage-srcOffset-00144",
    buffer_range: "VUID-vkCmdCopyImage-srcImage-01548",
    unbound: "VUID-vkCmdCopyImage-srcImage-07966",
    unbound_dst: "VUID-vkCmdCopyImage-dstImage-07966",
};
const COPY_IMAGE2: Vuids = Vuids {
    command: "vkCmdCopyImage2",
    usage: "VUID-VkCopyImageInfo2-srcImage-00126",
    buffer_usage: "VUID-VkCopyImageInfo2-dstImage-00131",
    subresource: "VUID-VkCopyImageInfo2-srcSubresource-07967",
    bounds: "VUID-VkCopyImageInfo2-srcOffset-00144",
    buffer_range: "VUID-VkCopyImageInfo2-srcImage-01548",
    unbound: "VUID-VkCopyImageInfo2-srcImage-07966",
    unbound_dst: "VUID-VkCopyImageInfo2-dstImage-07966",
};

fn region(s: vk::ImageSubresourceLayers, o: vk::Offset3D, e: vk::Extent3D) -> ImageRegion {
    ImageRegion { level: s.mip_level, base_layer: s.base_array_layer, layer_count: s.layer_count, offset: [o.x, o.y, o.z], extent: [e.width, e.height, e.depth] }
}

fn buffer_image(r: &vk::BufferImageCopy) -> BufferImageRegion {
    BufferImageRegion {
        buffer_offset: r.buffer_offset,
        row_length: r.buffer_row_length,
        image_height: r.buffer_image_height,
        image: region(r.image_subresource, r.image_offset, r.image_extent),
    }
}

fn buffer_image2(r: &vk::BufferImageCopy2) -> BufferImageRegion {
    BufferImageRegion {
        buffer_offset: r.buffer_offset,
        row_length: r.buffer_row_length,
        image_height: r.buffer_image_height,
        image: region(r.image_subresource, r.image_offset, r.image_extent),
    }
}

fn image_copy(s: vk::ImageSubresourceLayers, so: vk::Offset3D, d: vk::ImageSubresourceLayers, d_off: vk::Offset3D, e: vk::Extent3D) -> ImageCopyRegion {
    ImageCopyRegion {
        src: region(s, so, e),
        dst_level: d.mip_level,
        dst_base_layer: d.base_array_layer,
        dst_layer_count: d.layer_count,
        dst_offset: [d_off.x, d_off.y, d_off.z],
    }
}

/// The command buffer, image and buffer of a copy, or None after reporting a bad handle.
fn objects(cb: vk::CommandBuffer, image: vk::Image, buffer: vk::Buffer, v: &Vuids) -> Option<(Arc<CommandBuffer>, Arc<Image>, Arc<Buffer>)> {
    let c = command_buffer_from(cb)?;
    match (image_from(image), get::<Buffer>(buffer.as_raw())) {
        (Some(i), Some(b)) => Some((c, i, b)),
        _ => {
            c.violation(&format!("VUID-{}-commandBuffer-parameter", v.command), v.command, "invalid image or buffer handle");
            None
        }
    }
}

unsafe extern "system" fn cmd_copy_buffer_to_image(
    cb: vk::CommandBuffer,
    src: vk::Buffer,
    dst: vk::Image,
    _layout: vk::ImageLayout,
    count: u32,
    p_regions: *const vk::BufferImageCopy,
) {
    guard(TO_IMAGE.command, (), || {
        let Some((c, i, b)) = objects(cb, dst, src, &TO_IMAGE) else { return };
        // SAFETY: valid array of count regions per the spec.
        let regions = unsafe { util::slice(p_regions, count) }.iter().map(buffer_image).collect();
        image_copy::cmd_copy_buffer_image(&c, &TO_IMAGE, b, i, true, regions);
    })
}

unsafe extern "system" fn cmd_copy_buffer_to_image2(cb: vk::CommandBuffer, p_info: *const vk::CopyBufferToImageInfo2) {
    guard(TO_IMAGE2.command, (), || {
        if p_info.is_null() {
            return;
        }
        // SAFETY: valid info per the spec.
        let info = unsafe { &*p_info };
        let Some((c, i, b)) = objects(cb, info.dst_image, info.src_buffer, &TO_IMAGE2) else { return };
        // SAFETY: valid array of regionCount regions per the spec.
        let regions = unsafe { util::slice(info.p_regions, info.region_count) }.iter().map(buffer_image2).collect();
        image_copy::cmd_copy_buffer_image(&c, &TO_IMAGE2, b, i, true, regions);
    })
}

unsafe extern "system" fn cmd_copy_image_to_buffer(
    cb: vk::CommandBuffer,
    src: vk::Image,
    _layout: vk::ImageLayout,
    dst: vk::Buffer,
    count: u32,
    p_regions: *const vk::BufferImageCopy,
) {
    guard(TO_BUFFER.command, (), || {
        let Some((c, i, b)) = objects(cb, src, dst, &TO_BUFFER) else { return };
        // SAFETY: valid array of count regions per the spec.
        let regions = unsafe { util::slice(p_regions, count) }.iter().map(buffer_image).collect();
        image_copy::cmd_copy_buffer_image(&c, &TO_BUFFER, b, i, false, regions);
    })
}

unsafe extern "system" fn cmd_copy_image_to_buffer2(cb: vk::CommandBuffer, p_info: *const vk::CopyImageToBufferInfo2) {
    guard(TO_BUFFER2.command, (), || {
        if p_info.is_null() {
            return;
        }
        // SAFETY: valid info per the spec.
        let info = unsafe { &*p_info };
        let Some((c, i, b)) = objects(cb, info.src_image, info.dst_buffer, &TO_BUFFER2) else { return };
        // SAFETY: valid array of regionCount regions per the spec.
        let regions = unsafe { util::slice(info.p_regions, info.region_count) }.iter().map(buffer_image2).collect();
        image_copy::cmd_copy_buffer_image(&c, &TO_BUFFER2, b, i, false, regions);
    })
}

/// Both images of a copy, or None after reporting a bad handle.
fn images(c: &CommandBuffer, src: vk::Image, dst: vk::Image, v: &Vuids) -> Option<(Arc<Image>, Arc<Image>)> {
    match (image_from(src), image_from(dst)) {
        (Some(s), Some(d)) => Some((s, d)),
        _ => {
            c.violation(&format!("VUID-{}-commandBuffer-parameter", v.command), v.command, "invalid image handle");
            None
        }
    }
}

unsafe extern "system" fn cmd_copy_image(
    cb: vk::CommandBuffer,
    src: vk::Image,
    _src_layout: vk::ImageLayout,
    dst: vk::Image,
    _dst_layout: vk::ImageLayout,
    count: u32,
    p_regions: *const vk::ImageCopy,
) {
    guard(COPY_IMAGE.command, (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        let Some((s, d)) = images(&c, src, dst, &COPY_IMAGE) else { return };
        // SAFETY: valid array of count regions per the spec.
        let regions = unsafe { util::slice(p_regions, count) }
            .iter()
            .map(|r| image_copy(r.src_subresource, r.src_offset, r.dst_subresource, r.dst_offset, r.extent))
            .collect();
        image_copy::cmd_copy_image(&c, &COPY_IMAGE, s, d, regions);
    })
}

unsafe extern "system" fn cmd_copy_image2(cb: vk::CommandBuffer, p_info: *const vk::CopyImageInfo2) {
    guard(COPY_IMAGE2.command, (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        if p_info.is_null() {
            return;
        }
        // SAFETY: valid info per the spec.
        let info = unsafe { &*p_info };
        let Some((s, d)) = images(&c, info.src_image, info.dst_image, &COPY_IMAGE2) else { return };
        // SAFETY: valid array of regionCount regions per the spec.
        let regions = unsafe { util::slice(info.p_regions, info.region_count) }
            .iter()
            .map(|r| image_copy(r.src_subresource, r.src_offset, r.dst_subresource, r.dst_offset, r.extent))
            .collect();
        image_copy::cmd_copy_image(&c, &COPY_IMAGE2, s, d, regions);
    })
}

unsafe extern "system" fn cmd_clear_color_image(
    cb: vk::CommandBuffer,
    image: vk::Image,
    _layout: vk::ImageLayout,
    p_color: *const vk::ClearColorValue,
    count: u32,
    p_ranges: *const vk::ImageSubresourceRange,
) {
    const CMD: &str = "vkCmdClearColorImage";
    guard(CMD, (), || {
        let Some(c) = command_buffer_from(cb) else { return };
        let Some(i) = image_from(image) else {
            return c.violation("VUID-vkCmdClearColorImage-image-parameter", CMD, "image is not a live VkImage");
        };
        if p_color.is_null() {
            return c.violation("VUID-vkCmdClearColorImage-pColor-parameter", CMD, "pColor is null");
        }
        // SAFETY: valid pointer per the spec (checked non-null); every member of the union is
        // 16 plain bytes, so reading `uint32` is reading those bytes.
        let words = unsafe { (*p_color).uint32 };
        // SAFETY: valid array of count ranges per the spec.
        let ranges = unsafe { util::slice(p_ranges, count) };
        image_copy::cmd_clear_color_image(&c, i, words, ranges);
    })
}

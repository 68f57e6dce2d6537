//! Images and image views: creation (checked by `runtime::image`), memory requirements,
//! binding, the linear subresource layout, and destruction. Texel storage is
//! `crate::memory::image`'s; the image transfer commands are in `image_cmd`.
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::device::device_from;
use super::handle::{get, register, unregister};
use super::memory::{buffer_from, memory_from};
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::diag;
use crate::memory::BindError;
use crate::runtime::image::{BufferView, CreateError, Image, ImageDesc, ImageView, TexelBufferLimits};

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCreateImage => create_image),
        imp!(PFN_vkDestroyImage => destroy_image),
        imp!(PFN_vkGetImageMemoryRequirements => get_image_memory_requirements),
        imp!(PFN_vkGetImageMemoryRequirements2 => get_image_memory_requirements2),
        imp!(PFN_vkGetImageSparseMemoryRequirements => get_image_sparse_memory_requirements),
        imp!(PFN_vkGetImageSparseMemoryRequirements2 => get_image_sparse_memory_requirements2),
        imp!(PFN_vkBindImageMemory => bind_image_memory),
        imp!(PFN_vkBindImageMemory2 => bind_image_memory2),
        imp!(PFN_vkGetImageSubresourceLayout => get_image_subresource_layout),
        imp!(PFN_vkCreateImageView => create_image_view),
        imp!(PFN_vkDestroyImageView => destroy_image_view),
        imp!(PFN_vkCreateBufferView => create_buffer_view),
        imp!(PFN_vkDestroyBufferView => destroy_buffer_view),
    ]
}

fn invalid(vuid: &str, command: &str, message: &str) -> vk::Result {
    diag::vuid(vuid, command, message);
    vk::Result::ERROR_VALIDATION_FAILED_EXT
}

fn unknown_device(command: &str) -> vk::Result {
    report_unknown_device(command);
    vk::Result::ERROR_VALIDATION_FAILED_EXT
}

fn report_unknown_device(command: &str) {
    diag::vuid(&format!("VUID-{command}-device-parameter"), command, "device is not a valid VkDevice");
}

pub fn image_from(h: vk::Image) -> Option<Arc<Image>> {
    get::<Image>(h.as_raw())
}

fn create_error(command: &str, e: CreateError) -> vk::Result {
    match e {
        CreateError::Invalid { vuid, message } => invalid(vuid, command, &message),
        // Creating an image vkGetPhysicalDeviceImageFormatProperties does not support is
        // invalid usage; the format query is where VK_ERROR_FORMAT_NOT_SUPPORTED belongs.
        CreateError::Unsupported(what) => {
            invalid("VUID-VkImageCreateInfo-imageCreateMaxMipLevels-02251", command, &format!("{what} is not supported for images"))
        }
    }
}

unsafe extern "system" fn create_image(
    device: vk::Device,
    p_info: *const vk::ImageCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_image: *mut vk::Image,
) -> vk::Result {
    const CMD: &str = "vkCreateImage";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return unknown_device(CMD);
        }
        if p_info.is_null() || p_image.is_null() {
            return invalid("VUID-vkCreateImage-pCreateInfo-parameter", CMD, "null pointer argument");
        }
        // SAFETY: valid create info and output pointer per the spec (checked non-null).
        let i = unsafe {
            *p_image = vk::Image::null();
            &*p_info
        };
        let d = ImageDesc {
            flags: i.flags,
            image_type: i.image_type,
            format: i.format,
            extent: [i.extent.width, i.extent.height, i.extent.depth],
            mip_levels: i.mip_levels,
            array_layers: i.array_layers,
            samples: i.samples,
            tiling: i.tiling,
            usage: i.usage,
            initial_layout: i.initial_layout,
        };
        match Image::new(&d) {
            Ok(img) => {
                // SAFETY: checked non-null.
                unsafe { *p_image = vk::Image::from_raw(register(Arc::new(img))) };
                vk::Result::SUCCESS
            }
            Err(e) => create_error(CMD, e),
        }
    })
}

unsafe extern "system" fn destroy_image(device: vk::Device, image: vk::Image, _p_allocator: *const vk::AllocationCallbacks) {
    const CMD: &str = "vkDestroyImage";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_unknown_device(CMD);
            return;
        }
        if image != vk::Image::null() && unregister::<Image>(image.as_raw()).is_none() {
            diag::vuid("VUID-vkDestroyImage-image-parameter", CMD, "image is not a live VkImage");
        }
    })
}

fn requirements(image: &Image) -> vk::MemoryRequirements {
    let (size, alignment) = image.storage.requirements();
    // Like ordinary buffers, images take every type but the sparse one (memfd-backed, for sparse buffers).
    let all = (1 << super::memory::MEMORY_TYPE_COUNT) - 1;
    vk::MemoryRequirements { size, alignment, memory_type_bits: all & !(1 << super::memory::SPARSE_MEMORY_TYPE) }
}

unsafe extern "system" fn get_image_memory_requirements(device: vk::Device, image: vk::Image, p_req: *mut vk::MemoryRequirements) {
    const CMD: &str = "vkGetImageMemoryRequirements";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_unknown_device(CMD);
            return;
        }
        let Some(i) = image_from(image) else {
            diag::vuid("VUID-vkGetImageMemoryRequirements-image-parameter", CMD, "image is not a live VkImage");
            return;
        };
        // SAFETY: valid output pointer per the spec.
        unsafe { util::out(p_req, requirements(&i)) };
    })
}

unsafe extern "system" fn get_image_memory_requirements2(
    device: vk::Device,
    p_info: *const vk::ImageMemoryRequirementsInfo2,
    p_req: *mut vk::MemoryRequirements2,
) {
    const CMD: &str = "vkGetImageMemoryRequirements2";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_unknown_device(CMD);
            return;
        }
        if p_info.is_null() || p_req.is_null() {
            diag::vuid("VUID-vkGetImageMemoryRequirements2-pInfo-parameter", CMD, "null pointer argument");
            return;
        }
        // SAFETY: valid info per the spec.
        let Some(i) = image_from(unsafe { (*p_info).image }) else {
            diag::vuid("VUID-VkImageMemoryRequirementsInfo2-image-parameter", CMD, "image is not a live VkImage");
            return;
        };
        // SAFETY: valid output struct and chain per the spec.
        unsafe { super::memory::write_requirements2(p_req, requirements(&i)) };
    })
}

unsafe extern "system" fn get_image_sparse_memory_requirements(
    _device: vk::Device,
    _image: vk::Image,
    p_count: *mut u32,
    _p: *mut vk::SparseImageMemoryRequirements,
) {
    // No sparse images: never any requirements.
    // SAFETY: valid pointer per the spec.
    unsafe { util::out(p_count, 0) };
}

unsafe extern "system" fn get_image_sparse_memory_requirements2(
    _device: vk::Device,
    _p_info: *const vk::ImageSparseMemoryRequirementsInfo2,
    p_count: *mut u32,
    _p: *mut vk::SparseImageMemoryRequirements2,
) {
    // SAFETY: valid pointer per the spec.
    unsafe { util::out(p_count, 0) };
}

/// Bind one image; `prefix` is the VUID prefix ("vkBindImageMemory" or "VkBindImageMemoryInfo").
fn bind_one(command: &str, prefix: &str, image: vk::Image, memory: vk::DeviceMemory, offset: u64) -> vk::Result {
    let Some(i) = image_from(image) else {
        return invalid(&format!("VUID-{prefix}-image-parameter"), command, "image is not a live VkImage");
    };
    let Some(m) = memory_from(memory) else {
        return invalid(&format!("VUID-{prefix}-memory-parameter"), command, "memory is not a live VkDeviceMemory");
    };
    if offset >= m.size {
        return invalid(&format!("VUID-{prefix}-memoryOffset-01046"), command, &format!("memoryOffset {offset} is not less than the memory size {}", m.size));
    }
    let (size, alignment) = i.storage.requirements();
    if !offset.is_multiple_of(alignment) {
        return invalid(&format!("VUID-{prefix}-memoryOffset-01048"), command, &format!("memoryOffset {offset} is not a multiple of {alignment}"));
    }
    if m.size - offset < size {
        return invalid(&format!("VUID-{prefix}-size-01049"), command, &format!("{} bytes after memoryOffset, the image requires {size}", m.size - offset));
    }
    match i.storage.bind(m, offset) {
        Ok(()) => vk::Result::SUCCESS,
        Err(BindError::AlreadyBound) => invalid(&format!("VUID-{prefix}-image-07460"), command, "the image is already bound to memory"),
        Err(BindError::Misaligned) => invalid(&format!("VUID-{prefix}-memoryOffset-01048"), command, "memoryOffset is misaligned"),
        Err(BindError::Access(e)) => invalid(&format!("VUID-{prefix}-size-01049"), command, &e.to_string()),
    }
}

unsafe extern "system" fn bind_image_memory(device: vk::Device, image: vk::Image, memory: vk::DeviceMemory, offset: vk::DeviceSize) -> vk::Result {
    const CMD: &str = "vkBindImageMemory";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return unknown_device(CMD);
        }
        bind_one(CMD, CMD, image, memory, offset)
    })
}

unsafe extern "system" fn bind_image_memory2(device: vk::Device, count: u32, p_infos: *const vk::BindImageMemoryInfo) -> vk::Result {
    const CMD: &str = "vkBindImageMemory2";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return unknown_device(CMD);
        }
        // SAFETY: valid array per the spec.
        let infos = unsafe { util::slice(p_infos, count) };
        infos.iter().fold(vk::Result::SUCCESS, |result, i| {
            let r = bind_one(CMD, "VkBindImageMemoryInfo", i.image, i.memory, i.memory_offset);
            if result == vk::Result::SUCCESS {
                r
            } else {
                result
            }
        })
    })
}

unsafe extern "system" fn get_image_subresource_layout(
    device: vk::Device,
    image: vk::Image,
    p_sub: *const vk::ImageSubresource,
    p_layout: *mut vk::SubresourceLayout,
) {
    const CMD: &str = "vkGetImageSubresourceLayout";
    guard(CMD, (), || {
        if device_from(device).is_none() || p_sub.is_null() {
            report_unknown_device(CMD);
            return;
        }
        let Some(i) = image_from(image) else {
            diag::vuid("VUID-vkGetImageSubresourceLayout-image-parameter", CMD, "image is not a live VkImage");
            return;
        };
        // SAFETY: valid input per the spec (checked non-null).
        let s = unsafe { *p_sub };
        if i.tiling != vk::ImageTiling::LINEAR {
            diag::vuid("VUID-vkGetImageSubresourceLayout-image-07790", CMD, "the image was not created with VK_IMAGE_TILING_LINEAR");
            return;
        }
        let Some(l) = i.storage.subresource(s.mip_level, s.array_layer).filter(|_| s.aspect_mask == vk::ImageAspectFlags::COLOR) else {
            diag::vuid("VUID-vkGetImageSubresourceLayout-mipLevel-01716", CMD, &format!("subresource {s:?} is not in the image"));
            return;
        };
        let out = vk::SubresourceLayout { offset: l.offset, size: l.size, row_pitch: l.row_pitch, array_pitch: l.array_pitch, depth_pitch: l.depth_pitch };
        // SAFETY: valid output pointer per the spec.
        unsafe { util::out(p_layout, out) };
    })
}

unsafe extern "system" fn create_image_view(
    device: vk::Device,
    p_info: *const vk::ImageViewCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_view: *mut vk::ImageView,
) -> vk::Result {
    const CMD: &str = "vkCreateImageView";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return unknown_device(CMD);
        }
        if p_info.is_null() || p_view.is_null() {
            return invalid("VUID-vkCreateImageView-pCreateInfo-parameter", CMD, "null pointer argument");
        }
        // SAFETY: valid create info and output pointer per the spec (checked non-null).
        let i = unsafe {
            *p_view = vk::ImageView::null();
            &*p_info
        };
        let Some(image) = image_from(i.image) else {
            return invalid("VUID-VkImageViewCreateInfo-image-parameter", CMD, "image is not a live VkImage");
        };
        let identity = |c: vk::ComponentSwizzle, own: vk::ComponentSwizzle| c == vk::ComponentSwizzle::IDENTITY || c == own;
        let c = i.components;
        // Storage images ignore swizzles; only the identity is accepted, so none is silently dropped.
        if !(identity(c.r, vk::ComponentSwizzle::R) && identity(c.g, vk::ComponentSwizzle::G) && identity(c.b, vk::ComponentSwizzle::B) && identity(c.a, vk::ComponentSwizzle::A)) {
            return invalid("VUID-VkImageViewCreateInfo-usage-02275", CMD, "component swizzles other than the identity are not supported");
        }
        match ImageView::new(image, i.view_type, i.format, i.subresource_range) {
            Ok(v) => {
                // SAFETY: checked non-null.
                unsafe { *p_view = vk::ImageView::from_raw(register(Arc::new(v))) };
                vk::Result::SUCCESS
            }
            Err(e) => create_error(CMD, e),
        }
    })
}

unsafe extern "system" fn destroy_image_view(device: vk::Device, view: vk::ImageView, _p_allocator: *const vk::AllocationCallbacks) {
    const CMD: &str = "vkDestroyImageView";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_unknown_device(CMD);
            return;
        }
        if view != vk::ImageView::null() && unregister::<ImageView>(view.as_raw()).is_none() {
            diag::vuid("VUID-vkDestroyImageView-imageView-parameter", CMD, "imageView is not a live VkImageView");
        }
    })
}

unsafe extern "system" fn create_buffer_view(
    device: vk::Device,
    p_info: *const vk::BufferViewCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_view: *mut vk::BufferView,
) -> vk::Result {
    const CMD: &str = "vkCreateBufferView";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if device_from(device).is_none() {
            return unknown_device(CMD);
        }
        if p_info.is_null() || p_view.is_null() {
            return invalid("VUID-vkCreateBufferView-pCreateInfo-parameter", CMD, "null pointer argument");
        }
        // SAFETY: valid create info and output pointer per the spec (checked non-null).
        let i = unsafe {
            *p_view = vk::BufferView::null();
            &*p_info
        };
        let Some(buffer) = buffer_from(i.buffer) else {
            return invalid("VUID-VkBufferViewCreateInfo-buffer-parameter", CMD, "buffer is not a live VkBuffer");
        };
        let l = super::physical_device::limits();
        let limits = TexelBufferLimits { min_offset_alignment: l.min_texel_buffer_offset_alignment, max_elements: l.max_texel_buffer_elements as u64 };
        match BufferView::new(buffer, i.format, i.offset, i.range, &limits) {
            Ok(v) => {
                // SAFETY: checked non-null.
                unsafe { *p_view = vk::BufferView::from_raw(register(Arc::new(v))) };
                vk::Result::SUCCESS
            }
            Err(e) => create_error(CMD, e),
        }
    })
}

unsafe extern "system" fn destroy_buffer_view(device: vk::Device, view: vk::BufferView, _p_allocator: *const vk::AllocationCallbacks) {
    const CMD: &str = "vkDestroyBufferView";
    guard(CMD, (), || {
        if device_from(device).is_none() {
            report_unknown_device(CMD);
            return;
        }
        if view != vk::BufferView::null() && unregister::<BufferView>(view.as_raw()).is_none() {
            diag::vuid("VUID-vkDestroyBufferView-bufferView-parameter", CMD, "bufferView is not a live VkBufferView");
        }
    })
}

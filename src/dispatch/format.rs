//! Format queries: vkGetPhysicalDeviceFormatProperties(2) and
//! vkGetPhysicalDeviceImageFormatProperties(2), answering exactly what works — storage images
//! and transfers for the formats of `runtime::image::FORMATS` in both tilings (and uniform and
//! storage texel buffers of them), and the vertex
//! formats acceleration-structure builds decode — and sparse queries (none).
use std::ffi::c_void;

use ash::vk;

use super::physical_device::physical_from;
use super::table::{imp, Implemented};
use super::{guard, util};
use crate::runtime::image::{format_info, full_chain, max_extent, MAX_ARRAY_LAYERS, SUPPORTED_USAGE};

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkGetPhysicalDeviceFormatProperties => get_physical_device_format_properties),
        imp!(PFN_vkGetPhysicalDeviceFormatProperties2 => get_physical_device_format_properties2),
        imp!(PFN_vkGetPhysicalDeviceImageFormatProperties => get_physical_device_image_format_properties),
        imp!(PFN_vkGetPhysicalDeviceImageFormatProperties2 => get_physical_device_image_format_properties2),
        imp!(PFN_vkGetPhysicalDeviceSparseImageFormatProperties => get_physical_device_sparse_image_format_properties),
        imp!(PFN_vkGetPhysicalDeviceSparseImageFormatProperties2 => get_physical_device_sparse_image_format_properties2),
    ]
}

/// Vertex formats Arbor decodes for acceleration-structure builds (the spec's mandatory six
/// and the optional ones src/accel offers).
pub const AS_VERTEX_FORMATS: &[vk::Format] = &[
    vk::Format::R32G32_SFLOAT,
    vk::Format::R32G32B32_SFLOAT,
    vk::Format::R32G32B32A32_SFLOAT,
    vk::Format::R16G16_SFLOAT,
    vk::Format::R16G16B16_SFLOAT,
    vk::Format::R16G16B16A16_SFLOAT,
    vk::Format::R16G16_SNORM,
    vk::Format::R16G16B16A16_SNORM,
    vk::Format::R16G16_UNORM,
    vk::Format::R16G16B16A16_UNORM,
    vk::Format::R8G8_SNORM,
    vk::Format::R8G8B8A8_SNORM,
    vk::Format::R8G8_UNORM,
    vk::Format::R8G8B8A8_UNORM,
    vk::Format::A2B10G10R10_UNORM_PACK32,
];

/// Formats whose texels shader atomics run on (OpImageTexelPointer: 32-bit integers).
fn atomic_format(format: vk::Format) -> bool {
    matches!(format, vk::Format::R32_UINT | vk::Format::R32_SINT)
}

/// Features of an image format (both tilings store linearly, so they are the same).
fn image_features(format: vk::Format) -> vk::FormatFeatureFlags {
    if format_info(format).is_some() {
        let base = vk::FormatFeatureFlags::STORAGE_IMAGE | vk::FormatFeatureFlags::TRANSFER_SRC | vk::FormatFeatureFlags::TRANSFER_DST;
        if atomic_format(format) {
            base | vk::FormatFeatureFlags::STORAGE_IMAGE_ATOMIC
        } else {
            base
        }
    } else {
        vk::FormatFeatureFlags::empty()
    }
}

/// What `format` supports: storage images and transfers for the image formats; for vertex
/// formats builds decode, ACCELERATION_STRUCTURE_VERTEX_BUFFER.
pub fn format_properties(format: vk::Format) -> vk::FormatProperties {
    let mut buffer = vk::FormatFeatureFlags::empty();
    if AS_VERTEX_FORMATS.contains(&format) {
        buffer |= vk::FormatFeatureFlags::ACCELERATION_STRUCTURE_VERTEX_BUFFER_KHR;
    }
    // Texel buffers run for the storage-image formats (the executor converts the same way).
    if format_info(format).is_some() {
        buffer |= vk::FormatFeatureFlags::UNIFORM_TEXEL_BUFFER | vk::FormatFeatureFlags::STORAGE_TEXEL_BUFFER;
    }
    if atomic_format(format) {
        buffer |= vk::FormatFeatureFlags::STORAGE_TEXEL_BUFFER_ATOMIC;
    }
    let image = image_features(format);
    vk::FormatProperties { linear_tiling_features: image, optimal_tiling_features: image, buffer_features: buffer }
}

/// The 64-bit features (VkFormatProperties3): the 32-bit ones, plus storage access without a
/// format in the shader, which the executor serves from the bound view's format.
fn format_properties3(format: vk::Format) -> vk::FormatProperties3<'static> {
    let p = format_properties(format);
    let wide = |f: vk::FormatFeatureFlags| vk::FormatFeatureFlags2::from_raw(f.as_raw() as u64);
    let mut image = wide(p.optimal_tiling_features);
    if !image.is_empty() {
        image |= vk::FormatFeatureFlags2::STORAGE_READ_WITHOUT_FORMAT | vk::FormatFeatureFlags2::STORAGE_WRITE_WITHOUT_FORMAT;
    }
    let mut buffer = wide(p.buffer_features);
    if buffer.contains(vk::FormatFeatureFlags2::STORAGE_TEXEL_BUFFER) {
        buffer |= vk::FormatFeatureFlags2::STORAGE_READ_WITHOUT_FORMAT | vk::FormatFeatureFlags2::STORAGE_WRITE_WITHOUT_FORMAT;
    }
    vk::FormatProperties3 { linear_tiling_features: image, optimal_tiling_features: image, buffer_features: buffer, ..Default::default() }
}

unsafe extern "system" fn get_physical_device_format_properties(pd: vk::PhysicalDevice, format: vk::Format, p: *mut vk::FormatProperties) {
    guard("vkGetPhysicalDeviceFormatProperties", (), || {
        if physical_from(pd).is_some() {
            // SAFETY: valid output pointer per the spec.
            unsafe { util::out(p, format_properties(format)) };
        }
    })
}

unsafe extern "system" fn get_physical_device_format_properties2(pd: vk::PhysicalDevice, format: vk::Format, p: *mut vk::FormatProperties2) {
    guard("vkGetPhysicalDeviceFormatProperties2", (), || {
        if physical_from(pd).is_some() && !p.is_null() {
            // SAFETY: valid output struct and chain per the spec; write_keep_chain keeps pNext.
            unsafe {
                (*p).format_properties = format_properties(format);
                util::for_each_out((*p).p_next, |s, q| {
                    if s == vk::StructureType::FORMAT_PROPERTIES_3 {
                        util::write_keep_chain(q, format_properties3(format));
                    }
                });
            }
        }
    })
}

/// What an image of these parameters may be, or None (VK_ERROR_FORMAT_NOT_SUPPORTED).
pub fn image_format_properties(
    format: vk::Format,
    ty: vk::ImageType,
    tiling: vk::ImageTiling,
    usage: vk::ImageUsageFlags,
    flags: vk::ImageCreateFlags,
) -> Option<vk::ImageFormatProperties> {
    format_info(format)?;
    let max = max_extent(ty)?;
    let ok = matches!(tiling, vk::ImageTiling::OPTIMAL | vk::ImageTiling::LINEAR) && !usage.is_empty() && (usage & !SUPPORTED_USAGE).is_empty() && flags.is_empty();
    ok.then(|| vk::ImageFormatProperties {
        max_extent: vk::Extent3D { width: max[0], height: max[1], depth: max[2] },
        max_mip_levels: full_chain(max),
        max_array_layers: if ty == vk::ImageType::TYPE_3D { 1 } else { MAX_ARRAY_LAYERS },
        sample_counts: vk::SampleCountFlags::TYPE_1,
        // The largest image is 4096 x 4096 x 16 bytes x 256 layers x 4/3 for mips.
        max_resource_size: 1 << 40,
    })
}

unsafe extern "system" fn get_physical_device_image_format_properties(
    pd: vk::PhysicalDevice,
    format: vk::Format,
    ty: vk::ImageType,
    tiling: vk::ImageTiling,
    usage: vk::ImageUsageFlags,
    flags: vk::ImageCreateFlags,
    p: *mut vk::ImageFormatProperties,
) -> vk::Result {
    guard("vkGetPhysicalDeviceImageFormatProperties", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if physical_from(pd).is_none() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        match image_format_properties(format, ty, tiling, usage, flags) {
            Some(props) => {
                // SAFETY: valid output pointer per the spec.
                unsafe { util::out(p, props) };
                vk::Result::SUCCESS
            }
            None => vk::Result::ERROR_FORMAT_NOT_SUPPORTED,
        }
    })
}

/// # Safety
/// `p_next` is a valid VkPhysicalDeviceImageFormatInfo2 pNext chain.
unsafe fn asks_external(p_next: *const c_void) -> bool {
    // SAFETY: valid chain; the struct is read as the type its sType names.
    let ext = unsafe {
        util::find_in::<vk::PhysicalDeviceExternalImageFormatInfo>(p_next, vk::StructureType::PHYSICAL_DEVICE_EXTERNAL_IMAGE_FORMAT_INFO)
    };
    ext.is_some_and(|e| !e.handle_type.is_empty())
}

unsafe extern "system" fn get_physical_device_image_format_properties2(
    pd: vk::PhysicalDevice,
    p_info: *const vk::PhysicalDeviceImageFormatInfo2,
    p: *mut vk::ImageFormatProperties2,
) -> vk::Result {
    guard("vkGetPhysicalDeviceImageFormatProperties2", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if physical_from(pd).is_none() || p_info.is_null() || p.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid info per the spec (checked non-null).
        let i = unsafe { &*p_info };
        // No external memory handle types are offered.
        // SAFETY: valid chain per the spec.
        if unsafe { asks_external(i.p_next) } {
            return vk::Result::ERROR_FORMAT_NOT_SUPPORTED;
        }
        match image_format_properties(i.format, i.ty, i.tiling, i.usage, i.flags) {
            Some(props) => {
                // SAFETY: valid output struct and chain per the spec; chained outputs
                // (external memory, YCbCr) keep their zeroed "nothing" answers.
                unsafe {
                    (*p).image_format_properties = props;
                    util::for_each_out((*p).p_next, |s, q| {
                        if s == vk::StructureType::EXTERNAL_IMAGE_FORMAT_PROPERTIES {
                            util::write_keep_chain(q, vk::ExternalImageFormatProperties::default());
                        }
                    });
                }
                vk::Result::SUCCESS
            }
            None => vk::Result::ERROR_FORMAT_NOT_SUPPORTED,
        }
    })
}

unsafe extern "system" fn get_physical_device_sparse_image_format_properties(
    _pd: vk::PhysicalDevice,
    _format: vk::Format,
    _ty: vk::ImageType,
    _samples: vk::SampleCountFlags,
    _usage: vk::ImageUsageFlags,
    _tiling: vk::ImageTiling,
    p_count: *mut u32,
    _p: *mut vk::SparseImageFormatProperties,
) {
    // No sparse images.
    // SAFETY: valid pointer per the spec.
    unsafe { util::out(p_count, 0) };
}

unsafe extern "system" fn get_physical_device_sparse_image_format_properties2(
    _pd: vk::PhysicalDevice,
    _info: *const vk::PhysicalDeviceSparseImageFormatInfo2,
    p_count: *mut u32,
    _p: *mut vk::SparseImageFormatProperties2,
) {
    // SAFETY: valid pointer per the spec.
    unsafe { util::out(p_count, 0) };
}

//! `libvulkan_arbor.so`: the loader-facing exports and nothing else. Every other entry point is
//! reached through `vk_icdGetInstanceProcAddr`, so no official `vk*` symbol is exported.
use std::ffi::c_char;

use ash::vk;

/// # Safety
/// Called by the Vulkan loader with a valid pointer.
#[no_mangle]
pub unsafe extern "system" fn vk_icdNegotiateLoaderICDInterfaceVersion(p_supported_version: *mut u32) -> vk::Result {
    // SAFETY: forwarded unchanged; the loader's contract holds.
    unsafe { arbor::dispatch::instance::vk_icd_negotiate_loader_icd_interface_version(p_supported_version) }
}

/// # Safety
/// Called by the Vulkan loader; `name` is a valid C string.
#[no_mangle]
pub unsafe extern "system" fn vk_icdGetInstanceProcAddr(instance: vk::Instance, name: *const c_char) -> vk::PFN_vkVoidFunction {
    // SAFETY: forwarded unchanged; the loader's contract holds.
    unsafe { arbor::dispatch::instance::vk_icd_get_instance_proc_addr(instance, name) }
}

/// # Safety
/// Called by the Vulkan loader; `name` is a valid C string.
#[no_mangle]
pub unsafe extern "system" fn vk_icdGetPhysicalDeviceProcAddr(instance: vk::Instance, name: *const c_char) -> vk::PFN_vkVoidFunction {
    // SAFETY: forwarded unchanged; the loader's contract holds.
    unsafe { arbor::dispatch::instance::vk_icd_get_physical_device_proc_addr(instance, name) }
}

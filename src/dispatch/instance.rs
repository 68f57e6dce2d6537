//! Loader interface, global commands and instance commands.
use std::ffi::c_char;
use std::sync::Arc;

use ash::vk;

use super::handle::{dispatchable, free_dispatchable, new_dispatchable, Dispatchable};
use super::table::{self, imp, Implemented, Level};
use super::{guard, util};
use crate::runtime::{Instance, PhysicalDevice};

/// Highest loader–driver interface version Arbor speaks (vk_icd.h CURRENT = 7).
pub const LOADER_INTERFACE_VERSION: u32 = 7;

/// Instance extensions Arbor advertises, with spec versions.
pub const INSTANCE_EXTENSIONS: &[(&str, u32)] = &[("VK_KHR_get_physical_device_properties2", 2)];

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCreateInstance => create_instance),
        imp!(PFN_vkDestroyInstance => destroy_instance),
        imp!(PFN_vkEnumerateInstanceVersion => enumerate_instance_version),
        imp!(PFN_vkEnumerateInstanceExtensionProperties => enumerate_instance_extension_properties),
        imp!(PFN_vkEnumerateInstanceLayerProperties => enumerate_instance_layer_properties),
        imp!(PFN_vkEnumeratePhysicalDevices => enumerate_physical_devices),
        imp!(PFN_vkEnumeratePhysicalDeviceGroups => enumerate_physical_device_groups),
        imp!(PFN_vkGetInstanceProcAddr => get_instance_proc_addr),
    ]
}

pub type InstanceHandle = *mut Dispatchable<Instance>;
pub type PhysicalDeviceHandle = *mut Dispatchable<PhysicalDevice>;

/// # Safety
/// Called by the loader with a valid pointer.
pub unsafe extern "system" fn vk_icd_negotiate_loader_icd_interface_version(p_version: *mut u32) -> vk::Result {
    guard("vk_icdNegotiateLoaderICDInterfaceVersion", vk::Result::ERROR_INCOMPATIBLE_DRIVER, || {
        if p_version.is_null() {
            return vk::Result::ERROR_INCOMPATIBLE_DRIVER;
        }
        // SAFETY: checked non-null; the loader passes its supported version in and reads ours out.
        unsafe {
            let loader = *p_version;
            // Versions below 5 would require rejecting apiVersion > 1.0 ourselves: refuse them.
            if loader < 5 {
                return vk::Result::ERROR_INCOMPATIBLE_DRIVER;
            }
            *p_version = loader.min(LOADER_INTERFACE_VERSION);
        }
        vk::Result::SUCCESS
    })
}

/// # Safety
/// Called by the loader; `name` is a valid C string.
pub unsafe extern "system" fn vk_icd_get_instance_proc_addr(instance: vk::Instance, name: *const c_char) -> vk::PFN_vkVoidFunction {
    guard("vk_icdGetInstanceProcAddr", None, || {
        // SAFETY: the loader passes a valid string.
        let n = (unsafe { util::cstr(name) })?;
        let icd: Option<table::VoidFn> = match n {
            // SAFETY: function pointers of any signature have the same
            // size; the loader casts back to the export's own type before calling (so below).
            "vk_icdNegotiateLoaderICDInterfaceVersion" => Some(unsafe {
                std::mem::transmute::<unsafe extern "system" fn(*mut u32) -> vk::Result, table::VoidFn>(
                    vk_icd_negotiate_loader_icd_interface_version,
                )
            }),
            // SAFETY: as above.
            "vk_icdGetInstanceProcAddr" => Some(unsafe {
                std::mem::transmute::<vk::PFN_vkGetInstanceProcAddr, table::VoidFn>(vk_icd_get_instance_proc_addr)
            }),
            // SAFETY: as above.
            "vk_icdGetPhysicalDeviceProcAddr" => Some(unsafe {
                std::mem::transmute::<vk::PFN_vkGetInstanceProcAddr, table::VoidFn>(vk_icd_get_physical_device_proc_addr)
            }),
            _ => None,
        };
        if icd.is_some() {
            return icd;
        }
        instance_proc_addr(instance, n)
    })
}

/// # Safety
/// Called by the loader; `name` is a valid C string.
pub unsafe extern "system" fn vk_icd_get_physical_device_proc_addr(_instance: vk::Instance, name: *const c_char) -> vk::PFN_vkVoidFunction {
    guard("vk_icdGetPhysicalDeviceProcAddr", None, || {
        // SAFETY: the loader passes a valid string.
        let n = unsafe { util::cstr(name) }?;
        let r = table::lookup(n)?;
        (r.entry.level == Level::PhysicalDevice).then_some(r.f).and_then(table::to_pfn)
    })
}

/// vkGetInstanceProcAddr: with a null instance only global commands; otherwise every command
/// Arbor knows (the loader builds its dispatch tables from these).
fn instance_proc_addr(instance: vk::Instance, name: &str) -> vk::PFN_vkVoidFunction {
    let r = table::lookup(name)?;
    if instance == vk::Instance::null() {
        return (r.entry.level == Level::Global && name != "vkGetDeviceProcAddr").then_some(r.f).and_then(table::to_pfn);
    }
    table::to_pfn(r.f)
}

unsafe extern "system" fn get_instance_proc_addr(instance: vk::Instance, name: *const c_char) -> vk::PFN_vkVoidFunction {
    guard("vkGetInstanceProcAddr", None, || {
        // SAFETY: the application passes a valid string.
        let n = unsafe { util::cstr(name) }?;
        instance_proc_addr(instance, n)
    })
}

unsafe extern "system" fn enumerate_instance_version(p_api_version: *mut u32) -> vk::Result {
    // SAFETY: valid pointer per the spec.
    unsafe { util::out(p_api_version, crate::API_VERSION) };
    vk::Result::SUCCESS
}

fn extension_properties(list: &[(&str, u32)]) -> Vec<vk::ExtensionProperties> {
    list.iter()
        .map(|(name, v)| {
            let mut p = vk::ExtensionProperties { spec_version: *v, ..Default::default() };
            util::write_name(&mut p.extension_name, name);
            p
        })
        .collect()
}

unsafe extern "system" fn enumerate_instance_extension_properties(
    p_layer_name: *const c_char,
    p_count: *mut u32,
    p_props: *mut vk::ExtensionProperties,
) -> vk::Result {
    guard("vkEnumerateInstanceExtensionProperties", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if !p_layer_name.is_null() {
            return vk::Result::ERROR_LAYER_NOT_PRESENT;
        }
        // SAFETY: valid pointers per the spec.
        unsafe { util::enumerate(&extension_properties(INSTANCE_EXTENSIONS), p_count, p_props) }
    })
}

unsafe extern "system" fn enumerate_instance_layer_properties(p_count: *mut u32, p_props: *mut vk::LayerProperties) -> vk::Result {
    // SAFETY: valid pointers per the spec.
    unsafe { util::enumerate::<vk::LayerProperties>(&[], p_count, p_props) }
}

pub fn device_extension_properties() -> Vec<vk::ExtensionProperties> {
    extension_properties(super::physical_device::DEVICE_EXTENSIONS)
}

unsafe extern "system" fn create_instance(
    p_create_info: *const vk::InstanceCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_instance: *mut vk::Instance,
) -> vk::Result {
    guard("vkCreateInstance", vk::Result::ERROR_INITIALIZATION_FAILED, || {
        if p_create_info.is_null() || p_instance.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid create info per the spec.
        let info = unsafe { &*p_create_info };
        // SAFETY: the application passes valid strings.
        let exts = unsafe { util::cstr_array(info.pp_enabled_extension_names, info.enabled_extension_count) };
        for e in &exts {
            if !INSTANCE_EXTENSIONS.iter().any(|(n, _)| n == e) {
                crate::diag::report(crate::diag::Level::Warn, "vkCreateInstance", &format!("extension {e} not present"));
                return vk::Result::ERROR_EXTENSION_NOT_PRESENT;
            }
        }
        let api_version = if info.p_application_info.is_null() {
            vk::API_VERSION_1_0
        } else {
            // SAFETY: non-null application info is valid per the spec.
            let v = unsafe { (*info.p_application_info).api_version };
            if v == 0 { vk::API_VERSION_1_0 } else { v }
        };
        let pd = new_dispatchable(PhysicalDevice::new());
        let inst = Arc::new(Instance { api_version, enabled_extensions: exts, physical_device: pd as usize });
        let h = new_dispatchable(inst);
        // SAFETY: checked non-null.
        unsafe { *p_instance = vk::Handle::from_raw(h as u64) };
        vk::Result::SUCCESS
    })
}

pub fn instance_from(h: vk::Instance) -> Option<Arc<Instance>> {
    // SAFETY: a non-null VkInstance is a live handle we created (application obligation).
    unsafe { dispatchable::<Instance>(vk::Handle::as_raw(h) as InstanceHandle) }
}

unsafe extern "system" fn destroy_instance(instance: vk::Instance, _p_allocator: *const vk::AllocationCallbacks) {
    guard("vkDestroyInstance", (), || {
        // SAFETY: the application destroys a live instance once.
        if let Some(inst) = unsafe { free_dispatchable::<Instance>(vk::Handle::as_raw(instance) as InstanceHandle) } {
            // SAFETY: the physical device handle was created with the instance and dies with it.
            unsafe { free_dispatchable::<PhysicalDevice>(inst.physical_device as PhysicalDeviceHandle) };
        }
    })
}

unsafe extern "system" fn enumerate_physical_devices(
    instance: vk::Instance,
    p_count: *mut u32,
    p_devices: *mut vk::PhysicalDevice,
) -> vk::Result {
    guard("vkEnumeratePhysicalDevices", vk::Result::ERROR_INITIALIZATION_FAILED, || {
        let Some(inst) = instance_from(instance) else { return vk::Result::ERROR_INITIALIZATION_FAILED };
        let list = [<vk::PhysicalDevice as vk::Handle>::from_raw(inst.physical_device as u64)];
        // SAFETY: valid pointers per the spec.
        unsafe { util::enumerate(&list, p_count, p_devices) }
    })
}

unsafe extern "system" fn enumerate_physical_device_groups(
    instance: vk::Instance,
    p_count: *mut u32,
    p_groups: *mut vk::PhysicalDeviceGroupProperties,
) -> vk::Result {
    guard("vkEnumeratePhysicalDeviceGroups", vk::Result::ERROR_INITIALIZATION_FAILED, || {
        let Some(inst) = instance_from(instance) else { return vk::Result::ERROR_INITIALIZATION_FAILED };
        if p_count.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid pointers per the spec; output structs keep their sType/pNext.
        unsafe {
            if p_groups.is_null() {
                *p_count = 1;
                return vk::Result::SUCCESS;
            }
            if *p_count == 0 {
                return vk::Result::INCOMPLETE;
            }
            let g = &mut *p_groups;
            g.physical_device_count = 1;
            g.physical_devices[0] = vk::Handle::from_raw(inst.physical_device as u64);
            g.subset_allocation = vk::FALSE;
            *p_count = 1;
        }
        vk::Result::SUCCESS
    })
}

//! Device creation, queues by index, vkGetDeviceProcAddr.
use std::collections::HashSet;
use std::ffi::c_char;
use std::sync::{Arc, OnceLock};

use ash::vk;

use super::handle::{self, dispatchable, free_dispatchable, new_dispatchable, Dispatchable};
use super::physical_device::{physical_from, DEVICE_EXTENSIONS, QUEUE_COUNT, QUEUE_FAMILY_COUNT};
use super::table::{self, imp, Implemented, Level, Origin};
use super::{guard, util};
use crate::runtime::device::EnabledFeatures;
use crate::runtime::{Device, Queue};

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCreateDevice => create_device),
        imp!(PFN_vkDestroyDevice => destroy_device),
        imp!(PFN_vkGetDeviceQueue => get_device_queue),
        imp!(PFN_vkGetDeviceQueue2 => get_device_queue2),
        imp!(PFN_vkGetDeviceProcAddr => get_device_proc_addr),
    ]
}

pub type DeviceHandle = *mut Dispatchable<Device>;
pub type QueueHandle = *mut Dispatchable<Queue>;

pub fn device_from(h: vk::Device) -> Option<Arc<Device>> {
    // SAFETY: a non-null VkDevice is a live handle we created (application obligation).
    let dev = unsafe { dispatchable::<Device>(vk::Handle::as_raw(h) as DeviceHandle) }?;
    handle::note_device(&dev);
    Some(dev)
}

pub fn queue_from(h: vk::Queue) -> Option<Arc<Queue>> {
    // SAFETY: a non-null VkQueue is a live handle we created (application obligation).
    unsafe { dispatchable::<Queue>(vk::Handle::as_raw(h) as QueueHandle) }
}

/// Read the features the application enabled (pEnabledFeatures and the pNext structs).
///
/// # Safety
/// `info` is a valid VkDeviceCreateInfo.
unsafe fn enabled_features(info: &vk::DeviceCreateInfo) -> EnabledFeatures {
    let mut f = EnabledFeatures::default();
    let mut p = info.p_next;
    let mut guard = 0;
    while !p.is_null() && guard < 4096 {
        // SAFETY: a valid pNext chain; each struct is read as the type its sType names.
        unsafe {
            let base = &*(p as *const vk::BaseInStructure);
            match base.s_type {
                vk::StructureType::PHYSICAL_DEVICE_BUFFER_DEVICE_ADDRESS_FEATURES => {
                    let s = &*(p as *const vk::PhysicalDeviceBufferDeviceAddressFeatures);
                    f.buffer_device_address |= s.buffer_device_address != 0;
                    f.buffer_device_address_capture_replay |= s.buffer_device_address_capture_replay != 0;
                }
                vk::StructureType::PHYSICAL_DEVICE_TIMELINE_SEMAPHORE_FEATURES => {
                    let s = &*(p as *const vk::PhysicalDeviceTimelineSemaphoreFeatures);
                    f.timeline_semaphore |= s.timeline_semaphore != 0;
                }
                vk::StructureType::PHYSICAL_DEVICE_SYNCHRONIZATION_2_FEATURES => {
                    let s = &*(p as *const vk::PhysicalDeviceSynchronization2Features);
                    f.synchronization2 |= s.synchronization2 != 0;
                }
                vk::StructureType::PHYSICAL_DEVICE_HOST_QUERY_RESET_FEATURES => {
                    let s = &*(p as *const vk::PhysicalDeviceHostQueryResetFeatures);
                    f.host_query_reset |= s.host_query_reset != 0;
                }
                vk::StructureType::PHYSICAL_DEVICE_VULKAN_1_2_FEATURES => {
                    // The 1.2 aggregate enables the promoted features it contains.
                    let s = &*(p as *const vk::PhysicalDeviceVulkan12Features);
                    f.buffer_device_address |= s.buffer_device_address != 0;
                    f.buffer_device_address_capture_replay |= s.buffer_device_address_capture_replay != 0;
                    f.timeline_semaphore |= s.timeline_semaphore != 0;
                    f.host_query_reset |= s.host_query_reset != 0;
                }
                vk::StructureType::PHYSICAL_DEVICE_ACCELERATION_STRUCTURE_FEATURES_KHR => {
                    let s = &*(p as *const vk::PhysicalDeviceAccelerationStructureFeaturesKHR);
                    f.acceleration_structure |= s.acceleration_structure != 0;
                    f.acceleration_structure_capture_replay |= s.acceleration_structure_capture_replay != 0;
                    f.acceleration_structure_indirect_build |= s.acceleration_structure_indirect_build != 0;
                    f.acceleration_structure_host_commands |= s.acceleration_structure_host_commands != 0;
                }
                s if s == super::nv_cluster::STYPE_FEATURES => {
                    let s = &*(p as *const super::nv_cluster::PhysicalDeviceClusterAccelerationStructureFeaturesNV);
                    f.cluster_acceleration_structure = Some(f.cluster_acceleration_structure.unwrap_or(false) | (s.cluster_acceleration_structure != 0));
                }
                _ => {}
            }
            p = base.p_next as *const std::ffi::c_void;
        }
        guard += 1;
    }
    f
}

/// Check requested features against what Arbor offers: a feature we report VK_FALSE must not
/// be enabled (VK_ERROR_FEATURE_NOT_PRESENT).
///
/// # Safety
/// `info` is a valid VkDeviceCreateInfo.
unsafe fn unsupported_feature_requested(info: &vk::DeviceCreateInfo) -> Option<String> {
    let offered = super::physical_device::features();
    let check = |req: &vk::PhysicalDeviceFeatures| -> Option<String> {
        // Both are arrays of VkBool32 (55 fields): compare field by field.
        let n = std::mem::size_of::<vk::PhysicalDeviceFeatures>() / 4;
        // SAFETY: VkPhysicalDeviceFeatures is a plain array of VkBool32.
        let (a, b) = unsafe {
            (
                std::slice::from_raw_parts(req as *const _ as *const u32, n),
                std::slice::from_raw_parts(&offered as *const _ as *const u32, n),
            )
        };
        a.iter().zip(b).position(|(r, o)| *r != 0 && *o == 0).map(|i| format!("VkPhysicalDeviceFeatures field #{i}"))
    };
    if !info.p_enabled_features.is_null() {
        // SAFETY: non-null enabled features are valid per the spec.
        if let Some(e) = check(unsafe { &*info.p_enabled_features }) {
            return Some(e);
        }
    }
    // SAFETY: valid chain.
    if let Some(f2) = unsafe { util::find_in::<vk::PhysicalDeviceFeatures2>(info.p_next, vk::StructureType::PHYSICAL_DEVICE_FEATURES_2) } {
        if let Some(e) = check(&f2.features) {
            return Some(e);
        }
    }
    None
}

unsafe extern "system" fn create_device(
    pd: vk::PhysicalDevice,
    p_create_info: *const vk::DeviceCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_device: *mut vk::Device,
) -> vk::Result {
    guard("vkCreateDevice", vk::Result::ERROR_INITIALIZATION_FAILED, || {
        let Some(physical) = physical_from(pd) else { return vk::Result::ERROR_INITIALIZATION_FAILED };
        if p_create_info.is_null() || p_device.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid create info per the spec.
        let info = unsafe { &*p_create_info };
        // SAFETY: valid strings per the spec.
        let exts = unsafe { util::cstr_array(info.pp_enabled_extension_names, info.enabled_extension_count) };
        for e in &exts {
            if !DEVICE_EXTENSIONS.iter().any(|(n, _)| n == e) {
                crate::diag::report(crate::diag::Level::Warn, "vkCreateDevice", &format!("extension {e} not present"));
                return vk::Result::ERROR_EXTENSION_NOT_PRESENT;
            }
        }
        // SAFETY: valid create info.
        if let Some(f) = unsafe { unsupported_feature_requested(info) } {
            crate::diag::report(crate::diag::Level::Warn, "vkCreateDevice", &format!("feature not present: {f}"));
            return vk::Result::ERROR_FEATURE_NOT_PRESENT;
        }
        // SAFETY: valid queue create infos per the spec.
        let qinfos = unsafe { util::slice(info.p_queue_create_infos, info.queue_create_info_count) };
        for q in qinfos {
            if q.queue_family_index >= QUEUE_FAMILY_COUNT || q.queue_count == 0 || q.queue_count > QUEUE_COUNT {
                crate::diag::report(crate::diag::Level::Error, "vkCreateDevice", "invalid queue family index or count");
                return vk::Result::ERROR_INITIALIZATION_FAILED;
            }
        }
        // SAFETY: valid create info.
        let features = unsafe { enabled_features(info) };
        let memory = Arc::new(crate::memory::AddressSpace::new(physical.heap_size));
        let device = Arc::new(Device {
            physical,
            enabled_extensions: exts.into_iter().collect::<HashSet<_>>(),
            api_minor: vk::api_version_minor(crate::API_VERSION),
            features,
            memory,
            queues: OnceLock::new(),
            epoch: std::time::Instant::now(),
            lost: Default::default(),
        });
        let mut queues = Vec::new();
        for q in qinfos {
            for i in 0..q.queue_count {
                let queue = Arc::new(Queue::new(Arc::downgrade(&device), q.queue_family_index, i));
                queues.push((q.queue_family_index, i, new_dispatchable(queue) as usize));
            }
        }
        let _ = device.queues.set(queues);
        let h = new_dispatchable(device);
        // SAFETY: checked non-null.
        unsafe { *p_device = vk::Handle::from_raw(h as u64) };
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn destroy_device(device: vk::Device, _p_allocator: *const vk::AllocationCallbacks) {
    guard("vkDestroyDevice", (), || {
        // SAFETY: the application destroys a live device once.
        if let Some(dev) = unsafe { free_dispatchable::<Device>(vk::Handle::as_raw(device) as DeviceHandle) } {
            for (_, _, q) in dev.queues.get().map(|v| v.as_slice()).unwrap_or(&[]) {
                // SAFETY: queue handles were created with the device and die with it.
                if let Some(queue) = unsafe { free_dispatchable::<Queue>(*q as QueueHandle) } {
                    // Work still pending finishes first, as after vkDeviceWaitIdle (which the
                    // spec asks for); a submission no one can unblock is abandoned (`stall`).
                    queue.finish_before_destroy();
                    // Stop and join the queue's worker (cancels waits it is blocked in).
                    queue.shutdown();
                }
            }
            report_leaks(&dev);
        }
    })
}

/// Objects of the device still alive at vkDestroyDevice: one report with the count of each
/// type, as the validation layer's object tracker gives; they are destroyed with the device.
fn report_leaks(dev: &Device) {
    let children = handle::remove_children(dev);
    if !children.is_empty() {
        let list: Vec<String> = children.iter().map(|(name, n)| format!("{n} {name}")).collect();
        crate::diag::vuid(
            "VUID-vkDestroyDevice-device-05137",
            "vkDestroyDevice",
            &format!("child objects not destroyed: {}; destroyed with the device", list.join(", ")),
        );
    }
}

fn find_queue(dev: &Device, family: u32, index: u32) -> Option<usize> {
    dev.queues.get()?.iter().find(|(f, i, _)| *f == family && *i == index).map(|(_, _, h)| *h)
}

unsafe extern "system" fn get_device_queue(device: vk::Device, family: u32, index: u32, p_queue: *mut vk::Queue) {
    guard("vkGetDeviceQueue", (), || {
        let Some(dev) = device_from(device) else { return };
        let h = find_queue(&dev, family, index).unwrap_or(0);
        if h == 0 {
            crate::diag::report(crate::diag::Level::Error, "vkGetDeviceQueue", "no such queue was created");
        }
        // SAFETY: valid output pointer per the spec.
        unsafe { util::out(p_queue, vk::Handle::from_raw(h as u64)) };
    })
}

unsafe extern "system" fn get_device_queue2(device: vk::Device, p_info: *const vk::DeviceQueueInfo2, p_queue: *mut vk::Queue) {
    guard("vkGetDeviceQueue2", (), || {
        let Some(dev) = device_from(device) else { return };
        if p_info.is_null() {
            return;
        }
        // SAFETY: valid info per the spec.
        let info = unsafe { &*p_info };
        // Arbor creates no protected queues: a flags value other than 0 matches no queue.
        let h = if info.flags.is_empty() { find_queue(&dev, info.queue_family_index, info.queue_index).unwrap_or(0) } else { 0 };
        // SAFETY: valid output pointer per the spec.
        unsafe { util::out(p_queue, vk::Handle::from_raw(h as u64)) };
    })
}

/// Whether a device-level command is available on this device (core version or enabled extension).
pub fn device_command_enabled(dev: &Device, origin: Origin) -> bool {
    match origin {
        Origin::Core(minor) => minor <= dev.api_minor,
        Origin::Extension(e) => dev.extension_enabled(e),
    }
}

unsafe extern "system" fn get_device_proc_addr(device: vk::Device, name: *const c_char) -> vk::PFN_vkVoidFunction {
    guard("vkGetDeviceProcAddr", None, || {
        let dev = device_from(device)?;
        // SAFETY: valid string per the spec.
        let n = unsafe { util::cstr(name) }?;
        let r = table::lookup(n)?;
        if r.entry.level != Level::Device || !device_command_enabled(&dev, r.entry.origin) {
            return None;
        }
        table::to_pfn(r.f)
    })
}

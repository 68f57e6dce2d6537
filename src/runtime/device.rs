//! The logical device: enabled extensions/features, its queues and its emulated memory.
use std::collections::HashSet;
use std::sync::Arc;

use crate::memory::AddressSpace;

use super::PhysicalDevice;

pub struct Device {
    pub physical: Arc<PhysicalDevice>,
    pub enabled_extensions: HashSet<String>,
    /// Minor version of the API the device exposes (`1.<minor>`).
    pub api_minor: u32,
    pub features: EnabledFeatures,
    /// The device-address space and allocations of this device.
    pub memory: Arc<AddressSpace>,
    /// Queue handles (`Dispatchable<Queue>` pointers), by (family, index); set once at creation.
    pub queues: std::sync::OnceLock<Vec<(u32, u32, usize)>>,
    /// Monotonic origin of timestamps.
    pub epoch: std::time::Instant,
    /// Set when a submission lost the device (strict mode); waits and submits then report
    /// VK_ERROR_DEVICE_LOST.
    pub lost: std::sync::atomic::AtomicBool,
}

/// Features the application enabled that change behaviour.
#[derive(Default, Clone, Debug)]
pub struct EnabledFeatures {
    pub buffer_device_address: bool,
    pub buffer_device_address_capture_replay: bool,
    pub timeline_semaphore: bool,
    pub synchronization2: bool,
    pub host_query_reset: bool,
    pub acceleration_structure: bool,
    pub acceleration_structure_capture_replay: bool,
    pub acceleration_structure_indirect_build: bool,
    pub acceleration_structure_host_commands: bool,
    /// VkPhysicalDeviceClusterAccelerationStructureFeaturesNV::clusterAccelerationStructure;
    /// None when the struct was not in the chain (a layer that predates the extension drops it).
    pub cluster_acceleration_structure: Option<bool>,
}

impl Device {
    pub fn extension_enabled(&self, name: &str) -> bool {
        self.enabled_extensions.contains(name)
    }

    pub fn is_lost(&self) -> bool {
        self.lost.load(std::sync::atomic::Ordering::Acquire)
    }

    pub fn mark_lost(&self) {
        self.lost.store(true, std::sync::atomic::Ordering::Release);
        crate::runtime::sync::notify();
    }

    /// Nanoseconds since device creation (timestamp queries; timestampPeriod = 1 ns).
    pub fn timestamp_now(&self) -> u64 {
        self.epoch.elapsed().as_nanos() as u64
    }
}

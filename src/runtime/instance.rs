//! Instance and the one physical device.
use std::sync::Arc;

pub struct Instance {
    pub api_version: u32,
    pub enabled_extensions: Vec<String>,
    /// Handle value of the physical device (a `Dispatchable<PhysicalDevice>`), freed with the instance.
    pub physical_device: usize,
}

/// What the machine offers; derived once per instance.
pub struct PhysicalDevice {
    /// Size of the one memory heap: a share of the machine's RAM.
    pub heap_size: u64,
}

impl PhysicalDevice {
    pub fn new() -> Arc<Self> {
        Arc::new(PhysicalDevice { heap_size: heap_size_from_ram(total_ram()) })
    }
}

/// Total RAM in bytes from /proc/meminfo (falls back to 4 GiB when unreadable).
pub fn total_ram() -> u64 {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("MemTotal:")).and_then(|l| {
                l.split_whitespace().nth(1).and_then(|kb| kb.parse::<u64>().ok()).map(|kb| kb * 1024)
            })
        })
        .unwrap_or(4 << 30)
}

/// The heap is three quarters of RAM: the rest stays for the application and the OS.
pub fn heap_size_from_ram(ram: u64) -> u64 {
    (ram / 4 * 3) & !0xFFFF
}

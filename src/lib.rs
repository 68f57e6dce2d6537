//! Arbor: a Vulkan driver that runs on the CPU and specialises in ray-tracing acceleration
//! structures.
//!
//! Layers (see DESIGN.md): `dispatch` is the only code that sees raw application pointers;
//! `runtime` is the object model and the queues that execute recorded commands; `memory` is the
//! emulated device (allocations, the device-address space, checked reads and writes); `accel` is
//! the pure acceleration-structure library.


pub mod accel;
pub mod diag;
pub mod dispatch;
pub mod memory;
pub mod runtime;
pub mod shader;
pub mod threads;

/// The loader's magic word for dispatchable handles (vk_icd.h `ICD_LOADER_MAGIC`).
pub const ICD_LOADER_MAGIC: usize = 0x01CD_C0DE;

/// Vulkan version Arbor implements: 1.2, whose requirements for a compute-only device it meets
/// (`dispatch::core_caps` lists them and the graphics ones that do not apply).
pub const API_VERSION: u32 = ash::vk::make_api_version(0, 1, 2, ash::vk::HEADER_VERSION);
/// Driver version reported in VkPhysicalDeviceProperties.
pub const DRIVER_VERSION: u32 = ash::vk::make_api_version(0, 0, 1, 0);
/// Stable identity. driverUUID names the driver build family; deviceUUID the (one) device.
pub const DRIVER_UUID: [u8; 16] = *b"ArborDriver0001\0";
pub const DEVICE_UUID: [u8; 16] = *b"ArborCpuDevice1\0";
pub const DEVICE_NAME: &str = "Arbor (software)";

//! Arbor: a Vulkan driver that runs on the CPU and specialises in ray-tracing acceleration structures.
pub mod accel;
pub mod scene;

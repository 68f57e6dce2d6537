//! The object model: plain Rust types with Arc-shared state. No raw application pointers here.
pub mod accel;
pub mod command;
pub mod descriptor;
pub mod deferred;
pub mod device;
pub mod instance;
pub mod query;
pub mod queue;
pub mod sync;

pub use device::Device;
pub use instance::{Instance, PhysicalDevice};
pub use queue::Queue;

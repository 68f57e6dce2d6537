//! The object model: plain Rust types with Arc-shared state, the queues that execute recorded
//! commands, the acceleration-structure commands (`accel`) and compute pipelines (`shader`). No raw application pointers
//! and no `unsafe` here, and nothing of the dispatch layer: handles, their type tags and the
//! handle registry are `dispatch`'s, and memory views are `memory`'s.
#![forbid(unsafe_code)]
pub mod accel;
pub mod command;
pub mod descriptor;
pub mod deferred;
pub mod device;
pub mod image;
pub mod image_copy;
pub mod in_use;
pub mod instance;
pub mod query;
pub mod queue;
pub mod shader;
pub mod stall;
pub mod sync;

pub use device::Device;
pub use instance::{Instance, PhysicalDevice};
pub use queue::Queue;

//! The only code that sees raw application pointers: one thin `extern "system"` function per
//! Vulkan command (raw pointers → checked Rust values → one call into the object model →
//! outputs written), the name → function table, pNext walking and the enumerate idiom.
//! No panic crosses this boundary: every entry point runs inside [`guard`].
pub mod accel;
pub mod command;
pub mod core_caps;
pub mod deferred;
pub mod descriptor;
pub mod device;
pub mod format;
pub mod handle;
pub mod image;
pub mod image_cmd;
pub mod instance;
pub mod memory;
pub mod nv_cluster;
pub mod nv_partitioned;
pub mod physical_device;
pub mod pipeline;
pub mod query;
pub mod queue;
pub mod registry;
pub mod sync;
pub mod table;
pub mod util;

use table::Implemented;

/// Run an entry point body, turning a panic into a diagnostic and `on_panic`.
pub fn guard<R>(command: &str, on_panic: R, body: impl FnOnce() -> R) -> R {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(body)) {
        Ok(r) => r,
        Err(e) => {
            let msg = e
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| e.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            crate::diag::report(crate::diag::Level::Error, command, &format!("internal error (caught panic): {msg}"));
            on_panic
        }
    }
}

/// Every command Arbor implements, by area. Each area module lists its own.
pub fn implemented() -> Vec<Implemented> {
    let mut v = Vec::new();
    v.extend(instance::commands());
    v.extend(accel::commands());
    v.extend(deferred::commands());
    v.extend(physical_device::commands());
    v.extend(device::commands());
    v.extend(memory::commands());
    v.extend(format::commands());
    v.extend(image::commands());
    v.extend(image_cmd::commands());
    v.extend(descriptor::commands());
    v.extend(pipeline::commands());
    v.extend(command::commands());
    v.extend(queue::commands());
    v.extend(sync::commands());
    v.extend(query::commands());
    v.extend(nv_cluster::commands());
    v.extend(nv_partitioned::commands());
    v
}


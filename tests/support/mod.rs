//! The old path of the loader harness, kept only because benches/accel_api.rs still includes it by
//! `#[path = "../tests/support/mod.rs"]`: delete this file once that line names
//! `../tests/harness/mod.rs`.
#[path = "../harness/mod.rs"]
mod harness;
pub use harness::*;

//! Pure acceleration-structure library: no Vulkan handles, no FFI, no unsafe.
#![forbid(unsafe_code)]

//! Borrowed, shared views of device memory: byte slices whose lifetime is tied to a pinned
//! buffer, and [`DeviceMemoryView`], which follows device addresses (the runtime adapts it to
//! the acceleration-structure library's `DeviceView`). Writable views are `region`'s.
//!
//! Like every module of `memory`, this one knows nothing of acceleration structures beyond the
//! size of the prefix that identifies one ([`STRUCTURE_PROBE`]).
use std::sync::{Arc, Mutex};

use super::{AccessError, AddressSpace, Buffer};

impl Buffer {
    /// A shared view of `[offset, offset + len)` of this buffer, valid while the buffer is
    /// borrowed (the buffer keeps its memory alive).
    pub fn bytes(&self, offset: u64, len: u64) -> Result<&[u8], AccessError> {
        let (m, o) = self.locate(offset, len)?;
        m.check(o, len)?;
        // SAFETY: range checked against the allocation; the backing lives as long as the
        // Arc<Memory> this buffer holds, hence as long as &self. Concurrent writers would violate
        // the application's synchronisation obligations (module docs of `memory`).
        Ok(unsafe { std::slice::from_raw_parts(m.backing.ptr.as_ptr().add(o as usize), len as usize) })
    }

    /// Identity of the backing memory and the byte range of `[offset, offset + len)` within it,
    /// for overlap checks between regions.
    pub fn memory_range(&self, offset: u64, len: u64) -> Option<(usize, u64, u64)> {
        let (m, base) = self.memory()?;
        Some((Arc::as_ptr(m) as usize, base + offset, base + offset.saturating_add(len)))
    }
}

/// Smallest prefix of an acceleration structure that identifies it (the accel header).
pub const STRUCTURE_PROBE: u64 = 16;

/// Reads through a device's address space: device addresses resolve to the live buffers
/// containing them; every buffer a returned slice borrows from is pinned for the view's
/// lifetime.
pub struct DeviceMemoryView<'a> {
    space: &'a AddressSpace,
    pins: Mutex<Vec<Arc<Buffer>>>,
    /// Structures already resolved (a TLAS build looks each BLAS up once per instance).
    structures: Mutex<std::collections::HashMap<u64, (usize, usize)>>,
}

impl<'a> DeviceMemoryView<'a> {
    pub fn new(space: &'a AddressSpace) -> Self {
        DeviceMemoryView { space, pins: Mutex::new(Vec::new()), structures: Mutex::new(std::collections::HashMap::new()) }
    }

    fn pinned_slice(&self, buffer: Arc<Buffer>, offset: u64, len: u64) -> Option<&[u8]> {
        let s = buffer.bytes(offset, len).ok()?;
        let (ptr, n) = (s.as_ptr(), s.len());
        let mut pins = self.pins.lock().unwrap_or_else(|e| e.into_inner());
        // Consecutive reads usually hit the same buffer (instance arrays, BLAS lookups): pin once.
        if !pins.iter().rev().take(8).any(|b| Arc::ptr_eq(b, &buffer)) {
            pins.push(buffer);
        }
        // SAFETY: the slice points into memory owned by `buffer`, which is now pinned in
        // `self.pins` until the view is dropped, so it outlives the returned borrow of `self`.
        Some(unsafe { std::slice::from_raw_parts(ptr, n) })
    }
}

impl DeviceMemoryView<'_> {
    /// The `len` bytes at device address `address`, inside one live buffer.
    pub fn bytes(&self, address: u64, len: u64) -> Option<&[u8]> {
        let r = self.space.resolve(address, len).ok()?;
        self.pinned_slice(r.buffer, r.offset, len)
    }

    /// The bytes from device address `reference` to the end of the buffer holding it (an
    /// acceleration structure's extent as far as memory knows), looked up once per address.
    pub fn structure(&self, reference: u64) -> Option<&[u8]> {
        if let Some(&(ptr, len)) = self.structures.lock().unwrap_or_else(|e| e.into_inner()).get(&reference) {
            // SAFETY: recorded below from a slice whose buffer is pinned for the view's lifetime.
            return Some(unsafe { std::slice::from_raw_parts(ptr as *const u8, len) });
        }
        let r = self.space.resolve(reference, STRUCTURE_PROBE).ok()?;
        let len = r.buffer.size - r.offset;
        let s = self.pinned_slice(r.buffer, r.offset, len)?;
        self.structures.lock().unwrap_or_else(|e| e.into_inner()).insert(reference, (s.as_ptr() as usize, s.len()));
        Some(s)
    }
}

//! Borrowed, shared views of device memory: byte slices whose lifetime is tied to a pinned
//! buffer, and [`DeviceMemoryView`], which follows device addresses (the runtime adapts it to
//! the acceleration-structure library's `DeviceView`). Writable views are `region`'s.
//!
//! Like every module of `memory`, this one knows nothing of acceleration structures beyond the
//! size of the prefix that identifies one ([`STRUCTURE_PROBE`]).
use std::sync::{Arc, Mutex, OnceLock};

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
    /// Structures already resolved (a TLAS build looks each BLAS up once per instance; a ray
    /// query once per instance it enters). Every worker thread of a dispatch reads it per ray,
    /// so a lookup writes nothing shared: see [`Memo`].
    structures: Memo,
}

/// One resolved structure: (reference, address of its first byte, length).
type Entry = (u64, usize, usize);

/// Slots probed per level before a lookup or an insertion moves on to the next level.
const PROBE: usize = 8;

/// Slots of the first level (each further level has four times as many).
const FIRST_LEVEL: usize = 64;

/// An insert-only hash table of [`Entry`]s whose lookups only read: levels of write-once slots,
/// each level probed linearly over a window of [`PROBE`] slots from the reference's hash. A
/// slot once set never changes, so an insertion takes the first empty slot of its window
/// (`OnceLock::get_or_init`: two threads inserting the same reference meet in the same slot)
/// and moves to the next level only when the window is full. Hence a lookup that finds an
/// empty slot in the window knows the reference is in no level at all.
struct Memo {
    slots: Box<[OnceLock<Entry>]>,
    next: OnceLock<Box<Memo>>,
}

impl Memo {
    fn new(size: usize) -> Memo {
        Memo { slots: (0..size).map(|_| OnceLock::new()).collect(), next: OnceLock::new() }
    }

    fn window(&self, reference: u64) -> impl Iterator<Item = &OnceLock<Entry>> {
        // Structures are 256-byte aligned: a multiplicative hash spreads their addresses.
        let start = (reference.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 32) as usize;
        let mask = self.slots.len() - 1;
        (0..PROBE).map(move |k| &self.slots[(start + k) & mask])
    }

    fn get(&self, reference: u64) -> Option<Entry> {
        for slot in self.window(reference) {
            match slot.get() {
                Some(e) if e.0 == reference => return Some(*e),
                Some(_) => {}
                None => return None,
            }
        }
        self.next.get()?.get(reference)
    }

    /// Records `entry` unless its reference already is; returns the recorded entry.
    fn insert(&self, entry: Entry) -> Entry {
        for slot in self.window(entry.0) {
            let e = *slot.get_or_init(|| entry);
            if e.0 == entry.0 {
                return e;
            }
        }
        self.next.get_or_init(|| Box::new(Memo::new(self.slots.len() * 4))).insert(entry)
    }
}

impl<'a> DeviceMemoryView<'a> {
    pub fn new(space: &'a AddressSpace) -> Self {
        DeviceMemoryView { space, pins: Mutex::new(Vec::new()), structures: Memo::new(FIRST_LEVEL) }
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
    /// acceleration structure's extent as far as memory knows), looked up once per address:
    /// later lookups read the memo and write nothing shared.
    pub fn structure(&self, reference: u64) -> Option<&[u8]> {
        let (_, ptr, len) = match self.structures.get(reference) {
            Some(e) => e,
            None => {
                let r = self.space.resolve(reference, STRUCTURE_PROBE).ok()?;
                let len = r.buffer.size - r.offset;
                let s = self.pinned_slice(r.buffer, r.offset, len)?;
                // Two threads may resolve the same reference at once: both slices are pinned,
                // the memo keeps the first.
                self.structures.insert((reference, s.as_ptr() as usize, s.len()))
            }
        };
        // SAFETY: every entry of the memo was recorded above from a slice whose buffer is pinned
        // in `self.pins` for the view's lifetime, so it outlives the returned borrow of `self`.
        Some(unsafe { std::slice::from_raw_parts(ptr as *const u8, len) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memo_keeps_the_first_entry_per_reference_across_levels() {
        let m = Memo::new(4);
        // 4-slot levels with 8-slot windows: later references spill into further levels.
        let entries: Vec<Entry> = (0..300u64).map(|k| (0x1000 + 256 * k, k as usize, k as usize + 1)).collect();
        for &e in &entries {
            assert_eq!(m.insert(e), e);
        }
        for &e in &entries {
            assert_eq!(m.get(e.0), Some(e));
            assert_eq!(m.insert((e.0, 7, 7)), e, "a second insertion keeps the first entry");
        }
        assert_eq!(m.get(0x1000 + 256 * 300), None);
        assert_eq!(m.get(0x1001), None);
    }

    #[test]
    fn memo_is_consistent_under_concurrent_insertion() {
        let m = Memo::new(FIRST_LEVEL);
        std::thread::scope(|s| {
            for t in 0..4usize {
                let m = &m;
                s.spawn(move || {
                    for k in 0..500u64 {
                        let e = m.insert((256 * (k + 1), t, k as usize));
                        assert_eq!(m.get(256 * (k + 1)), Some(e));
                    }
                });
            }
        });
        for k in 0..500u64 {
            assert_eq!(m.get(256 * (k + 1)).map(|e| e.2), Some(k as usize));
        }
    }
}

//! Borrowed, shared views of device memory: byte slices whose lifetime is tied to a pinned
//! buffer, and [`DeviceMemoryView`], which follows device addresses (the runtime adapts it to
//! the acceleration-structure library's `DeviceView`). Writable views are `region`'s.
//!
//! Like every module of `memory`, this one knows nothing of acceleration structures beyond the
//! size of the prefix that identifies one ([`STRUCTURE_PROBE`]).
use std::cell::RefCell;
use std::sync::atomic::{AtomicU64, Ordering};
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
    /// Distinguishes this view's entries in the per-thread [`Spans`] (never reused).
    id: u64,
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

/// A buffer a thread resolved through a view: the view's id, the buffer's device range
/// [start, end), the host address of its first byte and its backing memory range (identity,
/// offset of its first byte).
#[derive(Clone, Copy, Default)]
struct Span {
    view: u64,
    start: u64,
    end: u64,
    host: usize,
    memory: (usize, u64),
}

/// Slots of [`Spans`]: a command reads a handful of buffers (records, indices, vertices,
/// templates) over and over.
const SPANS: usize = 8;

/// The buffers this thread resolved most recently, round robin. Resolving an address takes the
/// address space's lock, the memory's buffer list lock, the view's pin lock and three shared
/// reference counts: per read, on every worker at once, that serialises a wide pool (the
/// cluster commands read a few buffers thousands of times). A read inside a remembered buffer
/// touches nothing shared.
struct Spans {
    slots: [Span; SPANS],
    next: usize,
}

thread_local! {
    static RECENT: RefCell<Spans> = const { RefCell::new(Spans { slots: [Span { view: 0, start: 0, end: 0, host: 0, memory: (0, 0) }; SPANS], next: 0 }) };
}

/// Ids of views; 0 marks an empty slot of [`Spans`].
static NEXT_VIEW: AtomicU64 = AtomicU64::new(1);

impl<'a> DeviceMemoryView<'a> {
    pub fn new(space: &'a AddressSpace) -> Self {
        let id = NEXT_VIEW.fetch_add(1, Ordering::Relaxed);
        DeviceMemoryView { space, id, pins: Mutex::new(Vec::new()), structures: Memo::new(FIRST_LEVEL) }
    }

    /// The remembered buffer of this view that holds the whole of [address, address + len).
    fn recent(&self, address: u64, len: u64) -> Option<Span> {
        let end = address.checked_add(len)?;
        RECENT.with(|r| r.borrow().slots.iter().find(|s| s.view == self.id && s.start <= address && address < s.end && end <= s.end).copied())
    }

    /// Resolves `[address, address + len)` the slow way, pins its buffer and, where every read
    /// inside that buffer resolves to it, remembers it for this thread.
    fn resolve_span(&self, address: u64, len: u64) -> Option<Span> {
        let r = self.space.resolve(address, len).ok()?;
        let start = r.buffer.device_address()?;
        let (memory, base) = r.buffer.memory().map(|(m, o)| (Arc::as_ptr(m) as usize, o))?;
        let exclusive = Self::first_of_its_range(&r.buffer);
        let size = r.buffer.size;
        let whole = self.pinned_slice(r.buffer, 0, size)?;
        let span = Span { view: self.id, start, end: start + size, host: whole.as_ptr() as usize, memory: (memory, base) };
        if exclusive && size > 0 {
            RECENT.with(|c| {
                let mut c = c.borrow_mut();
                let k = c.next;
                c.slots[k] = span;
                c.next = (k + 1) % SPANS;
            });
        }
        Some(span)
    }

    /// Whether no buffer bound before `buffer` overlaps it: then resolving any range inside it
    /// finds `buffer` (resolution takes the first buffer in bind order), so a remembered span
    /// answers exactly as resolution would.
    fn first_of_its_range(buffer: &Arc<Buffer>) -> bool {
        let (Some((m, _)), Some(start)) = (buffer.memory(), buffer.device_address()) else { return false };
        let end = start + buffer.size;
        for b in m.bound_buffers() {
            if Arc::ptr_eq(&b, buffer) {
                return true;
            }
            if b.device_address().is_some_and(|s| s < end && start < s + b.size) {
                return false;
            }
        }
        false
    }

    /// `len` bytes at `offset` of the buffer `span` describes (pinned in `self.pins`).
    fn span_bytes(&self, span: &Span, address: u64, len: u64) -> &[u8] {
        let offset = (address - span.start) as usize;
        // SAFETY: `span` was recorded from a whole-buffer slice whose buffer is pinned in
        // `self.pins` until the view is dropped (its id is this view's, and ids are never
        // reused), and every caller passes a range inside that buffer (`recent` checked it, or
        // resolution found it there).
        unsafe { std::slice::from_raw_parts((span.host + offset) as *const u8, len as usize) }
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
        if let Some(s) = self.recent(address, len) {
            return Some(self.span_bytes(&s, address, len));
        }
        let s = self.resolve_span(address, len)?;
        Some(self.span_bytes(&s, address, len))
    }

    /// The backing memory range (identity, start, end) of the whole buffer that holds
    /// `address`, as `Buffer::memory_range` gives it, for overlap checks between regions.
    pub fn buffer_memory(&self, address: u64) -> Option<(usize, u64, u64)> {
        let s = match self.recent(address, 1) {
            Some(s) => s,
            None => self.resolve_span(address, 1)?,
        };
        Some((s.memory.0, s.memory.1, s.memory.1 + (s.end - s.start)))
    }

    /// The bytes from device address `reference` to the end of the buffer holding it (an
    /// acceleration structure's extent as far as memory knows), looked up once per address:
    /// later lookups read the memo and write nothing shared.
    pub fn structure(&self, reference: u64) -> Option<&[u8]> {
        if let Some(s) = self.recent(reference, STRUCTURE_PROBE) {
            return Some(self.span_bytes(&s, reference, s.end - reference));
        }
        let (_, ptr, len) = match self.structures.get(reference) {
            Some(e) => e,
            None => {
                let span = self.resolve_span(reference, STRUCTURE_PROBE)?;
                let s = self.span_bytes(&span, reference, span.end - reference);
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

    fn buffer(memory: &Arc<super::super::Memory>, offset: u64, size: u64) -> Arc<Buffer> {
        let b = Arc::new(Buffer::new(size, ash::vk::BufferUsageFlags::STORAGE_BUFFER, ash::vk::BufferCreateFlags::empty()));
        b.bind(memory.clone(), offset).expect("bind");
        b
    }

    /// What a view answers equals what resolution gives, read twice (the second read is served
    /// from the thread's remembered buffers where that is exact), on several threads.
    #[test]
    fn remembered_buffers_answer_as_resolution_does() {
        let space = AddressSpace::new(1 << 24);
        let m = space.allocate(1 << 16, true, None).expect("allocate");
        let bytes: Vec<u8> = (0..1u32 << 16).map(|i| (i * 7 + i / 251) as u8).collect();
        m.write(0, &bytes).expect("write");
        // `small` is bound first and lies inside `large`: resolution takes `small` for ranges
        // it holds, so `large` must never be remembered; `alone` overlaps nothing.
        let small = buffer(&m, 4096, 4096);
        let large = buffer(&m, 0, 32768);
        let alone = buffer(&m, 40960, 8192);
        let base = m.address;
        let probes: Vec<(u64, u64)> = [(0, 16), (4096, 16), (8000, 192), (8192, 16), (100, 4000), (4000, 200), (32760, 8), (32760, 16), (40960, 64), (49100, 52), (49100, 53), (45000, 100)]
            .iter()
            .map(|&(o, n)| (base + o, n))
            .collect();
        let expect = |a: u64, n: u64| space.resolve(a, n).ok().map(|r| (r.buffer.device_address().unwrap_or(0), r.buffer.size));
        let view = DeviceMemoryView::new(&space);
        std::thread::scope(|s| {
            for _ in 0..3 {
                s.spawn(|| {
                    for _ in 0..2 {
                        for &(a, n) in &probes {
                            let want = expect(a, n);
                            let got = view.bytes(a, n);
                            assert_eq!(got.is_some(), want.is_some(), "bytes at {a:#x}+{n}");
                            if let Some(g) = got {
                                assert_eq!(g, &bytes[(a - base) as usize..][..n as usize]);
                            }
                            let extent = view.structure(a).map(|s| s.len() as u64);
                            assert_eq!(extent, expect(a, STRUCTURE_PROBE).map(|(start, size)| start + size - a), "structure at {a:#x}");
                        }
                    }
                });
            }
        });
        drop((small, large, alone));
    }

    /// A buffer remembered by one view is not used by the next: after the memory is freed, a
    /// new view reads nothing there.
    #[test]
    fn remembered_buffers_belong_to_their_view() {
        let space = AddressSpace::new(1 << 24);
        let m = space.allocate(8192, true, None).expect("allocate");
        let _b = buffer(&m, 0, 8192);
        let a = m.address + 64;
        {
            let view = DeviceMemoryView::new(&space);
            assert!(view.bytes(a, 8).is_some());
            assert!(view.bytes(a, 8).is_some());
        }
        space.free(&m);
        let view = DeviceMemoryView::new(&space);
        assert!(view.bytes(a, 8).is_none());
        assert!(view.buffer_memory(a).is_none());
    }

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

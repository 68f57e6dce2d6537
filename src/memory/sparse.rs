//! Sparse binding of buffers, the memory side: the range of a sparse buffer and the binding of
//! its pages to pages of memory objects.
//!
//! A sparse buffer is bound once to a range of its own ([`AddressSpace::reserve_sparse`]): an
//! allocation with a device address and a host mapping, whose pages start as zero pages. Binding
//! a page maps the bytes of a memory object there a second time, so the buffer and the memory
//! are the same bytes (writes through either show through the other) and every access path of
//! the parent module (reads, writes, views, device addresses) works unchanged, contiguous across
//! pages. Only shareable memory ([`AddressSpace::allocate_shareable`], a memfd) can be bound.
//! Unbinding maps fresh zero pages: an unbound page reads as zero, never faults, and what is
//! written to it reaches no memory.
//!
//! This module keeps the page table and does the checks; the mappings are `backing`'s. It is
//! the layer under `vkQueueBindSparse` (docs/ROBUSTNESS.md, section 4).
use std::sync::{Arc, Mutex};

use super::{AddressSpace, AllocError, Memory};

/// The sparse page: alignment and granularity of sparse buffers and of their bindings.
pub const SPARSE_PAGE: u64 = 64 << 10;

/// What backs an allocation.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(super) enum Kind {
    Ordinary,
    /// Can be bound to sparse buffers (a memfd).
    Shareable,
    /// The range of a sparse buffer.
    SparseRange,
}

/// What each page of a sparse range is bound to: the memory and the byte offset in it. The
/// `Arc` keeps the bound memory's bytes (and its memfd) alive while they are mapped here.
pub(super) struct Pages {
    bound: Mutex<Vec<Option<Binding>>>,
}

/// One bound page: the memory and the byte offset in it.
type Binding = (Arc<Memory>, u64);

impl Pages {
    pub(super) fn new(size: u64) -> Pages {
        Pages { bound: Mutex::new(vec![None; size.div_ceil(SPARSE_PAGE) as usize]) }
    }
}

/// Why a sparse bind was refused.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum SparseError {
    /// The memory bound into is not the range of a sparse buffer.
    NotSparse,
    /// An offset or size is not a multiple of [`SPARSE_PAGE`].
    Misaligned,
    /// The range runs past the buffer's range or the memory.
    Range,
    /// The memory was not allocated shareable, or was freed.
    Unbindable,
    /// The system refused the mapping.
    Host,
}

impl AddressSpace {
    /// Memory that sparse buffers can bind (zeroed, shareable).
    pub fn allocate_shareable(&self, size: u64, device_address_flag: bool) -> Result<Arc<Memory>, AllocError> {
        self.allocate_shareable_with(size, device_address_flag, false, None)
    }

    /// [`AddressSpace::allocate_shareable`] with the capture/replay options of
    /// [`AddressSpace::allocate_with`].
    pub fn allocate_shareable_with(
        &self,
        size: u64,
        device_address_flag: bool,
        capture_replay: bool,
        capture_address: Option<u64>,
    ) -> Result<Arc<Memory>, AllocError> {
        self.allocate_kind(size, device_address_flag, capture_replay, capture_address, Kind::Shareable)
    }

    /// The range of a sparse buffer of `size` bytes (rounded up to [`SPARSE_PAGE`]), every page
    /// unbound. It counts against the heap like an allocation: Arbor's emulated heap is host
    /// memory, and the range is host address space the buffer holds.
    pub fn reserve_sparse(&self, size: u64) -> Result<Arc<Memory>, AllocError> {
        let size = size.max(1).checked_next_multiple_of(SPARSE_PAGE).ok_or(AllocError::OutOfDeviceMemory)?;
        self.allocate_kind(size, true, false, None, Kind::SparseRange)
    }
}

impl Memory {
    /// Whether this is the range of a sparse buffer.
    pub fn is_sparse(&self) -> bool {
        self.sparse.is_some()
    }

    /// Whether this memory can be bound to sparse buffers (allocated shareable).
    pub fn is_shareable(&self) -> bool {
        self.backing.is_shared()
    }

    /// Bind `[offset, offset + size)` of this sparse range to `target` (memory, offset in it),
    /// or unbind it (`None`). All offsets and the size are multiples of [`SPARSE_PAGE`].
    pub fn bind_sparse(&self, offset: u64, size: u64, target: Option<(&Arc<Memory>, u64)>) -> Result<(), SparseError> {
        let pages = self.sparse.as_ref().ok_or(SparseError::NotSparse)?;
        let aligned = |v: u64| v.is_multiple_of(SPARSE_PAGE);
        if !aligned(offset) || !aligned(size) || target.is_some_and(|(_, o)| !aligned(o)) {
            return Err(SparseError::Misaligned);
        }
        let end = offset.checked_add(size).ok_or(SparseError::Range)?;
        if end > self.committed_size() {
            return Err(SparseError::Range);
        }
        if let Some((m, o)) = target {
            if m.is_freed() || m.is_sparse() {
                return Err(SparseError::Unbindable);
            }
            if o.checked_add(size).is_none_or(|e| e > m.committed_size()) {
                return Err(SparseError::Range);
            }
        }
        let mut bound = pages.bound.lock().unwrap_or_else(|e| e.into_inner());
        let source = target.map(|(m, o)| (&m.backing, o as usize));
        if size > 0 && !self.backing.remap(offset as usize, size as usize, source) {
            return Err(if target.is_some_and(|(m, _)| !m.backing.is_shared()) { SparseError::Unbindable } else { SparseError::Host });
        }
        let first = (offset / SPARSE_PAGE) as usize;
        for (i, page) in bound.iter_mut().enumerate().skip(first).take((size / SPARSE_PAGE) as usize) {
            *page = target.map(|(m, o)| (m.clone(), o + (i - first) as u64 * SPARSE_PAGE));
        }
        Ok(())
    }

    /// Whether every page of `[offset, offset + len)` of this sparse range is bound (true for
    /// memory that is not a sparse range).
    pub fn is_bound(&self, offset: u64, len: u64) -> bool {
        let Some(pages) = &self.sparse else { return true };
        if len == 0 {
            return true;
        }
        let bound = pages.bound.lock().unwrap_or_else(|e| e.into_inner());
        let (first, last) = ((offset / SPARSE_PAGE) as usize, ((offset + len - 1) / SPARSE_PAGE) as usize);
        (first..=last).all(|p| bound.get(p).is_some_and(Option::is_some))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bound_pages_alias_the_memory_and_unbound_pages_read_zero() {
        let space = AddressSpace::new(1 << 26);
        let memory = space.allocate_shareable(2 * SPARSE_PAGE, true).unwrap();
        memory.write(0, &[7u8; 16]).unwrap();
        let range = space.reserve_sparse(3 * SPARSE_PAGE - 100).unwrap();
        assert_eq!(range.committed_size(), 3 * SPARSE_PAGE);
        assert!(range.is_sparse() && !range.is_bound(0, 1));
        // Page 1 of the range onto page 0 of the memory: the same bytes, both ways.
        range.bind_sparse(SPARSE_PAGE, SPARSE_PAGE, Some((&memory, 0))).unwrap();
        assert!(range.is_bound(SPARSE_PAGE, SPARSE_PAGE) && !range.is_bound(0, SPARSE_PAGE + 1));
        let mut out = [0u8; 16];
        range.read(SPARSE_PAGE, &mut out).unwrap();
        assert_eq!(out, [7u8; 16]);
        range.write(SPARSE_PAGE + 8, &[9u8; 4]).unwrap();
        memory.read(8, &mut out[..4]).unwrap();
        assert_eq!(out[..4], [9u8; 4]);
        // Unbound pages: zero, and what is written there reaches no memory.
        range.write(0, &[5u8; 16]).unwrap();
        memory.read(0, &mut out[..8]).unwrap();
        assert_eq!(out[..8], [7u8; 8]);
        range.read(2 * SPARSE_PAGE, &mut out).unwrap();
        assert_eq!(out, [0u8; 16]);
        // Unbinding: zero again, the memory keeps its bytes.
        range.bind_sparse(SPARSE_PAGE, SPARSE_PAGE, None).unwrap();
        range.read(SPARSE_PAGE, &mut out).unwrap();
        assert_eq!(out, [0u8; 16]);
        memory.read(0, &mut out[..8]).unwrap();
        assert_eq!(out[..8], [7u8; 8]);
    }

    #[test]
    fn binds_are_checked() {
        let space = AddressSpace::new(1 << 26);
        let shareable = space.allocate_shareable(SPARSE_PAGE, true).unwrap();
        let ordinary = space.allocate(4 * SPARSE_PAGE, true, None).unwrap();
        let range = space.reserve_sparse(2 * SPARSE_PAGE).unwrap();
        assert_eq!(ordinary.bind_sparse(0, SPARSE_PAGE, None), Err(SparseError::NotSparse));
        assert_eq!(range.bind_sparse(4096, SPARSE_PAGE, Some((&shareable, 0))), Err(SparseError::Misaligned));
        assert_eq!(range.bind_sparse(SPARSE_PAGE, 2 * SPARSE_PAGE, Some((&shareable, 0))), Err(SparseError::Range));
        assert_eq!(range.bind_sparse(0, 2 * SPARSE_PAGE, Some((&shareable, 0))), Err(SparseError::Range), "past the memory");
        assert_eq!(range.bind_sparse(0, SPARSE_PAGE, Some((&ordinary, 0))), Err(SparseError::Unbindable));
        space.free(&shareable);
        assert_eq!(range.bind_sparse(0, SPARSE_PAGE, Some((&shareable, 0))), Err(SparseError::Unbindable));
        assert!(!range.is_bound(0, 1));
    }

    #[test]
    fn a_bound_memory_outlives_its_handle_while_mapped() {
        let space = AddressSpace::new(1 << 26);
        let range = space.reserve_sparse(SPARSE_PAGE).unwrap();
        {
            let memory = space.allocate_shareable(SPARSE_PAGE, true).unwrap();
            memory.write(0, &[3u8; 4]).unwrap();
            range.bind_sparse(0, SPARSE_PAGE, Some((&memory, 0))).unwrap();
        }
        let mut out = [0u8; 4];
        range.read(0, &mut out).unwrap();
        assert_eq!(out, [3u8; 4]);
    }
}

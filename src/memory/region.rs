//! Writable regions handed to the acceleration-structure library, and the application host
//! memory that host commands name by pointer.
//!
//! A build writes its destination and its scratch through `&mut [u8]` for as long as it runs,
//! on several pool threads at once, and a command runs several builds side by side. This module
//! owns the argument that makes those views sound, so that callers (the runtime) stay free of
//! `unsafe`:
//!
//! - a [`Region`] is a checked byte range: inside a live allocation it keeps alive (device
//!   memory), or inside host memory the application vouched for ([`HostMemory`]);
//! - a [`WriteSet`] hands out [`Claim`]s, each owning some regions, and refuses any region that
//!   overlaps one it has handed out before, comparing the host bytes the regions really cover.
//!   So the mutable views of all claims of one set are disjoint, and a claim lends them only
//!   through `&mut self`.
//!
//! What no type here can see is the rest of the world: another command, the application or a
//! shared view made by [`Buffer::bytes`](super::Buffer::bytes) touching the same bytes while a
//! claim lives. Those are excluded as for every device-memory access (the module docs of
//! `memory`): by the application's synchronisation obligations and, within one command, by the
//! aliasing checks the runtime makes (and reports with their VUIDs) before it claims anything.
//!
//! This module must not know what the bytes mean (no acceleration-structure types).
use std::marker::PhantomData;
use std::ptr::NonNull;
use std::sync::Arc;

use super::{AccessError, AddressSpace, Buffer, Memory};

/// Application host memory named by the host addresses of one host command
/// (`vkBuildAccelerationStructuresKHR`, the host copies): the proof, given once where the
/// pointers come in, that those addresses may be read and written.
pub struct HostMemory {
    /// Not Send or Sync by accident: the contract holds for one command, which may run on other
    /// threads (the pool, joiners of a deferred operation); see the impls below.
    _contract: PhantomData<*const u8>,
}

// SAFETY: `HostMemory` holds no data; the contract of `HostMemory::new` covers the command
// wherever it runs (the application may not touch the memory until the command completes,
// whichever thread completes it).
unsafe impl Send for HostMemory {}
// SAFETY: as above; shared use only makes shared views, and mutable views go through
// `WriteSet`, which keeps them disjoint.
unsafe impl Sync for HostMemory {}

impl HostMemory {
    /// # Safety
    /// For as long as the returned value lives, every non-zero host address later passed to
    /// [`HostMemory::bytes`] or [`HostMemory::region`] must be valid for reads (and, for
    /// `region`, writes) of the length passed with it, and nothing else may write those bytes
    /// (nor, for `region`, read them). For a host command this is the application's obligation
    /// (the host-address rules of VK_KHR_acceleration_structure, e.g.
    /// VUID-vkBuildAccelerationStructuresKHR-pInfos-03725), given that the lengths are the ones
    /// the spec derives from the command's parameters.
    pub unsafe fn new() -> HostMemory {
        HostMemory { _contract: PhantomData }
    }

    /// The `len` bytes at host address `address`, or None for a null address.
    pub fn bytes(&self, address: u64, len: u64) -> Option<&[u8]> {
        let len = usize::try_from(len).ok()?;
        let ptr = NonNull::new(address as usize as *mut u8)?;
        // SAFETY: `HostMemory::new`'s contract: the application vouched that these bytes are
        // readable and not written while this value (hence the borrow) lives.
        Some(unsafe { std::slice::from_raw_parts(ptr.as_ptr(), len) })
    }

    /// The `len` bytes at host address `address` as a region to write, or None for a null
    /// address.
    pub fn region(&self, address: u64, len: u64) -> Option<Region<'_>> {
        let len = usize::try_from(len).ok()?;
        let ptr = NonNull::new(address as usize as *mut u8)?;
        Some(Region { ptr, len, _pin: None, _host: PhantomData })
    }
}

/// A checked byte range that may be written: part of a live allocation (which it keeps alive)
/// or of host memory vouched for by a [`HostMemory`] (which it borrows).
pub struct Region<'a> {
    ptr: NonNull<u8>,
    len: usize,
    /// The allocation, kept alive while the region is (device memory only).
    _pin: Option<Arc<Memory>>,
    _host: PhantomData<&'a HostMemory>,
}

impl Region<'static> {
    /// An empty region (nothing to write; overlaps nothing).
    pub fn empty() -> Region<'static> {
        Region { ptr: NonNull::dangling(), len: 0, _pin: None, _host: PhantomData }
    }

    /// `[offset, offset + len)` of `buffer`, which must be bound to live memory that holds it.
    pub fn of_buffer(buffer: &Buffer, offset: u64, len: u64) -> Result<Region<'static>, AccessError> {
        let (memory, at) = buffer.locate(offset, len)?;
        memory.check(at, len)?;
        // SAFETY: `check` proved `at + len <= memory.size`, so `at` is inside the allocation
        // (or at its end for an empty range) and fits in usize (the backing is that large).
        let ptr = unsafe { NonNull::new_unchecked(memory.backing.ptr.as_ptr().add(at as usize)) };
        Ok(Region { ptr, len: len as usize, _pin: Some(memory.clone()), _host: PhantomData })
    }

    /// The device-address range `[address, address + len)`, which must lie inside one live
    /// buffer.
    pub fn of_device(space: &AddressSpace, address: u64, len: u64) -> Result<Region<'static>, AccessError> {
        let r = space.resolve(address, len)?;
        Region::of_buffer(&r.buffer, r.offset, len)
    }
}

impl Region<'_> {
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Host bytes covered, as [start, end).
    fn span(&self) -> (usize, usize) {
        let start = self.ptr.as_ptr() as usize;
        (start, start.saturating_add(self.len))
    }

    /// Writes the region alone, through a view that ends with `f` (a one-off write: a
    /// serialized structure, a copy's destination).
    pub fn write_with<R>(self, f: impl FnOnce(&mut [u8]) -> R) -> R {
        let mut claim = Claim { regions: [self] };
        let [bytes] = claim.slices();
        f(bytes)
    }
}

/// The regions were refused: one overlaps another of the same claim or of an earlier one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Overlap;

/// Hands out claims whose regions are pairwise disjoint: all writable regions of one command.
#[derive(Default)]
pub struct WriteSet {
    /// Host byte ranges [start, end) of every non-empty region claimed so far.
    claimed: Vec<(usize, usize)>,
}

impl WriteSet {
    pub fn new() -> WriteSet {
        WriteSet::default()
    }

    /// Claims `regions` together (a build's destination and scratch), or none of them when one
    /// overlaps another or a region claimed before.
    pub fn claim<'a, const N: usize>(&mut self, regions: [Region<'a>; N]) -> Result<Claim<'a, N>, Overlap> {
        let overlaps = |a: (usize, usize), b: (usize, usize)| a.0 < b.1 && b.0 < a.1;
        let spans: Vec<(usize, usize)> = regions.iter().filter(|r| !r.is_empty()).map(Region::span).collect();
        for (i, &s) in spans.iter().enumerate() {
            if spans[..i].iter().chain(&self.claimed).any(|&c| overlaps(s, c)) {
                return Err(Overlap);
            }
        }
        self.claimed.extend(spans);
        Ok(Claim { regions })
    }
}

/// Regions claimed together from a [`WriteSet`], writable through `&mut self`.
pub struct Claim<'a, const N: usize> {
    regions: [Region<'a>; N],
}

// SAFETY: a claim's regions are disjoint from every other claim of its set (`WriteSet::claim`),
// device regions keep their allocation alive, and host regions are covered by `HostMemory`'s
// contract on whichever thread the command runs; so a claim may move to a pool thread.
unsafe impl<const N: usize> Send for Claim<'_, N> {}

impl<const N: usize> Claim<'_, N> {
    /// The claimed regions' bytes, in the order they were claimed.
    pub fn slices(&mut self) -> [&mut [u8]; N] {
        // SAFETY: each region is in bounds of live memory (`Region`'s constructors; the pin or
        // the `HostMemory` borrow keeps it so for the region's lifetime, which outlives this
        // borrow). The regions are disjoint from each other and from every other claim of the
        // set (`WriteSet::claim`), and the slices borrow `self` mutably, so no second view of
        // the same bytes is made through this claim while they live.
        self.regions.each_mut().map(|r| unsafe { std::slice::from_raw_parts_mut(r.ptr.as_ptr(), r.len) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ash::vk;

    fn buffer(space: &AddressSpace, size: u64) -> Arc<Buffer> {
        let memory = space.allocate(size, true, None).unwrap();
        let b = Arc::new(Buffer::new(size, vk::BufferUsageFlags::STORAGE_BUFFER, vk::BufferCreateFlags::empty()));
        b.bind(memory, 0).unwrap();
        b
    }

    #[test]
    fn claims_of_one_set_never_overlap() {
        let space = AddressSpace::new(1 << 24);
        let b = buffer(&space, 4096);
        let mut set = WriteSet::new();
        let r = |o, n| Region::of_buffer(&b, o, n).unwrap();
        let mut first = set.claim([r(0, 1024), r(1024, 1024)]).unwrap();
        assert_eq!(set.claim([r(2048, 16), r(2056, 16)]).err(), Some(Overlap), "overlap inside one claim");
        assert_eq!(set.claim([r(1000, 100)]).err(), Some(Overlap), "overlap with an earlier claim");
        let mut second = set.claim([r(2048, 2048), Region::empty()]).unwrap();
        let [a, s] = first.slices();
        a.fill(1);
        s.fill(2);
        let [c, e] = second.slices();
        c.fill(3);
        assert!(e.is_empty());
        let mut out = vec![0u8; 4096];
        b.read(0, &mut out).unwrap();
        assert!(out[..1024].iter().all(|&x| x == 1) && out[1024..2048].iter().all(|&x| x == 2) && out[2048..].iter().all(|&x| x == 3));
    }

    #[test]
    fn regions_are_checked_and_keep_their_memory_alive() {
        let space = AddressSpace::new(1 << 24);
        let b = buffer(&space, 256);
        assert!(Region::of_buffer(&b, 200, 100).is_err(), "past the buffer");
        let address = b.device_address().unwrap();
        assert!(Region::of_device(&space, address + (1 << 30), 4).is_err(), "unmapped");
        let region = Region::of_device(&space, address + 16, 16).unwrap();
        let (memory, _) = b.memory().unwrap();
        space.free(memory);
        drop(b);
        // The region still owns its bytes after the memory was freed and the buffer dropped.
        region.write_with(|bytes| bytes.fill(7));
    }

    #[test]
    fn host_regions_cover_the_application_s_bytes() {
        let mut data = vec![0u8; 64];
        let address = data.as_mut_ptr() as u64;
        // SAFETY: `data` lives and is not otherwise used until `host` is dropped.
        let host = unsafe { HostMemory::new() };
        assert!(host.bytes(0, 4).is_none() && host.region(0, 4).is_none(), "a null address names nothing");
        let mut set = WriteSet::new();
        let mut claim = set.claim([host.region(address, 32).unwrap()]).unwrap();
        assert!(set.claim([host.region(address + 16, 32).unwrap()]).is_err());
        claim.slices()[0].fill(9);
        drop(claim);
        assert_eq!(host.bytes(address, 33).unwrap()[31..], [9, 0]);
        let _ = host; // the contract ends here; `data` is the test's again
        assert_eq!(data[0], 9);
    }
}

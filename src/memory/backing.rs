//! The host bytes behind each allocation: allocated zeroed and page aligned, large ones as
//! their own mapping advised for huge pages, freed when the allocation's last reference goes;
//! and, for sparse binding, shareable bytes (a memfd) and reserved ranges whose pages can be
//! remapped onto them.
//!
//! This module owns only the bytes' lifetime; reads, writes and views are the parent module's.
use std::ptr::NonNull;

use super::ALLOCATION_ALIGNMENT;

/// Host backing of one allocation.
///
/// Allocated through the allocator's zeroing path with 16-byte alignment (calloc: large blocks
/// come straight from mmap, zero and uncommitted until touched, so a big allocation costs RAM
/// only as it is used), over-sized by one page so that `ptr` can be page aligned: host pointers
/// then have the alignment of the device addresses they back, up to 4096.
///
/// On Linux, allocations of at least [`HUGE_MAPPING_MIN`] are their own anonymous mapping
/// (page aligned, zero, uncommitted until touched, as above) advised for transparent huge
/// pages: a build's scratch and destination are tens of megabytes read and written in
/// patterns the TLB follows badly with 4 KiB pages (dragon, 16 threads on the 16-core machine:
/// builds through the API 1–5 % faster, recorded with commit 743e1e6 of 2026-11-22). Where the
/// system does not grant huge pages the advice changes nothing.
pub(super) struct Backing {
    /// Page-aligned start of the bytes.
    pub(super) ptr: NonNull<u8>,
    /// What the allocator returned (the mapping's start for a mapped backing).
    base: NonNull<u8>,
    /// The allocator's layout, or None for a mapping of `mapped` bytes.
    layout: Option<std::alloc::Layout>,
    #[cfg_attr(not(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64"))), allow(dead_code))]
    mapped: usize,
    /// The memfd behind a shareable backing ([`Backing::new_shared`]), or -1.
    #[cfg_attr(not(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64"))), allow(dead_code))]
    fd: i32,
}

/// Allocations from this size on get their own mapping advised for huge pages (Linux on
/// x86-64 and AArch64).
pub const HUGE_MAPPING_MIN: usize = 2 << 20;

/// Linux's mmap/madvise constants as on x86-64 and AArch64 (some other architectures number
/// them differently, so they keep the allocator path).
#[cfg(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64")))]
mod sys {
    use std::ffi::{c_char, c_int, c_long, c_uint, c_void};
    pub const PROT_READ: c_int = 1;
    pub const PROT_WRITE: c_int = 2;
    pub const MAP_SHARED: c_int = 1;
    pub const MAP_PRIVATE: c_int = 2;
    pub const MAP_FIXED: c_int = 0x10;
    pub const MAP_ANONYMOUS: c_int = 0x20;
    pub const MADV_HUGEPAGE: c_int = 14;
    pub const MFD_CLOEXEC: c_uint = 1;
    extern "C" {
        pub fn mmap(addr: *mut c_void, len: usize, prot: c_int, flags: c_int, fd: c_int, off: c_long) -> *mut c_void;
        pub fn munmap(addr: *mut c_void, len: usize) -> c_int;
        pub fn madvise(addr: *mut c_void, len: usize, advice: c_int) -> c_int;
        pub fn memfd_create(name: *const c_char, flags: c_uint) -> c_int;
        pub fn ftruncate(fd: c_int, length: c_long) -> c_int;
        pub fn close(fd: c_int) -> c_int;
    }
}

impl Backing {
    /// Zeroed bytes for `size` (a multiple of [`ALLOCATION_ALIGNMENT`]); None when the host
    /// allocator fails.
    pub(super) fn new(size: usize) -> Option<Backing> {
        #[cfg(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64")))]
        if size >= HUGE_MAPPING_MIN {
            // SAFETY: a fresh private anonymous mapping (no address hint, no file) touches no
            // existing memory; the kernel returns it zeroed and page aligned, or MAP_FAILED.
            let p = unsafe { sys::mmap(std::ptr::null_mut(), size, sys::PROT_READ | sys::PROT_WRITE, sys::MAP_PRIVATE | sys::MAP_ANONYMOUS, -1, 0) };
            if p as isize != -1 {
                // SAFETY: the range is exactly the mapping just made and owned here; the advice
                // only changes how the kernel backs it (never its contents), and failure
                // (huge pages disabled) leaves the mapping as it was.
                unsafe { sys::madvise(p, size, sys::MADV_HUGEPAGE) };
                let ptr = NonNull::new(p as *mut u8)?;
                return Some(Backing { ptr, base: ptr, layout: None, mapped: size, fd: -1 });
            }
        }
        let layout = std::alloc::Layout::from_size_align(size.checked_add(ALLOCATION_ALIGNMENT as usize)?, 16).ok()?;
        // SAFETY: layout has non-zero size.
        let base = NonNull::new(unsafe { std::alloc::alloc_zeroed(layout) })?;
        let pad = base.as_ptr().align_offset(ALLOCATION_ALIGNMENT as usize);
        // SAFETY: pad < ALLOCATION_ALIGNMENT, so ptr..ptr+size lies inside the block.
        let ptr = unsafe { NonNull::new_unchecked(base.as_ptr().add(pad)) };
        Some(Backing { ptr, base, layout: Some(layout), mapped: 0, fd: -1 })
    }

    /// Zeroed bytes that can be mapped a second time elsewhere (a memfd mapped shared): the
    /// memory that sparse buffers bind pages of (`sparse`). `size` is a multiple of the page
    /// size. None where the system has no memfd.
    #[cfg(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64")))]
    pub(super) fn new_shared(size: usize) -> Option<Backing> {
        // SAFETY: a NUL-terminated name; the call creates a new file descriptor or fails.
        let fd = unsafe { sys::memfd_create(c"arbor-memory".as_ptr(), sys::MFD_CLOEXEC) };
        if fd < 0 {
            return None;
        }
        // SAFETY: fd is the memfd just created and owned here; sizing it touches nothing else,
        // and a fresh shared mapping of it (no address hint) overlaps no existing memory.
        let p = unsafe {
            if sys::ftruncate(fd, size as std::ffi::c_long) != 0 {
                sys::close(fd);
                return None;
            }
            sys::mmap(std::ptr::null_mut(), size, sys::PROT_READ | sys::PROT_WRITE, sys::MAP_SHARED, fd, 0)
        };
        if p as isize == -1 {
            // SAFETY: the memfd owned here, closed once.
            unsafe { sys::close(fd) };
            return None;
        }
        let ptr = NonNull::new(p as *mut u8)?;
        Some(Backing { ptr, base: ptr, layout: None, mapped: size, fd })
    }

    #[cfg(not(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64"))))]
    pub(super) fn new_shared(_size: usize) -> Option<Backing> {
        None
    }

    /// Map `len` bytes at byte `at` of this backing (a mapped one: shared or large) onto the
    /// bytes at `offset` of `source` (a shared backing), or onto fresh zero pages (`None`).
    /// `at`, `offset` and `len` are multiples of the page size and in range (the caller checked).
    /// Returns false when the system refused (the old pages then stay).
    #[cfg(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64")))]
    pub(super) fn remap(&self, at: usize, len: usize, source: Option<(&Backing, usize)>) -> bool {
        if self.layout.is_some() || at + len > self.mapped || source.is_some_and(|(b, o)| b.fd < 0 || o + len > b.mapped) {
            return false;
        }
        // SAFETY: [at, at + len) lies inside this backing's own mapping (checked above), which
        // MAP_FIXED replaces in place; no Rust reference into device memory outlives a call
        // (module docs), so none sees the pages change. The source is a live memfd of at least
        // offset + len bytes.
        let p = unsafe {
            let addr = self.ptr.as_ptr().add(at).cast();
            let rw = sys::PROT_READ | sys::PROT_WRITE;
            match source {
                Some((b, offset)) => sys::mmap(addr, len, rw, sys::MAP_SHARED | sys::MAP_FIXED, b.fd, offset as std::ffi::c_long),
                None => sys::mmap(addr, len, rw, sys::MAP_PRIVATE | sys::MAP_ANONYMOUS | sys::MAP_FIXED, -1, 0),
            }
        };
        p as isize != -1
    }

    #[cfg(not(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64"))))]
    pub(super) fn remap(&self, _at: usize, _len: usize, _source: Option<(&Backing, usize)>) -> bool {
        false
    }

    /// Whether these bytes can be mapped a second time ([`Backing::new_shared`]).
    pub(super) fn is_shared(&self) -> bool {
        self.fd >= 0
    }

    /// Zeroed bytes as their own private mapping, without huge pages (the range a sparse
    /// buffer's pages are mapped into). None where mappings are not available.
    #[cfg(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64")))]
    pub(super) fn new_reserved(size: usize) -> Option<Backing> {
        // SAFETY: a fresh private anonymous mapping touches no existing memory.
        let p = unsafe { sys::mmap(std::ptr::null_mut(), size, sys::PROT_READ | sys::PROT_WRITE, sys::MAP_PRIVATE | sys::MAP_ANONYMOUS, -1, 0) };
        if p as isize == -1 {
            return None;
        }
        let ptr = NonNull::new(p as *mut u8)?;
        Some(Backing { ptr, base: ptr, layout: None, mapped: size, fd: -1 })
    }

    #[cfg(not(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64"))))]
    pub(super) fn new_reserved(_size: usize) -> Option<Backing> {
        None
    }
}

// SAFETY: the backing is plain bytes owned by the allocation; concurrent access follows the
// Vulkan synchronisation rules (see the docs of `memory`).
unsafe impl Send for Backing {}
// SAFETY: as above.
unsafe impl Sync for Backing {}

impl Drop for Backing {
    fn drop(&mut self) {
        match self.layout {
            // SAFETY: allocated with this layout in Backing::new.
            Some(layout) => unsafe { std::alloc::dealloc(self.base.as_ptr(), layout) },
            #[cfg(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64")))]
            // SAFETY: the mapping of `mapped` bytes made here, unmapped once (with whatever pages
            // were remapped into it), and its memfd, if any, closed once; no reference into it
            // outlives the backing.
            None => unsafe {
                sys::munmap(self.base.as_ptr().cast(), self.mapped);
                if self.fd >= 0 {
                    sys::close(self.fd);
                }
            },
            #[cfg(not(all(target_os = "linux", any(target_arch = "x86_64", target_arch = "aarch64"))))]
            None => {}
        }
    }
}

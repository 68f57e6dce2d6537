//! The emulated device: allocations, the device-address space, checked reads and writes.
//!
//! Every read and write of device memory by the driver goes through this module. Device
//! addresses are virtual: each allocation gets a range of the device's address space (aligned,
//! non-zero, with unmapped gaps between allocations, never a host pointer); a buffer's address is
//! its memory's base plus its bind offset. Resolving (address, length) finds the one live buffer
//! that contains the whole range, or says what is wrong. Allocations made for capture/replay
//! take addresses from a region of their own, so a replay can place them where they were
//! captured ([`AddressSpace::allocate_with`]). [`AddressSpace::with_range`],
//! [`AddressSpace::buffer_usage_at`] and [`AddressSpace::resolve_with_usage`] serve the
//! acceleration-structure code and its VUID checks (usage of the buffer containing a range).
//!
//! Concurrency: device memory is shared with the application (mapped pointers) and with queue
//! workers, exactly like GPU memory. Accesses are raw copies; the Vulkan synchronisation rules
//! (the application's obligation) make them race-free. No `&mut [u8]` over device memory
//! outlives the call that made it, except the writable regions a command claims for as long as
//! it runs ([`region`], which holds the argument for them).
//!
//! Submodules: `backing` (the host bytes of an allocation), [`image`] (image storage: texels
//! laid out linearly in the memory an image is bound to), [`view`] (shared views and reads
//! that follow device addresses), [`region`] (writable regions and application host memory).
//! This module imports nothing from the rest of the driver: what the bytes mean (acceleration
//! structures, commands) is for the layers above.
mod backing;
pub mod image;
pub mod region;
pub mod sparse;
pub mod view;

use backing::Backing;
pub use backing::HUGE_MAPPING_MIN;

use std::collections::BTreeMap;
use std::fmt;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock, Weak};

use ash::vk;

/// Alignment of every allocation's host backing and of its device address.
pub const ALLOCATION_ALIGNMENT: u64 = 4096;
/// Gap left unmapped between two allocations' device-address ranges (catches overruns).
const ADDRESS_GAP: u64 = 1 << 20;
/// First device address handed out (addresses are never 0 and never look like host pointers).
const ADDRESS_BASE: u64 = 0x0000_0100_0000_0000;
/// Allocations made for capture/replay (VK_MEMORY_ALLOCATE_DEVICE_ADDRESS_CAPTURE_REPLAY_BIT
/// without a requested address) take addresses from their own region, as the spec recommends,
/// so that a replay's ordinary allocations never take the addresses its captured ones need.
const REPLAY_BASE: u64 = 0x0000_4100_0000_0000;
/// Buffers are bound at offsets aligned to this (memory requirements alignment): keeps
/// acceleration-structure storage 256-aligned in device-address space.
pub const BUFFER_ALIGNMENT: u64 = 256;

/// Why a device-memory access was refused.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum AccessError {
    /// No live buffer with a device address contains the address.
    Unmapped { address: u64 },
    /// The range starts inside a buffer but runs past its end.
    OutOfBounds { address: u64, len: u64, buffer_address: u64, buffer_size: u64 },
    /// A buffer-relative range runs past the buffer's end.
    BufferRange { offset: u64, len: u64, size: u64 },
    /// The buffer has no memory bound.
    Unbound,
    /// The memory was freed.
    Freed,
    /// An atomic access of `size` bytes at an offset not aligned to its size.
    Misaligned { offset: u64, size: u64 },
}

impl fmt::Display for AccessError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            AccessError::Unmapped { address } => write!(f, "device address {address:#x} is not inside any live buffer"),
            AccessError::OutOfBounds { address, len, buffer_address, buffer_size } => write!(
                f,
                "range [{address:#x}, +{len}) runs past the end of the buffer at {buffer_address:#x} (size {buffer_size})"
            ),
            AccessError::BufferRange { offset, len, size } => {
                write!(f, "range [offset {offset}, +{len}) exceeds the buffer size {size}")
            }
            AccessError::Unbound => write!(f, "the buffer has no memory bound"),
            AccessError::Freed => write!(f, "the memory was freed"),
            AccessError::Misaligned { offset, size } => write!(f, "atomic access of {size} bytes at offset {offset} is not aligned to its size"),
        }
    }
}

/// One `VkDeviceMemory`.
pub struct Memory {
    backing: Backing,
    pub size: u64,
    /// Start of this allocation's device-address range.
    pub address: u64,
    /// Allocated with VK_MEMORY_ALLOCATE_DEVICE_ADDRESS_BIT.
    pub device_address_flag: bool,
    /// The current host mapping (offset, size in bytes), if mapped.
    mapping: Mutex<Option<(u64, u64)>>,
    freed: AtomicBool,
    /// Buffers bound to this memory (for address resolution).
    buffers: Mutex<Vec<Weak<Buffer>>>,
    /// For the range of a sparse buffer: what each page is bound to (`sparse`).
    sparse: Option<sparse::Pages>,
}

impl Memory {
    /// Host pointer to byte `offset` (for vkMapMemory). None past the end.
    pub fn host_ptr(&self, offset: u64) -> Option<*mut u8> {
        (offset <= self.size).then(|| {
            // SAFETY: offset <= size, inside (or one past) the allocation.
            unsafe { self.backing.ptr.as_ptr().add(offset as usize) }
        })
    }

    fn check(&self, offset: u64, len: u64) -> Result<(), AccessError> {
        if self.freed.load(Ordering::Acquire) {
            return Err(AccessError::Freed);
        }
        match offset.checked_add(len) {
            Some(end) if end <= self.size => Ok(()),
            _ => Err(AccessError::BufferRange { offset, len, size: self.size }),
        }
    }

    /// Copy out of the allocation.
    pub fn read(&self, offset: u64, out: &mut [u8]) -> Result<(), AccessError> {
        self.check(offset, out.len() as u64)?;
        // SAFETY: range checked above; raw copy (see module docs on concurrency).
        unsafe { std::ptr::copy(self.backing.ptr.as_ptr().add(offset as usize), out.as_mut_ptr(), out.len()) };
        Ok(())
    }

    /// Copy into the allocation.
    pub fn write(&self, offset: u64, data: &[u8]) -> Result<(), AccessError> {
        self.check(offset, data.len() as u64)?;
        // SAFETY: range checked above; raw copy (see module docs on concurrency).
        unsafe { std::ptr::copy(data.as_ptr(), self.backing.ptr.as_ptr().add(offset as usize), data.len()) };
        Ok(())
    }

    /// A shared byte view for the duration of `f` (for builds that read inputs in place).
    pub fn with_slice<R>(&self, offset: u64, len: u64, f: impl FnOnce(&[u8]) -> R) -> Result<R, AccessError> {
        self.check(offset, len)?;
        // SAFETY: range checked; the view does not outlive this call. Writers racing with it
        // would violate the application's synchronisation obligations.
        let s = unsafe { std::slice::from_raw_parts(self.backing.ptr.as_ptr().add(offset as usize), len as usize) };
        Ok(f(s))
    }

    /// A mutable byte view for the duration of `f` (for builds writing their destination).
    pub fn with_slice_mut<R>(&self, offset: u64, len: u64, f: impl FnOnce(&mut [u8]) -> R) -> Result<R, AccessError> {
        self.check(offset, len)?;
        // SAFETY: range checked; the view does not outlive this call; the caller guarantees no
        // other view of the same range exists during it (Arbor checks overlap between the
        // regions of one command before making views).
        let s = unsafe { std::slice::from_raw_parts_mut(self.backing.ptr.as_ptr().add(offset as usize), len as usize) };
        Ok(f(s))
    }

    /// Atomically replace the `size`-byte (4 or 8) little-endian value at `offset` with
    /// `update(old)`; returns `old`. Shader atomics from workgroups running in parallel.
    pub fn atomic(&self, offset: u64, size: usize, update: &dyn Fn(u64) -> u64) -> Result<u64, AccessError> {
        self.check(offset, size as u64)?;
        let ptr = self.backing.ptr.as_ptr().wrapping_add(offset as usize);
        if !(size == 4 || size == 8) || !(ptr as usize).is_multiple_of(size) {
            return Err(AccessError::Misaligned { offset, size: size as u64 });
        }
        let old = if size == 4 {
            // SAFETY: range checked above, aligned to 4, inside the live backing; concurrent
            // atomic users of the same word all go through this function.
            let a = unsafe { std::sync::atomic::AtomicU32::from_ptr(ptr as *mut u32) };
            let r = a.fetch_update(Ordering::AcqRel, Ordering::Acquire, |v| Some(update(u64::from(v)) as u32));
            u64::from(r.unwrap_or_else(|v| v))
        } else {
            // SAFETY: as above, aligned to 8.
            let a = unsafe { std::sync::atomic::AtomicU64::from_ptr(ptr as *mut u64) };
            a.fetch_update(Ordering::AcqRel, Ordering::Acquire, |v| Some(update(v))).unwrap_or_else(|v| v)
        };
        Ok(old)
    }

    pub fn is_freed(&self) -> bool {
        self.freed.load(Ordering::Acquire)
    }

    /// Map `[offset, offset + size)` (`size` already resolved from VK_WHOLE_SIZE) for the host.
    /// One mapping at a time, as in Vulkan.
    pub fn map(&self, offset: u64, size: u64) -> Result<*mut u8, MapError> {
        if self.is_freed() {
            return Err(MapError::Freed);
        }
        match offset.checked_add(size) {
            Some(end) if offset < self.size && size > 0 && end <= self.size => {}
            _ => return Err(MapError::Range),
        }
        let mut mapping = self.mapping.lock().unwrap_or_else(|e| e.into_inner());
        if mapping.is_some() {
            return Err(MapError::AlreadyMapped);
        }
        let ptr = self.host_ptr(offset).ok_or(MapError::Range)?;
        *mapping = Some((offset, size));
        Ok(ptr)
    }

    /// End the host mapping; false when the memory was not mapped.
    pub fn unmap(&self) -> bool {
        self.mapping.lock().unwrap_or_else(|e| e.into_inner()).take().is_some()
    }

    /// The current mapping (offset, size), if any.
    pub fn mapped_range(&self) -> Option<(u64, u64)> {
        *self.mapping.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Bytes the host backing really occupies (the allocation rounded to whole pages; where
    /// the system grants huge pages to a large backing, what is resident grows in 2 MiB steps
    /// as it is touched).
    pub fn committed_size(&self) -> u64 {
        self.size.next_multiple_of(ALLOCATION_ALIGNMENT)
    }

    /// Buffers currently bound to this memory.
    pub fn bound_buffers(&self) -> Vec<Arc<Buffer>> {
        self.buffers.lock().unwrap_or_else(|e| e.into_inner()).iter().filter_map(Weak::upgrade).collect()
    }
}

/// Why a host mapping was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MapError {
    /// The memory is mapped already (VUID-vkMapMemory-memory-00678).
    AlreadyMapped,
    /// Offset or size outside the allocation, or size 0.
    Range,
    Freed,
}

/// Allocation failure.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AllocError {
    OutOfDeviceMemory,
    OutOfHostMemory,
    /// The requested opaque capture address is not available.
    InvalidCaptureAddress,
}

/// One `VkBuffer`.
pub struct Buffer {
    pub size: u64,
    pub usage: vk::BufferUsageFlags,
    pub flags: vk::BufferCreateFlags,
    /// VkBufferOpaqueCaptureAddressCreateInfo::opaqueCaptureAddress (0 when none was given).
    pub capture_address: u64,
    binding: OnceLock<(Arc<Memory>, u64)>,
}

/// Why a bind was refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BindError {
    /// The buffer is bound already (VUID-vkBindBufferMemory-buffer-07459).
    AlreadyBound,
    /// The offset is not a multiple of [`BUFFER_ALIGNMENT`] (VUID-vkBindBufferMemory-memoryOffset-01036).
    Misaligned,
    /// The buffer does not fit in the memory at that offset, or the memory was freed.
    Access(AccessError),
}

impl Buffer {
    pub fn new(size: u64, usage: vk::BufferUsageFlags, flags: vk::BufferCreateFlags) -> Buffer {
        Buffer { size, usage, flags, capture_address: 0, binding: OnceLock::new() }
    }

    /// Memory requirements: size rounded up to the alignment, which is [`BUFFER_ALIGNMENT`]
    /// for every usage (acceleration-structure storage included).
    pub fn requirements(&self) -> (u64, u64) {
        (self.size.checked_next_multiple_of(BUFFER_ALIGNMENT).unwrap_or(self.size), BUFFER_ALIGNMENT)
    }

    /// Bind to `memory` at `offset` (once). Registers the buffer for address resolution.
    pub fn bind(self: &Arc<Self>, memory: Arc<Memory>, offset: u64) -> Result<(), BindError> {
        if self.binding.get().is_some() {
            return Err(BindError::AlreadyBound);
        }
        if !offset.is_multiple_of(BUFFER_ALIGNMENT) {
            return Err(BindError::Misaligned);
        }
        memory.check(offset, self.size).map_err(BindError::Access)?;
        let weak = Arc::downgrade(self);
        self.binding.set((memory.clone(), offset)).map_err(|_| BindError::AlreadyBound)?;
        let mut buffers = memory.buffers.lock().unwrap_or_else(|e| e.into_inner());
        buffers.retain(|b| b.strong_count() > 0);
        buffers.push(weak);
        Ok(())
    }

    pub fn memory(&self) -> Option<(&Arc<Memory>, u64)> {
        self.binding.get().map(|(m, o)| (m, *o))
    }

    /// The buffer's device address (bound buffers only).
    pub fn device_address(&self) -> Option<u64> {
        self.binding.get().map(|(m, o)| m.address + o)
    }

    fn locate(&self, offset: u64, len: u64) -> Result<(&Arc<Memory>, u64), AccessError> {
        let (m, base) = self.binding.get().ok_or(AccessError::Unbound)?;
        match offset.checked_add(len) {
            Some(end) if end <= self.size => Ok((m, base + offset)),
            _ => Err(AccessError::BufferRange { offset, len, size: self.size }),
        }
    }

    pub fn read(&self, offset: u64, out: &mut [u8]) -> Result<(), AccessError> {
        let (m, o) = self.locate(offset, out.len() as u64)?;
        m.read(o, out)
    }

    pub fn write(&self, offset: u64, data: &[u8]) -> Result<(), AccessError> {
        let (m, o) = self.locate(offset, data.len() as u64)?;
        m.write(o, data)
    }

    /// The host address of `len` bytes at buffer offset `offset`, when they are ordinary
    /// memory that holds them for as long as the buffer lives: bound, not freed, not a sparse
    /// range (whose pages come and go). Loads and stores there are what `read`/`write` do.
    pub fn host_span(&self, offset: u64, len: u64) -> Option<usize> {
        let (m, o) = self.locate(offset, len).ok()?;
        if m.sparse.is_some() {
            return None;
        }
        m.check(o, len).ok()?;
        m.host_ptr(o).map(|p| p as usize)
    }

    /// [`Memory::atomic`] at a buffer-relative offset.
    pub fn atomic(&self, offset: u64, size: usize, update: &dyn Fn(u64) -> u64) -> Result<u64, AccessError> {
        let (m, o) = self.locate(offset, size as u64)?;
        m.atomic(o, size, update)
    }

    pub fn with_slice<R>(&self, offset: u64, len: u64, f: impl FnOnce(&[u8]) -> R) -> Result<R, AccessError> {
        let (m, o) = self.locate(offset, len)?;
        m.with_slice(o, len, f)
    }

    pub fn with_slice_mut<R>(&self, offset: u64, len: u64, f: impl FnOnce(&mut [u8]) -> R) -> Result<R, AccessError> {
        let (m, o) = self.locate(offset, len)?;
        m.with_slice_mut(o, len, f)
    }
}

/// The result of resolving a device-address range: the buffer containing it and the offset.
pub struct Resolved {
    pub buffer: Arc<Buffer>,
    pub offset: u64,
}

/// The device-address space and allocations of one device.
pub struct AddressSpace {
    pub heap_size: u64,
    used: AtomicU64,
    /// Next free address of the ordinary and of the capture/replay region.
    next_address: Mutex<(u64, u64)>,
    /// Live allocations by base device address.
    allocations: RwLock<BTreeMap<u64, Weak<Memory>>>,
}

impl AddressSpace {
    pub fn new(heap_size: u64) -> AddressSpace {
        AddressSpace {
            heap_size,
            used: AtomicU64::new(0),
            next_address: Mutex::new((ADDRESS_BASE, REPLAY_BASE)),
            allocations: RwLock::new(BTreeMap::new()),
        }
    }

    /// Bytes currently allocated.
    pub fn used(&self) -> u64 {
        self.used.load(Ordering::Relaxed)
    }

    /// Allocate `size` bytes (zeroed). `capture_address`: place the allocation at exactly this
    /// device address (opaque capture/replay), failing if it is taken.
    pub fn allocate(&self, size: u64, device_address_flag: bool, capture_address: Option<u64>) -> Result<Arc<Memory>, AllocError> {
        self.allocate_with(size, device_address_flag, false, capture_address)
    }

    /// [`AddressSpace::allocate`] with the capture/replay flag: without a requested address the
    /// allocation is placed in the capture/replay region.
    pub fn allocate_with(
        &self,
        size: u64,
        device_address_flag: bool,
        capture_replay: bool,
        capture_address: Option<u64>,
    ) -> Result<Arc<Memory>, AllocError> {
        self.allocate_kind(size, device_address_flag, capture_replay, capture_address, sparse::Kind::Ordinary)
    }

    fn allocate_kind(
        &self,
        size: u64,
        device_address_flag: bool,
        capture_replay: bool,
        capture_address: Option<u64>,
        kind: sparse::Kind,
    ) -> Result<Arc<Memory>, AllocError> {
        let size = size.max(1);
        let reserved = self.used.fetch_add(size, Ordering::Relaxed).saturating_add(size);
        if reserved > self.heap_size {
            self.used.fetch_sub(size, Ordering::Relaxed);
            return Err(AllocError::OutOfDeviceMemory);
        }
        let release = |e| {
            self.used.fetch_sub(size, Ordering::Relaxed);
            e
        };
        let rounded = size.checked_add(ALLOCATION_ALIGNMENT - 1).ok_or(AllocError::OutOfDeviceMemory).map_err(release)? & !(ALLOCATION_ALIGNMENT - 1);
        let new_backing = match kind {
            sparse::Kind::Ordinary => Backing::new,
            sparse::Kind::Shareable => Backing::new_shared,
            sparse::Kind::SparseRange => Backing::new_reserved,
        };
        let backing = usize::try_from(rounded).ok().and_then(new_backing).ok_or_else(|| release(AllocError::OutOfHostMemory))?;

        let mut allocations = self.allocations.write().unwrap_or_else(|e| e.into_inner());
        let address = match capture_address {
            Some(a) => {
                let end = a.checked_add(rounded + ADDRESS_GAP);
                let clash = end.is_none()
                    || a % ALLOCATION_ALIGNMENT != 0
                    || a < ADDRESS_BASE
                    || allocations.range(..end.unwrap_or(u64::MAX)).any(|(base, m)| {
                        m.upgrade().is_some_and(|m| base + m.size.next_multiple_of(ALLOCATION_ALIGNMENT) + ADDRESS_GAP > a)
                    });
                if clash {
                    return Err(release(AllocError::InvalidCaptureAddress));
                }
                let mut next = self.next_address.lock().unwrap_or_else(|e| e.into_inner());
                let cursor = if a >= REPLAY_BASE { &mut next.1 } else { &mut next.0 };
                *cursor = (*cursor).max(a + rounded + ADDRESS_GAP);
                a
            }
            None => {
                let mut next = self.next_address.lock().unwrap_or_else(|e| e.into_inner());
                let cursor = if capture_replay { &mut next.1 } else { &mut next.0 };
                let a = *cursor;
                *cursor = a + rounded + ADDRESS_GAP;
                a
            }
        };
        let memory = Arc::new(Memory {
            backing,
            size,
            address,
            device_address_flag,
            mapping: Mutex::new(None),
            freed: AtomicBool::new(false),
            buffers: Mutex::new(Vec::new()),
            sparse: (kind == sparse::Kind::SparseRange).then(|| sparse::Pages::new(rounded)),
        });
        allocations.retain(|_, m| m.strong_count() > 0);
        allocations.insert(address, Arc::downgrade(&memory));
        Ok(memory)
    }

    /// Free an allocation: its addresses stop resolving at once; the host backing goes when
    /// the last reference (for example a queued command) is dropped.
    pub fn free(&self, memory: &Memory) {
        if !memory.freed.swap(true, Ordering::AcqRel) {
            // Freeing implicitly unmaps.
            memory.unmap();
            self.used.fetch_sub(memory.size, Ordering::Relaxed);
            self.allocations.write().unwrap_or_else(|e| e.into_inner()).remove(&memory.address);
        }
    }

    /// Find the live buffer that contains the whole range [address, address + len).
    pub fn resolve(&self, address: u64, len: u64) -> Result<Resolved, AccessError> {
        let memory = {
            let allocations = self.allocations.read().unwrap_or_else(|e| e.into_inner());
            allocations
                .range(..=address)
                .next_back()
                .and_then(|(_, m)| m.upgrade())
                .filter(|m| !m.is_freed() && address < m.address + m.size)
                .ok_or(AccessError::Unmapped { address })?
        };
        let end = address.checked_add(len).ok_or(AccessError::Unmapped { address })?;
        let buffers = memory.buffers.lock().unwrap_or_else(|e| e.into_inner());
        let mut partial = None;
        for b in buffers.iter().filter_map(Weak::upgrade) {
            let Some(start) = b.device_address() else { continue };
            if address >= start && address < start + b.size.max(1) {
                if end <= start + b.size {
                    return Ok(Resolved { offset: address - start, buffer: b });
                }
                partial = Some(AccessError::OutOfBounds { address, len, buffer_address: start, buffer_size: b.size });
            }
        }
        Err(partial.unwrap_or(AccessError::Unmapped { address }))
    }

    /// Every live buffer that contains the whole range [address, address + len), in bind
    /// order. Several buffers may alias the same memory; the first error explains a miss.
    pub fn resolve_all(&self, address: u64, len: u64) -> Result<Vec<Resolved>, AccessError> {
        let first = self.resolve(address, len)?;
        let Some((memory, _)) = first.buffer.memory() else { return Ok(vec![first]) };
        let end = address.checked_add(len).ok_or(AccessError::Unmapped { address })?;
        Ok(memory
            .bound_buffers()
            .into_iter()
            .filter_map(|b| {
                let start = b.device_address()?;
                (address >= start && end <= start + b.size).then(|| Resolved { offset: address - start, buffer: b })
            })
            .collect())
    }

    /// Union of the usage flags of the live buffers that contain the whole range (for the
    /// valid-usage rules that ask how "the buffer the address was queried from" was created:
    /// the address alone cannot say which of several aliasing buffers that was).
    pub fn buffer_usage_at(&self, address: u64, len: u64) -> Result<vk::BufferUsageFlags, AccessError> {
        Ok(self.resolve_all(address, len)?.iter().fold(vk::BufferUsageFlags::empty(), |u, r| u | r.buffer.usage))
    }

    /// Resolve to a live buffer containing the range whose usage includes `usage`.
    /// `Err(Ok(found))`: the range resolves but no containing buffer has the usage; `found` is
    /// the union of their usages.
    pub fn resolve_with_usage(
        &self,
        address: u64,
        len: u64,
        usage: vk::BufferUsageFlags,
    ) -> Result<Resolved, Result<vk::BufferUsageFlags, AccessError>> {
        let all = self.resolve_all(address, len).map_err(Err)?;
        let found = all.iter().fold(vk::BufferUsageFlags::empty(), |u, r| u | r.buffer.usage);
        all.into_iter().find(|r| r.buffer.usage.contains(usage)).ok_or(Ok(found))
    }

    /// A shared view of the device-memory range [address, address + len) for the duration of
    /// `f` (resolve + [`Buffer::with_slice`]).
    pub fn with_range<R>(&self, address: u64, len: u64, f: impl FnOnce(&[u8]) -> R) -> Result<R, AccessError> {
        let r = self.resolve(address, len)?;
        r.buffer.with_slice(r.offset, len, f)
    }

    /// A mutable view of the device-memory range [address, address + len) for the duration of
    /// `f`. The caller guarantees no other view of the range exists meanwhile (see
    /// [`Memory::with_slice_mut`]).
    pub fn with_range_mut<R>(&self, address: u64, len: u64, f: impl FnOnce(&mut [u8]) -> R) -> Result<R, AccessError> {
        let r = self.resolve(address, len)?;
        r.buffer.with_slice_mut(r.offset, len, f)
    }

    /// Read bytes at a device address.
    pub fn read(&self, address: u64, out: &mut [u8]) -> Result<(), AccessError> {
        let r = self.resolve(address, out.len() as u64)?;
        r.buffer.read(r.offset, out)
    }

    /// Write bytes at a device address.
    pub fn write(&self, address: u64, data: &[u8]) -> Result<(), AccessError> {
        let r = self.resolve(address, data.len() as u64)?;
        r.buffer.write(r.offset, data)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIB: u64 = 1 << 20;

    fn bound(space: &AddressSpace, size: u64, usage: vk::BufferUsageFlags) -> (Arc<Memory>, Arc<Buffer>) {
        let m = space.allocate(size, true, None).unwrap();
        let b = Arc::new(Buffer::new(size, usage, vk::BufferCreateFlags::empty()));
        b.bind(m.clone(), 0).unwrap();
        (m, b)
    }

    #[test]
    fn addresses_are_distinct_aligned_nonzero() {
        let space = AddressSpace::new(64 * MIB);
        let all: Vec<_> = (0..8).map(|i| bound(&space, 100 + i * 1000, vk::BufferUsageFlags::STORAGE_BUFFER)).collect();
        let addrs: Vec<u64> = all.iter().map(|(_, b)| b.device_address().unwrap()).collect();
        for (i, a) in addrs.iter().enumerate() {
            assert_ne!(*a, 0);
            assert_eq!(a % BUFFER_ALIGNMENT, 0);
            assert_eq!(a % ALLOCATION_ALIGNMENT, 0);
            assert!(addrs[i + 1..].iter().all(|b| b != a));
            // Stable: asking again gives the same answer.
            assert_eq!(all[i].1.device_address(), Some(*a));
        }
    }

    #[test]
    fn resolve_finds_the_containing_buffer() {
        let space = AddressSpace::new(64 * MIB);
        let (_m, b) = bound(&space, 4096, vk::BufferUsageFlags::STORAGE_BUFFER);
        let a = b.device_address().unwrap();
        let r = space.resolve(a + 100, 200).unwrap();
        assert!(Arc::ptr_eq(&r.buffer, &b));
        assert_eq!(r.offset, 100);
        // The whole buffer, and its last byte.
        assert_eq!(space.resolve(a, 4096).unwrap().offset, 0);
        assert_eq!(space.resolve(a + 4095, 1).unwrap().offset, 4095);
        space.write(a + 8, &[1, 2, 3, 4]).unwrap();
        let mut out = [0u8; 4];
        b.read(8, &mut out).unwrap();
        assert_eq!(out, [1, 2, 3, 4]);
    }

    #[test]
    fn resolve_errors_say_what_is_wrong() {
        let space = AddressSpace::new(64 * MIB);
        let (m, b) = bound(&space, 4096, vk::BufferUsageFlags::STORAGE_BUFFER);
        let a = b.device_address().unwrap();
        // Runs past the end of the buffer.
        assert_eq!(
            space.resolve(a + 4000, 200).err(),
            Some(AccessError::OutOfBounds { address: a + 4000, len: 200, buffer_address: a, buffer_size: 4096 })
        );
        // In the gap after the allocation, below the first, and at 0.
        assert_eq!(space.resolve(a + 4096 + 10, 1).err(), Some(AccessError::Unmapped { address: a + 4096 + 10 }));
        assert_eq!(space.resolve(a - 1, 1).err(), Some(AccessError::Unmapped { address: a - 1 }));
        assert_eq!(space.resolve(0, 1).err(), Some(AccessError::Unmapped { address: 0 }));
        // Length overflow.
        assert!(space.resolve(a, u64::MAX).is_err());
        // Freed memory stops resolving at once, and buffer-relative access says why.
        space.free(&m);
        assert_eq!(space.resolve(a, 4).err(), Some(AccessError::Unmapped { address: a }));
        assert_eq!(b.read(0, &mut [0u8; 4]).err(), Some(AccessError::Freed));
        assert_eq!(space.used(), 0);
    }

    /// Allocations on both sides of the huge-page threshold (their own mapping from it on)
    /// start zeroed, hold what is written at both ends, and are freed independently.
    #[test]
    fn large_and_small_backings_are_zeroed_and_independent() {
        let space = AddressSpace::new(64 * MIB);
        let sizes = [HUGE_MAPPING_MIN as u64 - 4096, HUGE_MAPPING_MIN as u64, 5 * MIB + 4096];
        let mems: Vec<_> = sizes.iter().map(|&s| space.allocate(s, true, None).unwrap()).collect();
        for (i, (m, &s)) in mems.iter().zip(&sizes).enumerate() {
            let mut all = vec![1u8; s as usize];
            m.read(0, &mut all).unwrap();
            assert!(all.iter().all(|&b| b == 0), "allocation {i} not zeroed");
            m.write(0, &[i as u8 + 1; 8]).unwrap();
            m.write(s - 8, &[i as u8 + 11; 8]).unwrap();
        }
        let mut mems = mems;
        drop(mems.remove(1));
        let again = space.allocate(HUGE_MAPPING_MIN as u64, true, None).unwrap();
        let mut b = [9u8; 8];
        again.read(HUGE_MAPPING_MIN as u64 - 8, &mut b).unwrap();
        assert_eq!(b, [0; 8]);
        for (m, (i, s)) in mems.iter().zip([(0u8, sizes[0]), (2, sizes[2])]) {
            m.read(0, &mut b).unwrap();
            assert_eq!(b, [i + 1; 8]);
            m.read(s - 8, &mut b).unwrap();
            assert_eq!(b, [i + 11; 8]);
        }
    }

    #[test]
    fn memory_without_a_buffer_does_not_resolve() {
        let space = AddressSpace::new(64 * MIB);
        let m = space.allocate(8192, true, None).unwrap();
        assert_eq!(space.resolve(m.address, 4).err(), Some(AccessError::Unmapped { address: m.address }));
        let unbound = Buffer::new(16, vk::BufferUsageFlags::STORAGE_BUFFER, vk::BufferCreateFlags::empty());
        assert_eq!(unbound.read(0, &mut [0u8; 4]).err(), Some(AccessError::Unbound));
        assert_eq!(unbound.device_address(), None);
    }

    #[test]
    fn straddling_two_buffers_is_out_of_bounds() {
        let space = AddressSpace::new(64 * MIB);
        let m = space.allocate(1024, true, None).unwrap();
        let lo = Arc::new(Buffer::new(256, vk::BufferUsageFlags::STORAGE_BUFFER, vk::BufferCreateFlags::empty()));
        let hi = Arc::new(Buffer::new(256, vk::BufferUsageFlags::UNIFORM_BUFFER, vk::BufferCreateFlags::empty()));
        lo.bind(m.clone(), 0).unwrap();
        hi.bind(m.clone(), 256).unwrap();
        let a = m.address;
        assert_eq!(hi.device_address(), Some(a + 256));
        assert!(matches!(space.resolve(a + 200, 100), Err(AccessError::OutOfBounds { buffer_address, .. }) if buffer_address == a));
        assert!(Arc::ptr_eq(&space.resolve(a + 256, 100).unwrap().buffer, &hi));
        // Past both buffers but inside the memory.
        assert_eq!(space.resolve(a + 600, 4).err(), Some(AccessError::Unmapped { address: a + 600 }));
    }

    #[test]
    fn usage_of_aliasing_buffers() {
        let space = AddressSpace::new(64 * MIB);
        let m = space.allocate(1024, true, None).unwrap();
        let whole = Arc::new(Buffer::new(1024, vk::BufferUsageFlags::STORAGE_BUFFER, vk::BufferCreateFlags::empty()));
        let part = Arc::new(Buffer::new(
            256,
            vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR,
            vk::BufferCreateFlags::empty(),
        ));
        whole.bind(m.clone(), 0).unwrap();
        part.bind(m.clone(), 512).unwrap();
        let a = m.address;
        assert_eq!(
            space.buffer_usage_at(a + 512, 64).unwrap(),
            vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR
        );
        assert_eq!(space.buffer_usage_at(a, 64).unwrap(), vk::BufferUsageFlags::STORAGE_BUFFER);
        let r = space.resolve_with_usage(a + 520, 8, vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR).unwrap();
        assert!(Arc::ptr_eq(&r.buffer, &part));
        assert_eq!(r.offset, 8);
        assert_eq!(
            space.resolve_with_usage(a, 8, vk::BufferUsageFlags::UNIFORM_BUFFER).err(),
            Some(Ok(vk::BufferUsageFlags::STORAGE_BUFFER))
        );
        assert!(matches!(space.resolve_with_usage(0, 8, vk::BufferUsageFlags::STORAGE_BUFFER), Err(Err(_))));
        // A destroyed buffer no longer counts.
        drop((r, part));
        assert_eq!(space.buffer_usage_at(a + 512, 64).unwrap(), vk::BufferUsageFlags::STORAGE_BUFFER);
    }

    #[test]
    fn with_range_views() {
        let space = AddressSpace::new(64 * MIB);
        let (_m, b) = bound(&space, 512, vk::BufferUsageFlags::STORAGE_BUFFER);
        let a = b.device_address().unwrap();
        space.with_range_mut(a + 16, 4, |s| s.copy_from_slice(&[9, 8, 7, 6])).unwrap();
        let sum = space.with_range(a + 16, 4, |s| s.iter().map(|&x| x as u32).sum::<u32>()).unwrap();
        assert_eq!(sum, 30);
        assert!(space.with_range(a + 510, 4, |_| ()).is_err());
    }

    #[test]
    fn bind_rules() {
        let space = AddressSpace::new(64 * MIB);
        let m = space.allocate(1024, false, None).unwrap();
        let b = Arc::new(Buffer::new(300, vk::BufferUsageFlags::STORAGE_BUFFER, vk::BufferCreateFlags::empty()));
        assert_eq!(b.requirements(), (512, BUFFER_ALIGNMENT));
        assert_eq!(b.bind(m.clone(), 100), Err(BindError::Misaligned));
        assert!(matches!(b.bind(m.clone(), 768), Err(BindError::Access(_))));
        b.bind(m.clone(), 512).unwrap();
        assert_eq!(b.bind(m.clone(), 0), Err(BindError::AlreadyBound));
        assert_eq!(m.bound_buffers().len(), 1);
    }

    #[test]
    fn map_rules() {
        let space = AddressSpace::new(64 * MIB);
        let m = space.allocate(1000, false, None).unwrap();
        assert_eq!(m.map(1000, 1).err(), Some(MapError::Range));
        assert_eq!(m.map(0, 0).err(), Some(MapError::Range));
        assert_eq!(m.map(10, 991).err(), Some(MapError::Range));
        let p = m.map(10, 990).unwrap();
        assert_eq!(m.mapped_range(), Some((10, 990)));
        assert_eq!(m.map(0, 4).err(), Some(MapError::AlreadyMapped));
        // SAFETY: inside the mapping made above.
        unsafe { p.write(42) };
        let mut out = [0u8];
        m.read(10, &mut out).unwrap();
        assert_eq!(out, [42]);
        // Host pointers have the alignment of the device addresses they back.
        assert_eq!(m.host_ptr(0).unwrap() as usize % ALLOCATION_ALIGNMENT as usize, 0);
        assert!(m.unmap());
        assert!(!m.unmap());
        // Freeing unmaps.
        m.map(0, 4).unwrap();
        space.free(&m);
        assert_eq!(m.mapped_range(), None);
    }

    #[test]
    fn out_of_device_memory_is_accounted() {
        let space = AddressSpace::new(MIB);
        let a = space.allocate(MIB / 2 + 1, false, None).unwrap();
        assert_eq!(space.allocate(MIB / 2, false, None).err(), Some(AllocError::OutOfDeviceMemory));
        assert_eq!(space.used(), MIB / 2 + 1);
        space.free(&a);
        space.free(&a);
        assert_eq!(space.used(), 0);
        assert!(space.allocate(MIB, false, None).is_ok());
    }

    #[test]
    fn capture_replay_reproduces_addresses() {
        let capture = AddressSpace::new(64 * MIB);
        let _filler = capture.allocate(3 * MIB, true, None).unwrap();
        let captured = capture.allocate_with(8192, true, true, None).unwrap();
        let plain = capture.allocate(4096, true, None).unwrap();
        // Capture/replay allocations come from their own region.
        assert!(captured.address >= REPLAY_BASE && plain.address < REPLAY_BASE);

        let replay = AddressSpace::new(64 * MIB);
        let ordinary = replay.allocate(5 * MIB, true, None).unwrap();
        let replayed = replay.allocate_with(8192, true, true, Some(captured.address)).unwrap();
        assert_eq!(replayed.address, captured.address);
        let b = Arc::new(Buffer::new(4096, vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS, vk::BufferCreateFlags::empty()));
        b.bind(replayed.clone(), 256).unwrap();
        assert_eq!(b.device_address(), Some(captured.address + 256));
        // The address is taken now; overlapping or misaligned requests are refused.
        assert_eq!(replay.allocate_with(16, true, true, Some(captured.address)).err(), Some(AllocError::InvalidCaptureAddress));
        assert_eq!(replay.allocate_with(16, true, true, Some(captured.address + 4096)).err(), Some(AllocError::InvalidCaptureAddress));
        assert_eq!(replay.allocate_with(16, true, true, Some(ordinary.address)).err(), Some(AllocError::InvalidCaptureAddress));
        assert_eq!(replay.allocate_with(16, true, true, Some(REPLAY_BASE + 7)).err(), Some(AllocError::InvalidCaptureAddress));
        assert_eq!(replay.allocate_with(16, true, true, Some(12345)).err(), Some(AllocError::InvalidCaptureAddress));
        // A failed request costs no heap.
        assert_eq!(replay.used(), 5 * MIB + 8192);
        // Later allocations of both regions stay clear of the replayed one.
        let next = replay.allocate_with(8192, true, true, None).unwrap();
        assert!(next.address >= replayed.address + 8192 + ADDRESS_GAP);
        // Freed addresses can be requested again.
        replay.free(&replayed);
        assert!(replay.allocate_with(8192, true, true, Some(captured.address)).is_ok());
    }

    #[test]
    fn memory_imports_nothing_of_the_rest_of_the_driver() {
        let sources = [include_str!("mod.rs"), include_str!("backing.rs"), include_str!("view.rs"), include_str!("region.rs")];
        let crate_path = concat!("crate", "::");
        for source in sources {
            assert!(!source.contains(crate_path), "src/memory must not depend on the layers above it");
        }
    }
}

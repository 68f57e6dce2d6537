//! The emulated device: allocations, the device-address space, checked reads and writes.
//!
//! Every read and write of device memory by the driver goes through this module. Device
//! addresses are virtual: each allocation gets a range of the device's address space (aligned,
//! non-zero, with unmapped gaps between allocations, never a host pointer); a buffer's address is
//! its memory's base plus its bind offset. Resolving (address, length) finds the one live buffer
//! that contains the whole range, or says what is wrong.
//!
//! Concurrency: device memory is shared with the application (mapped pointers) and with queue
//! workers, exactly like GPU memory. Accesses are raw copies; the Vulkan synchronisation rules
//! (the application's obligation) make them race-free. No `&mut [u8]` over device memory
//! outlives the call that made it.
use std::collections::BTreeMap;
use std::fmt;
use std::ptr::NonNull;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock, Weak};

use ash::vk;

/// Alignment of every allocation's host backing and of its device address.
pub const ALLOCATION_ALIGNMENT: u64 = 4096;
/// Gap left unmapped between two allocations' device-address ranges (catches overruns).
const ADDRESS_GAP: u64 = 1 << 20;
/// First device address handed out (addresses are never 0 and never look like host pointers).
const ADDRESS_BASE: u64 = 0x0000_0100_0000_0000;
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
        }
    }
}

/// Host backing of one allocation.
struct Backing {
    ptr: NonNull<u8>,
    layout: std::alloc::Layout,
}

// SAFETY: the backing is plain bytes owned by the allocation; concurrent access follows the
// Vulkan synchronisation rules (see the module docs).
unsafe impl Send for Backing {}
// SAFETY: as above.
unsafe impl Sync for Backing {}

impl Drop for Backing {
    fn drop(&mut self) {
        // SAFETY: allocated with this layout in Memory::new.
        unsafe { std::alloc::dealloc(self.ptr.as_ptr(), self.layout) };
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
    pub mapped: AtomicBool,
    freed: AtomicBool,
    /// Buffers bound to this memory (for address resolution).
    buffers: Mutex<Vec<Weak<Buffer>>>,
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

    pub fn is_freed(&self) -> bool {
        self.freed.load(Ordering::Acquire)
    }
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
    binding: OnceLock<(Arc<Memory>, u64)>,
}

impl Buffer {
    pub fn new(size: u64, usage: vk::BufferUsageFlags, flags: vk::BufferCreateFlags) -> Buffer {
        Buffer { size, usage, flags, binding: OnceLock::new() }
    }

    /// Bind to `memory` at `offset` (once). Registers the buffer for address resolution.
    pub fn bind(self: &Arc<Self>, memory: Arc<Memory>, offset: u64) -> Result<(), AccessError> {
        memory.check(offset, self.size)?;
        memory.buffers.lock().unwrap_or_else(|e| e.into_inner()).push(Arc::downgrade(self));
        self.binding.set((memory, offset)).map_err(|_| AccessError::Unbound)
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
    next_address: Mutex<u64>,
    /// Live allocations by base device address.
    allocations: RwLock<BTreeMap<u64, Weak<Memory>>>,
}

impl AddressSpace {
    pub fn new(heap_size: u64) -> AddressSpace {
        AddressSpace {
            heap_size,
            used: AtomicU64::new(0),
            next_address: Mutex::new(ADDRESS_BASE),
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
        let layout = std::alloc::Layout::from_size_align(rounded as usize, ALLOCATION_ALIGNMENT as usize)
            .map_err(|_| release(AllocError::OutOfDeviceMemory))?;
        // SAFETY: layout has non-zero size.
        let ptr = NonNull::new(unsafe { std::alloc::alloc_zeroed(layout) }).ok_or_else(|| release(AllocError::OutOfHostMemory))?;
        let backing = Backing { ptr, layout };

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
                *next = (*next).max(a + rounded + ADDRESS_GAP);
                a
            }
            None => {
                let mut next = self.next_address.lock().unwrap_or_else(|e| e.into_inner());
                let a = *next;
                *next = a + rounded + ADDRESS_GAP;
                a
            }
        };
        let memory = Arc::new(Memory {
            backing,
            size,
            address,
            device_address_flag,
            mapped: AtomicBool::new(false),
            freed: AtomicBool::new(false),
            buffers: Mutex::new(Vec::new()),
        });
        allocations.retain(|_, m| m.strong_count() > 0);
        allocations.insert(address, Arc::downgrade(&memory));
        Ok(memory)
    }

    /// Free an allocation: its addresses stop resolving at once; the host backing goes when
    /// the last reference (for example a queued command) is dropped.
    pub fn free(&self, memory: &Memory) {
        if !memory.freed.swap(true, Ordering::AcqRel) {
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

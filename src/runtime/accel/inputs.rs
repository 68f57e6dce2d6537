//! Where an acceleration-structure command reads its inputs and finds the regions it writes:
//! device memory for commands a queue executes ([`DeviceInputs`]), application host memory for
//! host commands ([`HostInputs`]); both are the `accel::DeviceView` the library follows device
//! addresses (or, on the host, handles) through.
//!
//! This module owns the translation of addresses into memory; it must not check valid usage
//! (that is `validate`'s) nor make views of memory itself: shared and writable views come from
//! `crate::memory` (`view::DeviceMemoryView`, `region`), host bytes from the `HostMemory` the
//! dispatch layer vouched for.
use std::sync::Arc;

use ash::vk;

use super::AccelerationStructure;
use crate::accel;
use crate::memory::region::{HostMemory, Region};
use crate::memory::view::DeviceMemoryView;
use crate::memory::{AccessError, AddressSpace};

/// Where a build reads its inputs: device memory (device and indirect builds) or host memory
/// (host builds, where addresses are host pointers and instance references are handles).
pub trait InputMemory: accel::DeviceView {
    /// Input bytes at `address`; on device, also checks the containing buffer has `usage`.
    fn input(&self, address: u64, len: u64, usage: vk::BufferUsageFlags) -> Result<&[u8], InputError>;
    /// A region the command writes (scratch, a serialized structure) at `address`, checked to
    /// be addressable; exclusivity is claimed through `memory::region::WriteSet`.
    fn writable(&self, address: u64, len: u64) -> Result<Region<'_>, InputError>;
    /// The backing memory range of a device-memory region, for overlap checks (None on host).
    fn memory_range(&self, address: u64, len: u64) -> Option<(usize, u64, u64)>;
    /// Command name for diagnostics.
    fn command(&self) -> &'static str;
    fn is_host(&self) -> bool;
}

#[derive(Debug, Clone)]
pub enum InputError {
    Access(AccessError),
    /// The range resolves but no containing buffer has the required usage (the union found).
    Usage(vk::BufferUsageFlags),
}

impl std::fmt::Display for InputError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            InputError::Access(e) => write!(f, "{e}"),
            InputError::Usage(u) => write!(f, "the buffer containing it lacks the required usage (has {u:?})"),
        }
    }
}

/// Device-memory inputs.
pub struct DeviceInputs<'a> {
    pub space: &'a AddressSpace,
    pub view: DeviceMemoryView<'a>,
    pub command: &'static str,
}

impl<'a> DeviceInputs<'a> {
    pub fn new(space: &'a AddressSpace, command: &'static str) -> Self {
        DeviceInputs { space, view: DeviceMemoryView::new(space), command }
    }
}

impl accel::DeviceView for DeviceInputs<'_> {
    fn bytes(&self, address: u64, len: u64) -> Option<&[u8]> {
        self.view.bytes(address, len)
    }
    fn acceleration_structure(&self, reference: u64) -> Option<&[u8]> {
        self.view.structure(reference)
    }
}

impl InputMemory for DeviceInputs<'_> {
    fn input(&self, address: u64, len: u64, usage: vk::BufferUsageFlags) -> Result<&[u8], InputError> {
        match self.space.resolve_with_usage(address, len, usage) {
            Ok(_) => self.view.bytes(address, len).ok_or(InputError::Access(AccessError::Unmapped { address })),
            Err(Ok(found)) => Err(InputError::Usage(found)),
            Err(Err(e)) => Err(InputError::Access(e)),
        }
    }
    fn writable(&self, address: u64, len: u64) -> Result<Region<'_>, InputError> {
        Region::of_device(self.space, address, len).map_err(InputError::Access)
    }
    fn memory_range(&self, address: u64, len: u64) -> Option<(usize, u64, u64)> {
        let r = self.space.resolve(address, len.max(1)).ok()?;
        r.buffer.memory_range(r.offset, len)
    }
    fn command(&self) -> &'static str {
        self.command
    }
    fn is_host(&self) -> bool {
        false
    }
}

/// The structure a handle value names, as the dispatch layer's handle registry finds it.
pub type StructureLookup = fn(u64) -> Option<Arc<AccelerationStructure>>;

/// Host-memory inputs for host commands: addresses are host pointers the application promises
/// are valid while the command (or its deferred operation) runs (`HostMemory`); instance
/// references are `VkAccelerationStructureKHR` handles, translated to device addresses so host
/// and device builds produce the same bytes.
pub struct HostInputs<'a> {
    host: HostMemory,
    device_view: DeviceMemoryView<'a>,
    lookup: StructureLookup,
    command: &'static str,
    /// Distinguishes this command's entries in the per-thread handle memo.
    id: u64,
}

/// Handle → device address of the structures named by the instances of the host command
/// running on this thread: its last few lookups, round robin. A TLAS names a handful of
/// BLASes thousands of times, and each registry lookup takes the registry's read lock and
/// an `Arc` of the structure, whose shared counters the worker threads would pass back and
/// forth between cores. Entries count only for the command (`HostInputs::id`) that made
/// them: the structures a host command names must stay alive until it completes (the
/// application's obligation, as for its host addresses), so within one command a handle
/// keeps its address; ids are never reused.
#[derive(Clone, Copy)]
struct HandleMemo {
    entries: [(u64, u64, u64); 4],
    next: usize,
}

thread_local! {
    static HANDLE_MEMO: std::cell::Cell<HandleMemo> = const { std::cell::Cell::new(HandleMemo { entries: [(0, 0, 0); 4], next: 0 }) };
}

impl<'a> HostInputs<'a> {
    /// Inputs of one host command: `host` vouches for its host addresses, `lookup` turns the
    /// handle values its instances name into structures.
    pub fn new(host: HostMemory, space: &'a AddressSpace, lookup: StructureLookup, command: &'static str) -> Self {
        static NEXT_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
        let id = NEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        HostInputs { host, device_view: DeviceMemoryView::new(space), lookup, command, id }
    }

    /// The device address of the structure whose handle value is `handle`: Some(None) for a
    /// structure without one, None when `handle` names no structure.
    fn structure_address(&self, handle: u64) -> Option<Option<u64>> {
        HANDLE_MEMO.with(|m| {
            let mut memo = m.get();
            if let Some(&(_, _, address)) = memo.entries.iter().find(|e| e.0 == self.id && e.1 == handle) {
                return Some(Some(address));
            }
            let address = (self.lookup)(handle)?.address();
            if let Some(a) = address {
                memo.entries[memo.next % 4] = (self.id, handle, a);
                memo.next = (memo.next + 1) % 4;
                m.set(memo);
            }
            Some(address)
        })
    }
}

impl accel::DeviceView for HostInputs<'_> {
    fn bytes(&self, address: u64, len: u64) -> Option<&[u8]> {
        self.host.bytes(address, len)
    }
    fn acceleration_structure(&self, reference: u64) -> Option<&[u8]> {
        match self.structure_address(reference) {
            Some(address) => self.device_view.structure(address?),
            None => self.device_view.structure(reference),
        }
    }
    fn translate_reference(&self, reference: u64) -> u64 {
        self.structure_address(reference).flatten().unwrap_or(reference)
    }
}

impl InputMemory for HostInputs<'_> {
    fn input(&self, address: u64, len: u64, _usage: vk::BufferUsageFlags) -> Result<&[u8], InputError> {
        self.host.bytes(address, len).ok_or(InputError::Access(AccessError::Unmapped { address }))
    }
    fn writable(&self, address: u64, len: u64) -> Result<Region<'_>, InputError> {
        self.host.region(address, len).ok_or(InputError::Access(AccessError::Unmapped { address }))
    }
    fn memory_range(&self, _address: u64, _len: u64) -> Option<(usize, u64, u64)> {
        None
    }
    fn command(&self) -> &'static str {
        self.command
    }
    fn is_host(&self) -> bool {
        true
    }
}

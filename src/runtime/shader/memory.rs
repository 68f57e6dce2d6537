//! The shader library's view of device memory for one dispatch: [`DispatchMemory`] implements
//! [`crate::shader::Memory`] over `src/memory`. Descriptor bindings are resolved once, when the
//! dispatch starts, to (buffer, offset after dynamic offsets, range); device addresses
//! (buffer device address) are resolved per access through the address space's checked
//! resolve, so a null, unmapped or freed address is a fault, never a host access.
//!
//! This module only maps; it reports nothing (the dispatch turns faults into diagnostics).
//!
//! Image bindings plug in here: `resolve_binding` is the one place a descriptor becomes something
//! the shader can reach, and `DispatchMemory::new` the one loop that collects them. Storage
//! images reach the library through their own interface, not as buffer regions, so an image
//! descriptor resolves to `Unresolved::Image` for now (the `Descriptor::Image` arm); the images
//! work resolves it there into its image view and keeps it beside `regions`.
use std::sync::Arc;

use crate::memory::{AddressSpace, Buffer};
use crate::runtime::descriptor::{is_dynamic, Descriptor};
use crate::shader::{Memory, Region};

use super::BoundSet;

/// Buffer ids at or above this are device-address resolutions: the id is the buffer's device
/// address with this bit set. Ids below it index `DispatchMemory::buffers` (descriptors).
const ADDRESS_TAG: u64 = 1 << 63;

/// One dispatch's memory: the buffers its descriptors name, and the device's address space.
pub struct DispatchMemory<'a> {
    space: &'a AddressSpace,
    /// ((set, binding), region) for every binding the pipeline uses that resolved.
    regions: Vec<((u32, u32), Region)>,
    /// The buffers `regions` refer to, by `Region::buffer`.
    buffers: Vec<Arc<Buffer>>,
}

/// Where a binding the shader uses points, for the diagnostics of an unbound binding.
#[derive(Debug, PartialEq, Eq)]
pub enum Unresolved {
    /// No set bound at that number, or the set lacks the binding.
    NotBound,
    /// The descriptor was never written or its buffer was destroyed.
    Empty,
    /// A dynamic offset moves the range past the buffer's end.
    PastEnd { offset: u64, size: u64 },
    /// An image descriptor: not a buffer region (see the module docs).
    Image,
}

/// The bindings a dispatch uses that did not resolve, and why.
pub type Missing = Vec<((u32, u32), Unresolved)>;

impl<'a> DispatchMemory<'a> {
    /// Resolve every (set, binding) the pipeline uses against the bound sets. Bindings that do
    /// not resolve are returned beside the memory: the shader sees them as unbound (each access
    /// a contained fault).
    pub fn new(space: &'a AddressSpace, sets: &[Option<BoundSet>], used: &[(u32, u32)]) -> (Self, Missing) {
        let mut m = DispatchMemory { space, regions: Vec::new(), buffers: Vec::new() };
        let mut missing = Vec::new();
        for &(set, binding) in used {
            match resolve_binding(sets, set, binding) {
                Ok((buffer, offset, len)) => {
                    let region = Region { buffer: m.buffers.len() as u64, offset, len };
                    m.buffers.push(buffer);
                    m.regions.push(((set, binding), region));
                }
                Err(e) => missing.push(((set, binding), e)),
            }
        }
        (m, missing)
    }

    /// The buffer of a descriptor region (offsets the library passes are buffer-relative).
    fn buffer(&self, id: u64) -> Option<&Buffer> {
        self.buffers.get(usize::try_from(id).ok()?).map(|b| &**b)
    }
}

/// The buffer range a bound descriptor gives the shader: element 0 of the binding, dynamic
/// offset applied. Dynamic offsets are ordered by binding number, then array element.
fn resolve_binding(sets: &[Option<BoundSet>], set: u32, binding: u32) -> Result<(Arc<Buffer>, u64, u64), Unresolved> {
    let bound = sets.get(set as usize).and_then(Option::as_ref).ok_or(Unresolved::NotBound)?;
    let layout = &bound.set.layout;
    let lb = layout.binding(binding).ok_or(Unresolved::NotBound)?;
    let dynamic = if is_dynamic(lb.descriptor_type) {
        let index: u32 = layout.bindings.iter().take_while(|b| b.binding < binding).filter(|b| is_dynamic(b.descriptor_type)).map(|b| b.count).sum();
        bound.dynamic_offsets.get(index as usize).copied().unwrap_or(0) as u64
    } else {
        0
    };
    match bound.set.descriptor(binding, 0).ok_or(Unresolved::NotBound)? {
        d @ Descriptor::Buffer { .. } => {
            let (buffer, offset, len) = d.buffer_range(dynamic).ok_or(Unresolved::Empty)?;
            match offset.checked_add(len) {
                Some(end) if end <= buffer.size => Ok((buffer, offset, len)),
                _ => Err(Unresolved::PastEnd { offset, size: buffer.size }),
            }
        }
        // The image hook (module docs): storage images are resolved here by the images work.
        Descriptor::Image { .. } => Err(Unresolved::Image),
        _ => Err(Unresolved::Empty),
    }
}

impl Memory for DispatchMemory<'_> {
    fn binding(&self, set: u32, binding: u32) -> Option<Region> {
        self.regions.iter().find(|(k, _)| *k == (set, binding)).map(|(_, r)| *r)
    }

    fn address(&self, address: u64, len: u64) -> Option<Region> {
        if address == 0 {
            return None;
        }
        let r = self.space.resolve(address, len).ok()?;
        let base = r.buffer.device_address()?;
        Some(Region { buffer: base | ADDRESS_TAG, offset: r.offset, len: r.buffer.size - r.offset })
    }

    fn read(&self, buffer: u64, offset: u64, out: &mut [u8]) -> bool {
        if buffer & ADDRESS_TAG != 0 {
            return self.space.read((buffer & !ADDRESS_TAG) + offset, out).is_ok();
        }
        self.buffer(buffer).is_some_and(|b| b.read(offset, out).is_ok())
    }

    fn write(&self, buffer: u64, offset: u64, data: &[u8]) -> bool {
        if buffer & ADDRESS_TAG != 0 {
            return self.space.write((buffer & !ADDRESS_TAG) + offset, data).is_ok();
        }
        self.buffer(buffer).is_some_and(|b| b.write(offset, data).is_ok())
    }

    fn atomic(&self, buffer: u64, offset: u64, size: usize, update: &dyn Fn(u64) -> u64) -> Option<u64> {
        if buffer & ADDRESS_TAG != 0 {
            let address = (buffer & !ADDRESS_TAG) + offset;
            let r = self.space.resolve(address, size as u64).ok()?;
            return r.buffer.atomic(r.offset, size, update).ok();
        }
        self.buffer(buffer)?.atomic(offset, size, update).ok()
    }
}

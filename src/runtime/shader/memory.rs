//! The shader library's view of device memory for one dispatch: [`DispatchMemory`] implements
//! [`crate::shader::Memory`] over `src/memory`. Descriptor bindings are resolved once, when the
//! dispatch starts, to (buffer, offset after dynamic offsets, range); device addresses
//! (buffer device address) are resolved per access through the address space's checked
//! resolve, so a null, unmapped or freed address is a fault, never a host access.
//!
//! This module only maps; it reports nothing (the dispatch turns faults into diagnostics).
//!
//! `resolve_binding` is the one place a descriptor becomes something the shader can reach, and
//! `DispatchMemory::new` the one loop that collects them. Storage images reach the library
//! through `Memory::image`, not as buffer regions: they are kept in `images`, and their texel
//! reads and writes arrive with an id tagged `IMAGE_TAG`. Texel buffers are images to the
//! library too (one row of texels), but their memory is a buffer: kept in `texels`, their
//! ids index `buffers` like descriptor buffers.
use std::sync::Arc;

use crate::accel::DeviceView;
use crate::memory::{AddressSpace, Buffer};
use crate::runtime::accel::inputs::DeviceInputs;
use crate::runtime::descriptor::{is_dynamic, Descriptor};
use crate::runtime::image::{storage_image_binding, texel_buffer_binding, Image};
use crate::shader::{ImageBinding, Memory, Region};

use super::BoundSet;

/// Buffer ids at or above this are device-address resolutions: the id is the buffer's device
/// address with this bit set. Ids below it index `DispatchMemory::buffers` (descriptors).
const ADDRESS_TAG: u64 = 1 << 63;

/// Ids with this bit (and not `ADDRESS_TAG`) name a storage image: the low bits index
/// `DispatchMemory::images`. Address ids always carry `ADDRESS_TAG` (checked first) and
/// descriptor buffer ids are small indices, so the three kinds cannot collide.
const IMAGE_TAG: u64 = 1 << 62;

/// (set, binding, array element) of one resolved descriptor.
type ElementKey = (u32, u32, u32);

/// One dispatch's memory: the buffers its descriptors name, and the device's address space.
pub struct DispatchMemory<'a> {
    space: &'a AddressSpace,
    /// ((set, binding, array element), region) for every buffer element the pipeline's
    /// bindings have that resolved.
    regions: Vec<(ElementKey, Region)>,
    /// ((set, binding), elements) of every buffer binding: the length a runtime array takes.
    counts: Vec<((u32, u32), u32)>,
    /// The buffers `regions` refer to, by `Region::buffer`.
    buffers: Vec<Arc<Buffer>>,
    /// ((set, binding), image, its view for the library) for every storage image that resolved;
    /// the binding's id is `IMAGE_TAG | index`.
    images: Vec<(ElementKey, Arc<Image>, ImageBinding)>,
    /// ((set, binding), view) of every texel buffer: texels live in `buffers` (the view's
    /// `buffer` id indexes it), so reads and writes take the descriptor-buffer path.
    texels: Vec<(ElementKey, ImageBinding)>,
    /// ((set, binding, array element), device address) of every acceleration-structure
    /// descriptor.
    structures: Vec<(ElementKey, u64)>,
    /// Ray queries follow structure addresses (and each TLAS's BLAS references) through the
    /// same view builds use, which pins the buffers it hands out for the dispatch.
    device: DeviceInputs<'a>,
}

/// What a used binding resolved to.
enum Resolved {
    Buffer(Arc<Buffer>, u64, u64),
    Image(Arc<Image>, ImageBinding),
    /// A texel buffer: its buffer and its view (whose id is filled in when stored).
    Texel(Arc<Buffer>, ImageBinding),
    Structure(u64),
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
    /// An image descriptor that is not a usable storage image: a sampler or sampled image, a
    /// view or image destroyed, no memory bound, or several levels in the view.
    Image,
}

/// The bindings a dispatch uses that did not resolve, and why.
pub type Missing = Vec<((u32, u32), Unresolved)>;

impl<'a> DispatchMemory<'a> {
    /// Resolve every (set, binding) the pipeline uses against the bound sets. Bindings that do
    /// not resolve are returned beside the memory: the shader sees them as unbound (each access
    /// a contained fault).
    pub fn new(space: &'a AddressSpace, sets: &[Option<BoundSet>], used: &[(u32, u32)]) -> (Self, Missing) {
        let device = DeviceInputs::new(space, "vkCmdDispatch");
        let mut m = DispatchMemory { space, regions: Vec::new(), counts: Vec::new(), buffers: Vec::new(), images: Vec::new(), texels: Vec::new(), structures: Vec::new(), device };
        let mut missing = Vec::new();
        for &(set, binding) in used {
            if m.array(sets, set, binding) {
                continue;
            }
            match resolve_binding(sets, set, binding, 0, IMAGE_TAG | m.images.len() as u64) {
                Ok(r) => m.store((set, binding, 0), r),
                Err(e) => missing.push(((set, binding), e)),
            }
        }
        (m, missing)
    }

    /// Keeps what element `key` resolved to.
    fn store(&mut self, key: ElementKey, resolved: Resolved) {
        match resolved {
            Resolved::Buffer(buffer, offset, len) => {
                self.regions.push((key, Region { buffer: self.buffers.len() as u64, offset, len }));
                self.buffers.push(buffer);
            }
            Resolved::Image(image, view) => self.images.push((key, image, view)),
            Resolved::Texel(buffer, view) => {
                self.texels.push((key, ImageBinding { buffer: self.buffers.len() as u64, ..view }));
                self.buffers.push(buffer);
            }
            Resolved::Structure(address) => self.structures.push((key, address)),
        }
    }

    /// Resolves every element of a binding with more than one descriptor and returns true;
    /// false for a single descriptor. An array's elements need not all be valid (partially
    /// bound, or simply not used by this dispatch): one that does not resolve is reported by
    /// the access that reaches it, as an unbound fault naming the element.
    fn array(&mut self, sets: &[Option<BoundSet>], set: u32, binding: u32) -> bool {
        let Some(bound) = sets.get(set as usize).and_then(Option::as_ref) else { return false };
        let Some(elements) = bound.set.binding(binding) else { return false };
        if elements.len() == 1 {
            return false;
        }
        self.counts.push(((set, binding), elements.len() as u32));
        for e in 0..elements.len() as u32 {
            if let Ok(r) = resolve_binding(sets, set, binding, e, IMAGE_TAG | self.images.len() as u64) {
                self.store((set, binding, e), r);
            }
        }
        true
    }

    /// The buffer of a descriptor region (offsets the library passes are buffer-relative).
    fn buffer(&self, id: u64) -> Option<&Buffer> {
        self.buffers.get(usize::try_from(id).ok()?).map(|b| &**b)
    }

    /// The image of a storage-image id (`IMAGE_TAG | index`).
    fn image_of(&self, id: u64) -> Option<&Image> {
        self.images.get(usize::try_from(id & !IMAGE_TAG).ok()?).map(|(_, image, _)| &**image)
    }
}

/// The buffer range a bound descriptor gives the shader: array element `element` of the
/// binding, dynamic offset applied, or the storage image it names (its texels under id
/// `image_id`). Dynamic offsets are ordered by binding number, then array element.
fn resolve_binding(sets: &[Option<BoundSet>], set: u32, binding: u32, element: u32, image_id: u64) -> Result<Resolved, Unresolved> {
    let bound = sets.get(set as usize).and_then(Option::as_ref).ok_or(Unresolved::NotBound)?;
    let layout = &bound.set.layout;
    let lb = layout.binding(binding).ok_or(Unresolved::NotBound)?;
    let dynamic = if is_dynamic(lb.descriptor_type) {
        let index: u32 = layout.bindings.iter().take_while(|b| b.binding < binding).filter(|b| is_dynamic(b.descriptor_type)).map(|b| b.count).sum();
        bound.dynamic_offsets.get((index + element) as usize).copied().unwrap_or(0) as u64
    } else {
        0
    };
    match bound.set.descriptor(binding, element).ok_or(Unresolved::NotBound)? {
        d @ Descriptor::Buffer { .. } => {
            let (buffer, offset, len) = d.buffer_range(dynamic).ok_or(Unresolved::Empty)?;
            match offset.checked_add(len) {
                Some(end) if end <= buffer.size => Ok(Resolved::Buffer(buffer, offset, len)),
                _ => Err(Unresolved::PastEnd { offset, size: buffer.size }),
            }
        }
        d @ Descriptor::StorageImage { .. } => {
            let (image, view) = storage_image_binding(&d, image_id).ok_or(Unresolved::Image)?;
            Ok(Resolved::Image(image, view))
        }
        d @ Descriptor::AccelerationStructure { .. } => {
            let address = d.acceleration_structure().and_then(|s| s.address()).ok_or(Unresolved::Empty)?;
            Ok(Resolved::Structure(address))
        }
        // A PTLAS descriptor holds the blob's address; traversal recognises the blob from its
        // bytes. Address 0 is the null descriptor: unbound, as for a destroyed structure.
        Descriptor::PartitionedAccelerationStructure { address } if address != 0 => Ok(Resolved::Structure(address)),
        d @ Descriptor::TexelBuffer { .. } => {
            let (buffer, view) = texel_buffer_binding(&d, 0).ok_or(Unresolved::Empty)?;
            Ok(Resolved::Texel(buffer, view))
        }
        // Samplers and sampled images: the library has no sampling.
        Descriptor::Image { .. } => Err(Unresolved::Image),
        _ => Err(Unresolved::Empty),
    }
}

impl Memory for DispatchMemory<'_> {
    fn binding(&self, set: u32, binding: u32) -> Option<Region> {
        self.binding_element(set, binding, 0)
    }

    fn binding_element(&self, set: u32, binding: u32, element: u32) -> Option<Region> {
        self.regions.iter().find(|(k, _)| *k == (set, binding, element)).map(|(_, r)| *r)
    }

    fn binding_count(&self, set: u32, binding: u32) -> u32 {
        self.counts.iter().find(|(k, _)| *k == (set, binding)).map_or(1, |(_, n)| *n)
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
        if buffer & IMAGE_TAG != 0 {
            return self.image_of(buffer).is_some_and(|i| i.storage.read(offset, out).is_ok());
        }
        self.buffer(buffer).is_some_and(|b| b.read(offset, out).is_ok())
    }

    fn write(&self, buffer: u64, offset: u64, data: &[u8]) -> bool {
        if buffer & ADDRESS_TAG != 0 {
            return self.space.write((buffer & !ADDRESS_TAG) + offset, data).is_ok();
        }
        if buffer & IMAGE_TAG != 0 {
            return self.image_of(buffer).is_some_and(|i| i.storage.write(offset, data).is_ok());
        }
        self.buffer(buffer).is_some_and(|b| b.write(offset, data).is_ok())
    }

    fn host_span(&self, buffer: u64, offset: u64, len: u64) -> Option<usize> {
        if buffer & (ADDRESS_TAG | IMAGE_TAG) != 0 {
            return None;
        }
        self.buffer(buffer)?.host_span(offset, len)
    }

    fn atomic(&self, buffer: u64, offset: u64, size: usize, update: &dyn Fn(u64) -> u64) -> Option<u64> {
        if buffer & ADDRESS_TAG != 0 {
            let address = (buffer & !ADDRESS_TAG) + offset;
            let r = self.space.resolve(address, size as u64).ok()?;
            return r.buffer.atomic(r.offset, size, update).ok();
        }
        // Image atomics (OpImageTexelPointer): the executor has checked the texel's format.
        if buffer & IMAGE_TAG != 0 {
            return self.image_of(buffer)?.storage.atomic(offset, size, update).ok();
        }
        self.buffer(buffer)?.atomic(offset, size, update).ok()
    }

    fn acceleration_structure(&self, set: u32, binding: u32) -> Option<u64> {
        self.acceleration_structure_element(set, binding, 0)
    }

    fn acceleration_structure_element(&self, set: u32, binding: u32, element: u32) -> Option<u64> {
        self.structures.iter().find(|(k, _)| *k == (set, binding, element)).map(|(_, a)| *a)
    }

    fn acceleration_structures(&self) -> Option<&dyn DeviceView> {
        Some(&self.device)
    }

    fn image(&self, set: u32, binding: u32) -> Option<ImageBinding> {
        self.image_element(set, binding, 0)
    }

    fn image_element(&self, set: u32, binding: u32, element: u32) -> Option<ImageBinding> {
        let key = (set, binding, element);
        let image = self.images.iter().find(|(k, _, _)| *k == key).map(|(_, _, view)| *view);
        image.or_else(|| self.texels.iter().find(|(k, _)| *k == key).map(|(_, view)| *view))
    }
}

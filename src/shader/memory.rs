//! How a shader sees device memory: the [`Memory`] trait, the [`Fault`]s an access can raise,
//! and [`HostMemory`], a Vec-backed implementation for tests and benches.
//!
//! The executor resolves each descriptor binding once per dispatch into a [`Region`] and checks
//! every access against the region's length itself; only in-range accesses reach
//! [`Memory::read`] / [`Memory::write`] / [`Memory::atomic`]. Device addresses
//! (PhysicalStorageBuffer64) are resolved per access through [`Memory::address`]. A failed
//! check is a [`Fault`]: the load reads zero, the store or atomic is dropped, execution goes on.
//! Storage images ([`Memory::image`], [`ImageBinding`]) are resolved once per dispatch too;
//! their texels are read and written through the same `read`/`write`, after the executor has
//! checked the coordinates against the view (robustness: an outside read gives zero, an
//! outside write is dropped, both are faults).
//! Ray queries reach acceleration structures through the two provided methods at the end of
//! the trait; a structure that cannot be resolved or parsed is a fault too, and the query
//! finds nothing.
use std::sync::atomic::{AtomicU64, Ordering};

use crate::accel::DeviceView;

/// A range of one buffer, as a descriptor or an address resolves to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Region {
    /// The implementation's own name for the buffer (an index, a handle value): passed back to
    /// `read`/`write`/`atomic` unchanged.
    pub buffer: u64,
    /// Where the range starts inside the buffer.
    pub offset: u64,
    /// Bytes the shader may access from `offset` (a descriptor's range).
    pub len: u64,
}

/// The device memory a dispatch reads and writes. Implementations must be `Sync`: workgroups run
/// in parallel. Offsets passed to `read`/`write`/`atomic` are absolute within the buffer and
/// lie inside a region this trait returned; returning `false`/`None` still reports a fault
/// (for memory freed under a running dispatch, say).
pub trait Memory: Sync {
    /// The region bound at (set, binding), after dynamic offsets; None when nothing is bound.
    fn binding(&self, set: u32, binding: u32) -> Option<Region>;
    /// Element `element` of an array of buffer descriptors at (set, binding); None when that
    /// element has nothing bound. The default knows single descriptors only.
    fn binding_element(&self, set: u32, binding: u32, element: u32) -> Option<Region> {
        if element == 0 {
            self.binding(set, binding)
        } else {
            None
        }
    }
    /// How many array elements the binding at (set, binding) has as bound (the length a
    /// runtime descriptor array of buffers or images takes). The default knows single descriptors only.
    fn binding_count(&self, set: u32, binding: u32) -> u32 {
        let _ = (set, binding);
        1
    }
    /// The region of the one live buffer containing `[address, address + len)`, with `offset`
    /// the position of `address` in that buffer and `len` the bytes from there to the buffer's
    /// end; None for an unmapped or null address.
    fn address(&self, address: u64, len: u64) -> Option<Region>;
    fn read(&self, buffer: u64, offset: u64, out: &mut [u8]) -> bool;
    fn write(&self, buffer: u64, offset: u64, data: &[u8]) -> bool;
    /// Atomically replaces the `size`-byte (4 or 8) little-endian value at `offset` with
    /// `update(old)` and returns `old`.
    fn atomic(&self, buffer: u64, offset: u64, size: usize, update: &dyn Fn(u64) -> u64) -> Option<u64>;
    /// The host address of bytes [offset, offset + len) of `buffer`, when they are ordinary
    /// host memory, in order, that native code may load from and store to directly for the
    /// rest of the dispatch (exactly what `read`/`write` would do there, never a fault). None
    /// keeps every access on `read`/`write`.
    fn host_span(&self, _buffer: u64, _offset: u64, _len: u64) -> Option<usize> {
        None
    }

    /// Ray queries: the device address of the acceleration structure bound at (set, binding)
    /// (an `accelerationStructureEXT` descriptor), resolved once per dispatch; None when
    /// nothing is bound (a query on it then faults and finds nothing). The default binds none.
    fn acceleration_structure(&self, _set: u32, _binding: u32) -> Option<u64> {
        None
    }

    /// Element `element` of an array of acceleration-structure descriptors (its length is
    /// [`Memory::binding_count`]). The default knows single descriptors only.
    fn acceleration_structure_element(&self, set: u32, binding: u32, element: u32) -> Option<u64> {
        if element == 0 {
            self.acceleration_structure(set, binding)
        } else {
            None
        }
    }

    /// Ray queries: where traversal finds structures, keyed by device address.
    /// `DeviceView::acceleration_structure(address)` must give the bytes of the live structure
    /// starting exactly at `address` (the one a query is initialised with, from a descriptor
    /// or `OpConvertUToAccelerationStructureKHR`, and every BLAS its instances reference), and
    /// None for an address that is not one; `bytes` serves instances stored by pointer. The
    /// default has no structures: every ray query faults and finds nothing.
    fn acceleration_structures(&self) -> Option<&dyn DeviceView> {
        None
    }

    /// The storage image bound at (set, binding): its format and geometry, with texel reads
    /// and writes going through `read`/`write` at `ImageBinding::buffer`. None when nothing is
    /// bound (the default, for implementations without images).
    fn image(&self, set: u32, binding: u32) -> Option<ImageBinding> {
        let _ = (set, binding);
        None
    }

    /// Element `element` of an array of storage images or texel buffers at (set, binding)
    /// (its length is [`Memory::binding_count`]). The default knows single images only.
    fn image_element(&self, set: u32, binding: u32, element: u32) -> Option<ImageBinding> {
        if element == 0 {
            self.image(set, binding)
        } else {
            None
        }
    }
}

/// Texel formats of storage images the executor converts to and from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    R32Uint,
    R32Sint,
    R32Sfloat,
    Rgba32Uint,
    Rgba32Sint,
    Rgba32Sfloat,
    /// Four bytes, each `round(clamp(v, 0, 1) * 255)`.
    Rgba8Unorm,
}

impl ImageFormat {
    /// Bytes of one texel.
    pub fn texel_size(self) -> u32 {
        match self {
            ImageFormat::R32Uint | ImageFormat::R32Sint | ImageFormat::R32Sfloat | ImageFormat::Rgba8Unorm => 4,
            _ => 16,
        }
    }
}

/// One storage-image view as a shader sees it: a linear array of texels inside one buffer-like
/// allocation. Texel (x, y, z, layer) is at `offset + layer * layer_pitch + z * slice_pitch +
/// y * row_pitch + x * texel_size`; coordinates outside `extent`/`layers` are out of bounds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageBinding {
    /// The implementation's name for the memory holding the texels (passed back to
    /// `read`/`write` unchanged).
    pub buffer: u64,
    /// Where texel (0, 0, 0) of the view's first layer is.
    pub offset: u64,
    pub format: ImageFormat,
    /// Width, height, depth of the view's level (1 for dimensions the image lacks).
    pub extent: [u32; 3],
    /// Array layers of the view (1 when not arrayed).
    pub layers: u32,
    pub row_pitch: u64,
    pub slice_pitch: u64,
    pub layer_pitch: u64,
}

impl ImageBinding {
    /// A tightly packed image at `offset` of `buffer` (what tests and [`HostMemory`] use).
    pub fn packed(buffer: u64, offset: u64, format: ImageFormat, extent: [u32; 3], layers: u32) -> ImageBinding {
        let row_pitch = extent[0] as u64 * format.texel_size() as u64;
        let slice_pitch = row_pitch * extent[1] as u64;
        ImageBinding { buffer, offset, format, extent, layers, row_pitch, slice_pitch, layer_pitch: slice_pitch * extent[2] as u64 }
    }

    /// Byte offset of texel (x, y, z, layer) from `offset`, None when outside the view.
    pub fn texel_offset(&self, x: i64, y: i64, z: i64, layer: i64) -> Option<u64> {
        let inside = |v: i64, n: u32| v >= 0 && v < n as i64;
        if !(inside(x, self.extent[0]) && inside(y, self.extent[1]) && inside(z, self.extent[2]) && inside(layer, self.layers)) {
            return None;
        }
        let t = self.format.texel_size() as u64;
        Some(layer as u64 * self.layer_pitch + z as u64 * self.slice_pitch + y as u64 * self.row_pitch + x as u64 * t)
    }
}

/// What went wrong with one access.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FaultKind {
    /// Outside the descriptor's range, the push-constant block, or shared/lane memory.
    OutOfBounds,
    /// A descriptor binding the shader uses has nothing bound.
    Unbound,
    /// A descriptor-array index past the array's end (the access is dropped or reads zero).
    ArrayIndex,
    /// A device address no live buffer contains (including null).
    Unmapped,
    /// The memory refused an in-range access.
    Refused,
    /// A ray query was initialised with bytes that fail the structure's header check (never
    /// built, a failed build, another driver's format, a destroyed structure).
    InvalidStructure,
    /// A ray-query instruction other than Initialize on a query never initialised.
    Uninitialized,
    /// A top-level structure's instance references an address that is no built bottom-level
    /// structure (`at`: that address); traversal treats the instance as absent. Reported once
    /// per workgroup, not per ray; the dispatch turns it into one diagnostic.
    UnresolvedInstance,
}

/// Which memory a faulting access went to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FaultSpace {
    Binding { set: u32, binding: u32 },
    /// One element of an array of descriptors; `at` is the offset inside that element.
    ArrayElement { set: u32, binding: u32, element: u32 },
    DeviceAddress,
    PushConstant,
    Workgroup,
    Invocation,
    /// A ray query: `at` is the structure's device address (Unmapped, InvalidStructure) or
    /// the query variable's lane-frame offset (Uninitialized).
    RayQuery,
}

/// One contained memory fault: what, where, and which invocation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Fault {
    pub kind: FaultKind,
    pub space: FaultSpace,
    /// Byte offset in the binding / block, or the device address.
    pub at: u64,
    pub len: u32,
    pub write: bool,
    pub workgroup: [u32; 3],
    /// LocalInvocationIndex of the faulting invocation.
    pub invocation: u32,
}

impl std::fmt::Display for Fault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let what = if self.write { "write" } else { "read" };
        write!(f, "{:?} {what} of {} bytes at {:#x} in {:?} (workgroup {:?}, invocation {})",
            self.kind, self.len, self.at, self.space, self.workgroup, self.invocation)
    }
}

/// Buffers in host memory, each at a fake device address, with word-granular atomic storage so
/// concurrent workgroups never race at the Rust level.
#[derive(Default)]
pub struct HostMemory {
    buffers: Vec<HostBuffer>,
    bindings: Vec<((u32, u32), Region)>,
    /// Elements of descriptor arrays: ((set, binding, element), region); element 0 of an
    /// array is in `bindings`.
    elements: Vec<((u32, u32, u32), Region)>,
    /// ((set, binding, array element), view).
    images: Vec<((u32, u32, u32), ImageBinding)>,
}

struct HostBuffer {
    address: u64,
    len: u64,
    words: Vec<AtomicU64>,
}

impl HostMemory {
    pub fn new() -> HostMemory {
        HostMemory::default()
    }

    /// Adds a buffer holding `bytes`; returns its index. Device addresses start at 1 MiB and
    /// leave a gap after each buffer so overruns land nowhere.
    pub fn add_buffer(&mut self, bytes: &[u8]) -> usize {
        let address = self.buffers.last().map_or(1 << 20, |b| (b.address + b.len + 0x1_0000) & !0xFFFF);
        let words = bytes
            .chunks(8)
            .map(|c| {
                let mut w = [0u8; 8];
                w[..c.len()].copy_from_slice(c);
                AtomicU64::new(u64::from_le_bytes(w))
            })
            .collect();
        self.buffers.push(HostBuffer { address, len: bytes.len() as u64, words });
        self.buffers.len() - 1
    }

    /// Binds the whole of buffer `index` at (set, binding).
    pub fn bind(&mut self, set: u32, binding: u32, index: usize) {
        let len = self.buffers[index].len;
        self.bind_range(set, binding, index, 0, len);
    }

    pub fn bind_range(&mut self, set: u32, binding: u32, index: usize, offset: u64, len: u64) {
        self.bindings.retain(|(k, _)| *k != (set, binding));
        self.bindings.push(((set, binding), Region { buffer: index as u64, offset, len }));
    }

    /// Binds the whole of buffer `index` as element `element` of the array at (set, binding).
    pub fn bind_element(&mut self, set: u32, binding: u32, element: u32, index: usize) {
        if element == 0 {
            return self.bind(set, binding, index);
        }
        let region = Region { buffer: index as u64, offset: 0, len: self.buffers[index].len };
        self.elements.retain(|(k, _)| *k != (set, binding, element));
        self.elements.push(((set, binding, element), region));
    }

    /// Binds a storage image at (set, binding); its texels live in buffer `image.buffer`.
    pub fn bind_image(&mut self, set: u32, binding: u32, image: ImageBinding) {
        self.bind_image_element(set, binding, 0, image);
    }

    /// Binds a storage image as element `element` of the array at (set, binding).
    pub fn bind_image_element(&mut self, set: u32, binding: u32, element: u32, image: ImageBinding) {
        self.images.retain(|(k, _)| *k != (set, binding, element));
        self.images.push(((set, binding, element), image));
    }

    pub fn device_address(&self, index: usize) -> u64 {
        self.buffers[index].address
    }

    /// The current contents of buffer `index`.
    pub fn bytes(&self, index: usize) -> Vec<u8> {
        let b = &self.buffers[index];
        let mut out: Vec<u8> =
            b.words.iter().flat_map(|w| w.load(Ordering::Relaxed).to_le_bytes()).collect();
        out.truncate(b.len as usize);
        out
    }

    fn buffer(&self, buffer: u64, offset: u64, len: usize) -> Option<&HostBuffer> {
        let b = self.buffers.get(usize::try_from(buffer).ok()?)?;
        (offset.checked_add(len as u64)? <= b.len).then_some(b)
    }
}

/// Replaces bytes [shift, shift + n) of a word; one CAS keeps neighbouring bytes that other
/// workgroups write intact.
fn merge_word(word: &AtomicU64, shift: u32, n: u32, value: u64) {
    let mask = if n >= 8 { !0u64 } else { ((1u64 << (8 * n)) - 1) << (8 * shift) };
    let value = (value << (8 * shift)) & mask;
    let _ = word.fetch_update(Ordering::Relaxed, Ordering::Relaxed, |w| Some((w & !mask) | value));
}

impl Memory for HostMemory {
    fn binding(&self, set: u32, binding: u32) -> Option<Region> {
        self.bindings.iter().find(|(k, _)| *k == (set, binding)).map(|(_, r)| *r)
    }

    fn binding_element(&self, set: u32, binding: u32, element: u32) -> Option<Region> {
        if element == 0 {
            return self.binding(set, binding);
        }
        self.elements.iter().find(|(k, _)| *k == (set, binding, element)).map(|(_, r)| *r)
    }

    fn binding_count(&self, set: u32, binding: u32) -> u32 {
        let buffers = self.elements.iter().filter(|((s, b, _), _)| (*s, *b) == (set, binding)).map(|((_, _, e), _)| e + 1);
        let images = self.images.iter().filter(|((s, b, _), _)| (*s, *b) == (set, binding)).map(|((_, _, e), _)| e + 1);
        buffers.chain(images).max().unwrap_or(1)
    }

    fn image(&self, set: u32, binding: u32) -> Option<ImageBinding> {
        self.image_element(set, binding, 0)
    }

    fn image_element(&self, set: u32, binding: u32, element: u32) -> Option<ImageBinding> {
        self.images.iter().find(|(k, _)| *k == (set, binding, element)).map(|(_, r)| *r)
    }

    fn address(&self, address: u64, len: u64) -> Option<Region> {
        self.buffers.iter().enumerate().find_map(|(i, b)| {
            let end = address.checked_add(len)?;
            (address >= b.address && end <= b.address + b.len).then(|| Region {
                buffer: i as u64,
                offset: address - b.address,
                len: b.address + b.len - address,
            })
        })
    }

    fn read(&self, buffer: u64, offset: u64, out: &mut [u8]) -> bool {
        let Some(b) = self.buffer(buffer, offset, out.len()) else { return false };
        for (i, o) in out.iter_mut().enumerate() {
            let at = offset + i as u64;
            *o = (b.words[(at / 8) as usize].load(Ordering::Relaxed) >> (8 * (at % 8))) as u8;
        }
        true
    }

    fn write(&self, buffer: u64, offset: u64, data: &[u8]) -> bool {
        let Some(b) = self.buffer(buffer, offset, data.len()) else { return false };
        let mut i = 0;
        while i < data.len() {
            let at = offset + i as u64;
            let shift = (at % 8) as u32;
            let n = (8 - shift as usize).min(data.len() - i);
            let mut v = [0u8; 8];
            v[..n].copy_from_slice(&data[i..i + n]);
            merge_word(&b.words[(at / 8) as usize], shift, n as u32, u64::from_le_bytes(v));
            i += n;
        }
        true
    }

    fn host_span(&self, buffer: u64, offset: u64, len: u64) -> Option<usize> {
        // The words hold the bytes in order only on a little-endian host.
        let b = self.buffer(buffer, offset, usize::try_from(len).ok()?).filter(|_| cfg!(target_endian = "little"))?;
        Some(b.words.as_ptr() as usize + offset as usize)
    }

    fn atomic(&self, buffer: u64, offset: u64, size: usize, update: &dyn Fn(u64) -> u64) -> Option<u64> {
        let b = self.buffer(buffer, offset, size)?;
        let shift = (offset % 8) as u32;
        if shift as usize + size > 8 {
            return None; // misaligned atomics are invalid SPIR-V; refuse rather than tear
        }
        let mask = if size >= 8 { !0u64 } else { (1u64 << (8 * size)) - 1 };
        let word = &b.words[(offset / 8) as usize];
        let old = word
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |w| {
                let old = (w >> (8 * shift)) & mask;
                let new = update(old) & mask;
                Some((w & !(mask << (8 * shift))) | (new << (8 * shift)))
            })
            .unwrap_or(0);
        Some((old >> (8 * shift)) & mask)
    }
}

//! Acceleration structures in the object model: the `VkAccelerationStructureKHR` view object,
//! the owned (lowered) description of a build, and the execution of builds, copies and property
//! queries — with the valid-usage checks the driver can see, including those about data in
//! device memory that no validation layer can check.
//!
//! An acceleration structure is only a view (buffer, offset, size, type): its content lives in
//! device memory and is produced by `crate::accel`. Nothing about a structure's content is kept
//! here (principle 1).
use std::sync::Arc;

use ash::vk;
use rayon::prelude::*;

use crate::accel::{self, AsType, BuildFlags, DeviceView as _, GeometryFlags, GeometryShape, IndexType, VertexFormat};
use crate::diag;
use crate::memory::view::DeviceMemoryView;
use crate::memory::{AccessError, AddressSpace, Buffer};

/// Required alignment of scratch addresses (minAccelerationStructureScratchOffsetAlignment).
pub const SCRATCH_ALIGNMENT: u64 = 128;
/// Alignment of acceleration-structure offsets and addresses.
pub const STRUCTURE_ALIGNMENT: u64 = 256;

/// One `VkAccelerationStructureKHR`.
pub struct AccelerationStructure {
    pub buffer: Arc<Buffer>,
    pub offset: u64,
    pub size: u64,
    /// VkAccelerationStructureTypeKHR as created (TOP_LEVEL 0, BOTTOM_LEVEL 1, GENERIC 2).
    pub create_type: vk::AccelerationStructureTypeKHR,
    pub create_flags: vk::AccelerationStructureCreateFlagsKHR,
}

impl AccelerationStructure {
    /// Device address: the buffer's address plus the offset (buffers are placed on 256-aligned
    /// addresses, so this is 256-aligned too).
    pub fn address(&self) -> Option<u64> {
        self.buffer.device_address().map(|a| a + self.offset)
    }

    /// The structure's bytes (shared view).
    pub fn bytes(&self) -> Result<&[u8], AccessError> {
        self.buffer.bytes(self.offset, self.size)
    }

    /// Identity of the backing memory and the byte range, for overlap checks.
    pub fn memory_range(&self, len: u64) -> Option<(usize, u64, u64)> {
        self.buffer.memory_range(self.offset, len.min(self.size))
    }

    /// Whether the buffer is bound to host-visible memory (all Arbor memory is).
    pub fn host_visible(&self) -> bool {
        self.buffer.memory().is_some()
    }
}

/// Owned geometry description captured at record time (addresses, not data: the data is read
/// when the command executes).
#[derive(Clone, Debug)]
pub enum GeometryDesc {
    Triangles {
        vertex_format: vk::Format,
        vertex_data: u64,
        vertex_stride: u64,
        max_vertex: u32,
        index_type: vk::IndexType,
        index_data: u64,
        transform_data: u64,
    },
    Aabbs {
        data: u64,
        stride: u64,
    },
    Instances {
        array_of_pointers: bool,
        data: u64,
    },
    /// A geometry type Arbor does not support.
    Unsupported(vk::GeometryTypeKHR),
}

#[derive(Clone, Debug)]
pub struct GeometryInfo {
    pub desc: GeometryDesc,
    pub flags: vk::GeometryFlagsKHR,
}

/// One `VkAccelerationStructureBuildRangeInfoKHR`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RangeInfo {
    pub primitive_count: u32,
    pub primitive_offset: u32,
    pub first_vertex: u32,
    pub transform_offset: u32,
}

impl RangeInfo {
    pub fn from_bytes(b: &[u8]) -> RangeInfo {
        let w = |i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        RangeInfo { primitive_count: w(0), primitive_offset: w(4), first_vertex: w(8), transform_offset: w(12) }
    }
}

/// Where a build's range records come from.
#[derive(Clone, Debug)]
pub enum Ranges {
    /// Given by the application at record time (direct and host builds).
    Direct(Vec<RangeInfo>),
    /// Read from device memory when the command executes (indirect builds).
    Indirect { address: u64, stride: u32, max_primitive_counts: Vec<u32> },
}

/// Owned description of one element of `pInfos`.
#[derive(Clone)]
pub struct BuildInfo {
    pub ty: vk::AccelerationStructureTypeKHR,
    pub flags: vk::BuildAccelerationStructureFlagsKHR,
    pub mode: vk::BuildAccelerationStructureModeKHR,
    pub src: Option<Arc<AccelerationStructure>>,
    /// Handle value of src as given (to report a dangling handle).
    pub src_handle: u64,
    pub dst: Option<Arc<AccelerationStructure>>,
    pub dst_handle: u64,
    pub scratch: u64,
    /// geometryCount as given (the arrays may have been missing).
    pub geometry_count: u32,
    pub geometries: Vec<GeometryInfo>,
    pub ranges: Ranges,
}

/// Where a build reads its inputs: device memory (device and indirect builds) or host memory
/// (host builds, where addresses are host pointers and instance references are handles).
pub trait InputMemory: accel::DeviceView {
    /// Input bytes at `address`; on device, also checks the containing buffer has `usage`.
    fn input(&self, address: u64, len: u64, usage: vk::BufferUsageFlags) -> Result<&[u8], InputError>;
    /// Scratch bytes: a mutable view, plus the backing memory range for overlap checks (device).
    ///
    /// # Safety
    /// No other view of the range may exist while the slice lives (checked by the caller's
    /// overlap checks on device; the application's obligation on the host).
    #[allow(clippy::mut_from_ref)] // exclusivity is the contract above, as in Buffer::bytes_mut
    unsafe fn scratch(&self, address: u64, len: u64) -> Result<&mut [u8], InputError>;
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
        self.view.acceleration_structure(reference)
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
    unsafe fn scratch(&self, address: u64, len: u64) -> Result<&mut [u8], InputError> {
        let r = self.space.resolve(address, len).map_err(InputError::Access)?;
        // SAFETY: the caller's contract (exclusive range); the buffer is pinned by `self.view`
        // below before the slice is handed out.
        let s = unsafe { r.buffer.bytes_mut(r.offset, len) }.map_err(InputError::Access)?;
        let (ptr, n) = (s.as_mut_ptr(), s.len());
        let _ = self.view.bytes(address, 0); // pin the buffer for the view's lifetime
        // SAFETY: same memory as `s`, kept alive by the pin above (the resolve found a live buffer
        // whose memory stays referenced by `r.buffer`, which the pin also references).
        Ok(unsafe { std::slice::from_raw_parts_mut(ptr, n) })
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

/// Outcome of a command that checks valid usage: `Err(LostDevice)` in strict mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeviceLost;

/// A violation found while executing: reported once with its VUID and the offending index.
/// `vuid` is either the part after `VUID-<command>-` or a full `VUID-...` of a structure rule.
fn violation(command: &str, vuid: &str, index: usize, message: &str) {
    let full = if vuid.starts_with("VUID-") { vuid.to_string() } else { format!("VUID-{command}-{vuid}") };
    diag::vuid(&full, command, &format!("pInfos[{index}]: {message}"));
}

fn to_as_type(t: vk::AccelerationStructureTypeKHR) -> Option<AsType> {
    match t {
        vk::AccelerationStructureTypeKHR::TOP_LEVEL => Some(AsType::TopLevel),
        vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL => Some(AsType::BottomLevel),
        _ => None,
    }
}

/// The size-query shape of a geometry; None for unsupported formats/types.
pub fn shape_of(g: &GeometryInfo) -> Option<GeometryShape> {
    Some(match &g.desc {
        GeometryDesc::Triangles { vertex_format, max_vertex, index_type, transform_data, .. } => GeometryShape::Triangles {
            format: VertexFormat::from_vk(vertex_format.as_raw())?,
            index_type: IndexType::from_vk(index_type.as_raw())?,
            max_vertex: *max_vertex,
            has_transform: *transform_data != 0,
        },
        GeometryDesc::Aabbs { .. } => GeometryShape::Aabbs,
        GeometryDesc::Instances { .. } => GeometryShape::Instances,
        GeometryDesc::Unsupported(_) => return None,
    })
}

/// vkGetAccelerationStructureBuildSizesKHR.
pub fn build_sizes(
    ty: vk::AccelerationStructureTypeKHR,
    flags: vk::BuildAccelerationStructureFlagsKHR,
    geometries: &[GeometryInfo],
    max_primitive_counts: &[u32],
) -> Option<accel::BuildSizes> {
    let ty = to_as_type(ty)?;
    let shapes: Option<Vec<_>> = geometries.iter().map(shape_of).collect();
    Some(accel::build_sizes(ty, BuildFlags(flags.as_raw()), &shapes?, max_primitive_counts))
}

/// A build whose checks passed: everything resolved, ready to run.
struct Prepared<'m> {
    index: usize,
    info: &'m BuildInfo,
    dst: Arc<AccelerationStructure>,
    ranges: Vec<RangeInfo>,
    scratch_len: u64,
    /// (memory id, start, end) of dst, scratch, src.
    dst_range: Option<(usize, u64, u64)>,
    scratch_range: Option<(usize, u64, u64)>,
    src_range: Option<(usize, u64, u64)>,
    /// Device addresses of the BLASes its instances reference (for 03706/03407).
    referenced: Vec<u64>,
    /// Memory ranges of every geometry input it reads (device builds).
    inputs: Vec<(usize, u64, u64)>,
}

fn overlaps(a: Option<(usize, u64, u64)>, b: Option<(usize, u64, u64)>) -> bool {
    match (a, b) {
        (Some((ma, sa, ea)), Some((mb, sb, eb))) => ma == mb && sa < eb && sb < ea,
        _ => false,
    }
}

/// Execute the builds of one command (`vkCmdBuildAccelerationStructures(Indirect)KHR` at queue
/// execution time, or `vkBuildAccelerationStructuresKHR` on the host). Invalid builds are
/// reported, skipped and their destination marked invalid; valid ones run in parallel on the
/// worker pool. Returns Err(DeviceLost) in strict mode when anything was invalid.
pub fn execute_builds(mem: &dyn InputMemory, infos: &[BuildInfo]) -> Result<(), DeviceLost> {
    let cmd = mem.command();
    let mut invalid = false;
    let mut prepared: Vec<Prepared> = Vec::new();
    for (i, info) in infos.iter().enumerate() {
        match prepare(mem, i, info) {
            Ok(p) => prepared.push(p),
            Err(()) => {
                invalid = true;
                if let Some(dst) = &info.dst {
                    mark_invalid(dst);
                }
            }
        }
    }
    // Aliasing between the regions of different elements (and dst vs its own scratch). Of each
    // overlapping pair at least the element that writes into the other's region is skipped, so
    // no two views handed to running builds overlap.
    let mut bad = vec![false; prepared.len()];
    for a in 0..prepared.len() {
        let pa = &prepared[a];
        if overlaps(pa.dst_range, pa.scratch_range) {
            violation(cmd, "dstAccelerationStructure-03703", pa.index, "dst overlaps its own scratch memory");
            bad[a] = true;
        }
        if pa.info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE && overlaps(pa.scratch_range, pa.src_range) {
            violation(cmd, "scratchData-03705", pa.index, "scratch overlaps its own srcAccelerationStructure");
            bad[a] = true;
        }
        for b in 0..prepared.len() {
            if a == b {
                continue;
            }
            let pb = &prepared[b];
            if overlaps(pa.dst_range, pb.dst_range) {
                violation(cmd, "dstAccelerationStructure-03702", pa.index, &format!("dst overlaps the dst of pInfos[{}]", pb.index));
                bad[a] = true;
            }
            if overlaps(pa.dst_range, pb.scratch_range) {
                violation(cmd, "dstAccelerationStructure-03703", pa.index, &format!("dst overlaps the scratch of pInfos[{}]", pb.index));
                bad[a] = true;
            }
            if pb.info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE && overlaps(pa.dst_range, pb.src_range) {
                violation(cmd, "dstAccelerationStructure-03701", pa.index, &format!("dst overlaps the src of pInfos[{}]", pb.index));
                bad[a] = true;
            }
            if overlaps(pa.scratch_range, pb.scratch_range) {
                violation(cmd, "scratchData-03704", pa.index, &format!("scratch overlaps the scratch of pInfos[{}]", pb.index));
                bad[a] = true;
            }
            if pb.info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE && overlaps(pa.scratch_range, pb.src_range) {
                violation(cmd, "scratchData-03705", pa.index, &format!("scratch overlaps the src of pInfos[{}]", pb.index));
                bad[a] = true;
            }
            if let Some(addr) = pa.dst.address() {
                let end = addr + pa.dst.size;
                if pb.referenced.iter().any(|&r| r >= addr && r < end) {
                    violation(cmd, "dstAccelerationStructure-03706", pa.index, &format!("dst is referenced by an instance of pInfos[{}]", pb.index));
                    bad[a] = true;
                }
            }
        }
    }
    // A build must not read what this command writes: inputs inside any element's dst or
    // scratch (no VUID names it; it is a write-after-read hazard within one command, and Arbor
    // will not hand out a shared view of bytes another view may write).
    for a in 0..prepared.len() {
        let pa = &prepared[a];
        if let Some(pb) = prepared.iter().find(|pb| pa.inputs.iter().any(|r| overlaps(Some(*r), pb.dst_range) || overlaps(Some(*r), pb.scratch_range))) {
            diag::vuid(
                "ARBOR-build-input-aliases-output",
                cmd,
                &format!("pInfos[{}]: a geometry input overlaps the dst or scratch memory of pInfos[{}]", pa.index, pb.index),
            );
            bad[a] = true;
        }
    }
    let mut runnable = Vec::new();
    for (p, b) in prepared.into_iter().zip(bad) {
        if b {
            invalid = true;
            mark_invalid(&p.dst);
        } else {
            runnable.push(p);
        }
    }
    // Small builds (`threads::runs_inline`: too little work to share among the pool's threads)
    // run on the queue thread itself, without a hand-off to the pool and back. Updates always
    // go to the pool: a refit splits even small trees across threads.
    let prims: u64 = runnable.iter().flat_map(|p| p.ranges.iter()).map(|r| r.primitive_count as u64).sum();
    let builds_only = runnable.iter().all(|p| p.info.mode != vk::BuildAccelerationStructureModeKHR::UPDATE);
    let small = builds_only && crate::threads::runs_inline(prims);
    let results: Vec<bool> = crate::threads::run_parallel(small, || runnable.par_iter().map(|p| run(mem, p)).collect());
    invalid |= results.iter().any(|ok| !ok);
    if invalid && diag::strict() {
        return Err(DeviceLost);
    }
    Ok(())
}

fn mark_invalid(dst: &AccelerationStructure) {
    // SAFETY: the destination range belongs to this command (its writes are the command's own);
    // the view ends with this call.
    if let Ok(bytes) = unsafe { dst.buffer.bytes_mut(dst.offset, dst.size.min(4096)) } {
        accel::mark_invalid(bytes);
    }
}

/// Check one element; report every violation found (once each) and return the resolved build.
fn prepare<'m>(mem: &dyn InputMemory, i: usize, info: &'m BuildInfo) -> Result<Prepared<'m>, ()> {
    let cmd = mem.command();
    let mut ok = true;
    let mut fail = |vuid: &str, msg: &str| {
        violation(cmd, vuid, i, msg);
        ok = false;
    };
    let update = info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE;
    let Some(dst) = info.dst.clone() else {
        fail("dstAccelerationStructure-03800", &format!("dstAccelerationStructure {:#x} is not a valid handle", info.dst_handle));
        return Err(());
    };
    let Some(ty) = to_as_type(info.ty) else {
        fail("pInfos-parameter", "type must be TOP_LEVEL or BOTTOM_LEVEL");
        return Err(());
    };
    if dst.create_type != info.ty && dst.create_type != vk::AccelerationStructureTypeKHR::GENERIC {
        let v = if ty == AsType::TopLevel { "pInfos-03699" } else { "pInfos-03700" };
        fail(v, "dstAccelerationStructure was created with another type");
    }
    if dst.buffer.memory().is_none() {
        fail("pInfos-03707", "dstAccelerationStructure is not bound to device memory");
        return Err(());
    }
    if mem.is_host() && !dst.host_visible() {
        fail("pInfos-03722", "dstAccelerationStructure is not bound to host-visible memory");
    }
    // Update-mode rules that the structure's own header lets us check.
    if update {
        match &info.src {
            None => fail("pInfos-04630", &format!("mode is UPDATE but srcAccelerationStructure {:#x} is not valid", info.src_handle)),
            Some(src) => {
                if src.buffer.memory().is_none() {
                    fail("pInfos-03708", "srcAccelerationStructure is not bound to device memory");
                } else {
                    match src.bytes().ok().and_then(accel::header) {
                        None => fail("pInfos-03667", "srcAccelerationStructure has not been built (or its last build was invalid)"),
                        Some(h) => {
                            if !h.flags.contains(BuildFlags::ALLOW_UPDATE) {
                                fail("pInfos-03667", "srcAccelerationStructure was not built with ALLOW_UPDATE");
                            }
                            if h.flags.0 != info.flags.as_raw() {
                                fail("pInfos-03759", "flags differ from the last build of srcAccelerationStructure");
                            }
                            if h.ty != ty {
                                fail("pInfos-03760", "type differs from the last build of srcAccelerationStructure");
                            }
                            if h.geometry_count as usize != info.geometries.len() {
                                fail("pInfos-03758", "geometryCount differs from the last build of srcAccelerationStructure");
                            }
                        }
                    }
                    if !Arc::ptr_eq(src, &dst) && overlaps(src.memory_range(src.size), dst.memory_range(dst.size)) {
                        fail("pInfos-03668", "srcAccelerationStructure and dstAccelerationStructure alias without being the same");
                    }
                }
            }
        }
    }
    if info.geometries.len() != info.geometry_count as usize {
        fail(
            "VUID-VkAccelerationStructureBuildGeometryInfoKHR-pGeometries-03788",
            "geometryCount is not 0 but both pGeometries and ppGeometries are NULL",
        );
        return Err(());
    }
    // Formats and types the size query needs, named by geometry.
    let mut shapes_ok = true;
    for (j, g) in info.geometries.iter().enumerate() {
        if shape_of(g).is_none() {
            let (v, what) = match &g.desc {
                GeometryDesc::Triangles { vertex_format, index_type, .. } if VertexFormat::from_vk(vertex_format.as_raw()).is_none() => (
                    "VUID-VkAccelerationStructureGeometryTrianglesDataKHR-vertexFormat-03797",
                    format!("vertex format {vertex_format:?} lacks ACCELERATION_STRUCTURE_VERTEX_BUFFER support (index type {index_type:?})"),
                ),
                GeometryDesc::Triangles { index_type, .. } => (
                    "VUID-VkAccelerationStructureGeometryTrianglesDataKHR-indexType-03798",
                    format!("index type {index_type:?} is not UINT16, UINT32 or NONE"),
                ),
                GeometryDesc::Unsupported(t) => ("VUID-VkAccelerationStructureGeometryKHR-geometryType-parameter", format!("geometry type {t:?} is not supported")),
                _ => ("VUID-VkAccelerationStructureGeometryKHR-geometryType-parameter", "unsupported geometry".to_string()),
            };
            fail(v, &format!("geometry {j}: {what}"));
            shapes_ok = false;
        }
    }
    if !shapes_ok {
        return Err(());
    }
    // Geometry types.
    if ty == AsType::TopLevel {
        if info.geometries.len() != 1 || !matches!(info.geometries[0].desc, GeometryDesc::Instances { .. }) {
            fail("VUID-VkAccelerationStructureBuildGeometryInfoKHR-type-03789", "a top-level build must have exactly one geometry of type INSTANCES");
        }
    } else if info.geometries.iter().any(|g| matches!(g.desc, GeometryDesc::Instances { .. })) {
        fail("VUID-VkAccelerationStructureBuildGeometryInfoKHR-type-03790", "a bottom-level build must not have INSTANCES geometry");
    } else if info.geometries.windows(2).any(|w| std::mem::discriminant(&w[0].desc) != std::mem::discriminant(&w[1].desc)) {
        fail("VUID-VkAccelerationStructureBuildGeometryInfoKHR-type-03791", "all geometries of a bottom-level build must have the same type");
    }
    // Range records.
    let ranges: Vec<RangeInfo> = match &info.ranges {
        Ranges::Direct(r) => r.clone(),
        Ranges::Indirect { address, stride, max_primitive_counts } => {
            let n = info.geometries.len() as u64;
            if address % 4 != 0 {
                fail("pIndirectDeviceAddresses-03648", &format!("indirect address {address:#x} is not a multiple of 4"));
                return Err(());
            }
            if stride % 4 != 0 {
                fail("pIndirectStrides-03787", &format!("indirect stride {stride} is not a multiple of 4"));
                return Err(());
            }
            let len = if n == 0 { 0 } else { (n - 1) * *stride as u64 + 16 };
            let mut out = Vec::with_capacity(n as usize);
            if n > 0 {
                match mem.input(*address, len, vk::BufferUsageFlags::INDIRECT_BUFFER) {
                    Ok(bytes) => {
                        for j in 0..n as usize {
                            let o = j * *stride as usize;
                            out.push(RangeInfo::from_bytes(&bytes[o..o + 16]));
                        }
                    }
                    Err(InputError::Usage(found)) => {
                        fail("pIndirectDeviceAddresses-03647", &format!("the buffer of the indirect records lacks INDIRECT_BUFFER usage (has {found:?})"));
                        return Err(());
                    }
                    Err(InputError::Access(e)) => {
                        fail("pIndirectDeviceAddresses-03646", &format!("indirect records [{address:#x}, +{len}) are not inside one buffer: {e}"));
                        return Err(());
                    }
                }
            }
            for (j, r) in out.iter().enumerate() {
                let max = max_primitive_counts.get(j).copied().unwrap_or(0);
                if r.primitive_count > max {
                    fail(
                        "ppMaxPrimitiveCounts-03653",
                        &format!("geometry {j}: indirect primitiveCount {} exceeds ppMaxPrimitiveCounts {max}", r.primitive_count),
                    );
                }
            }
            out
        }
    };
    if ranges.len() != info.geometries.len() {
        fail("ppBuildRangeInfos-03676", "the range array does not have geometryCount elements");
        return Err(());
    }
    // Sizes against our own query, with the counts the application sized for.
    let counts: Vec<u32> = match &info.ranges {
        Ranges::Indirect { max_primitive_counts, .. } => max_primitive_counts.clone(),
        Ranges::Direct(r) => r.iter().map(|r| r.primitive_count).collect(),
    };
    let sizes = match build_sizes(info.ty, info.flags, &info.geometries, &counts) {
        Some(s) => s,
        None => {
            fail(
                "VUID-VkAccelerationStructureGeometryTrianglesDataKHR-vertexFormat-03797",
                "a geometry has an unsupported type, vertex format or index type",
            );
            return Err(());
        }
    };
    let size_vuid = if matches!(info.ranges, Ranges::Indirect { .. }) { "pInfos-03652" } else { "pInfos-03675" };
    if update {
        // An update writes a structure of the source's size into dst.
        let src_used = info.src.as_ref().and_then(|s| s.bytes().ok().and_then(accel::header)).map(|h| h.used_size);
        if let Some(used) = src_used {
            if dst.size < used {
                fail(size_vuid, &format!("dstAccelerationStructure size {} is below the {used} bytes of the source", dst.size));
            }
        }
    } else if dst.size < sizes.acceleration_structure_size {
        fail(size_vuid, &format!("dstAccelerationStructure size {} is below the {} the size query requires", dst.size, sizes.acceleration_structure_size));
    }
    let scratch_len = if update { sizes.update_scratch_size } else { sizes.build_scratch_size };
    if info.scratch % SCRATCH_ALIGNMENT != 0 && !mem.is_host() {
        fail("pInfos-03710", &format!("scratchData {:#x} is not a multiple of {SCRATCH_ALIGNMENT}", info.scratch));
    }
    if mem.is_host() && scratch_len > 0 && info.scratch == 0 {
        let v = if update { "pInfos-03726" } else { "pInfos-03725" };
        fail(v, "scratchData.hostAddress is NULL");
    }
    let scratch_range = if mem.is_host() || scratch_len == 0 {
        None
    } else {
        match mem.input(info.scratch, scratch_len, vk::BufferUsageFlags::STORAGE_BUFFER) {
            Ok(_) => mem.memory_range(info.scratch, scratch_len),
            Err(InputError::Usage(found)) => {
                let v = if update { "pInfos-12260" } else { "pInfos-12261" };
                fail(v, &format!("the scratch buffer lacks STORAGE_BUFFER usage (has {found:?})"));
                None
            }
            Err(InputError::Access(e)) => {
                let (v, n) = if update { ("pInfos-12259", "updateScratchSize") } else { ("pInfos-12258", "buildScratchSize") };
                fail(v, &format!("scratch [{:#x}, +{scratch_len}) ({n}) is not inside one buffer: {e}", info.scratch));
                None
            }
        }
    };
    // Geometry inputs: addresses valid, aligned, inside buffers with BUILD_INPUT_READ_ONLY usage.
    let mut referenced = Vec::new();
    let inputs = std::cell::RefCell::new(Vec::new());
    for (j, (g, r)) in info.geometries.iter().zip(&ranges).enumerate() {
        if let Err((vuid, msg)) = check_geometry(mem, g, r, &mut referenced, &inputs) {
            fail(vuid, &format!("geometry {j}: {msg}"));
        }
    }
    if !ok {
        return Err(());
    }
    Ok(Prepared {
        index: i,
        info,
        dst_range: dst.memory_range(dst.size),
        src_range: if update { info.src.as_ref().and_then(|s| s.memory_range(s.size)) } else { None },
        dst,
        ranges,
        scratch_len,
        scratch_range,
        referenced,
        inputs: inputs.into_inner(),
    })
}

const INPUT_USAGE: vk::BufferUsageFlags = vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR;

/// Byte ranges a geometry reads: (vertices start, len, max vertex for accel), etc.
fn triangle_ranges(
    vertex_format: VertexFormat,
    vertex_data: u64,
    stride: u64,
    max_vertex: u32,
    index_type: IndexType,
    r: &RangeInfo,
) -> Option<(u64, u64, u32, u64)> {
    // Returns (vertex start, vertex len, accel max_vertex, index start) — index len is 3*count*size.
    let fsize = vertex_format.size() as u64;
    if index_type == IndexType::None {
        let start = vertex_data.checked_add(r.primitive_offset as u64)?.checked_add(r.first_vertex as u64 * stride)?;
        let n = r.primitive_count as u64 * 3;
        let len = if n == 0 { 0 } else { (n - 1).checked_mul(stride)?.checked_add(fsize)? };
        Some((start, len, n.saturating_sub(1).min(u32::MAX as u64) as u32, 0))
    } else {
        let start = vertex_data.checked_add(r.first_vertex as u64 * stride)?;
        let maxv = max_vertex.checked_sub(r.first_vertex)? as u64;
        let len = maxv.checked_mul(stride)?.checked_add(fsize)?;
        Some((start, len, maxv as u32, r.primitive_offset as u64))
    }
}

fn check_geometry(
    mem: &dyn InputMemory,
    g: &GeometryInfo,
    r: &RangeInfo,
    referenced: &mut Vec<u64>,
    inputs: &std::cell::RefCell<Vec<(usize, u64, u64)>>,
) -> Result<(), (&'static str, String)> {
    let count = r.primitive_count as u64;
    let input = |addr: u64, len: u64, vuid_addr: &'static str| -> Result<&[u8], (&'static str, String)> {
        if let Some(range) = mem.memory_range(addr, len) {
            inputs.borrow_mut().push(range);
        }
        mem.input(addr, len, INPUT_USAGE).map_err(|e| match e {
            InputError::Usage(found) => (
                "geometry-03673",
                format!("the buffer at {addr:#x} lacks ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY usage (has {found:?})"),
            ),
            InputError::Access(e) => (vuid_addr, format!("[{addr:#x}, +{len}): {e}")),
        })
    };
    match &g.desc {
        GeometryDesc::Unsupported(t) => {
            Err(("VUID-VkAccelerationStructureGeometryKHR-geometryType-parameter", format!("geometry type {t:?} is not supported")))
        }
        GeometryDesc::Triangles { vertex_format, vertex_data, vertex_stride, max_vertex, index_type, index_data, transform_data } => {
            let Some(fmt) = VertexFormat::from_vk(vertex_format.as_raw()) else {
                return Err(("VUID-VkAccelerationStructureGeometryTrianglesDataKHR-vertexFormat-03797", format!("vertex format {vertex_format:?} lacks ACCELERATION_STRUCTURE_VERTEX_BUFFER support")));
            };
            let Some(it) = IndexType::from_vk(index_type.as_raw()) else {
                return Err(("VUID-VkAccelerationStructureGeometryTrianglesDataKHR-indexType-03798", format!("index type {index_type:?} is not UINT16, UINT32 or NONE")));
            };
            if count == 0 {
                return Ok(());
            }
            if !mem.is_host() && vertex_data % fmt.component_size() as u64 != 0 {
                return Err(("pInfos-03711", format!("vertexData {vertex_data:#x} is not aligned to {}", fmt.component_size())));
            }
            if *vertex_stride % fmt.component_size() as u64 != 0 || *vertex_stride > u32::MAX as u64 {
                return Err(("VUID-VkAccelerationStructureGeometryTrianglesDataKHR-vertexStride-03735", format!("vertexStride {vertex_stride} is not a multiple of the component size")));
            }
            if it != IndexType::None {
                if !mem.is_host() && index_data % it.size() as u64 != 0 {
                    return Err(("pInfos-03712", format!("indexData {index_data:#x} is not aligned to {}", it.size())));
                }
                if r.primitive_offset as u64 % it.size() as u64 != 0 {
                    return Err((
                        "VUID-VkAccelerationStructureBuildRangeInfoKHR-primitiveOffset-03656",
                        format!("primitiveOffset {} is not a multiple of the index size", r.primitive_offset),
                    ));
                }
            } else if r.primitive_offset as u64 % fmt.component_size() as u64 != 0 {
                return Err((
                    "VUID-VkAccelerationStructureBuildRangeInfoKHR-primitiveOffset-03657",
                    format!("primitiveOffset {} is not aligned to the vertex component size", r.primitive_offset),
                ));
            }
            if *transform_data != 0 {
                if !mem.is_host() && transform_data % 16 != 0 {
                    return Err(("pInfos-03810", format!("transformData {transform_data:#x} is not aligned to 16")));
                }
                if r.transform_offset % 16 != 0 {
                    return Err((
                        "VUID-VkAccelerationStructureBuildRangeInfoKHR-transformOffset-03658",
                        format!("transformOffset {} is not a multiple of 16", r.transform_offset),
                    ));
                }
                input(transform_data + r.transform_offset as u64, 48, "pInfos-03808")?;
            }
            let Some((vstart, vlen, _, istart)) = triangle_ranges(fmt, *vertex_data, *vertex_stride, *max_vertex, it, r) else {
                return Err(("pInfos-03651", format!("firstVertex {} exceeds maxVertex {max_vertex} or the range overflows", r.first_vertex)));
            };
            input(vstart, vlen, "pInfos-03804")?;
            if it != IndexType::None {
                input(index_data + istart, count * 3 * it.size() as u64, "pInfos-03806")?;
            }
            Ok(())
        }
        GeometryDesc::Aabbs { data, stride } => {
            if count == 0 {
                return Ok(());
            }
            if !mem.is_host() && data % 8 != 0 {
                return Err(("pInfos-03714", format!("aabbs.data {data:#x} is not aligned to 8")));
            }
            if stride % 8 != 0 || *stride > u32::MAX as u64 {
                return Err(("VUID-VkAccelerationStructureGeometryAabbsDataKHR-stride-03545", format!("aabbs.stride {stride} is not a multiple of 8")));
            }
            if r.primitive_offset % 8 != 0 {
                return Err((
                    "VUID-VkAccelerationStructureBuildRangeInfoKHR-primitiveOffset-03659",
                    format!("primitiveOffset {} is not a multiple of 8", r.primitive_offset),
                ));
            }
            input(data + r.primitive_offset as u64, (count - 1) * stride + 24, "pInfos-03811")?;
            Ok(())
        }
        GeometryDesc::Instances { array_of_pointers, data } => {
            if count == 0 {
                return Ok(());
            }
            let align = if *array_of_pointers { 8 } else { 16 };
            if !mem.is_host() && data % align != 0 {
                let v = if *array_of_pointers { "pInfos-03716" } else { "pInfos-03715" };
                return Err((v, format!("instances.data {data:#x} is not aligned to {align}")));
            }
            if r.primitive_offset % 16 != 0 {
                return Err((
                    "VUID-VkAccelerationStructureBuildRangeInfoKHR-primitiveOffset-03660",
                    format!("primitiveOffset {} is not a multiple of 16", r.primitive_offset),
                ));
            }
            let start = data + r.primitive_offset as u64;
            let bytes = input(start, count * if *array_of_pointers { 8 } else { 64 }, "pInfos-03813")?;
            // Every reference must be 0 or the address of a built bottom-level structure (12281).
            // The last four references found valid: a TLAS usually instances few BLASes, and
            // the lookup takes a lock and a hash; a repeat needs no second check or entry.
            let mut known_ok = [0u64; 4];
            let mut next_ok = 0usize;
            let mut check_instance = |k: u64, inst: &[u8]| -> Result<(), (&'static str, String)> {
                let reference = u64::from_le_bytes(inst[56..64].try_into().unwrap());
                if reference == 0 || known_ok.contains(&reference) {
                    return Ok(());
                }
                let blas = accel::DeviceView::acceleration_structure(mem, reference).and_then(accel::header);
                match blas {
                    Some(h) if h.ty == AsType::BottomLevel => {
                        referenced.push(mem.translate_reference(reference));
                        known_ok[next_ok] = reference;
                        next_ok = (next_ok + 1) % known_ok.len();
                        Ok(())
                    }
                    _ => Err((
                        "pInfos-12281",
                        format!("instance {k}: accelerationStructureReference {reference:#x} is neither 0 nor a built bottom-level structure"),
                    )),
                }
            };
            for k in 0..count {
                if *array_of_pointers {
                    let p = u64::from_le_bytes(bytes[k as usize * 8..k as usize * 8 + 8].try_into().unwrap());
                    if !mem.is_host() && p % 16 != 0 {
                        return Err(("pInfos-03717", format!("instance pointer {k} ({p:#x}) is not aligned to 16")));
                    }
                    if let Some(range) = mem.memory_range(p, 64) {
                        inputs.borrow_mut().push(range);
                    }
                    let inst = accel::DeviceView::bytes(mem, p, 64)
                        .ok_or(("pInfos-03813", format!("instance pointer {k} ({p:#x}) does not address 64 valid bytes")))?;
                    check_instance(k, inst)?;
                } else {
                    check_instance(k, &bytes[k as usize * 64..k as usize * 64 + 64])?;
                }
            }
            referenced.sort_unstable();
            referenced.dedup();
            Ok(())
        }
    }
}

/// The VUID of an update that does not match the source's last build, by what differs.
fn update_vuid(what: &str) -> &'static str {
    match what {
        w if w.contains("ALLOW_UPDATE") => "pInfos-03667",
        w if w.contains("type differs") && w.contains("geometry") => "pInfos-03761",
        w if w.contains("structure type") => "pInfos-03760",
        w if w.contains("build flags") => "pInfos-03759",
        w if w.contains("geometry count") => "pInfos-03758",
        w if w.contains("geometry flags") => "pInfos-03762",
        w if w.contains("primitive count") => "primitiveCount-03769",
        // The library compares the three together; maxVertex is the one applications change.
        w if w.contains("maxVertex") => "pInfos-03764",
        w if w.contains("transform") => "pInfos-03766",
        w if w.contains("index values") => "pInfos-03768",
        w if w.contains("became inactive") => "pInfos-03664",
        w if w.contains("active/inactive") => "pInfos-03663",
        _ => "pInfos-03768",
    }
}

/// Run one checked build. Returns false when the library rejected it (reported, dst invalid).
fn run(mem: &dyn InputMemory, p: &Prepared) -> bool {
    let cmd = mem.command();
    let info = p.info;
    let mut geometries = Vec::with_capacity(info.geometries.len());
    for (g, r) in info.geometries.iter().zip(&p.ranges) {
        let count = r.primitive_count as u64;
        let flags = GeometryFlags(g.flags.as_raw());
        let data = match &g.desc {
            GeometryDesc::Triangles { vertex_format, vertex_data, vertex_stride, max_vertex, index_type, index_data, transform_data } => {
                // Checked in prepare: formats known, ranges resolve.
                let (Some(fmt), Some(it)) = (VertexFormat::from_vk(vertex_format.as_raw()), IndexType::from_vk(index_type.as_raw())) else {
                    return false;
                };
                let (vertices, max_v, indices, transform) = if count == 0 {
                    (&[][..], 0, &[][..], None)
                } else {
                    let Some((vstart, vlen, max_v, istart)) = triangle_ranges(fmt, *vertex_data, *vertex_stride, *max_vertex, it, r) else {
                        return false;
                    };
                    let v = mem.input(vstart, vlen, INPUT_USAGE).ok();
                    let i = if it == IndexType::None { Some(&[][..]) } else { mem.input(index_data + istart, count * 3 * it.size() as u64, INPUT_USAGE).ok() };
                    let t = if *transform_data == 0 {
                        Some(None)
                    } else {
                        mem.input(transform_data + r.transform_offset as u64, 48, INPUT_USAGE).ok().map(|b| {
                            let mut m = [0f32; 12];
                            for (k, v) in m.iter_mut().enumerate() {
                                *v = f32::from_le_bytes(b[k * 4..k * 4 + 4].try_into().unwrap());
                            }
                            Some(m)
                        })
                    };
                    let (Some(v), Some(i), Some(t)) = (v, i, t) else { return false };
                    (v, max_v, i, t)
                };
                accel::GeometryData::Triangles {
                    format: fmt,
                    vertices,
                    stride: *vertex_stride,
                    max_vertex: max_v,
                    index_type: it,
                    indices,
                    transform,
                }
            }
            GeometryDesc::Aabbs { data, stride } => {
                let bytes = if count == 0 { &[][..] } else {
                    match mem.input(data + r.primitive_offset as u64, (count - 1) * stride + 24, INPUT_USAGE) {
                        Ok(b) => b,
                        Err(_) => return false,
                    }
                };
                accel::GeometryData::Aabbs { data: bytes, stride: *stride }
            }
            GeometryDesc::Instances { array_of_pointers, data } => {
                let bytes = if count == 0 { &[][..] } else {
                    match mem.input(data + r.primitive_offset as u64, count * if *array_of_pointers { 8 } else { 64 }, INPUT_USAGE) {
                        Ok(b) => b,
                        Err(_) => return false,
                    }
                };
                accel::GeometryData::Instances { array_of_pointers: *array_of_pointers, data: bytes }
            }
            GeometryDesc::Unsupported(_) => return false,
        };
        geometries.push(accel::Geometry { flags, primitive_count: r.primitive_count, data });
    }
    let Some(ty) = to_as_type(info.ty) else { return false };
    let desc = accel::BuildDesc { ty, flags: BuildFlags(info.flags.as_raw()), geometries: &geometries };
    // SAFETY: dst and scratch were checked not to overlap each other, any other element's
    // regions, or (for updates) the source, so these views are exclusive for this build.
    let dst = match unsafe { p.dst.buffer.bytes_mut(p.dst.offset, p.dst.size) } {
        Ok(d) => d,
        Err(_) => return false,
    };
    let mut host_scratch_dummy = [];
    // SAFETY: as above (scratch exclusive: checked against every other region on device; the
    // application's obligation on the host).
    let scratch = if p.scratch_len == 0 {
        &mut host_scratch_dummy[..]
    } else {
        match unsafe { mem.scratch(info.scratch, p.scratch_len) } {
            Ok(s) => s,
            Err(_) => return false,
        }
    };
    let result = if info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE {
        let src = info.src.as_ref().filter(|s| !Arc::ptr_eq(s, &p.dst));
        match src {
            None => accel::update(&desc, mem, None, dst, scratch),
            Some(s) => match s.bytes() {
                Ok(sb) => accel::update(&desc, mem, Some(sb), dst, scratch),
                Err(_) => return false,
            },
        }
    } else {
        accel::build(&desc, mem, dst, scratch)
    };
    match result {
        Ok(_) => true,
        Err(e) => {
            let (vuid, msg) = match &e {
                accel::BuildError::IndexOutOfRange { geometry, primitive, index } => (
                    "pInfos-03651",
                    format!("geometry {geometry} primitive {primitive}: index {index} exceeds maxVertex"),
                ),
                accel::BuildError::UpdateMismatch(what) => (update_vuid(what), format!("update does not match the last build: {what}")),
                accel::BuildError::InvalidAddress { geometry, primitive } => {
                    ("pInfos-03813", format!("geometry {geometry} instance {primitive}: pointer does not address a valid instance"))
                }
                other => ("pInfos-03651", format!("build rejected: {other:?}")),
            };
            violation(cmd, vuid, p.index, &msg);
            accel::mark_invalid(dst);
            false
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Copies and properties

/// An acceleration-structure copy; memory sides are device addresses (commands) or host
/// pointers (host commands), read through the command's `InputMemory`.
pub enum Copy {
    Structure { src: Option<Arc<AccelerationStructure>>, dst: Option<Arc<AccelerationStructure>>, mode: vk::CopyAccelerationStructureModeKHR },
    ToMemory { src: Option<Arc<AccelerationStructure>>, dst: u64, mode: vk::CopyAccelerationStructureModeKHR },
    FromMemory { src: u64, dst: Option<Arc<AccelerationStructure>>, mode: vk::CopyAccelerationStructureModeKHR },
}

fn copy_violation(command: &str, vuid: &str, message: &str) {
    let info = match command {
        "vkCmdCopyAccelerationStructureKHR" | "vkCopyAccelerationStructureKHR" => "VkCopyAccelerationStructureInfoKHR",
        "vkCmdCopyAccelerationStructureToMemoryKHR" | "vkCopyAccelerationStructureToMemoryKHR" => "VkCopyAccelerationStructureToMemoryInfoKHR",
        _ => "VkCopyMemoryToAccelerationStructureInfoKHR",
    };
    diag::vuid(&format!("VUID-{info}-{vuid}"), command, message);
}

/// The constructed structure's bytes and header, or a reported violation.
fn built(command: &str, s: &Option<Arc<AccelerationStructure>>, what: &str) -> Option<(Arc<AccelerationStructure>, accel::Header)> {
    let Some(s) = s else {
        copy_violation(command, &format!("{what}-parameter"), &format!("{what} is not a valid acceleration structure"));
        return None;
    };
    match s.bytes().ok().and_then(accel::header) {
        Some(h) => Some((s.clone(), h)),
        None => {
            let v = if command.contains("ToMemory") { "04959" } else { "04963" };
            copy_violation(command, &format!("{what}-{v}"), &format!("{what} has not been built (or its last build was invalid)"));
            None
        }
    }
}

/// Execute one copy. Invalid copies are reported and skipped (a structure destination is
/// marked invalid); Err(DeviceLost) in strict mode.
pub fn execute_copy(mem: &dyn InputMemory, op: &Copy) -> Result<(), DeviceLost> {
    let cmd = mem.command();
    // A large copy is split across the worker pool (`accel::PAR_COPY_CHUNK`); a small one stays
    // on a queue thread, as small builds do.
    let size = match op {
        Copy::Structure { src, .. } | Copy::ToMemory { src, .. } => src.as_ref().map_or(0, |s| s.size),
        Copy::FromMemory { dst, .. } => dst.as_ref().map_or(0, |d| d.size),
    };
    let small = size < 2 * accel::PAR_COPY_CHUNK as u64;
    let ok = crate::threads::run_parallel(small, || match op {
        Copy::Structure { src, dst, mode } => copy_structure(cmd, src, dst, *mode),
        Copy::ToMemory { src, dst, mode } => serialize_to(mem, src, *dst, *mode),
        Copy::FromMemory { src, dst, mode } => deserialize_from(mem, *src, dst, *mode),
    });
    if !ok && diag::strict() {
        return Err(DeviceLost);
    }
    Ok(())
}

fn copy_structure(
    cmd: &str,
    src: &Option<Arc<AccelerationStructure>>,
    dst: &Option<Arc<AccelerationStructure>>,
    mode: vk::CopyAccelerationStructureModeKHR,
) -> bool {
    let Some((src, h)) = built(cmd, src, "src") else {
        if let Some(d) = dst {
            mark_invalid(d);
        }
        return false;
    };
    let Some(dst) = dst.clone() else {
        copy_violation(cmd, "dst-parameter", "dst is not a valid acceleration structure");
        return false;
    };
    if mode != vk::CopyAccelerationStructureModeKHR::CLONE && mode != vk::CopyAccelerationStructureModeKHR::COMPACT {
        copy_violation(cmd, "mode-03410", "mode must be CLONE or COMPACT");
        mark_invalid(&dst);
        return false;
    }
    if mode == vk::CopyAccelerationStructureModeKHR::COMPACT && !h.flags.contains(BuildFlags::ALLOW_COMPACTION) {
        copy_violation(cmd, "src-03411", "src was not built with ALLOW_COMPACTION");
        mark_invalid(&dst);
        return false;
    }
    if overlaps(src.memory_range(src.size), dst.memory_range(dst.size)) {
        copy_violation(cmd, "dst-07791", "the memory of src and dst overlap");
        return false;
    }
    let needed = h.used_size;
    if dst.size < needed {
        let v = if mode == vk::CopyAccelerationStructureModeKHR::COMPACT { "dst-12285" } else { "dst-12284" };
        copy_violation(cmd, v, &format!("dst size {} is below the {needed} bytes the copy needs", dst.size));
        mark_invalid(&dst);
        return false;
    }
    let (Ok(s), Ok(d)) = (
        src.bytes(),
        // SAFETY: src and dst were checked not to overlap; the view ends with this function.
        unsafe { dst.buffer.bytes_mut(dst.offset, dst.size) },
    ) else {
        return false;
    };
    let r = if mode == vk::CopyAccelerationStructureModeKHR::COMPACT { accel::compact_into(s, d) } else { accel::clone_into(s, d) };
    if r.is_err() {
        accel::mark_invalid(d);
        return false;
    }
    true
}

fn serialize_to(mem: &dyn InputMemory, src: &Option<Arc<AccelerationStructure>>, dst: u64, mode: vk::CopyAccelerationStructureModeKHR) -> bool {
    let cmd = mem.command();
    if mode != vk::CopyAccelerationStructureModeKHR::SERIALIZE {
        copy_violation(cmd, "mode-03412", "mode must be SERIALIZE");
        return false;
    }
    let Some((src, _)) = built(cmd, src, "src") else { return false };
    let Ok(s) = src.bytes() else { return false };
    let Some(size) = accel::serialized_size(s) else { return false };
    let align = if mem.is_host() { 16 } else { 256 };
    if dst % align != 0 {
        let v = if mem.is_host() { "pInfo-03751" } else { "pInfo-03740" };
        diag::vuid(&format!("VUID-{cmd}-{v}"), cmd, &format!("dst address {dst:#x} is not aligned to {align}"));
        return false;
    }
    if !mem.is_host() {
        if let Some(r) = mem.memory_range(dst, size) {
            if overlaps(Some(r), src.memory_range(src.size)) {
                copy_violation(cmd, "dst-03561", "the destination memory overlaps the source structure");
                return false;
            }
        }
    }
    // SAFETY: exclusive destination (checked against the source above on device; the
    // application's obligation on the host).
    match unsafe { mem.scratch(dst, size) } {
        Ok(d) => accel::serialize(s, crate::DRIVER_UUID, d).is_ok(),
        Err(e) => {
            copy_violation(cmd, "dst-03561", &format!("[{dst:#x}, +{size}) is not writable device memory: {e}"));
            false
        }
    }
}

fn deserialize_from(mem: &dyn InputMemory, src: u64, dst: &Option<Arc<AccelerationStructure>>, mode: vk::CopyAccelerationStructureModeKHR) -> bool {
    let cmd = mem.command();
    let Some(dst) = dst.clone() else {
        copy_violation(cmd, "dst-parameter", "dst is not a valid acceleration structure");
        return false;
    };
    if mode != vk::CopyAccelerationStructureModeKHR::DESERIALIZE {
        copy_violation(cmd, "mode-03413", "mode must be DESERIALIZE");
        return false;
    }
    let align = if mem.is_host() { 16 } else { 256 };
    if src % align != 0 {
        let v = if mem.is_host() { "pInfo-03750" } else { "pInfo-03743" };
        diag::vuid(&format!("VUID-{cmd}-{v}"), cmd, &format!("src address {src:#x} is not aligned to {align}"));
        mark_invalid(&dst);
        return false;
    }
    // The header says how long the serialized data is.
    let Ok(head) = mem.input(src, 56, vk::BufferUsageFlags::empty()) else {
        let v = if mem.is_host() { "pInfo-03729" } else { "pInfo-03742" };
        diag::vuid(&format!("VUID-{cmd}-{v}"), cmd, &format!("src {src:#x} does not address a serialized structure"));
        mark_invalid(&dst);
        return false;
    };
    let total = u64::from_le_bytes(head[32..40].try_into().unwrap_or([0; 8]));
    let data = match mem.input(src, total.max(56), vk::BufferUsageFlags::empty()) {
        Ok(d) => d,
        Err(e) => {
            let v = if mem.is_host() { "pInfo-03729" } else { "pInfo-03742" };
            diag::vuid(&format!("VUID-{cmd}-{v}"), cmd, &format!("serialized data [{src:#x}, +{total}) is not readable: {e}"));
            mark_invalid(&dst);
            return false;
        }
    };
    let mut version = [0u8; 32];
    version.copy_from_slice(&data[..32]);
    if !accel::compatible(&version, crate::DRIVER_UUID) {
        copy_violation(cmd, "pInfo-03749", "the serialized data is not compatible with this device (driver or format UUID differs)");
        mark_invalid(&dst);
        return false;
    }
    if !mem.is_host() {
        if let Some(r) = mem.memory_range(src, total) {
            if overlaps(Some(r), dst.memory_range(dst.size)) {
                copy_violation(cmd, "dst-07791", "the source memory overlaps the destination structure");
                return false;
            }
        }
    }
    // SAFETY: exclusive destination (checked against the source above).
    let Ok(d) = (unsafe { dst.buffer.bytes_mut(dst.offset, dst.size) }) else { return false };
    match accel::deserialize(data, crate::DRIVER_UUID, d) {
        Ok(()) => true,
        Err(e) => {
            copy_violation(cmd, "dst-03746", &format!("cannot deserialize into dst (size {}): {e:?}", dst.size));
            accel::mark_invalid(d);
            false
        }
    }
}

/// One property of a structure for vkCmdWrite/vkWriteAccelerationStructuresPropertiesKHR.
/// None (reported) when the structure or query type is invalid.
pub fn property(s: Option<&AccelerationStructure>, query_type: vk::QueryType, command: &str, index: usize) -> Option<u64> {
    let Some(s) = s else {
        diag::vuid(&format!("VUID-{command}-pAccelerationStructures-parameter"), command, &format!("element {index} is not a valid acceleration structure"));
        return None;
    };
    let bytes = s.bytes().ok()?;
    let Some(h) = accel::header(bytes) else {
        diag::vuid(&format!("VUID-{command}-pAccelerationStructures-04964"), command, &format!("element {index} has not been built"));
        return None;
    };
    match query_type {
        vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR => {
            if !h.flags.contains(BuildFlags::ALLOW_COMPACTION) {
                diag::vuid(
                    &format!("VUID-{command}-accelerationStructures-03431"),
                    command,
                    &format!("element {index} was not built with ALLOW_COMPACTION"),
                );
                return None;
            }
            accel::compacted_size(bytes)
        }
        vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR => accel::serialized_size(bytes),
        vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR => Some(h.used_size),
        vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_BOTTOM_LEVEL_POINTERS_KHR => Some(accel::blas_references(bytes).len() as u64),
        other => {
            diag::vuid(&format!("VUID-{command}-queryType-06742"), command, &format!("query type {other:?} is not an acceleration-structure property"));
            None
        }
    }
}

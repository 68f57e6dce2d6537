//! The valid-usage checks of a build command (`vkCmdBuildAccelerationStructures(Indirect)KHR`,
//! `vkBuildAccelerationStructuresKHR`), made when the command executes and before anything is
//! written: handles, types, update rules, formats, range records (read from device memory for
//! indirect builds), sizes against our own size query, scratch, geometry inputs and the
//! aliasing between the regions of the command's elements. Each violation is reported once
//! with its VUID and the element's index.
//!
//! This module decides which builds may run; it must not build or write anything but the
//! invalid marks of skipped destinations.
use std::sync::Arc;

use ash::vk;

use super::inputs::{InputError, InputMemory};
use super::{build_sizes, mark_invalid, overlaps, shape_of, to_as_type, AccelerationStructure, BuildInfo, GeometryDesc, GeometryInfo, RangeInfo, Ranges, SCRATCH_ALIGNMENT};
use crate::accel::{self, AsType, BuildFlags, IndexType, VertexFormat};
use crate::diag;

/// A memory range for overlap checks: (memory identity, start, end).
type MemoryRange = (usize, u64, u64);

/// A build whose checks passed: everything resolved, ready to run.
pub(super) struct Prepared<'m> {
    pub index: usize,
    pub info: &'m BuildInfo,
    pub dst: Arc<AccelerationStructure>,
    pub ranges: Vec<RangeInfo>,
    pub scratch_len: u64,
    /// Memory ranges of dst, scratch, src.
    dst_range: Option<MemoryRange>,
    scratch_range: Option<MemoryRange>,
    src_range: Option<MemoryRange>,
    /// Device addresses of the BLASes its instances reference (for 03706/03407).
    referenced: Vec<u64>,
    /// Memory ranges of every geometry input it reads (device builds).
    inputs: Vec<MemoryRange>,
}

/// A violation found while executing: reported once with its VUID and the offending index.
/// `vuid` is either the part after `VUID-<command>-` or a full `VUID-...` of a structure rule.
pub(super) fn violation(command: &str, vuid: &str, index: usize, message: &str) {
    let full = if vuid.starts_with("VUID-") { vuid.to_string() } else { format!("VUID-{command}-{vuid}") };
    diag::vuid(&full, command, &format!("pInfos[{index}]: {message}"));
}

/// Checks every element of one build command. Invalid elements are reported and their
/// destinations marked invalid; returns the builds that may run and whether any was invalid.
pub(super) fn check_builds<'m>(mem: &dyn InputMemory, infos: &'m [BuildInfo]) -> (Vec<Prepared<'m>>, bool) {
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
    let bad = check_aliasing(mem.command(), &prepared);
    let mut runnable = Vec::new();
    for (p, b) in prepared.into_iter().zip(bad) {
        if b {
            invalid = true;
            mark_invalid(&p.dst);
        } else {
            runnable.push(p);
        }
    }
    (runnable, invalid)
}

/// Aliasing between the regions of different elements (and dst vs its own scratch). Of each
/// overlapping pair at least the element that writes into the other's region is skipped, so
/// no two views handed to running builds overlap. Returns which elements to skip.
fn check_aliasing(cmd: &str, prepared: &[Prepared]) -> Vec<bool> {
    let mut bad = vec![false; prepared.len()];
    for (a, pa) in prepared.iter().enumerate() {
        if overlaps(pa.dst_range, pa.scratch_range) {
            violation(cmd, "dstAccelerationStructure-03703", pa.index, "dst overlaps its own scratch memory");
            bad[a] = true;
        }
        if pa.info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE && overlaps(pa.scratch_range, pa.src_range) {
            violation(cmd, "scratchData-03705", pa.index, "scratch overlaps its own srcAccelerationStructure");
            bad[a] = true;
        }
        for (b, pb) in prepared.iter().enumerate() {
            if a != b && !check_pair(cmd, pa, pb) {
                bad[a] = true;
            }
        }
    }
    // A build must not read what this command writes: inputs inside any element's dst or
    // scratch (no VUID names it; it is a write-after-read hazard within one command, and Arbor
    // will not hand out a shared view of bytes another view may write).
    for (a, pa) in prepared.iter().enumerate() {
        if let Some(pb) = prepared.iter().find(|pb| pa.inputs.iter().any(|r| overlaps(Some(*r), pb.dst_range) || overlaps(Some(*r), pb.scratch_range))) {
            diag::vuid(
                "ARBOR-build-input-aliases-output",
                cmd,
                &format!("pInfos[{}]: a geometry input overlaps the dst or scratch memory of pInfos[{}]", pa.index, pb.index),
            );
            bad[a] = true;
        }
    }
    bad
}

/// Whether element `pa` writes nothing that element `pb` uses (every violation reported).
fn check_pair(cmd: &str, pa: &Prepared, pb: &Prepared) -> bool {
    let mut ok = true;
    let mut fail = |vuid: &str, msg: String| {
        violation(cmd, vuid, pa.index, &msg);
        ok = false;
    };
    let pb_updates = pb.info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE;
    if overlaps(pa.dst_range, pb.dst_range) {
        fail("dstAccelerationStructure-03702", format!("dst overlaps the dst of pInfos[{}]", pb.index));
    }
    if overlaps(pa.dst_range, pb.scratch_range) {
        fail("dstAccelerationStructure-03703", format!("dst overlaps the scratch of pInfos[{}]", pb.index));
    }
    if pb_updates && overlaps(pa.dst_range, pb.src_range) {
        fail("dstAccelerationStructure-03701", format!("dst overlaps the src of pInfos[{}]", pb.index));
    }
    if overlaps(pa.scratch_range, pb.scratch_range) {
        fail("scratchData-03704", format!("scratch overlaps the scratch of pInfos[{}]", pb.index));
    }
    if pb_updates && overlaps(pa.scratch_range, pb.src_range) {
        fail("scratchData-03705", format!("scratch overlaps the src of pInfos[{}]", pb.index));
    }
    if let Some(addr) = pa.dst.address() {
        let end = addr + pa.dst.size;
        if pb.referenced.iter().any(|&r| r >= addr && r < end) {
            fail("dstAccelerationStructure-03706", format!("dst is referenced by an instance of pInfos[{}]", pb.index));
        }
    }
    ok
}

/// Collects the violations of one element: each reported once, any of them failing it.
struct Findings<'c> {
    cmd: &'c str,
    index: usize,
    ok: bool,
}

impl Findings<'_> {
    fn fail(&mut self, vuid: &str, msg: &str) {
        violation(self.cmd, vuid, self.index, msg);
        self.ok = false;
    }
}

/// Check one element; report every violation found (once each) and return the resolved build.
/// `Err(())` once a violation leaves nothing further to check.
fn prepare<'m>(mem: &dyn InputMemory, i: usize, info: &'m BuildInfo) -> Result<Prepared<'m>, ()> {
    let mut f = Findings { cmd: mem.command(), index: i, ok: true };
    let update = info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE;
    let (dst, ty) = check_target(mem, info, &mut f)?;
    check_geometry_types(info, ty, &mut f)?;
    let ranges = read_ranges(mem, info, &mut f)?;
    let scratch_len = check_sizes(info, &dst, &mut f)?;
    let scratch_range = check_scratch(mem, info, scratch_len, &mut f);
    // Geometry inputs: addresses valid, aligned, inside buffers with BUILD_INPUT_READ_ONLY usage.
    let mut referenced = Vec::new();
    let mut inputs = Vec::new();
    for (j, (g, r)) in info.geometries.iter().zip(&ranges).enumerate() {
        if let Err((vuid, msg)) = check_geometry(mem, g, r, &mut referenced, &mut inputs) {
            f.fail(vuid, &format!("geometry {j}: {msg}"));
        }
    }
    if !f.ok {
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
        inputs,
    })
}

/// The destination (handle, type, binding) and, for an update, the source.
fn check_target(mem: &dyn InputMemory, info: &BuildInfo, f: &mut Findings) -> Result<(Arc<AccelerationStructure>, AsType), ()> {
    let Some(dst) = info.dst.clone() else {
        f.fail("dstAccelerationStructure-03800", &format!("dstAccelerationStructure {:#x} is not a valid handle", info.dst_handle));
        return Err(());
    };
    let Some(ty) = to_as_type(info.ty) else {
        f.fail("pInfos-parameter", "type must be TOP_LEVEL or BOTTOM_LEVEL");
        return Err(());
    };
    if dst.create_type != info.ty && dst.create_type != vk::AccelerationStructureTypeKHR::GENERIC {
        let v = if ty == AsType::TopLevel { "pInfos-03699" } else { "pInfos-03700" };
        f.fail(v, "dstAccelerationStructure was created with another type");
    }
    if dst.buffer.memory().is_none() {
        f.fail("pInfos-03707", "dstAccelerationStructure is not bound to device memory");
        return Err(());
    }
    if mem.is_host() && !dst.host_visible() {
        f.fail("pInfos-03722", "dstAccelerationStructure is not bound to host-visible memory");
    }
    if info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE {
        check_update_source(info, &dst, ty, f);
    }
    Ok((dst, ty))
}

/// Update-mode rules that the source structure's own header lets us check.
fn check_update_source(info: &BuildInfo, dst: &Arc<AccelerationStructure>, ty: AsType, f: &mut Findings) {
    let Some(src) = &info.src else {
        f.fail("pInfos-04630", &format!("mode is UPDATE but srcAccelerationStructure {:#x} is not valid", info.src_handle));
        return;
    };
    if src.buffer.memory().is_none() {
        f.fail("pInfos-03708", "srcAccelerationStructure is not bound to device memory");
        return;
    }
    match src.bytes().ok().and_then(accel::header) {
        None => f.fail("pInfos-03667", "srcAccelerationStructure has not been built (or its last build was invalid)"),
        Some(h) => {
            if !h.flags.contains(BuildFlags::ALLOW_UPDATE) {
                f.fail("pInfos-03667", "srcAccelerationStructure was not built with ALLOW_UPDATE");
            }
            if h.flags.0 != info.flags.as_raw() {
                f.fail("pInfos-03759", "flags differ from the last build of srcAccelerationStructure");
            }
            if h.ty != ty {
                f.fail("pInfos-03760", "type differs from the last build of srcAccelerationStructure");
            }
            if h.geometry_count as usize != info.geometries.len() {
                f.fail("pInfos-03758", "geometryCount differs from the last build of srcAccelerationStructure");
            }
        }
    }
    if !Arc::ptr_eq(src, dst) && overlaps(src.memory_range(src.size), dst.memory_range(dst.size)) {
        f.fail("pInfos-03668", "srcAccelerationStructure and dstAccelerationStructure alias without being the same");
    }
}

/// Geometry count, formats and types the size query needs, and the geometry types a level
/// allows.
fn check_geometry_types(info: &BuildInfo, ty: AsType, f: &mut Findings) -> Result<(), ()> {
    if info.geometries.len() != info.geometry_count as usize {
        f.fail(
            "VUID-VkAccelerationStructureBuildGeometryInfoKHR-pGeometries-03788",
            "geometryCount is not 0 but both pGeometries and ppGeometries are NULL",
        );
        return Err(());
    }
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
            f.fail(v, &format!("geometry {j}: {what}"));
            shapes_ok = false;
        }
    }
    if !shapes_ok {
        return Err(());
    }
    if ty == AsType::TopLevel {
        if info.geometries.len() != 1 || !matches!(info.geometries[0].desc, GeometryDesc::Instances { .. }) {
            f.fail("VUID-VkAccelerationStructureBuildGeometryInfoKHR-type-03789", "a top-level build must have exactly one geometry of type INSTANCES");
        }
    } else if info.geometries.iter().any(|g| matches!(g.desc, GeometryDesc::Instances { .. })) {
        f.fail("VUID-VkAccelerationStructureBuildGeometryInfoKHR-type-03790", "a bottom-level build must not have INSTANCES geometry");
    } else if info.geometries.windows(2).any(|w| std::mem::discriminant(&w[0].desc) != std::mem::discriminant(&w[1].desc)) {
        f.fail("VUID-VkAccelerationStructureBuildGeometryInfoKHR-type-03791", "all geometries of a bottom-level build must have the same type");
    }
    Ok(())
}

/// The range records: as given, or read from device memory now (indirect builds).
fn read_ranges(mem: &dyn InputMemory, info: &BuildInfo, f: &mut Findings) -> Result<Vec<RangeInfo>, ()> {
    let ranges = match &info.ranges {
        Ranges::Direct(r) => r.clone(),
        Ranges::Indirect { address, stride, max_primitive_counts } => read_indirect_ranges(mem, info, *address, *stride, max_primitive_counts, f)?,
    };
    if ranges.len() != info.geometries.len() {
        f.fail("ppBuildRangeInfos-03676", "the range array does not have geometryCount elements");
        return Err(());
    }
    Ok(ranges)
}

fn read_indirect_ranges(
    mem: &dyn InputMemory,
    info: &BuildInfo,
    address: u64,
    stride: u32,
    max_primitive_counts: &[u32],
    f: &mut Findings,
) -> Result<Vec<RangeInfo>, ()> {
    let n = info.geometries.len() as u64;
    if !address.is_multiple_of(4) {
        f.fail("pIndirectDeviceAddresses-03648", &format!("indirect address {address:#x} is not a multiple of 4"));
        return Err(());
    }
    if !stride.is_multiple_of(4) {
        f.fail("pIndirectStrides-03787", &format!("indirect stride {stride} is not a multiple of 4"));
        return Err(());
    }
    let len = if n == 0 { 0 } else { (n - 1) * stride as u64 + 16 };
    let mut out = Vec::with_capacity(n as usize);
    if n > 0 {
        match mem.input(address, len, vk::BufferUsageFlags::INDIRECT_BUFFER) {
            Ok(bytes) => {
                for j in 0..n as usize {
                    let o = j * stride as usize;
                    out.push(RangeInfo::from_bytes(&bytes[o..o + 16]));
                }
            }
            Err(InputError::Usage(found)) => {
                f.fail("pIndirectDeviceAddresses-03647", &format!("the buffer of the indirect records lacks INDIRECT_BUFFER usage (has {found:?})"));
                return Err(());
            }
            Err(InputError::Access(e)) => {
                f.fail("pIndirectDeviceAddresses-03646", &format!("indirect records [{address:#x}, +{len}) are not inside one buffer: {e}"));
                return Err(());
            }
        }
    }
    for (j, r) in out.iter().enumerate() {
        let max = max_primitive_counts.get(j).copied().unwrap_or(0);
        if r.primitive_count > max {
            f.fail("ppMaxPrimitiveCounts-03653", &format!("geometry {j}: indirect primitiveCount {} exceeds ppMaxPrimitiveCounts {max}", r.primitive_count));
        }
    }
    Ok(out)
}

/// The destination's size against our own size query, with the counts the application sized
/// for; returns the scratch size the build needs.
fn check_sizes(info: &BuildInfo, dst: &AccelerationStructure, f: &mut Findings) -> Result<u64, ()> {
    let update = info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE;
    let counts: Vec<u32> = match &info.ranges {
        Ranges::Indirect { max_primitive_counts, .. } => max_primitive_counts.clone(),
        Ranges::Direct(r) => r.iter().map(|r| r.primitive_count).collect(),
    };
    let Some(sizes) = build_sizes(info.ty, info.flags, &info.geometries, &counts) else {
        f.fail("VUID-VkAccelerationStructureGeometryTrianglesDataKHR-vertexFormat-03797", "a geometry has an unsupported type, vertex format or index type");
        return Err(());
    };
    let size_vuid = if matches!(info.ranges, Ranges::Indirect { .. }) { "pInfos-03652" } else { "pInfos-03675" };
    if update {
        // An update writes a structure of the source's size into dst.
        let src_used = info.src.as_ref().and_then(|s| s.bytes().ok().and_then(accel::header)).map(|h| h.used_size);
        if let Some(used) = src_used {
            if dst.size < used {
                f.fail(size_vuid, &format!("dstAccelerationStructure size {} is below the {used} bytes of the source", dst.size));
            }
        }
    } else if dst.size < sizes.acceleration_structure_size {
        f.fail(size_vuid, &format!("dstAccelerationStructure size {} is below the {} the size query requires", dst.size, sizes.acceleration_structure_size));
    }
    Ok(if update { sizes.update_scratch_size } else { sizes.build_scratch_size })
}

/// The scratch region: aligned, present, inside one buffer with STORAGE_BUFFER usage. Returns
/// its memory range for the aliasing checks (device builds).
fn check_scratch(mem: &dyn InputMemory, info: &BuildInfo, scratch_len: u64, f: &mut Findings) -> Option<MemoryRange> {
    let update = info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE;
    if !info.scratch.is_multiple_of(SCRATCH_ALIGNMENT) && !mem.is_host() {
        f.fail("pInfos-03710", &format!("scratchData {:#x} is not a multiple of {SCRATCH_ALIGNMENT}", info.scratch));
    }
    if mem.is_host() && scratch_len > 0 && info.scratch == 0 {
        let v = if update { "pInfos-03726" } else { "pInfos-03725" };
        f.fail(v, "scratchData.hostAddress is NULL");
    }
    if mem.is_host() || scratch_len == 0 {
        return None;
    }
    match mem.input(info.scratch, scratch_len, vk::BufferUsageFlags::STORAGE_BUFFER) {
        Ok(_) => mem.memory_range(info.scratch, scratch_len),
        Err(InputError::Usage(found)) => {
            let v = if update { "pInfos-12260" } else { "pInfos-12261" };
            f.fail(v, &format!("the scratch buffer lacks STORAGE_BUFFER usage (has {found:?})"));
            None
        }
        Err(InputError::Access(e)) => {
            let (v, n) = if update { ("pInfos-12259", "updateScratchSize") } else { ("pInfos-12258", "buildScratchSize") };
            f.fail(v, &format!("scratch [{:#x}, +{scratch_len}) ({n}) is not inside one buffer: {e}", info.scratch));
            None
        }
    }
}

pub(super) const INPUT_USAGE: vk::BufferUsageFlags = vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR;

/// Byte ranges a geometry reads: (vertices start, len, max vertex for accel), etc.
pub(super) fn triangle_ranges(
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

/// A violation found in one geometry: the VUID (short or full) and what is wrong.
type Finding = (&'static str, String);

/// The geometry's inputs: addresses valid, aligned, inside buffers with BUILD_INPUT_READ_ONLY
/// usage; instance references name built BLASes (collected in `referenced`); the memory ranges
/// read are collected in `inputs` for the aliasing checks.
fn check_geometry(mem: &dyn InputMemory, g: &GeometryInfo, r: &RangeInfo, referenced: &mut Vec<u64>, inputs: &mut Vec<MemoryRange>) -> Result<(), Finding> {
    match &g.desc {
        GeometryDesc::Unsupported(t) => {
            Err(("VUID-VkAccelerationStructureGeometryKHR-geometryType-parameter", format!("geometry type {t:?} is not supported")))
        }
        GeometryDesc::Triangles { .. } => check_triangles(mem, &g.desc, r, inputs),
        GeometryDesc::Aabbs { data, stride } => check_aabbs(mem, *data, *stride, r, inputs),
        GeometryDesc::Instances { array_of_pointers, data } => check_instances(mem, *array_of_pointers, *data, r, referenced, inputs),
    }
}

/// Input bytes a geometry reads, with its memory range noted for the aliasing checks.
fn read_input<'m>(mem: &'m dyn InputMemory, inputs: &mut Vec<MemoryRange>, addr: u64, len: u64, vuid_addr: &'static str) -> Result<&'m [u8], Finding> {
    if let Some(range) = mem.memory_range(addr, len) {
        inputs.push(range);
    }
    mem.input(addr, len, INPUT_USAGE).map_err(|e| match e {
        InputError::Usage(found) => {
            ("geometry-03673", format!("the buffer at {addr:#x} lacks ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY usage (has {found:?})"))
        }
        InputError::Access(e) => (vuid_addr, format!("[{addr:#x}, +{len}): {e}")),
    })
}

fn check_triangles(mem: &dyn InputMemory, desc: &GeometryDesc, r: &RangeInfo, inputs: &mut Vec<MemoryRange>) -> Result<(), Finding> {
    let GeometryDesc::Triangles { vertex_format, vertex_data, vertex_stride, max_vertex, index_type, index_data, transform_data } = desc else {
        return Ok(());
    };
    let count = r.primitive_count as u64;
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
        if !(r.primitive_offset as u64).is_multiple_of(it.size() as u64) {
            return Err((
                "VUID-VkAccelerationStructureBuildRangeInfoKHR-primitiveOffset-03656",
                format!("primitiveOffset {} is not a multiple of the index size", r.primitive_offset),
            ));
        }
    } else if !(r.primitive_offset as u64).is_multiple_of(fmt.component_size() as u64) {
        return Err((
            "VUID-VkAccelerationStructureBuildRangeInfoKHR-primitiveOffset-03657",
            format!("primitiveOffset {} is not aligned to the vertex component size", r.primitive_offset),
        ));
    }
    if *transform_data != 0 {
        if !mem.is_host() && transform_data % 16 != 0 {
            return Err(("pInfos-03810", format!("transformData {transform_data:#x} is not aligned to 16")));
        }
        if !r.transform_offset.is_multiple_of(16) {
            return Err((
                "VUID-VkAccelerationStructureBuildRangeInfoKHR-transformOffset-03658",
                format!("transformOffset {} is not a multiple of 16", r.transform_offset),
            ));
        }
        read_input(mem, inputs, transform_data + r.transform_offset as u64, 48, "pInfos-03808")?;
    }
    let Some((vstart, vlen, _, istart)) = triangle_ranges(fmt, *vertex_data, *vertex_stride, *max_vertex, it, r) else {
        return Err(("pInfos-03651", format!("firstVertex {} exceeds maxVertex {max_vertex} or the range overflows", r.first_vertex)));
    };
    read_input(mem, inputs, vstart, vlen, "pInfos-03804")?;
    if it != IndexType::None {
        read_input(mem, inputs, index_data + istart, count * 3 * it.size() as u64, "pInfos-03806")?;
    }
    Ok(())
}

fn check_aabbs(mem: &dyn InputMemory, data: u64, stride: u64, r: &RangeInfo, inputs: &mut Vec<MemoryRange>) -> Result<(), Finding> {
    let count = r.primitive_count as u64;
    if count == 0 {
        return Ok(());
    }
    if !mem.is_host() && !data.is_multiple_of(8) {
        return Err(("pInfos-03714", format!("aabbs.data {data:#x} is not aligned to 8")));
    }
    if !stride.is_multiple_of(8) || stride > u32::MAX as u64 {
        return Err(("VUID-VkAccelerationStructureGeometryAabbsDataKHR-stride-03545", format!("aabbs.stride {stride} is not a multiple of 8")));
    }
    if !r.primitive_offset.is_multiple_of(8) {
        return Err((
            "VUID-VkAccelerationStructureBuildRangeInfoKHR-primitiveOffset-03659",
            format!("primitiveOffset {} is not a multiple of 8", r.primitive_offset),
        ));
    }
    let bytes = read_input(mem, inputs, data + r.primitive_offset as u64, (count - 1) * stride + 24, "pInfos-03811")?;
    check_aabb_order(bytes, stride, count)
}

/// VkAabbPositionsKHR: min <= max on every axis (minX-03546, minY-03547, minZ-03548). An AABB
/// with a NaN minX is inactive (the spec's rule), so it is not checked; the first offending
/// primitive of the geometry is reported.
fn check_aabb_order(bytes: &[u8], stride: u64, count: u64) -> Result<(), Finding> {
    const VUIDS: [&str; 3] = ["VUID-VkAabbPositionsKHR-minX-03546", "VUID-VkAabbPositionsKHR-minY-03547", "VUID-VkAabbPositionsKHR-minZ-03548"];
    let f = |b: &[u8], k: usize| f32::from_le_bytes([b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]]);
    for p in 0..count {
        let Some(b) = bytes.get((p * stride) as usize..(p * stride) as usize + 24) else { break };
        if f(b, 0).is_nan() {
            continue;
        }
        if let Some(axis) = (0..3).find(|&a| f(b, a) > f(b, a + 3)) {
            let name = ["X", "Y", "Z"][axis];
            return Err((VUIDS[axis], format!("primitive {p}: min{name} {} > max{name} {}", f(b, axis), f(b, axis + 3))));
        }
    }
    Ok(())
}

fn check_instances(
    mem: &dyn InputMemory,
    array_of_pointers: bool,
    data: u64,
    r: &RangeInfo,
    referenced: &mut Vec<u64>,
    inputs: &mut Vec<MemoryRange>,
) -> Result<(), Finding> {
    let count = r.primitive_count as u64;
    if count == 0 {
        return Ok(());
    }
    let align = if array_of_pointers { 8 } else { 16 };
    if !mem.is_host() && !data.is_multiple_of(align) {
        let v = if array_of_pointers { "pInfos-03716" } else { "pInfos-03715" };
        return Err((v, format!("instances.data {data:#x} is not aligned to {align}")));
    }
    if !r.primitive_offset.is_multiple_of(16) {
        return Err((
            "VUID-VkAccelerationStructureBuildRangeInfoKHR-primitiveOffset-03660",
            format!("primitiveOffset {} is not a multiple of 16", r.primitive_offset),
        ));
    }
    let start = data + r.primitive_offset as u64;
    let bytes = read_input(mem, inputs, start, count * if array_of_pointers { 8 } else { 64 }, "pInfos-03813")?;
    // Every reference must be 0 or the address of a built bottom-level structure (12281).
    // The last four references found valid: a TLAS usually instances few BLASes, and
    // the lookup takes a lock and a hash; a repeat needs no second check or entry.
    let mut known_ok = [0u64; 4];
    let mut next_ok = 0usize;
    let mut check_instance = |k: u64, inst: &[u8]| -> Result<(), Finding> {
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
        if array_of_pointers {
            let p = u64::from_le_bytes(bytes[k as usize * 8..k as usize * 8 + 8].try_into().unwrap());
            if !mem.is_host() && p % 16 != 0 {
                return Err(("pInfos-03717", format!("instance pointer {k} ({p:#x}) is not aligned to 16")));
            }
            if let Some(range) = mem.memory_range(p, 64) {
                inputs.push(range);
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

/// The VUID of an update that does not match the source's last build, by what differs.
/// The library names what differs only in text (`accel::BuildError::UpdateMismatch(&str)`), so
/// this matches its wording; a typed reason from `accel` would make it a match on values.
pub(super) fn update_vuid(what: &str) -> &'static str {
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

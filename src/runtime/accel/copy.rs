//! Acceleration-structure copies: clone and compaction between structures, serialization into
//! memory and deserialization from it, for the copy commands a queue executes and for the host
//! copy commands (whose memory side is a host pointer).
//!
//! This module must not make views of memory itself: destinations are written through
//! `crate::memory` (`Buffer::with_slice_mut`, `region::Region`).
use std::sync::Arc;

use ash::vk;

use super::inputs::InputMemory;
use super::{mark_invalid, overlaps, AccelerationStructure, DeviceLost};
use crate::accel::{self, BuildFlags};
use crate::diag;

/// An acceleration-structure copy; memory sides are device addresses (commands) or host
/// pointers (host commands), read through the command's `InputMemory`.
pub enum Copy {
    Structure { src: Option<Arc<AccelerationStructure>>, dst: Option<Arc<AccelerationStructure>>, mode: vk::CopyAccelerationStructureModeKHR },
    ToMemory { src: Option<Arc<AccelerationStructure>>, dst: u64, mode: vk::CopyAccelerationStructureModeKHR },
    FromMemory { src: u64, dst: Option<Arc<AccelerationStructure>>, mode: vk::CopyAccelerationStructureModeKHR },
}

/// Which copy a violation is about (it names the info structure in the VUID).
#[derive(Clone, Copy, PartialEq, Eq)]
enum CopyKind {
    Structure,
    ToMemory,
    FromMemory,
}

fn copy_violation(kind: CopyKind, command: &str, vuid: &str, message: &str) {
    let info = match kind {
        CopyKind::Structure => "VkCopyAccelerationStructureInfoKHR",
        CopyKind::ToMemory => "VkCopyAccelerationStructureToMemoryInfoKHR",
        CopyKind::FromMemory => "VkCopyMemoryToAccelerationStructureInfoKHR",
    };
    diag::vuid(&format!("VUID-{info}-{vuid}"), command, message);
}

/// What a copy error says about its source, for a diagnostic.
fn describe(e: &accel::CopyError) -> String {
    match e {
        accel::CopyError::Corrupt(reason) => format!("failed check: {reason}"),
        other => format!("{other:?}"),
    }
}

/// The constructed structure's bytes and header, or a reported violation.
fn built(kind: CopyKind, command: &str, s: &Option<Arc<AccelerationStructure>>, what: &str) -> Option<(Arc<AccelerationStructure>, accel::Header)> {
    let Some(s) = s else {
        copy_violation(kind, command, &format!("{what}-parameter"), &format!("{what} is not a valid acceleration structure"));
        return None;
    };
    match s.bytes().ok().and_then(accel::header) {
        Some(h) => Some((s.clone(), h)),
        None => {
            let v = if kind == CopyKind::ToMemory { "04959" } else { "04963" };
            copy_violation(kind, command, &format!("{what}-{v}"), &format!("{what} has not been built (or its last build was invalid)"));
            None
        }
    }
}

/// Whether the `len` bytes of device memory at `address` overlap structure `s` (never on the
/// host, where the application keeps them apart).
fn overlaps_structure(mem: &dyn InputMemory, address: u64, len: u64, s: &AccelerationStructure) -> bool {
    !mem.is_host() && mem.memory_range(address, len).is_some_and(|r| overlaps(Some(r), s.memory_range(s.size)))
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
    let Some((src, h)) = built(CopyKind::Structure, cmd, src, "src") else {
        if let Some(d) = dst {
            mark_invalid(d);
        }
        return false;
    };
    let Some(dst) = dst.clone() else {
        copy_violation(CopyKind::Structure, cmd, "dst-parameter", "dst is not a valid acceleration structure");
        return false;
    };
    if mode != vk::CopyAccelerationStructureModeKHR::CLONE && mode != vk::CopyAccelerationStructureModeKHR::COMPACT {
        copy_violation(CopyKind::Structure, cmd, "mode-03410", "mode must be CLONE or COMPACT");
        mark_invalid(&dst);
        return false;
    }
    if mode == vk::CopyAccelerationStructureModeKHR::COMPACT && !h.flags.contains(BuildFlags::ALLOW_COMPACTION) {
        copy_violation(CopyKind::Structure, cmd, "src-03411", "src was not built with ALLOW_COMPACTION");
        mark_invalid(&dst);
        return false;
    }
    if overlaps(src.memory_range(src.size), dst.memory_range(dst.size)) {
        copy_violation(CopyKind::Structure, cmd, "dst-07791", "the memory of src and dst overlap");
        return false;
    }
    let needed = h.used_size;
    if dst.size < needed {
        let v = if mode == vk::CopyAccelerationStructureModeKHR::COMPACT { "dst-12285" } else { "dst-12284" };
        copy_violation(CopyKind::Structure, cmd, v, &format!("dst size {} is below the {needed} bytes the copy needs", dst.size));
        mark_invalid(&dst);
        return false;
    }
    let Ok(s) = src.bytes() else { return false };
    // src and dst were checked not to overlap (07791): the write cannot change what is read.
    let copied = dst.buffer.with_slice_mut(dst.offset, dst.size, |d| {
        let r = if mode == vk::CopyAccelerationStructureModeKHR::COMPACT { accel::compact_into(s, d) } else { accel::clone_into(s, d) };
        if let Err(e) = &r {
            // The source's checks run before anything is copied: a failure writes only the mark.
            copy_violation(CopyKind::Structure, cmd, "src-04963", &format!("src fails its integrity check and is not a constructed structure: {}", describe(e)));
            accel::mark_invalid(d);
        }
        r.is_ok()
    });
    copied.unwrap_or(false)
}

fn serialize_to(mem: &dyn InputMemory, src: &Option<Arc<AccelerationStructure>>, dst: u64, mode: vk::CopyAccelerationStructureModeKHR) -> bool {
    let cmd = mem.command();
    if mode != vk::CopyAccelerationStructureModeKHR::SERIALIZE {
        copy_violation(CopyKind::ToMemory, cmd, "mode-03412", "mode must be SERIALIZE");
        return false;
    }
    let Some((src, _)) = built(CopyKind::ToMemory, cmd, src, "src") else { return false };
    let Ok(s) = src.bytes() else { return false };
    let Some(size) = accel::serialized_size(s) else { return false };
    let align = if mem.is_host() { 16 } else { 256 };
    if !dst.is_multiple_of(align) {
        let v = if mem.is_host() { "pInfo-03751" } else { "pInfo-03740" };
        diag::vuid(&format!("VUID-{cmd}-{v}"), cmd, &format!("dst address {dst:#x} is not aligned to {align}"));
        return false;
    }
    if overlaps_structure(mem, dst, size, &src) {
        copy_violation(CopyKind::ToMemory, cmd, "dst-03561", "the destination memory overlaps the source structure");
        return false;
    }
    // The destination does not overlap the source (checked above on device; the application's
    // obligation on the host).
    match mem.writable(dst, size) {
        Ok(d) => d.write_with(|d| match accel::serialize(s, crate::DRIVER_UUID, d) {
            Ok(_) => true,
            Err(e) => {
                copy_violation(CopyKind::ToMemory, cmd, "src-04959", &format!("src fails its integrity check and is not a constructed structure: {}", describe(&e)));
                false
            }
        }),
        Err(e) => {
            copy_violation(CopyKind::ToMemory, cmd, "dst-03561", &format!("[{dst:#x}, +{size}) is not writable device memory: {e}"));
            false
        }
    }
}

fn deserialize_from(mem: &dyn InputMemory, src: u64, dst: &Option<Arc<AccelerationStructure>>, mode: vk::CopyAccelerationStructureModeKHR) -> bool {
    let cmd = mem.command();
    let Some(dst) = dst.clone() else {
        copy_violation(CopyKind::FromMemory, cmd, "dst-parameter", "dst is not a valid acceleration structure");
        return false;
    };
    if mode != vk::CopyAccelerationStructureModeKHR::DESERIALIZE {
        copy_violation(CopyKind::FromMemory, cmd, "mode-03413", "mode must be DESERIALIZE");
        return false;
    }
    let align = if mem.is_host() { 16 } else { 256 };
    if !src.is_multiple_of(align) {
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
        copy_violation(CopyKind::FromMemory, cmd, "pInfo-03749", "the serialized data is not compatible with this device (driver or format UUID differs)");
        mark_invalid(&dst);
        return false;
    }
    if overlaps_structure(mem, src, total, &dst) {
        copy_violation(CopyKind::FromMemory, cmd, "dst-07791", "the source memory overlaps the destination structure");
        return false;
    }
    let handles = match checked_handles(mem, data, &dst) {
        Ok(h) => h,
        Err(message) => {
            copy_violation(CopyKind::FromMemory, cmd, "src-04960", &message);
            mark_invalid(&dst);
            return false;
        }
    };
    // The source does not overlap the destination (checked above on device; the application's
    // obligation on the host).
    let written = dst.buffer.with_slice_mut(dst.offset, dst.size, |d| match accel::deserialize_relocated(data, crate::DRIVER_UUID, d, handles.as_deref()) {
        Ok(()) => true,
        Err(e @ accel::CopyError::DestinationTooSmall { .. }) => {
            copy_violation(CopyKind::FromMemory, cmd, "dst-03746", &format!("cannot deserialize into dst (size {}): {e:?}", dst.size));
            accel::mark_invalid(d);
            false
        }
        Err(e) => {
            // Checked before anything is copied: a rejected source writes only the mark.
            copy_violation(CopyKind::FromMemory, cmd, "src-04960", &format!("the serialized data is not what serialization wrote: {}", describe(&e)));
            accel::mark_invalid(d);
            false
        }
    });
    written.unwrap_or(false)
}

/// The handles of serialized data, each checked, as the structure will store them (host
/// commands: handles become device addresses); None when the list is not readable (the
/// library rejects such data by name). Each handle must name a bottom-level structure: a built
/// one whose header checks out, or, as the spec allows, one created but not built yet (a
/// 256-aligned address in a buffer with ACCELERATION_STRUCTURE_STORAGE usage, or a live
/// handle on the host). Never 0 (every listed handle belongs to an active instance), never the
/// destination itself. Err: the first bad handle and how many are bad.
fn checked_handles(mem: &dyn InputMemory, data: &[u8], dst: &AccelerationStructure) -> Result<Option<Vec<u64>>, String> {
    let at = |o: usize| data.get(o..o + 8).map(|b| u64::from_le_bytes(b.try_into().unwrap_or([0; 8])));
    let Some(n) = at(48).filter(|&n| n <= (data.len() as u64).saturating_sub(56) / 8) else { return Ok(None) };
    let mut out = Vec::with_capacity(n as usize);
    let mut first: Option<String> = None;
    let mut bad = 0u64;
    let own = dst.address().map(|a| a..a.saturating_add(dst.size));
    for k in 0..n as usize {
        let h = at(56 + 8 * k).unwrap_or(0);
        let address = mem.translate_reference(h);
        let problem = if h == 0 {
            Some("is 0, but every listed handle belongs to an active instance".to_string())
        } else if own.as_ref().is_some_and(|r| r.contains(&address)) {
            Some("addresses the destination itself".to_string())
        } else {
            handle_problem(mem, h, address)
        };
        if let Some(p) = problem {
            bad += 1;
            first.get_or_insert_with(|| format!("handle {k} ({h:#x}) {p}"));
        }
        out.push(address);
    }
    match first {
        Some(f) => Err(format!("{f} ({bad} of {n} handles are not bottom-level structures)")),
        None => Ok(Some(out)),
    }
}

/// What is wrong with handle `h` (structure address `address`), if anything.
fn handle_problem(mem: &dyn InputMemory, h: u64, address: u64) -> Option<String> {
    let Some(bytes) = accel::DeviceView::acceleration_structure(mem, h) else {
        return Some("does not address live memory (a freed or never-created structure)".into());
    };
    match accel::header(bytes) {
        Some(header) if header.ty == accel::AsType::BottomLevel => None,
        Some(_) => Some("is a top-level structure".into()),
        // Not built (yet): allowed for a created structure.
        None if !address.is_multiple_of(super::STRUCTURE_ALIGNMENT) => Some("is not the address of an acceleration structure (not 256-aligned)".into()),
        None if mem.is_host() => (address == h).then(|| "is neither a built structure nor a live structure handle".into()),
        None => match mem.input(address, 1, vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR) {
            Ok(_) => None,
            Err(_) => Some("is not in a buffer with ACCELERATION_STRUCTURE_STORAGE usage".into()),
        },
    }
}

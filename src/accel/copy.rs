//! Clone, compaction, serialization. The blob is position-independent, so all of these are
//! byte copies; serialization adds the Vulkan header and takes BLAS addresses from its list.
//! Every copy verifies its source first, so a structure the application wrote over, or
//! serialized data it corrupted, is rejected with the check that failed and nothing is copied:
//! a structure in device memory by its integrity (`check_integrity`: header and checksum, which
//! keeps compaction a byte copy in time), serialized data from the application by every check
//! (`check`: integrity and the structure itself).
use super::check::{check, check_integrity, Reason};
use super::layout::parse;

/// Identifies this format version in serialized data; change with layout::FORMAT_VERSION.
pub const ACCEL_FORMAT_UUID: [u8; 16] = *b"ArborAS-BVH4q-04";

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CopyError {
    /// Source is not a valid structure (or serialized blob).
    InvalidSource,
    DestinationTooSmall { needed: u64, got: u64 },
    /// Serialized data from another driver or format version.
    Incompatible,
    /// The source (a structure, or the payload of serialized data) fails a check of its
    /// integrity or structure: the name of the check (`check::check`).
    Corrupt(Reason),
}

const SER_HEADER: u64 = 56;

/// Copies of at least twice this many bytes are split into chunks of it across the current
/// rayon pool: one core copies a dragon-sized structure (50 MB) at
/// about 10 GB/s, sixteen at about 100.
pub const PAR_COPY_CHUNK: usize = 1 << 20;

/// `dst.copy_from_slice(src)`, in parallel chunks when large.
fn copy_bytes(dst: &mut [u8], src: &[u8]) {
    if src.len() < 2 * PAR_COPY_CHUNK || dst.len() != src.len() {
        dst.copy_from_slice(src);
        return;
    }
    use rayon::prelude::*;
    dst.par_chunks_mut(PAR_COPY_CHUNK).zip(src.par_chunks(PAR_COPY_CHUNK)).for_each(|(d, s)| d.copy_from_slice(s));
}

pub fn compacted_size(src: &[u8]) -> Option<u64> {
    parse(src).map(|p| p.raw.used_size)
}

/// The source's parsed header, once its integrity checked out (`InvalidSource` when it is not
/// a structure at all: never built, or marked invalid).
fn checked(src: &[u8]) -> Result<super::layout::Parsed<'_>, CopyError> {
    parse(src).ok_or(CopyError::InvalidSource)?;
    check_integrity(src).map_err(CopyError::Corrupt)
}

fn copy_used(src: &[u8], dst: &mut [u8]) -> Result<usize, CopyError> {
    let p = checked(src)?;
    let used = p.raw.used_size as usize;
    let got = dst.len() as u64;
    let d = dst.get_mut(..used).ok_or(CopyError::DestinationTooSmall { needed: used as u64, got })?;
    copy_bytes(d, &src[..used]);
    Ok(used)
}

pub fn clone_into(src: &[u8], dst: &mut [u8]) -> Result<(), CopyError> {
    copy_used(src, dst).map(|_| ())
}

pub fn compact_into(src: &[u8], dst: &mut [u8]) -> Result<(), CopyError> {
    copy_used(src, dst).map(|_| ())
}

/// 56 + 8N + payload.
pub fn serialized_size(src: &[u8]) -> Option<u64> {
    let p = parse(src)?;
    Some(SER_HEADER + 8 * p.raw.blas_reference_count as u64 + p.raw.used_size)
}

/// The N addresses of the serialized header: one per stored (active) instance, duplicates
/// included, in the instance order of the build's input; inactive instances contribute none.
/// N is also what the BOTTOM_LEVEL_POINTERS query reports.
pub fn blas_references(src: &[u8]) -> Vec<u64> {
    match parse(src) {
        Some(p) => (0..p.raw.blas_reference_count).filter_map(|i| p.blas_address(i)).collect(),
        None => Vec::new(),
    }
}

pub fn serialize(src: &[u8], driver_uuid: [u8; 16], dst: &mut [u8]) -> Result<u64, CopyError> {
    let p = checked(src)?;
    let n = p.raw.blas_reference_count as u64;
    let used = p.raw.used_size;
    let total = SER_HEADER + 8 * n + used;
    if (dst.len() as u64) < total {
        return Err(CopyError::DestinationTooSmall { needed: total, got: dst.len() as u64 });
    }
    dst[0..16].copy_from_slice(&driver_uuid);
    dst[16..32].copy_from_slice(&ACCEL_FORMAT_UUID);
    dst[32..40].copy_from_slice(&total.to_le_bytes());
    dst[40..48].copy_from_slice(&used.to_le_bytes());
    dst[48..56].copy_from_slice(&n.to_le_bytes());
    for i in 0..n as usize {
        let a = p.blas_address(i as u32).unwrap_or(0);
        dst[56 + 8 * i..64 + 8 * i].copy_from_slice(&a.to_le_bytes());
    }
    let off = (SER_HEADER + 8 * n) as usize;
    copy_bytes(&mut dst[off..off + used as usize], &src[..used as usize]);
    Ok(total)
}

fn u64_at(b: &[u8], off: usize) -> Option<u64> {
    super::input::rd_u64(b, off)
}

pub fn deserialize(data: &[u8], driver_uuid: [u8; 16], dst: &mut [u8]) -> Result<(), CopyError> {
    deserialize_relocated(data, driver_uuid, dst, None)
}

/// `deserialize` storing `handles` (one per entry of the header's list, in order) instead of the
/// list itself: the driver checks each handle and host commands translate handles into device
/// addresses first.
pub fn deserialize_relocated(data: &[u8], driver_uuid: [u8; 16], dst: &mut [u8], handles: Option<&[u64]>) -> Result<(), CopyError> {
    let version: &[u8; 32] = data.get(..32).and_then(|s| s.try_into().ok()).ok_or(CopyError::Corrupt("serialized header"))?;
    if !compatible(version, driver_uuid) {
        return Err(CopyError::Incompatible);
    }
    let total = u64_at(data, 32).ok_or(CopyError::Corrupt("serialized header"))?;
    let size = u64_at(data, 40).ok_or(CopyError::Corrupt("serialized header"))?;
    let n = u64_at(data, 48).ok_or(CopyError::Corrupt("serialized header"))?;
    let off = n.checked_mul(8).and_then(|x| x.checked_add(SER_HEADER)).ok_or(CopyError::Corrupt("serialized header"))?;
    let end = off.checked_add(size).ok_or(CopyError::Corrupt("serialized header"))?;
    if end > data.len() as u64 || end > total {
        return Err(CopyError::Corrupt("serialized header"));
    }
    let payload = &data[off as usize..end as usize];
    let p = check(payload).map_err(CopyError::Corrupt)?;
    if p.raw.used_size != size {
        return Err(CopyError::Corrupt("deserialized size"));
    }
    if p.raw.blas_reference_count as u64 != n || handles.is_some_and(|h| h.len() as u64 != n) {
        return Err(CopyError::Corrupt("handle count"));
    }
    let got = dst.len() as u64;
    let d = dst.get_mut(..size as usize).ok_or(CopyError::DestinationTooSmall { needed: size, got })?;
    copy_bytes(d, payload);
    // The application rewrote the header's addresses: they replace the payload's table.
    let table = p.raw.blas_table_offset as usize;
    for i in 0..n as usize {
        let a = match handles {
            Some(h) => h[i],
            None => u64_at(data, 56 + 8 * i).ok_or(CopyError::Corrupt("serialized header"))?,
        };
        if let Some(s) = d.get_mut(table + 8 * i..table + 8 * i + 8) {
            s.copy_from_slice(&a.to_le_bytes());
        }
    }
    // Each instance refers to its own table slot, so each is relocated by its own handle.
    Ok(())
}

/// Both UUIDs equal ours.
pub fn compatible(version_data: &[u8; 32], driver_uuid: [u8; 16]) -> bool {
    version_data[..16] == driver_uuid && version_data[16..] == ACCEL_FORMAT_UUID
}

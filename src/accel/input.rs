//! Reading primitives out of the caller's geometry views: vertex format decode, index fetch,
//! build-time transforms, AABB records and instance records. Every read is bounds-checked and
//! reports a typed `BuildError`; nothing here panics.
use super::{BuildError, DeviceView, Geometry, GeometryData, IndexType, VertexFormat};
use glam::Vec3;

/// Size of one VkAccelerationStructureInstanceKHR record.
pub const INSTANCE_SIZE: usize = 64;

fn rd_u16(b: &[u8], off: usize) -> Option<u16> {
    let s = b.get(off..off.checked_add(2)?)?;
    Some(u16::from_le_bytes([s[0], s[1]]))
}
pub fn rd_u32(b: &[u8], off: usize) -> Option<u32> {
    let s = b.get(off..off.checked_add(4)?)?;
    Some(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
}
pub fn rd_u64(b: &[u8], off: usize) -> Option<u64> {
    let s = b.get(off..off.checked_add(8)?)?;
    let mut a = [0u8; 8];
    a.copy_from_slice(s);
    Some(u64::from_le_bytes(a))
}
pub fn rd_f32(b: &[u8], off: usize) -> Option<f32> {
    rd_u32(b, off).map(f32::from_bits)
}

/// IEEE half → f32 (exact: every half is representable).
pub fn half_to_f32(h: u16) -> f32 {
    let sign = ((h >> 15) as u32) << 31;
    let exp = ((h >> 10) & 0x1f) as u32;
    let man = (h & 0x3ff) as u32;
    let bits = if exp == 0 {
        if man == 0 {
            sign
        } else {
            // Subnormal half: value = man * 2^-24, exact in f32.
            let v = man as f32 * (1.0 / 16_777_216.0);
            return if sign != 0 { -v } else { v };
        }
    } else if exp == 31 {
        sign | 0x7f80_0000 | (man << 13)
    } else {
        sign | ((exp + 112) << 23) | (man << 13)
    };
    f32::from_bits(bits)
}

fn snorm16(v: u16) -> f32 {
    ((v as i16) as f32 / 32767.0).max(-1.0)
}
fn snorm8(v: u8) -> f32 {
    ((v as i8) as f32 / 127.0).max(-1.0)
}

/// Decode one vertex from the start of `b` (the caller checked `b.len() >= format.size()`).
pub fn decode_vertex(format: VertexFormat, b: &[u8]) -> Option<Vec3> {
    use VertexFormat as F;
    let f = |i: usize| rd_f32(b, 4 * i);
    let h = |i: usize| rd_u16(b, 2 * i).map(half_to_f32);
    let s16 = |i: usize| rd_u16(b, 2 * i).map(snorm16);
    let u16n = |i: usize| rd_u16(b, 2 * i).map(|v| v as f32 / 65535.0);
    let s8 = |i: usize| b.get(i).map(|&v| snorm8(v));
    let u8n = |i: usize| b.get(i).map(|&v| v as f32 / 255.0);
    Some(match format {
        F::R32G32Sfloat => Vec3::new(f(0)?, f(1)?, 0.0),
        F::R32G32B32Sfloat | F::R32G32B32A32Sfloat => Vec3::new(f(0)?, f(1)?, f(2)?),
        F::R16G16Sfloat => Vec3::new(h(0)?, h(1)?, 0.0),
        F::R16G16B16Sfloat | F::R16G16B16A16Sfloat => Vec3::new(h(0)?, h(1)?, h(2)?),
        F::R16G16Snorm => Vec3::new(s16(0)?, s16(1)?, 0.0),
        F::R16G16B16A16Snorm => Vec3::new(s16(0)?, s16(1)?, s16(2)?),
        F::R8G8Snorm => Vec3::new(s8(0)?, s8(1)?, 0.0),
        F::R8G8B8A8Snorm => Vec3::new(s8(0)?, s8(1)?, s8(2)?),
        F::R16G16Unorm => Vec3::new(u16n(0)?, u16n(1)?, 0.0),
        F::R16G16B16A16Unorm => Vec3::new(u16n(0)?, u16n(1)?, u16n(2)?),
        F::R8G8Unorm => Vec3::new(u8n(0)?, u8n(1)?, 0.0),
        F::R8G8B8A8Unorm => Vec3::new(u8n(0)?, u8n(1)?, u8n(2)?),
        F::A2B10G10R10UnormPack32 => {
            let w = rd_u32(b, 0)?;
            Vec3::new(
                (w & 0x3ff) as f32 / 1023.0,
                ((w >> 10) & 0x3ff) as f32 / 1023.0,
                ((w >> 20) & 0x3ff) as f32 / 1023.0,
            )
        }
    })
}

/// Apply a row-major 3x4 affine transform to a point.
pub fn transform_point(m: &[f32; 12], p: Vec3) -> Vec3 {
    Vec3::new(
        m[0] * p.x + m[1] * p.y + m[2] * p.z + m[3],
        m[4] * p.x + m[5] * p.y + m[6] * p.z + m[7],
        m[8] * p.x + m[9] * p.y + m[10] * p.z + m[11],
    )
}
/// Apply the 3x3 part of a row-major 3x4 transform to a direction.
pub fn transform_dir(m: &[f32; 12], d: Vec3) -> Vec3 {
    Vec3::new(
        m[0] * d.x + m[1] * d.y + m[2] * d.z,
        m[4] * d.x + m[5] * d.y + m[6] * d.z,
        m[8] * d.x + m[9] * d.y + m[10] * d.z,
    )
}

/// Inverse of an affine 3x4 transform (computed in f64 for accuracy); a singular matrix gives
/// all-zero, which makes every object-space ray degenerate (no hits) rather than panicking.
pub fn invert_transform(m: &[f32; 12]) -> [f32; 12] {
    let a = |r: usize, c: usize| m[r * 4 + c] as f64;
    let c00 = a(1, 1) * a(2, 2) - a(1, 2) * a(2, 1);
    let c01 = a(1, 2) * a(2, 0) - a(1, 0) * a(2, 2);
    let c02 = a(1, 0) * a(2, 1) - a(1, 1) * a(2, 0);
    let det = a(0, 0) * c00 + a(0, 1) * c01 + a(0, 2) * c02;
    if det == 0.0 || !det.is_finite() {
        return [0.0; 12];
    }
    let inv_det = 1.0 / det;
    let r = [
        [c00, a(0, 2) * a(2, 1) - a(0, 1) * a(2, 2), a(0, 1) * a(1, 2) - a(0, 2) * a(1, 1)],
        [c01, a(0, 0) * a(2, 2) - a(0, 2) * a(2, 0), a(0, 2) * a(1, 0) - a(0, 0) * a(1, 2)],
        [c02, a(0, 1) * a(2, 0) - a(0, 0) * a(2, 1), a(0, 0) * a(1, 1) - a(0, 1) * a(1, 0)],
    ];
    let t = [a(0, 3), a(1, 3), a(2, 3)];
    let mut out = [0f32; 12];
    for row in 0..3 {
        let mut tr = 0.0;
        for col in 0..3 {
            let v = r[row][col] * inv_det;
            out[row * 4 + col] = v as f32;
            tr -= v * t[col];
        }
        out[row * 4 + 3] = tr as f32;
    }
    out
}

/// Vertex index of corner `k` of triangle `p` (checked against `max_vertex`).
fn vertex_index(geometry_index: u32, p: u32, k: u32, index_type: IndexType, indices: &[u8], max_vertex: u32) -> Result<u32, BuildError> {
    let slot = (p as u64) * 3 + k as u64;
    let idx = match index_type {
        IndexType::None => {
            // Non-indexed: the slice bound check on vertices is what protects the read; an
            // index beyond u32 cannot be a vertex of a valid geometry.
            u32::try_from(slot).map_err(|_| BuildError::InputTooShort { geometry: geometry_index })?
        }
        IndexType::U16 => {
            let off = usize::try_from(slot * 2).map_err(|_| BuildError::InputTooShort { geometry: geometry_index })?;
            rd_u16(indices, off).ok_or(BuildError::InputTooShort { geometry: geometry_index })? as u32
        }
        IndexType::U32 => {
            let off = usize::try_from(slot * 4).map_err(|_| BuildError::InputTooShort { geometry: geometry_index })?;
            rd_u32(indices, off).ok_or(BuildError::InputTooShort { geometry: geometry_index })?
        }
    };
    if index_type != IndexType::None && idx > max_vertex {
        return Err(BuildError::IndexOutOfRange { geometry: geometry_index, primitive: p, index: idx });
    }
    Ok(idx)
}

/// The three vertex indices of triangle `p`.
pub fn triangle_indices(geometry_index: u32, g: &Geometry, p: u32) -> Result<[u32; 3], BuildError> {
    // Fast path for the common 32-bit indices: one bounds check for the three.
    if let GeometryData::Triangles { index_type: IndexType::U32, indices, max_vertex, .. } = g.data {
        let off = p as usize * 12;
        if let Some(b) = indices.get(off..off + 12) {
            let i = [
                u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                u32::from_le_bytes([b[4], b[5], b[6], b[7]]),
                u32::from_le_bytes([b[8], b[9], b[10], b[11]]),
            ];
            if i[0] <= max_vertex && i[1] <= max_vertex && i[2] <= max_vertex {
                return Ok(i);
            }
        }
        // Errors (and their exact position) come from the general path below.
    }
    match g.data {
        GeometryData::Triangles { index_type, indices, max_vertex, .. } => Ok([
            vertex_index(geometry_index, p, 0, index_type, indices, max_vertex)?,
            vertex_index(geometry_index, p, 1, index_type, indices, max_vertex)?,
            vertex_index(geometry_index, p, 2, index_type, indices, max_vertex)?,
        ]),
        _ => Err(BuildError::WrongGeometryType { geometry: geometry_index }),
    }
}

/// Triangle `p` after decode and transform. Ok(None) = inactive (NaN in a vertex X, checked
/// before the transform, as the spec defines activity on the input data).
pub fn read_triangle(geometry_index: u32, g: &Geometry, p: u32) -> Result<Option<[Vec3; 3]>, BuildError> {
    let GeometryData::Triangles { format, vertices, stride, transform, .. } = g.data else {
        return Err(BuildError::WrongGeometryType { geometry: geometry_index });
    };
    let idx = triangle_indices(geometry_index, g, p)?;
    let short = BuildError::InputTooShort { geometry: geometry_index };
    let size = format.size() as u64;
    let mut v = [Vec3::ZERO; 3];
    let mut inactive = false;
    let is_f32x3 = matches!(format, VertexFormat::R32G32B32Sfloat | VertexFormat::R32G32B32A32Sfloat);
    for k in 0..3 {
        if is_f32x3 {
            // Fast path: plain f32 positions.
            let off = (idx[k] as u64).checked_mul(stride).and_then(|o| usize::try_from(o).ok());
            if let Some(b) = off.and_then(|o| vertices.get(o..o.checked_add(12)?)) {
                v[k] = Vec3::new(
                    f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                    f32::from_le_bytes([b[4], b[5], b[6], b[7]]),
                    f32::from_le_bytes([b[8], b[9], b[10], b[11]]),
                );
                if size == 12 || off.and_then(|o| o.checked_add(size as usize)).is_some_and(|e| e <= vertices.len()) {
                    inactive |= v[k].x.is_nan();
                    continue;
                }
            }
        }
        let off = (idx[k] as u64).checked_mul(stride).ok_or(short.clone())?;
        let end = off.checked_add(size).ok_or(short.clone())?;
        if end > vertices.len() as u64 {
            return Err(short);
        }
        let bytes = vertices.get(off as usize..end as usize).ok_or(short.clone())?;
        v[k] = decode_vertex(format, bytes).ok_or(short.clone())?;
        inactive |= v[k].x.is_nan();
    }
    if inactive {
        return Ok(None);
    }
    if let Some(m) = transform {
        for p in v.iter_mut() {
            *p = transform_point(&m, *p);
        }
    }
    Ok(Some(v))
}

/// AABB `p` as [minX, minY, minZ, maxX, maxY, maxZ]; Ok(None) = inactive (minX NaN).
pub fn read_aabb(geometry_index: u32, g: &Geometry, p: u32) -> Result<Option<[f32; 6]>, BuildError> {
    let GeometryData::Aabbs { data, stride } = g.data else {
        return Err(BuildError::WrongGeometryType { geometry: geometry_index });
    };
    let short = BuildError::InputTooShort { geometry: geometry_index };
    let off = (p as u64).checked_mul(stride).ok_or(short.clone())?;
    let end = off.checked_add(24).ok_or(short.clone())?;
    if end > data.len() as u64 {
        return Err(short);
    }
    let off = off as usize;
    let mut b = [0f32; 6];
    for (k, slot) in b.iter_mut().enumerate() {
        *slot = rd_f32(data, off + 4 * k).ok_or(short.clone())?;
    }
    if b[0].is_nan() {
        return Ok(None);
    }
    Ok(Some(b))
}

/// A decoded VkAccelerationStructureInstanceKHR.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InstanceDesc {
    pub transform: [f32; 12],
    pub custom_index: u32,
    pub mask: u32,
    pub sbt_offset: u32,
    pub flags: u32,
    pub reference: u64,
}

/// The record at the start of `b` (None when shorter than one): one length check, then
/// fixed-offset loads.
pub fn decode_instance(b: &[u8]) -> Option<InstanceDesc> {
    let b: &[u8; INSTANCE_SIZE] = b.get(..INSTANCE_SIZE)?.try_into().ok()?;
    let w = |k: usize| u32::from_le_bytes([b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]]);
    let (w0, w1) = (w(12), w(13));
    Some(InstanceDesc {
        transform: std::array::from_fn(|k| f32::from_bits(w(k))),
        custom_index: w0 & 0x00ff_ffff,
        mask: w0 >> 24,
        sbt_offset: w1 & 0x00ff_ffff,
        flags: w1 >> 24,
        reference: w(14) as u64 | (w(15) as u64) << 32,
    })
}

/// Instance `p`; Ok(None) = inactive (reference 0).
pub fn read_instance(geometry_index: u32, g: &Geometry, p: u32, view: &dyn DeviceView) -> Result<Option<InstanceDesc>, BuildError> {
    let GeometryData::Instances { array_of_pointers, data } = g.data else {
        return Err(BuildError::WrongGeometryType { geometry: geometry_index });
    };
    let short = BuildError::InputTooShort { geometry: geometry_index };
    let record: &[u8] = if array_of_pointers {
        let off = usize::try_from((p as u64) * 8).map_err(|_| short.clone())?;
        let addr = rd_u64(data, off).ok_or(short.clone())?;
        view.bytes(addr, INSTANCE_SIZE as u64)
            .filter(|b| b.len() >= INSTANCE_SIZE)
            .ok_or(BuildError::InvalidAddress { geometry: geometry_index, primitive: p })?
    } else {
        let off = usize::try_from((p as u64) * INSTANCE_SIZE as u64).map_err(|_| short.clone())?;
        data.get(off..off.checked_add(INSTANCE_SIZE).ok_or(short.clone())?).ok_or(short.clone())?
    };
    let mut inst = decode_instance(record).ok_or(short)?;
    if inst.reference == 0 {
        return Ok(None);
    }
    // Host builds name BLASes by handle; the stored reference is always the device address.
    inst.reference = view.translate_reference(inst.reference);
    Ok(Some(inst))
}

/// The (translated) BLAS reference of instance `p`: what `read_instance` gives as
/// `reference`, without decoding the rest; None where it gives no instance.
pub fn read_instance_reference(g: &Geometry, p: u32, view: &dyn DeviceView) -> Option<u64> {
    let GeometryData::Instances { array_of_pointers, data } = g.data else { return None };
    let reference = if array_of_pointers {
        let addr = rd_u64(data, usize::try_from((p as u64) * 8).ok()?)?;
        let record = view.bytes(addr, INSTANCE_SIZE as u64).filter(|b| b.len() >= INSTANCE_SIZE)?;
        rd_u64(record, 56)?
    } else {
        let off = usize::try_from((p as u64) * INSTANCE_SIZE as u64).ok()?;
        rd_u64(data.get(off..off.checked_add(INSTANCE_SIZE)?)?, 56)?
    };
    (reference != 0).then(|| view.translate_reference(reference))
}

/// Triangle j of a geometry after format decode + transform, exactly as the builder reads it.
/// None: inactive, out of range, not a triangle geometry or unreadable.
pub fn fetch_triangle(geometry: &Geometry, primitive: u32) -> Option<[Vec3; 3]> {
    if primitive >= geometry.primitive_count {
        return None;
    }
    read_triangle(0, geometry, primitive).ok().flatten()
}

/// AABB j of a geometry. None: inactive, out of range or unreadable.
pub fn fetch_aabb(geometry: &Geometry, primitive: u32) -> Option<[f32; 6]> {
    if primitive >= geometry.primitive_count {
        return None;
    }
    read_aabb(0, geometry, primitive).ok().flatten()
}

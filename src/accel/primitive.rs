//! Primitives read from the caller's geometry: one primitive as a reference and its stored
//! data (`make_ref_data`), the fast reader of plain f32 indexed triangles (`FastTris`), the
//! geometry table's records, and the checks of a description's types and counts. Shared by
//! ingest, the planned top's sample and refit.
//!
//! Owns: decoding primitives. Must not touch: scratch, the tree, anything written to dst
//! beyond a geometry record's value.
use super::geometry::{instance_bounds, sanitize, triangle_box, triangle_bounds, PrimRef};
use super::input::{self, read_aabb, read_instance, read_triangle};
use super::layout::{self, GeometryRecord};
use super::{AsType, BuildDesc, BuildError, DeviceView, Geometry, GeometryData, IndexType, VertexFormat};
use bytemuck::Zeroable;
use glam::{Vec3, Vec3A};


/// FNV-style 64-bit hash over the index bytes, word at a time (the update's index check).
pub fn index_hash(g: &Geometry) -> [u32; 2] {
    let GeometryData::Triangles { index_type, indices, .. } = g.data else { return [0, 0] };
    let len = (g.primitive_count as u64 * 3 * index_type.size() as u64).min(indices.len() as u64) as usize;
    let bytes = &indices[..len];
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut chunks = bytes.chunks_exact(8);
    for c in &mut chunks {
        let mut w = [0u8; 8];
        w.copy_from_slice(c);
        h = (h ^ u64::from_le_bytes(w)).wrapping_mul(0x0000_0100_0000_01b3);
    }
    for &b in chunks.remainder() {
        h = (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3);
    }
    h = (h ^ len as u64).wrapping_mul(0x0000_0100_0000_01b3);
    [h as u32, (h >> 32) as u32]
}

/// Reads primitive `p` of geometry `gi` as a reference; None = not stored (inactive, or a
/// degenerate triangle that may be dropped).
pub fn make_ref(gi: u32, g: &Geometry, p: u32, view: &dyn DeviceView, allow_update: bool) -> Result<Option<PrimRef>, BuildError> {
    Ok(make_ref_data(gi, g, p, view, allow_update)?.map(|x| x.0))
}

/// `make_ref` plus the primitive data the format stores (vertices, or the AABB).
pub fn make_ref_data(gi: u32, g: &Geometry, p: u32, view: &dyn DeviceView, allow_update: bool) -> Result<Option<(PrimRef, [f32; 9])>, BuildError> {
    let mut data = [0f32; 9];
    let (lo, hi) = match g.data {
        GeometryData::Triangles { .. } => {
            let Some(v) = read_triangle(gi, g, p)? else { return Ok(None) };
            if !allow_update {
                // Degenerate (zero-area) triangles produce no hits; dropping them is allowed
                // only when a later update cannot make them non-degenerate.
                let n = (v[1] - v[0]).cross(v[2] - v[0]);
                if n == Vec3::ZERO {
                    return Ok(None);
                }
            } else {
                // Repeated indices may always be dropped: an update cannot change indices.
                let idx = input::triangle_indices(gi, g, p)?;
                let repeated = idx[0] == idx[1] || idx[1] == idx[2] || idx[0] == idx[2];
                if repeated && !matches!(g.data, GeometryData::Triangles { index_type: IndexType::None, .. }) {
                    return Ok(None);
                }
            }
            data = [v[0].x, v[0].y, v[0].z, v[1].x, v[1].y, v[1].z, v[2].x, v[2].y, v[2].z];
            triangle_bounds(&v)
        }
        GeometryData::Aabbs { .. } => {
            let Some(b) = read_aabb(gi, g, p)? else { return Ok(None) };
            data[..6].copy_from_slice(&b);
            sanitize([b[0], b[1], b[2]], [b[3], b[4], b[5]])
        }
        GeometryData::Instances { .. } => {
            let Some(inst) = read_instance(gi, g, p, view)? else { return Ok(None) };
            instance_bounds(&inst.transform, inst.reference, view)
        }
    };
    Ok(Some((PrimRef { lo, geom: gi, hi, prim: p }, data)))
}

/// Triangles with plain f32 positions (R32G32B32_SFLOAT, or R32G32B32A32_SFLOAT whose first
/// three floats are the same), U32 or U16 indices and no transform: the common input, read with
/// direct little-endian loads instead of the generic per-format decode. Gives exactly what
/// `make_ref_data` gives; anything out of range falls back to it (which reports the error).
pub struct FastTris<'a> {
    vertices: &'a [u8],
    indices: &'a [u8],
    stride: usize,
    size: usize,
    max_vertex: u32,
    u16_indices: bool,
}

impl<'a> FastTris<'a> {
    pub fn of(g: &Geometry<'a>) -> Option<Self> {
        let GeometryData::Triangles { format, vertices, stride, max_vertex, index_type, indices, transform: None } = g.data else { return None };
        if !matches!(format, VertexFormat::R32G32B32Sfloat | VertexFormat::R32G32B32A32Sfloat) {
            return None;
        }
        let u16_indices = match index_type {
            IndexType::U16 => true,
            IndexType::U32 => false,
            IndexType::None => return None,
        };
        Some(FastTris { vertices, indices, stride: usize::try_from(stride).ok()?, size: format.size() as usize, max_vertex, u16_indices })
    }

    #[inline(always)]
    fn vertex(&self, i: u32) -> Option<Vec3A> {
        let o = (i as usize).checked_mul(self.stride)?;
        let b = self.vertices.get(o..o.checked_add(self.size)?)?;
        // A fixed-size view: the twelve byte reads need no bounds checks.
        let (b, _) = b.split_first_chunk::<12>()?;
        Some(Vec3A::new(
            f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
            f32::from_le_bytes([b[4], b[5], b[6], b[7]]),
            f32::from_le_bytes([b[8], b[9], b[10], b[11]]),
        ))
    }

    /// Vertex indices and positions of triangle `p`; None when an index or vertex is out of range.
    #[inline(always)]
    pub fn read(&self, p: u32) -> Option<([u32; 3], [Vec3A; 3])> {
        let idx = self.indices(p)?;
        Some((idx, self.positions(idx)?))
    }

    /// The vertex indices of triangle `p` (what `read` gives first); None when out of range.
    #[inline(always)]
    pub fn indices(&self, p: u32) -> Option<[u32; 3]> {
        let idx = if self.u16_indices {
            let o = (p as usize).checked_mul(6)?;
            let (b, _) = self.indices.get(o..)?.split_first_chunk::<6>()?;
            [u16::from_le_bytes([b[0], b[1]]) as u32, u16::from_le_bytes([b[2], b[3]]) as u32, u16::from_le_bytes([b[4], b[5]]) as u32]
        } else {
            let o = (p as usize).checked_mul(12)?;
            let (b, _) = self.indices.get(o..)?.split_first_chunk::<12>()?;
            [
                u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                u32::from_le_bytes([b[4], b[5], b[6], b[7]]),
                u32::from_le_bytes([b[8], b[9], b[10], b[11]]),
            ]
        };
        if idx[0] > self.max_vertex || idx[1] > self.max_vertex || idx[2] > self.max_vertex {
            return None;
        }
        Some(idx)
    }

    /// Prefetches the index bytes of triangle `p`.
    #[inline(always)]
    pub fn prefetch_indices(&self, p: u32) {
        arbor_prefetch::read(self.indices, p as usize * if self.u16_indices { 6 } else { 12 });
    }

    /// Prefetches the vertices of triangle `p` (ingest runs this PREFETCH_AHEAD triangles
    /// ahead: indices come in order, vertices at random).
    #[inline(always)]
    pub fn prefetch(&self, p: u32) {
        if let Some(idx) = self.indices(p) {
            for i in idx {
                if let Some(o) = (i as usize).checked_mul(self.stride) {
                    arbor_prefetch::read(self.vertices, o);
                }
            }
        }
    }

    /// The positions of vertices `idx` (what `read` gives second); None when out of range.
    #[inline(always)]
    pub fn positions(&self, idx: [u32; 3]) -> Option<[Vec3A; 3]> {
        Some([self.vertex(idx[0])?, self.vertex(idx[1])?, self.vertex(idx[2])?])
    }

    /// What `make_ref_data` gives for this geometry, as (lo, hi, vertices) in registers for
    /// `ingest` to store directly (a data array built on the stack and copied out stalled
    /// every triangle on a failed store-to-load forward); outer None = use the general path.
    #[inline(always)]
    pub fn bounds(&self, p: u32, allow_update: bool) -> Option<Option<(Vec3A, Vec3A, [Vec3A; 3])>> {
        let (idx, [a, b, c]) = self.read(p)?;
        if a.x.is_nan() || b.x.is_nan() || c.x.is_nan() {
            return Some(None);
        }
        if !allow_update {
            if (b - a).cross(c - a) == Vec3A::ZERO {
                return Some(None);
            }
        } else if idx[0] == idx[1] || idx[1] == idx[2] || idx[0] == idx[2] {
            return Some(None);
        }
        let (lo, hi) = triangle_box(a, b, c);
        Some(Some((lo, hi, [a, b, c])))
    }
}


pub fn check_types(desc: &BuildDesc) -> Result<(), BuildError> {
    for (gi, g) in desc.geometries.iter().enumerate() {
        let ok = matches!((desc.ty, &g.data), (AsType::TopLevel, GeometryData::Instances { .. }) | (AsType::BottomLevel, GeometryData::Triangles { .. } | GeometryData::Aabbs { .. }));
        if !ok {
            return Err(BuildError::WrongGeometryType { geometry: gi as u32 });
        }
    }
    Ok(())
}

pub fn total_primitives(desc: &BuildDesc) -> Result<u64, BuildError> {
    let total: u64 = desc.geometries.iter().map(|g| g.primitive_count as u64).sum();
    if total > u32::MAX as u64 || desc.geometries.len() as u64 > u32::MAX as u64 {
        return Err(BuildError::TooManyPrimitives);
    }
    Ok(total)
}

pub fn geometry_record(g: &Geometry, active: u32, allow_update: bool) -> GeometryRecord {
    let mut r = GeometryRecord::zeroed();
    r.flags = g.flags.0;
    r.primitive_count = g.primitive_count;
    r.active_count = active;
    match g.data {
        GeometryData::Triangles { format, max_vertex, index_type, transform, .. } => {
            r.kind = layout::KIND_TRIANGLES;
            r.format = format.to_vk();
            r.index_type = index_type.to_vk();
            r.max_vertex = max_vertex;
            r.has_transform = transform.is_some() as u32;
            if allow_update {
                r.index_hash = index_hash(g);
            }
        }
        GeometryData::Aabbs { .. } => r.kind = layout::KIND_AABBS,
        GeometryData::Instances { .. } => r.kind = layout::KIND_INSTANCES,
    }
    r
}


/// The geometry of global primitive ID `id`: `firsts[g]` is geometry g's first ID, `firsts[ngeo]`
/// the total.
#[inline(always)]
pub fn geometry_of(id: u32, firsts: &[u32]) -> u32 {
    if firsts.len() <= 2 {
        return 0;
    }
    (firsts[1..].partition_point(|&f| f <= id)) as u32
}

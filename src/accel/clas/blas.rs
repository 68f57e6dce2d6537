//! Cluster BLAS: the triangles of the CLASes it references, gathered in reference order into an
//! ordinary bottom-level BVH embedded in the blob (the KHR builder, one non-opaque triangle
//! geometry), beside a side table that gives each stored triangle its cluster ID, geometry index
//! and flags and its index within its cluster. Traversal walks the embedded BVH with the
//! ordinary code and asks `Side` for those facts; `open_walkable` is the one place it learns
//! which kind of blob it was handed.
use super::format::{self, align_up, new_header, open, put_u32, rd_u32, Kind, HEADER_SIZE, SIDE_SIZE};
use super::{ClusterError, MAX_TRIANGLES};
use crate::accel::layout::{self, Parsed};
use crate::accel::{self as accel, AsType, BuildFlags, Geometry, GeometryData, GeometryFlags, GeometryShape, IndexType, NoDevice, VertexFormat};

/// Offset of the embedded BVH for `clusters` references over `triangles` triangles.
pub fn bvh_offset(clusters: u64, triangles: u64) -> u64 {
    align_up(HEADER_SIZE + 8 * clusters + SIDE_SIZE * triangles, layout::SECTION_ALIGN)
}

fn bvh_sizes(triangles: u64) -> accel::BuildSizes {
    let n = triangles.min(u32::MAX as u64) as u32;
    let shape = GeometryShape::Triangles { format: VertexFormat::R32G32B32Sfloat, index_type: IndexType::None, max_vertex: n.saturating_mul(3), has_transform: false };
    accel::build_sizes(AsType::BottomLevel, BuildFlags(0), &[shape], &[n])
}

/// Worst-case size of a cluster BLAS over `clusters` references of up to MAX_TRIANGLES each.
pub fn blas_size_bound(clusters: u64) -> u64 {
    let t = clusters.saturating_mul(MAX_TRIANGLES as u64);
    bvh_offset(clusters, t).saturating_add(bvh_sizes(t).acceleration_structure_size)
}

/// The size a cluster BLAS over `clusters` CLASes of `triangles` triangles in all can take.
pub fn blas_size_for(clusters: u64, triangles: u64) -> u64 {
    bvh_offset(clusters, triangles).saturating_add(bvh_sizes(triangles).acceleration_structure_size)
}

/// BUILD_CLUSTERS_BOTTOM_LEVEL: one cluster BLAS over `clusters` (each CLAS's address and bytes,
/// in reference order). Only the build-flag bits that steer the builder are passed on.
pub fn build_cluster_blas(clusters: &[(u64, &[u8])], flags: u32, dst: &mut [u8]) -> Result<u64, ClusterError> {
    let mut opened = Vec::with_capacity(clusters.len());
    for &(address, bytes) in clusters {
        let b = open(bytes).filter(|b| b.kind == Kind::Clas).ok_or(ClusterError::NotAClas { address })?;
        opened.push(b);
    }
    let total: u64 = opened.iter().map(|b| b.header.triangle_count as u64).sum();
    let bvh_at = bvh_offset(clusters.len() as u64, total);
    let bound = blas_size_for(clusters.len() as u64, total);
    if (dst.len() as u64) < bound {
        return Err(ClusterError::DestinationTooSmall { needed: bound, got: dst.len() as u64 });
    }
    let mut vertices = Vec::with_capacity(total as usize * 36);
    let mut side = HEADER_SIZE + 8 * clusters.len() as u64;
    for (ordinal, (b, &(address, _))) in opened.iter().zip(clusters).enumerate() {
        dst[(HEADER_SIZE + 8 * ordinal as u64) as usize..][..8].copy_from_slice(&address.to_le_bytes());
        for i in 0..b.header.triangle_count {
            for x in b.triangle(i) {
                vertices.extend_from_slice(&x.to_bits().to_le_bytes());
            }
            for (k, v) in [b.header.cluster_id, b.word(i), i, ordinal as u32].into_iter().enumerate() {
                put_u32(dst, side + 4 * k as u64, v);
            }
            side += SIDE_SIZE;
        }
    }
    let keep = flags & (BuildFlags::PREFER_FAST_TRACE | BuildFlags::PREFER_FAST_BUILD);
    let geometry = Geometry {
        flags: GeometryFlags(0),
        primitive_count: total as u32,
        data: GeometryData::Triangles {
            format: VertexFormat::R32G32B32Sfloat,
            vertices: &vertices,
            stride: 12,
            max_vertex: (3 * total as u32).saturating_sub(1),
            index_type: IndexType::None,
            indices: &[],
            transform: None,
        },
    };
    let desc = accel::BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(keep), geometries: &[geometry] };
    let mut scratch = vec![0u8; bvh_sizes(total).build_scratch_size as usize];
    let report = accel::build(&desc, &NoDevice, &mut dst[bvh_at as usize..bound as usize], &mut scratch).map_err(ClusterError::Build)?;
    let mut h = new_header(Kind::ClusterBlas);
    h.cluster_count = clusters.len() as u32;
    h.triangle_count = total as u32;
    h.bvh_offset = bvh_at;
    h.bvh_size = report.used_size;
    h.used_size = bvh_at + report.used_size;
    h.bounds = layout::header(&dst[bvh_at as usize..]).map_or([0.0; 6], |e| e.bounds);
    format::write_header(dst, &h);
    Ok(h.used_size)
}

/// The CLAS addresses a cluster BLAS was built over, in reference order.
pub fn cluster_references(bytes: &[u8]) -> Option<Vec<u64>> {
    let b = open(bytes).filter(|b| b.kind == Kind::ClusterBlas)?;
    Some((0..b.header.cluster_count as u64).map(|k| (rd_u32(b.bytes, HEADER_SIZE + 8 * k) as u64) | ((rd_u32(b.bytes, HEADER_SIZE + 8 * k + 4) as u64) << 32)).collect())
}

/// A cluster BLAS's per-triangle facts, indexed by the embedded BVH's primitive index.
#[derive(Clone, Copy, Debug)]
pub struct Side<'a> {
    table: &'a [u8],
}

/// VkGeometryFlagBitsKHR bits traversal reads, plus one of its own for per-triangle
/// CULL_DISABLE (KHR geometries have no such flag).
pub const FLAG_CULL_DISABLE: u32 = 1 << 31;

/// What a cluster triangle reports: cluster ID, geometry index, index in its cluster, and its
/// flags as traversal reads them (opaque 1, no-duplicate-any-hit 2, FLAG_CULL_DISABLE).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SideEntry {
    pub cluster_id: u32,
    pub geometry_index: u32,
    pub primitive_index: u32,
    pub flags: u32,
}

impl Side<'_> {
    pub fn get(&self, primitive: u32) -> Option<SideEntry> {
        let off = primitive as u64 * SIDE_SIZE;
        if off + SIDE_SIZE > self.table.len() as u64 {
            return None;
        }
        let w = super::args::GeometryIndexAndFlags(rd_u32(self.table, off + 4));
        let g = w.geometry_flags();
        let bit = |cluster_bit: u32, traversal_bit: u32| if g & cluster_bit != 0 { traversal_bit } else { 0 };
        let flags = bit(4, GeometryFlags::OPAQUE) | bit(2, GeometryFlags::NO_DUPLICATE_ANY_HIT_INVOCATION) | bit(1, FLAG_CULL_DISABLE);
        Some(SideEntry { cluster_id: rd_u32(self.table, off), geometry_index: w.geometry_index(), primitive_index: rd_u32(self.table, off + 8), flags })
    }
}

/// The BVH traversal walks for the structure at the start of `bytes`: a KHR structure as it is,
/// or a cluster BLAS's embedded BVH with its side table. None for anything else.
pub fn open_walkable(bytes: &[u8]) -> Option<(Parsed<'_>, Option<Side<'_>>)> {
    if let Some(p) = layout::parse(bytes) {
        return Some((p, None));
    }
    let b = open(bytes).filter(|b| b.kind == Kind::ClusterBlas)?;
    let h = b.header;
    let p = layout::parse(&b.bytes[h.bvh_offset as usize..]).filter(|p| !p.is_tlas())?;
    let start = HEADER_SIZE + 8 * h.cluster_count as u64;
    let table = &b.bytes[start as usize..(start + SIDE_SIZE * h.triangle_count as u64) as usize];
    Some((p, Some(Side { table })))
}

//! Cluster BLAS: a top tree over the CLASes it references, which stay where they are. The blob
//! holds the CLAS address table, a table of the non-empty CLASes (reference ordinal and
//! triangle count, in top-tree leaf order) and a small bottom-level BVH whose nodes are the top
//! tree alone; the CLAS trees and triangles are not copied. Traversal resolves a CLAS through
//! the device view when it reaches one (as a TLAS resolves its BLASes), checks its header and
//! walks its own tree; `Side` is that resolution, `open_walkable` the one place traversal learns
//! which kind of blob it was handed. Moving a CLAS requires rebuilding the BLASes that name it
//! (nv-extensions.md B.7); a freed or overwritten CLAS is a contained fault.
use super::format::{self, align_up, new_header, open, rd_u32, Blob, Kind, HEADER_SIZE, NODE_SIZE};
use super::tree::{build_top, local_node_count, quantize_top, TopChild, LEAF};
use super::{ClusterError, MAX_TRIANGLES};
use crate::accel::geometry::Aabb;
use crate::accel::layout::{self, GeometryRecord, Parsed, RawHeader, WideNode, CHILD_INTERNAL};
use crate::accel::{checksum, AsType, BuildError, BuildFlags, DeviceView, GeometryFlags, IndexType, VertexFormat};
use bytemuck::Zeroable;

/// Bytes per entry of the table of non-empty CLASes: reference ordinal, triangle count.
const LIVE_SIZE: u64 = 8;
/// Node and slot indices of a CLAS tree, seen from the cluster BLAS, are
/// `k_top + x * STRIDE + local` and `x * STRIDE + slot` for the x-th non-empty CLAS: a CLAS
/// has at most MAX_TRIANGLES slots and fewer nodes, so the ranges never meet, and a child's
/// index stays above its parent's.
const STRIDE: u32 = MAX_TRIANGLES;
const _: () = assert!(MAX_TRIANGLES as u64 <= STRIDE as u64 && STRIDE.is_power_of_two());
/// Non-empty CLASes a cluster BLAS can index with u32 node indices.
const MAX_LIVE: u64 = (u32::MAX / STRIDE / 2) as u64;

/// Offset of the embedded BVH for `clusters` references.
pub fn bvh_offset(clusters: u64) -> u64 {
    align_up(HEADER_SIZE.saturating_add(clusters.saturating_mul(8 + LIVE_SIZE)), layout::SECTION_ALIGN)
}

fn bvh_size(nodes: u64) -> u64 {
    layout::sections(AsType::BottomLevel, nodes, 0, 1).end
}

/// Worst-case size of a cluster BLAS over `clusters` references.
pub fn blas_size_bound(clusters: u64) -> u64 {
    blas_size_for(clusters, clusters.saturating_mul(MAX_TRIANGLES as u64))
}

/// The size a cluster BLAS over `clusters` CLASes of `triangles` triangles in all can take: the
/// tables and a top tree of fewer nodes than clusters (four-way). The triangle count no longer
/// matters (the CLASes keep their triangles); the argument stays for the callers' bound.
pub fn blas_size_for(clusters: u64, _triangles: u64) -> u64 {
    bvh_offset(clusters).saturating_add(bvh_size(clusters.max(1)))
}

/// BUILD_CLUSTERS_BOTTOM_LEVEL: one cluster BLAS over `clusters` (each CLAS's address and bytes,
/// in reference order). Only the build-flag bits that steer the builder are recorded.
pub fn build_cluster_blas(clusters: &[(u64, &[u8])], flags: u32, dst: &mut [u8]) -> Result<u64, ClusterError> {
    let mut live: Vec<(u32, Blob<'_>)> = Vec::with_capacity(clusters.len());
    let mut total = 0u64;
    for (k, &(address, bytes)) in clusters.iter().enumerate() {
        let blob = open(bytes).filter(|b| b.kind == Kind::Clas).ok_or(ClusterError::NotAClas { address })?;
        total += blob.header.triangle_count as u64;
        if blob.header.triangle_count > 0 {
            live.push((k as u32, blob));
        }
    }
    let c = clusters.len() as u64;
    if total > u32::MAX as u64 / 2 || live.len() as u64 > MAX_LIVE {
        return Err(ClusterError::Build(BuildError::TooManyPrimitives));
    }
    let bound = blas_size_for(c, total);
    if (dst.len() as u64) < bound {
        return Err(ClusterError::DestinationTooSmall { needed: bound, got: dst.len() as u64 });
    }
    let boxes: Vec<Aabb> = live.iter().map(|p| p.1.header.bounds).map(|b| Aabb { lo: [b[0], b[1], b[2]], hi: [b[3], b[4], b[5]] }).collect();
    let top = if live.len() >= 2 { build_top(&boxes) } else { Vec::new() };
    let k_top = top.len() as u32;
    let bvh_at = bvh_offset(c) as usize;
    let s = layout::sections(AsType::BottomLevel, k_top as u64, 0, 1);
    let used = bvh_at + s.end as usize;
    let (head, bvh) = dst[..used].split_at_mut(bvh_at);
    head[HEADER_SIZE as usize..].fill(0);
    for (k, &(address, _)) in clusters.iter().enumerate() {
        head[HEADER_SIZE as usize + 8 * k..][..8].copy_from_slice(&address.to_le_bytes());
    }
    let live_at = HEADER_SIZE as usize + 8 * clusters.len();
    for (x, (ordinal, b)) in live.iter().enumerate() {
        let e = &mut head[live_at + LIVE_SIZE as usize * x..][..LIVE_SIZE as usize];
        e[..4].copy_from_slice(&ordinal.to_le_bytes());
        e[4..].copy_from_slice(&b.header.triangle_count.to_le_bytes());
    }
    let leaves = live.iter().map(|p| p.1.header.triangle_count.div_ceil(LEAF)).sum();
    write_bvh_frame(bvh, &s, (k_top as u64, total, leaves), flags, &boxes);
    for (i, n) in top.iter().enumerate() {
        let w = quantize_top(n, |ch| match ch {
            TopChild::Node(j) => j,
            TopChild::Cluster(x) => k_top + x * STRIDE,
        });
        bvh[(s.nodes + i as u64 * NODE_SIZE) as usize..][..NODE_SIZE as usize].copy_from_slice(bytemuck::bytes_of(&w));
    }
    checksum::seal(bvh);
    let mut h = new_header(Kind::ClusterBlas);
    h.cluster_count = c as u32;
    h.live_count = live.len() as u32;
    h.triangle_count = total as u32;
    h.bvh_offset = bvh_at as u64;
    h.bvh_size = s.end;
    h.used_size = used as u64;
    h.bounds = layout::header(bvh).map_or([0.0; 6], |e| e.bounds);
    format::write_header(dst, &h);
    Ok(used as u64)
}

/// The embedded BVH's header and geometry record, and zeros in every byte no section fills
/// (so the blob is a function of its inputs). It holds the top tree's nodes and no primitives.
fn write_bvh_frame(bvh: &mut [u8], s: &layout::Sections, (nodes, total, leaves): (u64, u64, u32), flags: u32, boxes: &[Aabb]) {
    bvh[layout::HEADER_SIZE..].fill(0);
    let g = GeometryRecord {
        kind: layout::KIND_TRIANGLES,
        flags: GeometryFlags(0).0,
        primitive_count: total as u32,
        active_count: total as u32,
        format: VertexFormat::R32G32B32Sfloat.to_vk(),
        index_type: IndexType::None.to_vk(),
        max_vertex: (3 * total as u32).saturating_sub(1),
        ..GeometryRecord::zeroed()
    };
    bvh[s.geometries as usize..][..layout::GEOMETRY_SIZE].copy_from_slice(bytemuck::bytes_of(&g));
    let b = boxes.iter().fold(Aabb::EMPTY, |a, b| a.union(b));
    let keep = flags & (BuildFlags::PREFER_FAST_TRACE | BuildFlags::PREFER_FAST_BUILD);
    let raw = RawHeader {
        magic: layout::MAGIC,
        version: layout::FORMAT_VERSION,
        ty: AsType::BottomLevel as u32,
        flags: keep,
        valid: layout::valid_word(),
        geometry_count: 1,
        primitive_count: 0,
        node_count: nodes as u32,
        leaf_count: leaves,
        bounds: if boxes.is_empty() { [0.0; 6] } else { [b.lo[0], b.lo[1], b.lo[2], b.hi[0], b.hi[1], b.hi[2]] },
        total_primitives: total as u32,
        used_size: s.end,
        nodes_offset: s.nodes,
        prims_offset: s.prims,
        records_offset: s.records,
        geometries_offset: s.geometries,
        instances_offset: s.instances,
        blas_table_offset: s.blas_table,
        max_leaf_size: LEAF,
        ..RawHeader::zeroed()
    };
    layout::write_header(bvh, &raw);
}

fn rd_u64(b: &[u8], off: u64) -> u64 {
    (rd_u32(b, off) as u64) | ((rd_u32(b, off + 4) as u64) << 32)
}

/// The CLAS addresses a cluster BLAS was built over, in reference order.
pub fn cluster_references(bytes: &[u8]) -> Option<Vec<u64>> {
    let b = open(bytes).filter(|b| b.kind == Kind::ClusterBlas)?;
    Some((0..b.header.cluster_count as u64).map(|k| rd_u64(b.bytes, HEADER_SIZE + 8 * k)).collect())
}

/// A cluster BLAS's tables and the view its CLASes are resolved through. Node and primitive
/// indices past the top tree name a CLAS and a node or slot of its own tree (`STRIDE`).
#[derive(Clone, Copy)]
pub struct Side<'a> {
    /// The address table followed by the table of non-empty CLASes.
    tables: &'a [u8],
    clusters: u32,
    live: u32,
    k_top: u32,
    view: Option<&'a dyn DeviceView>,
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

impl<'a> Side<'a> {
    /// The same tables, resolving CLASes through `view`.
    pub fn with_view(self, view: &'a dyn DeviceView) -> Self {
        Side { view: Some(view), ..self }
    }

    /// The x-th non-empty CLAS, or Err(its address) when no CLAS of the recorded triangle count
    /// is there (freed, moved or overwritten since the build).
    pub fn clas(&self, x: u32) -> Result<Blob<'a>, u64> {
        if x >= self.live {
            return Err(0);
        }
        let e = 8 * self.clusters as u64 + LIVE_SIZE * x as u64;
        let (ordinal, t) = (rd_u32(self.tables, e), rd_u32(self.tables, e + 4));
        if ordinal >= self.clusters {
            return Err(0);
        }
        let address = rd_u64(self.tables, 8 * ordinal as u64);
        let bytes = self.view.and_then(|v| v.acceleration_structure(address)).ok_or(address)?;
        open(bytes).filter(|b| b.kind == Kind::Clas && b.header.triangle_count == t).ok_or(address)
    }

    /// The address of the CLAS that node `i` lies in when it cannot be resolved.
    pub fn fault(&self, i: u32) -> Option<u64> {
        let e = i.checked_sub(self.k_top)?;
        self.clas(e / STRIDE).err()
    }

    /// Node `i`: one of the top tree's, or a CLAS tree's with its indices moved into the BLAS's
    /// ranges. None when its CLAS cannot be resolved or the node is out of range.
    pub fn node(&self, top: &Parsed<'_>, i: u32) -> Option<WideNode> {
        let Some(e) = i.checked_sub(self.k_top) else { return top.node(i) };
        let (x, local) = (e / STRIDE, e % STRIDE);
        let b = self.clas(x).ok()?;
        if local as u64 >= local_node_count(b.header.triangle_count as u64) {
            return None;
        }
        let mut n = b.node(local);
        for c in 0..(n.child_count as usize).min(4) {
            match n.kind[c] {
                0 => {}
                _ if n.child[c] >= STRIDE => n.kind[c] = 0,
                CHILD_INTERNAL => n.child[c] += self.k_top + x * STRIDE,
                _ => n.child[c] += x * STRIDE,
            }
        }
        Some(n)
    }

    /// The triangle in slot `slot` (a CLAS and a slot of its tree): its stored vertices and
    /// what it reports.
    pub fn triangle(&self, slot: u32) -> Option<([f32; 9], SideEntry)> {
        let b = self.clas(slot / STRIDE).ok()?;
        let t = b.header.triangle_count;
        let s = slot % STRIDE;
        if s >= t {
            return None;
        }
        let i = b.slot(s);
        if i >= t {
            return None;
        }
        let w = super::args::GeometryIndexAndFlags(b.word(i));
        let g = w.geometry_flags();
        let bit = |cluster_bit: u32, traversal_bit: u32| if g & cluster_bit != 0 { traversal_bit } else { 0 };
        let flags = bit(4, GeometryFlags::OPAQUE) | bit(2, GeometryFlags::NO_DUPLICATE_ANY_HIT_INVOCATION) | bit(1, FLAG_CULL_DISABLE);
        Some((b.triangle(i), SideEntry { cluster_id: b.header.cluster_id, geometry_index: w.geometry_index(), primitive_index: i, flags }))
    }
}

/// The BVH traversal walks for the structure at the start of `bytes`: a KHR structure as it is,
/// or a cluster BLAS's top tree with its tables (resolving nothing until `Side::with_view`). A
/// cluster BLAS's node and primitive counts are those of its index ranges (what bounds a walk).
/// None for anything else.
pub fn open_walkable(bytes: &[u8]) -> Option<(Parsed<'_>, Option<Side<'_>>)> {
    if let Some(p) = layout::parse(bytes) {
        return Some((p, None));
    }
    let b = open(bytes).filter(|b| b.kind == Kind::ClusterBlas)?;
    let h = b.header;
    let mut p = layout::parse(&b.bytes[h.bvh_offset as usize..]).filter(|p| !p.is_tlas())?;
    let k_top = p.raw.node_count;
    if h.live_count == 0 {
        p.raw.node_count = 0;
    } else {
        p.raw.node_count = k_top.checked_add(h.live_count.checked_mul(STRIDE)?)?;
    }
    p.raw.primitive_count = h.triangle_count;
    let end = HEADER_SIZE + 8 * h.cluster_count as u64 + LIVE_SIZE * h.live_count as u64;
    let tables = &b.bytes[HEADER_SIZE as usize..end as usize];
    Some((p, Some(Side { tables, clusters: h.cluster_count, live: h.live_count, k_top, view: None })))
}

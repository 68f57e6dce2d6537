//! Cluster BLAS: a BVH over the CLASes it references. Each CLAS brings its own small tree
//! (tree.rs); the BLAS builds a top tree over the CLAS boxes whose bottom children are those
//! trees' roots, and copies the trees, the triangles in tree-slot order and a side table (cluster
//! ID, geometry index and flags, index within the cluster) into one ordinary bottom-level BVH
//! embedded in the blob, so the blob stays self-contained and a move stays a byte copy. The work
//! is a top build over the clusters plus copies, not a build over the triangles. Traversal walks
//! the embedded BVH with the ordinary code and asks `Side` for the cluster facts;
//! `open_walkable` is the one place it learns which kind of blob it was handed.
use super::format::{self, align_up, new_header, open, rd_u32, Blob, Kind, HEADER_SIZE, NODE_SIZE, SIDE_SIZE, TRIANGLE_SIZE};
use super::tree::{build_top, local_node_bound, local_node_count, quantize_top, TopChild, LEAF};
use super::{ClusterError, MAX_TRIANGLES};
use crate::accel::geometry::Aabb;
use crate::accel::layout::{self, GeometryRecord, Parsed, RawHeader, WideNode, CHILD_INTERNAL, PRIM_SIZE, RECORD_SIZE};
use crate::accel::{checksum, AsType, BuildError, BuildFlags, GeometryFlags, IndexType, VertexFormat};
use bytemuck::Zeroable;
use rayon::prelude::*;

/// Offset of the embedded BVH for `clusters` references over `triangles` triangles.
pub fn bvh_offset(clusters: u64, triangles: u64) -> u64 {
    align_up(HEADER_SIZE.saturating_add(clusters.saturating_mul(8)).saturating_add(triangles.saturating_mul(SIDE_SIZE)), layout::SECTION_ALIGN)
}

/// Nodes of the embedded BVH at most: the CLAS trees' plus a top tree over the clusters
/// (four-way, so fewer nodes than clusters).
fn node_bound(clusters: u64, triangles: u64) -> u64 {
    local_node_bound(clusters, triangles).saturating_add(clusters.max(1))
}

fn bvh_size(nodes: u64, triangles: u64) -> u64 {
    layout::sections(AsType::BottomLevel, nodes, triangles, 1).end
}

/// Worst-case size of a cluster BLAS over `clusters` references of up to MAX_TRIANGLES each.
pub fn blas_size_bound(clusters: u64) -> u64 {
    blas_size_for(clusters, clusters.saturating_mul(MAX_TRIANGLES as u64))
}

/// The size a cluster BLAS over `clusters` CLASes of `triangles` triangles in all can take.
pub fn blas_size_for(clusters: u64, triangles: u64) -> u64 {
    bvh_offset(clusters, triangles).saturating_add(bvh_size(node_bound(clusters, triangles), triangles))
}

/// One referenced CLAS and where its slots and tree nodes land in the BLAS.
struct Part<'a> {
    blob: Blob<'a>,
    ordinal: u32,
    slot_base: u32,
    node_base: u32,
}

/// The destination regions of one CLAS: side entries, triangles, records, nodes.
type Regions<'d> = (&'d mut [u8], &'d mut [u8], &'d mut [u8], &'d mut [u8]);

/// Copies one CLAS into its regions: triangles in tree-slot order, their records and side
/// entries, and its tree with node and slot indices moved to their BLAS positions.
fn copy_cluster(p: &Part<'_>, node_shift: u32, (side, prims, recs, nodes): Regions<'_>) {
    let b = &p.blob;
    let t = b.header.triangle_count as usize;
    let tris = &b.bytes[HEADER_SIZE as usize..][..t * TRIANGLE_SIZE as usize];
    let words = &b.bytes[HEADER_SIZE as usize + t * TRIANGLE_SIZE as usize..][..4 * t];
    let id = b.header.cluster_id.to_le_bytes();
    let ordinal = p.ordinal.to_le_bytes();
    let out = side.chunks_exact_mut(SIDE_SIZE as usize).zip(prims.chunks_exact_mut(PRIM_SIZE)).zip(recs.chunks_exact_mut(RECORD_SIZE));
    for (s, (((sd, pr), rc), &i)) in out.zip(b.order()).enumerate() {
        let i = i as usize;
        pr.copy_from_slice(&tris[i * TRIANGLE_SIZE as usize..][..PRIM_SIZE]);
        rc[..4].fill(0);
        rc[4..].copy_from_slice(&(p.slot_base + s as u32).to_le_bytes());
        sd[..4].copy_from_slice(&id);
        sd[4..8].copy_from_slice(&words[4 * i..4 * i + 4]);
        sd[8..12].copy_from_slice(&(i as u32).to_le_bytes());
        sd[12..].copy_from_slice(&ordinal);
    }
    for (k, out) in nodes.chunks_exact_mut(NODE_SIZE as usize).enumerate() {
        let mut n: WideNode = b.node(k as u32);
        for c in 0..(n.child_count as usize).min(4) {
            match n.kind[c] {
                0 => {}
                CHILD_INTERNAL => n.child[c] = n.child[c].wrapping_add(node_shift),
                _ => n.child[c] = n.child[c].wrapping_add(p.slot_base),
            }
        }
        out.copy_from_slice(bytemuck::bytes_of(&n));
    }
}

/// Splits `region` into consecutive pieces of `per` × the parts' triangle or node counts.
fn pieces(mut region: &mut [u8], counts: impl Iterator<Item = usize>, per: usize) -> Vec<&mut [u8]> {
    counts
        .map(|n| {
            let (a, b) = std::mem::take(&mut region).split_at_mut(n * per);
            region = b;
            a
        })
        .collect()
}

/// BUILD_CLUSTERS_BOTTOM_LEVEL: one cluster BLAS over `clusters` (each CLAS's address and bytes,
/// in reference order). Only the build-flag bits that steer the builder are recorded.
pub fn build_cluster_blas(clusters: &[(u64, &[u8])], flags: u32, dst: &mut [u8]) -> Result<u64, ClusterError> {
    let mut parts = Vec::with_capacity(clusters.len());
    let (mut slots, mut local_nodes) = (0u64, 0u64);
    for (k, &(address, bytes)) in clusters.iter().enumerate() {
        let blob = open(bytes).filter(|b| b.kind == Kind::Clas).ok_or(ClusterError::NotAClas { address })?;
        let t = blob.header.triangle_count as u64;
        parts.push(Part { blob, ordinal: k as u32, slot_base: slots as u32, node_base: local_nodes as u32 });
        slots += t;
        local_nodes += local_node_count(t);
    }
    let (c, total) = (clusters.len() as u64, slots);
    if total > u32::MAX as u64 / 2 {
        return Err(ClusterError::Build(BuildError::TooManyPrimitives));
    }
    let bound = blas_size_for(c, total);
    if (dst.len() as u64) < bound {
        return Err(ClusterError::DestinationTooSmall { needed: bound, got: dst.len() as u64 });
    }
    let live: Vec<&Part<'_>> = parts.iter().filter(|p| p.blob.header.triangle_count > 0).collect();
    let boxes: Vec<Aabb> = live.iter().map(|p| p.blob.header.bounds).map(|b| Aabb { lo: [b[0], b[1], b[2]], hi: [b[3], b[4], b[5]] }).collect();
    let top = if live.len() >= 2 { build_top(&boxes) } else { Vec::new() };
    let k_top = top.len() as u32;
    let node_count = k_top as u64 + local_nodes;
    let bvh_at = bvh_offset(c, total) as usize;
    let s = layout::sections(AsType::BottomLevel, node_count, total, 1);
    let used = bvh_at + s.end as usize;
    let (head, bvh) = dst[..used].split_at_mut(bvh_at);
    for (k, &(address, _)) in clusters.iter().enumerate() {
        head[HEADER_SIZE as usize + 8 * k..][..8].copy_from_slice(&address.to_le_bytes());
    }
    let side_at = HEADER_SIZE as usize + 8 * clusters.len();
    let (_, side_all) = head.split_at_mut(side_at);
    let (side, gap) = side_all.split_at_mut(total as usize * SIDE_SIZE as usize);
    gap.fill(0);
    let t_of = || parts.iter().map(|p| p.blob.header.triangle_count as usize);
    let leaves = t_of().map(|t| t.div_ceil(LEAF as usize) as u32).sum();
    write_bvh_frame(bvh, &s, (node_count, total, leaves), flags, &boxes);
    let (pre, node_area) = bvh.split_at_mut(s.nodes as usize);
    let (top_area, local_area) = node_area[..node_count as usize * NODE_SIZE as usize].split_at_mut(k_top as usize * NODE_SIZE as usize);
    for (i, n) in top.iter().enumerate() {
        let w = quantize_top(n, |ch| match ch {
            TopChild::Node(j) => j,
            TopChild::Cluster(x) => k_top + live[x as usize].node_base,
        });
        top_area[i * NODE_SIZE as usize..][..NODE_SIZE as usize].copy_from_slice(bytemuck::bytes_of(&w));
    }
    let (pre, rec_area) = pre.split_at_mut(s.records as usize);
    let prim_area = &mut pre[s.prims as usize..][..total as usize * PRIM_SIZE];
    let side = pieces(side, t_of(), SIDE_SIZE as usize);
    let prims = pieces(prim_area, t_of(), PRIM_SIZE);
    let recs = pieces(&mut rec_area[..total as usize * RECORD_SIZE], t_of(), RECORD_SIZE);
    let nodes = pieces(local_area, parts.iter().map(|p| local_node_count(p.blob.header.triangle_count as u64) as usize), NODE_SIZE as usize);
    let work: Vec<_> = parts.iter().zip(side.into_iter().zip(prims).zip(recs.into_iter().zip(nodes))).collect();
    work.into_par_iter().with_min_len(16).for_each(|(p, ((a, b), (c, d)))| copy_cluster(p, k_top + p.node_base, (a, b, c, d)));
    checksum::seal(bvh);
    let mut h = new_header(Kind::ClusterBlas);
    h.cluster_count = c as u32;
    h.triangle_count = total as u32;
    h.bvh_offset = bvh_at as u64;
    h.bvh_size = s.end;
    h.used_size = used as u64;
    h.bounds = layout::header(bvh).map_or([0.0; 6], |e| e.bounds);
    format::write_header(dst, &h);
    Ok(used as u64)
}

/// The embedded BVH's header and geometry record, and zeros in every byte no section fills
/// (so the blob is a function of its inputs).
fn write_bvh_frame(bvh: &mut [u8], s: &layout::Sections, (nodes, total, leaves): (u64, u64, u32), flags: u32, boxes: &[Aabb]) {
    let filled = [(s.geometries, s.geometries + layout::GEOMETRY_SIZE as u64), (s.prims, s.prims + total * PRIM_SIZE as u64), (s.records, s.records + total * RECORD_SIZE as u64), (s.nodes, s.nodes + nodes * NODE_SIZE)];
    let mut at = layout::HEADER_SIZE as u64;
    for (a, b) in filled {
        if a > at {
            bvh[at as usize..a as usize].fill(0);
        }
        at = at.max(b);
    }
    bvh[at as usize..].fill(0);
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
        primitive_count: total as u32,
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

//! Encoding: a built binary tree and its references → the bytes of the structure in dst. Leaf
//! data and records (`leaves`), the wide nodes (`nodes`, quantised by `quantize`), the TLAS
//! instance sections (`instances`), then the gaps zeroed and the header written (`finish`).
//!
//! Owns: every byte of dst a build writes after ingest (ingest writes the geometry table, and
//! the staging area in scratch). Must not touch: how the tree was built (it reads `BinNode`s only).
pub mod instances;
pub mod leaves;
pub mod nodes;
pub mod quantize;
pub mod tlas;

use super::checksum;
use super::geometry::{Aabb, PrimRef};
use super::layout::{self, RawHeader, NODE_SIZE, PRIM_SIZE, RECORD_SIZE, STAGE_SIZE};
use super::params::EMIT_CUT;
use super::tree::{is_cut, wide_size, BinNode};
use super::{BuildDesc, BuildError, DeviceView};
use instances::write_instances;
use leaves::{gather_clusters, gather_leaf_data, write_leaf_data};
use nodes::{copy_block, emit_seq, emit_wide, pre_block};

/// Where the primitive data of a BLAS comes from.
pub enum LeafSource<'a> {
    /// The staging area at global IDs, leaves naming cluster references mapped to primitives
    /// through `map` (`leaves::cluster_prefix`); `firsts` maps global IDs to geometries.
    Clusters { map: &'a [u32], firsts: &'a [u32] },
    /// The staging area at global IDs (one reference per primitive).
    Staged,
    /// The input again (builds too small to stage).
    Input,
}

/// Writes the prims and records sections of a BLAS of `active` primitives in leaf order from
/// the `references` of `refs`. `stage` is the staging area in scratch (`total` records; empty
/// with `LeafSource::Input`); with `LeafSource::Staged` the references get their in-geometry
/// indices back.
pub fn leaf_data(desc: &BuildDesc, dst: &mut [u8], stage: &[u8], total: usize, refs: &mut [PrimRef], (references, active): (usize, usize), source: LeafSource) {
    let at = layout::sections(desc.ty, 0, active as u64, desc.geometries.len() as u64);
    let (head, rec_part) = dst.split_at_mut(at.records as usize);
    let prims = &mut head[at.prims as usize..at.prims as usize + active * PRIM_SIZE];
    let records = &mut rec_part[..active * RECORD_SIZE];
    match source {
        LeafSource::Clusters { map, firsts } => gather_clusters(&refs[..references], map, &stage[..total * STAGE_SIZE], prims, records, firsts),
        LeafSource::Staged => gather_leaf_data(&mut refs[..active], &stage[..total * STAGE_SIZE], prims, records),
        LeafSource::Input => write_leaf_data(desc, &refs[..active], prims, records),
    }
}

/// Emits the wide nodes of `tree` (non-empty) at `nodes_at` of dst, in preorder; returns the
/// node count and the leaf count. `pre` is the pre-emission area (in scratch,
/// PRE_BYTES_PER_PRIM per reference; empty when nothing was pre-emitted), where cut roots
/// were encoded while the tree was built; their blocks are copied from there.
pub fn wide_nodes(tree: &[BinNode], dst: &mut [u8], nodes_at: usize, pre: &[u8], map: Option<&[u32]>) -> Result<(u32, u32), BuildError> {
    let node_count = wide_size(tree);
    let end = nodes_at.saturating_add(node_count as usize * NODE_SIZE);
    let got = dst.len() as u64;
    if end > dst.len() || nodes_at > end {
        return Err(BuildError::DestinationTooSmall { needed: end as u64, got });
    }
    let out = &mut dst[nodes_at..end];
    let pre_area = (!pre.is_empty()).then_some(pre);
    let root_block = match (pre_area, tree.first()) {
        (Some(p), Some(root)) if is_cut(u32::MAX, root.count) => pre_block(root, p.len()).and_then(|r| p.get(r)),
        _ => None,
    };
    let leaf_count = match root_block {
        Some(src) if src.len() == out.len() => copy_block(src, out, 0, map),
        _ if tree.first().is_some_and(|r| r.left_count != 0 && r.count <= EMIT_CUT) => {
            // The root is a cut root whose block is not usable: encode it here.
            let (mut cursor, mut leaves) = (0u32, 0u32);
            let _ = emit_seq(tree, 0, out, 0, &mut cursor, &mut leaves, map);
            leaves
        }
        _ => emit_wide(tree, 0, out, pre_area, map),
    };
    Ok((node_count, leaf_count))
}

/// What the header records of a finished build.
pub struct Summary {
    pub active: usize,
    pub total: usize,
    pub node_count: u32,
    pub leaf_count: u32,
    pub bounds: Aabb,
    /// Unnormalised binary SAH sum of the tree (normalised by the root's area here).
    pub sah_sum: f64,
    pub max_leaf_size: u32,
    /// Where `wide_nodes` wrote the nodes (the section's offset, checked again here).
    pub nodes_at: usize,
}

/// Writes the TLAS sections (instance records and BLAS table; `keys` is scratch for sorting
/// the BLAS addresses), zeroes the gaps between sections and writes the header. Returns the
/// bytes of dst in use.
pub fn finish(desc: &BuildDesc, view: &dyn DeviceView, dst: &mut [u8], refs: &[PrimRef], keys: &mut [u8], sum: &Summary) -> Result<u64, BuildError> {
    let (active, ngeo, is_tlas) = (sum.active, desc.geometries.len() as u64, desc.ty == super::AsType::TopLevel);
    let s = layout::sections(desc.ty, sum.node_count as u64, active as u64, ngeo);
    if s.end > dst.len() as u64 || s.nodes as usize != sum.nodes_at {
        return Err(BuildError::DestinationTooSmall { needed: s.end, got: dst.len() as u64 });
    }
    let used = s.end;
    let dst = &mut dst[..used as usize];
    let mut blas_refs = 0u32;
    if is_tlas {
        let (head, tail) = dst.split_at_mut(s.instances as usize);
        let records = &mut head[s.records as usize..s.records as usize + active * RECORD_SIZE];
        let (inst, table_part) = tail.split_at_mut((s.blas_table - s.instances) as usize);
        let inst = &mut inst[..active * layout::INSTANCE_RECORD_SIZE];
        let table = &mut table_part[..active * 8];
        let keys: &mut [u64] = bytemuck::try_cast_slice_mut(&mut keys[..active * 8]).map_err(|_| BuildError::ScratchTooSmall { needed: layout::build_scratch_size(desc.ty, sum.total as u64), got: 0 })?;
        blas_refs = write_instances(desc, view, &refs[..active], keys, inst, records, table);
    }
    let tlas_only = |n: u64| if is_tlas { n } else { 0 };
    let filled = [
        (s.nodes, s.nodes + sum.node_count as u64 * NODE_SIZE as u64),
        (s.prims, s.prims + if is_tlas { 0 } else { active as u64 * PRIM_SIZE as u64 }),
        (s.records, s.records + active as u64 * RECORD_SIZE as u64),
        (s.geometries, s.geometries + ngeo * layout::GEOMETRY_SIZE as u64),
        (s.instances, s.instances + tlas_only(active as u64 * layout::INSTANCE_RECORD_SIZE as u64)),
        (s.blas_table, s.blas_table + tlas_only(active as u64 * 8)),
    ];
    zero_gaps(dst, &filled, used);
    let raw = header(desc, sum, &s, blas_refs);
    layout::write_header(dst, &raw);
    checksum::seal(dst);
    Ok(used)
}

/// Writes the header of a TLAS whose sections `tlas::write` wrote (`sum.node_count` its
/// node count) and its checksum from the parts' hashes. Returns the bytes of dst in use.
pub fn finish_tlas(desc: &BuildDesc, dst: &mut [u8], sum: &Summary, written: &tlas::Written) -> Result<u64, BuildError> {
    let s = layout::sections(desc.ty, sum.node_count as u64, sum.active as u64, desc.geometries.len() as u64);
    if s.end > dst.len() as u64 || s.nodes as usize != sum.nodes_at {
        return Err(BuildError::DestinationTooSmall { needed: s.end, got: dst.len() as u64 });
    }
    let raw = header(desc, sum, &s, written.blas_refs);
    layout::write_header(dst, &raw);
    checksum::seal_parts(dst, written.parts);
    Ok(s.end)
}

/// The header of a finished build laid out as `s`.
fn header(desc: &BuildDesc, sum: &Summary, s: &layout::Sections, blas_refs: u32) -> RawHeader {
    let (active, ngeo, is_tlas) = (sum.active, desc.geometries.len() as u64, desc.ty == super::AsType::TopLevel);
    let tlas_only = |n: u64| if is_tlas { n } else { 0 };
    let used = s.end;
    let root_area = sum.bounds.half_area() as f64;
    let sah = if active > 0 && root_area > 0.0 && root_area.is_finite() { (sum.sah_sum / root_area) as f32 } else { 0.0 };
    let b = sum.bounds;
    RawHeader {
        magic: layout::MAGIC,
        version: layout::FORMAT_VERSION,
        ty: desc.ty as u32,
        flags: desc.flags.0,
        valid: layout::valid_word(),
        geometry_count: ngeo as u32,
        primitive_count: active as u32,
        instance_count: tlas_only(active as u64) as u32,
        node_count: sum.node_count,
        leaf_count: sum.leaf_count,
        blas_reference_count: blas_refs,
        sah_cost: sah,
        bounds: if active > 0 { [b.lo[0], b.lo[1], b.lo[2], b.hi[0], b.hi[1], b.hi[2]] } else { [0.0; 6] },
        total_primitives: sum.total as u32,
        blas_table_capacity: tlas_only(active as u64) as u32,
        used_size: used,
        nodes_offset: s.nodes,
        prims_offset: s.prims,
        records_offset: s.records,
        geometries_offset: s.geometries,
        instances_offset: s.instances,
        blas_table_offset: s.blas_table,
        max_leaf_size: sum.max_leaf_size,
        reserved: 0,
        checksum: 0,
        spare: 0,
    }
}

/// Zero the padding between sections so dst[..used] is a function of the input only.
fn zero_gaps(dst: &mut [u8], filled: &[(u64, u64)], end: u64) {
    let mut pos = layout::HEADER_SIZE as u64;
    let mut spans: Vec<(u64, u64)> = filled.to_vec(); // ≤ 8 entries: O(1) heap
    spans.sort_unstable();
    for (s, e) in spans.into_iter().chain(std::iter::once((end, end))) {
        if s > pos {
            if let Some(d) = dst.get_mut(pos as usize..s as usize) {
                d.fill(0);
            }
        }
        pos = pos.max(e);
    }
}

//! Primitive data and records in leaf order (BLAS): gathered from the staging area ingest
//! filled (`gather_leaf_data`, `gather_clusters`), or read from the input again when nothing
//! was staged (`write_leaf_data`). Clustered builds map leaves from references to primitives
//! through a prefix of primitives per reference (`cluster_prefix`).
//!
//! Owns: the prims and records sections. Must not touch: nodes, the tree's shape.
use crate::accel::geometry::PrimRef;
use crate::accel::input::{read_aabb, read_triangle};
use crate::accel::layout::{PrimRecord, PRIM_SIZE, RECORD_SIZE, STAGE_SIZE};
use crate::accel::params::{LEAF_DATA_CHUNK, MAX_CLUSTER, PREFETCH_AHEAD, PREFIX_CHUNK};
use crate::accel::primitive::geometry_of;
use crate::accel::{BuildDesc, GeometryData};
use rayon::prelude::*;

/// Prefetches the stage record of global ID `id` (both of its cache lines when it straddles).
#[inline(always)]
fn prefetch_stage(stage: &[u8], id: u32) {
    let o = id as usize * STAGE_SIZE;
    arbor_prefetch::read(stage, o);
    arbor_prefetch::read(stage, o + STAGE_SIZE - 1);
}

/// Leaf-order primitive data and records from the staging area; restores `PrimRef::prim` to
/// the index within the geometry.
pub fn gather_leaf_data(refs: &mut [PrimRef], stage: &[u8], prims: &mut [u8], records: &mut [u8]) {
    prims
        .par_chunks_mut(LEAF_DATA_CHUNK * PRIM_SIZE)
        .zip(records.par_chunks_mut(LEAF_DATA_CHUNK * RECORD_SIZE))
        .zip(refs.par_chunks_mut(LEAF_DATA_CHUNK))
        .for_each(|((pd, rd), rs)| {
            for r in rs.iter().take(PREFETCH_AHEAD) {
                prefetch_stage(stage, r.prim);
            }
            // Fixed-size chunks and arrays: no per-byte bounds checks or variable-length copies.
            for (k, (d, rec)) in pd.chunks_exact_mut(PRIM_SIZE).zip(rd.chunks_exact_mut(RECORD_SIZE)).enumerate() {
                if let Some(next) = rs.get(k + PREFETCH_AHEAD) {
                    prefetch_stage(stage, next.prim);
                }
                let Some(r) = rs.get_mut(k) else { break };
                let o = r.prim as usize * STAGE_SIZE;
                let Some((st, _)) = stage.get(o..).and_then(|x| x.split_first_chunk::<STAGE_SIZE>()) else { continue };
                let (data, tail) = st.split_at(PRIM_SIZE);
                d.copy_from_slice(data);
                let prim = u32::from_le_bytes([tail[0], tail[1], tail[2], tail[3]]);
                r.prim = prim;
                rec[..4].copy_from_slice(&r.geom.to_le_bytes());
                rec[4..].copy_from_slice(&prim.to_le_bytes());
            }
        });
}

/// Writes primitive data and records (BLAS) for stored slots in parallel; slot order = leaf order.
pub fn write_leaf_data(desc: &BuildDesc, refs: &[PrimRef], prims: &mut [u8], records: &mut [u8]) {
    prims
        .par_chunks_mut(LEAF_DATA_CHUNK * PRIM_SIZE)
        .zip(records.par_chunks_mut(LEAF_DATA_CHUNK * RECORD_SIZE))
        .zip(refs.par_chunks(LEAF_DATA_CHUNK))
        .for_each(|((pd, rd), rs)| {
            for (k, r) in rs.iter().enumerate() {
                let mut data = [0f32; 9];
                if let Some(g) = desc.geometries.get(r.geom as usize) {
                    match g.data {
                        GeometryData::Triangles { .. } => {
                            if let Ok(Some(v)) = read_triangle(r.geom, g, r.prim) {
                                data = [v[0].x, v[0].y, v[0].z, v[1].x, v[1].y, v[1].z, v[2].x, v[2].y, v[2].z];
                            }
                        }
                        GeometryData::Aabbs { .. } => {
                            if let Ok(Some(b)) = read_aabb(r.geom, g, r.prim) {
                                data[..6].copy_from_slice(&b);
                            }
                        }
                        GeometryData::Instances { .. } => {}
                    }
                }
                if let Some(d) = pd.get_mut(k * PRIM_SIZE..(k + 1) * PRIM_SIZE) {
                    d.copy_from_slice(bytemuck::bytes_of(&data));
                }
                let rec = PrimRecord { geometry: r.geom, primitive: r.prim };
                if let Some(d) = rd.get_mut(k * RECORD_SIZE..(k + 1) * RECORD_SIZE) {
                    d.copy_from_slice(bytemuck::bytes_of(&rec));
                }
            }
        });
}


/// `p[i]` = primitives before reference i of `refs` (leaf order); `p[refs.len()]` = all of them.
/// `p` must hold refs.len() + 1 entries.
pub fn cluster_prefix(refs: &[PrimRef], p: &mut [u32]) {
    let n = refs.len();
    let Some((last, p)) = p.get_mut(..=n).and_then(|p| p.split_last_mut()) else { return };
    // Local exclusive prefixes per chunk (at most 256 chunks), then each chunk's offset added.
    let mut totals = [0u32; 256];
    let chunk = n.div_ceil(256).max(PREFIX_CHUNK);
    p.par_chunks_mut(chunk).zip(refs.par_chunks(chunk)).zip(totals.par_iter_mut()).for_each(|((pc, rc), t)| {
        let mut s = 0u32;
        for (d, r) in pc.iter_mut().zip(rc) {
            *d = s;
            s += r.cluster_size();
        }
        *t = s;
    });
    let mut offs = [0u32; 256];
    let mut run = 0u32;
    for (o, t) in offs.iter_mut().zip(&totals) {
        *o = run;
        run += t;
    }
    p.par_chunks_mut(chunk).zip(offs.par_iter()).for_each(|(pc, &o)| {
        for d in pc {
            *d += o;
        }
    });
    *last = run;
}

/// Leaf-order primitive data and records for cluster references: reference i's primitives go
/// to positions p[i] (and p[i] + 1) of `prims` / `records`, read from the staging area at their
/// global IDs; `firsts` maps IDs to geometries. Two passes: the IDs into the records in leaf
/// order (split at the prefix, in parallel), then one independent read of the stage per
/// record, in order, with the stage records of the IDs PREFETCH_AHEAD records on prefetched
/// (the reads follow leaf order, which no hardware prefetcher can guess; reading by pairs took
/// twice as long).
pub fn gather_clusters(refs: &[PrimRef], p: &[u32], stage: &[u8], prims: &mut [u8], records: &mut [u8], firsts: &[u32]) {
    ids_in_leaf_order(refs, p, records);
    prims.par_chunks_mut(LEAF_DATA_CHUNK * PRIM_SIZE).zip(records.par_chunks_mut(LEAF_DATA_CHUNK * RECORD_SIZE)).for_each(|(pd, rd)| {
        let id_at = |rd: &[u8], k: usize| rd.get(k * RECORD_SIZE..k * RECORD_SIZE + 4).map(|a| u32::from_le_bytes([a[0], a[1], a[2], a[3]]));
        for k in 0..PREFETCH_AHEAD {
            if let Some(id) = id_at(rd, k) {
                prefetch_stage(stage, id);
            }
        }
        for k in 0..rd.len() / RECORD_SIZE {
            if let Some(id) = id_at(rd, k + PREFETCH_AHEAD) {
                prefetch_stage(stage, id);
            }
            let (Some(d), Some(rec)) = (pd.get_mut(k * PRIM_SIZE..(k + 1) * PRIM_SIZE), rd.get_mut(k * RECORD_SIZE..(k + 1) * RECORD_SIZE)) else { break };
            let id = u32::from_le_bytes([rec[0], rec[1], rec[2], rec[3]]);
            let o = id as usize * STAGE_SIZE;
            let Some((st, _)) = stage.get(o..).and_then(|x| x.split_first_chunk::<STAGE_SIZE>()) else { continue };
            let (data, tail) = st.split_at(PRIM_SIZE);
            d.copy_from_slice(data);
            rec[..4].copy_from_slice(&geometry_of(id, firsts).to_le_bytes());
            rec[4..].copy_from_slice(&tail[..4]);
        }
    });
}

/// Writes each primitive's global ID into the first word of its record slot (leaf order).
/// Nothing outside `records` is written (each split half gets exactly its own slots).
fn ids_in_leaf_order(refs: &[PrimRef], p: &[u32], records: &mut [u8]) {
    if refs.len() > PREFIX_CHUNK && p.len() > refs.len() {
        let mid = refs.len() / 2;
        let cut = p[mid].saturating_sub(p[0]) as usize * RECORD_SIZE;
        let (ra, rb) = records.split_at_mut(cut.min(records.len()));
        rayon::join(|| ids_in_leaf_order(&refs[..mid], &p[..=mid], ra), || ids_in_leaf_order(&refs[mid..], &p[mid..], rb));
        return;
    }
    // Each reference writes MAX_CLUSTER IDs from its first slot on, without a branch on its
    // size; the next reference overwrites the ones past its own (a loop of the reference's
    // own length mispredicted on every cluster).
    let mut pos = 0usize;
    for r in refs {
        for k in 0..MAX_CLUSTER as usize {
            if let Some(rec) = records.get_mut((pos + k) * RECORD_SIZE..).and_then(|x| x.first_chunk_mut::<4>()) {
                *rec = r.prim.wrapping_add(k as u32).to_le_bytes();
            }
        }
        pos += r.geom.min(MAX_CLUSTER) as usize;
    }
}


//! Ingest: the caller's geometry → primitive references in scratch (slot = global primitive
//! ID), in parallel chunks. Each chunk keeps its references as a prefix of its slots
//! (inactive and degenerate primitives squeezed out, or neighbours clustered while the chunk
//! is in cache); with staging the stored primitive data goes to the staging area (scratch) at
//! the global ID; each geometry's record goes to the geometry table. Then, unless the planned top
//! takes the chunks as they are, the prefixes are compacted (`compact_chunks`).
//!
//! Owns: references, the staging area, the geometry table. Must not touch: nodes.
use super::cluster::cluster_in_place;
use crate::accel::geometry::{instance_bounds_of, to_aabb, Aabb, BlasBoundsMemo, PrimRef, DROPPED};
use crate::accel::input::read_instance;
use crate::accel::layout::{self, STAGE_SIZE};
use crate::accel::params::{INGEST_CHUNK, INGEST_CHUNK_INSTANCES, MAX_CLUSTER, PREFETCH_AHEAD};
use crate::accel::primitive::{geometry_record, make_ref_data, FastTris};
use crate::accel::{BuildDesc, BuildError, BuildFlags, DeviceView, Geometry, GeometryData};
use bytemuck::Zeroable;
use glam::{Vec3A, Vec4};
use rayon::prelude::*;

/// Where ingest writes.
pub struct IngestTarget<'a> {
    /// One slot per primitive (global ID order).
    pub refs: &'a mut [PrimRef],
    /// The staging area (STAGE_SIZE bytes per primitive), when the build stages.
    pub stage: Option<&'a mut [u8]>,
    /// The geometry table of dst.
    pub geometry_table: &'a mut [u8],
    /// At least one entry per ingest chunk: each chunk's kept count.
    pub kept: &'a mut [u32],
    /// Compact the kept references to the front of this (the root's node slots) when it holds
    /// them, else of `refs`; None: leave them in their chunks (the planned top scatters them).
    pub compact_into: Option<&'a mut [PrimRef]>,
}

/// Clusters made by ingest: `tau` 0 for none (`BuildParams::cluster_tau`, `max_cluster`).
#[derive(Clone, Copy)]
pub struct Clustering {
    pub tau: f32,
    pub max_cluster: u32,
}

/// What ingest found.
pub struct Ingested {
    /// References kept (clusters count once).
    pub references: usize,
    /// Active primitives.
    pub active: usize,
    pub bounds: Aabb,
    /// The references' centroid box.
    pub centroid_bounds: Aabb,
    /// The references are at the start of `compact_into` (the root's node slots).
    pub in_temp: bool,
}

/// Fills `target.refs` from `desc` (see the module doc); clustering applies to staged builds
/// only. Errors are the lowest (geometry, primitive) position's, whatever the thread count.
pub fn ingest(desc: &BuildDesc, view: &dyn DeviceView, target: IngestTarget<'_>, clustering: Clustering) -> Result<Ingested, BuildError> {
    let IngestTarget { refs, mut stage, geometry_table, kept, compact_into } = target;
    let allow_update = desc.flags.contains(BuildFlags::ALLOW_UPDATE);
    let tau = if stage.is_some() { clustering.tau } else { 0.0 };
    let max_cluster = clustering.max_cluster.clamp(1, MAX_CLUSTER);
    let mut base = 0usize;
    let mut sum = ChunkSum::EMPTY;
    // Every chunk keeps its references as a prefix of its slots; `kept` counts them, chunk by
    // chunk in order, for the compaction below.
    let mut chunks = 0usize;
    for (gi, g) in desc.geometries.iter().enumerate() {
        let count = g.primitive_count as usize;
        let slice = refs.get_mut(base..base + count).ok_or(BuildError::TooManyPrimitives)?;
        let reader = ChunkReader { g, gi: gi as u32, gbase: base, fast: FastTris::of(g), is_instances: matches!(g.data, GeometryData::Instances { .. }), chunk_len: ingest_chunk(g), allow_update, view, tau, max_cluster };
        let chunk_len = reader.chunk_len;
        let nch = count.div_ceil(chunk_len);
        let kept = kept.get_mut(chunks..chunks + nch).ok_or(BuildError::TooManyPrimitives)?;
        chunks += nch;
        // Clustered chunks are read and clustered in a buffer of the task's and only their
        // clusters written to `refs`: the slots they free are never written.
        let buf_len = if tau > 0.0 { chunk_len } else { 0 };
        let work = |ci: usize, chunk: &mut [PrimRef], st: Option<&mut [u8]>, kept: &mut u32, buf: &mut Vec<PrimRef>| {
            let r = match buf.get_mut(..chunk.len()) {
                Some(b) if tau > 0.0 => {
                    let r = reader.fill(ci, b, st);
                    if let Ok(cs) = &r {
                        let w = b.len() - cs.dropped;
                        chunk[..w].copy_from_slice(&b[..w]);
                    }
                    r
                }
                _ => reader.fill(ci, chunk, st),
            };
            if let Ok(cs) = &r {
                *kept = (chunk.len() - cs.dropped) as u32;
            }
            r
        };
        let new_buf = || vec![PrimRef::zeroed(); buf_len];
        let res = match stage.as_deref_mut() {
            Some(st) => {
                let st = st.get_mut(base * STAGE_SIZE..(base + count) * STAGE_SIZE).ok_or(BuildError::TooManyPrimitives)?;
                slice
                    .par_chunks_mut(chunk_len)
                    .zip(st.par_chunks_mut(chunk_len * STAGE_SIZE))
                    .zip(kept.par_iter_mut())
                    .enumerate()
                    .map_init(new_buf, |buf, (ci, ((chunk, st), k))| work(ci, chunk, Some(st), k, buf))
                    .reduce(|| Ok(ChunkSum::EMPTY), first_err)
            }
            None => slice.par_chunks_mut(chunk_len).zip(kept.par_iter_mut()).enumerate().map_init(new_buf, |buf, (ci, (chunk, k))| work(ci, chunk, None, k, buf)).reduce(|| Ok(ChunkSum::EMPTY), first_err),
        };
        let res = res.map_err(|e| e.1)?;
        let rec = geometry_record(g, (count - res.lost) as u32, allow_update);
        if let Some(d) = geometry_table.get_mut(gi * layout::GEOMETRY_SIZE..(gi + 1) * layout::GEOMETRY_SIZE) {
            d.copy_from_slice(bytemuck::bytes_of(&rec));
        }
        sum = sum.join(&res);
        base += count;
    }
    let (bounds, centroid_bounds) = (to_aabb(sum.lo, sum.hi), to_aabb(sum.clo, sum.chi));
    let (dropped_total, active) = (sum.dropped, base - sum.lost);
    let mut out = Ingested { references: base - dropped_total, active, bounds, centroid_bounds, in_temp: false };
    if let Some(temp) = compact_into.filter(|_| dropped_total > 0) {
        (out.references, out.in_temp) = compact_chunks(desc, refs, temp, kept, base - dropped_total);
    }
    Ok(out)
}

/// Reads the chunks of one geometry.
struct ChunkReader<'g, 'v> {
    g: &'g Geometry<'g>,
    gi: u32,
    /// Global ID of the geometry's first primitive.
    gbase: usize,
    fast: Option<FastTris<'g>>,
    is_instances: bool,
    chunk_len: usize,
    allow_update: bool,
    view: &'v dyn DeviceView,
    tau: f32,
    max_cluster: u32,
}

impl ChunkReader<'_, '_> {
    /// Reads chunk `ci`'s primitives into `chunk` (and their staged records into `st`),
    /// clusters them or squeezes out the dropped ones: the references kept are its prefix.
    fn fill(&self, ci: usize, chunk: &mut [PrimRef], st: Option<&mut [u8]>) -> Result<ChunkSum, (u64, BuildError)> {
        let (g, gi32, gbase, chunk_len, allow_update, view) = (self.g, self.gi, self.gbase, self.chunk_len, self.allow_update, self.view);
        let mut st = st;
        let mut cs = ChunkSum::EMPTY;
        let mut memo = BlasBoundsMemo::new();
        for (k, slot) in chunk.iter_mut().enumerate() {
            let p = (ci * chunk_len + k) as u32;
            if let Some(ft) = self.fast.as_ref() {
                ft.prefetch(p.saturating_add(PREFETCH_AHEAD as u32));
                // Plain f32 triangles: everything stored straight from registers.
                match ft.bounds(p, allow_update) {
                    Some(Some((lo, hi, v))) => {
                        cs.add(lo, hi);
                        let id = if st.is_some() { (gbase + ci * chunk_len + k) as u32 } else { p };
                        let record = st.as_deref_mut().and_then(|st| st.get_mut(k * STAGE_SIZE..)).and_then(|x| x.first_chunk_mut::<STAGE_SIZE>());
                        store_triangle(slot, record, (gi32, id, p), (lo, hi), v);
                        continue;
                    }
                    Some(None) => {
                        *slot = PrimRef { lo: [0.0; 3], geom: DROPPED, hi: [0.0; 3], prim: p };
                        cs.dropped += 1;
                        cs.lost += 1;
                        continue;
                    }
                    None => {}
                }
            }
            let r = if self.is_instances {
                // Instances: the BLAS lookup (a locked map in the driver's view) and its header
                // parse are memoised for the last four references (a TLAS usually instances
                // few BLASes). Same bounds as `make_ref_data`.
                match read_instance(gi32, g, p, view) {
                    Ok(Some(inst)) => {
                        let (lo, hi) = instance_bounds_of(&inst.transform, memo.get(inst.reference, view));
                        Ok(Some((PrimRef { lo, geom: gi32, hi, prim: p }, [0f32; 9])))
                    }
                    Ok(None) => Ok(None),
                    Err(e) => Err(e),
                }
            } else {
                make_ref_data(gi32, g, p, view, allow_update)
            };
            match r {
                Ok(Some((mut r, data))) => {
                    cs.add(Vec3A::from(r.lo), Vec3A::from(r.hi));
                    if let Some(st) = st.as_deref_mut() {
                        if let Some(d) = st.get_mut(k * STAGE_SIZE..(k + 1) * STAGE_SIZE) {
                            d[..36].copy_from_slice(bytemuck::bytes_of(&data));
                            d[36..].copy_from_slice(&p.to_le_bytes());
                        }
                        r.prim = (gbase + ci * chunk_len + k) as u32;
                    }
                    *slot = r
                }
                Ok(None) => {
                    *slot = PrimRef { lo: [0.0; 3], geom: DROPPED, hi: [0.0; 3], prim: p };
                    cs.dropped += 1;
                    cs.lost += 1;
                }
                Err(e) => return Err(((gi32 as u64) << 32 | p as u64, e)),
            }
        }
        if self.tau > 0.0 {
            let (w, clo, chi) = cluster_in_place(chunk, self.tau, self.max_cluster, DROPPED);
            (cs.dropped, cs.clo, cs.chi) = (chunk.len() - w, clo, chi);
        } else if cs.dropped > 0 {
            // Stable, in the chunk while it is in cache.
            let mut w = 0;
            for i in 0..chunk.len() {
                if chunk[i].geom != DROPPED {
                    chunk[w] = chunk[i];
                    w += 1;
                }
            }
        }
        Ok(cs)
    }
}

/// Stores a plain f32 triangle straight from registers: its reference (box, geometry `ids.0`,
/// `prim` = `ids.1`) and, when staged, its record (the nine vertex floats and its index
/// `ids.2` in the geometry).
#[inline(always)]
fn store_triangle(slot: &mut PrimRef, record: Option<&mut [u8; STAGE_SIZE]>, ids: (u32, u32, u32), (lo, hi): (Vec3A, Vec3A), [a, b, c]: [Vec3A; 3]) {
    let f: &mut [[f32; 4]; 2] = bytemuck::cast_mut(slot);
    f[0] = Vec4::from((lo, f32::from_bits(ids.0))).to_array();
    f[1] = Vec4::from((hi, f32::from_bits(ids.1))).to_array();
    if let Some(d) = record {
        // Overlapping 16-byte stores of the three vertices (9 floats), then the primitive
        // index over c's fourth lane.
        let v = |x: Vec3A| bytemuck::cast::<[f32; 4], [u8; 16]>(Vec4::from((x, 0.0)).to_array());
        d[0..16].copy_from_slice(&v(a));
        d[12..28].copy_from_slice(&v(b));
        d[24..40].copy_from_slice(&v(c));
        d[36..40].copy_from_slice(&ids.2.to_le_bytes());
    }
}

/// Deterministic first error: the one with the lowest (geometry, chunk) position wins.
/// Also sums the dropped counts of successful chunks.
fn first_err(a: Result<ChunkSum, (u64, BuildError)>, b: Result<ChunkSum, (u64, BuildError)>) -> Result<ChunkSum, (u64, BuildError)> {
    match (a, b) {
        (Err(x), Err(y)) => Err(if x.0 <= y.0 { x } else { y }),
        (Err(x), _) | (_, Err(x)) => Err(x),
        (Ok(x), Ok(y)) => Ok(x.join(&y)),
    }
}

/// What ingest reports per chunk: references dropped, and the box and centroid box of those
/// kept, so that the root's boxes need no second pass over the references (the same
/// arithmetic as a pass over the references would use; min/max do not depend on order).
#[derive(Clone, Copy)]
struct ChunkSum {
    /// Reference slots freed (dropped primitives, and the later members of clusters).
    dropped: usize,
    /// Primitives dropped.
    lost: usize,
    lo: Vec3A,
    hi: Vec3A,
    clo: Vec3A,
    chi: Vec3A,
}
impl ChunkSum {
    const EMPTY: ChunkSum = ChunkSum { dropped: 0, lost: 0, lo: Vec3A::INFINITY, hi: Vec3A::NEG_INFINITY, clo: Vec3A::INFINITY, chi: Vec3A::NEG_INFINITY };
    #[inline(always)]
    fn add(&mut self, lo: Vec3A, hi: Vec3A) {
        let c = lo * 0.5 + hi * 0.5;
        self.lo = self.lo.min(lo);
        self.hi = self.hi.max(hi);
        self.clo = self.clo.min(c);
        self.chi = self.chi.max(c);
    }
    fn join(&self, o: &ChunkSum) -> ChunkSum {
        ChunkSum { dropped: self.dropped + o.dropped, lost: self.lost + o.lost, lo: self.lo.min(o.lo), hi: self.hi.max(o.hi), clo: self.clo.min(o.clo), chi: self.chi.max(o.chi) }
    }
}

/// The ingest chunk of geometry `g`'s primitives: an instance costs far more than a triangle
/// (record decode, BLAS bounds, eight transformed corners), so instances go in smaller chunks
/// (a 10,000-instance TLAS is then more than three tasks).
pub fn ingest_chunk(g: &Geometry) -> usize {
    if matches!(g.data, GeometryData::Instances { .. }) { INGEST_CHUNK_INSTANCES } else { INGEST_CHUNK }
}

/// Stable compaction of ingest's chunks (each keeps the prefix `kept[c]` of its slots; the
/// counts are consumed): each chunk's prefix is copied to its range of `temp` (in parallel,
/// geometry by geometry, from a prefix sum of the chunks' counts), where the root finds them
/// (`in_nodes`: the root's first partition moves them back, which saves a copy of every
/// reference). Without a large enough `temp`, sequentially in place in `refs`. Returns the
/// references kept and whether they are in `temp`.
pub fn compact_chunks(desc: &BuildDesc, refs: &mut [PrimRef], temp: &mut [PrimRef], kept: &mut [u32], kept_total: usize) -> (usize, bool) {
    let in_temp = temp.len() >= kept_total;
    let (mut w, mut first, mut src_base) = (0usize, 0usize, 0usize);
    for g in desc.geometries {
        let count = g.primitive_count as usize;
        let chunk_len = ingest_chunk(g);
        let nch = count.div_ceil(chunk_len);
        let Some(counts) = kept.get_mut(first..first + nch) else { break };
        first += nch;
        // Exclusive prefix sum in place: chunk ci's references go to [counts[ci], counts[ci + 1]).
        let mut acc = 0usize;
        for c in counts.iter_mut() {
            let k = *c as usize;
            *c = acc as u32;
            acc += k;
        }
        if in_temp {
            if let (Some(src), Some(dst)) = (refs.get(src_base..src_base + count), temp.get_mut(w..w + acc)) {
                copy_prefixes(src, chunk_len, counts, 0, acc, dst);
            }
        } else {
            for ci in 0..nch {
                let lo = counts[ci] as usize;
                let hi = counts.get(ci + 1).map_or(acc, |&x| x as usize);
                let s = src_base + ci * chunk_len;
                refs.copy_within(s..s + (hi - lo), w + lo);
            }
        }
        w += acc;
        src_base += count;
    }
    (if in_temp { kept_total } else { w }, in_temp)
}

/// Copies the kept prefix of each `chunk_len`-slot chunk of `src` (chunk ci keeps
/// `offs[ci + 1] - offs[ci]` references, the last `hi - offs[last]`) to `dst`, which holds
/// destination positions `lo..hi`: halves in parallel, no heap.
pub fn copy_prefixes(src: &[PrimRef], chunk_len: usize, offs: &[u32], lo: usize, hi: usize, dst: &mut [PrimRef]) {
    const LEAF: usize = 16;
    if offs.len() > LEAF {
        let mid = offs.len() / 2;
        let cut = (offs[mid] as usize).max(lo).min(hi.max(lo));
        let (da, db) = dst.split_at_mut((cut - lo).min(dst.len()));
        let (sa, sb) = src.split_at((mid * chunk_len).min(src.len()));
        rayon::join(|| copy_prefixes(sa, chunk_len, &offs[..mid], lo, cut, da), || copy_prefixes(sb, chunk_len, &offs[mid..], cut, hi, db));
        return;
    }
    for (ci, &o) in offs.iter().enumerate() {
        let (a, b) = (o as usize, offs.get(ci + 1).map_or(hi, |&x| x as usize));
        let (Some(from), Some(to)) = (src.get(ci * chunk_len..ci * chunk_len + b.saturating_sub(a)), dst.get_mut(a.saturating_sub(lo)..b.saturating_sub(lo))) else { continue };
        if from.len() == to.len() {
            to.copy_from_slice(from);
        }
    }
}

//! Primitive pairing for all three tiers: neighbours in input order (global IDs that follow
//! each other) whose union is tight become one reference of up to four (fast-build) or three
//! (default, fast-trace) primitives, and the binned builder runs over these clusters
//! ("pairs" below; dragon fast-build: about 590,000 references instead of 871,306, the same
//! SAH). Ingest pairs each chunk while it is in cache (`pair_in_place`), after a sample of
//! the input said it pays (`worth_pairing`). A pair reference keeps the first primitive's
//! global ID in `PrimRef::prim` and its primitive count in `PrimRef::geom`. A pair
//! always ends in one leaf; leaves name references while building and primitives in the
//! output, through the prefix of primitives per reference in leaf order (`prim_prefix`).
//!
//! Owns: pairing, that prefix, and the leaf-data gather for pairs. Deterministic: pairs never
//! cross an ingest chunk, whose bounds depend on the input only.
use super::builder::{half_area_v, prefetch_stage, ref_hi, ref_lo, PrimRef, PREFETCH_AHEAD, STAGE_SIZE};
use super::layout::{PRIM_SIZE, RECORD_SIZE};
use glam::Vec3A;
use rayon::prelude::*;

/// The most primitives a cluster reference may hold in any tier (consecutive global IDs;
/// `BuildParams::cluster` per tier).
pub const MAX_CLUSTER: u32 = 4;
/// Builds with fewer active primitives are not paired (the bunny, 3,674 triangles, keeps its
/// tree: small builds are dominated by fixed costs).
pub const PAIR_MIN: usize = 8192;
/// Geometries a paired build may have: the geometry of a primitive comes from its global ID
/// through a table of first IDs kept on the stack.
pub const MAX_PAIR_GEOMETRIES: usize = 64;
/// Two neighbours pair when the half area of their union is at most `tau` times the sum of
/// their half areas (`BuildParams::pair_tau`, per tier). Dragon FAST_BUILD (clusters of up to 4,
/// leaves of up to 3, leaf decisions counting primitives), SAH and B/tri: unpaired 53.75, 52.4;
/// 0.9 → 53.14, 54.2; 1.0 → 53.90, 53.8; **1.1 → 54.98, 53.4**. On the 16-core machine, four
/// interleaved rounds at 16 threads, through the API: 0.9 18.3–21.5 ms, 1.0 17.9–19.8 ms (20.0–23.7
/// for `95b33ec`, whose leaf rule counted references). Session 9 took 1.1: one thread on this
/// box, four interleaved rounds (minimum ms), 1.0 99.6–103.0 against 1.1 93.3–96.6 (6 % faster
/// for 2 % SAH; res3 1.124 of the full sweep, the tier's guard is 1.18); 1.1 with leaves of 4
/// clusters 91.7–95.8 at SAH 55.49. The default tier (16 bins on three axes,
/// pairs): 0.7 keeps its SAH (49.11) and is 2–4 % faster on one thread; at 0.6 too few
/// neighbours pass `worth_pairing`. FAST_TRACE (32 bins) did not pair while its top came from
/// per-node samples (0.7: 48.97 against 48.87); with the top planned from the input (`top`) it
/// pairs at 0.7: clusters of up to 2 in leaves of up to 4, dragon SAH 49.00 → 48.92, the BVH4's
/// 28.89 → 28.81, 60.6 → 60.5 B/tri, 16 threads on the 16-core machine (four interleaved
/// rounds, medians) 26.4 / 26.5 / 24.5 / 27.1 → 25.8 / 24.5 / 23.5 / 25.2 ms (the tier takes
/// clusters of 3 in leaves of 3: 48.90 / 28.74); the terrain 34.65 → 34.63; the bunny, the soup
/// and the res3 and res4 dragons do not pair. 0.8 is 11 % faster on the dragon at its old SAH
/// (49.00, BVH4 28.82) but the res4 dragon's goes 30.37 → 30.45. Since session 15 the default
/// tier clusters as FAST_TRACE does (`BuildParams::from_flags`).
pub const FAST_BUILD_TAU: f32 = 1.1;
pub const DEFAULT_TAU: f32 = 0.7;
pub const FAST_TRACE_TAU: f32 = 0.7;

/// Whether references `a` and `b` are worth one leaf entry: the half area of their union is
/// at most `tau` times the sum of theirs.
#[inline(always)]
fn tight(a: &PrimRef, b: &PrimRef, tau: f32) -> bool {
    let (alo, ahi, blo, bhi) = (ref_lo(a), ref_hi(a), ref_lo(b), ref_hi(b));
    half_area_v(alo.min(blo), ahi.max(bhi)) <= tau * (half_area_v(alo, ahi) + half_area_v(blo, bhi))
}

/// Pairs one ingest chunk in place: references in input order, dropped ones marked by
/// `geom == dropped`. A reference takes the next one when both are kept, their global IDs
/// follow, they are `tight`, and the cluster stays within `cluster` primitives with its union
/// within `tau` times the sum of the members' half areas. The neighbour tests of a block run
/// first, independently (the walk's next step depends on them; testing inside it serialised
/// the loads). The pairs replace the chunk's start (pair w is written after the references it
/// reads, all at w or later) and the rest of the chunk is marked dropped. A pair: the union
/// box, `prim` = the first primitive's global ID, `geom` = how many (their IDs follow).
/// Returns how many there are and their centroid box.
pub fn pair_in_place(c: &mut [PrimRef], tau: f32, cluster: u32, dropped: u32) -> (usize, Vec3A, Vec3A) {
    const BLOCK: usize = 256;
    let n = c.len();
    // Each reference's half area once per block (the flags and the walk read it up to four
    // times): the same values `tight` computes, so the same pairs.
    let area_of = |r: &PrimRef| half_area_v(ref_lo(r), ref_hi(r));
    let mut areas = [0f32; BLOCK + 1];
    let mut flags = [false; BLOCK];
    let (mut w, mut i, mut base) = (0usize, 0usize, 0usize);
    let (mut clo, mut chi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    while base < n {
        let end = (base + BLOCK).min(n);
        for (k, a) in (base..(end + 1).min(n)).zip(areas.iter_mut()) {
            *a = area_of(&c[k]);
        }
        // Reference j's area: cached in this block (through `end`), else computed (the walk
        // may run past the block; nothing there is written yet).
        let area = |c: &[PrimRef], areas: &[f32; BLOCK + 1], j: usize| if j >= base && j <= end { areas[(j - base).min(BLOCK)] } else { area_of(&c[j]) };
        let linked = |c: &[PrimRef], areas: &[f32; BLOCK + 1], j: usize| {
            c.get(j + 1).is_some_and(|b| {
                let a = &c[j];
                a.geom != dropped && b.geom != dropped && b.prim == a.prim.wrapping_add(1) && half_area_v(ref_lo(a).min(ref_lo(b)), ref_hi(a).max(ref_hi(b))) <= tau * (area(c, areas, j) + area(c, areas, j + 1))
            })
        };
        for (j, f) in (base..end).zip(flags.iter_mut()) {
            *f = linked(c, &areas, j);
        }
        while i < end {
            let a = c[i];
            if a.geom == dropped {
                i += 1;
                continue;
            }
            let (mut lo, mut hi) = (ref_lo(&a), ref_hi(&a));
            let mut sum = area(c, &areas, i);
            let mut count = 1u32;
            let mut j = i;
            // Flags beyond this block are computed on the fly (nothing there is written yet).
            while count < cluster && if j < end { flags[(j - base) & (BLOCK - 1)] } else { linked(c, &areas, j) } {
                let bsum = sum + area(c, &areas, j + 1);
                let b = &c[j + 1];
                let (blo, bhi) = (ref_lo(b), ref_hi(b));
                let (ulo, uhi) = (lo.min(blo), hi.max(bhi));
                // A pair is exactly the flag's test (`tight`); larger clusters test their union.
                if count > 1 && half_area_v(ulo, uhi) > tau * bsum {
                    break;
                }
                (lo, hi, sum) = (ulo, uhi, bsum);
                count += 1;
                j += 1;
            }
            let ctr = lo * 0.5 + hi * 0.5;
            clo = clo.min(ctr);
            chi = chi.max(ctr);
            if let Some(d) = c.get_mut(w) {
                *d = PrimRef { lo: lo.to_array(), geom: count, hi: hi.to_array(), prim: a.prim };
            }
            w += 1;
            i = j + 1;
        }
        base = end;
    }
    for r in c.iter_mut().skip(w) {
        r.geom = dropped;
    }
    (w, clo, chi)
}

/// Whether pairing is likely to pay for these geometries (`firsts` as for `geometry_of`): at
/// least one in PAIR_WORTH of SAMPLE neighbours, evenly spaced over the global primitive IDs,
/// is `tight` (`boxes(g, p)` gives primitive p of geometry g's box, None for a dropped or
/// unreadable one). A random soup pairs almost nothing and would pay the pass for nothing.
/// The sample is read in parallel (counts, so the same answer for any thread count): through
/// the driver's checked reads a neighbour costs about 0.2 µs on this box, 0.4 ms for the whole
/// sample on one thread, which would otherwise be a serial step in front of every paired build.
pub fn worth_pairing(firsts: &[u32], tau: f32, boxes: impl Fn(u32, u32) -> Option<PrimRef> + Sync) -> bool {
    const SAMPLE: u32 = 1024;
    const PAIR_WORTH: u32 = 8;
    let total = firsts.last().copied().unwrap_or(0);
    let step = (total / SAMPLE).max(1);
    let (tested, hits) = (0..total.saturating_sub(1).div_ceil(step))
        .into_par_iter()
        .with_min_len(64)
        .map(|s| {
            let id = s * step;
            // Neighbours within one geometry.
            let g = geometry_of(id, firsts);
            let first = firsts.get(g as usize).copied().unwrap_or(0);
            if !firsts.get(g as usize + 1).is_some_and(|&end| id + 1 < end) {
                return (0u32, 0u32);
            }
            match (boxes(g, id - first), boxes(g, id - first + 1)) {
                (Some(a), Some(b)) => (1, tight(&a, &b, tau) as u32),
                _ => (1, 0),
            }
        })
        .reduce(|| (0, 0), |x, y| (x.0 + y.0, x.1 + y.1));
    tested > 0 && hits * PAIR_WORTH >= tested
}

/// Primitives of a cluster reference.
#[inline(always)]
pub fn weight(r: &PrimRef) -> u32 {
    r.geom
}

/// `p[i]` = primitives before reference i of `refs` (leaf order); `p[refs.len()]` = all of them.
/// `p` must hold refs.len() + 1 entries.
pub fn prim_prefix(refs: &[PrimRef], p: &mut [u32]) {
    const CH: usize = 1 << 14;
    let n = refs.len();
    let Some((last, p)) = p.get_mut(..=n).and_then(|p| p.split_last_mut()) else { return };
    // Local exclusive prefixes per chunk (at most 256 chunks), then each chunk's offset added.
    let mut totals = [0u32; 256];
    let chunk = n.div_ceil(256).max(CH);
    p.par_chunks_mut(chunk).zip(refs.par_chunks(chunk)).zip(totals.par_iter_mut()).for_each(|((pc, rc), t)| {
        let mut s = 0u32;
        for (d, r) in pc.iter_mut().zip(rc) {
            *d = s;
            s += weight(r);
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

/// The geometry of global primitive ID `id`: `firsts[g]` is geometry g's first ID, `firsts[ngeo]`
/// the total.
#[inline(always)]
pub fn geometry_of(id: u32, firsts: &[u32]) -> u32 {
    if firsts.len() <= 2 {
        return 0;
    }
    (firsts[1..].partition_point(|&f| f <= id)) as u32
}

/// Leaf-order primitive data and records for paired references: reference i's primitives go
/// to positions p[i] (and p[i] + 1) of `prims` / `records`, read from the staging area at their
/// global IDs; `firsts` maps IDs to geometries. Two passes: the IDs into the records in leaf
/// order (split at the prefix, in parallel), then one independent read of the stage per
/// record, in order, with the stage records of the IDs PREFETCH_AHEAD records on prefetched
/// (the reads follow leaf order, which no hardware prefetcher can guess; reading by pairs took
/// twice as long).
pub fn gather_pairs(refs: &[PrimRef], p: &[u32], stage: &[u8], prims: &mut [u8], records: &mut [u8], firsts: &[u32]) {
    ids_in_leaf_order(refs, p, records);
    const CH: usize = 4096;
    prims.par_chunks_mut(CH * PRIM_SIZE).zip(records.par_chunks_mut(CH * RECORD_SIZE)).for_each(|(pd, rd)| {
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
    const CH: usize = 1 << 14;
    if refs.len() > CH && p.len() > refs.len() {
        let mid = refs.len() / 2;
        let cut = p[mid].saturating_sub(p[0]) as usize * RECORD_SIZE;
        let (ra, rb) = records.split_at_mut(cut.min(records.len()));
        rayon::join(|| ids_in_leaf_order(&refs[..mid], &p[..=mid], ra), || ids_in_leaf_order(&refs[mid..], &p[mid..], rb));
        return;
    }
    // Each reference writes MAX_CLUSTER IDs from its first slot on, without a branch on its
    // size; the next reference overwrites the ones past its own. (A loop of the reference's
    // own length mispredicted on every cluster: 2.6 ms of a one-thread dragon build.)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_prefix_and_geometries_account_for_every_primitive() {
        const DROP: u32 = u32::MAX;
        let r = |x: f32, id: u32| PrimRef { lo: [x, 0.0, 0.0], geom: 0, hi: [x + 1.0, 1.0, 1.0], prim: id };
        // Touching unit boxes pair (union 1x2 against two 1x1); far ones stay single; 15 and
        // 17 touch but their IDs do not follow; a dropped reference (18) breaks the 17-19 run.
        let mut c = vec![r(0.0, 10), r(1.0, 11), r(50.0, 12), r(51.0, 13), r(200.0, 14), r(90.0, 15), r(91.0, 17), PrimRef { geom: DROP, ..r(92.0, 18) }, r(93.0, 19)];
        let (m, clo, chi) = pair_in_place(&mut c, FAST_BUILD_TAU, 2, DROP);
        let out = c[..m].to_vec();
        let ids: Vec<(u32, u32)> = out.iter().map(|p| (p.prim, p.geom)).collect();
        assert_eq!(ids, vec![(10, 2), (12, 2), (14, 1), (15, 1), (17, 1), (19, 1)]);
        assert!(c[m..].iter().all(|r| r.geom == DROP));
        assert_eq!((out[0].lo, out[0].hi), ([0.0; 3], [2.0, 1.0, 1.0]));
        assert_eq!((clo.to_array(), chi.to_array()), ([1.0, 0.5, 0.5], [200.5, 0.5, 0.5]));
        // The sampled test: every neighbour of a touching row is tight, none of a spread one.
        let row = |gap: f32| move |_g: u32, p: u32| Some(r(p as f32 * gap, p));
        assert!(worth_pairing(&[0, 5000, 9000], FAST_BUILD_TAU, row(1.0)));
        assert!(!worth_pairing(&[0, 9000], FAST_BUILD_TAU, row(3.0)));
        assert!(!worth_pairing(&[0, 9000], FAST_BUILD_TAU, |_, _| None));
        let mut p = vec![0u32; m + 1];
        prim_prefix(&out, &mut p);
        assert_eq!(p, vec![0, 2, 4, 5, 6, 7, 8]);
        assert_eq!(geometry_of(7, &[0, 5, 9, 20]), 1);
        assert_eq!(geometry_of(9, &[0, 5, 9, 20]), 2);
        assert_eq!(geometry_of(0, &[0, 5, 9, 20]), 0);
        assert_eq!(geometry_of(19, &[0, 20]), 0);
        // An empty geometry (1) owns no ID: 5 is geometry 2's first.
        assert_eq!(geometry_of(5, &[0, 5, 5, 9]), 2);
        assert_eq!(geometry_of(4, &[0, 5, 5, 9]), 0);
        // Clusters of up to four: a row of touching unit boxes groups by fours while the union
        // stays within tau times the members' sum (half areas 2x1x1: 5 against 2 x 3; 3x1x1: 7
        // against 3 x 3; 4x1x1: 9 against 4 x 3).
        let mut row: Vec<PrimRef> = (0..10).map(|i| r(i as f32, 100 + i)).collect();
        let (m, ..) = pair_in_place(&mut row, FAST_BUILD_TAU, 4, DROP);
        let ids: Vec<(u32, u32)> = row[..m].iter().map(|p| (p.prim, p.geom)).collect();
        assert_eq!(ids, vec![(100, 4), (104, 4), (108, 2)]);
    }
}

//! Primitive pairing for the fast-build and default tiers: after ingest, neighbours in input order (global
//! IDs that follow each other) whose union is tight become one two-primitive reference, and the
//! binned builder runs over the pairs (dragon: about 658,700 references instead of 871,306, the
//! same SAH). A pair reference keeps the first primitive's global ID in `PrimRef::prim` and its
//! primitive count (1 or 2) in `PrimRef::geom`. A pair always ends in one leaf; leaves name
//! references while building and primitives in the output, through the prefix of primitives
//! per reference in leaf order (`prim_prefix`).
//!
//! Owns: pairing, that prefix, and the leaf-data gather for pairs. Deterministic: fixed
//! chunks (pairs never cross one), independent of the thread count.
use super::builder::{half_area_v, ref_hi, ref_lo, Aabb, PrimRef, STAGE_SIZE};
use super::layout::{PRIM_SIZE, RECORD_SIZE};
use glam::Vec3A;
use rayon::prelude::*;

/// Primitives a cluster reference may hold (consecutive global IDs). Four: dragon SAH 52.78
/// with leaves of up to two clusters but a 49 % larger tree (57.0 B/tri), 54.13 with up to
/// four (more than 8 primitives per leaf), and not measurably faster than pairs on this box.
pub const MAX_CLUSTER: u32 = 2;
/// Builds with fewer active primitives are not paired (the bunny, 3,674 triangles, keeps its
/// tree: small builds are dominated by fixed costs).
pub const PAIR_MIN: usize = 8192;
/// Geometries a paired build may have: the geometry of a primitive comes from its global ID
/// through a table of first IDs kept on the stack.
pub const MAX_PAIR_GEOMETRIES: usize = 64;
/// Two neighbours pair when the half area of their union is at most `tau` times the sum of
/// their half areas (`BuildParams::pair_tau`, per tier). Dragon FAST_BUILD, one thread, this
/// repository's 2-vCPU box (build minimum; SAH; references): unpaired 117 ms, 53.75, 871,306;
/// 0.8 → 114.0 ms, 53.15, 698,306; 0.9 → 111.6 ms, 53.74, 658,694; 1.0 → 108.3 ms, 54.35,
/// 634,116; 1.1 → 105.9 ms, 55.02, 604,375: 0.9 keeps the tier's SAH. The default tier (16
/// bins on three axes): unpaired 197–198 ms, 49.11; 0.6 pairs too few to pass
/// `worth_pairing`; 0.7 → 185.4–185.7 ms, 49.19, 59.4 B/tri (60.6); 0.8 → 174–177 ms, 49.40.
/// FAST_TRACE loses 0.3 % at 0.7 (48.97, over its 48.9) and does not pair.
pub const FAST_BUILD_TAU: f32 = 0.9;
pub const DEFAULT_TAU: f32 = 0.7;
/// Pairing runs in at most this many fixed chunks of the input order, of at least
/// PAIR_CHUNK_MIN references (pairs never cross a chunk).
const PAIR_CHUNKS: usize = 64;
const PAIR_CHUNK_MIN: usize = 4096;
/// Whether references `a` and `b` are worth one leaf entry: the half area of their union is
/// at most `tau` times the sum of theirs.
#[inline(always)]
fn tight(a: &PrimRef, b: &PrimRef, tau: f32) -> bool {
    let (alo, ahi, blo, bhi) = (ref_lo(a), ref_hi(a), ref_lo(b), ref_hi(b));
    half_area_v(alo.min(blo), ahi.max(bhi)) <= tau * (half_area_v(alo, ahi) + half_area_v(blo, bhi))
}

/// Clusters one chunk `src` into `dst`: greedily, a cluster takes the next reference while
/// it is `tight` with the last one, its global ID follows, the cluster has fewer than
/// MAX_CLUSTER primitives and the union stays within `tau` times the sum of the members'
/// half areas. The neighbour tests of a block run first, independently. A cluster: the union
/// box, `prim` = the first primitive's global ID, `geom` = how many (their IDs follow).
/// Returns how many were written.
fn pair_chunk(src: &[PrimRef], dst: &mut [PrimRef], tau: f32) -> usize {
    const BLOCK: usize = 256;
    let n = src.len();
    let mut flags = [false; BLOCK];
    let (mut w, mut i, mut base) = (0usize, 0usize, 0usize);
    while base < n {
        let end = (base + BLOCK).min(n);
        for (j, f) in (base..end).zip(flags.iter_mut()) {
            *f = src.get(j + 1).is_some_and(|b| b.prim == src[j].prim.wrapping_add(1) && tight(&src[j], b, tau));
        }
        while i < end {
            let a = &src[i];
            let (mut lo, mut hi) = (ref_lo(a), ref_hi(a));
            let mut sum = half_area_v(lo, hi);
            let mut count = 1u32;
            let mut j = i;
            while count < MAX_CLUSTER && j + 1 < n {
                // Flags beyond this block are computed on the fly.
                let linked = if j < end { flags[(j - base) & (BLOCK - 1)] } else { src[j + 1].prim == src[j].prim.wrapping_add(1) && tight(&src[j], &src[j + 1], tau) };
                if !linked {
                    break;
                }
                let b = &src[j + 1];
                let (blo, bhi) = (ref_lo(b), ref_hi(b));
                let (ulo, uhi) = (lo.min(blo), hi.max(bhi));
                let bsum = sum + half_area_v(blo, bhi);
                if half_area_v(ulo, uhi) > tau * bsum {
                    break;
                }
                (lo, hi, sum) = (ulo, uhi, bsum);
                count += 1;
                j += 1;
            }
            if let Some(d) = dst.get_mut(w) {
                *d = PrimRef { lo: lo.to_array(), geom: count, hi: hi.to_array(), prim: a.prim };
            }
            w += 1;
            i = j + 1;
        }
        base = end;
    }
    w
}

/// Whether pairing `refs` is likely to pay: at least one in PAIR_WORTH of SAMPLE evenly spaced
/// neighbours is `tight` (a random soup pairs almost nothing, and would pay the passes for
/// nothing).
pub fn worth_pairing(refs: &[PrimRef], tau: f32) -> bool {
    const SAMPLE: usize = 1024;
    const PAIR_WORTH: usize = 8;
    let n = refs.len();
    if n < 2 {
        return false;
    }
    let step = (n / SAMPLE).max(1);
    let (mut tested, mut hits) = (0usize, 0usize);
    let mut i = 0;
    while i + 1 < n {
        tested += 1;
        hits += tight(&refs[i], &refs[i + 1], tau) as usize;
        i += step;
    }
    hits * PAIR_WORTH >= tested
}

/// Pairs `refs` (input order) in fixed chunks (pairs never cross one), each chunk's pairs
/// written at the start of its own range of `staged`. Returns the pair count and the count
/// per chunk (`place_pairs` moves them into place).
pub fn pair_refs(refs: &[PrimRef], staged: &mut [PrimRef], tau: f32) -> (usize, [usize; PAIR_CHUNKS]) {
    let chunk = refs.len().div_ceil(PAIR_CHUNKS).max(PAIR_CHUNK_MIN);
    let mut counts = [0usize; PAIR_CHUNKS];
    staged.par_chunks_mut(chunk).zip(refs.par_chunks(chunk)).zip(counts.par_iter_mut()).for_each(|((s, r), c)| *c = pair_chunk(r, s, tau));
    (counts.iter().sum(), counts)
}

/// Moves the staged pairs of each chunk (`pair_refs`) to their place in `out`, in order;
/// returns the pairs' centroid box.
pub fn place_pairs(staged: &[PrimRef], counts: &[usize; PAIR_CHUNKS], out: &mut [PrimRef]) -> Aabb {
    let n = staged.len();
    let chunk = n.div_ceil(PAIR_CHUNKS).max(PAIR_CHUNK_MIN);
    let mut outs: [&mut [PrimRef]; PAIR_CHUNKS] = std::array::from_fn(|_| &mut [][..]);
    let mut rest = out;
    for (o, &k) in outs.iter_mut().zip(counts) {
        let cut = k.min(rest.len());
        let (mine, r) = std::mem::take(&mut rest).split_at_mut(cut);
        *o = mine;
        rest = r;
    }
    let (clo, chi) = staged
        .par_chunks(chunk)
        .zip(outs.par_iter_mut())
        .map(|(s, o)| {
            let len = o.len().min(s.len());
            o[..len].copy_from_slice(&s[..len]);
            let (mut clo, mut chi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
            for r in o.iter() {
                let c = ref_lo(r) * 0.5 + ref_hi(r) * 0.5;
                clo = clo.min(c);
                chi = chi.max(c);
            }
            (clo, chi)
        })
        .reduce(|| (Vec3A::INFINITY, Vec3A::NEG_INFINITY), |a, b| (a.0.min(b.0), a.1.max(b.1)));
    Aabb { lo: clo.to_array(), hi: chi.to_array() }
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
/// record, in order (a loop without data-dependent branches keeps many of these random reads
/// in flight; reading by pairs took twice as long).
pub fn gather_pairs(refs: &[PrimRef], p: &[u32], stage: &[u8], prims: &mut [u8], records: &mut [u8], firsts: &[u32]) {
    ids_in_leaf_order(refs, p, records);
    const CH: usize = 4096;
    prims.par_chunks_mut(CH * PRIM_SIZE).zip(records.par_chunks_mut(CH * RECORD_SIZE)).for_each(|(pd, rd)| {
        for (d, rec) in pd.chunks_exact_mut(PRIM_SIZE).zip(rd.chunks_exact_mut(RECORD_SIZE)) {
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
fn ids_in_leaf_order(refs: &[PrimRef], p: &[u32], records: &mut [u8]) {
    const CH: usize = 1 << 14;
    if refs.len() > CH && p.len() > refs.len() {
        let mid = refs.len() / 2;
        let cut = p[mid].saturating_sub(p[0]) as usize * RECORD_SIZE;
        let (ra, rb) = records.split_at_mut(cut.min(records.len()));
        rayon::join(|| ids_in_leaf_order(&refs[..mid], &p[..=mid], ra), || ids_in_leaf_order(&refs[mid..], &p[mid..], rb));
        return;
    }
    let mut slots = records.chunks_exact_mut(RECORD_SIZE);
    for r in refs {
        for k in 0..r.geom.min(MAX_CLUSTER) {
            if let Some(rec) = slots.next() {
                rec[..4].copy_from_slice(&r.prim.wrapping_add(k).to_le_bytes());
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_prefix_and_geometries_account_for_every_primitive() {
        let r = |x: f32, id: u32| PrimRef { lo: [x, 0.0, 0.0], geom: 0, hi: [x + 1.0, 1.0, 1.0], prim: id };
        // Touching unit boxes pair (union 1x2 against two 1x1); far ones stay single.
        let refs = vec![r(0.0, 10), r(1.0, 11), r(50.0, 12), r(51.0, 13), r(200.0, 14), r(90.0, 15), r(91.0, 17)];
        let mut staged = vec![PrimRef { lo: [0.0; 3], geom: 0, hi: [0.0; 3], prim: 0 }; refs.len()];
        let (m, counts) = pair_refs(&refs, &mut staged, FAST_BUILD_TAU);
        let mut out = vec![PrimRef { lo: [0.0; 3], geom: 0, hi: [0.0; 3], prim: 0 }; m];
        let cb = place_pairs(&staged, &counts, &mut out);
        let ids: Vec<(u32, u32)> = out.iter().map(|p| (p.prim, p.geom)).collect();
        // 15 and 17 touch, but their IDs do not follow: no pair.
        assert_eq!(ids, vec![(10, 2), (12, 2), (14, 1), (15, 1), (17, 1)]);
        assert_eq!((out[0].lo, out[0].hi), ([0.0; 3], [2.0, 1.0, 1.0]));
        assert_eq!((cb.lo, cb.hi), ([1.0, 0.5, 0.5], [200.5, 0.5, 0.5]));
        let mut p = vec![0u32; m + 1];
        prim_prefix(&out, &mut p);
        assert_eq!(p, vec![0, 2, 4, 5, 6, 7]);
        assert_eq!(geometry_of(7, &[0, 5, 9, 20]), 1);
        assert_eq!(geometry_of(9, &[0, 5, 9, 20]), 2);
        assert_eq!(geometry_of(0, &[0, 5, 9, 20]), 0);
        assert_eq!(geometry_of(19, &[0, 20]), 0);
    }
}

//! Clusters of neighbouring primitives, for every tier: neighbours in input order (global IDs
//! that follow each other) whose union is tight become one reference of up to `max_cluster`
//! primitives, and the binned builder runs over these clusters (about two thirds as
//! many references for the same SAH on a scanned mesh). Ingest clusters each chunk while it
//! is in cache (`cluster_in_place`), after a sample of the input said it pays
//! (`worth_clustering`). A cluster reference keeps the first primitive's global ID in
//! `PrimRef::prim` and its primitive count in `PrimRef::geom`; a cluster always ends in one
//! leaf, and leaves name references while building and primitives in the output
//! (`encode::leaves::cluster_prefix`).
//!
//! Owns: forming clusters. Must not touch: the tree, the output. Deterministic: clusters
//! never cross an ingest chunk, whose bounds depend on the input only.
use crate::accel::geometry::{half_area_vec, ref_hi, ref_lo, PrimRef};
use crate::accel::params::{CLUSTER_BLOCK, CLUSTER_SAMPLE, CLUSTER_WORTH};
use crate::accel::primitive::geometry_of;
use glam::Vec3A;
use rayon::prelude::*;

/// Whether references `a` and `b` are worth one leaf entry: the half area of their union is
/// at most `tau` times the sum of theirs.
#[inline(always)]
fn tight(a: &PrimRef, b: &PrimRef, tau: f32) -> bool {
    let (alo, ahi, blo, bhi) = (ref_lo(a), ref_hi(a), ref_lo(b), ref_hi(b));
    half_area_vec(alo.min(blo), ahi.max(bhi)) <= tau * (half_area_vec(alo, ahi) + half_area_vec(blo, bhi))
}

/// Clusters one ingest chunk in place: references in input order, dropped ones marked by
/// `geom == dropped`. A reference takes the next one when both are kept, their global IDs
/// follow, they are `tight`, and the cluster stays within `cluster` primitives with its union
/// within `tau` times the sum of the members' half areas. The neighbour tests of a block run
/// first, independently (the walk's next step depends on them; testing inside it serialised
/// the loads). The clusters replace the chunk's start (cluster w is written after the references it
/// reads, all at w or later) and the rest of the chunk is marked dropped. A cluster: the union
/// box, `prim` = the first primitive's global ID, `geom` = how many (their IDs follow).
/// Returns how many there are and their centroid box.
pub fn cluster_in_place(c: &mut [PrimRef], tau: f32, cluster: u32, dropped: u32) -> (usize, Vec3A, Vec3A) {
    let n = c.len();
    // Each reference's half area once per block (the flags and the walk read it up to four
    // times): the same values `tight` computes, so the same clusters.
    let area_of = |r: &PrimRef| half_area_vec(ref_lo(r), ref_hi(r));
    let mut areas = [0f32; CLUSTER_BLOCK + 1];
    let mut flags = [false; CLUSTER_BLOCK];
    let (mut w, mut i, mut base) = (0usize, 0usize, 0usize);
    let (mut clo, mut chi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    while base < n {
        let end = (base + CLUSTER_BLOCK).min(n);
        for (k, a) in (base..(end + 1).min(n)).zip(areas.iter_mut()) {
            *a = area_of(&c[k]);
        }
        // Reference j's area: cached in this block (through `end`), else computed (the walk
        // may run past the block; nothing there is written yet).
        let area = |c: &[PrimRef], areas: &[f32; CLUSTER_BLOCK + 1], j: usize| if j >= base && j <= end { areas[(j - base).min(CLUSTER_BLOCK)] } else { area_of(&c[j]) };
        let linked = |c: &[PrimRef], areas: &[f32; CLUSTER_BLOCK + 1], j: usize| {
            c.get(j + 1).is_some_and(|b| {
                let a = &c[j];
                a.geom != dropped && b.geom != dropped && b.prim == a.prim.wrapping_add(1) && half_area_vec(ref_lo(a).min(ref_lo(b)), ref_hi(a).max(ref_hi(b))) <= tau * (area(c, areas, j) + area(c, areas, j + 1))
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
            while count < cluster && if j < end { flags[(j - base) & (CLUSTER_BLOCK - 1)] } else { linked(c, &areas, j) } {
                let bsum = sum + area(c, &areas, j + 1);
                let b = &c[j + 1];
                let (blo, bhi) = (ref_lo(b), ref_hi(b));
                let (ulo, uhi) = (lo.min(blo), hi.max(bhi));
                // A pair is exactly the flag's test (`tight`); larger clusters test their union.
                if count > 1 && half_area_vec(ulo, uhi) > tau * bsum {
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

/// Whether clustering is likely to pay for these geometries (`firsts` as for `geometry_of`):
/// at least one in CLUSTER_WORTH of CLUSTER_SAMPLE neighbours, evenly spaced over the global
/// primitive IDs, is `tight` (`boxes(g, p)` gives primitive p of geometry g's box, None for a
/// dropped or unreadable one). A random soup clusters almost nothing and would pay the pass
/// for nothing. The sample is read in parallel (counts, so the same answer for any thread
/// count): through the driver's checked reads it would otherwise be a serial step in front of
/// every clustered build.
pub fn worth_clustering(firsts: &[u32], tau: f32, boxes: impl Fn(u32, u32) -> Option<PrimRef> + Sync) -> bool {
    let total = firsts.last().copied().unwrap_or(0);
    let step = (total / CLUSTER_SAMPLE).max(1);
    let (tested, hits) = (0..total.saturating_sub(1).div_ceil(step))
        .into_par_iter()
        .with_min_len(64)
        .map(|s| {
            let id = s * step;
            // Neighbours within one geometry.
            let g = geometry_of(id, firsts);
            let first = firsts.get(g as usize).copied().unwrap_or(0);
            if firsts.get(g as usize + 1).is_none_or(|&end| id + 1 >= end) {
                return (0u32, 0u32);
            }
            match (boxes(g, id - first), boxes(g, id - first + 1)) {
                (Some(a), Some(b)) => (1, tight(&a, &b, tau) as u32),
                _ => (1, 0),
            }
        })
        .reduce(|| (0, 0), |x, y| (x.0 + y.0, x.1 + y.1));
    tested > 0 && hits * CLUSTER_WORTH >= tested
}

#[cfg(test)]
mod tests;

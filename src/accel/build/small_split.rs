//! The exact split of small nodes (at most MAX_SMALL references): every bipartition for three
//! to five references (`enum_split`), else a SAH sweep over each axis sorted by a branch-free
//! network (`small_sweep`). Deterministic: ties go to the lowest position, axis and mask.
//!
//! Owns: the split choice of small nodes. Must not touch: node slots.
use crate::accel::geometry::{half_area_vec, ref_hi, ref_lo, PrimRef};
use crate::accel::params::MAX_SMALL;
use bytemuck::Zeroable;
use glam::{Vec3A, Vec4};

/// f32 bits mapped so that unsigned integer order is the float order (-0 before +0).
#[inline(always)]
pub fn ordered_bits(f: f32) -> u32 {
    let b = f.to_bits();
    b ^ (((b as i32 >> 31) as u32) | 0x8000_0000)
}

/// A sorting network (compare-exchange pairs) for 8 inputs (19 comparators).
pub const NET8: [(usize, usize); 19] = [(0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7), (0, 1), (2, 3), (4, 5), (6, 7), (2, 4), (3, 5), (1, 4), (3, 6), (1, 2), (3, 4), (5, 6)];

#[inline(always)]
pub fn sort_network(v: &mut [u64; MAX_SMALL], net: &[(usize, usize)]) {
    for &(i, j) in net {
        let (x, y) = (v[i & (MAX_SMALL - 1)], v[j & (MAX_SMALL - 1)]);
        v[i & (MAX_SMALL - 1)] = x.min(y);
        v[j & (MAX_SMALL - 1)] = x.max(y);
    }
}

/// The SAH sweep of `small_split` over one sorted order: the best (left count, cost) among
/// the n-1 split positions, lowest position on ties. `S` (n - 1 or more, at most 7) fixes the
/// step count; positions at and past n-1, and those leaving a side of fewer than `min_w`
/// primitives, get a NaN cost, which never wins.
#[inline(always)]
fn small_sweep<const S: usize>(order: &[u8; MAX_SMALL], lo: &[Vec3A; MAX_SMALL], hi: &[Vec3A; MAX_SMALL], w: &[f32; MAX_SMALL], n: usize, min_w: f32) -> Option<(usize, f32)> {
    let mut l_area = [0f32; S];
    let mut l_w = [0f32; S];
    let (mut l, mut h) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let mut acc = 0f32;
    for i in 0..S {
        let o = order[i] as usize & (MAX_SMALL - 1);
        l = l.min(lo[o]);
        h = h.max(hi[o]);
        l_area[i] = half_area_vec(l, h);
        acc += w[o];
        l_w[i] = acc;
    }
    let (mut l, mut h) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let (mut best_cost, mut best_i) = (f32::INFINITY, usize::MAX);
    let nf = w.iter().sum::<f32>();
    for i in (0..S).rev() {
        let o = order[(i + 1) & (MAX_SMALL - 1)] as usize & (MAX_SMALL - 1);
        l = l.min(lo[o]);
        h = h.max(hi[o]);
        let left = l_w[i];
        let cost = l_area[i] * left + half_area_vec(l, h) * (nf - left);
        let cost = if i + 1 < n && left >= min_w && nf - left >= min_w { cost } else { f32::NAN };
        let take = cost <= best_cost;
        best_cost = if take { cost } else { best_cost };
        best_i = if take { i } else { best_i };
    }
    (best_i != usize::MAX).then_some((best_i + 1, best_cost))
}

/// The best of all bipartitions of `N` references (2^(N-1) - 1 of them), which include every
/// split a sorted sweep on any axis can make. A left side is a nonempty subset of the first N-1
/// references (bit mask `m`, `H` = 2^(N-1) masks); the right side is the rest with the last
/// reference. The boxes of those subsets come from adding one reference to a smaller subset.
/// Reorders `refs` as (left, right), each side in its input order, and returns (left count,
/// A_L·N_L + A_R·N_R), N the sum of `w` (primitives per reference). A side of fewer than
/// `min_w` primitives is no split. Ties go to the lowest mask; None only when every cost is
/// NaN.
#[inline(always)]
fn enum_split<const N: usize, const H: usize>(refs: &mut [PrimRef], w_ref: &[f32; MAX_SMALL], min_w: f32) -> Option<(usize, f32)> {
    if refs.len() != N || H != 1 << (N - 1) {
        return None;
    }
    let mut elo = [Vec3A::ZERO; N];
    let mut ehi = [Vec3A::ZERO; N];
    let mut ew = [0f32; N];
    for i in 0..N {
        elo[i] = ref_lo(&refs[i]);
        ehi[i] = ref_hi(&refs[i]);
        ew[i] = w_ref[i & (MAX_SMALL - 1)];
    }
    let mut lo = [Vec3A::INFINITY; H];
    let mut hi = [Vec3A::NEG_INFINITY; H];
    let mut w = [0f32; H];
    for m in 1..H {
        let i = (m.trailing_zeros() as usize).min(N - 1);
        let p = m & (m - 1);
        lo[m] = lo[p].min(elo[i]);
        hi[m] = hi[p].max(ehi[i]);
        w[m] = w[p] + ew[i];
    }
    let (last_lo, last_hi, last_w) = (elo[N - 1], ehi[N - 1], ew[N - 1]);
    let full = H - 1;
    let (mut best, mut mask) = (f32::INFINITY, 0usize);
    for m in 1..H {
        let r = full ^ m;
        let c = half_area_vec(lo[m], hi[m]) * w[m] + half_area_vec(lo[r].min(last_lo), hi[r].max(last_hi)) * (w[r] + last_w);
        let c = if w[m] >= min_w && w[r] + last_w >= min_w { c } else { f32::NAN };
        // The first cost that is not NaN is taken even when infinite (huge sanitised boxes), as
        // the sweeps do; after it only a lower one.
        let take = c < best || (mask == 0 && c <= best);
        best = if take { c } else { best };
        mask = if take { m } else { mask };
    }
    if mask == 0 {
        return None;
    }
    let mut tmp = [PrimRef::zeroed(); N];
    tmp.copy_from_slice(refs);
    let mut at = 0;
    for side in [true, false] {
        for (i, r) in tmp.iter().enumerate() {
            if (mask >> i & 1 != 0) == side {
                refs[at] = *r;
                at += 1;
            }
        }
    }
    Some((mask.count_ones() as usize, best))
}

/// Best SAH split of <= MAX_SMALL references: reorders `refs` as (left, right) and returns
/// (left count, A_L·N_L + A_R·N_R), N counting primitives when `weighted`. Three to five
/// references (four on one axis) take the best bipartition, more the best sweep over the given
/// axes, sorted by a network with ties by position; either way the result is deterministic.
#[cfg(test)]
pub fn small_split(refs: &mut [PrimRef], axes: (usize, usize), weighted: bool) -> Option<(usize, f32)> {
    small_split_min(refs, axes, weighted, 0.0)
}

/// `small_split` among the splits whose sides hold at least `min_w` primitives each (None
/// when there is none).
#[inline(never)]
// The slot index reads several per-slot arrays at once.
#[allow(clippy::needless_range_loop)]
pub fn small_split_min(refs: &mut [PrimRef], axes: (usize, usize), weighted: bool, min_w: f32) -> Option<(usize, f32)> {
    let n = refs.len();
    if !(2..=MAX_SMALL).contains(&n) {
        return None;
    }
    // Primitives per reference (clusters when `weighted`), 0 in unused slots.
    let mut w = [0f32; MAX_SMALL];
    for (x, r) in w.iter_mut().zip(refs.iter()) {
        *x = if weighted { r.cluster_size() as f32 } else { 1.0 };
    }
    if n == 2 {
        if w[0] < min_w || w[1] < min_w {
            return None;
        }
        // Both orders give the same split and cost; keep the input order (what the sweep
        // picks on a tie).
        return Some((1, half_area_vec(ref_lo(&refs[0]), ref_hi(&refs[0])) * w[0] + half_area_vec(ref_lo(&refs[1]), ref_hi(&refs[1])) * w[1]));
    }
    // Three to five references: every bipartition (`enum_split`), which finds a split at least
    // as cheap as the sweeps in less time than sorting on three axes; on one axis sorting is
    // faster from five references on (docs/TUNING.md).
    let enum_max = if axes.1 - axes.0 == 1 { 4 } else { 5 };
    match n {
        3 => return enum_split::<3, 4>(refs, &w, min_w),
        4 => return enum_split::<4, 8>(refs, &w, min_w),
        5 if n <= enum_max => return enum_split::<5, 16>(refs, &w, min_w),
        _ => {}
    }
    // Boxes and centroids gathered once (the sweeps read them in sorted order per axis).
    // Unused slots hold empty boxes (+inf..-inf), which leave the sweeps' bounds unchanged,
    // so the sweeps run a step count fixed by n without data-dependent branches.
    let mut lo = [Vec3A::INFINITY; MAX_SMALL];
    let mut hi = [Vec3A::NEG_INFINITY; MAX_SMALL];
    let mut ctr = [[0f32; 4]; MAX_SMALL];
    for (i, r) in refs.iter().enumerate() {
        lo[i] = ref_lo(r);
        hi[i] = ref_hi(r);
        ctr[i] = Vec4::from((lo[i] * 0.5 + hi[i] * 0.5, 0.0)).to_array();
    }
    let mut best: Option<(usize, usize, f32)> = None;
    let mut best_order = [0u8; MAX_SMALL];
    for a in axes.0..axes.1.min(3) {
        // Sort (key, index) with a branch-free sorting network on order-preserving integer
        // keys: the same order as a stable sort by the key (ties by index), no mispredictions.
        // Unused slots keep u64::MAX keys, sort last and name slot 7 (an empty box when n < 8).
        let mut v = [u64::MAX; MAX_SMALL];
        for i in 0..n {
            v[i] = (ordered_bits(ctr[i][a]) as u64) << 32 | i as u64;
        }
        sort_network(&mut v, &NET8);
        let order: [u8; MAX_SMALL] = std::array::from_fn(|i| v[i] as u8);
        // n - 1 steps: the split positions there are (a fixed 7 cost small nodes dearly).
        // Three and four references never get here (`enum_split` above).
        let axis_best = match n {
            5 => small_sweep::<4>(&order, &lo, &hi, &w, n, min_w),
            6 => small_sweep::<5>(&order, &lo, &hi, &w, n, min_w),
            7 => small_sweep::<6>(&order, &lo, &hi, &w, n, min_w),
            _ => small_sweep::<7>(&order, &lo, &hi, &w, n, min_w),
        };
        // Ties across axes keep the earlier axis; within an axis the sweep keeps the lowest
        // position.
        if let Some((mid, cost)) = axis_best {
            if best.is_none_or(|b| cost < b.2) {
                best = Some((a, mid, cost));
                best_order = order;
            }
        }
    }
    let (_, mid, cost) = best?;
    let mut tmp = [PrimRef::zeroed(); MAX_SMALL];
    tmp[..n].copy_from_slice(refs);
    for i in 0..n {
        refs[i] = tmp[best_order[i] as usize & (MAX_SMALL - 1)];
    }
    Some((mid, cost))
}

//! Binned SAH: a node's bins over its box (`node_binning`), filling them (`bin_refs`, in
//! parallel chunks for the top of the tree), the sweep that picks the split (`sweep_bins`), and
//! the split test shared by binning and partition (`Splitter`).
//!
//! Owns: bins and the split choice of binned nodes. Must not touch: where references move.
use crate::accel::geometry::{half_area_vec, ref_hi, ref_lo, to_aabb, trunc_lanes3, trunc_lanes, Aabb, PrimRef};
use crate::accel::params::{BuildParams, MAX_BINS, ONE_BIN_SET_BELOW, ONE_BIN_SET_BELOW_3_AXES, REFS_PER_BIN};
use glam::{UVec3, Vec3A, Vec4};
use rayon::prelude::*;

/// Per-bin bounds for the three axes (SoA per axis). Only the first `k` entries of each axis
/// are reset and used, so small nodes pay for few bins; one buffer is reused down a
/// sequential recursion (a new one only at each parallel fork): O(threads) memory.
#[derive(Clone, Copy)]
pub struct Bins {
    pub lo: [[Vec3A; MAX_BINS]; 3],
    pub hi: [[Vec3A; MAX_BINS]; 3],
    pub count: [[u32; MAX_BINS]; 3],
}
impl Bins {
    pub fn new() -> Self {
        Bins { lo: [[Vec3A::INFINITY; MAX_BINS]; 3], hi: [[Vec3A::NEG_INFINITY; MAX_BINS]; 3], count: [[0; MAX_BINS]; 3] }
    }
    /// Resets the first `k` bins of the axes `axes.0..axes.1` (the only ones a node bins and
    /// sweeps: the others keep stale values that nothing reads).
    pub fn reset(&mut self, k: usize, axes: (usize, usize)) {
        for a in axes.0..axes.1.min(3) {
            self.lo[a][..k].fill(Vec3A::INFINITY);
            self.hi[a][..k].fill(Vec3A::NEG_INFINITY);
            self.count[a][..k].fill(0);
        }
    }
    pub fn merge(&mut self, o: &Bins, k: usize, axes: (usize, usize)) {
        for a in axes.0..axes.1.min(3) {
            for b in 0..k {
                self.lo[a][b] = self.lo[a][b].min(o.lo[a][b]);
                self.hi[a][b] = self.hi[a][b].max(o.hi[a][b]);
                self.count[a][b] += o.count[a][b];
            }
        }
    }
}

#[derive(Clone, Copy)]
pub struct Binning {
    pub cmin: Vec3A,
    pub scale: Vec3A,
    pub kmax: UVec3,
    pub kmax_f: Vec3A,
    /// Axes binned: a..b (all three, or the single widest one).
    pub axes: (usize, usize),
}
impl Binning {
    /// Bin indices of a reference on all three axes. `as u32` saturates (NaN → 0), so no
    /// input can index out of range; binning and partitioning share this exact arithmetic.
    /// The same arithmetic for one axis (bit-identical to the vector lane: same IEEE ops).
    #[inline(always)]
    pub fn bin_axis(&self, r: &PrimRef, a: usize) -> usize {
        let c = r.lo[a] * 0.5 + r.hi[a] * 0.5;
        (((c - self.cmin[a]) * self.scale[a]) as u32).min(self.kmax.x) as usize
    }
    #[inline(always)]
    pub fn bins(&self, r: &PrimRef) -> UVec3 {
        let c = ref_lo(r) * 0.5 + ref_hi(r) * 0.5;
        // Clamped in float first (max(NaN, 0) = 0 on SSE, like `as u32`), then an exact
        // conversion: the same bins as `(x as u32).min(kmax)`, without per-lane saturation.
        let t = trunc_lanes3(((c - self.cmin) * self.scale).max(Vec3A::ZERO).min(self.kmax_f));
        UVec3::new(t[0] as u32, t[1] as u32, t[2] as u32)
    }
    /// The split test of axis `a` at bin limit `limit` with its scalars hoisted.
    #[inline(always)]
    pub fn splitter(&self, a: usize, limit: f32) -> Splitter {
        let a = a.min(2);
        Splitter { a, cmin: self.cmin[a], scale: self.scale[a], limit }
    }
}

/// The split test of one axis with the axis' scalars taken out of the vectors once:
/// `bin_axis(r, a) <= b` for a split bin b < kmax, without the conversion: the scaled
/// position is finite or +inf (finite bounds, finite positive scale), so truncation <= b
/// is exactly x < b + 1 (negative x: bin 0, and x < b + 1 too).
#[derive(Clone, Copy)]
pub struct Splitter {
    pub a: usize,
    pub cmin: f32,
    pub scale: f32,
    pub limit: f32,
}
impl Splitter {
    /// The scaled centroid position (the same IEEE operations as `Binning::bin_axis`).
    #[inline(always)]
    pub fn pos(&self, r: &PrimRef) -> f32 {
        let c = r.lo[self.a] * 0.5 + r.hi[self.a] * 0.5;
        (c - self.cmin) * self.scale
    }
    #[inline(always)]
    pub fn left(&self, r: &PrimRef) -> bool {
        self.pos(r) < self.limit
    }
}
/// One reference into bin `b` (masked into range) of one axis' bin arrays.
#[inline(always)]
pub fn add_to_bin(lo: &mut [Vec3A; MAX_BINS], hi: &mut [Vec3A; MAX_BINS], cnt: &mut [u32; MAX_BINS], b: usize, r: &PrimRef) {
    let b = b & (MAX_BINS - 1);
    lo[b] = lo[b].min(ref_lo(r));
    hi[b] = hi[b].max(ref_hi(r));
    cnt[b] += 1;
}

#[inline(always)]
pub fn bin_one(r: &PrimRef, bn: &Binning, bins: &mut Bins) {
    let lo = ref_lo(r);
    let hi = ref_hi(r);
    if bn.axes.1 - bn.axes.0 == 1 {
        let a = bn.axes.0.min(2);
        add_to_bin(&mut bins.lo[a], &mut bins.hi[a], &mut bins.count[a], bn.bin_axis(r, a), r);
        return;
    }
    // All three axes (the only other case); indices are <= kmax < MAX_BINS, so the mask
    // changes nothing and lets the compiler drop the bounds checks.
    let idx = bn.bins(r);
    let bx = idx.x as usize & (MAX_BINS - 1);
    let by = idx.y as usize & (MAX_BINS - 1);
    let bz = idx.z as usize & (MAX_BINS - 1);
    bins.lo[0][bx] = bins.lo[0][bx].min(lo);
    bins.hi[0][bx] = bins.hi[0][bx].max(hi);
    bins.count[0][bx] += 1;
    bins.lo[1][by] = bins.lo[1][by].min(lo);
    bins.hi[1][by] = bins.hi[1][by].max(hi);
    bins.count[1][by] += 1;
    bins.lo[2][bz] = bins.lo[2][bz].min(lo);
    bins.hi[2][bz] = bins.hi[2][bz].max(hi);
    bins.count[2][bz] += 1;
}


/// Single-axis binning (fast-build tier) with the axis' scalars hoisted: the same bins as
/// `Binning::bin_axis`, into two interleaved sets merged at the end.
pub fn bin_refs_axis(refs: &[PrimRef], bn: &Binning, bins: &mut Bins) {
    let a = bn.axes.0.min(2);
    let (cmin, scale, kmax) = (bn.cmin[a], bn.scale[a], bn.kmax.x);
    let bin = |r: &PrimRef| ((((r.lo[a] * 0.5 + r.hi[a] * 0.5) - cmin) * scale) as u32).min(kmax) as usize & (MAX_BINS - 1);
    let k = (kmax as usize + 1).min(MAX_BINS);
    let (blo, bhi, bcnt) = (&mut bins.lo[a], &mut bins.hi[a], &mut bins.count[a]);
    if refs.len() < ONE_BIN_SET_BELOW {
        // Few references: one set (the second would cost more to clear and merge than the
        // chained min/max it avoids). Same bins: min, max and counts do not depend on order.
        for r in refs {
            add_to_bin(blo, bhi, bcnt, bin(r), r);
        }
        return;
    }
    let mut lo2 = [Vec3A::INFINITY; MAX_BINS];
    let mut hi2 = [Vec3A::NEG_INFINITY; MAX_BINS];
    let mut cnt2 = [0u32; MAX_BINS];
    // Four bin indices per vector conversion: the same centroid, offset and scale
    // operations per lane as `bin` (so the same bins), clamped in float and truncated
    // exactly (`trunc_lanes3`), instead of four saturating scalar conversions.
    let (cmin4, scale4, kmax4) = (Vec4::splat(cmin), Vec4::splat(scale), Vec4::splat(kmax as f32));
    let ctr = |r: &PrimRef| r.lo[a] * 0.5 + r.hi[a] * 0.5;
    let mut quads = refs.chunks_exact(4);
    for q in &mut quads {
        let pos = (Vec4::new(ctr(&q[0]), ctr(&q[1]), ctr(&q[2]), ctr(&q[3])) - cmin4) * scale4;
        let t = trunc_lanes(pos.max(Vec4::ZERO).min(kmax4));
        let b = t.map(|x| x as usize & (MAX_BINS - 1));
        // Even references into the node's bins, odd ones into the second set.
        add_to_bin(blo, bhi, bcnt, b[0], &q[0]);
        add_to_bin(&mut lo2, &mut hi2, &mut cnt2, b[1], &q[1]);
        add_to_bin(blo, bhi, bcnt, b[2], &q[2]);
        add_to_bin(&mut lo2, &mut hi2, &mut cnt2, b[3], &q[3]);
    }
    for r in quads.remainder() {
        add_to_bin(blo, bhi, bcnt, bin(r), r);
    }
    for b in 0..k {
        blo[b] = blo[b].min(lo2[b]);
        bhi[b] = bhi[b].max(hi2[b]);
        bcnt[b] += cnt2[b];
    }
}

pub fn bin_refs(refs: &[PrimRef], bn: &Binning, bins: &mut Bins) {
    if bn.axes.1 - bn.axes.0 == 1 {
        return bin_refs_axis(refs, bn, bins);
    }
    if refs.len() < ONE_BIN_SET_BELOW_3_AXES {
        for r in refs {
            bin_one(r, bn, bins);
        }
        return;
    }
    // Two interleaved bin sets: neighbouring primitives often fall into the same bin, and one
    // set would chain every min/max through memory. Merging is exact (min/max, integer counts).
    let k = (bn.kmax.x as usize + 1).min(MAX_BINS);
    let mut other = Bins::new();
    let mut pairs = refs.chunks_exact(2);
    for p in &mut pairs {
        bin_one(&p[0], bn, bins);
        bin_one(&p[1], bn, &mut other);
    }
    for r in pairs.remainder() {
        bin_one(r, bn, bins);
    }
    bins.merge(&other, k, bn.axes);
}

/// Bins per axis of a binned node of `n` references: at most one per REFS_PER_BIN, at least the
/// tier's `min_bins`, at most its `bins`.
#[inline]
pub fn bin_count(p: &BuildParams, n: usize) -> usize {
    p.bins.clamp(2, MAX_BINS).min((n / REFS_PER_BIN).max(p.min_bins.max(2)))
}

/// Bins of `src` binned by `bin` in parallel chunks of `chunk` references and merged (exact:
/// minima, maxima and counts), `k` bins on `axes`.
pub fn bin_in_chunks(src: &[PrimRef], chunk: usize, k: usize, axes: (usize, usize), bin: impl Fn(&[PrimRef], &mut Bins) + Sync) -> Bins {
    src.par_chunks(chunk.max(1))
        .map(|c| {
            let mut b = Bins::new();
            bin(c, &mut b);
            b
        })
        .reduce(Bins::new, |mut x, y| {
            x.merge(&y, k, axes);
            x
        })
}

/// The bins of a node of `n` references whose bins span `cb`: `k` per axis (the widest axis of
/// `cb` alone below the tier's `all_axes_from`), and the per-axis scales (0 for a flat axis);
/// None when every binned axis is flat.
// The axis index reads several per-axis arrays at once.
#[allow(clippy::needless_range_loop)]
pub fn node_binning(p: &BuildParams, cb: &Aabb, k: usize, n: usize) -> Option<(Binning, [f32; 3])> {
    let mut scale = [0f32; 3];
    let mut any = false;
    let widest = (0..3).fold(0, |w, a| if cb.hi[a] - cb.lo[a] > cb.hi[w] - cb.lo[w] { a } else { w });
    let axes = if n >= p.all_axes_from { (0, 3) } else { (widest, widest + 1) };
    for a in axes.0..axes.1 {
        let ext = cb.hi[a] - cb.lo[a];
        let sc = k as f32 / ext;
        if ext > 0.0 && sc.is_finite() && sc > 0.0 {
            // Shrink slightly so the max centroid lands in bin k-1, not k.
            scale[a] = sc * (1.0 - 1.0 / 1024.0);
            any = true;
        }
    }
    let bn = Binning { cmin: Vec3A::from(cb.lo), scale: Vec3A::from(scale), kmax: UVec3::splat(k as u32 - 1), kmax_f: Vec3A::splat((k - 1) as f32), axes };
    any.then_some((bn, scale))
}

/// The best binned split: (axis, last left bin, left box, right box, A_L·N_L + A_R·N_R), among
/// those whose sides hold at least `min_side` references each (1: both sides nonempty).
#[inline(never)]
// The axis index reads several per-axis arrays at once.
#[allow(clippy::needless_range_loop)]
pub fn sweep_bins(bins: &Bins, k: usize, scale: &[f32; 3], min_side: u32) -> Option<(usize, usize, Aabb, Aabb, f32)> {
    let mut split = None;
    // Sweep: prefix areas/counts left to right, then the right side accumulated on the
    // fly; boxes of the winning split are recomputed afterwards (keeps per-node stack
    // traffic proportional to k).
    let mut best: Option<(usize, usize, f32)> = None;
    for a in 0..3 {
        if scale[a] == 0.0 {
            continue;
        }
        let mut l_area = [0f32; MAX_BINS];
        let mut l_count = [0u32; MAX_BINS];
        let mut lo = Vec3A::INFINITY;
        let mut hi = Vec3A::NEG_INFINITY;
        let mut cnt = 0u32;
        for b in 0..k - 1 {
            lo = lo.min(bins.lo[a][b]);
            hi = hi.max(bins.hi[a][b]);
            cnt += bins.count[a][b];
            l_area[b] = half_area_vec(lo, hi);
            l_count[b] = cnt;
        }
        let mut lo = Vec3A::INFINITY;
        let mut hi = Vec3A::NEG_INFINITY;
        let mut rcount = 0u32;
        // Right-to-left; ties resolved to the lowest (axis, bin) for determinism.
        // Branch-free selection: an empty side's cost is NaN, which never compares <=, and
        // the first valid cost always wins against the initial +inf (as it did when this was
        // an Option), so ties still go to the lowest bin.
        let (mut ab_cost, mut ab_bin) = (f32::INFINITY, usize::MAX);
        for b in (0..k - 1).rev() {
            lo = lo.min(bins.lo[a][b + 1]);
            hi = hi.max(bins.hi[a][b + 1]);
            rcount += bins.count[a][b + 1];
            let lcount = l_count[b];
            let cost = l_area[b] * lcount as f32 + half_area_vec(lo, hi) * rcount as f32;
            let cost = if lcount < min_side || rcount < min_side { f32::NAN } else { cost };
            let take = cost <= ab_cost;
            ab_cost = if take { cost } else { ab_cost };
            ab_bin = if take { b } else { ab_bin };
        }
        if let Some((b, cost)) = (ab_bin != usize::MAX).then_some((ab_bin, ab_cost)) {
            if best.is_none_or(|x| cost < x.2) {
                best = Some((a, b, cost));
            }
        }
    }
    if let Some((a, b, cost)) = best {
        let (mut llo, mut lhi, mut rlo, mut rhi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY, Vec3A::INFINITY, Vec3A::NEG_INFINITY);
        for x in 0..k {
            if x <= b {
                llo = llo.min(bins.lo[a][x]);
                lhi = lhi.max(bins.hi[a][x]);
            } else {
                rlo = rlo.min(bins.lo[a][x]);
                rhi = rhi.max(bins.hi[a][x]);
            }
        }
        split = Some((a, b, to_aabb(llo, lhi), to_aabb(rlo, rhi), cost));
    }
    split
}


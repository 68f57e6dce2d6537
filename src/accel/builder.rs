//! Build: ingest (geometry → primitive references in scratch; in the fast-build and default
//! tiers, pairs of neighbouring primitives, `pairs`) → binned-SAH binary BVH in scratch
//! (rayon::join on the current pool, node slots derived from primitive ranges so the tree is
//! the same for any thread count; in large BLAS builds its first levels from one sample,
//! `top`) → collapse to BVH4 → encode into dst.
//! Host heap use is O(threads): all arrays proportional to the input live in `scratch`.
use super::input::{self, read_aabb, read_instance, read_triangle};
use super::pairs;
use super::layout::{self, GeometryRecord, InstanceRecord, PrimRecord, RawHeader, WideNode, CHILD_INTERNAL, NODE_SIZE, PRIM_SIZE, RECORD_SIZE};
use super::{AsType, BuildDesc, BuildError, BuildFlags, BuildPhases, BuildReport, DeviceView, Geometry, GeometryData};
use std::sync::Mutex;
use std::time::Instant;
use bytemuck::{Pod, Zeroable};
use glam::{UVec3, Vec3, Vec3A, Vec3Swizzles, Vec4};
use rayon::prelude::*;

mod top;

/// One primitive reference: its (sanitised, finite) bounds and where it came from.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct PrimRef {
    pub lo: [f32; 3],
    pub geom: u32,
    pub hi: [f32; 3],
    pub prim: u32,
}
const _: () = assert!(std::mem::size_of::<PrimRef>() == layout::PRIMREF_SIZE as usize);
/// Marks an inactive/dropped slot during ingest, before compaction.
const DROPPED: u32 = u32::MAX;

/// Binary node in scratch. A subtree over k primitives rooted at slot r owns slots r..r+2k-1:
/// left child at r+1, right child at r+2*left_count. Slots follow from primitive ranges, never
/// from timing, which is what makes the tree identical for every thread count.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct BinNode {
    pub lo: [f32; 3],
    pub start: u32,
    pub hi: [f32; 3],
    pub count: u32,
    /// 0 = leaf, else primitives in the left child.
    pub left_count: u32,
    pub reserved: u32,
}
const _: () = assert!(std::mem::size_of::<BinNode>() == layout::BINNODE_SIZE as usize);

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub lo: [f32; 3],
    pub hi: [f32; 3],
}
impl Aabb {
    pub const EMPTY: Aabb = Aabb { lo: [f32::INFINITY; 3], hi: [f32::NEG_INFINITY; 3] };
    #[inline]
    pub fn grow(&mut self, lo: &[f32; 3], hi: &[f32; 3]) {
        for a in 0..3 {
            self.lo[a] = self.lo[a].min(lo[a]);
            self.hi[a] = self.hi[a].max(hi[a]);
        }
    }
    #[inline]
    pub fn grow_point(&mut self, p: &[f32; 3]) {
        self.grow(p, p);
    }
    #[inline]
    pub fn union(mut self, o: &Aabb) -> Aabb {
        self.grow(&o.lo, &o.hi);
        self
    }
    /// Half surface area (the SAH uses ratios, so the factor 2 cancels).
    #[inline]
    pub fn half_area(&self) -> f32 {
        let d = [self.hi[0] - self.lo[0], self.hi[1] - self.lo[1], self.hi[2] - self.lo[2]];
        if d[0] < 0.0 || d[1] < 0.0 || d[2] < 0.0 {
            return 0.0;
        }
        d[0] * d[1] + d[1] * d[2] + d[2] * d[0]
    }
}

/// Bounds of a reference as vectors, each one 16-byte load (`lo` and `geom`, `hi` and `prim`
/// are adjacent) and a mask that zeroes the fourth lane: the integer's bits would be denormal
/// floats, slow in arithmetic on some CPUs.
#[inline(always)]
pub(super) fn ref_lo(r: &PrimRef) -> Vec3A {
    let a: &[[f32; 4]; 2] = bytemuck::cast_ref(r);
    Vec3A::from_vec4(Vec4::select(XYZ_MASK, Vec4::from_array(a[0]), Vec4::ZERO))
}
#[inline(always)]
pub(super) fn ref_hi(r: &PrimRef) -> Vec3A {
    let a: &[[f32; 4]; 2] = bytemuck::cast_ref(r);
    Vec3A::from_vec4(Vec4::select(XYZ_MASK, Vec4::from_array(a[1]), Vec4::ZERO))
}
const XYZ_MASK: glam::BVec4A = glam::BVec4A::from_array([true, true, true, false]);

#[inline]
fn centroid(r: &PrimRef) -> [f32; 3] {
    [r.lo[0] * 0.5 + r.hi[0] * 0.5, r.lo[1] * 0.5 + r.hi[1] * 0.5, r.lo[2] * 0.5 + r.hi[2] * 0.5]
}

/// Bounds with NaN and infinity removed: traversal skips NaN geometry anyway, and finite
/// boxes keep quantisation and SAH arithmetic total.
pub fn sanitize(lo: [f32; 3], hi: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let mut l = [0f32; 3];
    let mut h = [0f32; 3];
    for a in 0..3 {
        let (x, y) = (lo[a], hi[a]);
        if x.is_nan() || y.is_nan() {
            l[a] = -f32::MAX;
            h[a] = f32::MAX;
        } else {
            l[a] = x.min(y).clamp(-f32::MAX, f32::MAX);
            h[a] = x.max(y).clamp(-f32::MAX, f32::MAX);
        }
    }
    (l, h)
}

pub fn triangle_bounds(v: &[Vec3; 3]) -> ([f32; 3], [f32; 3]) {
    // Fast path: all coordinates finite, so vector min/max are exact and sanitising changes
    // nothing.
    let (a, b, c) = (Vec3A::from(v[0]), Vec3A::from(v[1]), Vec3A::from(v[2]));
    if a.is_finite() && b.is_finite() && c.is_finite() {
        return (a.min(b).min(c).to_array(), a.max(b).max(c).to_array());
    }
    let lo = v[0].min(v[1]).min(v[2]);
    let hi = v[0].max(v[1]).max(v[2]);
    // glam's min/max drop NaN like f32::min; recheck explicitly so a NaN Y/Z gives a huge box.
    let any_nan = v.iter().any(|p| p.is_nan());
    if any_nan {
        return sanitize([f32::NAN; 3], [f32::NAN; 3]);
    }
    sanitize(lo.to_array(), hi.to_array())
}

/// Bounds of an instance: its BLAS bounds transformed (8 corners); an empty or unreadable BLAS
/// is a point at the instance origin, as the spec suggests for instances of empty BLASes.
pub fn instance_bounds(transform: &[f32; 12], reference: u64, view: &dyn DeviceView) -> ([f32; 3], [f32; 3]) {
    instance_bounds_of(transform, blas_bounds(reference, view).as_ref())
}

/// The bounds of the BLAS `reference` names, or None when it is empty or not a structure
/// (the instance is then a point at its origin).
pub fn blas_bounds(reference: u64, view: &dyn DeviceView) -> Option<[f32; 6]> {
    view.acceleration_structure(reference).and_then(layout::parse).filter(|p| p.raw.primitive_count > 0).map(|p| p.raw.bounds)
}

/// `instance_bounds` from the BLAS bounds already looked up.
/// `blas` by reference: the caller's copy of an `Option<[f32; 6]>` read back whole right after
/// it was written stalled on store-to-load forwarding (a sixth of a TLAS update).
pub fn instance_bounds_of(transform: &[f32; 12], blas: Option<&[f32; 6]>) -> ([f32; 3], [f32; 3]) {
    match blas {
        Some(bb) => {
            let (x, y, z, t) = instance_terms(transform, bb);
            // Zero times a term is 0 when it is finite and NaN otherwise: one test for all seven.
            let zero = ((((((x[0] * 0.0 + x[1] * 0.0) + y[0] * 0.0) + y[1] * 0.0) + z[0] * 0.0) + z[1] * 0.0) + t * 0.0).cmpeq(Vec3A::ZERO);
            if zero.all() {
                // Finite terms: each rounding step is monotonic, so the least (greatest) corner
                // is the sum of the least (greatest) terms, to the bit: the same box as
                // `instance_box_corners`, from two sums instead of eight.
                let lo = ((x[0].min(x[1]) + y[0].min(y[1])) + z[0].min(z[1])) + t;
                let hi = ((x[0].max(x[1]) + y[0].max(y[1])) + z[0].max(z[1])) + t;
                if !(lo.is_nan() || hi.is_nan()) {
                    let b = to_aabb(lo, hi);
                    return sanitize(b.lo, b.hi);
                }
            }
            instance_box_corners(transform, bb)
        }
        _ => {
            let o = [transform[3], transform[7], transform[11]];
            if o.iter().any(|x| x.is_nan()) {
                return sanitize([f32::NAN; 3], [f32::NAN; 3]);
            }
            let mut b = Aabb::EMPTY;
            b.grow_point(&o);
            sanitize(b.lo, b.hi)
        }
    }
}

/// The six products of a 3x4 transform's columns with a box's bounds, and its translation:
/// corner k of the transformed box is ((x[k&1] + y[k>>1&1]) + z[k>>2&1]) + t, the same
/// operations as `transform_point`.
#[inline(always)]
fn instance_terms(m: &[f32; 12], bb: &[f32; 6]) -> ([Vec3A; 2], [Vec3A; 2], [Vec3A; 2], Vec3A) {
    let (c0, c1, c2) = (Vec3A::new(m[0], m[4], m[8]), Vec3A::new(m[1], m[5], m[9]), Vec3A::new(m[2], m[6], m[10]));
    let t = Vec3A::new(m[3], m[7], m[11]);
    ([c0 * bb[0], c0 * bb[3]], [c1 * bb[1], c1 * bb[4]], [c2 * bb[2], c2 * bb[5]], t)
}

/// The box of the eight transformed corners, lane-wise (any NaN corner: the NaN box).
#[inline(never)]
fn instance_box_corners(m: &[f32; 12], bb: &[f32; 6]) -> ([f32; 3], [f32; 3]) {
    let (x, y, z, t) = instance_terms(m, bb);
    let (mut lo, mut hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let mut nan = false;
    for c in 0..8 {
        let q = ((x[c & 1] + y[c >> 1 & 1]) + z[c >> 2 & 1]) + t;
        nan |= q.is_nan();
        lo = lo.min(q);
        hi = hi.max(q);
    }
    if nan {
        return sanitize([f32::NAN; 3], [f32::NAN; 3]);
    }
    let b = to_aabb(lo, hi);
    sanitize(b.lo, b.hi)
}

/// `blas_bounds` of the last four BLAS references looked up (a TLAS usually instances few
/// BLASes, and each lookup is a locked map search and a header parse).
pub struct BlasBoundsMemo {
    e: [(u64, Option<[f32; 6]>); 4],
    next: usize,
}
impl BlasBoundsMemo {
    pub fn new() -> Self {
        BlasBoundsMemo { e: [(0, None); 4], next: 0 }
    }
    /// The bounds of the BLAS at `reference` (0, never an active instance's, is not memoised),
    /// by reference into the memo: a copy read back at once stalls on store forwarding.
    pub fn get(&mut self, reference: u64, view: &dyn DeviceView) -> Option<&[f32; 6]> {
        let k = match self.e.iter().position(|m| m.0 == reference && reference != 0) {
            Some(k) => k,
            None => {
                let k = self.next % self.e.len();
                self.e[k] = (reference, blas_bounds(reference, view));
                self.next = (k + 1) % self.e.len();
                k
            }
        };
        self.e[k].1.as_ref()
    }
}

/// Builder settings chosen from the build flags.
#[derive(Clone, Copy, Debug)]
pub struct BuildParams {
    pub bins: usize,
    /// Nodes of at least this many references bin (and sweep) all three axes; smaller ones only
    /// the widest axis of their box (a third of the binning work for a few percent of SAH):
    /// from SMALL_N + 1 in the fast-trace tier (its exact sweeps of small nodes sort one axis),
    /// 1,024 in the default tier, never in the fast-build tier; instance trees outside the
    /// fast-build tier from 0 (`build`).
    pub all_axes_from: usize,
    /// C_T relative to C_I in the leaf/split decision (the reported SAH always uses 1): above
    /// 1 the fast-build tier makes bigger leaves, hence fewer nodes to build and encode.
    pub traversal_cost: f32,
    pub max_leaf: u32,
    /// Nodes up to this size use the exact sorted SAH sweep instead of binning (<= MAX_SMALL).
    pub small_n: usize,
    /// Below this many primitives a subtree is built on the calling thread. Output-neutral (it
    /// only chooses `rayon::join` or two calls). 1024: a 10,000-instance TLAS on the 16-core
    /// machine builds in 2.4–2.8 ms instead of 3.5–4.8 (fast-trace; 4096 gave it four tasks);
    /// the dragon does not change.
    pub parallel_cutoff: u32,
    /// Nodes of at least PAR_BIN_CUTOFF references bin a strided sample of about this many.
    pub sample_target: usize,
    /// Neighbouring primitives pair up before the build when their union's half area is at
    /// most this many times the sum of theirs (`pairs`); 0: no pairing.
    pub pair_tau: f32,
    /// Paired builds: the most primitives per cluster reference (<= pairs::MAX_CLUSTER) and
    /// the most cluster references per leaf.
    pub cluster: u32,
    pub cluster_leaf: u32,
    /// The fewest bins a binned node gets (it gets one per REFS_PER_BIN references, up to
    /// `bins`).
    pub min_bins: usize,
}
pub const MAX_BINS: usize = 32;
/// Depth after which splits become balanced object-median splits: bounds recursion depth
/// (stack use) to about 64 + log2(n) on any input.
const MAX_SAH_DEPTH: u32 = 64;
/// Above this many primitives binning runs on a sample of about `BuildParams::sample_target`
/// references, in parallel chunks in the top of the tree (`Ctx::top`) (this cutoff must stay
/// >= PAR_PART_CUTOFF: exact child boxes come from the parallel partition or its one-pass
/// form). Dragon, 1 thread: sampling 2^14 kept the
/// fast-build SAH (54.03) for 3 % fewer instructions; 2^15 cost FAST_TRACE 48.77 -> 48.79
/// for 6 % fewer. Since node boxes span the bins (`build_rec`), sampling from 2^14 references
/// instead of 2^16, 2^12 (fast-build) and 2^13 (fast-trace) of them instead of 2^14 and
/// 2^15, is 2 % faster on the dragon at the same SAH (53.74 -> 53.75, 48.85 -> 48.84); 2^13
/// from 2^13 cost FAST_TRACE 48.97.
pub(super) const PAR_BIN_CUTOFF: usize = 1 << 14;
const SAMPLE_TARGET: usize = 1 << 12;
/// Samples per parallel binning task of a sampled node (about 16 tasks: the strided reads
/// miss the cache, so one task per node would serialise the top of the tree).
const SAMPLE_CHUNK: usize = 1 << 10;
const BIN_CHUNK: usize = 1 << 14;

impl BuildParams {
    pub fn from_flags(flags: BuildFlags) -> Self {
        if flags.contains(BuildFlags::PREFER_FAST_TRACE) {
            // Clusters of up to 3 tight neighbours since session 14 (`pairs::FAST_TRACE_TAU`),
            // leaves of up to 3 clusters: dragon SAH 48.90, BVH4 28.74 (clusters of 2 in
            // leaves of 4: 48.92 / 28.81; of 3 in leaves of 4: 48.89 / 28.76; of 4 in leaves of
            // 2: 49.02 / 28.56 but 61.9 B/tri), the same time on one thread. Since session 15
            // the exact sweep of nodes of at most SMALL_N references sorts only their widest
            // axis: dragon one thread (this box, minima of 7, two interleaved rounds) 171–176 →
            // 163–167 ms, SAH 48.90 → 49.07 but the BVH4's 28.74 → 28.76, primary rays in the
            // same time (`trace_timing`: 27.8–28.1 ms either way); binning one axis below 12 / 16
            // references too: 160–162 ms at 49.18 / 28.80, 159–160 at 49.30 / 28.85.
            BuildParams { bins: 32, all_axes_from: SMALL_N + 1, traversal_cost: 1.0, max_leaf: 8, small_n: SMALL_N, parallel_cutoff: 1024, sample_target: 2 * SAMPLE_TARGET, pair_tau: pairs::FAST_TRACE_TAU, cluster: 3, cluster_leaf: 3, min_bins: 6 }
        } else if flags.contains(BuildFlags::PREFER_FAST_BUILD) {
            // 12 bins, not 8: over node boxes (see `build_rec`) 8 bins gave SAH 54.59 on the
            // dragon, 12 give 53.71 at the same speed. Clusters of up to 4 primitives, leaves
            // of up to 3 clusters (12 primitives): with tau 1.0 dragon SAH 53.90, 53.8 B/tri;
            // 16 threads 17.9–19.8 ms against 20.0–23.7 for pairs in leaves of 4 in interleaved
            // rounds on the 16-core machine (4 clusters per leaf: SAH 54.16 with the
            // reference-counting leaf rule). Since session 9 tau 1.1 (`pairs::FAST_BUILD_TAU`):
            // SAH 54.98, 53.4 B/tri, 6 % faster on one thread.
            BuildParams { bins: 12, all_axes_from: usize::MAX, traversal_cost: 2.5, max_leaf: 8, small_n: SMALL_N, parallel_cutoff: 1024, sample_target: SAMPLE_TARGET, pair_tau: pairs::FAST_BUILD_TAU, cluster: 4, cluster_leaf: 3, min_bins: 8 }
        } else {
            // Between the other two since session 15: the fast-trace tier's bins and clusters,
            // with three-axis binning only in nodes of at least 1,024 references. Dragon, one
            // thread (this box, minima of 7, two interleaved rounds): 141–144 ms at SAH 50.11
            // (BVH4 29.24), where the tier took 169–184 ms at 49.21 (16 bins on three axes,
            // clusters of 2 in leaves of 4), no faster than FAST_TRACE (176–187 ms, 48.90).
            // Three axes from 256 references: 145–148 ms at 49.91; from 16,384 (the sampled
            // nodes): 132–133 at 50.50, but the bunny's SAH 1.041× a full sweep's.
            BuildParams { bins: 32, all_axes_from: 1024, traversal_cost: 1.0, max_leaf: 8, small_n: SMALL_N, parallel_cutoff: 1024, sample_target: 2 * SAMPLE_TARGET, pair_tau: pairs::DEFAULT_TAU, cluster: 3, cluster_leaf: 3, min_bins: 6 }
        }
    }
}

/// Split the scratch into aligned PrimRef and BinNode arrays (no unsafe: skip to an aligned
/// offset, then let bytemuck check alignment and size).
pub fn carve<T: Pod>(bytes: &mut [u8], count: usize) -> Option<(&mut [T], &mut [u8])> {
    let align = std::mem::align_of::<T>().max(16);
    let addr = bytes.as_ptr() as usize;
    let skip = (align - addr % align) % align;
    let size = count.checked_mul(std::mem::size_of::<T>())?;
    let end = skip.checked_add(size)?;
    if end > bytes.len() {
        return None;
    }
    let (head, rest) = bytes.split_at_mut(end);
    let arr: &mut [T] = bytemuck::try_cast_slice_mut(&mut head[skip..]).ok()?;
    Some((arr, rest))
}

/// Per-bin bounds for the three axes (SoA per axis). Only the first `k` entries of each axis
/// are reset and used, so small nodes pay for few bins; one buffer is reused down a
/// sequential recursion (a new one only at each parallel fork): O(threads) memory.
#[derive(Clone, Copy)]
pub struct Bins {
    lo: [[Vec3A; MAX_BINS]; 3],
    hi: [[Vec3A; MAX_BINS]; 3],
    count: [[u32; MAX_BINS]; 3],
}
impl Bins {
    pub fn new() -> Self {
        Bins { lo: [[Vec3A::INFINITY; MAX_BINS]; 3], hi: [[Vec3A::NEG_INFINITY; MAX_BINS]; 3], count: [[0; MAX_BINS]; 3] }
    }
    /// Resets the first `k` bins of the axes `axes.0..axes.1` (the only ones a node bins and
    /// sweeps: the others keep stale values that nothing reads).
    fn reset(&mut self, k: usize, axes: (usize, usize)) {
        for a in axes.0..axes.1.min(3) {
            self.lo[a][..k].fill(Vec3A::INFINITY);
            self.hi[a][..k].fill(Vec3A::NEG_INFINITY);
            self.count[a][..k].fill(0);
        }
    }
    fn merge(&mut self, o: &Bins, k: usize, axes: (usize, usize)) {
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
struct Binning {
    cmin: Vec3A,
    scale: Vec3A,
    kmax: UVec3,
    kmax_f: Vec3A,
    /// Axes binned: a..b (all three, or the single widest one).
    axes: (usize, usize),
}
impl Binning {
    /// Bin indices of a reference on all three axes. `as u32` saturates (NaN → 0), so no
    /// input can index out of range; binning and partitioning share this exact arithmetic.
    /// The same arithmetic for one axis (bit-identical to the vector lane: same IEEE ops).
    #[inline(always)]
    fn bin_axis(&self, r: &PrimRef, a: usize) -> usize {
        let c = r.lo[a] * 0.5 + r.hi[a] * 0.5;
        (((c - self.cmin[a]) * self.scale[a]) as u32).min(self.kmax.x) as usize
    }
    #[inline(always)]
    fn bins(&self, r: &PrimRef) -> UVec3 {
        let c = ref_lo(r) * 0.5 + ref_hi(r) * 0.5;
        // Clamped in float first (max(NaN, 0) = 0 on SSE, like `as u32`), then an exact
        // conversion: the same bins as `(x as u32).min(kmax)`, without per-lane saturation.
        let t = trunc_i32x4(((c - self.cmin) * self.scale).max(Vec3A::ZERO).min(self.kmax_f));
        UVec3::new(t[0] as u32, t[1] as u32, t[2] as u32)
    }
    /// The split test of axis `a` at bin limit `limit` with its scalars hoisted.
    #[inline(always)]
    fn splitter(&self, a: usize, limit: f32) -> Splitter {
        let a = a.min(2);
        Splitter { a, cmin: self.cmin[a], scale: self.scale[a], limit }
    }
}

/// The split test of one axis with the axis' scalars taken out of the vectors once:
/// `bin_axis(r, a) <= b` for a split bin b < kmax, without the conversion: the scaled
/// position is finite or +inf (finite bounds, finite positive scale), so truncation <= b
/// is exactly x < b + 1 (negative x: bin 0, and x < b + 1 too).
#[derive(Clone, Copy)]
struct Splitter {
    a: usize,
    cmin: f32,
    scale: f32,
    limit: f32,
}
impl Splitter {
    /// The scaled centroid position (the same IEEE operations as `Binning::bin_axis`).
    #[inline(always)]
    fn pos(&self, r: &PrimRef) -> f32 {
        let c = r.lo[self.a] * 0.5 + r.hi[self.a] * 0.5;
        (c - self.cmin) * self.scale
    }
    #[inline(always)]
    fn left(&self, r: &PrimRef) -> bool {
        self.pos(r) < self.limit
    }
}

/// Lane-wise truncation of values already clamped to [0, 2^22), read as integers from the
/// mantissa: v + 2^23 rounds v to the nearest integer (exactly: the spacing there is 1), one is
/// taken off where that rounded up, and the mantissa of the result is floor(v) = trunc(v).
/// Five vector operations, where glam's SSE2 floor takes about eight; replaces saturating
/// float-to-int conversions, with no unsafe intrinsics.
#[inline(always)]
pub(super) fn trunc_i32x4(v: Vec3A) -> [i32; 4] {
    trunc_i32x4_4(Vec4::from((v, 0.0)))
}

/// `trunc_i32x4` for four lanes.
#[inline(always)]
fn trunc_i32x4_4(v: Vec4) -> [i32; 4] {
    const MAGIC: f32 = 8_388_608.0;
    let y = v + Vec4::splat(MAGIC);
    let up = (y - Vec4::splat(MAGIC)).cmpgt(v);
    let y = y - Vec4::select(up, Vec4::ONE, Vec4::ZERO);
    y.to_array().map(|f| (f.to_bits() & 0x7f_ffff) as i32)
}

/// floor(v) lane-wise for v in [0, 2^22): v + 2^23 - 2^23 rounds v to an integer exactly, and
/// one comes off where that rounded up (four vector operations).
#[inline(always)]
fn floor_pos(v: Vec4) -> Vec4 {
    const MAGIC: f32 = 8_388_608.0;
    let r = (v + Vec4::splat(MAGIC)) - Vec4::splat(MAGIC);
    r - Vec4::select(r.cmpgt(v), Vec4::ONE, Vec4::ZERO)
}

/// One reference into bin `b` (masked into range) of one axis' bin arrays.
#[inline(always)]
fn add_to_bin(lo: &mut [Vec3A; MAX_BINS], hi: &mut [Vec3A; MAX_BINS], cnt: &mut [u32; MAX_BINS], b: usize, r: &PrimRef) {
    let b = b & (MAX_BINS - 1);
    lo[b] = lo[b].min(ref_lo(r));
    hi[b] = hi[b].max(ref_hi(r));
    cnt[b] += 1;
}

#[inline(always)]
fn bin_one(r: &PrimRef, bn: &Binning, bins: &mut Bins) {
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

/// Below this many references single-axis binning uses one set of bins (see `bin_refs_axis`).
const SMALL_BIN_SET: usize = 64;

/// Single-axis binning (fast-build tier) with the axis' scalars hoisted: the same bins as
/// `Binning::bin_axis`, into two interleaved sets merged at the end.
fn bin_refs_axis(refs: &[PrimRef], bn: &Binning, bins: &mut Bins) {
    let a = bn.axes.0.min(2);
    let (cmin, scale, kmax) = (bn.cmin[a], bn.scale[a], bn.kmax.x);
    let bin = |r: &PrimRef| ((((r.lo[a] * 0.5 + r.hi[a] * 0.5) - cmin) * scale) as u32).min(kmax) as usize & (MAX_BINS - 1);
    let k = (kmax as usize + 1).min(MAX_BINS);
    let (blo, bhi, bcnt) = (&mut bins.lo[a], &mut bins.hi[a], &mut bins.count[a]);
    if refs.len() < SMALL_BIN_SET {
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
    // exactly (`trunc_i32x4`), instead of four saturating scalar conversions.
    let (cmin4, scale4, kmax4) = (Vec4::splat(cmin), Vec4::splat(scale), Vec4::splat(kmax as f32));
    let ctr = |r: &PrimRef| r.lo[a] * 0.5 + r.hi[a] * 0.5;
    let mut quads = refs.chunks_exact(4);
    for q in &mut quads {
        let pos = (Vec4::new(ctr(&q[0]), ctr(&q[1]), ctr(&q[2]), ctr(&q[3])) - cmin4) * scale4;
        let t = trunc_i32x4_4(pos.max(Vec4::ZERO).min(kmax4));
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

fn bin_refs(refs: &[PrimRef], bn: &Binning, bins: &mut Bins) {
    if bn.axes.1 - bn.axes.0 == 1 {
        return bin_refs_axis(refs, bn, bins);
    }
    if refs.len() < 512 {
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

#[inline]
pub(super) fn half_area_v(lo: Vec3A, hi: Vec3A) -> f32 {
    // (xy + yz) + zx, the same sum as `Aabb::half_area`, as one multiply and a lane sum.
    let d = (hi - lo).max(Vec3A::ZERO);
    (d * d.yzx()).element_sum()
}

fn to_aabb(lo: Vec3A, hi: Vec3A) -> Aabb {
    Aabb { lo: lo.to_array(), hi: hi.to_array() }
}

#[cfg(test)]
fn bounds_of(refs: &[PrimRef]) -> (Aabb, Aabb) {
    // Vector min/max (references are finite, so no NaN handling is needed).
    let (mut lo, mut hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let (mut clo, mut chi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    for r in refs {
        let (l, h) = (ref_lo(r), ref_hi(r));
        let c = l * 0.5 + h * 0.5;
        lo = lo.min(l);
        hi = hi.max(h);
        clo = clo.min(c);
        chi = chi.max(c);
    }
    (to_aabb(lo, hi), to_aabb(clo, chi))
}

/// The bounding box of `refs`.
fn box_of(refs: &[PrimRef]) -> Aabb {
    let (mut lo, mut hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    for r in refs {
        lo = lo.min(ref_lo(r));
        hi = hi.max(ref_hi(r));
    }
    to_aabb(lo, hi)
}

struct Ctx {
    params: BuildParams,
    /// References of the whole build and the pool's thread count (see `one_pass`).
    total: usize,
    threads: usize,
    /// The references are primitive pairs (`pairs`): leaves cost their primitives.
    paired: bool,
    /// The tier's C_T for costs counted in primitives (`params.traversal_cost` is scaled to
    /// references when paired).
    prim_ct: f32,
}
impl Ctx {
    /// Whether a node of `n` references partitions in one sequential pass rather than in
    /// parallel (statistics pass, then scatter): when there are likely at least as many nodes
    /// of its size as threads to keep them busy. Both ways are stable partitions with the same
    /// layout and the same side boxes, so the choice never changes the bytes.
    #[inline]
    fn one_pass(&self, n: usize) -> bool {
        n.saturating_mul(self.threads) <= self.total
    }
    /// Parallel partition (or its one-pass form) rather than `partition_out`: large nodes, and
    /// sampled ones always (their left count is not known before the partition).
    #[inline]
    fn big_partition(&self, n: usize) -> bool {
        n >= PAR_BIN_CUTOFF || (n >= PAR_PART_CUTOFF && !self.one_pass(n))
    }
    /// A node of the top of the tree (`build_tree`): one whose binning and partition fork
    /// (sampled, and too few nodes of its size to keep the threads busy otherwise).
    #[inline]
    fn top(&self, n: usize) -> bool {
        n >= PAR_BIN_CUTOFF && !self.one_pass(n)
    }
}

/// Builds the subtree over `refs` into `nodes[0..2n-1]`; returns its unnormalised SAH sum
/// (Σ inner A + Σ leaf A·|l|, half areas) and its depth.
///
/// `cb` is the box the node's bins span (and whose widest axis the fast-build tier bins):
/// the exact centroid bounds at the root, the node's own bounding box `bounds` below it. A
/// child's box comes free from its parent's bins, where its centroid bounds cost every
/// partition four vector min/max per reference. Dragon, one thread, against exact centroid
/// bounds: FAST_BUILD 139.5 → 122.3 ms (SAH 54.02 → 54.59 at 8 bins; 12 bins give 53.71 in
/// the same time), FAST_TRACE 228.8 → 208.5 ms (48.81 → 48.85); the soup and the terrain
/// keep their SAH within 0.7 %.
///
/// `in_nodes`: the node's references are not in `refs` yet but at the start of its own node
/// slots (where the parent's parallel partition put them); they reach `refs` through this
/// node's own parallel partition, or by `restore` before anything else reads or writes.
#[allow(clippy::too_many_arguments)]
fn build_rec<'a>(ctx: &Ctx, refs: &'a mut [PrimRef], nodes: &'a mut [BinNode], start: u32, bounds: Aabb, cb: Aabb, depth: u32, bins: &mut Bins, mut in_nodes: bool, pre: &'a mut [u8], parent_count: u32, sink: Option<&mut Vec<Task<'a>>>, idx: usize) -> (f64, u32) {
    let n = refs.len();
    let p = &ctx.params;
    // References still in the node slots (see `partition_out`) come back to `refs` where the
    // node will not partition them: leaves, small nodes, the depth limit.
    if in_nodes && (depth >= MAX_SAH_DEPTH || n <= p.small_n.clamp(1, MAX_SMALL)) {
        restore(refs, nodes);
        in_nodes = false;
    }
    let area = bounds.half_area();
    // Primitives under these references (a cluster counts its members).
    let prims_of = |refs: &[PrimRef]| if ctx.paired { refs.iter().map(pairs::weight).sum::<u32>() } else { refs.len() as u32 };
    let make_leaf = |nodes: &mut [BinNode], prims: u32| {
        if let Some(slot) = nodes.get_mut(0) {
            *slot = BinNode { lo: bounds.lo, start, hi: bounds.hi, count: n as u32, left_count: 0, reserved: 0 };
        }
        (area as f64 * prims as f64, 1u32)
    };
    if n <= 1 {
        return make_leaf(nodes, prims_of(refs));
    }
    if n as u32 <= p.max_leaf && n as f32 <= p.traversal_cost {
        // A split costs at least 0 more than C_T·A: no sweep can beat this leaf (the same
        // decision as the test below, made without sorting).
        return make_leaf(nodes, prims_of(refs));
    }
    if n <= p.small_n.min(MAX_SMALL) && depth < MAX_SAH_DEPTH {
        // Exact SAH sweep over sorted centroids: cheaper than binning for a handful of
        // primitives, and these nodes are most of the tree.
        let widest = (0..3).fold(0, |w, a| if cb.hi[a] - cb.lo[a] > cb.hi[w] - cb.lo[w] { a } else { w });
        let axes = if n >= p.all_axes_from { (0, 3) } else { (widest, widest + 1) };
        if let Some((mid, cost)) = small_split(refs, axes, ctx.paired) {
            // Clusters: the sweep's costs count primitives, so the leaf does too, with the
            // tier's own C_T.
            let (prims, ct) = (prims_of(refs), if ctx.paired { ctx.prim_ct } else { p.traversal_cost });
            if n as u32 <= p.max_leaf && area * prims as f32 <= area * ct + cost {
                return make_leaf(nodes, prims);
            }
            let (l, r) = refs.split_at(mid);
            let (lb, rb) = (box_of(l), box_of(r));
            return finish_split(ctx, refs, nodes, start, bounds, mid, lb, rb, depth, bins, false, pre, parent_count, sink, idx);
        }
        return make_leaf(nodes, prims_of(refs));
    }
    // Smaller nodes get fewer bins: at most one per four references, at least `min_bins` (the
    // sweep costs O(bins) per node; on the dragon FAST_TRACE this is 7 % fewer instructions for
    // SAH 48.79 -> 48.81 with at least 8). At least 6 in the three-axis tiers (session 10):
    // FAST_TRACE 3–5 % faster on one thread, SAH 48.84 -> 48.87 (then the tier's budget, 48.9;
    // the sample draw of the top alone moves it by ±0.08, see `top`), the default tier 1–3 %,
    // 49.11 -> 49.14; FAST_BUILD keeps 8 (6: SAH 54.70 -> 54.78 for no time measurable; 4 cost
    // FAST_TRACE 48.91).
    let k = bin_count(p, n);
    let split: Option<(usize, usize, Aabb, Aabb, f32)>; // (axis, bin, left box, right box, cost)
    if depth < MAX_SAH_DEPTH {
        if let Some((bn, scale)) = node_binning(p, &cb, k, n) {
            let axes = bn.axes;
            bins.reset(k, axes);
            let src: &[PrimRef] = if in_nodes { node_refs(nodes, n).unwrap_or(&[]) } else { refs };
            if n >= PAR_BIN_CUTOFF {
                // Large nodes bin an evenly strided sample of about SAMPLE_TARGET references
                // (the stride follows from n alone): the split choice needs only the relative
                // costs, and these nodes always take the parallel partition, which computes
                // the children's exact boxes.
                let step = (n / p.sample_target.max(1)).max(1);
                let bin_sample = |c: &[PrimRef], b: &mut Bins| {
                    if step == 1 {
                        bin_refs(c, &bn, b);
                    } else {
                        for r in c.iter().step_by(step) {
                            bin_one(r, &bn, b);
                        }
                    }
                };
                if !ctx.top(n) {
                    // One of at least as many nodes of its size as threads: sampled here, with
                    // no fork to wait on (see `build_tree`); the same bins as in chunks.
                    bin_sample(src, bins);
                } else {
                    bins.merge(&bin_in_chunks(src, if step == 1 { BIN_CHUNK } else { SAMPLE_CHUNK * step }, k, axes, bin_sample), k, axes);
                }
            } else {
                bin_refs(src, &bn, bins);
            }
            split = sweep_bins(bins, k, &scale);
            // SAH termination: a leaf costs A·n, a split A + children (C_T = C_I = 1).
            if let Some(s) = split {
                let leaf_cost = area * n as f32;
                if n as u32 <= p.max_leaf && leaf_cost <= area * p.traversal_cost + s.4 {
                    if in_nodes {
                        restore(refs, nodes);
                    }
                    return make_leaf(nodes, prims_of(refs));
                }
            }
            if let Some((a, b, lbox, rbox, _)) = split {
                let limit = (b + 1) as f32;
                let sp = bn.splitter(a, limit);
                // Left count from the bins (exact: binning and the split test share their
                // arithmetic), except for sampled nodes, which take the parallel partition.
                let nl_bins = bins.count[a][..=b.min(MAX_BINS - 1)].iter().map(|&c| c as usize).sum::<usize>();
                if in_nodes {
                    // Scatter from this node's slots straight into `refs` (no copy back);
                    // with everything on one side that is a plain copy, as a restore would be.
                    in_nodes = false;
                    if ctx.big_partition(n) {
                        match par_partition_from_nodes(refs, nodes, ctx.one_pass(n), |r| sp.left(r)) {
                            Some((i, l, r)) if i > 0 && i < n => return finish_split(ctx, refs, nodes, start, bounds, i, l, r, depth, bins, false, pre, parent_count, sink, idx),
                            Some(_) => {}
                            None => restore(refs, nodes),
                        }
                    } else {
                        let out = node_refs(nodes, n).and_then(|src| partition_out(src, bytemuck::cast_slice_mut(refs), nl_bins, PRIMREF_BYTES * nl_bins, &sp));
                        match out {
                            Some(i) if i > 0 && i < n => return finish_split(ctx, refs, nodes, start, bounds, i, lbox, rbox, depth, bins, false, pre, parent_count, sink, idx),
                            _ => restore(refs, nodes),
                        }
                    }
                } else if ctx.big_partition(n) {
                    // Large node: stable partition through the (still unwritten) node slots of
                    // this subtree, in parallel with fixed chunking or in one pass, the same
                    // order either way, so the same for any thread count.
                    if let Some((i, l, r)) = par_partition_to_nodes(refs, nodes, ctx.one_pass(n), |r| sp.left(r)) {
                        if i > 0 && i < n {
                            return finish_split(ctx, refs, nodes, start, bounds, i, l, r, depth, bins, true, pre, parent_count, sink, idx);
                        }
                    }
                } else if nl_bins > 0 && nl_bins < n {
                    // Sequential out-of-place partition into the children's node slots (one
                    // read and one write per reference); the children partition back into
                    // `refs`. `refs` is untouched if it fails (Lomuto below).
                    let rbase = (2 * nl_bins - 1) * std::mem::size_of::<BinNode>();
                    if let Some(rest) = nodes.get_mut(1..) {
                        if let Some(i) = partition_out(refs, bytemuck::cast_slice_mut(rest), nl_bins, rbase, &sp) {
                            if i > 0 && i < n {
                                return finish_split(ctx, refs, nodes, start, bounds, i, lbox, rbox, depth, bins, true, pre, parent_count, sink, idx);
                            }
                        }
                    }
                }
                let i = partition_seq(refs, &sp);
                if i > 0 && i < n {
                    // Bins of a sampled node do not bound every reference: exact boxes then.
                    let (lbox, rbox) = if n >= PAR_BIN_CUTOFF { (box_of(&refs[..i]), box_of(&refs[i..])) } else { (lbox, rbox) };
                    return finish_split(ctx, refs, nodes, start, bounds, i, lbox, rbox, depth, bins, false, pre, parent_count, sink, idx);
                }
            }
        }
    }
    if in_nodes {
        restore(refs, nodes);
    }
    if n as u32 <= p.max_leaf {
        return make_leaf(nodes, prims_of(refs));
    }
    // Fallback: object median along the widest axis of `cb` (all centroids equal, no SAH
    // split found, or depth limit). select_nth_unstable is deterministic and allocation-free.
    let mut axis = 0;
    for a in 1..3 {
        if cb.hi[a] - cb.lo[a] > cb.hi[axis] - cb.lo[axis] {
            axis = a;
        }
    }
    let mid = n / 2;
    refs.select_nth_unstable_by(mid, |x, y| centroid(x)[axis].total_cmp(&centroid(y)[axis]).then(x.geom.cmp(&y.geom)).then(x.prim.cmp(&y.prim)));
    let (l, r) = refs.split_at(mid);
    let (lb, rb) = (box_of(l), box_of(r));
    finish_split(ctx, refs, nodes, start, bounds, mid, lb, rb, depth, bins, false, pre, parent_count, sink, idx)
}

/// Bins per axis of a binned node of `n` references: at most one per REFS_PER_BIN, at least the
/// tier's `min_bins`, at most its `bins` (see `build_rec`).
#[inline]
pub(super) fn bin_count(p: &BuildParams, n: usize) -> usize {
    p.bins.clamp(2, MAX_BINS).min((n / REFS_PER_BIN).max(p.min_bins.max(2)))
}

/// Bins of `src` binned by `bin` in parallel chunks of `chunk` references and merged (exact:
/// minima, maxima and counts), `k` bins on `axes`.
fn bin_in_chunks(src: &[PrimRef], chunk: usize, k: usize, axes: (usize, usize), bin: impl Fn(&[PrimRef], &mut Bins) + Sync) -> Bins {
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
fn node_binning(p: &BuildParams, cb: &Aabb, k: usize, n: usize) -> Option<(Binning, [f32; 3])> {
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

/// The best binned split: (axis, last left bin, left box, right box, A_L·N_L + A_R·N_R).
#[inline(never)]
fn sweep_bins(bins: &Bins, k: usize, scale: &[f32; 3]) -> Option<(usize, usize, Aabb, Aabb, f32)> {
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
            l_area[b] = half_area_v(lo, hi);
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
            let cost = l_area[b] * lcount as f32 + half_area_v(lo, hi) * rcount as f32;
            let cost = if lcount == 0 || rcount == 0 { f32::NAN } else { cost };
            let take = cost <= ab_cost;
            ab_cost = if take { cost } else { ab_cost };
            ab_bin = if take { b } else { ab_bin };
        }
        if let Some((b, cost)) = (ab_bin != usize::MAX).then_some((ab_bin, ab_cost)) {
            if best.map_or(true, |x| cost < x.2) {
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

const PRIMREF_BYTES: usize = std::mem::size_of::<PrimRef>();

/// Out-of-place stable partition by `sp`: the lefts of `src` in order from `dst[0]`, the
/// rights in order from `dst[rbase]` (bytes). Returns the left count, or None when it is not
/// `nl` (what was written is then garbage; nothing is written outside `dst`). The sides'
/// boxes come from the bins, and no centroid bounds are needed (see `build_rec`).
#[inline(never)]
fn partition_out(src: &[PrimRef], dst: &mut [u8], nl: usize, rbase: usize, sp: &Splitter) -> Option<usize> {
    let n = src.len();
    if nl > n || nl * PRIMREF_BYTES > rbase || dst.len() < rbase + (n - nl) * PRIMREF_BYTES || dst.len() < PRIMREF_BYTES {
        return None;
    }
    // Write offsets are clamped to the last whole reference of `dst`, so the compiler drops
    // the per-store bounds checks; a clamp only matters when the count is not `nl`, and
    // then the result is discarded anyway.
    let cap = dst.len() - PRIMREF_BYTES;
    let (mut li, mut ri) = (0usize, rbase);
    for r in src {
        let left = sp.left(r) as usize;
        let at = if left != 0 { li } else { ri }.min(cap);
        if let Some(d) = dst.get_mut(at..).and_then(|x| x.first_chunk_mut::<PRIMREF_BYTES>()) {
            *d = bytemuck::cast(*r);
        }
        li += PRIMREF_BYTES * left;
        ri += PRIMREF_BYTES * (left ^ 1);
    }
    (li == nl * PRIMREF_BYTES).then_some(nl)
}

/// In-place partition by `sp`; returns the left count.
#[inline(never)]
fn partition_seq(refs: &mut [PrimRef], sp: &Splitter) -> usize {
    let n = refs.len();
    // Partition in place (deterministic: sequential, same bin function as binning).
    // Branchless Lomuto: every reference is swapped with the first right one and
    // the boundary advances by the comparison, so no branch depends on the data.
    let mut i = 0usize;
    for j in 0..n {
        let r = refs[j];
        let left = sp.left(&r);
        // i <= j always (i counts the lefts before j).
        refs[j] = refs[i];
        refs[i] = r;
        i += left as usize;
    }
    i
}

/// Above this many references a node's partition runs in parallel chunks.
const PAR_PART_CUTOFF: usize = 1 << 14;
const _: () = assert!(PAR_BIN_CUTOFF >= PAR_PART_CUTOFF);
/// Chunks of a parallel partition: a fixed count, independent of the thread count.
const PART_CHUNKS: usize = 64;

#[derive(Clone, Copy)]
struct PartStat {
    left: usize,
    l_lo: Vec3A,
    l_hi: Vec3A,
    r_lo: Vec3A,
    r_hi: Vec3A,
}

/// The first `n` references' worth of bytes of `nodes`, viewed as references.
fn node_refs(nodes: &[BinNode], n: usize) -> Option<&[PrimRef]> {
    let bytes: &[u8] = bytemuck::cast_slice(nodes);
    bytemuck::try_cast_slice(bytes.get(..n * std::mem::size_of::<PrimRef>())?).ok()
}
fn node_refs_mut(nodes: &mut [BinNode], n: usize) -> Option<&mut [PrimRef]> {
    let bytes: &mut [u8] = bytemuck::cast_slice_mut(nodes);
    bytemuck::try_cast_slice_mut(bytes.get_mut(..n * std::mem::size_of::<PrimRef>())?).ok()
}

/// Moves a node's references from the start of its node slots into `refs` (parallel copy in
/// the partition's fixed chunks).
fn restore(refs: &mut [PrimRef], nodes: &[BinNode]) {
    let n = refs.len();
    if n < PAR_PART_CUTOFF {
        if let Some(src) = node_refs(nodes, n) {
            refs.copy_from_slice(src);
        }
        return;
    }
    if let Some(src) = node_refs(nodes, n) {
        let chunk = n.div_ceil(PART_CHUNKS).max(1);
        refs.par_chunks_mut(chunk).zip(src.par_chunks(chunk)).for_each(|(d, s)| d.copy_from_slice(s));
    }
}

/// Per-chunk left counts and boxes of a stable partition of `src` (64 fixed chunks); the
/// totals are returned as (left count, left box, right box).
#[allow(clippy::type_complexity)]
fn part_stats(src: &[PrimRef], is_left: &(impl Fn(&PrimRef) -> bool + Sync)) -> (usize, usize, [PartStat; PART_CHUNKS], usize, Aabb, Aabb) {
    let n = src.len();
    let chunk = n.div_ceil(PART_CHUNKS).max(1);
    let (inf, ninf) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let empty = PartStat { left: 0, l_lo: inf, l_hi: ninf, r_lo: inf, r_hi: ninf };
    let mut stats = [empty; PART_CHUNKS];
    src.par_chunks(chunk).zip(stats.par_iter_mut()).for_each(|(c, st)| {
        let mut s = empty;
        for r in c {
            let (lo, hi) = (ref_lo(r), ref_hi(r));
            if is_left(r) {
                s.left += 1;
                s.l_lo = s.l_lo.min(lo);
                s.l_hi = s.l_hi.max(hi);
            } else {
                s.r_lo = s.r_lo.min(lo);
                s.r_hi = s.r_hi.max(hi);
            }
        }
        *st = s;
    });
    let nchunks = n.div_ceil(chunk);
    let nl: usize = stats[..nchunks].iter().map(|s| s.left).sum();
    let mut t = empty;
    for s in &stats[..nchunks] {
        t.l_lo = t.l_lo.min(s.l_lo);
        t.l_hi = t.l_hi.max(s.l_hi);
        t.r_lo = t.r_lo.min(s.r_lo);
        t.r_hi = t.r_hi.max(s.r_hi);
    }
    (chunk, nchunks, stats, nl, to_aabb(t.l_lo, t.l_hi), to_aabb(t.r_lo, t.r_hi))
}

/// Scatter of a stable partition: the lefts of `src` in order into `lout` (nl long), the rights
/// into `rout`, each chunk into its own disjoint range.
fn part_scatter(src: &[PrimRef], chunk: usize, nchunks: usize, stats: &[PartStat; PART_CHUNKS], lout: &mut [PrimRef], rout: &mut [PrimRef], is_left: &(impl Fn(&PrimRef) -> bool + Sync)) {
    let n = src.len();
    let (mut lrest, mut rrest) = (lout, rout);
    let mut outs: [(&mut [PrimRef], &mut [PrimRef]); PART_CHUNKS] = std::array::from_fn(|_| (&mut [][..], &mut [][..]));
    for (k, o) in outs.iter_mut().enumerate().take(nchunks) {
        let len = c_len(n, chunk, k);
        let l = stats[k].left;
        let (lcut, rcut) = (l.min(lrest.len()), (len - l).min(rrest.len()));
        let (lo_part, lr) = std::mem::take(&mut lrest).split_at_mut(lcut);
        let (ro_part, rr) = std::mem::take(&mut rrest).split_at_mut(rcut);
        lrest = lr;
        rrest = rr;
        *o = (lo_part, ro_part);
    }
    src.par_chunks(chunk).zip(outs.par_iter_mut()).for_each(|(c, (lo, ro))| {
        let (mut i, mut j) = (0usize, 0usize);
        for r in c {
            if is_left(r) {
                if let Some(d) = lo.get_mut(i) {
                    *d = *r;
                }
                i += 1;
            } else {
                if let Some(d) = ro.get_mut(j) {
                    *d = *r;
                }
                j += 1;
            }
        }
    });
}

/// Stable partition of `refs` by `is_left` (left ones first, both sides in input order) into
/// the subtree's (still unwritten) node slots: the lefts at the start of the left child's slots
/// (1..2·nl), the rights at the start of the right child's (2·nl..2n-1); each child then finds
/// its references at the start of its own slots (`in_nodes`), and `refs` is left as it was.
/// Returns the left count and the boxes of both sides; with everything on one side
/// the caller must ignore the slots. None (nothing usable moved) when the slots cannot be
/// viewed as references. `one_pass`: sequentially, in one pass (`partition_one_pass`).
fn par_partition_to_nodes(refs: &[PrimRef], nodes: &mut [BinNode], one_pass: bool, is_left: impl Fn(&PrimRef) -> bool + Sync) -> Option<(usize, Aabb, Aabb)> {
    let n = refs.len();
    if one_pass {
        let rest = nodes.get_mut(1..)?;
        if rest.len() < 2 * n - 2 {
            return None;
        }
        let slot = std::mem::size_of::<BinNode>();
        return partition_one_pass(refs, bytemuck::cast_slice_mut(&mut rest[..2 * n - 2]), |nl| (2 * nl).saturating_sub(1) * slot, &is_left);
    }
    let (chunk, nchunks, stats, nl, l, r) = part_stats(refs, &is_left);
    if nl == 0 || nl == n {
        return Some((nl, l, r));
    }
    let rest = nodes.get_mut(1..)?;
    if rest.len() < 2 * n - 2 {
        return None;
    }
    let (lslots, rslots) = rest.split_at_mut(2 * nl - 1);
    let lout = node_refs_mut(lslots, nl)?;
    let rout = node_refs_mut(rslots, n - nl)?;
    part_scatter(refs, chunk, nchunks, &stats, lout, rout, &is_left);
    Some((nl, l, r))
}

/// The same stable partition for a node whose references are at the start of its node slots:
/// scattered straight into `refs`, which then holds all of them (partitioned) in every case.
fn par_partition_from_nodes(refs: &mut [PrimRef], nodes: &[BinNode], one_pass: bool, is_left: impl Fn(&PrimRef) -> bool + Sync) -> Option<(usize, Aabb, Aabb)> {
    let n = refs.len();
    let src = node_refs(nodes, n)?;
    if one_pass {
        return partition_one_pass(src, bytemuck::cast_slice_mut(refs), |nl| nl * PRIMREF_BYTES, &is_left);
    }
    let (chunk, nchunks, stats, nl, l, r) = part_stats(src, &is_left);
    let (lout, rout) = refs.split_at_mut(nl);
    part_scatter(src, chunk, nchunks, &stats, lout, rout, &is_left);
    Some((nl, l, r))
}

/// The stable partition of `par_partition_to_nodes` / `_from_nodes` in one sequential pass
/// (for nodes that have the thread to themselves, `Ctx::one_pass`), where the left count is
/// not known in advance (sampled nodes): lefts ascending from the
/// start of `dst`, rights descending from its last whole reference, then the rights reversed
/// into place from byte `rbase(left count)`. The same order, count and boxes as `part_stats`
/// followed by `part_scatter` (same arithmetic, same branches), so the same bytes for any
/// thread count. Everything on one side still writes `dst`. None when `dst` is too small
/// (what was written is then garbage; `src` is never written).
fn partition_one_pass(src: &[PrimRef], dst: &mut [u8], rbase: impl Fn(usize) -> usize, is_left: &impl Fn(&PrimRef) -> bool) -> Option<(usize, Aabb, Aabb)> {
    let n = src.len();
    let top = dst.len() / PRIMREF_BYTES * PRIMREF_BYTES;
    if top < n * PRIMREF_BYTES {
        return None;
    }
    let (inf, ninf) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let (mut l_lo, mut l_hi, mut r_lo, mut r_hi) = (inf, ninf, inf, ninf);
    let (mut li, mut ri) = (0usize, top);
    for r in src {
        let (lo, hi) = (ref_lo(r), ref_hi(r));
        // Branches, as in `part_stats`: high in the tree the sides come in long runs.
        if is_left(r) {
            if let Some(d) = dst.get_mut(li..).and_then(|x| x.first_chunk_mut::<PRIMREF_BYTES>()) {
                *d = bytemuck::cast(*r);
            }
            li += PRIMREF_BYTES;
            l_lo = l_lo.min(lo);
            l_hi = l_hi.max(hi);
        } else {
            ri -= PRIMREF_BYTES;
            if let Some(d) = dst.get_mut(ri..).and_then(|x| x.first_chunk_mut::<PRIMREF_BYTES>()) {
                *d = bytemuck::cast(*r);
            }
            r_lo = r_lo.min(lo);
            r_hi = r_hi.max(hi);
        }
    }
    let nl = li / PRIMREF_BYTES;
    let nr = n - nl;
    let out = (nl, to_aabb(l_lo, l_hi), to_aabb(r_lo, r_hi));
    if nr == 0 {
        return Some(out);
    }
    let rb = rbase(nl);
    let rend = rb.checked_add(nr * PRIMREF_BYTES).filter(|&e| e <= dst.len())?;
    if rend <= ri {
        // Disjoint (the usual case in node slots): one reversed copy.
        for j in 0..nr {
            let from = top - (j + 1) * PRIMREF_BYTES;
            dst.copy_within(from..from + PRIMREF_BYTES, rb + j * PRIMREF_BYTES);
        }
    } else {
        // Overlapping (always in place when partitioning back into `refs`): reverse where they
        // are, then move.
        let seg: &mut [PrimRef] = bytemuck::try_cast_slice_mut(dst.get_mut(ri..top)?).ok()?;
        seg.reverse();
        if rb != ri {
            dst.copy_within(ri..top, rb);
        }
    }
    Some(out)
}

#[inline]
fn c_len(n: usize, chunk: usize, k: usize) -> usize {
    n.saturating_sub(k * chunk).min(chunk)
}

/// Binned nodes get at most one bin per this many references (at least 8 bins).
const REFS_PER_BIN: usize = 4;

/// Default size up to which nodes use the exact sorted sweep, and the largest allowed.
const SMALL_N: usize = 8;
const MAX_SMALL: usize = 8;

/// f32 bits mapped so that unsigned integer order is the float order (-0 before +0).
#[inline(always)]
fn ordered_bits(f: f32) -> u32 {
    let b = f.to_bits();
    b ^ (((b as i32 >> 31) as u32) | 0x8000_0000)
}

/// A sorting network (compare-exchange pairs) for 8 inputs (19 comparators).
const NET8: [(usize, usize); 19] = [(0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7), (0, 1), (2, 3), (4, 5), (6, 7), (2, 4), (3, 5), (1, 4), (3, 6), (1, 2), (3, 4), (5, 6)];

#[inline(always)]
fn sort_network(v: &mut [u64; MAX_SMALL], net: &[(usize, usize)]) {
    for &(i, j) in net {
        let (x, y) = (v[i & (MAX_SMALL - 1)], v[j & (MAX_SMALL - 1)]);
        v[i & (MAX_SMALL - 1)] = x.min(y);
        v[j & (MAX_SMALL - 1)] = x.max(y);
    }
}

/// The SAH sweep of `small_split` over one sorted order: the best (left count, cost) among
/// the n-1 split positions, lowest position on ties. `S` (n - 1 or more, at most 7) fixes the
/// step count; positions at and past n-1 get a NaN cost, which never wins.
#[inline(always)]
fn small_sweep<const S: usize>(order: &[u8; MAX_SMALL], lo: &[Vec3A; MAX_SMALL], hi: &[Vec3A; MAX_SMALL], w: &[f32; MAX_SMALL], n: usize) -> Option<(usize, f32)> {
    let mut l_area = [0f32; S];
    let mut l_w = [0f32; S];
    let (mut l, mut h) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let mut acc = 0f32;
    for i in 0..S {
        let o = order[i] as usize & (MAX_SMALL - 1);
        l = l.min(lo[o]);
        h = h.max(hi[o]);
        l_area[i] = half_area_v(l, h);
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
        let cost = l_area[i] * left + half_area_v(l, h) * (nf - left);
        let cost = if i + 1 < n { cost } else { f32::NAN };
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
/// A_L·N_L + A_R·N_R), N the sum of `w` (primitives per reference). Ties go to the lowest
/// mask; None only when every cost is NaN.
#[inline(always)]
fn enum_split<const N: usize, const H: usize>(refs: &mut [PrimRef], w_ref: &[f32; MAX_SMALL]) -> Option<(usize, f32)> {
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
        let c = half_area_v(lo[m], hi[m]) * w[m] + half_area_v(lo[r].min(last_lo), hi[r].max(last_hi)) * (w[r] + last_w);
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
#[inline(never)]
fn small_split(refs: &mut [PrimRef], axes: (usize, usize), weighted: bool) -> Option<(usize, f32)> {
    let n = refs.len();
    if !(2..=MAX_SMALL).contains(&n) {
        return None;
    }
    // Primitives per reference (clusters when `weighted`), 0 in unused slots.
    let mut w = [0f32; MAX_SMALL];
    for (x, r) in w.iter_mut().zip(refs.iter()) {
        *x = if weighted { pairs::weight(r) as f32 } else { 1.0 };
    }
    if n == 2 {
        // Both orders give the same split and cost; keep the input order (what the sweep
        // picks on a tie).
        return Some((1, half_area_v(ref_lo(&refs[0]), ref_hi(&refs[0])) * w[0] + half_area_v(ref_lo(&refs[1]), ref_hi(&refs[1])) * w[1]));
    }
    // Three to five references: every bipartition (`enum_split`), which finds a split at least
    // as cheap as the sweeps, in less time than sorting on three axes (dragon FAST_TRACE 2–3 %
    // faster, the same SAH to 0.01). One axis sorts faster from five references on, and four
    // cost the same either way: FAST_BUILD enumerates three and four (SAH 54.98 -> 54.70).
    let enum_max = if axes.1 - axes.0 == 1 { 4 } else { 5 };
    match n {
        3 => return enum_split::<3, 4>(refs, &w),
        4 => return enum_split::<4, 8>(refs, &w),
        5 if n <= enum_max => return enum_split::<5, 16>(refs, &w),
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
        // n - 1 steps: the split positions there are (fewer steps than 7 save 16 % of a
        // three-axis split of six references, 27 % of a one-axis split of five). Three and
        // four references never get here (`enum_split` above).
        let axis_best = match n {
            5 => small_sweep::<4>(&order, &lo, &hi, &w, n),
            6 => small_sweep::<5>(&order, &lo, &hi, &w, n),
            7 => small_sweep::<6>(&order, &lo, &hi, &w, n),
            _ => small_sweep::<7>(&order, &lo, &hi, &w, n),
        };
        // Ties across axes keep the earlier axis; within an axis the sweep keeps the lowest
        // position.
        if let Some((mid, cost)) = axis_best {
            if best.map_or(true, |b| cost < b.2) {
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

#[allow(clippy::too_many_arguments)]
fn finish_split<'a>(ctx: &Ctx, refs: &'a mut [PrimRef], nodes: &'a mut [BinNode], start: u32, bounds: Aabb, mid: usize, left: Aabb, right: Aabb, depth: u32, bins: &mut Bins, in_nodes: bool, pre: &'a mut [u8], parent_count: u32, sink: Option<&mut Vec<Task<'a>>>, idx: usize) -> (f64, u32) {
    let n = refs.len();
    if let Some(slot) = nodes.get_mut(0) {
        *slot = BinNode { lo: bounds.lo, start, hi: bounds.hi, count: n as u32, left_count: mid as u32, reserved: 0 };
    }
    if let Some(sink) = sink {
        // A node of the top of the tree (`build_tree`): its children become tasks; their
        // results and this node's come later, in `top_results`.
        let (lrefs, rrefs) = refs.split_at_mut(mid);
        let rest = nodes.get_mut(1..).unwrap_or(&mut []);
        let lslots = (2 * mid - 1).min(rest.len());
        let (lnodes, rnodes) = rest.split_at_mut(lslots);
        let (lpre, rpre) = pre.split_at_mut((PRE_BYTES_PER_PRIM * mid).min(pre.len()));
        let me = n as u32;
        sink.push(Task { refs: lrefs, nodes: lnodes, start, bounds: left, cb: left, depth: depth + 1, in_nodes, pre: lpre, parent_count: me, idx: idx + 1 });
        sink.push(Task { refs: rrefs, nodes: rnodes, start: start + mid as u32, bounds: right, cb: right, depth: depth + 1, in_nodes, pre: rpre, parent_count: me, idx: idx + 2 * mid });
        return (0.0, 0);
    }
    let (lrefs, rrefs) = refs.split_at_mut(mid);
    let rest = nodes.get_mut(1..).unwrap_or(&mut []);
    let lslots = (2 * mid - 1).min(rest.len());
    let (lnodes, rnodes) = rest.split_at_mut(lslots);
    let rstart = start + mid as u32;
    let area = bounds.half_area() as f64;
    let (lpre, rpre) = pre.split_at_mut((PRE_BYTES_PER_PRIM * mid).min(pre.len()));
    let me = n as u32;
    let (a, b) = if n as u32 >= ctx.params.parallel_cutoff {
        rayon::join(
            || build_rec(ctx, lrefs, lnodes, start, left, left, depth + 1, bins, in_nodes, lpre, me, None, 0),
            || build_rec(ctx, rrefs, rnodes, rstart, right, right, depth + 1, &mut Bins::new(), in_nodes, rpre, me, None, 0),
        )
    } else {
        (
            build_rec(ctx, lrefs, lnodes, start, left, left, depth + 1, bins, in_nodes, lpre, me, None, 0),
            build_rec(ctx, rrefs, rnodes, rstart, right, right, depth + 1, bins, in_nodes, rpre, me, None, 0),
        )
    };
    // Wide-subtree size if this node becomes a BVH4 node (kept in `reserved`), needed above
    // the cut roots only: emission hands disjoint output ranges to threads from it. A cut
    // root's wide subtree is encoded now, while its binary nodes are in cache, sequentially
    // into its own range of the pre-emission area (the final pass copies the block into
    // place); its size is what that wrote, or a count when it did not fit.
    let w = if n as u32 > EMIT_CUT {
        wide_reserved(nodes)
    } else if is_cut(parent_count, n as u32) {
        let mut cursor = 0u32;
        let mut leaves = 0u32;
        match emit_seq(nodes, 0, pre, 0, &mut cursor, &mut leaves, None) {
            Some(_) => cursor,
            None => wide_count(nodes, 0),
        }
    } else {
        0
    };
    if let Some(slot) = nodes.get_mut(0) {
        slot.reserved = w;
    }
    (area + a.0 + b.0, 1 + a.1.max(b.1))
}

/// The wide-subtree size of the node at `nodes[0]` above the cut roots (see `finish_split`):
/// one wide node plus its internal children's sizes.
fn wide_reserved(nodes: &[BinNode]) -> u32 {
    let (ch, cnt, _) = wide_children(nodes, 0);
    let mut w = 1u32;
    for &c in &ch[..cnt] {
        if let Some(nd) = nodes.get(c) {
            if nd.left_count != 0 {
                w = w.saturating_add(nd.reserved);
            }
        }
    }
    w
}

/// A node whose subtree is still to be built: `build_rec`'s arguments, and its slot in the
/// whole tree's node array.
struct Task<'a> {
    refs: &'a mut [PrimRef],
    nodes: &'a mut [BinNode],
    start: u32,
    bounds: Aabb,
    cb: Aabb,
    depth: u32,
    in_nodes: bool,
    pre: &'a mut [u8],
    parent_count: u32,
    idx: usize,
}

const _: () = assert!(PAR_BIN_CUTOFF as u64 > EMIT_CUT as u64);

/// Builds the tree over `refs` (see `build_rec`): the same nodes in the same slots, the same
/// sums, for any thread count. On more than one thread it runs in two phases. First the top
/// of the tree (`Ctx::top`: nodes that bin a sample and partition in parallel chunks, since
/// there are fewer nodes of their size than threads): each top node is a task that splits
/// its node and spawns its top children as tasks; its other children are set aside. Then
/// every set-aside subtree is built as a task of its own, largest first; none of their
/// nodes forks inside its binning or partition. The top nodes' SAH sums, depths and wide
/// sizes follow from their children's afterwards (`top_results`), added in the order
/// `finish_split` adds them.
///
/// Why not recursion all the way down: a thread waiting inside a top node's parallel
/// partition or sampled binning (`rayon::join`) steals whatever task is queued, and once
/// subtrees exist that is often a whole subtree, milliseconds of work; the top node's
/// partition, and with it the next subtrees, waits until that is done. Timed on the 16-core
/// machine (dragon, 16 threads), the subtrees started in waves, each when the last had ended,
/// with 5–12 of the 16 threads at work. In the first phase only top-node work is queued; in
/// the second every thread has subtrees to take and nothing waits on a fork but the joins
/// that sum a subtree. Dragon, 16 threads, interleaved rounds of 30 builds (medians): with
/// the top cut at 16,384 references, FAST_BUILD 16.6–18.9 → 15.1–17.1 ms, FAST_TRACE
/// 34.3–36.0 → 30.5–31.6 ms; cut where nodes stop forking (this), against that, FAST_BUILD
/// 19.1–19.3 → 17.6–20.0, FAST_TRACE 35.8–37.6 → 32.9–35.9 on a slower instance.
fn build_tree(ctx: &Ctx, refs: &mut [PrimRef], nodes: &mut [BinNode], bounds: Aabb, cb: Aabb, in_nodes: bool, pre: &mut [u8]) -> (f64, u32) {
    if ctx.threads <= 1 || !ctx.top(refs.len()) {
        return build_rec(ctx, refs, nodes, 0, bounds, cb, 0, &mut Bins::new(), in_nodes, pre, u32::MAX, None, 0);
    }
    let root = Task { refs, nodes: &mut *nodes, start: 0, bounds, cb, depth: 0, in_nodes, pre, parent_count: u32::MAX, idx: 0 };
    let done = run_tasks(ctx, vec![root]);
    top_results(nodes, 0, &done)
}

/// Builds the subtrees of `tasks` (disjoint parts of one tree whose nodes above them are
/// written) and returns (node slot, SAH sum and depth) of each subtree root not split by
/// `split_top`, sorted by slot, for `top_results`: on one thread one after the other,
/// otherwise in `build_tree`'s two phases.
fn run_tasks(ctx: &Ctx, tasks: Vec<Task<'_>>) -> Vec<(usize, (f64, u32))> {
    let mut done: Vec<(usize, (f64, u32))>;
    if ctx.threads <= 1 {
        done = tasks.into_iter().map(|t| (t.idx, build_rec(ctx, t.refs, t.nodes, t.start, t.bounds, t.cb, t.depth, &mut Bins::new(), t.in_nodes, t.pre, t.parent_count, None, t.idx))).collect();
    } else {
        let finished = Mutex::new(Vec::new());
        let below = Mutex::new(Vec::new());
        let (fin, bel) = (&finished, &below);
        rayon::scope(|s| {
            for t in tasks {
                if ctx.top(t.refs.len()) {
                    s.spawn(move |s| split_top(s, ctx, t, fin, bel));
                } else if let Ok(mut b) = bel.lock() {
                    b.push(t);
                }
            }
        });
        let mut subtrees = below.into_inner().unwrap_or_default();
        subtrees.sort_by_key(|t| (std::cmp::Reverse(t.refs.len()), t.idx));
        // (node slot, SAH sum and depth) of every subtree not split in the first phase.
        done = finished.into_inner().unwrap_or_default();
        done.par_extend(subtrees.into_par_iter().with_max_len(1).map(|t| (t.idx, build_rec(ctx, t.refs, t.nodes, t.start, t.bounds, t.cb, t.depth, &mut Bins::new(), t.in_nodes, t.pre, t.parent_count, None, t.idx))));
    }
    done.sort_by_key(|d| d.0);
    done
}

/// One top node of `build_tree`: splits it, spawns its top children as tasks, and sets the
/// others aside in `below` (a node that ends as a leaf goes to `finished` with its result).
fn split_top<'s, 'a: 's>(s: &rayon::Scope<'s>, ctx: &'s Ctx, t: Task<'a>, finished: &'s Mutex<Vec<(usize, (f64, u32))>>, below: &'s Mutex<Vec<Task<'a>>>) {
    let mut sink = Vec::new();
    let r = build_rec(ctx, t.refs, t.nodes, t.start, t.bounds, t.cb, t.depth, &mut Bins::new(), t.in_nodes, t.pre, t.parent_count, Some(&mut sink), t.idx);
    if sink.is_empty() {
        if let Ok(mut f) = finished.lock() {
            f.push((t.idx, r));
        }
    }
    for c in sink {
        if ctx.top(c.refs.len()) {
            s.spawn(move |s| split_top(s, ctx, c, finished, below));
        } else if let Ok(mut b) = below.lock() {
            b.push(c);
        }
    }
}

/// SAH sum and depth of the subtree at slot `i` of a tree built by `build_tree`: a task's
/// result, or for a top node its area plus its children's, as `finish_split` adds them,
/// setting its wide size on the way.
fn top_results(nodes: &mut [BinNode], i: usize, done: &[(usize, (f64, u32))]) -> (f64, u32) {
    if let Ok(k) = done.binary_search_by_key(&i, |d| d.0) {
        return done[k].1;
    }
    let Some((l, r)) = bin_children(nodes, i) else { return (0.0, 0) };
    let (a, b) = (top_results(nodes, l, done), top_results(nodes, r, done));
    let Some(sub) = nodes.get_mut(i..).filter(|s| !s.is_empty()) else { return (0.0, 0) };
    let w = wide_reserved(sub);
    sub[0].reserved = w;
    let area = Aabb { lo: sub[0].lo, hi: sub[0].hi }.half_area() as f64;
    (area + a.0 + b.0, 1 + a.1.max(b.1))
}

/// Subtrees of at most this many primitives whose parent is larger ("cut roots") are encoded
/// into wide nodes as soon as they are built (see `finish_split`), and the wide collapse never
/// opens a cut root, so each one is the root of a wide subtree.
const EMIT_CUT: u32 = 4096;
/// Bytes of the pre-emission area per primitive: a cut root over k primitives owns
/// PRE_BYTES_PER_PRIM·k bytes of it, enough for its wide nodes in every ordinary tree
/// (3k/8 nodes; FAST_TRACE makes about k/4). Larger subtrees are emitted by the final pass.
const PRE_BYTES_PER_PRIM: usize = 24;

#[inline]
fn is_cut(parent_count: u32, count: u32) -> bool {
    count <= EMIT_CUT && parent_count > EMIT_CUT
}

/// The byte range of cut root `nd`'s pre-emitted block in the pre-emission area of `pre_len`
/// bytes, if it was pre-emitted (the same test `finish_split` made).
fn pre_block(nd: &BinNode, pre_len: usize) -> Option<std::ops::Range<usize>> {
    let lo = PRE_BYTES_PER_PRIM.checked_mul(nd.start as usize)?;
    let hi = PRE_BYTES_PER_PRIM.checked_mul(nd.start as usize + nd.count as usize)?.min(pre_len);
    let len = nd.reserved as usize * NODE_SIZE;
    (nd.left_count != 0 && lo.checked_add(len)? <= hi).then_some(lo..lo + len)
}

/// Copies a pre-emitted block (local indices) to wide index `base`; returns its leaf children.
/// With `map` (paired builds) leaf children are turned from references into primitives
/// (`leaf_span`), which the block was encoded without.
fn copy_block(src: &[u8], out: &mut [u8], base: u32, map: Option<&[u32]>) -> u32 {
    let mut leaves = 0;
    out.copy_from_slice(src);
    for node in out.chunks_exact_mut(NODE_SIZE) {
        for c in 0..4 {
            let kind = node[56 + c];
            let at = 40 + 4 * c;
            let v = u32::from_le_bytes([node[at], node[at + 1], node[at + 2], node[at + 3]]);
            if kind == CHILD_INTERNAL {
                node[at..at + 4].copy_from_slice(&v.wrapping_add(base).to_le_bytes());
            } else if kind != 0 {
                leaves += 1;
                if map.is_some() {
                    let (first, count) = leaf_span(v, kind as u32, map);
                    node[at..at + 4].copy_from_slice(&first.to_le_bytes());
                    node[56 + c] = count.min(254) as u8;
                }
            }
        }
    }
    leaves
}

/// A leaf's first primitive and primitive count from its first reference and reference count:
/// the same numbers unpaired, through the prefix `map` of primitives per reference when paired.
#[inline]
fn leaf_span(start: u32, count: u32, map: Option<&[u32]>) -> (u32, u32) {
    match map {
        None => (start, count),
        Some(m) => {
            let a = m.get(start as usize).copied().unwrap_or(0);
            let b = m.get(start.saturating_add(count) as usize).copied().unwrap_or(a);
            (a, b.saturating_sub(a))
        }
    }
}

/// Binary children of a binary node: (left slot, right slot), for an internal node.
#[inline]
fn bin_children(nodes: &[BinNode], i: usize) -> Option<(usize, usize)> {
    let n = nodes.get(i)?;
    if n.left_count == 0 {
        return None;
    }
    Some((i + 1, i + 2 * n.left_count as usize))
}

/// The ≤4 binary subtrees that become the children of the wide node made from binary node `i`:
/// repeatedly open the internal child with the largest area (ties: lowest slot), never a cut
/// root (`is_cut`). The mask has bit k set when child k is a cut root.
pub fn wide_children(nodes: &[BinNode], i: usize) -> ([usize; 4], usize, u8) {
    let mut ch = [0usize; 4];
    let Some((l, r)) = bin_children(nodes, i) else {
        ch[0] = i;
        return (ch, 1, 0);
    };
    let cnt_of = |s: usize| nodes.get(s).map_or(0, |n| n.count);
    let root_count = cnt_of(i);
    ch[0] = l;
    ch[1] = r;
    let mut cut = [is_cut(root_count, cnt_of(l)), is_cut(root_count, cnt_of(r)), false, false];
    let mut count = 2;
    while count < 4 {
        let mut best: Option<(usize, f32)> = None;
        for (k, &c) in ch[..count].iter().enumerate() {
            if let Some(nd) = nodes.get(c) {
                if nd.left_count != 0 && !cut[k] {
                    let a = Aabb { lo: nd.lo, hi: nd.hi }.half_area();
                    if best.map_or(true, |b| a > b.1) {
                        best = Some((k, a));
                    }
                }
            }
        }
        let Some((k, _)) = best else { break };
        let Some((l, r)) = bin_children(nodes, ch[k]) else { break };
        let pc = cnt_of(ch[k]);
        ch[k] = l;
        cut[k] = is_cut(pc, cnt_of(l));
        ch[count] = r;
        cut[count] = is_cut(pc, cnt_of(r));
        count += 1;
    }
    let mask = cut.iter().enumerate().fold(0u8, |m, (k, &c)| m | (c as u8) << k);
    (ch, count, mask)
}

/// Quantise child boxes into the frame of `node_box`, rounding outward and verifying with the
/// exact decode arithmetic of `WideNode::child_box`, so decoded boxes always contain the input.
/// The child boxes come as vectors (slots past `cnt` hold the node's lo corner): each axis'
/// four values come from one transpose in registers, where gathering them through a stack
/// array stalled on store-to-load forwarding.
#[inline]
pub fn encode_node_v(node_box: &Aabb, clo: &[Vec3A; 4], chi: &[Vec3A; 4], cnt: usize, child: &[u32], kind: &[u8]) -> WideNode {
    let cnt = cnt.min(4);
    let col = |v: Vec3A| Vec4::from((v, 0.0));
    let tlo = glam::Mat4::from_cols(col(clo[0]), col(clo[1]), col(clo[2]), col(clo[3])).transpose();
    let thi = glam::Mat4::from_cols(col(chi[0]), col(chi[1]), col(chi[2]), col(chi[3])).transpose();
    let mut n = WideNode::zeroed();
    n.origin = node_box.lo;
    for a in 0..3 {
        let lo = node_box.lo[a];
        let hi = node_box.hi[a];
        let ext = (hi - lo).max(0.0);
        // Smallest power of two s with lo + 255*s >= hi, found from the extent then verified.
        let mut e: u32 = if ext > 0.0 && ext.is_finite() {
            ((ext * (1.0 / 255.0)).to_bits() >> 23 & 0xff).max(1)
        } else if ext > 0.0 {
            254
        } else {
            1
        };
        // Usually `e` already fits or the next one does: two explicit steps before the general
        // loop, which the compiler otherwise turned into a 16-wide search with a serial
        // byte-by-byte reduction (a third of the node's encoding time).
        let short = |e: u32| e < 254 && lo + 255.0 * f32::from_bits(e << 23) < hi;
        if short(e) {
            e += 1;
            if short(e) {
                e += 1;
                while short(e) {
                    e += 1;
                }
            }
        }
        n.exp[a] = e as u8;
        let s = f32::from_bits(e << 23);
        let inv_s = 1.0 / s; // exact: s is a power of two
        let dec = |q: u32| lo + q as f32 * s;
        // Four children at once: truncated guesses (clamped in float first: the same values as
        // the scalar `(x as u32).min(255)` for x > 0, else 0), checked with the decode
        // arithmetic lane-wise (same IEEE operations as `dec`); lanes that need a step (rare)
        // take the scalar path below.
        let (blo, bhi) = (tlo.col(a), thi.col(a));
        let (lov, sv, top) = (Vec4::splat(lo), Vec4::splat(s), Vec4::splat(255.0));
        // floor of values clamped to [0, 255] is the truncation `as u32` would give, already
        // as a float (no conversions until the final byte extraction).
        let qlf = floor_pos(((blo - lov) * inv_s).max(Vec4::ZERO).min(top));
        let q0 = floor_pos(((bhi - lov) * inv_s).max(Vec4::ZERO).min(top));
        let bad_l = (lov + qlf * sv).cmpgt(blo) & qlf.cmpgt(Vec4::ZERO);
        // The scalar search steps qh up from the truncated guess to the first value whose
        // decode reaches b.hi: usually the guess itself or the next one.
        let q1 = (q0 + Vec4::ONE).min(top);
        let ok0 = (lov + q0 * sv).cmpge(bhi) | q0.cmpge(top);
        let ok1 = (lov + q1 * sv).cmpge(bhi) | q1.cmpge(top);
        let qh = Vec4::select(ok0, q0, q1);
        let bad_h = !(ok0 | ok1);
        if !bad_l.any() && !bad_h.any() {
            // Integers below 2^23 read from the mantissa after adding 2^23 (exact).
            let magic = Vec4::splat(8_388_608.0);
            let (ql, qh) = ((qlf + magic).to_array(), (qh + magic).to_array());
            for c in 0..cnt {
                n.qlo[a][c] = ql[c].to_bits() as u8;
                n.qhi[a][c] = qh[c].to_bits() as u8;
            }
            continue;
        }
        for c in 0..cnt {
            // Guesses by truncation, then made exact and outward with the decode arithmetic
            // (usually zero or one step).
            let (bl, bh) = (clo[c][a], chi[c][a]);
            let x = (bl - lo) * inv_s;
            let mut ql = if x > 0.0 { (x as u32).min(255) } else { 0 };
            while ql > 0 && dec(ql) > bl {
                ql -= 1;
            }
            let y = (bh - lo) * inv_s;
            let mut qh = if y > 0.0 { (y as u32).min(255) } else { 0 };
            while qh < 255 && dec(qh) < bh {
                qh += 1;
            }
            n.qlo[a][c] = ql as u8;
            n.qhi[a][c] = qh as u8;
        }
    }
    n.child_count = cnt as u8;
    for c in 0..cnt {
        n.child[c] = child.get(c).copied().unwrap_or(0);
        n.kind[c] = kind.get(c).copied().unwrap_or(0);
    }
    n
}

/// Wide nodes of a subtree in preorder; `W` of an internal binary node is in `reserved`.
pub fn wide_size(nodes: &[BinNode]) -> u32 {
    match nodes.first() {
        Some(n) if n.left_count != 0 => n.reserved,
        Some(_) => 1,
        None => 0,
    }
}

/// One pending subtree emission: binary subtree (slice rooted at its node), its wide index,
/// exactly its output range, the pre-emission area, and whether it is a cut root to encode
/// sequentially (`emit_seq`: its inner nodes carry no sizes) rather than by `emit_wide`.
type EmitTask<'a> = Option<(&'a [BinNode], u32, &'a mut [u8], Option<&'a [u8]>, bool)>;
const PAR_EMIT_CUTOFF: u32 = 1024;

fn run_emit(tasks: &mut [EmitTask<'_>], map: Option<&[u32]>) -> u32 {
    match tasks.len() {
        0 => 0,
        1 => match tasks[0].take() {
            Some((n, me, out, _, true)) => {
                let (mut cursor, mut l) = (0u32, 0u32);
                let _ = emit_seq(n, 0, out, me, &mut cursor, &mut l, map);
                l
            }
            Some((n, me, out, pre, false)) => emit_wide(n, me, out, pre, map),
            None => 0,
        },
        len => {
            let size: u32 = tasks.iter().map(|t| t.as_ref().map_or(0, |t| wide_size(t.0))).sum();
            let (a, b) = tasks.split_at_mut(len / 2);
            if size >= PAR_EMIT_CUTOFF {
                let (x, y) = rayon::join(|| run_emit(a, map), || run_emit(b, map));
                x + y
            } else {
                run_emit(a, map) + run_emit(b, map)
            }
        }
    }
}

/// The wide node made from binary node `i` (its children from `wide_children`): leaf children
/// point at their primitives, and `internal(slot, node, is_cut_root)` gives each internal
/// child's node index, in child order (emission in preorder). Returns the node and its leaf
/// children; None when `internal` does.
fn wide_node(nodes: &[BinNode], i: usize, map: Option<&[u32]>, mut internal: impl FnMut(usize, &BinNode, bool) -> Option<u32>) -> Option<(WideNode, u32)> {
    let (ch, cnt, cut) = wide_children(nodes, i);
    let cnt = cnt.min(4);
    // Child boxes as vectors loaded straight from the (long since written) binary nodes.
    let mut clo = [Vec3A::ZERO; 4];
    let mut chi = [Vec3A::ZERO; 4];
    let mut child = [0u32; 4];
    let mut kind = [0u8; 4];
    let (mut nlo, mut nhi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let mut leaves = 0u32;
    for k in 0..cnt {
        let nd = nodes.get(ch[k])?;
        (clo[k], chi[k]) = (Vec3A::from(nd.lo), Vec3A::from(nd.hi));
        nlo = nlo.min(clo[k]);
        nhi = nhi.max(chi[k]);
        if nd.left_count != 0 && ch[k] != i {
            kind[k] = CHILD_INTERNAL;
            child[k] = internal(ch[k], nd, cut >> k & 1 != 0)?;
        } else {
            let (first, count) = leaf_span(nd.start, nd.count, map);
            kind[k] = count.min(254) as u8;
            child[k] = first;
            leaves += 1;
        }
    }
    for k in cnt..4 {
        (clo[k], chi[k]) = (nlo, nlo);
    }
    Some((encode_node_v(&to_aabb(nlo, nhi), &clo, &chi, cnt, &child, &kind), leaves))
}

/// Emits the wide subtree of binary node `i` (inside a cut subtree: no cut roots below it) in
/// preorder at local index `*cursor` onwards of `out`, child indices offset by `base`; the
/// same bytes `emit_wide` writes, without needing subtree sizes in advance. Counts leaf
/// children into `leaves`; None when `out` is too small (what was written is then garbage).
fn emit_seq(nodes: &[BinNode], i: usize, out: &mut [u8], base: u32, cursor: &mut u32, leaves: &mut u32, map: Option<&[u32]>) -> Option<u32> {
    let me = *cursor;
    *cursor += 1;
    let at = me as usize * NODE_SIZE;
    if at + NODE_SIZE > out.len() {
        return None;
    }
    let (wn, l) = wide_node(nodes, i, map, |slot, _, _| emit_seq(nodes, slot, out, base, cursor, leaves, map).map(|c| base + c))?;
    *leaves += l;
    out.get_mut(at..at + NODE_SIZE)?.copy_from_slice(bytemuck::bytes_of(&wn));
    Some(me)
}

/// Wide nodes of binary node `i`'s wide subtree (inside a cut subtree), by counting.
fn wide_count(nodes: &[BinNode], i: usize) -> u32 {
    let (ch, cnt, _) = wide_children(nodes, i);
    let mut w = 1u32;
    for &c in &ch[..cnt] {
        if nodes.get(c).is_some_and(|nd| nd.left_count != 0) && c != i {
            w = w.saturating_add(wide_count(nodes, c));
        }
    }
    w
}

/// Emits the wide node made from the binary subtree rooted at `nodes[0]` as node `me` into
/// `out[..64]` and its descendants (preorder) after it; returns the number of leaf children.
/// Child indices follow from subtree sizes, never from timing: same bytes for any thread count.
/// With `pre`, cut-root children whose blocks were pre-emitted are copied from there (the
/// same bytes the recursion would write).
fn emit_wide(nodes: &[BinNode], me: u32, out: &mut [u8], pre: Option<&[u8]>, map: Option<&[u32]>) -> u32 {
    let mut next = me + 1;
    let mut pending: [(usize, u32, u32, bool); 4] = [(0, 0, 0, false); 4];
    let mut np = 0;
    let Some((wn, mut leaves)) = wide_node(nodes, 0, map, |slot, nd, is_cut_root| {
        let idx = next;
        pending[np] = (slot, idx, nd.reserved, is_cut_root);
        np += 1;
        next = next.saturating_add(nd.reserved);
        Some(idx)
    }) else {
        return 0;
    };
    let (head, mut rest) = out.split_at_mut(NODE_SIZE.min(out.len()));
    if head.len() == NODE_SIZE {
        head.copy_from_slice(bytemuck::bytes_of(&wn));
    }
    let mut tasks: [EmitTask<'_>; 4] = [None, None, None, None];
    let mut nt = 0;
    for &(rel, idx, w, is_cut_root) in &pending[..np] {
        let len = (w as usize * NODE_SIZE).min(rest.len());
        let (mine, others) = std::mem::take(&mut rest).split_at_mut(len);
        rest = others;
        if is_cut_root {
            // Inner nodes of a cut subtree carry no sizes: its block is copied, or encoded
            // here sequentially into its exact range.
            if let (Some(pre), Some(nd)) = (pre, nodes.get(rel)) {
                if let Some(src) = pre_block(nd, pre.len()).and_then(|r| pre.get(r)) {
                    if src.len() == mine.len() {
                        leaves += copy_block(src, mine, idx, map);
                        continue;
                    }
                }
            }
            // Without a usable block (builds that stage nothing, such as every TLAS, have no
            // pre-emission area) it is a task like the others, so that sibling cut roots are
            // encoded in parallel.
            tasks[nt] = nodes.get(rel..).map(|n| (n, idx, mine, pre, true));
            nt += 1;
            continue;
        }
        tasks[nt] = nodes.get(rel..).map(|n| (n, idx, mine, pre, false));
        nt += 1;
    }
    leaves + run_emit(&mut tasks[..nt], map)
}

/// FNV-style 64-bit hash over the index bytes, word at a time (the update's index check).
pub fn index_hash(g: &Geometry) -> [u32; 2] {
    let GeometryData::Triangles { index_type, indices, .. } = g.data else { return [0, 0] };
    let len = (g.primitive_count as u64 * 3 * index_type.size() as u64).min(indices.len() as u64) as usize;
    let bytes = &indices[..len];
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut chunks = bytes.chunks_exact(8);
    for c in &mut chunks {
        let mut w = [0u8; 8];
        w.copy_from_slice(c);
        h = (h ^ u64::from_le_bytes(w)).wrapping_mul(0x0000_0100_0000_01b3);
    }
    for &b in chunks.remainder() {
        h = (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3);
    }
    h = (h ^ len as u64).wrapping_mul(0x0000_0100_0000_01b3);
    [h as u32, (h >> 32) as u32]
}

/// Reads primitive `p` of geometry `gi` as a reference; None = not stored (inactive, or a
/// degenerate triangle that may be dropped).
pub fn make_ref(gi: u32, g: &Geometry, p: u32, view: &dyn DeviceView, allow_update: bool) -> Result<Option<PrimRef>, BuildError> {
    Ok(make_ref_data(gi, g, p, view, allow_update)?.map(|x| x.0))
}

/// `make_ref` plus the primitive data the format stores (vertices, or the AABB).
pub fn make_ref_data(gi: u32, g: &Geometry, p: u32, view: &dyn DeviceView, allow_update: bool) -> Result<Option<(PrimRef, [f32; 9])>, BuildError> {
    let mut data = [0f32; 9];
    let (lo, hi) = match g.data {
        GeometryData::Triangles { .. } => {
            let Some(v) = read_triangle(gi, g, p)? else { return Ok(None) };
            if !allow_update {
                // Degenerate (zero-area) triangles produce no hits; dropping them is allowed
                // only when a later update cannot make them non-degenerate.
                let n = (v[1] - v[0]).cross(v[2] - v[0]);
                if n == Vec3::ZERO {
                    return Ok(None);
                }
            } else {
                // Repeated indices may always be dropped: an update cannot change indices.
                let idx = input::triangle_indices(gi, g, p)?;
                if idx[0] == idx[1] || idx[1] == idx[2] || idx[0] == idx[2] {
                    if !matches!(g.data, GeometryData::Triangles { index_type: super::IndexType::None, .. }) {
                        return Ok(None);
                    }
                }
            }
            data = [v[0].x, v[0].y, v[0].z, v[1].x, v[1].y, v[1].z, v[2].x, v[2].y, v[2].z];
            triangle_bounds(&v)
        }
        GeometryData::Aabbs { .. } => {
            let Some(b) = read_aabb(gi, g, p)? else { return Ok(None) };
            data[..6].copy_from_slice(&b);
            sanitize([b[0], b[1], b[2]], [b[3], b[4], b[5]])
        }
        GeometryData::Instances { .. } => {
            let Some(inst) = read_instance(gi, g, p, view)? else { return Ok(None) };
            instance_bounds(&inst.transform, inst.reference, view)
        }
    };
    Ok(Some((PrimRef { lo, geom: gi, hi, prim: p }, data)))
}

/// Triangles with plain f32 positions (R32G32B32_SFLOAT, or R32G32B32A32_SFLOAT whose first
/// three floats are the same), U32 or U16 indices and no transform: the common input, read with
/// direct little-endian loads instead of the generic per-format decode. Gives exactly what
/// `make_ref_data` gives; anything out of range falls back to it (which reports the error).
pub(super) struct FastTris<'a> {
    vertices: &'a [u8],
    indices: &'a [u8],
    stride: usize,
    size: usize,
    max_vertex: u32,
    u16_indices: bool,
}

impl<'a> FastTris<'a> {
    pub(super) fn of(g: &Geometry<'a>) -> Option<Self> {
        use super::{IndexType, VertexFormat};
        let GeometryData::Triangles { format, vertices, stride, max_vertex, index_type, indices, transform: None } = g.data else { return None };
        if !matches!(format, VertexFormat::R32G32B32Sfloat | VertexFormat::R32G32B32A32Sfloat) {
            return None;
        }
        let u16_indices = match index_type {
            IndexType::U16 => true,
            IndexType::U32 => false,
            IndexType::None => return None,
        };
        Some(FastTris { vertices, indices, stride: usize::try_from(stride).ok()?, size: format.size() as usize, max_vertex, u16_indices })
    }

    #[inline(always)]
    fn vertex(&self, i: u32) -> Option<Vec3A> {
        let o = (i as usize).checked_mul(self.stride)?;
        let b = self.vertices.get(o..o.checked_add(self.size)?)?;
        // A fixed-size view: the twelve byte reads need no bounds checks.
        let (b, _) = b.split_first_chunk::<12>()?;
        Some(Vec3A::new(
            f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
            f32::from_le_bytes([b[4], b[5], b[6], b[7]]),
            f32::from_le_bytes([b[8], b[9], b[10], b[11]]),
        ))
    }

    /// Vertex indices and positions of triangle `p`; None when an index or vertex is out of range.
    #[inline(always)]
    pub(super) fn read(&self, p: u32) -> Option<([u32; 3], [Vec3A; 3])> {
        let idx = self.indices(p)?;
        Some((idx, self.positions(idx)?))
    }

    /// The vertex indices of triangle `p` (what `read` gives first); None when out of range.
    #[inline(always)]
    pub(super) fn indices(&self, p: u32) -> Option<[u32; 3]> {
        let idx = if self.u16_indices {
            let o = (p as usize).checked_mul(6)?;
            let (b, _) = self.indices.get(o..)?.split_first_chunk::<6>()?;
            [u16::from_le_bytes([b[0], b[1]]) as u32, u16::from_le_bytes([b[2], b[3]]) as u32, u16::from_le_bytes([b[4], b[5]]) as u32]
        } else {
            let o = (p as usize).checked_mul(12)?;
            let (b, _) = self.indices.get(o..)?.split_first_chunk::<12>()?;
            [
                u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                u32::from_le_bytes([b[4], b[5], b[6], b[7]]),
                u32::from_le_bytes([b[8], b[9], b[10], b[11]]),
            ]
        };
        if idx[0] > self.max_vertex || idx[1] > self.max_vertex || idx[2] > self.max_vertex {
            return None;
        }
        Some(idx)
    }

    /// Prefetches the vertices of triangle `p` (ingest runs this PREFETCH_AHEAD triangles
    /// ahead: indices come in order, vertices at random).
    #[inline(always)]
    fn prefetch(&self, p: u32) {
        if let Some(idx) = self.indices(p) {
            for i in idx {
                if let Some(o) = (i as usize).checked_mul(self.stride) {
                    crate::memory::prefetch_read(self.vertices, o);
                }
            }
        }
    }

    /// The positions of vertices `idx` (what `read` gives second); None when out of range.
    #[inline(always)]
    pub(super) fn positions(&self, idx: [u32; 3]) -> Option<[Vec3A; 3]> {
        Some([self.vertex(idx[0])?, self.vertex(idx[1])?, self.vertex(idx[2])?])
    }

    /// What `make_ref_data` gives for this geometry, as (lo, hi, vertices) in registers for
    /// `ingest` to store directly (a data array built on the stack and copied out stalled
    /// every triangle on a failed store-to-load forward); outer None = use the general path.
    #[inline(always)]
    fn bounds(&self, p: u32, allow_update: bool) -> Option<Option<(Vec3A, Vec3A, [Vec3A; 3])>> {
        let (idx, [a, b, c]) = self.read(p)?;
        if a.x.is_nan() || b.x.is_nan() || c.x.is_nan() {
            return Some(None);
        }
        if !allow_update {
            if (b - a).cross(c - a) == Vec3A::ZERO {
                return Some(None);
            }
        } else if idx[0] == idx[1] || idx[1] == idx[2] || idx[0] == idx[2] {
            return Some(None);
        }
        let (lo, hi) = triangle_box(a, b, c);
        Some(Some((lo, hi, [a, b, c])))
    }
}

/// `triangle_bounds` of vertices in registers: when every lane is finite (v - v is 0 for finite
/// v, NaN for NaN and inf, and NaN survives the sums) vector min/max are exact; otherwise the
/// sanitising path. A max of the |v| would not do: maxps drops a NaN operand, which would hide
/// a NaN y or z from the huge box.
#[inline(always)]
pub(super) fn triangle_box(a: Vec3A, b: Vec3A, c: Vec3A) -> (Vec3A, Vec3A) {
    if ((a - a) + (b - b) + (c - c)).cmpeq(Vec3A::ZERO).all() {
        return (a.min(b).min(c), a.max(b).max(c));
    }
    let (lo, hi) = triangle_bounds(&[a.into(), b.into(), c.into()]);
    (Vec3A::from(lo), Vec3A::from(hi))
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
/// arithmetic as `bounds_of`; min/max do not depend on order).
#[derive(Clone, Copy)]
struct ChunkSum {
    /// Reference slots freed (dropped primitives, and the second primitives of pairs).
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

pub const INGEST_CHUNK: usize = 4096;
/// Ingest chunk of instance geometries (see `ingest`).
const INGEST_CHUNK_INSTANCES: usize = 256;

/// The ingest chunk of geometry `g`'s primitives: an instance costs far more than a triangle
/// (record decode, BLAS bounds, eight transformed corners), so instances go in smaller chunks
/// (a 10,000-instance TLAS is then more than three tasks).
fn ingest_chunk(g: &Geometry) -> usize {
    if matches!(g.data, GeometryData::Instances { .. }) { INGEST_CHUNK_INSTANCES } else { INGEST_CHUNK }
}

/// Staged primitive data: what the format stores plus the primitive's index in its geometry.
pub const STAGE_SIZE: usize = 40;
/// The leaf-data gathers prefetch the stage record this many records ahead of the one they
/// copy. Dragon FAST_BUILD, one thread, this box (minimum ms, two rounds): none 106.7 / 105.2,
/// 8 ahead 104.4 / 104.9, 16 104.9 / 103.1, 32 102.0 / 100.4, 64 101.9 / 99.6: the gather's
/// 9 ms fall to about 4.
pub(super) const PREFETCH_AHEAD: usize = 32;

/// Prefetches the stage record of global ID `id` (both of its cache lines when it straddles).
#[inline(always)]
pub(super) fn prefetch_stage(stage: &[u8], id: u32) {
    let o = id as usize * STAGE_SIZE;
    crate::memory::prefetch_read(stage, o);
    crate::memory::prefetch_read(stage, o + STAGE_SIZE - 1);
}

/// Fills `refs[..total]` (slot = global primitive ID; each ingest chunk keeps its references
/// as a prefix, counted in `kept`), then with `compact` compacts them (`compact_chunks`), in
/// order, to the front of `temp` when it holds them (the last value returned is then true:
/// `temp` is the root's node slots, see `build_rec`'s `in_nodes`) or else of `refs`. With
/// `stage`, the primitive data is also written there at the global ID (one sequential pass
/// over the input) and `PrimRef::prim` holds the global ID until
/// `gather_leaf_data` puts data and records in leaf order. With `pair_tau` > 0 (staged builds
/// only) each chunk is paired in place while in cache (`pairs::pair_in_place`), so the
/// references are pairs. Writes each geometry's record (with its active count) into `geo`
/// (the geometry table) and returns the reference count, the active primitive count, the box
/// and the references' centroid box.
#[allow(clippy::too_many_arguments)]
fn ingest(desc: &BuildDesc, view: &dyn DeviceView, refs: &mut [PrimRef], mut stage: Option<&mut [u8]>, temp: &mut [PrimRef], (pair_tau, cluster): (f32, u32), geo: &mut [u8], kept: &mut [u32], compact: bool) -> Result<(usize, usize, Aabb, Aabb, bool), BuildError> {
    let allow_update = desc.flags.contains(BuildFlags::ALLOW_UPDATE);
    let pair_tau = if stage.is_some() { pair_tau } else { 0.0 };
    let mut base = 0usize;
    let mut sum = ChunkSum::EMPTY;
    // Every chunk keeps its references as a prefix of its slots (pairs are written to the
    // front, dropped primitives squeezed out); `kept` (scratch, at least one entry per chunk:
    // a chunk holds at least one primitive) counts them, chunk by chunk in order, for the
    // compaction below.
    let mut chunks = 0usize;
    for (gi, g) in desc.geometries.iter().enumerate() {
        let count = g.primitive_count as usize;
        let slice = refs.get_mut(base..base + count).ok_or(BuildError::TooManyPrimitives)?;
        let gi32 = gi as u32;
        let gbase = base;
        let fast = FastTris::of(g);
        let is_inst = matches!(g.data, GeometryData::Instances { .. });
        let chunk_len = ingest_chunk(g);
        // Reads chunk `ci`'s primitives into `chunk` (and their staged records into `st`),
        // pairs them or squeezes out the dropped ones: the references kept are its prefix.
        let fill = |ci: usize, chunk: &mut [PrimRef], st: Option<&mut [u8]>| -> Result<ChunkSum, (u64, BuildError)> {
            let mut st = st;
            let mut cs = ChunkSum::EMPTY;
            let mut memo = BlasBoundsMemo::new();
            for (k, slot) in chunk.iter_mut().enumerate() {
                let p = (ci * chunk_len + k) as u32;
                if let Some(ft) = fast.as_ref() {
                    ft.prefetch(p.saturating_add(PREFETCH_AHEAD as u32));
                    // Plain f32 triangles: everything stored straight from registers.
                    match ft.bounds(p, allow_update) {
                        Some(Some((lo, hi, [a, b, c]))) => {
                            cs.add(lo, hi);
                            let id = if st.is_some() { (gbase + ci * chunk_len + k) as u32 } else { p };
                            let f: &mut [[f32; 4]; 2] = bytemuck::cast_mut(slot);
                            f[0] = Vec4::from((lo, f32::from_bits(gi32))).to_array();
                            f[1] = Vec4::from((hi, f32::from_bits(id))).to_array();
                            if let Some(d) = st.as_deref_mut().and_then(|st| st.get_mut(k * STAGE_SIZE..)).and_then(|x| x.first_chunk_mut::<STAGE_SIZE>()) {
                                // Overlapping 16-byte stores of the three vertices (9 floats),
                                // then the primitive index over c's fourth lane.
                                let v = |x: Vec3A| bytemuck::cast::<[f32; 4], [u8; 16]>(Vec4::from((x, 0.0)).to_array());
                                d[0..16].copy_from_slice(&v(a));
                                d[12..28].copy_from_slice(&v(b));
                                d[24..40].copy_from_slice(&v(c));
                                d[36..40].copy_from_slice(&p.to_le_bytes());
                            }
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
                let r = if is_inst {
                    // Instances: the BLAS lookup (a locked map in the driver's view) and its
                    // header parse are memoised for the last four references (a TLAS usually
                    // instances few BLASes). Same bounds as `make_ref_data`.
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
                    Err(e) => return Err(((gi as u64) << 32 | p as u64, e)),
                }
            }
            if pair_tau > 0.0 {
                let (w, clo, chi) = pairs::pair_in_place(chunk, pair_tau, cluster.clamp(1, pairs::MAX_CLUSTER), DROPPED);
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
        };
        let nch = count.div_ceil(chunk_len);
        let kept = kept.get_mut(chunks..chunks + nch).ok_or(BuildError::TooManyPrimitives)?;
        chunks += nch;
        // Paired chunks are read and paired in a buffer of the task's and only their pairs
        // written to `refs`: the slots the pairs free are never written (dragon FAST_BUILD:
        // 15 MB of writes fewer).
        let buf_len = if pair_tau > 0.0 { chunk_len } else { 0 };
        let work = |ci: usize, chunk: &mut [PrimRef], st: Option<&mut [u8]>, kept: &mut u32, buf: &mut Vec<PrimRef>| {
            let r = match buf.get_mut(..chunk.len()) {
                Some(b) if pair_tau > 0.0 => {
                    let r = fill(ci, b, st);
                    if let Ok(cs) = &r {
                        let w = b.len() - cs.dropped;
                        chunk[..w].copy_from_slice(&b[..w]);
                    }
                    r
                }
                _ => fill(ci, chunk, st),
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
        if let Some(d) = geo.get_mut(gi * layout::GEOMETRY_SIZE..(gi + 1) * layout::GEOMETRY_SIZE) {
            d.copy_from_slice(bytemuck::bytes_of(&rec));
        }
        sum = sum.join(&res);
        base += count;
    }
    let boxes = (to_aabb(sum.lo, sum.hi), to_aabb(sum.clo, sum.chi));
    let (dropped_total, prims) = (sum.dropped, base - sum.lost);
    if dropped_total == 0 || !compact {
        return Ok((base - dropped_total, prims, boxes.0, boxes.1, false));
    }
    let (w, in_temp) = compact_chunks(desc, refs, temp, kept, base - dropped_total);
    Ok((w, prims, boxes.0, boxes.1, in_temp))
}

/// Stable compaction of ingest's chunks (each keeps the prefix `kept[c]` of its slots; the
/// counts are consumed): each chunk's prefix is copied to its range of `temp` (in parallel,
/// geometry by geometry, from a prefix sum of the chunks' counts), where the root finds them
/// (`in_nodes`: the root's first partition moves them back, which saves a copy of every
/// reference). Without a large enough `temp`, sequentially in place in `refs`. Returns the
/// references kept and whether they are in `temp`.
fn compact_chunks(desc: &BuildDesc, refs: &mut [PrimRef], temp: &mut [PrimRef], kept: &mut [u32], kept_total: usize) -> (usize, bool) {
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

/// Leaf-order primitive data and records from the staging area; restores `PrimRef::prim` to
/// the index within the geometry.
/// Copies the kept prefix of each `chunk_len`-slot chunk of `src` (chunk ci keeps
/// `offs[ci + 1] - offs[ci]` references, the last `hi - offs[last]`) to `dst`, which holds
/// destination positions `lo..hi`: halves in parallel, no heap.
fn copy_prefixes(src: &[PrimRef], chunk_len: usize, offs: &[u32], lo: usize, hi: usize, dst: &mut [PrimRef]) {
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

fn gather_leaf_data(refs: &mut [PrimRef], stage: &[u8], prims: &mut [u8], records: &mut [u8]) {
    const CH: usize = 4096;
    prims
        .par_chunks_mut(CH * PRIM_SIZE)
        .zip(records.par_chunks_mut(CH * RECORD_SIZE))
        .zip(refs.par_chunks_mut(CH))
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

fn check_types(desc: &BuildDesc) -> Result<(), BuildError> {
    for (gi, g) in desc.geometries.iter().enumerate() {
        let ok = match (desc.ty, &g.data) {
            (AsType::TopLevel, GeometryData::Instances { .. }) => true,
            (AsType::BottomLevel, GeometryData::Triangles { .. } | GeometryData::Aabbs { .. }) => true,
            _ => false,
        };
        if !ok {
            return Err(BuildError::WrongGeometryType { geometry: gi as u32 });
        }
    }
    Ok(())
}

pub fn total_primitives(desc: &BuildDesc) -> Result<u64, BuildError> {
    let total: u64 = desc.geometries.iter().map(|g| g.primitive_count as u64).sum();
    if total > u32::MAX as u64 || desc.geometries.len() as u64 > u32::MAX as u64 {
        return Err(BuildError::TooManyPrimitives);
    }
    Ok(total)
}

pub fn geometry_record(g: &Geometry, active: u32, allow_update: bool) -> GeometryRecord {
    let mut r = GeometryRecord::zeroed();
    r.flags = g.flags.0;
    r.primitive_count = g.primitive_count;
    r.active_count = active;
    match g.data {
        GeometryData::Triangles { format, max_vertex, index_type, transform, .. } => {
            r.kind = layout::KIND_TRIANGLES;
            r.format = format.to_vk();
            r.index_type = index_type.to_vk();
            r.max_vertex = max_vertex;
            r.has_transform = transform.is_some() as u32;
            if allow_update {
                r.index_hash = index_hash(g);
            }
        }
        GeometryData::Aabbs { .. } => r.kind = layout::KIND_AABBS,
        GeometryData::Instances { .. } => r.kind = layout::KIND_INSTANCES,
    }
    r
}

/// Writes primitive data and records (BLAS) for stored slots in parallel; slot order = leaf order.
pub fn write_leaf_data(desc: &BuildDesc, refs: &[PrimRef], prims: &mut [u8], records: &mut [u8]) {
    const CH: usize = 4096;
    prims
        .par_chunks_mut(CH * PRIM_SIZE)
        .zip(records.par_chunks_mut(CH * RECORD_SIZE))
        .zip(refs.par_chunks(CH))
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

/// Instance records + BLAS table for stored instances (TLAS). `keys` is scratch for the sort.
/// Sort `keys` and move the distinct values to the front; returns how many there are.
pub fn sort_distinct(keys: &mut [u64]) -> usize {
    keys.sort_unstable();
    let mut distinct = 0usize;
    for i in 0..keys.len() {
        if i == 0 || keys[i] != keys[distinct - 1] {
            keys[distinct] = keys[i];
            distinct += 1;
        }
    }
    distinct
}

/// Returns the number of distinct BLAS addresses.
pub fn write_instances(desc: &BuildDesc, view: &dyn DeviceView, refs: &[PrimRef], keys: &mut [u64], instances: &mut [u8], records: &mut [u8], table: &mut [u8]) -> u32 {
    let n = refs.len();
    let read = |r: &PrimRef| desc.geometries.get(r.geom as usize).and_then(|g| read_instance(r.geom, g, r.prim, view).ok().flatten());
    // Distinct references, sorted (deterministic, no hashing, no heap).
    let keys = &mut keys[..n];
    let reference = |r: &PrimRef| desc.geometries.get(r.geom as usize).and_then(|g| input::read_instance_reference(g, r.prim, view));
    keys.par_iter_mut().zip(refs.par_iter()).for_each(|(k, r)| *k = reference(r).unwrap_or(0));
    let distinct = sort_distinct(keys);
    let keys = &keys[..distinct];
    for (i, k) in keys.iter().enumerate() {
        if let Some(d) = table.get_mut(i * 8..i * 8 + 8) {
            d.copy_from_slice(&k.to_le_bytes());
        }
    }
    // Unused table slots (capacity > distinct) are zero so the bytes stay deterministic.
    if let Some(rest) = table.get_mut(distinct * 8..) {
        rest.fill(0);
    }
    const CH: usize = 1024;
    instances
        .par_chunks_mut(CH * layout::INSTANCE_RECORD_SIZE)
        .zip(records.par_chunks_mut(CH * RECORD_SIZE))
        .zip(refs.par_chunks(CH))
        .for_each(|((id, rd), rs)| {
            for (k, r) in rs.iter().enumerate() {
                let mut rec = InstanceRecord::zeroed();
                if let Some(inst) = read(r) {
                    rec.object_to_world = inst.transform;
                    rec.world_to_object = input::invert_transform(&inst.transform);
                    rec.custom_index = inst.custom_index;
                    rec.mask = inst.mask;
                    rec.sbt_offset = inst.sbt_offset;
                    rec.flags = inst.flags;
                    rec.blas_index = keys.binary_search(&inst.reference).map_or(u32::MAX, |x| x as u32);
                }
                rec.instance_index = r.prim;
                let o = k * layout::INSTANCE_RECORD_SIZE;
                if let Some(d) = id.get_mut(o..o + layout::INSTANCE_RECORD_SIZE) {
                    d.copy_from_slice(bytemuck::bytes_of(&rec));
                }
                let prec = PrimRecord { geometry: r.geom, primitive: r.prim };
                if let Some(d) = rd.get_mut(k * RECORD_SIZE..(k + 1) * RECORD_SIZE) {
                    d.copy_from_slice(bytemuck::bytes_of(&prec));
                }
            }
        });
    distinct as u32
}

/// Zero the padding between sections so dst[..used] is a function of the input only.
pub fn zero_gaps(dst: &mut [u8], filled: &[(u64, u64)], end: u64) {
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

#[cfg(test)]
thread_local! {
    /// The pair count of the last build on this thread (None: built unpaired), for tests.
    pub static LAST_BUILD_PAIRS: std::cell::Cell<Option<usize>> = const { std::cell::Cell::new(None) };
    /// Where the last build on this thread planned its top (`top`): 0 nowhere, 1 from the
    /// input beside ingest, 2 from the references after it. For tests.
    pub static LAST_BUILD_PLAN: std::cell::Cell<u8> = const { std::cell::Cell::new(0) };
    /// How many buckets of the last planned build on this thread split further in parallel
    /// (`split_top`). For tests.
    pub static LAST_BUILD_SPLIT_BUCKETS: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

pub fn build(desc: &BuildDesc, view: &dyn DeviceView, dst: &mut [u8], scratch: &mut [u8]) -> Result<(BuildReport, BuildPhases), BuildError> {
    let t_start = Instant::now();
    check_types(desc)?;
    let total = total_primitives(desc)?;
    let is_tlas = desc.ty == AsType::TopLevel;
    let allow_update = desc.flags.contains(BuildFlags::ALLOW_UPDATE);
    let ngeo = desc.geometries.len() as u64;

    let need_scratch = layout::build_scratch_size(total);
    if (scratch.len() as u64) < need_scratch {
        return Err(BuildError::ScratchTooSmall { needed: need_scratch, got: scratch.len() as u64 });
    }
    // Worst case for this input's counts: checked before any work so failure is cheap and
    // independent of the tree shape.
    let worst = layout::sections(desc.ty, layout::max_nodes(total), total, ngeo).end;
    if (dst.len() as u64) < worst {
        return Err(BuildError::DestinationTooSmall { needed: worst, got: dst.len() as u64 });
    }
    let total = total as usize;
    let (refs, rest) = carve::<PrimRef>(scratch, total).ok_or(BuildError::ScratchTooSmall { needed: need_scratch, got: 0 })?;
    let (nodes, rest) = carve::<BinNode>(rest, 2 * total).ok_or(BuildError::ScratchTooSmall { needed: need_scratch, got: 0 })?;
    // Paired builds: the prefix of primitives per reference in leaf order (`pairs`).
    let (prefix, _) = carve::<u32>(rest, total + 1).ok_or(BuildError::ScratchTooSmall { needed: need_scratch, got: 0 })?;

    // BLAS primitive data is staged in the (still unused) node area of dst during ingest, so
    // the leaf-order pass reads one 40-byte record per primitive instead of indices and three
    // vertices at random. Needs 40·total <= the worst-case node area (true for total >= 3).
    let stage_at = layout::sections(desc.ty, 0, total as u64, ngeo).nodes as usize;
    let staged = !is_tlas && total >= 3 && stage_at.checked_add(total * STAGE_SIZE).is_some_and(|e| e <= dst.len());
    let mut params = BuildParams::from_flags(desc.flags);
    if is_tlas && params.all_axes_from != usize::MAX {
        // Instance trees bin all three axes outside the fast-build tier: few, overlapping
        // boxes at the top of every ray's walk.
        params.all_axes_from = 0;
    }
    // Every tier builds over primitive clusters (`pairs`) in staged BLAS
    // builds of at least PAIR_MIN primitives over at most MAX_PAIR_GEOMETRIES geometries whose
    // neighbours pair well in a sample. Ingest pairs each chunk while it is in cache.
    // First global primitive ID of each geometry, then the total (IDs → geometries).
    let mut firsts = [0u32; pairs::MAX_PAIR_GEOMETRIES + 1];
    for (gi, g) in desc.geometries.iter().enumerate().take(pairs::MAX_PAIR_GEOMETRIES) {
        firsts[gi + 1] = firsts[gi].saturating_add(g.primitive_count);
    }
    let firsts = &firsts[..=desc.geometries.len().min(pairs::MAX_PAIR_GEOMETRIES)];
    let pair_tau = if staged && params.pair_tau > 0.0 && total >= pairs::PAIR_MIN && desc.geometries.len() <= pairs::MAX_PAIR_GEOMETRIES {
        let read = |g: u32, p: u32| desc.geometries.get(g as usize).and_then(|geo| make_ref(g, geo, p, view, allow_update).ok().flatten());
        if pairs::worth_pairing(firsts, params.pair_tau, read) { params.pair_tau } else { 0.0 }
    } else {
        0.0
    };
    let paired = pair_tau > 0.0;
    // Large BLAS builds take the top of their tree from a sample of the references (`top`):
    // ingest leaves its chunks uncompacted, and the scatter into the top's buckets moves them.
    let nch = top::chunk_count(desc);
    let want_plan = top::wanted(desc, total, nch, prefix.len());
    let (ingested, input_plan) = {
        // The node slots are unused until the tree is built: compaction's temporary, or the
        // planned top's sample (the plan from the input runs beside ingest, which then does
        // not compact).
        let slots = node_refs_mut(nodes, total).unwrap_or(&mut []);
        let goff = layout::sections(desc.ty, 0, 0, ngeo).geometries as usize;
        let (head, tail) = dst.split_at_mut(stage_at.min(dst.len()));
        let geo = head.get_mut(goff..goff + desc.geometries.len() * layout::GEOMETRY_SIZE).unwrap_or(&mut []);
        let kept = if want_plan { &mut prefix[..nch] } else { &mut *prefix };
        let stage = if staged { Some(tail) } else { None };
        let pair = (pair_tau, params.cluster);
        if want_plan {
            rayon::join(|| ingest(desc, view, refs, stage, &mut [], pair, geo, kept, false), || top::plan_from_input(desc, &params, total, slots))
        } else {
            (ingest(desc, view, refs, stage, slots, pair, geo, kept, true), None)
        }
    };
    let (mut built, active, root_box, root_cb, mut in_temp) = ingested?;
    // Otherwise the sample of the references goes to the node slots, unused until the scatter.
    let (plan, _from) = match input_plan {
        Some(pl) => (Some(pl), 1u8),
        None if want_plan => (top::plan(desc, &params, refs, &prefix[..nch], built, root_cb, node_refs_mut(nodes, total).unwrap_or(&mut [])), 2),
        None => (None, 0),
    };
    #[cfg(test)]
    LAST_BUILD_PLAN.with(|c| c.set(if plan.is_some() { _from } else { 0 }));
    if want_plan && plan.is_none() {
        // No top from the sample (it did not split): the compaction ingest skipped.
        let temp = node_refs_mut(nodes, total).unwrap_or(&mut []);
        (built, in_temp) = compact_chunks(desc, refs, temp, &mut prefix[..nch], built);
    }
    #[cfg(test)]
    LAST_BUILD_PAIRS.with(|c| c.set(paired.then_some(built)));
    let t_ingest = Instant::now();
    let threads = rayon::current_num_threads().max(1);
    // Paired: leaves of up to `cluster_leaf` cluster references; C_T scaled by the references
    // per primitive keeps the leaf/split balance of the unpaired tier.
    let mut bparams = params;
    if paired {
        bparams.max_leaf = params.cluster_leaf.max(1);
        bparams.traversal_cost = (params.traversal_cost * built as f32 / active.max(1) as f32).max(1.0);
    }
    let ctx = Ctx { params: bparams, total: built, threads, paired, prim_ct: params.traversal_cost };
    // Pre-emission area (see `finish_split`): after the staging area in the (still unused)
    // node section of dst. Whether a block fits there never changes the output bytes.
    // Without staging the area would start where the final nodes start, so no block could
    // ever be used (see the final pass): then there is none, and nothing is encoded twice
    // (TLAS builds spent a sixth of their time on blocks the final pass re-encoded).
    let pre_at = (stage_at + if staged { total * STAGE_SIZE } else { 0 }).min(dst.len());
    let pre_len = if staged { (dst.len() - pre_at).min(PRE_BYTES_PER_PRIM * active) } else { 0 };
    let (sah_sum, _depth) = if built > 0 {
        let pre = &mut dst[pre_at..pre_at + pre_len];
        let planned = plan.as_ref().and_then(|pl| {
            let (kept, rest) = prefix.split_at_mut(nch);
            let (cells, rest) = rest.split_at_mut(nch * pl.buckets * top::CELL_WORDS);
            let cells: &mut [top::BucketCell] = bytemuck::cast_slice_mut(cells);
            let ids = bytemuck::cast_slice_mut::<u32, u8>(rest).get_mut(..total)?;
            top::classify_chunks(pl, desc, refs, kept, cells, ids);
            let s = top::sums(pl, cells).filter(|s| s.total() == built)?;
            top::scatter(pl, &s, desc, refs, kept, cells, ids, &mut nodes[..2 * built - 1])?;
            Some(s)
        });
        match (plan.as_ref(), planned) {
            (Some(pl), Some(s)) => {
                let mut tasks = Vec::new();
                top::tasks(pl, &s, 0, &mut refs[..built], &mut nodes[..2 * built - 1], pre, 0, 0, 0, u32::MAX, &mut tasks);
                #[cfg(test)]
                LAST_BUILD_SPLIT_BUCKETS.with(|c| c.set(tasks.iter().filter(|t| ctx.threads > 1 && ctx.top(t.refs.len())).count()));
                let done = run_tasks(&ctx, tasks);
                top_results(&mut nodes[..2 * built - 1], 0, &done)
            }
            (plan, _) => {
                if plan.is_some() {
                    // The plan did not apply after all: the compaction ingest skipped, in place.
                    compact_chunks(desc, refs, &mut [], &mut prefix[..nch], built);
                }
                build_tree(&ctx, &mut refs[..built], &mut nodes[..2 * built - 1], root_box, root_cb, in_temp, pre)
            }
        }
    } else {
        (0.0, 0)
    };
    // Paired builds: leaves name references while building, primitives in the output, through
    // the prefix of primitives per reference in leaf order.
    let tree = &nodes[..(2 * built).saturating_sub(1)];
    let map: Option<&[u32]> = if paired {
        let p = &mut prefix[..=built];
        pairs::prim_prefix(&refs[..built], p);
        Some(&*p)
    } else {
        None
    };
    let t_sah = Instant::now();
    // Leaf data first: with staging, the node section overlaps the staging area.
    let pre = layout::sections(desc.ty, 0, active as u64, ngeo);
    if !is_tlas {
        let (head, tail) = dst.split_at_mut(stage_at.min(dst.len()));
        let (head, rec_part) = head.split_at_mut(pre.records as usize);
        let prims = &mut head[pre.prims as usize..pre.prims as usize + active * PRIM_SIZE];
        let records = &mut rec_part[..active * RECORD_SIZE];
        if let Some(map) = map {
            pairs::gather_pairs(&refs[..built], map, &tail[..total * STAGE_SIZE], prims, records, firsts);
        } else if staged {
            gather_leaf_data(&mut refs[..active], &tail[..total * STAGE_SIZE], prims, records);
        } else {
            write_leaf_data(desc, &refs[..active], prims, records);
        }
    }
    let t_leaf = Instant::now();
    // Nodes are the last section, so their offset is known before their count: emit directly.
    let nodes_at = pre.nodes as usize;
    let wide_count = if active > 0 { wide_size(tree) } else { 0 };
    let mut leaf_count = 0u32;
    if active > 0 {
        let end = nodes_at.saturating_add(wide_count as usize * NODE_SIZE);
        let got = dst.len() as u64;
        if end > dst.len() || nodes_at > end {
            return Err(BuildError::DestinationTooSmall { needed: end as u64, got });
        }
        // Pre-emitted blocks are used when the final node range ends before the area.
        let (head, tail) = dst.split_at_mut(pre_at.max(end));
        let out = &mut head[nodes_at..end];
        let pre_area = (end <= pre_at).then(|| &tail[..pre_len]);
        let root_block = match (pre_area, tree.first()) {
            (Some(p), Some(root)) if is_cut(u32::MAX, root.count) => pre_block(root, p.len()).and_then(|r| p.get(r)),
            _ => None,
        };
        leaf_count = match root_block {
            Some(src) if src.len() == out.len() => copy_block(src, out, 0, map),
            _ if tree.first().is_some_and(|r| r.left_count != 0 && r.count <= EMIT_CUT) => {
                // The root is a cut root whose block is not usable: encode it here.
                let (mut cursor, mut l) = (0u32, 0u32);
                let _ = emit_seq(tree, 0, out, 0, &mut cursor, &mut l, map);
                l
            }
            _ => emit_wide(tree, 0, out, pre_area, map),
        };
    }
    let t_nodes = Instant::now();
    let s = layout::sections(desc.ty, wide_count as u64, active as u64, ngeo);
    if s.end > dst.len() as u64 || s.nodes as usize != nodes_at {
        return Err(BuildError::DestinationTooSmall { needed: s.end, got: dst.len() as u64 });
    }
    let used = s.end;
    let dst = &mut dst[..used as usize];

    let mut blas_refs = 0u32;
    let mut instance_count = 0;
    if is_tlas {
        let (head, tail) = dst.split_at_mut(s.instances as usize);
        let records = &mut head[s.records as usize..s.records as usize + active * RECORD_SIZE];
        let (inst, table_part) = tail.split_at_mut((s.blas_table - s.instances) as usize);
        let inst = &mut inst[..active * layout::INSTANCE_RECORD_SIZE];
        let table = &mut table_part[..active * 8];
        // Reuse the binary node area (no longer needed) for the sort keys.
        let node_bytes: &mut [u8] = bytemuck::cast_slice_mut(nodes);
        let keys: &mut [u64] = bytemuck::try_cast_slice_mut(&mut node_bytes[..active * 8]).map_err(|_| BuildError::ScratchTooSmall { needed: need_scratch, got: 0 })?;
        blas_refs = write_instances(desc, view, &refs[..active], keys, inst, records, table);
        instance_count = active as u32;
    }
    let filled = [
        (s.nodes, s.nodes + wide_count as u64 * NODE_SIZE as u64),
        (s.prims, s.prims + if is_tlas { 0 } else { active as u64 * PRIM_SIZE as u64 }),
        (s.records, s.records + active as u64 * RECORD_SIZE as u64),
        (s.geometries, s.geometries + ngeo * layout::GEOMETRY_SIZE as u64),
        (s.instances, s.instances + if is_tlas { active as u64 * layout::INSTANCE_RECORD_SIZE as u64 } else { 0 }),
        (s.blas_table, s.blas_table + if is_tlas { active as u64 * 8 } else { 0 }),
    ];
    zero_gaps(dst, &filled, used);

    let root_area = root_box.half_area() as f64;
    let sah = if active > 0 && root_area > 0.0 && root_area.is_finite() { (sah_sum / root_area) as f32 } else { 0.0 };
    let raw = RawHeader {
        magic: layout::MAGIC,
        version: layout::FORMAT_VERSION,
        ty: desc.ty as u32,
        flags: desc.flags.0,
        valid: layout::valid_word(),
        geometry_count: ngeo as u32,
        primitive_count: active as u32,
        instance_count,
        node_count: wide_count,
        leaf_count,
        blas_reference_count: blas_refs,
        sah_cost: sah,
        bounds: if active > 0 { [root_box.lo[0], root_box.lo[1], root_box.lo[2], root_box.hi[0], root_box.hi[1], root_box.hi[2]] } else { [0.0; 6] },
        total_primitives: total as u32,
        blas_table_capacity: if is_tlas { active as u32 } else { 0 },
        used_size: used,
        nodes_offset: s.nodes,
        prims_offset: s.prims,
        records_offset: s.records,
        geometries_offset: s.geometries,
        instances_offset: s.instances,
        blas_table_offset: s.blas_table,
        max_leaf_size: if paired { bparams.max_leaf * params.cluster.clamp(1, pairs::MAX_CLUSTER) } else { params.max_leaf },
        reserved: 0,
    };
    layout::write_header(dst, &raw);
    let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3;
    let phases = BuildPhases {
        ingest_ms: ms(t_start, t_ingest),
        sah_ms: ms(t_ingest, t_sah),
        leaf_data_ms: ms(t_sah, t_leaf),
        nodes_ms: ms(t_leaf, t_nodes),
        total_ms: ms(t_start, Instant::now()),
    };
    Ok((BuildReport { used_size: used, node_count: wide_count, leaf_count, primitive_count: active as u32 }, phases))
}


#[cfg(test)]
mod network_tests {
    use super::*;

    /// The mantissa truncation equals `as i32` and `floor_pos` equals `floor` on [0, 2^22):
    /// every integer boundary of the bin and quantisation ranges and its float neighbours,
    /// halves (round-to-even ties), and a sweep.
    #[test]
    fn vector_truncation_is_exact() {
        let mut xs = vec![0.0f32, 1e-30, 0.49999997, 0.5, 0.50000006, 1.5, 2.5, 31.999998, 4_194_303.5];
        for i in 0..=300u32 {
            let f = i as f32;
            xs.extend([f, f32::from_bits(f.to_bits().saturating_sub(1)), f32::from_bits(f.to_bits() + 1), f + 0.5]);
        }
        xs.extend((0..100_000).map(|i| i as f32 * 0.000_37));
        for q in xs.chunks(4) {
            let mut v = [0f32; 4];
            v[..q.len()].copy_from_slice(q);
            let got = trunc_i32x4_4(Vec4::from_array(v));
            let got3 = trunc_i32x4(Vec3A::new(v[0], v[1], v[2]));
            let fl = floor_pos(Vec4::from_array(v)).to_array();
            for k in 0..4 {
                assert_eq!(got[k], v[k] as i32, "{}", v[k]);
                assert_eq!(fl[k].to_bits(), v[k].floor().to_bits(), "{}", v[k]);
            }
            assert_eq!(&got3[..3], &got[..3]);
        }
    }

    /// 0-1 principle: a comparator network sorts every input iff it sorts every 0/1 input.
    #[test]
    fn sorting_networks_sort() {
        for bits in 0u32..(1 << MAX_SMALL) {
            let mut v = [u64::MAX; MAX_SMALL];
            for (i, x) in v.iter_mut().enumerate() {
                *x = (bits >> i & 1) as u64;
            }
            sort_network(&mut v, &NET8);
            assert!(v.windows(2).all(|w| w[0] <= w[1]), "input {bits:#b}: {v:?}");
        }
        let keys = [-1.5f32, -0.0, 0.0, 2.0, f32::MIN, f32::MAX, 1e-30, -1e-30];
        let mut sorted = keys;
        sorted.sort_by(|a, b| a.total_cmp(b));
        let mut by_bits = keys;
        by_bits.sort_by_key(|&k| ordered_bits(k));
        assert_eq!(sorted.map(f32::to_bits), by_bits.map(f32::to_bits));
    }

    /// Nodes of three to five references split at the cheapest of all their bipartitions: the
    /// cost `small_split` returns is that of a brute-force enumeration in f64 (sides' boxes and
    /// weights from the references), the reordered references describe a split of that cost,
    /// and nothing is lost; weighted (cluster) references count their primitives. The sweeps'
    /// splits are among the bipartitions, so no tier's small nodes got worse.
    #[test]
    fn small_nodes_take_the_cheapest_bipartition() {
        let mut next = xorshift(0x9e37_79b9_7f4a_7c15);
        let mut f = move || (next() >> 40) as f32 / (1u64 << 24) as f32;
        let cost64 = |set: &[PrimRef], weighted: bool| -> f64 {
            let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
            let mut w = 0f64;
            for r in set {
                for a in 0..3 {
                    lo[a] = lo[a].min(r.lo[a] as f64);
                    hi[a] = hi[a].max(r.hi[a] as f64);
                }
                w += if weighted { r.geom as f64 } else { 1.0 };
            }
            let d = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
            (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]) * w
        };
        for case in 0..3000 {
            let n = 3 + case % 3;
            let weighted = case % 2 == 1;
            // Clustered boxes, some flat or shared, so that ties and degenerate sides occur.
            let refs: Vec<PrimRef> = (0..n)
                .map(|k| {
                    let c = [f() * 4.0, if case % 7 == 0 { 1.0 } else { f() * 4.0 }, f() * 4.0];
                    let e = [f(), f() * 0.3, if case % 5 == 0 { 0.0 } else { f() }];
                    PrimRef { lo: c, geom: 1 + (k as u32 * 7 + case as u32) % 4, hi: [c[0] + e[0], c[1] + e[1], c[2] + e[2]], prim: k as u32 }
                })
                .collect();
            let mut brute = f64::INFINITY;
            for m in 1u32..(1 << n) - 1 {
                let (mut l, mut r) = (Vec::new(), Vec::new());
                for (i, x) in refs.iter().enumerate() {
                    if m >> i & 1 != 0 { l.push(*x) } else { r.push(*x) }
                }
                brute = brute.min(cost64(&l, weighted) + cost64(&r, weighted));
            }
            for axes in [(0, 3), (1, 2)] {
                if axes == (1, 2) && n == 5 {
                    continue; // one axis sorts from five references on
                }
                let mut got = refs.clone();
                let (mid, cost) = small_split(&mut got, axes, weighted).expect("a split");
                assert!((cost as f64 - brute).abs() <= 1e-4 * brute.max(1e-3), "case {case} n {n}: cost {cost} against brute force {brute}");
                let again = cost64(&got[..mid], weighted) + cost64(&got[mid..], weighted);
                assert!((again - brute).abs() <= 1e-4 * brute.max(1e-3), "case {case}: the reordered split costs {again}, not {brute}");
                let mut ids: Vec<u32> = got.iter().map(|r| r.prim).collect();
                ids.sort_unstable();
                assert_eq!(ids, (0..n as u32).collect::<Vec<_>>());
            }
        }
        // Huge sanitised boxes (areas overflow to infinity) still split, as the sweeps did.
        for n in 3..=5 {
            let huge: Vec<PrimRef> = (0..n).map(|k| PrimRef { lo: [-f32::MAX; 3], geom: 1, hi: [f32::MAX; 3], prim: k }).collect();
            for axes in [(0, 3), (1, 2)] {
                let mut got = huge.clone();
                let (mid, cost) = small_split(&mut got, axes, true).expect("huge boxes split");
                assert!((1..n as usize).contains(&mid) && cost == f32::INFINITY, "n {n}: {mid} {cost}");
            }
        }
    }

    /// A deterministic xorshift64 stream.
    fn xorshift(mut seed: u64) -> impl FnMut() -> u64 {
        move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        }
    }

    /// The two-sum instance box equals the eight-corner one bit for bit on finite terms
    /// (monotonic rounding), including signed zeros, overflow to infinity and mirrored axes.
    #[test]
    fn instance_box_from_two_sums_matches_eight_corners() {
        let mut next = xorshift(0x2545_f491_4f6c_dd1d);
        let specials = [0.0f32, -0.0, 1.0, -1.0, 3.0e38, -3.0e38, 1e-38, -1e-45, 0.5, 2.0];
        let mut pick = move || {
            let r = next();
            if r % 3 == 0 {
                specials[(r >> 8) as usize % specials.len()]
            } else {
                ((r >> 11) as f64 / (1u64 << 53) as f64 * 200.0 - 100.0) as f32
            }
        };
        let bits = |b: ([f32; 3], [f32; 3])| (b.0.map(f32::to_bits), b.1.map(f32::to_bits));
        for _ in 0..200_000 {
            let m: [f32; 12] = std::array::from_fn(|_| pick());
            let (a, b, c) = (pick(), pick(), pick());
            let (d, e, f) = (pick(), pick(), pick());
            let bb = [a.min(d), b.min(e), c.min(f), a.max(d), b.max(e), c.max(f)];
            let want = instance_box_corners(&m, &bb);
            let got = instance_bounds_of(&m, Some(&bb));
            assert_eq!(bits(got), bits(want), "transform {m:?} box {bb:?}");
        }
    }

    /// The compaction's parallel copy of chunk prefixes gives what copying them one after the
    /// other gives: chunks of every fill from empty to full, more of them than one task takes
    /// (the halves in parallel), on a pool of three.
    #[test]
    fn chunk_prefixes_are_copied_in_order() {
        let mut bits = xorshift(0x2545_f491_4f6c_dd1d);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        for (chunks, chunk_len) in [(1usize, 7usize), (5, 16), (40, 9), (133, 32)] {
            let src: Vec<PrimRef> = (0..chunks * chunk_len).map(|i| PrimRef { lo: [i as f32; 3], geom: 0, hi: [i as f32 + 1.0; 3], prim: i as u32 }).collect();
            let kept: Vec<usize> = (0..chunks).map(|c| if c % 7 == 3 { 0 } else if c % 5 == 1 { chunk_len } else { (bits() % (chunk_len as u64 + 1)) as usize }).collect();
            let expect: Vec<u32> = (0..chunks).flat_map(|c| (0..kept[c]).map(move |k| (c * chunk_len + k) as u32)).collect();
            let mut offs: Vec<u32> = Vec::new();
            let mut acc = 0usize;
            for &k in &kept {
                offs.push(acc as u32);
                acc += k;
            }
            let mut dst = vec![PrimRef { lo: [0.0; 3], geom: DROPPED, hi: [0.0; 3], prim: u32::MAX }; acc];
            pool.install(|| copy_prefixes(&src, chunk_len, &offs, 0, acc, &mut dst));
            assert_eq!(dst.iter().map(|r| r.prim).collect::<Vec<_>>(), expect, "{chunks} chunks of {chunk_len}");
        }
    }

    /// The one-pass partition (one-thread pools, small nodes) and the parallel one (statistics,
    /// then scatter) give the same count, boxes and bytes, both into node slots and back into
    /// `refs`, including everything on one side; the bytes of a build may not depend on which
    /// one ran.
    #[test]
    fn one_pass_partition_matches_the_parallel_one() {
        let mut bits = xorshift(0x9e37_79b9_7f4a_7c15);
        let mut next = move || (bits() >> 40) as f32 / (1u64 << 24) as f32;
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        for n in [2usize, 3, 5, 64, 1000, 4097] {
            let refs: Vec<PrimRef> = (0..n)
                .map(|i| {
                    let lo = [next() * 10.0, next() * 10.0, next() * 10.0];
                    PrimRef { lo, geom: i as u32 % 3, hi: [lo[0] + next(), lo[1] + next(), lo[2] + next()], prim: i as u32 }
                })
                .collect();
            for limit in [-1.0f32, 2.5, 5.0, 9.0, 11.0] {
                let is_left = |r: &PrimRef| r.lo[0] * 0.5 + r.hi[0] * 0.5 < limit;
                let empty = BinNode::zeroed();
                // Into node slots.
                let (mut a, mut b) = (vec![empty; 2 * n - 1], vec![empty; 2 * n - 1]);
                let x = pool.install(|| par_partition_to_nodes(&refs, &mut a, false, is_left));
                let y = pool.install(|| par_partition_to_nodes(&refs, &mut b, true, is_left));
                assert_eq!(x, y, "n {n} limit {limit}");
                let nl = x.unwrap().0;
                if nl > 0 && nl < n {
                    assert_eq!(node_refs(&a[1..], nl), node_refs(&b[1..], nl), "n {n} limit {limit}: lefts");
                    assert_eq!(node_refs(&a[2 * nl..], n - nl), node_refs(&b[2 * nl..], n - nl), "n {n} limit {limit}: rights");
                    // Stable: the lefts are the left references in input order.
                    let want: Vec<PrimRef> = refs.iter().filter(|r| is_left(r)).copied().collect();
                    assert_eq!(node_refs(&b[1..], nl), Some(&want[..]));
                }
                // From node slots back into refs.
                let mut slots = vec![empty; 2 * n - 1];
                node_refs_mut(&mut slots, n).unwrap().copy_from_slice(&refs);
                let (mut ra, mut rb) = (vec![refs[0]; n], vec![refs[0]; n]);
                let x = pool.install(|| par_partition_from_nodes(&mut ra, &slots, false, is_left));
                let y = pool.install(|| par_partition_from_nodes(&mut rb, &slots, true, is_left));
                assert_eq!(x, y, "n {n} limit {limit}: from nodes");
                assert_eq!(ra, rb, "n {n} limit {limit}: from nodes");
            }
        }
    }
}

/// Timing of the top levels' passes on their own (ignored; run by hand, e.g. on the 16-core
/// machine): a parallel copy of the dragon's references (the memory bound), the parallel
/// partition's statistics pass, and the whole parallel partition, at each ARBOR_THREADS count.
#[cfg(test)]
mod pass_timing {
    use super::*;

    /// The references of `ARBOR_MESH` (default: the full dragon), one per triangle.
    fn mesh_refs() -> Vec<PrimRef> {
        let path = std::env::var("ARBOR_MESH").unwrap_or_else(|_| concat!(env!("CARGO_MANIFEST_DIR"), "/data/dragon_vrip.ply.gz").to_string());
        let mesh = arbor_scene::load(&path).expect("mesh");
        let v = &mesh.positions;
        mesh.indices
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let (lo, hi) = triangle_bounds(&[Vec3::from(v[t[0] as usize]), Vec3::from(v[t[1] as usize]), Vec3::from(v[t[2] as usize])]);
                PrimRef { lo, geom: 0, hi, prim: i as u32 }
            })
            .collect()
    }

    /// Xorshift floats in [0, 1) from `seed` (also `top`'s tests).
    pub(super) fn unit_floats(mut seed: u64) -> impl FnMut() -> f32 {
        move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// `bin_refs` alone over the dragon's references on the root's grid: ns per reference for
    /// one axis with 8 bins (FAST_BUILD) and three with 32 (FAST_TRACE). Ignored; by hand.
    #[test]
    #[ignore]
    fn bin_refs_timing() {
        let refs = mesh_refs();
        let (_, cb) = bounds_of(&refs);
        for (k, axes) in [(8usize, (0usize, 1usize)), (32, (0, 3))] {
            let mut scale = [0f32; 3];
            for a in axes.0..axes.1 {
                scale[a] = k as f32 / (cb.hi[a] - cb.lo[a]) * (1.0 - 1.0 / 1024.0);
            }
            let bn = Binning { cmin: Vec3A::from(cb.lo), scale: Vec3A::from(scale), kmax: UVec3::splat(k as u32 - 1), kmax_f: Vec3A::splat((k - 1) as f32), axes };
            for _ in 0..5 {
                let mut bins = Bins::new();
                let s = std::time::Instant::now();
                bin_refs(&refs, &bn, &mut bins);
                let total: u32 = bins.count[axes.0][..k].iter().sum();
                println!("bin_refs {k} bins, axes {axes:?}: {:.2} ns per reference ({total} binned)", s.elapsed().as_secs_f64() * 1e9 / refs.len() as f64);
            }
            // Nodes of 16 to 256 references in cache: the first 64k references, binned that
            // many at a time, 20 rounds. On the root's grid these runs mostly share a bin: the
            // worst case for the chained min/max (four sets instead of two measured 12 %
            // faster here at 256, and the same for the whole dragon build, so they were not
            // kept).
            for c in [16usize, 32, 64, 128, 256] {
                let mut bins = Bins::new();
                let part = &refs[..refs.len().min(1 << 16)];
                let s = std::time::Instant::now();
                for _ in 0..20 {
                    for c in part.chunks(c) {
                        bin_refs(c, &bn, &mut bins);
                    }
                }
                println!("bin_refs in cache, {c} at a time, {k} bins, axes {axes:?}: {:.2} ns per reference", s.elapsed().as_secs_f64() * 1e9 / (20 * part.len()) as f64);
            }
            // Nodes below 512 references bin one reference at a time into one set.
            for _ in 0..3 {
                let mut bins = Bins::new();
                let s = std::time::Instant::now();
                for c in refs.chunks(256) {
                    for r in c {
                        bin_one(r, &bn, &mut bins);
                    }
                }
                println!("bin_one loop {k} bins, axes {axes:?}: {:.2} ns per reference", s.elapsed().as_secs_f64() * 1e9 / refs.len() as f64);
            }
        }
    }

    /// `sweep_bins` alone on bins filled from random boxes: ns per call for 8 bins on one axis
    /// and 32 on three. Ignored; run by hand.
    #[test]
    #[ignore]
    fn sweep_timing() {
        let mut f = unit_floats(0x9e37_79b9_7f4a_7c15);
        for (k, axes) in [(8usize, (0usize, 1usize)), (32, (0, 3))] {
            let sets: Vec<(Bins, [f32; 3])> = (0..8)
                .map(|_| {
                    let mut b = Bins::new();
                    let mut scale = [0f32; 3];
                    for a in axes.0..axes.1 {
                        scale[a] = 1.0;
                        for x in 0..k {
                            let lo = Vec3A::new(x as f32 + f(), f() * 10.0, f() * 10.0);
                            b.lo[a][x] = lo;
                            b.hi[a][x] = lo + Vec3A::new(f(), f(), f());
                            b.count[a][x] = 1 + (f() * 8.0) as u32;
                        }
                    }
                    (b, scale)
                })
                .collect();
            for _ in 0..5 {
                let s = std::time::Instant::now();
                let mut sum = 0f64;
                for _ in 0..10_000 {
                    for (b, scale) in &sets {
                        if let Some(x) = sweep_bins(b, k, scale) {
                            sum += x.4 as f64 + x.1 as f64;
                        }
                    }
                }
                println!("sweep_bins {k} bins, axes {axes:?}: {:.1} ns per call (checksum {sum:.1})", s.elapsed().as_secs_f64() * 1e9 / (10_000.0 * sets.len() as f64));
            }
        }
    }

    /// What 16-byte references (a box quantised to 16 bits per coordinate on the root's grid,
    /// and an index) would save in the out-of-place partition: `partition_out` over the
    /// dragon's 32-byte references against the same loop over 16-byte ones, split at the
    /// median centroid of x, over the whole array (memory) and in nodes of 16k and 1k
    /// references (cache). ns per reference. Ignored; run by hand.
    #[test]
    #[ignore]
    fn quantised_partition_timing() {
        #[repr(C)]
        #[derive(Clone, Copy, Pod, Zeroable)]
        struct QRef {
            lo: [u16; 3],
            hi: [u16; 3],
            id: u32,
        }
        let refs = mesh_refs();
        let (root, cb) = bounds_of(&refs);
        let q = |v: f32, a: usize| (((v - root.lo[a]) / (root.hi[a] - root.lo[a])).clamp(0.0, 1.0) * 65535.0) as u16;
        let qrefs: Vec<QRef> = refs.iter().map(|r| QRef { lo: [q(r.lo[0], 0), q(r.lo[1], 1), q(r.lo[2], 2)], hi: [q(r.hi[0], 0), q(r.hi[1], 1), q(r.hi[2], 2)], id: r.prim }).collect();
        let k = 2.0f32;
        let sp = Splitter { a: 0, cmin: cb.lo[0], scale: k / (cb.hi[0] - cb.lo[0]), limit: 1.0 };
        let qlimit = q(cb.lo[0], 0) as u32 + q(cb.hi[0], 0) as u32;
        for node in [refs.len(), 1 << 14, 1 << 10] {
            for _ in 0..3 {
                let mut out = vec![0u8; refs.len() * PRIMREF_BYTES + PRIMREF_BYTES];
                let rounds = if node == refs.len() { 3 } else { 20 };
                let part = &refs[..refs.len().min(if node == refs.len() { refs.len() } else { 1 << 16 })];
                let s = std::time::Instant::now();
                let mut total = 0usize;
                for _ in 0..rounds {
                    for c in part.chunks(node) {
                        let nl = c.iter().filter(|r| sp.left(r)).count();
                        total += partition_out(c, &mut out[..c.len() * PRIMREF_BYTES + PRIMREF_BYTES], nl, nl * PRIMREF_BYTES, &sp).unwrap_or(0);
                    }
                }
                let t32 = s.elapsed().as_secs_f64() * 1e9 / (rounds * part.len()) as f64;
                let qpart = &qrefs[..part.len()];
                let mut qout = vec![QRef::zeroed(); qrefs.len() + 1];
                let s = std::time::Instant::now();
                let mut qtotal = 0usize;
                for _ in 0..rounds {
                    for c in qpart.chunks(node) {
                        let left = |r: &QRef| (r.lo[0] as u32 + r.hi[0] as u32) < qlimit;
                        let nl = c.iter().filter(|r| left(r)).count();
                        let (mut li, mut ri) = (0usize, nl);
                        let cap = qout.len() - 1;
                        for r in c {
                            let l = left(r) as usize;
                            let at = if l != 0 { li } else { ri }.min(cap);
                            qout[at] = *r;
                            li += l;
                            ri += l ^ 1;
                        }
                        qtotal += li;
                    }
                }
                let t16 = s.elapsed().as_secs_f64() * 1e9 / (rounds * qpart.len()) as f64;
                println!("nodes of {node}: count + partition, 32-byte {t32:.2} ns, 16-byte {t16:.2} ns per reference (lefts {total} / {qtotal})");
            }
        }
    }

    /// `small_split` alone: 200,000 groups of 2–8 nearby references, one axis (FAST_BUILD) and
    /// three (FAST_TRACE), ns per call. Ignored; run by hand with `--ignored --nocapture`.
    #[test]
    #[ignore]
    fn small_split_timing() {
        let mut f = unit_floats(0x2545_f491_4f6c_dd1d);
        let groups: Vec<Vec<PrimRef>> = (0..200_000)
            .map(|g| {
                let n = 2 + g % 7;
                let c = [f() * 100.0, f() * 100.0, f() * 100.0];
                (0..n)
                    .map(|k| {
                        let lo = [c[0] + f(), c[1] + f(), c[2] + f()];
                        PrimRef { lo, geom: 0, hi: [lo[0] + f() * 0.5, lo[1] + f() * 0.5, lo[2] + f() * 0.5], prim: k as u32 }
                    })
                    .collect()
            })
            .collect();
        for axes in [(0, 1), (0, 3)] {
            for _ in 0..5 {
                let mut work = groups.clone();
                let s = std::time::Instant::now();
                let mut sum = 0f64;
                for g in work.iter_mut() {
                    if let Some((mid, cost)) = small_split(g, axes, false) {
                        sum += mid as f64 + cost as f64;
                    }
                }
                println!("small_split axes {axes:?}: {:.1} ns per group (checksum {sum:.3})", s.elapsed().as_secs_f64() * 1e9 / groups.len() as f64);
            }
        }
    }

    #[test]
    #[ignore]
    fn top_pass_scaling() {
        let refs = mesh_refs();
        let n = refs.len();
        let (_, cb) = bounds_of(&refs);
        let mid = 0.5 * (cb.lo[0] + cb.hi[0]);
        let is_left = move |r: &PrimRef| r.lo[0] * 0.5 + r.hi[0] * 0.5 < mid;
        let mut copy = vec![PrimRef::zeroed(); n];
        let mut nodes = vec![BinNode::zeroed(); 2 * n];
        let threads: Vec<usize> = std::env::var("ARBOR_THREADS").ok().map(|s| s.split(',').filter_map(|x| x.parse().ok()).collect()).unwrap_or(vec![1, 2]);
        for t in threads {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
            let time = |f: &mut dyn FnMut()| {
                let mut best = f64::MAX;
                for _ in 0..20 {
                    let s = std::time::Instant::now();
                    f();
                    best = best.min(s.elapsed().as_secs_f64() * 1e3);
                }
                best
            };
            let chunk = n.div_ceil(PART_CHUNKS);
            let c = time(&mut || pool.install(|| copy.par_chunks_mut(chunk).zip(refs.par_chunks(chunk)).for_each(|(d, s)| d.copy_from_slice(s))));
            let st = time(&mut || {
                pool.install(|| std::hint::black_box(part_stats(&refs, &is_left)));
            });
            let p = time(&mut || {
                pool.install(|| std::hint::black_box(par_partition_to_nodes(&refs, &mut nodes, false, is_left)));
            });
            println!("threads {t:2}: {n} refs ({} MB): copy {c:.2} ms, stats {st:.2} ms, stats+scatter {p:.2} ms", n * PRIMREF_BYTES >> 20);
        }
    }
}

//! Geometry shared by building, refit and metrics: boxes (`Aabb`), primitive references
//! (`PrimRef`) and their vector views, sanitised triangle and instance bounds, and the exact
//! lane-wise truncations the binning and quantisation rely on.
//!
//! Owns: arithmetic on boxes and points. Must not touch: scratch layout, the stored format,
//! tree building.
use super::layout::PRIMREF_SIZE;
use super::DeviceView;
use bytemuck::{Pod, Zeroable};
use glam::{Vec3, Vec3A, Vec3Swizzles, Vec4};


/// One primitive reference: its (sanitised, finite) bounds and where it came from.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct PrimRef {
    pub lo: [f32; 3],
    pub geom: u32,
    pub hi: [f32; 3],
    pub prim: u32,
}
impl PrimRef {
    /// Primitives under a cluster reference (clustered builds keep the count in `geom`).
    #[inline(always)]
    pub fn cluster_size(&self) -> u32 {
        self.geom
    }
}
const _: () = assert!(std::mem::size_of::<PrimRef>() == PRIMREF_SIZE as usize);
/// Marks an inactive/dropped slot during ingest, before compaction.
pub const DROPPED: u32 = u32::MAX;

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
pub fn ref_lo(r: &PrimRef) -> Vec3A {
    let a: &[[f32; 4]; 2] = bytemuck::cast_ref(r);
    Vec3A::from_vec4(Vec4::select(XYZ_MASK, Vec4::from_array(a[0]), Vec4::ZERO))
}
#[inline(always)]
pub fn ref_hi(r: &PrimRef) -> Vec3A {
    let a: &[[f32; 4]; 2] = bytemuck::cast_ref(r);
    Vec3A::from_vec4(Vec4::select(XYZ_MASK, Vec4::from_array(a[1]), Vec4::ZERO))
}
const XYZ_MASK: glam::BVec4A = glam::BVec4A::from_array([true, true, true, false]);

#[inline]
pub fn centroid(r: &PrimRef) -> [f32; 3] {
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
    view.acceleration_structure(reference).and_then(super::clas::open_walkable).map(|w| w.0).filter(|p| p.raw.primitive_count > 0).map(|p| p.raw.bounds)
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
                    // lo <= hi lane by lane (monotonic rounding again), so `sanitize` only
                    // clamps the infinities: lane-wise here, where no lane is a zero (its
                    // scalar min/max may pick either sign of a zero; `sanitize` decides those).
                    if (lo.cmpne(Vec3A::ZERO) & hi.cmpne(Vec3A::ZERO)).all() {
                        let (least, most) = (Vec3A::splat(-f32::MAX), Vec3A::splat(f32::MAX));
                        return (lo.max(least).min(most).to_array(), hi.max(least).min(most).to_array());
                    }
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
pub fn instance_box_corners(m: &[f32; 12], bb: &[f32; 6]) -> ([f32; 3], [f32; 3]) {
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

#[inline]
pub fn half_area_vec(lo: Vec3A, hi: Vec3A) -> f32 {
    // (xy + yz) + zx, the same sum as `Aabb::half_area`, as one multiply and a lane sum.
    let d = (hi - lo).max(Vec3A::ZERO);
    (d * d.yzx()).element_sum()
}

pub fn to_aabb(lo: Vec3A, hi: Vec3A) -> Aabb {
    Aabb { lo: lo.to_array(), hi: hi.to_array() }
}

/// The bounding box of `refs`.
pub fn box_of(refs: &[PrimRef]) -> Aabb {
    let (mut lo, mut hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    for r in refs {
        lo = lo.min(ref_lo(r));
        hi = hi.max(ref_hi(r));
    }
    to_aabb(lo, hi)
}
/// `triangle_bounds` of vertices in registers: when every lane is finite (v - v is 0 for finite
/// v, NaN for NaN and inf, and NaN survives the sums) vector min/max are exact; otherwise the
/// sanitising path. A max of the |v| would not do: maxps drops a NaN operand, which would hide
/// a NaN y or z from the huge box.
#[inline(always)]
#[allow(clippy::eq_op)] // v - v is the finiteness test, not a zero.
pub fn triangle_box(a: Vec3A, b: Vec3A, c: Vec3A) -> (Vec3A, Vec3A) {
    if ((a - a) + (b - b) + (c - c)).cmpeq(Vec3A::ZERO).all() {
        return (a.min(b).min(c), a.max(b).max(c));
    }
    let (lo, hi) = triangle_bounds(&[a.into(), b.into(), c.into()]);
    (Vec3A::from(lo), Vec3A::from(hi))
}



/// Lane-wise truncation of values already clamped to [0, 2^22), read as integers from the
/// mantissa: v + 2^23 rounds v to the nearest integer (exactly: the spacing there is 1), one is
/// taken off where that rounded up, and the mantissa of the result is floor(v) = trunc(v).
/// Five vector operations, where glam's SSE2 floor takes about eight; replaces saturating
/// float-to-int conversions, with no unsafe intrinsics.
#[inline(always)]
pub fn trunc_lanes3(v: Vec3A) -> [i32; 4] {
    trunc_lanes(Vec4::from((v, 0.0)))
}

/// `trunc_lanes3` for four lanes.
#[inline(always)]
pub fn trunc_lanes(v: Vec4) -> [i32; 4] {
    const MAGIC: f32 = 8_388_608.0;
    let y = v + Vec4::splat(MAGIC);
    let up = (y - Vec4::splat(MAGIC)).cmpgt(v);
    let y = y - Vec4::select(up, Vec4::ONE, Vec4::ZERO);
    y.to_array().map(|f| (f.to_bits() & 0x7f_ffff) as i32)
}

/// floor(v) lane-wise for v in [0, 2^22): v + 2^23 - 2^23 rounds v to an integer exactly, and
/// one comes off where that rounded up (four vector operations).
#[inline(always)]
pub fn floor_lanes(v: Vec4) -> Vec4 {
    const MAGIC: f32 = 8_388_608.0;
    let r = (v + Vec4::splat(MAGIC)) - Vec4::splat(MAGIC);
    r - Vec4::select(r.cmpgt(v), Vec4::ONE, Vec4::ZERO)
}


#[cfg(test)]
mod tests;

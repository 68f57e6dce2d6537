//! The brute-force reference of the Vulkan ray traversal rules (written from the specification,
//! not from `arbor::accel`'s traversal) and the comparison of the library's closest_hit, any_hit
//! and all_hits with it.

use arbor::accel::{self, DeviceView, Geometry, GeometryData, Hit, HitKind, Ray, RayFlags};
use arbor_scene::InstanceRecord;
use glam::Vec3;
use std::collections::{BTreeSet, HashMap};

use super::{
    invert_3x4, xform_point, xform_vector, CULL_BACK, CULL_FRONT, CULL_NO_OPAQUE, CULL_OPAQUE, FACING_CULL_DISABLE, FLIP_FACING,
    FORCE_NO_OPAQUE, FORCE_OPAQUE, GEOMETRY_OPAQUE, NO_OPAQUE, OPAQUE, SKIP_AABBS, SKIP_TRIANGLES, TERMINATE_ON_FIRST_HIT,
};

/// What the reference traverses: a BLAS (its geometries) or a TLAS (its instance records in
/// array order, including inactive ones, and the BLASes they refer to).
pub enum RefScene<'a> {
    Blas(&'a [Geometry<'a>]),
    Tlas { instances: Vec<InstanceRecord>, blases: HashMap<u64, &'a [Geometry<'a>]> },
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct PrimId {
    pub instance: u32,
    pub geometry: u32,
    pub primitive: u32,
}

#[derive(Clone, Debug)]
pub struct RefHit {
    pub id: PrimId,
    pub t: f32,
    pub triangle: bool,
    /// After FLIP_FACING (triangles).
    pub front: bool,
    pub opaque: bool,
    pub custom_index: u32,
    pub sbt_offset: u32,
    /// Barycentrics (weights of v1, v2) from `intersect_triangle` on the reference's ray.
    pub uv: [f32; 2],
    /// How far this decision is from flipping, computed in f64: for triangles the smallest
    /// barycentric / the relative distance of t to tmin/tmax; for boxes the relative slab gap.
    /// Mismatches with the library are forgiven only when the margin is tiny and the ray went
    /// through an instance transform (whose f32 rounding the reference cannot reproduce).
    pub margin: f64,
}

/// Every intersection the Vulkan rules make a candidate (or an opaque hit) for `ray`, each
/// primitive once, not sorted. Near-misses are returned too, flagged by `hit == false`, so that
/// callers can tell robust disagreements from rounding ones.
pub struct RefResult {
    pub hits: Vec<RefHit>,
    /// Primitives missed by less than the tolerance (ambiguous), and whether each is a triangle.
    pub near_misses: Vec<(PrimId, bool)>,
}

const AMBIGUOUS: f64 = 1e-5;

pub fn hit_id(h: &Hit) -> PrimId {
    PrimId { instance: h.instance_index, geometry: h.geometry_index, primitive: h.primitive_index }
}

/// Double-precision ray/triangle (Möller–Trumbore, no epsilon): (t, u, v, det·sign) or None
/// when parallel. u, v may be outside [0,1]: the caller judges with margins.
pub fn intersect_f64(o: [f64; 3], d: [f64; 3], v0: [f64; 3], v1: [f64; 3], v2: [f64; 3]) -> Option<(f64, f64, f64)> {
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let cross = |a: [f64; 3], b: [f64; 3]| [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let e1 = sub(v1, v0);
    let e2 = sub(v2, v0);
    let p = cross(d, e2);
    let det = dot(e1, p);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv = 1.0 / det;
    let s = sub(o, v0);
    let u = dot(s, p) * inv;
    let q = cross(s, e1);
    let v = dot(d, q) * inv;
    let t = dot(e2, q) * inv;
    Some((t, u, v))
}

/// Facing in object space, independent of the library: front iff ((v1-v0)x(v2-v0))·dir < 0
/// (DXR/Vulkan: clockwise as seen from the ray origin in a left-handed frame).
pub fn front_facing_f64(d: [f64; 3], v0: [f64; 3], v1: [f64; 3], v2: [f64; 3]) -> bool {
    let e1 = [v1[0] - v0[0], v1[1] - v0[1], v1[2] - v0[2]];
    let e2 = [v2[0] - v0[0], v2[1] - v0[1], v2[2] - v0[2]];
    let n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
    n[0] * d[0] + n[1] * d[1] + n[2] * d[2] < 0.0
}

fn v3(v: Vec3) -> [f64; 3] {
    [v.x as f64, v.y as f64, v.z as f64]
}

/// Slab test in f64: (t_enter, t_exit), possibly empty (enter > exit).
pub fn slab_f64(o: [f64; 3], d: [f64; 3], b: &[f32; 6]) -> (f64, f64) {
    let mut t0 = f64::NEG_INFINITY;
    let mut t1 = f64::INFINITY;
    for k in 0..3 {
        let (lo, hi) = (b[k] as f64, b[k + 3] as f64);
        if d[k] == 0.0 {
            if o[k] < lo || o[k] > hi {
                return (f64::INFINITY, f64::NEG_INFINITY);
            }
        } else {
            let a = (lo - o[k]) / d[k];
            let c = (hi - o[k]) / d[k];
            t0 = t0.max(a.min(c));
            t1 = t1.min(a.max(c));
        }
    }
    (t0, t1)
}

/// The reference traversal of one BLAS for an object-space ray.
// One function: the reference rules per primitive (opacity, culling, margins) read in one place.
// why: the ray in two precisions and the four attributes of the instance that reached the BLAS
// (0 for a bare BLAS) are what a reference hit records; two private call sites.
#[allow(clippy::too_many_arguments)]
fn ref_blas(
    geometries: &[Geometry],
    ray: &Ray,
    ray64: ([f64; 3], [f64; 3]),
    flags: u32,
    instance: u32,
    inst_flags: u8,
    custom_index: u32,
    sbt_offset: u32,
    out: &mut RefResult,
) {
    let (tmin, tmax) = (ray.tmin, ray.tmax);
    let (o64, d64) = ray64;
    let tscale = |t: f64| t.abs().max(1.0);
    for (gi, g) in geometries.iter().enumerate() {
        let is_tri = matches!(g.data, GeometryData::Triangles { .. });
        if (is_tri && flags & SKIP_TRIANGLES != 0) || (!is_tri && flags & SKIP_AABBS != 0) {
            continue;
        }
        // Opacity: geometry flag, overridden by instance flags, overridden by ray flags.
        let mut opaque = g.flags.0 & GEOMETRY_OPAQUE != 0;
        if inst_flags & FORCE_OPAQUE != 0 {
            opaque = true;
        }
        if inst_flags & FORCE_NO_OPAQUE != 0 {
            opaque = false;
        }
        if flags & OPAQUE != 0 {
            opaque = true;
        }
        if flags & NO_OPAQUE != 0 {
            opaque = false;
        }
        if (opaque && flags & CULL_OPAQUE != 0) || (!opaque && flags & CULL_NO_OPAQUE != 0) {
            continue;
        }
        for p in 0..g.primitive_count {
            let id = PrimId { instance, geometry: gi as u32, primitive: p };
            if is_tri {
                let Some([a, b, c]) = accel::fetch_triangle(g, p) else { continue };
                let (a64, b64, c64) = (v3(a), v3(b), v3(c));
                let mut front = front_facing_f64(d64, a64, b64, c64);
                if inst_flags & FLIP_FACING != 0 {
                    front = !front;
                }
                let culled = inst_flags & FACING_CULL_DISABLE == 0
                    && ((front && flags & CULL_FRONT != 0) || (!front && flags & CULL_BACK != 0));
                // Margin in f64 (for judging mismatches that come from rounding only).
                let margin = match intersect_f64(o64, d64, a64, b64, c64) {
                    Some((t, u, v)) => {
                        let bary = u.min(v).min(1.0 - u - v);
                        let tm = ((t - tmin as f64) / tscale(t)).min((tmax as f64 - t) / tscale(t));
                        bary.min(tm)
                    }
                    None => -1.0,
                };
                let hit = accel::intersect_triangle(ray, a, b, c).filter(|&(t, ..)| t >= tmin && t <= tmax);
                match hit {
                    Some((t, u, v, _)) if !culled => out.hits.push(RefHit {
                        id,
                        t,
                        uv: [u, v],
                        triangle: true,
                        front,
                        opaque,
                        custom_index,
                        sbt_offset,
                        margin: margin.abs(),
                    }),
                    Some(_) => {}
                    None => {
                        if !culled && margin.abs() < AMBIGUOUS {
                            out.near_misses.push((id, true));
                        }
                    }
                }
            } else {
                let Some(bx) = accel::fetch_aabb(g, p) else { continue };
                let (t0, t1) = slab_f64(o64, d64, &bx);
                let lo = t0.max(tmin as f64);
                let hi = t1.min(tmax as f64);
                let gap = (hi - lo) / tscale(lo.abs().max(hi.abs()).min(1e30));
                if lo <= hi {
                    out.hits.push(RefHit {
                        id,
                        t: lo as f32,
                        triangle: false,
                        front: false,
                        opaque,
                        custom_index,
                        sbt_offset,
                        uv: [0.0; 2],
                        margin: gap.abs(),
                    });
                } else if gap.abs() < AMBIGUOUS || !gap.is_finite() {
                    out.near_misses.push((id, false));
                }
            }
        }
    }
}

/// Brute force over every primitive (and instance) of the scene.
pub fn reference(scene: &RefScene, ray: &Ray, flags: u32, cull_mask: u8) -> RefResult {
    let mut out = RefResult { hits: Vec::new(), near_misses: Vec::new() };
    match scene {
        RefScene::Blas(geoms) => {
            ref_blas(geoms, ray, (v3(ray.origin), v3(ray.direction)), flags, 0, 0, 0, 0, &mut out);
        }
        RefScene::Tlas { instances, blases } => {
            for (i, inst) in instances.iter().enumerate() {
                if inst.reference == 0 || inst.mask & cull_mask == 0 {
                    continue;
                }
                let Some(geoms) = blases.get(&inst.reference) else {
                    panic!("reference scene lacks BLAS {:#x}", inst.reference)
                };
                let Some(inv) = invert_3x4(&inst.transform) else { continue };
                let o = xform_point(&inv, v3(ray.origin));
                let d = xform_vector(&inv, v3(ray.direction));
                let obj = Ray {
                    origin: Vec3::new(o[0] as f32, o[1] as f32, o[2] as f32),
                    direction: Vec3::new(d[0] as f32, d[1] as f32, d[2] as f32),
                    tmin: ray.tmin,
                    tmax: ray.tmax,
                };
                ref_blas(geoms, &obj, (o, d), flags, i as u32, inst.flags, inst.custom_index, inst.sbt_offset, &mut out);
            }
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Comparing the library with the reference

/// Tolerances: `exact` for BLAS (same decode, same intersection function: bit-equal t),
/// relaxed for TLAS (the object-space ray is rounded differently).
#[derive(Clone, Copy, Debug)]
pub struct Tolerance {
    pub exact: bool,
}

impl Tolerance {
    /// Whether a disagreement on a primitive this close to the decision boundary is rounding:
    /// always for boxes (slab tests round differently), for triangles only in TLAS mode.
    pub fn forgive(&self, triangle: bool, margin: f64) -> bool {
        margin < AMBIGUOUS && (!self.exact || !triangle)
    }

    pub fn near_miss(&self, r: &RefResult, id: PrimId) -> bool {
        r.near_misses.iter().any(|&(n, tri)| n == id && (!self.exact || !tri))
    }

    fn t_equal(&self, a: f32, b: f32, triangle: bool) -> bool {
        if self.exact && triangle {
            a == b
        } else {
            (a - b).abs() <= 2e-5 * a.abs().max(b.abs()).max(1.0)
        }
    }
}

/// Checks a library hit's attributes against the reference hit of the same primitive.
fn check_hit_fields(h: &Hit, r: &RefHit, tol: Tolerance, ctx: &str) {
    let tri = matches!(h.kind, HitKind::Triangle);
    assert_eq!(tri, r.triangle, "{ctx}: kind of {:?}", r.id);
    if tri {
        assert!(tol.t_equal(h.t, r.t, true), "{ctx}: t of {:?}: lib {} ref {}", r.id, h.t, r.t);
        if r.margin > AMBIGUOUS {
            assert_eq!(h.front_face, r.front, "{ctx}: front_face of {:?}", r.id);
        }
        if tol.exact {
            assert_eq!(h.barycentrics, r.uv, "{ctx}: barycentrics of {:?}", r.id);
        } else if r.margin > 1e-3 {
            let close = (h.barycentrics[0] - r.uv[0]).abs() < 1e-3 && (h.barycentrics[1] - r.uv[1]).abs() < 1e-3;
            assert!(close, "{ctx}: barycentrics of {:?}: {:?} vs {:?}", r.id, h.barycentrics, r.uv);
        }
    }
    assert_eq!(h.opaque, r.opaque, "{ctx}: opaque of {:?}", r.id);
    assert_eq!(h.instance_custom_index, r.custom_index, "{ctx}: custom index of {:?}", r.id);
    assert_eq!(h.sbt_record_offset, r.sbt_offset, "{ctx}: sbt offset of {:?}", r.id);
}

/// all_hits (as a set of primitives) == reference set, up to rounding-ambiguous primitives
/// (only in TLAS mode). With TERMINATE_ON_FIRST_HIT only "non-empty iff reference non-empty"
/// and "subset" are required.
pub fn check_all_hits(lib: &[Hit], r: &RefResult, flags: u32, tol: Tolerance, ctx: &str) {
    let by_id: HashMap<PrimId, &RefHit> = r.hits.iter().map(|h| (h.id, h)).collect();
    let mut seen = BTreeSet::new();
    for h in lib {
        let id = hit_id(h);
        assert!(seen.insert(id), "{ctx}: all_hits reports {id:?} twice");
        match by_id.get(&id) {
            Some(rh) => check_hit_fields(h, rh, tol, ctx),
            None => assert!(
                tol.near_miss(r, id),
                "{ctx}: all_hits reports {id:?} (t {}) that the reference does not hit",
                h.t
            ),
        }
    }
    let forgivable = |rh: &RefHit| tol.forgive(rh.triangle, rh.margin);
    if flags & TERMINATE_ON_FIRST_HIT == 0 {
        for rh in &r.hits {
            assert!(seen.contains(&rh.id) || forgivable(rh), "{ctx}: all_hits misses {:?} at t {} (margin {:e})", rh.id, rh.t, rh.margin);
        }
    } else if r.hits.iter().any(|h| !forgivable(h)) {
        assert!(!lib.is_empty(), "{ctx}: all_hits with TERMINATE_ON_FIRST_HIT found nothing");
    }
}

/// closest_hit == the reference's nearest (t, identity; ties by t accepted), any_hit ∈ reference.
pub fn check_closest(lib: Option<&Hit>, r: &RefResult, flags: u32, tol: Tolerance, ctx: &str) {
    let by_id: HashMap<PrimId, &RefHit> = r.hits.iter().map(|h| (h.id, h)).collect();
    let best = r.hits.iter().min_by(|a, b| a.t.total_cmp(&b.t).then(a.id.cmp(&b.id)));
    if flags & TERMINATE_ON_FIRST_HIT != 0 {
        // Any reference hit will do.
        match lib {
            Some(h) => {
                let id = hit_id(h);
                match by_id.get(&id) {
                    Some(rh) => check_hit_fields(h, rh, tol, ctx),
                    None => assert!(tol.near_miss(r, id), "{ctx}: first hit {id:?} is not a hit"),
                }
            }
            None => assert!(
                r.hits.iter().all(|h| tol.forgive(h.triangle, h.margin)),
                "{ctx}: TERMINATE_ON_FIRST_HIT found nothing, reference has {} hits",
                r.hits.len()
            ),
        }
        return;
    }
    match (lib, best) {
        (None, None) => {}
        (Some(h), None) => {
            let id = hit_id(h);
            assert!(tol.near_miss(r, id), "{ctx}: closest hit {id:?} t {} but reference misses", h.t)
        }
        (None, Some(b)) => {
            // Only forgivable when every reference hit is ambiguous.
            assert!(
                r.hits.iter().all(|h| tol.forgive(h.triangle, h.margin)),
                "{ctx}: closest misses, reference hits {:?} at t {}",
                b.id,
                b.t
            );
        }
        (Some(h), Some(b)) => {
            let id = hit_id(h);
            let tri = matches!(h.kind, HitKind::Triangle);
            if tri && b.triangle {
                assert!(tol.t_equal(h.t, b.t, true) || tol.forgive(true, b.margin), "{ctx}: closest t lib {} ({id:?}) ref {} ({:?})", h.t, b.t, b.id);
            } else {
                assert!(tol.t_equal(h.t, b.t, false) || tol.forgive(b.triangle, b.margin) || tol.forgive(tri, 0.0), "{ctx}: closest t lib {} ({id:?}) ref {} ({:?})", h.t, b.t, b.id);
            }
            if id != b.id {
                // A tie (shared edge, coincident faces, boxes entered at tmin) is fine.
                let rh = by_id.get(&id).copied();
                match rh {
                    Some(rh) => assert!(
                        tol.t_equal(rh.t, b.t, rh.triangle && b.triangle) || tol.forgive(rh.triangle, rh.margin) || tol.forgive(b.triangle, b.margin),
                        "{ctx}: closest is {id:?} at {} but reference nearest is {:?} at {}",
                        rh.t,
                        b.id,
                        b.t
                    ),
                    None => assert!(tol.near_miss(r, id), "{ctx}: closest {id:?} is not a reference hit"),
                }
            }
            if let Some(rh) = by_id.get(&id) {
                check_hit_fields(h, rh, tol, ctx);
            }
        }
    }
}

/// Runs closest_hit, any_hit and all_hits for one ray and compares each with the reference.
// why: each argument is an independent input of the comparison (structure, view, scene, ray,
// flags, mask, tolerance, label), and the many one-line call sites read best flat.
#[allow(clippy::too_many_arguments)]
pub fn compare_ray(structure: &[u8], view: &dyn DeviceView, scene: &RefScene, ray: &Ray, flags: u32, mask: u8, tol: Tolerance, ctx: &str) -> usize {
    let r = reference(scene, ray, flags, mask);
    let all = accel::all_hits(structure, view, copy_ray(ray), RayFlags(flags), mask);
    check_all_hits(&all, &r, flags, tol, ctx);
    let closest = accel::closest_hit(structure, view, copy_ray(ray), RayFlags(flags), mask);
    check_closest(closest.as_ref(), &r, flags, tol, &format!("{ctx} closest_hit"));
    let any = accel::any_hit(structure, view, copy_ray(ray), RayFlags(flags), mask);
    check_closest(any.as_ref(), &r, flags | TERMINATE_ON_FIRST_HIT, tol, &format!("{ctx} any_hit"));
    r.hits.len()
}

pub fn copy_ray(r: &Ray) -> Ray {
    Ray { origin: r.origin, direction: r.direction, tmin: r.tmin, tmax: r.tmax }
}

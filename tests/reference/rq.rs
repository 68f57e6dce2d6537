//! What tests/shaders/rq_api.comp must write, from the brute-force reference: its rays (each with
//! its own flags, cull mask and mode), its 16-word records, the reference of what it may commit
//! (triangles after its alpha rule, boxes replaced by the spheres it intersects), the check of
//! one record against that reference, and the comparison of two drivers' records.

use arbor::accel::{Geometry, Hit, HitKind, Ray};
use arbor_scene::{InstanceRecord, Rng};
use glam::Vec3;

use super::brute_force::{check_closest, reference, RefHit, RefResult, RefScene, Tolerance};
use super::*;

/// Below this a decision is a matter of rounding (the brute-force reference's threshold).
pub const AMBIGUOUS: f64 = 1e-5;

/// One ray of rq_api.comp. `mode` bit 0: confirm non-opaque triangles of even primitive index
/// only.
#[derive(Clone, Copy, Debug)]
pub struct RqRay {
    pub ray: Ray,
    pub flags: u32,
    pub cull: u8,
    pub mode: u32,
}

/// The rays buffer: origin, tmin, direction, tmax, flags, cull mask, mode, 0 (48 bytes each).
pub fn ray_bytes(rays: &[RqRay]) -> Vec<u8> {
    let mut out = Vec::with_capacity(48 * rays.len());
    for r in rays {
        let (o, d) = (r.ray.origin, r.ray.direction);
        for v in [o.x, o.y, o.z, r.ray.tmin, d.x, d.y, d.z, r.ray.tmax] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for w in [r.flags, r.cull as u32, r.mode, 0] {
            out.extend_from_slice(&w.to_le_bytes());
        }
    }
    out
}

/// The spheres buffer (centre, radius per primitive) and the boxes around them.
pub fn sphere_bytes(spheres: &[[f32; 4]]) -> Vec<u8> {
    spheres.iter().flatten().flat_map(|x| x.to_le_bytes()).collect()
}

pub fn sphere_boxes(spheres: &[[f32; 4]]) -> Vec<[f32; 6]> {
    spheres.iter().map(|s| [s[0] - s[3], s[1] - s[3], s[2] - s[3], s[0] + s[3], s[1] + s[3], s[2] + s[3]]).collect()
}

/// One record of rq_api.comp.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Record {
    /// Committed type: 0 none, 1 triangle, 2 generated.
    pub kind: u32,
    pub t: f32,
    pub instance: u32,
    pub custom: u32,
    pub geometry: u32,
    pub primitive: u32,
    pub bary: [f32; 2],
    pub front: bool,
    pub sbt: u32,
    /// The committed hit is the last one the shader confirmed or generated.
    pub decided: bool,
    /// The candidate AABB opacity the shader saw when it generated the committed hit.
    pub aabb_opaque: bool,
    pub candidates: u32,
}

pub fn records(bytes: &[u8]) -> Vec<Record> {
    let w: Vec<u32> = bytes.chunks(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
    w.chunks(16)
        .map(|r| Record {
            kind: r[0],
            t: f32::from_bits(r[1]),
            instance: r[2],
            custom: r[3],
            geometry: r[4],
            primitive: r[5],
            bary: [f32::from_bits(r[6]), f32::from_bits(r[7])],
            front: r[8] != 0,
            sbt: r[9],
            decided: r[10] != 0,
            aabb_opaque: r[11] != 0,
            candidates: r[12],
        })
        .collect()
}

/// The object-space t at which the ray enters the sphere, and how far that decision is from
/// flipping (relative discriminant, distance to the interval's ends).
fn sphere_hit(inst: &InstanceRecord, ray: &Ray, s: [f32; 4]) -> (Option<f64>, f64) {
    let inv = invert_3x4(&inst.transform).expect("invertible instance transform");
    let f = |v: Vec3| [v.x as f64, v.y as f64, v.z as f64];
    let (o, d) = (xform_point(&inv, f(ray.origin)), xform_vector(&inv, f(ray.direction)));
    let oc = [o[0] - s[0] as f64, o[1] - s[1] as f64, o[2] - s[2] as f64];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let r = s[3] as f64;
    let (a, b, c) = (dot(d, d), dot(oc, d), dot(oc, oc) - r * r);
    let disc = b * b - a * c;
    let disc_margin = disc.abs() / (b * b + (a * c).abs()).max(1e-300);
    if disc < 0.0 {
        return (None, disc_margin);
    }
    let t = (-b - disc.sqrt()) / a;
    let scale = t.abs().max(1.0);
    let (lo, hi) = ((t - ray.tmin as f64) / scale, (ray.tmax as f64 - t) / scale);
    let margin = disc_margin.min(lo.abs()).min(hi.abs());
    ((lo >= 0.0 && hi >= 0.0).then_some(t), margin)
}

/// What rq_api.comp may commit for `r`: the reference's hits, non-opaque triangles of odd
/// primitive index dropped under mode bit 0, boxes replaced by their sphere's hit (or dropped,
/// a near miss when the decision is within rounding). Spheres of geometry g, primitive p are
/// `spheres[g * stride + p]`.
pub fn shader_reference(scene: &RefScene, instances: &[InstanceRecord], spheres: &[[f32; 4]], stride: u32, r: &RqRay) -> RefResult {
    let base = reference(scene, &r.ray, r.flags, r.cull);
    let mut out = RefResult { hits: Vec::new(), near_misses: base.near_misses };
    for h in base.hits {
        if h.triangle {
            if r.mode & 1 == 0 || h.opaque || h.id.primitive & 1 == 0 {
                out.hits.push(h);
            }
            continue;
        }
        let s = spheres[(h.id.geometry * stride + h.id.primitive) as usize];
        match sphere_hit(&instances[h.id.instance as usize], &r.ray, s) {
            (Some(t), margin) => out.hits.push(RefHit { t: t as f32, margin, ..h }),
            (None, margin) if margin < AMBIGUOUS => out.near_misses.push((h.id, false)),
            (None, _) => {}
        }
    }
    out
}

/// A record as the library's hit type, for `check_closest`. Opacity is what the shader saw: a
/// triangle it confirmed was a candidate (not opaque), one it did not was committed by the
/// traversal (opaque); a generated hit has its candidate's AABB opacity.
pub fn hit_of(rec: &Record) -> Option<Hit> {
    let kind = match rec.kind {
        0 => return None,
        1 => HitKind::Triangle,
        2 => HitKind::Aabb,
        k => panic!("committed type {k}"),
    };
    let opaque = if kind == HitKind::Triangle { !rec.decided } else { rec.aabb_opaque };
    Some(Hit {
        t: rec.t,
        kind,
        barycentrics: rec.bary,
        front_face: rec.front,
        opaque,
        instance_index: rec.instance,
        instance_custom_index: rec.custom,
        sbt_record_offset: rec.sbt,
        geometry_index: rec.geometry,
        primitive_index: rec.primitive,
        object_ray_origin: Vec3::ZERO,
        object_ray_direction: Vec3::ZERO,
        object_to_world: [0.0; 12],
        world_to_object: [0.0; 12],
        vertices: [Vec3::ZERO; 3],
        cluster_id: -1,
    })
}

/// One record against the shader's reference (nearest hit up to ties and rounding; any hit
/// with TERMINATE_ON_FIRST_HIT). Returns whether something was committed.
pub fn check_record(rec: &Record, r: &RefResult, ray: &RqRay, ctx: &str) -> bool {
    if rec.kind == 0 {
        assert_eq!((rec.t, rec.instance, rec.primitive), (0.0, 0, 0), "{ctx}: a miss record writes nothing but its type and count");
    }
    if rec.kind == 2 {
        assert!(rec.decided, "{ctx}: a generated hit the shader did not generate");
    }
    let hit = hit_of(rec);
    check_closest(hit.as_ref(), r, ray.flags, Tolerance { exact: false }, ctx);
    hit.is_some()
}

/// Whether the reference leaves this ray's answer to rounding: a hit or near miss within
/// `AMBIGUOUS` of flipping, or two accepted hits at the same t (a tie either driver may take).
pub fn ambiguous(r: &RefResult) -> bool {
    let mut ts: Vec<f32> = r.hits.iter().map(|h| h.t).collect();
    ts.sort_by(f32::total_cmp);
    !r.near_misses.is_empty() || r.hits.iter().any(|h| h.margin < AMBIGUOUS) || ts.windows(2).take(1).any(|w| w[1] - w[0] <= 1e-6 * w[0].abs().max(1.0))
}

fn close(a: f32, b: f32, rel: f32) -> bool {
    (a - b).abs() <= rel * a.abs().max(b.abs()).max(1.0)
}

/// Two drivers' records of the same rays: hit or miss, then (without TERMINATE_ON_FIRST_HIT)
/// type, instance, geometry and primitive exactly unless the two hits tie in t, t within `rel`
/// relative, barycentrics within `bary_tol(ray index, record)`, front face, custom index and
/// SBT offset. A ray the reference calls ambiguous may differ; returns how many did.
pub fn compare_drivers(a: &[Record], b: &[Record], rays: &[RqRay], refs: &[RefResult], rel: f32, bary_tol: &dyn Fn(usize, &Record) -> f32, what: &str) -> usize {
    let mut forgiven = 0;
    for (i, ((x, y), ray)) in a.iter().zip(b).zip(rays).enumerate() {
        let ctx = format!("{what}: ray {i} flags {:#x} cull {:#x} mode {}", ray.flags, ray.cull, ray.mode);
        let same = if ray.flags & TERMINATE_ON_FIRST_HIT != 0 {
            (x.kind == 0) == (y.kind == 0)
        } else if x.kind != y.kind {
            false
        } else if x.kind == 0 {
            true
        } else {
            let tie_or_same = (x.instance, x.geometry, x.primitive) == (y.instance, y.geometry, y.primitive) || close(x.t, y.t, rel);
            let fields = (x.instance, x.geometry, x.primitive) != (y.instance, y.geometry, y.primitive)
                || ((0..2).all(|k| (x.bary[k] - y.bary[k]).abs() <= bary_tol(i, x)) && (x.front, x.custom, x.sbt) == (y.front, y.custom, y.sbt));
            tie_or_same && close(x.t, y.t, rel) && fields
        };
        if !same {
            assert!(ambiguous(&refs[i]), "{ctx}: the drivers differ: {x:?} vs {y:?}");
            println!("{ctx}: differs where the reference is ambiguous: {x:?} vs {y:?}");
            forgiven += 1;
        }
    }
    forgiven
}

// ---------------------------------------------------------------------------------------------
// Scenes and rays

/// A scene for rq_api.comp: BLAS 1 the mesh (non-opaque) and an opaque triangle soup with a
/// geometry transform, BLAS 2 the mesh again (opaque), BLAS 3 spheres in two AABB geometries
/// (opaque, non-opaque); instances over them with every instance flag combination, several
/// masks, rotations with non-uniform scales, one inactive. An instance's `reference` is its
/// BLAS index + 1 (0: inactive), the key of the reference scene's BLASes too.
pub struct RqScene {
    pub blases: Vec<(Vec<TriData>, Vec<AabbData>)>,
    pub instances: Vec<InstanceRecord>,
    pub spheres: Vec<[f32; 4]>,
    /// Spheres per AABB geometry: geometry g's primitive p is spheres[g * stride + p].
    pub stride: u32,
    pub bounds: [f32; 6],
}

pub const INSTANCE_MASKS: [u8; 6] = [0xFF, 0x01, 0x02, 0x80, 0x0F, 0xF0];
pub const CULL_MASKS: [u8; 5] = [0xFF, 0x01, 0x70, 0x80, 0x0F];

/// `mesh` moved and scaled into the unit cube.
pub fn unit_cube(m: &arbor_scene::Mesh) -> arbor_scene::Mesh {
    let b = m.bounds();
    let s = 1.0 / (b[3] - b[0]).max(b[4] - b[1]).max(b[5] - b[2]);
    let positions = m.positions.iter().map(|p| [(p[0] - b[0]) * s, (p[1] - b[1]) * s, (p[2] - b[2]) * s]).collect();
    arbor_scene::Mesh { positions, indices: m.indices.clone() }
}

impl RqScene {
    pub fn new(mesh: &arbor_scene::Mesh, instance_count: usize, seed: u64) -> RqScene {
        let mesh = unit_cube(mesh);
        let mut soup = TriData::from_mesh(&arbor_scene::random_soup(200, seed), GEOMETRY_OPAQUE);
        soup.transform = Some([0.9, 0.2, 0.0, 0.05, 0.0, 1.1, 0.1, 0.0, -0.1, 0.0, 0.8, 0.1]);
        let mut rng = Rng::new(seed + 1);
        let stride = 40u32;
        let spheres: Vec<[f32; 4]> = (0..2 * stride).map(|_| [rng.range(0.1, 0.9), rng.range(0.1, 0.9), rng.range(0.1, 0.9), rng.range(0.03, 0.1)]).collect();
        let boxes = sphere_boxes(&spheres);
        let blases = vec![
            (vec![TriData::from_mesh(&mesh, 0), soup], vec![]),
            (vec![TriData::from_mesh(&mesh, GEOMETRY_OPAQUE)], vec![]),
            (vec![], vec![AabbData::new(&boxes[..stride as usize], 24, GEOMETRY_OPAQUE), AabbData::new(&boxes[stride as usize..], 32, 0)]),
        ];
        let refs: Vec<u64> = (1..=blases.len() as u64).collect();
        let mut instances = arbor_scene::instance_records(instance_count, &refs, seed);
        let flag_sets = all_instance_flag_combinations();
        for (i, inst) in instances.iter_mut().enumerate() {
            // Non-uniform scale after the rotation: object axes stretched differently.
            let s = [rng.range(0.6, 1.6), rng.range(0.6, 1.6), rng.range(0.6, 1.6)];
            for r in 0..3 {
                for (c, sc) in s.iter().enumerate() {
                    inst.transform[4 * r + c] *= sc;
                }
            }
            inst.flags = flag_sets[i % flag_sets.len()];
            inst.mask = INSTANCE_MASKS[rng.below(INSTANCE_MASKS.len() as u32) as usize];
            inst.custom_index = rng.next_u32() & 0xFF_FFFF;
            inst.sbt_offset = rng.next_u32() & 0xFF_FFFF;
            if i % 11 == 5 {
                inst.reference = 0;
            }
        }
        let mut corners = Vec::new();
        for inst in instances.iter().filter(|i| i.reference != 0) {
            let m: [f64; 12] = inst.transform.map(|x| x as f64);
            for c in 0..8 {
                let p = [(c & 1) as f64, ((c >> 1) & 1) as f64, ((c >> 2) & 1) as f64];
                corners.push(xform_point(&m, p).map(|x| x as f32));
            }
        }
        RqScene { blases, instances, spheres, stride, bounds: union_bounds(corners) }
    }

    /// Each BLAS's geometries (triangles first, then boxes).
    pub fn geoms(&self) -> Vec<Vec<Geometry<'_>>> {
        self.blases.iter().map(|(t, b)| t.iter().map(|d| d.geometry()).chain(b.iter().map(|x| x.geometry())).collect()).collect()
    }

    pub fn reference_scene<'a>(&self, geoms: &'a [Vec<Geometry<'a>>]) -> RefScene<'a> {
        RefScene::Tlas { instances: self.instances.clone(), blases: geoms.iter().enumerate().map(|(k, g)| (k as u64 + 1, g.as_slice())).collect() }
    }

    /// `per_flags` rays for each flag set, each aimed at a random point of a random active
    /// instance from a random direction (a third start inside the object's box, a third stop
    /// at a finite tmax, some start at tmin > 0); cull masks and modes vary between them.
    pub fn rays(&self, flag_sets: &[u32], per_flags: usize, seed: u64) -> Vec<RqRay> {
        let mut rng = Rng::new(seed);
        let active: Vec<&InstanceRecord> = self.instances.iter().filter(|i| i.reference != 0).collect();
        (0..flag_sets.len() * per_flags)
            .map(|i| {
                let inst = active[rng.below(active.len() as u32) as usize];
                let m: [f64; 12] = inst.transform.map(|x| x as f64);
                let local = [rng.range(0.1, 0.9), rng.range(0.1, 0.9), rng.range(0.1, 0.9)].map(|x| x as f64);
                let target = Vec3::from(xform_point(&m, local).map(|x| x as f32));
                let direction = Vec3::from(rng.unit_vector()) * rng.range(0.5, 2.0);
                let back = if i % 3 == 0 { rng.range(0.0, 0.3) } else { rng.range(2.0, 5.0) };
                let origin = target - direction * back;
                let tmin = if rng.below(4) == 0 { rng.range(0.0, 0.5) } else { 0.0 };
                let tmax = if i % 3 == 1 { back + rng.range(-0.5, 1.0) } else { f32::INFINITY };
                let ray = Ray { origin, direction, tmin, tmax: tmax.max(tmin) };
                RqRay { ray, flags: flag_sets[i % flag_sets.len()], cull: CULL_MASKS[(i / flag_sets.len()) % CULL_MASKS.len()], mode: ((i / 3) % 2) as u32 }
            })
            .collect()
    }

    /// The shader's reference for every ray (in parallel). Instances whose object box (padded
    /// far beyond rounding) the ray cannot reach within [tmin, tmax] are left out of its brute
    /// force, which only saves time: none of their primitives could be a hit or a near miss.
    pub fn references(&self, rays: &[RqRay]) -> Vec<RefResult> {
        use rayon::prelude::*;
        let geoms = self.geoms();
        let boxes: Vec<[f32; 6]> = geoms.iter().map(|g| blas_bounds(g)).collect();
        rays.par_iter()
            .map(|r| {
                let mut scene = self.reference_scene(&geoms);
                if let RefScene::Tlas { instances, .. } = &mut scene {
                    for inst in instances.iter_mut().filter(|i| i.reference != 0) {
                        if !reaches(inst, &boxes[inst.reference as usize - 1], &r.ray) {
                            inst.reference = 0;
                        }
                    }
                }
                shader_reference(&scene, &self.instances, &self.spheres, self.stride, r)
            })
            .collect()
    }
}

impl RqScene {
    /// How far two correct f32 barycentrics of `rec`'s triangle may lie apart: `rel`, or 16 ulps
    /// of the condition of the problem (the larger of the object-space ray origin and vertex
    /// magnitudes over the triangle's size) when that is larger. Small triangles far from the
    /// origin (the dragon's, under non-uniform scales) lose digits in any f32 intersection
    /// test: on dragon_vrip_res3 both Arbor and lavapipe land up to 5e-5 from the f64 value.
    pub fn bary_tolerance(&self, geoms: &[Vec<Geometry>], rec: &Record, ray: &Ray, rel: f32) -> f32 {
        if rec.kind != 1 {
            return rel;
        }
        let inst = &self.instances[rec.instance as usize];
        let g = &geoms[inst.reference as usize - 1][rec.geometry as usize];
        let Some([v0, v1, v2]) = arbor::accel::fetch_triangle(g, rec.primitive) else { return rel };
        let inv = invert_3x4(&inst.transform).expect("invertible instance transform");
        let o = xform_point(&inv, [ray.origin.x as f64, ray.origin.y as f64, ray.origin.z as f64]);
        let magnitude = [v0, v1, v2].iter().map(|v| v.abs().max_element() as f64).fold(Vec3::from(o.map(|x| x as f32)).abs().max_element() as f64, f64::max);
        let size = ((v1 - v0).cross(v2 - v0).length() as f64).sqrt().max(1e-30);
        rel.max((16.0 * f32::EPSILON as f64 * magnitude / size) as f32)
    }
}

/// The object-space bounds of a BLAS's primitives.
fn blas_bounds(geoms: &[Geometry]) -> [f32; 6] {
    let mut points = Vec::new();
    for g in geoms {
        for p in 0..g.primitive_count {
            if let Some(t) = arbor::accel::fetch_triangle(g, p) {
                points.extend(t.map(|v| v.to_array()));
            } else if let Some(b) = arbor::accel::fetch_aabb(g, p) {
                points.extend([[b[0], b[1], b[2]], [b[3], b[4], b[5]]]);
            }
        }
    }
    union_bounds(points)
}

/// Whether the ray, in the instance's object space (f64), can meet `bounds` padded by 1e-3 of
/// their extent within [tmin, tmax] (also padded).
fn reaches(inst: &InstanceRecord, bounds: &[f32; 6], ray: &Ray) -> bool {
    let Some(inv) = invert_3x4(&inst.transform) else { return true };
    let f = |v: Vec3| [v.x as f64, v.y as f64, v.z as f64];
    let (o, d) = (xform_point(&inv, f(ray.origin)), xform_vector(&inv, f(ray.direction)));
    let pad = 1e-3 * (0..3).map(|k| (bounds[k + 3] - bounds[k]) as f64).fold(1e-3, f64::max);
    let padded = [0, 1, 2, 3, 4, 5].map(|k| (bounds[k] as f64 + if k < 3 { -pad } else { pad }) as f32);
    let (t0, t1) = brute_force::slab_f64(o, d, &padded);
    let slack = |t: f64| 1e-4 * t.abs().max(1.0);
    t0 <= t1 && t1 >= ray.tmin as f64 - slack(ray.tmin as f64) && t0 <= ray.tmax as f64 + slack(ray.tmax as f64)
}

/// Flag sets that exercise each ray flag and the combinations that interact: every opacity
/// override and cull, each facing cull, each skip, terminate-on-first-hit with culls.
pub fn selected_flag_sets() -> Vec<u32> {
    vec![
        0,
        OPAQUE,
        NO_OPAQUE,
        TERMINATE_ON_FIRST_HIT,
        CULL_BACK,
        CULL_FRONT,
        CULL_OPAQUE,
        CULL_NO_OPAQUE,
        SKIP_TRIANGLES,
        SKIP_AABBS,
        TERMINATE_ON_FIRST_HIT | CULL_BACK,
        NO_OPAQUE | CULL_FRONT,
        OPAQUE | SKIP_AABBS | SKIP_CLOSEST_HIT,
        CULL_NO_OPAQUE | SKIP_TRIANGLES,
        CULL_OPAQUE | CULL_BACK | SKIP_AABBS,
        TERMINATE_ON_FIRST_HIT | NO_OPAQUE | SKIP_TRIANGLES,
    ]
}

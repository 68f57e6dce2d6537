//! The library-level test support of the `accel_*` integration tests: they call `arbor::accel`
//! directly, with no Vulkan loader or device. Helpers for building structures with guard bytes,
//! vertex-format encoders, random rays, and a brute-force reference of the Vulkan ray traversal
//! rules that is written independently of `arbor::accel`'s traversal. (API tests through the
//! loader use `tests/harness` instead.)
//!
//! The reference only borrows three things from the library, on purpose:
//! `fetch_triangle`/`fetch_aabb` (decode exactly what the builder reads, checked separately
//! against our own decoders) and `intersect_triangle` (so t values compare bit for bit;
//! checked separately against a double-precision test). Everything else — instance masks,
//! instance and ray flags, opacity, facing, culling, tmin/tmax, inactive instances, the
//! instance transform and its inverse — is implemented here from the specification.
// Each test binary uses a different part of these helpers.
#![allow(dead_code)]

use arbor::accel::{
    self, AsType, BuildDesc, BuildFlags, BuildReport, BuildSizes, DeviceView, Geometry, GeometryData, GeometryShape,
    Hit, HitKind, Ray, RayFlags,
};
use arbor_scene::{InstanceRecord, Rng};
use glam::Vec3;
use std::collections::{BTreeSet, HashMap};

// SPIR-V ray flags.
pub const OPAQUE: u32 = 0x1;
pub const NO_OPAQUE: u32 = 0x2;
pub const TERMINATE_ON_FIRST_HIT: u32 = 0x4;
pub const SKIP_CLOSEST_HIT: u32 = 0x8;
pub const CULL_BACK: u32 = 0x10;
pub const CULL_FRONT: u32 = 0x20;
pub const CULL_OPAQUE: u32 = 0x40;
pub const CULL_NO_OPAQUE: u32 = 0x80;
pub const SKIP_TRIANGLES: u32 = 0x100;
pub const SKIP_AABBS: u32 = 0x200;

// VkGeometryInstanceFlagBitsKHR.
pub const FACING_CULL_DISABLE: u8 = 0x1;
pub const FLIP_FACING: u8 = 0x2;
pub const FORCE_OPAQUE: u8 = 0x4;
pub const FORCE_NO_OPAQUE: u8 = 0x8;

// VkGeometryFlagBitsKHR.
pub const GEOMETRY_OPAQUE: u32 = 0x1;

/// Every valid combination of ray flags (the spec forbids more than one of the four opacity
/// flags, both facing culls, both skips, and SKIP_TRIANGLES with a facing cull).
pub fn all_ray_flag_combinations() -> Vec<u32> {
    let mut out = Vec::new();
    for opacity in [0, OPAQUE, NO_OPAQUE, CULL_OPAQUE, CULL_NO_OPAQUE] {
        for facing in [0, CULL_BACK, CULL_FRONT] {
            for skip in [0, SKIP_TRIANGLES, SKIP_AABBS] {
                if skip == SKIP_TRIANGLES && facing != 0 {
                    continue;
                }
                for term in [0, TERMINATE_ON_FIRST_HIT] {
                    for sch in [0, SKIP_CLOSEST_HIT] {
                        out.push(opacity | facing | skip | term | sch);
                    }
                }
            }
        }
    }
    out
}

/// Every valid instance flag combination (FORCE_OPAQUE with FORCE_NO_OPAQUE is excluded).
pub fn all_instance_flag_combinations() -> Vec<u8> {
    (0u8..16).filter(|f| f & 0xC != 0xC).collect()
}

// ---------------------------------------------------------------------------------------------
// Building

pub fn shape_of(g: &Geometry) -> GeometryShape {
    match g.data {
        GeometryData::Triangles { format, index_type, max_vertex, transform, .. } => {
            GeometryShape::Triangles { format, index_type, max_vertex, has_transform: transform.is_some() }
        }
        GeometryData::Aabbs { .. } => GeometryShape::Aabbs,
        GeometryData::Instances { .. } => GeometryShape::Instances,
    }
}

const GUARD: usize = 256;
const GUARD_BYTE: u8 = 0xA5;

/// A built structure: `bytes` is exactly the destination region (size from the size query).
pub struct Built {
    pub bytes: Vec<u8>,
    pub report: BuildReport,
    pub sizes: BuildSizes,
}

/// Size query → allocate dst and scratch (surrounded by guard bytes) → build; checks that
/// nothing outside dst and scratch was written, used_size ≤ size, and that validate() passes.
pub fn try_build(ty: AsType, flags: u32, geometries: &[Geometry], view: &dyn DeviceView) -> Result<Built, accel::BuildError> {
    let shapes: Vec<GeometryShape> = geometries.iter().map(shape_of).collect();
    let counts: Vec<u32> = geometries.iter().map(|g| g.primitive_count).collect();
    let sizes = accel::build_sizes(ty, BuildFlags(flags), &shapes, &counts);
    let dst_len = sizes.acceleration_structure_size as usize;
    let scratch_len = sizes.build_scratch_size as usize;
    let mut dst = vec![GUARD_BYTE; dst_len + 2 * GUARD];
    let mut scratch = vec![GUARD_BYTE; scratch_len + 2 * GUARD + 3];
    let desc = BuildDesc { ty, flags: BuildFlags(flags), geometries };
    // Misalign scratch on purpose: the contract says any alignment.
    let (d, s) = (&mut dst[GUARD..GUARD + dst_len], &mut scratch[GUARD + 3..GUARD + 3 + scratch_len]);
    let result = accel::build(&desc, view, d, s);
    assert!(dst[..GUARD].iter().chain(&dst[GUARD + dst_len..]).all(|&b| b == GUARD_BYTE), "build wrote outside dst");
    assert!(
        scratch[..GUARD + 3].iter().chain(&scratch[GUARD + 3 + scratch_len..]).all(|&b| b == GUARD_BYTE),
        "build wrote outside scratch"
    );
    let report = result?;
    assert!(report.used_size <= sizes.acceleration_structure_size, "used {} > size {}", report.used_size, sizes.acceleration_structure_size);
    let bytes = dst[GUARD..GUARD + dst_len].to_vec();
    // ARBOR_TEST_SKIP_VALIDATE=1 lets a developer see the traversal results of a build that
    // validate() rejects (triage only; the suite is strict by default).
    if let Err(e) = accel::validate(&bytes) {
        if std::env::var_os("ARBOR_TEST_SKIP_VALIDATE").is_some() {
            eprintln!("validate() failed after build (ignored): {e}");
        } else {
            panic!("validate() failed after build: {e}");
        }
    }
    let h = accel::header(&bytes).expect("header of a freshly built structure");
    assert_eq!(h.used_size, report.used_size);
    assert_eq!(accel::compacted_size(&bytes), Some(report.used_size));
    Ok(Built { bytes, report, sizes })
}

pub fn build(ty: AsType, flags: u32, geometries: &[Geometry], view: &dyn DeviceView) -> Built {
    match try_build(ty, flags, geometries, view) {
        Ok(b) => b,
        Err(e) => panic!("build failed: {e:?}"),
    }
}

pub fn build_blas(flags: u32, geometries: &[Geometry]) -> Built {
    build(AsType::BottomLevel, flags, geometries, &accel::NoDevice)
}

/// Owned vertex/index bytes of one triangle geometry.
#[derive(Clone)]
pub struct TriData {
    pub vertices: Vec<u8>,
    pub stride: u64,
    pub format: accel::VertexFormat,
    pub indices: Vec<u8>,
    pub index_type: accel::IndexType,
    pub max_vertex: u32,
    pub count: u32,
    pub transform: Option<[f32; 12]>,
    pub flags: u32,
}

impl TriData {
    /// R32G32B32_SFLOAT, U32 indices.
    pub fn from_mesh(m: &arbor_scene::Mesh, flags: u32) -> Self {
        TriData {
            vertices: m.vertex_bytes(),
            stride: 12,
            format: accel::VertexFormat::R32G32B32Sfloat,
            indices: m.index_bytes(),
            index_type: accel::IndexType::U32,
            max_vertex: m.positions.len().saturating_sub(1) as u32,
            count: m.indices.len() as u32,
            transform: None,
            flags,
        }
    }

    pub fn geometry(&self) -> Geometry<'_> {
        Geometry {
            flags: accel::GeometryFlags(self.flags),
            primitive_count: self.count,
            data: GeometryData::Triangles {
                format: self.format,
                vertices: &self.vertices,
                stride: self.stride,
                max_vertex: self.max_vertex,
                index_type: self.index_type,
                indices: &self.indices,
                transform: self.transform,
            },
        }
    }
}

/// Owned AABB records.
#[derive(Clone)]
pub struct AabbData {
    pub bytes: Vec<u8>,
    pub stride: u64,
    pub count: u32,
    pub flags: u32,
}

impl AabbData {
    pub fn new(boxes: &[[f32; 6]], stride: u64, flags: u32) -> Self {
        assert!(stride >= 24 && stride.is_multiple_of(8));
        let mut bytes = vec![0xEEu8; boxes.len() * stride as usize];
        for (i, b) in boxes.iter().enumerate() {
            for (k, v) in b.iter().enumerate() {
                let o = i * stride as usize + 4 * k;
                bytes[o..o + 4].copy_from_slice(&v.to_le_bytes());
            }
        }
        AabbData { bytes, stride, count: boxes.len() as u32, flags }
    }

    pub fn geometry(&self) -> Geometry<'_> {
        Geometry {
            flags: accel::GeometryFlags(self.flags),
            primitive_count: self.count,
            data: GeometryData::Aabbs { data: &self.bytes, stride: self.stride },
        }
    }
}

/// Boxes around the triangles of a mesh (with a small pad), for AABB geometries.
pub fn boxes_of(m: &arbor_scene::Mesh) -> Vec<[f32; 6]> {
    (0..m.indices.len())
        .map(|i| {
            let t = m.triangle(i);
            let mut b = [f32::INFINITY, f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY];
            for p in t {
                for k in 0..3 {
                    b[k] = b[k].min(p[k]);
                    b[k + 3] = b[k + 3].max(p[k]);
                }
            }
            b
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Vertex format encoders/decoders (independent of the library)

/// f32 → IEEE binary16 bits, round to nearest even (finite inputs in range; inf/NaN kept).
pub fn f32_to_f16(x: f32) -> u16 {
    let bits = x.to_bits();
    let sign = ((bits >> 16) & 0x8000) as u16;
    let exp = ((bits >> 23) & 0xFF) as i32;
    let mant = bits & 0x7F_FFFF;
    if exp == 0xFF {
        return sign | 0x7C00 | if mant != 0 { 0x200 } else { 0 };
    }
    let e = exp - 127 + 15;
    if e >= 0x1F {
        return sign | 0x7C00;
    }
    if e <= 0 {
        if e < -10 {
            return sign;
        }
        let m = mant | 0x80_0000;
        let shift = (14 - e) as u32;
        let half = 1u32 << (shift - 1);
        let mut r = m >> shift;
        let rem = m & ((1 << shift) - 1);
        if rem > half || (rem == half && r & 1 == 1) {
            r += 1;
        }
        return sign | r as u16;
    }
    let mut r = ((e as u32) << 10) | (mant >> 13);
    let rem = mant & 0x1FFF;
    if rem > 0x1000 || (rem == 0x1000 && r & 1 == 1) {
        r += 1;
    }
    sign | r as u16
}

pub fn f16_to_f32(h: u16) -> f32 {
    let sign = if h & 0x8000 != 0 { -1.0f64 } else { 1.0 };
    let exp = ((h >> 10) & 0x1F) as i32;
    let mant = (h & 0x3FF) as f64;
    let v = match exp {
        0 => mant * 2f64.powi(-24),
        0x1F => {
            if mant == 0.0 {
                f64::INFINITY
            } else {
                f64::NAN
            }
        }
        _ => (1.0 + mant / 1024.0) * 2f64.powi(exp - 15),
    };
    (sign * v) as f32
}

pub fn f32_to_snorm16(x: f32) -> i16 {
    (x.clamp(-1.0, 1.0) * 32767.0).round() as i16
}

pub fn snorm16_to_f32(v: i16) -> f32 {
    (v as f64 / 32767.0).max(-1.0) as f32
}

/// Encodes positions as the given format (the formats the tests use), with `stride`.
/// Returns the bytes and the decoded positions the encoding actually represents.
pub fn encode_vertices(positions: &[[f32; 3]], format: accel::VertexFormat, stride: usize) -> (Vec<u8>, Vec<[f32; 3]>) {
    use accel::VertexFormat as F;
    assert!(stride >= format.size() as usize);
    let mut bytes = vec![0x5Au8; positions.len() * stride];
    let mut decoded = Vec::with_capacity(positions.len());
    for (i, p) in positions.iter().enumerate() {
        let o = i * stride;
        let mut d = [0f32; 3];
        match format {
            F::R32G32B32Sfloat | F::R32G32B32A32Sfloat | F::R32G32Sfloat => {
                let n = if format == F::R32G32Sfloat { 2 } else { 3 };
                for k in 0..n {
                    bytes[o + 4 * k..o + 4 * k + 4].copy_from_slice(&p[k].to_le_bytes());
                    d[k] = p[k];
                }
                if format == F::R32G32B32A32Sfloat {
                    bytes[o + 12..o + 16].copy_from_slice(&7.0f32.to_le_bytes());
                }
            }
            F::R16G16Sfloat | F::R16G16B16A16Sfloat | F::R16G16B16Sfloat => {
                let n = if format == F::R16G16Sfloat { 2 } else { 3 };
                for k in 0..n {
                    let h = f32_to_f16(p[k]);
                    bytes[o + 2 * k..o + 2 * k + 2].copy_from_slice(&h.to_le_bytes());
                    d[k] = f16_to_f32(h);
                }
                if format == F::R16G16B16A16Sfloat {
                    bytes[o + 6..o + 8].copy_from_slice(&f32_to_f16(-3.0).to_le_bytes());
                }
            }
            F::R16G16Snorm | F::R16G16B16A16Snorm => {
                let n = if format == F::R16G16Snorm { 2 } else { 3 };
                for k in 0..n {
                    let s = f32_to_snorm16(p[k]);
                    bytes[o + 2 * k..o + 2 * k + 2].copy_from_slice(&s.to_le_bytes());
                    d[k] = snorm16_to_f32(s);
                }
                if format == F::R16G16B16A16Snorm {
                    bytes[o + 6..o + 8].copy_from_slice(&(-32768i16).to_le_bytes());
                }
            }
            other => panic!("encode_vertices: {other:?} not used by the tests"),
        }
        decoded.push(d);
    }
    (bytes, decoded)
}

// ---------------------------------------------------------------------------------------------
// Transforms

/// Applies a row-major 3x4 to a point (w = 1) in f64.
pub fn xform_point(m: &[f64; 12], p: [f64; 3]) -> [f64; 3] {
    [
        m[0] * p[0] + m[1] * p[1] + m[2] * p[2] + m[3],
        m[4] * p[0] + m[5] * p[1] + m[6] * p[2] + m[7],
        m[8] * p[0] + m[9] * p[1] + m[10] * p[2] + m[11],
    ]
}

pub fn xform_vector(m: &[f64; 12], v: [f64; 3]) -> [f64; 3] {
    [
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[4] * v[0] + m[5] * v[1] + m[6] * v[2],
        m[8] * v[0] + m[9] * v[1] + m[10] * v[2],
    ]
}

/// Inverse of an affine row-major 3x4 in f64 (None when singular).
pub fn invert_3x4(m: &[f32; 12]) -> Option<[f64; 12]> {
    let a: Vec<f64> = m.iter().map(|&x| x as f64).collect();
    let (m00, m01, m02, m10, m11, m12, m20, m21, m22) = (a[0], a[1], a[2], a[4], a[5], a[6], a[8], a[9], a[10]);
    let c00 = m11 * m22 - m12 * m21;
    let c01 = m12 * m20 - m10 * m22;
    let c02 = m10 * m21 - m11 * m20;
    let det = m00 * c00 + m01 * c01 + m02 * c02;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv_det = 1.0 / det;
    let r = [
        c00 * inv_det,
        (m02 * m21 - m01 * m22) * inv_det,
        (m01 * m12 - m02 * m11) * inv_det,
        c01 * inv_det,
        (m00 * m22 - m02 * m20) * inv_det,
        (m02 * m10 - m00 * m12) * inv_det,
        c02 * inv_det,
        (m01 * m20 - m00 * m21) * inv_det,
        (m00 * m11 - m01 * m10) * inv_det,
    ];
    let t = [a[3], a[7], a[11]];
    let mut out = [0f64; 12];
    for row in 0..3 {
        out[4 * row] = r[3 * row];
        out[4 * row + 1] = r[3 * row + 1];
        out[4 * row + 2] = r[3 * row + 2];
        out[4 * row + 3] = -(r[3 * row] * t[0] + r[3 * row + 1] * t[1] + r[3 * row + 2] * t[2]);
    }
    Some(out)
}

// ---------------------------------------------------------------------------------------------
// Brute-force reference

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

// ---------------------------------------------------------------------------------------------
// Rays

/// Random rays for a box: half from outside aimed at a random point inside, half from inside in
/// random directions; tmin in {0, small}, tmax ∞ or finite inside the box's extent.
pub fn random_rays(bounds: [f32; 6], n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = Rng::new(seed);
    let lo = Vec3::new(bounds[0], bounds[1], bounds[2]);
    let hi = Vec3::new(bounds[3], bounds[4], bounds[5]);
    let ext = (hi - lo).max(Vec3::splat(1e-6));
    let diag = ext.length();
    let centre = (lo + hi) * 0.5;
    (0..n)
        .map(|i| {
            let inside = |rng: &mut Rng| lo + ext * Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            let (origin, direction) = if i % 2 == 0 {
                let u = Vec3::from(rng.unit_vector());
                let o = centre + u * diag * rng.range(0.75, 3.0);
                let target = inside(&mut rng);
                (o, (target - o) * rng.range(0.2, 5.0))
            } else {
                (inside(&mut rng), Vec3::from(rng.unit_vector()) * rng.range(0.5, 2.0))
            };
            let tmin = if rng.below(3) == 0 { rng.range(0.0, 0.3) } else { 0.0 };
            let tmax = if rng.below(3) == 0 { tmin + rng.range(0.05, 2.0) * diag / direction.length() } else { f32::INFINITY };
            Ray { origin, direction, tmin, tmax }
        })
        .collect()
}

/// Bounds of a list of boxes/points.
pub fn union_bounds(points: impl IntoIterator<Item = [f32; 3]>) -> [f32; 6] {
    let mut b = [f32::INFINITY, f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY];
    for p in points {
        if p.iter().all(|c| c.is_finite()) {
            for k in 0..3 {
                b[k] = b[k].min(p[k]);
                b[k + 3] = b[k + 3].max(p[k]);
            }
        }
    }
    b
}

pub fn data_path(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data").join(name)
}

/// Runs `f` on a fresh rayon pool of `threads` threads.
pub fn with_threads<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
    rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("rayon pool").install(f)
}

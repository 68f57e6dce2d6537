//! The library-level test support of the `accel_*` integration tests: they call `arbor::accel`
//! directly, with no Vulkan loader or device. Helpers for building structures with guard bytes,
//! vertex-format encoders, transforms, random rays; and in `brute_force` a reference of the Vulkan
//! ray traversal rules that is written independently of `arbor::accel`'s traversal, with the
//! comparison of the library against it. (API tests through the loader use `tests/harness`.)
//!
//! The reference only borrows three things from the library, on purpose:
//! `fetch_triangle`/`fetch_aabb` (decode exactly what the builder reads, checked separately
//! against our own decoders) and `intersect_triangle` (so t values compare bit for bit;
//! checked separately against a double-precision test). Everything else — instance masks,
//! instance and ray flags, opacity, facing, culling, tmin/tmax, inactive instances, the
//! instance transform and its inverse — is implemented here from the specification.
// Each test binary uses a different part of these helpers.
#![allow(dead_code)]

use arbor::accel::{self, AsType, BuildDesc, BuildFlags, BuildReport, BuildSizes, DeviceView, Geometry, GeometryData, GeometryShape, Ray};
use arbor_scene::Rng;
use glam::Vec3;

pub mod brute_force;
pub mod rq;

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

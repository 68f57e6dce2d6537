//! Unit tests for the core pieces: decode, intersection, trees vs brute force, determinism
//! across thread counts, refit, copies, degenerate and hostile inputs.
use super::*;
use glam::Vec3;

mod determinism;
mod inputs;
mod integrity;
mod quality;
mod refit;
mod sizes;
mod tlas;

/// Small deterministic generator (no dev-dependencies needed).
pub struct Rng(u64);
impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }
    pub fn next_u32(&mut self) -> u32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 16) as u32
    }
    pub fn f(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 / (1u32 << 24) as f32
    }
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f()
    }
    pub fn v3(&mut self, s: f32) -> Vec3 {
        Vec3::new(self.range(-s, s), self.range(-s, s), self.range(-s, s))
    }
}

pub fn f32_bytes(v: &[Vec3]) -> Vec<u8> {
    v.iter().flat_map(|p| p.to_array()).flat_map(|x| x.to_le_bytes()).collect()
}

pub fn u32_bytes(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

pub fn tri_geom<'a>(verts: &'a [u8], nverts: u32, idx: &'a [u8], ntri: u32, flags: u32) -> Geometry<'a> {
    Geometry {
        flags: GeometryFlags(flags),
        primitive_count: ntri,
        data: GeometryData::Triangles {
            format: VertexFormat::R32G32B32Sfloat,
            vertices: verts,
            stride: 12,
            max_vertex: nverts.saturating_sub(1),
            index_type: if idx.is_empty() { IndexType::None } else { IndexType::U32 },
            indices: idx,
            transform: None,
        },
    }
}

pub fn shape_of(g: &Geometry) -> GeometryShape {
    match g.data {
        GeometryData::Triangles { format, index_type, max_vertex, transform, .. } => GeometryShape::Triangles { format, index_type, max_vertex, has_transform: transform.is_some() },
        GeometryData::Aabbs { .. } => GeometryShape::Aabbs,
        GeometryData::Instances { .. } => GeometryShape::Instances,
    }
}

pub fn try_build(ty: AsType, flags: u32, geoms: &[Geometry], view: &dyn DeviceView) -> (Result<BuildReport, BuildError>, Vec<u8>) {
    let shapes: Vec<_> = geoms.iter().map(shape_of).collect();
    let counts: Vec<_> = geoms.iter().map(|g| g.primitive_count).collect();
    let sz = build_sizes(ty, BuildFlags(flags), &shapes, &counts);
    let mut dst = vec![0xAAu8; sz.acceleration_structure_size as usize];
    // Odd offset: the builder must align scratch itself.
    let mut scratch = vec![0u8; sz.build_scratch_size as usize + 3];
    let desc = BuildDesc { ty, flags: BuildFlags(flags), geometries: geoms };
    let r = build(&desc, view, &mut dst, &mut scratch[3..]);
    (r, dst)
}

pub fn build_ok(ty: AsType, flags: u32, geoms: &[Geometry], view: &dyn DeviceView) -> Vec<u8> {
    build_ok_report(ty, flags, geoms, view).0
}

/// `build_ok` with the build's report.
pub fn build_ok_report(ty: AsType, flags: u32, geoms: &[Geometry], view: &dyn DeviceView) -> (Vec<u8>, BuildReport) {
    let (r, dst) = try_build(ty, flags, geoms, view);
    let r = r.expect("build");
    assert_eq!(header(&dst).unwrap().used_size, r.used_size);
    validate(&dst).expect("validate");
    (dst, r)
}

fn random_soup(rng: &mut Rng, n: usize, scale: f32, size: f32) -> Vec<Vec3> {
    let mut v = Vec::with_capacity(n * 3);
    for _ in 0..n {
        let c = rng.v3(scale);
        for _ in 0..3 {
            v.push(c + rng.v3(size));
        }
    }
    v
}

fn random_ray(rng: &mut Rng, s: f32) -> Ray {
    let o = rng.v3(s * 1.5);
    let target = rng.v3(s * 0.5);
    Ray { origin: o, direction: target - o, tmin: 0.0, tmax: if rng.f() < 0.2 { rng.range(0.1, 1.0) } else { f32::INFINITY } }
}

/// Brute force closest t with the same exact test and face culling rules (no instances).
fn brute_closest(v: &[Vec3], ray: &Ray, flags: u32) -> Option<(f32, u32)> {
    let mut best: Option<(f32, u32)> = None;
    let mut r = *ray;
    for (i, t) in v.chunks_exact(3).enumerate() {
        if let Some((tt, _, _, front)) = intersect_triangle(&r, t[0], t[1], t[2]) {
            if (flags & RayFlags::CULL_BACK_FACING_TRIANGLES != 0 && !front) || (flags & RayFlags::CULL_FRONT_FACING_TRIANGLES != 0 && front) {
                continue;
            }
            best = Some((tt, i as u32));
            r.tmax = tt;
        }
    }
    best
}

/// Builds `geoms` with `flags` on a pool of each thread count: the used bytes of each build
/// and what `inspect` (on the pool, right after the build) says of it.
fn builds_on<T: Send>(threads: &[usize], flags: u32, geoms: &[Geometry], inspect: impl Fn(&[u8], &BuildReport) -> T + Sync) -> Vec<(Vec<u8>, T)> {
    threads
        .iter()
        .map(|&t| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
            pool.install(|| {
                let (blas, report) = build_ok_report(AsType::BottomLevel, flags, geoms, &NoDevice);
                let seen = inspect(&blas, &report);
                let used = header(&blas).unwrap().used_size as usize;
                (blas[..used].to_vec(), seen)
            })
        })
        .collect()
}

/// Destination and scratch for building `g` (`n` primitives) with `flags`, from the size query.
fn blas_buffers(g: &Geometry, n: u32, flags: BuildFlags) -> (Vec<u8>, Vec<u8>) {
    let sz = build_sizes(AsType::BottomLevel, flags, &[shape_of(g)], &[n]);
    (vec![0u8; sz.acceleration_structure_size as usize], vec![0u8; sz.build_scratch_size as usize])
}

fn instance_bytes(transform: [f32; 12], custom: u32, mask: u8, sbt: u32, flags: u8, reference: u64) -> Vec<u8> {
    let mut b = Vec::with_capacity(64);
    for x in transform {
        b.extend(x.to_le_bytes());
    }
    b.extend((custom & 0xff_ffff | (mask as u32) << 24).to_le_bytes());
    b.extend((sbt & 0xff_ffff | (flags as u32) << 24).to_le_bytes());
    b.extend(reference.to_le_bytes());
    b
}

fn translate(x: f32, y: f32, z: f32) -> [f32; 12] {
    [1.0, 0.0, 0.0, x, 0.0, 1.0, 0.0, y, 0.0, 0.0, 1.0, z]
}

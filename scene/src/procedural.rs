//! Deterministic procedural scenes: a small PRNG (SplitMix64; no external crate, so the
//! sequences never change under us), triangle soups, a heightfield and TLAS instance records.

use super::Mesh;

/// SplitMix64 (Steele, Lea, Flood 2014): tiny, fast, and good enough for test geometry.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed ^ 0x5DEE_CE66_D1CE_4E5B)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    pub fn next_u32(&mut self) -> u32 {
        (self.next_u64() >> 32) as u32
    }

    /// Uniform in [0, 1).
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }

    /// Uniform in [0, 1) with double precision.
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next_f32()
    }

    /// Uniform integer in [0, n) (n > 0).
    pub fn below(&mut self, n: u32) -> u32 {
        ((self.next_u32() as u64 * n as u64) >> 32) as u32
    }

    /// A uniformly distributed unit vector.
    pub fn unit_vector(&mut self) -> [f32; 3] {
        loop {
            let v = [self.range(-1.0, 1.0), self.range(-1.0, 1.0), self.range(-1.0, 1.0)];
            let l2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
            if l2 > 1e-4 && l2 <= 1.0 {
                let l = l2.sqrt();
                return [v[0] / l, v[1] / l, v[2] / l];
            }
        }
    }
}

/// `n` independent triangles inside the unit cube [0,1]^3, deterministic from `seed`.
/// Sizes are like those of a real soup of `n` triangles (edge ≈ n^-1/2, so the total area
/// stays about constant as n grows) with a log-uniform spread of 16x between small and large.
pub fn random_soup(n: usize, seed: u64) -> Mesh {
    let mut rng = Rng::new(seed);
    let base = 1.5 / (n.max(1) as f32).sqrt();
    let mut mesh = Mesh { positions: Vec::with_capacity(3 * n), indices: Vec::with_capacity(n) };
    for i in 0..n {
        let c = [rng.next_f32(), rng.next_f32(), rng.next_f32()];
        let size = base * (rng.range(-2.0, 2.0) * std::f32::consts::LN_2).exp();
        for _ in 0..3 {
            let mut p = [0f32; 3];
            for k in 0..3 {
                p[k] = (c[k] + size * rng.range(-1.0, 1.0)).clamp(0.0, 1.0);
            }
            mesh.positions.push(p);
        }
        let b = 3 * i as u32;
        mesh.indices.push([b, b + 1, b + 2]);
    }
    mesh
}

/// A tessellated heightfield over [0,1]x[0,1] (x, z) with `grid` x `grid` cells, two
/// triangles each, heights a fixed sum of sines in about [-0.15, 0.15]. Shares vertices.
pub fn terrain(grid: u32) -> Mesh {
    let g = grid.max(1);
    let side = g + 1;
    let mut mesh = Mesh::default();
    mesh.positions.reserve((side * side) as usize);
    for j in 0..side {
        for i in 0..side {
            let x = i as f32 / g as f32;
            let z = j as f32 / g as f32;
            let y = 0.08 * (6.1 * x).sin() * (5.3 * z).cos()
                + 0.04 * (17.0 * x + 3.0 * z).sin()
                + 0.02 * (41.0 * z - 13.0 * x).cos();
            mesh.positions.push([x, y, z]);
        }
    }
    mesh.indices.reserve((2 * g * g) as usize);
    for j in 0..g {
        for i in 0..g {
            let a = j * side + i;
            let b = a + 1;
            let c = a + side;
            let d = c + 1;
            mesh.indices.push([a, c, b]);
            mesh.indices.push([b, c, d]);
        }
    }
    mesh
}

/// One VkAccelerationStructureInstanceKHR.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InstanceRecord {
    /// Row-major 3x4 object-to-world transform (VkTransformMatrixKHR).
    pub transform: [f32; 12],
    /// 24 bits.
    pub custom_index: u32,
    pub mask: u8,
    /// 24 bits.
    pub sbt_offset: u32,
    /// VkGeometryInstanceFlagBitsKHR (8 bits).
    pub flags: u8,
    /// Device address (or host handle) of the BLAS; 0 makes the instance inactive.
    pub reference: u64,
}

impl InstanceRecord {
    pub const SIZE: usize = 64;
    pub const IDENTITY: [f32; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

    pub fn to_bytes(&self) -> [u8; 64] {
        let mut out = [0u8; 64];
        for (k, v) in self.transform.iter().enumerate() {
            out[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
        }
        let w0 = (self.custom_index & 0x00FF_FFFF) | (self.mask as u32) << 24;
        let w1 = (self.sbt_offset & 0x00FF_FFFF) | (self.flags as u32) << 24;
        out[48..52].copy_from_slice(&w0.to_le_bytes());
        out[52..56].copy_from_slice(&w1.to_le_bytes());
        out[56..64].copy_from_slice(&self.reference.to_le_bytes());
        out
    }

    pub fn from_bytes(b: &[u8; 64]) -> Self {
        let word = |k: usize| u32::from_le_bytes([b[k], b[k + 1], b[k + 2], b[k + 3]]);
        let mut transform = [0f32; 12];
        for (k, v) in transform.iter_mut().enumerate() {
            *v = f32::from_bits(word(4 * k));
        }
        let (w0, w1) = (word(48), word(52));
        InstanceRecord {
            transform,
            custom_index: w0 & 0x00FF_FFFF,
            mask: (w0 >> 24) as u8,
            sbt_offset: w1 & 0x00FF_FFFF,
            flags: (w1 >> 24) as u8,
            reference: u64::from_le_bytes(b[56..64].try_into().unwrap_or([0; 8])),
        }
    }

    /// Packed bytes of many records (the `Instances { array_of_pointers: false }` layout).
    pub fn pack(records: &[InstanceRecord]) -> Vec<u8> {
        records.iter().flat_map(|r| r.to_bytes()).collect()
    }
}

/// `n` instances over the BLASes `blas_references` (round robin), deterministic from `seed`:
/// random rotation, uniform scale in [0.5, 2), translation in a cube of side ~2·n^(1/3) so that
/// neighbours overlap a little like a real scene. custom_index = i, mask 0xFF, sbt offset i % 4,
/// flags 0. Objects are assumed to lie roughly in the unit cube.
pub fn instance_records(n: usize, blas_references: &[u64], seed: u64) -> Vec<InstanceRecord> {
    let mut rng = Rng::new(seed ^ 0x1175_7A4C);
    let extent = 2.0 * (n.max(1) as f32).cbrt();
    (0..n)
        .map(|i| {
            let axis = rng.unit_vector();
            let angle = rng.range(0.0, std::f32::consts::TAU);
            let scale = rng.range(0.5, 2.0);
            let q = glam::Quat::from_axis_angle(glam::Vec3::from(axis), angle);
            let m = glam::Mat3::from_quat(q) * scale;
            let t = [rng.range(0.0, extent), rng.range(0.0, extent), rng.range(0.0, extent)];
            let mut transform = [0f32; 12];
            for r in 0..3 {
                for c in 0..3 {
                    transform[4 * r + c] = m.col(c)[r];
                }
                transform[4 * r + 3] = t[r];
            }
            InstanceRecord {
                transform,
                custom_index: i as u32 & 0x00FF_FFFF,
                mask: 0xFF,
                sbt_offset: i as u32 % 4,
                flags: 0,
                reference: if blas_references.is_empty() { 0 } else { blas_references[i % blas_references.len()] },
            }
        })
        .collect()
}

/// A ray of `primary_rays`: from the eye, through one pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraRay {
    pub origin: glam::Vec3,
    pub direction: glam::Vec3,
}

/// Primary rays of a `width` × `height` image of a scene with these bounds ([lo; 3], [hi; 3]):
/// a pinhole camera in front of the box (+z, slightly above), looking at its centre, rows top to
/// bottom, with unit directions.
pub fn primary_rays(b: [f32; 6], width: usize, height: usize) -> Vec<CameraRay> {
    use glam::Vec3;
    let centre = Vec3::new((b[0] + b[3]) / 2.0, (b[1] + b[4]) / 2.0, (b[2] + b[5]) / 2.0);
    let ext = Vec3::new(b[3] - b[0], b[4] - b[1], b[5] - b[2]);
    let eye = centre + Vec3::new(0.0, 0.1 * ext.y, 2.0 * ext.x.max(ext.y));
    let forward = (centre - eye).normalize();
    let right = forward.cross(Vec3::Y).normalize();
    let up = right.cross(forward);
    let half = (0.6 * ext.x.max(ext.y)) / (centre - eye).length();
    let mut out = Vec::with_capacity(width * height);
    for y in 0..height {
        for x in 0..width {
            let u = (2.0 * (x as f32 + 0.5) / width as f32 - 1.0) * half;
            let v = (1.0 - 2.0 * (y as f32 + 0.5) / height as f32) * half;
            out.push(CameraRay { origin: eye, direction: (forward + right * u + up * v).normalize() });
        }
    }
    out
}

//! Seeded mutation fuzzing of the acceleration-structure library on the stable toolchain (no
//! cargo-fuzz): the deserializer (bit flips, truncations, field splices and re-sealed
//! mutants of valid serialized data of every kind) and the build inputs (random formats,
//! strides, counts, offsets and range records against buffers with guard bytes). Every
//! execution must end in an accepted structure that passes `accel::verify` and traverses, or
//! in a named rejection; a panic escapes to the caller (a crash), and traversal is bounded by
//! its own budget (no hang). Used by `arbor-fuzz` (long runs) and tests/fuzz_short.rs.
use std::collections::BTreeMap;

use arbor::accel::{self, AsType, BuildDesc, BuildError, BuildFlags, CopyError, Geometry, GeometryData, GeometryFlags, GeometryShape, IndexType, MapView, Ray, RayFlags, VertexFormat};
use glam::Vec3;

/// Executions and rejections by reason.
#[derive(Default, Debug)]
pub struct Counts {
    pub executions: u64,
    pub accepted: u64,
    pub rejections: BTreeMap<String, u64>,
}

impl Counts {
    pub fn reject(&mut self, reason: String) {
        *self.rejections.entry(reason).or_default() += 1;
    }
}

/// xorshift64*: the whole run is a function of the seed.
pub struct Rng(u64);
impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }
    pub fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    pub fn below(&mut self, n: u64) -> u64 {
        if n == 0 {
            0
        } else {
            self.next() % n
        }
    }
}

const UUID: [u8; 16] = *b"arbor-fuzz-uuid!";
const BLAS_A: u64 = 0x10_0000;
const BLAS_B: u64 = 0x80_0000;

fn f32s(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn sized_build(ty: AsType, flags: u32, g: &[Geometry], view: &dyn accel::DeviceView) -> Vec<u8> {
    let shapes: Vec<GeometryShape> = g.iter().map(shape).collect();
    let counts: Vec<u32> = g.iter().map(|g| g.primitive_count).collect();
    let sz = accel::build_sizes(ty, BuildFlags(flags), &shapes, &counts);
    let mut dst = vec![0u8; sz.acceleration_structure_size as usize];
    let mut scratch = vec![0u8; sz.build_scratch_size as usize];
    let r = accel::build(&BuildDesc { ty, flags: BuildFlags(flags), geometries: g }, view, &mut dst, &mut scratch).expect("seed build");
    dst.truncate(r.used_size as usize);
    dst
}

fn shape(g: &Geometry) -> GeometryShape {
    match g.data {
        GeometryData::Triangles { format, index_type, max_vertex, transform, .. } => GeometryShape::Triangles { format, index_type, max_vertex, has_transform: transform.is_some() },
        GeometryData::Aabbs { .. } => GeometryShape::Aabbs,
        GeometryData::Instances { .. } => GeometryShape::Instances,
    }
}

fn instance(x: f32, custom: u32, reference: u64) -> Vec<u8> {
    let mut b = f32s(&[1.0, 0.0, 0.0, x, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    b.extend((custom | 0xFF << 24).to_le_bytes());
    b.extend(0u32.to_le_bytes());
    b.extend(reference.to_le_bytes());
    b
}

/// Valid structures of every kind (triangle BLAS in each tier and with ALLOW_UPDATE, AABB BLAS,
/// empty BLAS, TLAS with shared and inactive instances), serialized, and the view their TLAS
/// references resolve in.
pub fn seeds() -> (Vec<Vec<u8>>, MapView) {
    let mut rng = Rng::new(1);
    let verts: Vec<f32> = (0..3 * 3 * 200).map(|_| (rng.below(1000) as f32) / 100.0).collect();
    let vb = f32s(&verts);
    let tri = |n: u32| Geometry { flags: GeometryFlags(1), primitive_count: n, data: GeometryData::Triangles { format: VertexFormat::R32G32B32Sfloat, vertices: &vb, stride: 12, max_vertex: 599, index_type: IndexType::None, indices: &[], transform: None } };
    let boxes = f32s(&(0..40).flat_map(|k| [k as f32, 0.0, 0.0, k as f32 + 0.5, 1.0, 1.0]).collect::<Vec<_>>());
    let aabb = Geometry { flags: GeometryFlags(0), primitive_count: 40, data: GeometryData::Aabbs { data: &boxes, stride: 24 } };
    let mut structures = vec![
        sized_build(AsType::BottomLevel, BuildFlags::PREFER_FAST_TRACE, &[tri(200)], &accel::NoDevice),
        sized_build(AsType::BottomLevel, BuildFlags::PREFER_FAST_BUILD | BuildFlags::ALLOW_UPDATE, &[tri(150)], &accel::NoDevice),
        sized_build(AsType::BottomLevel, 0, &[aabb], &accel::NoDevice),
        sized_build(AsType::BottomLevel, 0, &[tri(0)], &accel::NoDevice),
    ];
    let mut view = MapView::new();
    view.insert(BLAS_A, structures[0].clone());
    view.insert(BLAS_B, structures[2].clone());
    let insts: Vec<u8> = (0..12).flat_map(|k| instance(3.0 * k as f32, k, [BLAS_A, BLAS_B, 0][k as usize % 3])).collect();
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: 12, data: GeometryData::Instances { array_of_pointers: false, data: &insts } }];
    structures.push(sized_build(AsType::TopLevel, 0, &g, &view));
    let blobs = structures
        .iter()
        .map(|s| {
            let mut out = vec![0u8; accel::serialized_size(s).unwrap() as usize];
            accel::serialize(s, UUID, &mut out).unwrap();
            out
        })
        .collect();
    (blobs, view)
}

/// Offset of the payload of serialized data (None if its header is too short).
fn payload_at(blob: &[u8]) -> Option<usize> {
    let n = u64::from_le_bytes(blob.get(48..56)?.try_into().ok()?);
    usize::try_from(n).ok()?.checked_mul(8)?.checked_add(56)
}

const INTERESTING: [u64; 8] = [0, 1, 0xFF, 0xFFFF, 0x7FFF_FFFF, 0xFFFF_FFFF, 0x8000_0000_0000_0000, u64::MAX];

/// One mutant of `blob`.
fn mutate(rng: &mut Rng, blob: &[u8], other: &[u8]) -> Vec<u8> {
    let mut b = blob.to_vec();
    let kind = rng.below(6);
    match kind {
        0 => {
            for _ in 0..1 + rng.below(4) {
                let at = rng.below(b.len() as u64) as usize;
                b[at] ^= 1 << rng.below(8);
            }
        }
        1 => b.truncate(rng.below(b.len() as u64) as usize),
        2 | 3 => {
            // Field splice: a 4- or 8-byte field set to an interesting value or copied from
            // another blob, at a field-aligned offset (header fields, counts, links).
            let w = if rng.below(2) == 0 { 4 } else { 8 };
            let at = (rng.below(b.len() as u64 / w) * w) as usize;
            let v = if kind == 2 {
                INTERESTING[rng.below(8) as usize].to_le_bytes()
            } else {
                let o = (rng.below(other.len() as u64 / 8) * 8) as usize;
                other.get(o..o + 8).and_then(|s| s.try_into().ok()).unwrap_or([0; 8])
            };
            let end = (at + w as usize).min(b.len());
            b[at..end].copy_from_slice(&v[..end - at]);
        }
        _ => {
            // A payload mutant with its checksum recomputed, so the structural checks (and,
            // for what passes them, traversal) see it.
            let Some(p) = payload_at(&b) else { return b };
            let at = p + 160 + rng.below((b.len().saturating_sub(p + 160)) as u64 + 1) as usize;
            if at + 4 <= b.len() {
                let v = INTERESTING[rng.below(8) as usize] as u32 ^ (rng.below(2) as u32 * rng.next() as u32);
                b[at..at + 4].copy_from_slice(&v.to_le_bytes());
            }
            if let Some(c) = b.get(p..).and_then(accel::structure_checksum) {
                b[p + 144..p + 152].copy_from_slice(&c.to_le_bytes());
            }
        }
    }
    b
}

fn copy_reason(e: &CopyError) -> String {
    match e {
        CopyError::Corrupt(r) => format!("deserialize: {r}"),
        CopyError::InvalidSource => "deserialize: invalid source".into(),
        CopyError::Incompatible => "deserialize: incompatible".into(),
        CopyError::DestinationTooSmall { .. } => "deserialize: destination too small".into(),
    }
}

/// Rays through an accepted structure: traversal must be total.
fn trace(structure: &[u8], view: &MapView, rng: &mut Rng) {
    for _ in 0..4 {
        let o = Vec3::new(rng.below(40) as f32 - 5.0, rng.below(12) as f32 - 1.0, -5.0);
        let d = Vec3::new(rng.below(5) as f32 * 0.1, rng.below(5) as f32 * 0.1, 1.0);
        let ray = Ray { origin: o, direction: d, tmin: 0.0, tmax: 100.0 };
        let _ = accel::closest_hit(structure, view, ray, RayFlags(rng.below(0x400) as u32), 0xFF);
    }
}

/// One deserializer execution.
pub fn deserialize_once(rng: &mut Rng, blobs: &[Vec<u8>], view: &MapView, counts: &mut Counts) {
    let blob = &blobs[rng.below(blobs.len() as u64) as usize];
    let other = &blobs[rng.below(blobs.len() as u64) as usize];
    let bad = mutate(rng, blob, other);
    let mut dst = vec![0xA5u8; blob.len() + 64];
    counts.executions += 1;
    let cap = blob.len();
    match accel::deserialize(&bad, UUID, &mut dst[..cap]) {
        Ok(()) => {
            counts.accepted += 1;
            assert!(dst[cap..].iter().all(|&b| b == 0xA5), "deserialize wrote past its destination");
            if let Err(r) = accel::verify(&dst[..cap]) {
                panic!("an accepted blob fails verification: {r}");
            }
            trace(&dst[..cap], view, rng);
        }
        Err(e) => {
            assert!(dst.iter().all(|&b| b == 0xA5), "a rejected blob wrote its destination");
            counts.reject(copy_reason(&e));
        }
    }
}

const FORMATS: [VertexFormat; 4] = [VertexFormat::R32G32B32Sfloat, VertexFormat::R16G16Sfloat, VertexFormat::R8G8B8A8Snorm, VertexFormat::A2B10G10R10UnormPack32];

fn build_reason(e: &BuildError) -> String {
    let name = format!("{e:?}");
    format!("build: {}", name.split([' ', '(', '{']).next().unwrap_or(&name))
}

/// One build-input execution: a random range record (primitive count, primitive offset, first
/// vertex, transform offset) over random buffers, as a driver turns it into slices, then a
/// build into guarded destination and scratch (sometimes smaller than the size query says).
pub fn build_once(rng: &mut Rng, counts: &mut Counts) {
    counts.executions += 1;
    let buffer: Vec<u8> = (0..64 + rng.below(4096)).map(|_| rng.next() as u8).collect();
    let (count, offset, first) = (rng.below(300) as u32, rng.below(512), rng.below(64));
    let kind = rng.below(3);
    let stride = [0u64, 4, 8, 12, 16, 24, 7, 1 << 20][rng.below(8) as usize];
    let Some(data) = buffer.get(offset.min(buffer.len() as u64) as usize..) else { return };
    let indices: Vec<u8> = (0..count as usize * 3).flat_map(|_| (rng.below(80) as u32).to_le_bytes()).collect();
    let transform = (rng.below(3) == 0).then_some([1.0, 0.0, 0.0, first as f32, 0.0, f32::NAN, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    let insts: Vec<u8> = (0..count).flat_map(|k| instance(k as f32, k, [BLAS_A, 0, rng.next(), BLAS_B][rng.below(4) as usize])).collect();
    let g = match kind {
        0 => {
            let index_type = [IndexType::None, IndexType::U16, IndexType::U32][rng.below(3) as usize];
            let idx = if index_type == IndexType::None { &[][..] } else { &indices[..] };
            let format = FORMATS[rng.below(4) as usize];
            GeometryData::Triangles { format, vertices: data, stride, max_vertex: rng.below(100) as u32, index_type, indices: idx, transform }
        }
        1 => GeometryData::Aabbs { data, stride: stride & !7 },
        _ => GeometryData::Instances { array_of_pointers: false, data: &insts },
    };
    let ty = if kind == 2 { AsType::TopLevel } else { AsType::BottomLevel };
    let geom = [Geometry { flags: GeometryFlags(rng.below(4) as u32), primitive_count: count, data: g }];
    let flags = [0, BuildFlags::PREFER_FAST_TRACE, BuildFlags::PREFER_FAST_BUILD, BuildFlags::ALLOW_UPDATE | BuildFlags::ALLOW_COMPACTION][rng.below(4) as usize];
    let sz = accel::build_sizes(ty, BuildFlags(flags), &[shape(&geom[0])], &[count]);
    let shrink = if rng.below(8) == 0 { 1 + rng.below(256) } else { 0 };
    let (dl, sl) = (sz.acceleration_structure_size.saturating_sub(shrink) as usize, sz.build_scratch_size as usize);
    const GUARD: usize = 64;
    let mut dst = vec![0xA5u8; dl + 2 * GUARD];
    let mut scratch = vec![0x5Au8; sl + 2 * GUARD];
    let (_, view) = (0, SEEDS.with(|s| s.1.clone_view()));
    let r = accel::build(&BuildDesc { ty, flags: BuildFlags(flags), geometries: &geom }, &view, &mut dst[GUARD..GUARD + dl], &mut scratch[GUARD..GUARD + sl]);
    let guards_hold = dst[..GUARD].iter().chain(&dst[GUARD + dl..]).all(|&b| b == 0xA5) && scratch[..GUARD].iter().chain(&scratch[GUARD + sl..]).all(|&b| b == 0x5A);
    assert!(guards_hold, "a build wrote outside its destination or scratch");
    match r {
        Ok(rep) => {
            counts.accepted += 1;
            let s = &dst[GUARD..GUARD + rep.used_size as usize];
            if let Err(e) = accel::verify(s) {
                panic!("a build produced a structure that fails verification: {e}");
            }
            trace(s, &view, rng);
        }
        // The size query is a true upper bound: only a destination made smaller than it may
        // be too small.
        Err(e @ (BuildError::DestinationTooSmall { .. } | BuildError::ScratchTooSmall { .. })) if shrink == 0 => panic!("a build into the queried sizes failed: {e:?}"),
        Err(e) => counts.reject(build_reason(&e)),
    }
}

/// The BLASes a fuzzed TLAS build may reference, built once per thread.
struct Seeds(Vec<Vec<u8>>, SeedView);
struct SeedView(Vec<(u64, Vec<u8>)>);
impl SeedView {
    fn clone_view(&self) -> MapView {
        let mut v = MapView::new();
        for (a, b) in &self.0 {
            v.insert(*a, b.clone());
        }
        v
    }
}
thread_local! {
    static SEEDS: Seeds = {
        let (blobs, _) = seeds();
        let payload = |b: &Vec<u8>| b[payload_at(b).unwrap()..].to_vec();
        Seeds(blobs.clone(), SeedView(vec![(BLAS_A, payload(&blobs[0])), (BLAS_B, payload(&blobs[2]))]))
    };
}

/// `iterations` executions from `seed`, alternating the deserializer and the build inputs.
pub fn run(iterations: u64, seed: u64) -> Counts {
    let mut counts = Counts::default();
    let mut rng = Rng::new(seed);
    let (blobs, view) = seeds();
    for i in 0..iterations {
        if i % 8 == 7 {
            build_once(&mut rng, &mut counts);
        } else {
            deserialize_once(&mut rng, &blobs, &view, &mut counts);
        }
    }
    let _ = SEEDS.with(|s| s.0.len());
    counts
}

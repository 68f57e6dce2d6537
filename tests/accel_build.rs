//! Build lifecycle: sizes, determinism across thread counts, refit, clone/compact/serialize
//! round trips, degenerate inputs, errors, invalid structures — each checked against the
//! brute-force reference rather than against numbers taken from the code under test.

mod reference;

use arbor::accel::{self, AsType, BuildDesc, BuildError, BuildFlags, Geometry, GeometryData, GeometryFlags, GeometryShape, MapView, Ray, RayFlags};
use arbor_scene::{self as scene, InstanceRecord, Mesh, Rng};
use reference::brute_force::*;
use reference::*;
use std::collections::HashMap;

const FAST_TRACE: u32 = BuildFlags::PREFER_FAST_TRACE;
const FAST_BUILD: u32 = BuildFlags::PREFER_FAST_BUILD;
const TIERS: [u32; 4] = [FAST_TRACE, 0, FAST_BUILD, BuildFlags::LOW_MEMORY];
const EXACT: Tolerance = Tolerance { exact: true };

fn compare_blas(bytes: &[u8], geoms: &[Geometry], rays: &[Ray], ctx: &str) -> usize {
    let scene = RefScene::Blas(geoms);
    rays.iter().enumerate().map(|(i, r)| compare_ray(bytes, &accel::NoDevice, &scene, r, 0, 0xFF, EXACT, &format!("{ctx} ray {i}"))).sum()
}

fn used(b: &Built) -> &[u8] {
    &b.bytes[..b.report.used_size as usize]
}

#[test]
fn deterministic_across_thread_counts_for_every_tier() {
    // Above 2^16 references the top nodes bin a sample and, on one thread or once a node is
    // small against the pool, partition in one pass instead of in parallel: both must give
    // the same bytes.
    let soup = scene::random_soup(140_000, 1);
    let dragon = scene::load(data_path("dragon_vrip_res3.ply.gz")).unwrap();
    for (name, mesh) in [("soup", &soup), ("dragon res3", &dragon)] {
        let data = TriData::from_mesh(mesh, GEOMETRY_OPAQUE);
        let geoms = [data.geometry()];
        for tier in TIERS.iter().copied().chain([FAST_TRACE | BuildFlags::ALLOW_UPDATE | BuildFlags::ALLOW_COMPACTION]) {
            let reference = with_threads(1, || build_blas(tier, &geoms));
            for threads in [2, 8, 1] {
                let again = with_threads(threads, || build_blas(tier, &geoms));
                assert_eq!(again.report, reference.report, "{name} tier {tier:#x}: report differs with {threads} threads");
                assert!(used(&again) == used(&reference), "{name} tier {tier:#x}: bytes differ with {threads} threads");
            }
        }
    }
    // A TLAS too.
    let blas = build_blas(FAST_TRACE, &[TriData::from_mesh(&scene::random_soup(500, 3), 0).geometry()]);
    let mut view = MapView::new();
    view.insert(0x1000_0000, blas.bytes);
    let insts = InstanceRecord::pack(&scene::instance_records(20_000, &[0x1000_0000], 4));
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: 20_000, data: GeometryData::Instances { array_of_pointers: false, data: &insts } }];
    for tier in [FAST_TRACE, FAST_BUILD] {
        let one = with_threads(1, || build(AsType::TopLevel, tier, &g, &view));
        let eight = with_threads(8, || build(AsType::TopLevel, tier, &g, &view));
        assert!(used(&one) == used(&eight), "TLAS tier {tier:#x}: bytes differ");
    }
}

#[test]
fn sizes_bound_what_builds_use() {
    let mut rng = Rng::new(2);
    for n in [0usize, 1, 2, 3, 8, 9, 100, 1000, 12_345] {
        let m = scene::random_soup(n, rng.next_u64());
        let data = TriData::from_mesh(&m, 0);
        for tier in TIERS.iter().copied().chain([BuildFlags::ALLOW_UPDATE, BuildFlags::ALLOW_COMPACTION]) {
            let b = build_blas(tier, &[data.geometry()]); // try_build asserts used ≤ size
            let compact = accel::compacted_size(&b.bytes).unwrap();
            assert!(compact <= b.sizes.acceleration_structure_size);
            // Query with larger maxima than the build uses: still enough.
            let shape = shape_of(&data.geometry());
            let bigger = accel::build_sizes(AsType::BottomLevel, BuildFlags(tier), &[shape], &[(n as u32) * 2 + 5]);
            assert!(bigger.acceleration_structure_size >= b.sizes.acceleration_structure_size);
            assert!(bigger.build_scratch_size >= b.sizes.build_scratch_size);
        }
    }
    // The size query must not overflow for the largest counts.
    let shape = GeometryShape::Triangles { format: accel::VertexFormat::R32G32B32Sfloat, index_type: accel::IndexType::U32, max_vertex: u32::MAX, has_transform: true };
    let s = accel::build_sizes(AsType::BottomLevel, BuildFlags(FAST_TRACE | BuildFlags::ALLOW_UPDATE), &[shape; 4], &[u32::MAX; 4]);
    assert!(s.acceleration_structure_size > 4 * u32::MAX as u64 && s.acceleration_structure_size < u64::MAX / 2);
    let s = accel::build_sizes(AsType::TopLevel, BuildFlags(0), &[GeometryShape::Instances], &[u32::MAX]);
    assert!(s.acceleration_structure_size > 64 * u32::MAX as u64 / 2);
}

#[test]
fn refit_in_place_and_out_of_place_matches_brute_force() {
    for base in [scene::random_soup(4000, 7), scene::load(data_path("dragon_vrip_res4.ply.gz")).unwrap()] {
        let data = TriData::from_mesh(&base, 0);
        let flags = BuildFlags::ALLOW_UPDATE | FAST_TRACE;
        let built = build_blas(flags, &[data.geometry()]);
        // Move every vertex (a wobble plus a shear, large compared with triangle size).
        let b = base.bounds();
        let ext = (b[3] - b[0]).max(b[4] - b[1]).max(b[5] - b[2]);
        let moved = Mesh {
            positions: base
                .positions
                .iter()
                .map(|p| [p[0] + 0.3 * p[1] + 0.05 * ext * (40.0 * p[2] / ext).sin(), p[1] * 1.5, p[2] - 0.2 * p[0]])
                .collect(),
            indices: base.indices.clone(),
        };
        let mdata = TriData::from_mesh(&moved, 0);
        let mgeoms = [mdata.geometry()];
        let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &mgeoms };
        let rays = random_rays(moved.bounds(), 400, 31);
        // Out of place.
        let mut dst = vec![0u8; built.bytes.len()];
        let mut scratch = vec![0u8; built.sizes.update_scratch_size as usize];
        let rep = accel::update(&desc, &accel::NoDevice, Some(&built.bytes), &mut dst, &mut scratch).expect("update");
        assert!(rep.used_size <= dst.len() as u64);
        accel::validate(&dst).expect("validate after refit");
        let hits = compare_blas(&dst, &mgeoms, &rays, "refit out-of-place");
        assert!(hits > 100);
        // In place.
        let mut inplace = built.bytes.clone();
        accel::update(&desc, &accel::NoDevice, None, &mut inplace, &mut scratch).expect("update in place");
        accel::validate(&inplace).expect("validate after in-place refit");
        compare_blas(&inplace, &mgeoms, &rays, "refit in-place");
        // Refit back to the original positions: behaves like the original build.
        let geoms = [data.geometry()];
        let back_desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &geoms };
        accel::update(&back_desc, &accel::NoDevice, None, &mut inplace, &mut scratch).expect("update back");
        compare_blas(&inplace, &geoms, &random_rays(base.bounds(), 200, 5), "refit back");
    }
}

#[test]
fn refit_rejects_rule_violations() {
    let m = scene::random_soup(500, 8);
    let data = TriData::from_mesh(&m, 0);
    let flags = BuildFlags::ALLOW_UPDATE;
    let built = build_blas(flags, &[data.geometry()]);
    let scratch = vec![0u8; built.sizes.update_scratch_size as usize + 64];
    let try_update = |geoms: &[Geometry], fl: u32| {
        let mut dst = built.bytes.clone();
        let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(fl), geometries: geoms };
        let mut s = scratch.clone();
        accel::update(&desc, &accel::NoDevice, Some(&built.bytes), &mut dst, &mut s).map(|_| dst)
    };
    // Fewer primitives.
    let mut fewer = data.clone();
    fewer.count -= 1;
    assert!(try_update(&[fewer.geometry()], flags).is_err(), "changed primitive count accepted");
    // Different indices.
    let mut other = data.clone();
    other.indices[0..4].copy_from_slice(&5u32.to_le_bytes());
    assert!(try_update(&[other.geometry()], flags).is_err(), "changed index accepted");
    // Different geometry flags.
    let mut opaque = data.clone();
    opaque.flags = GEOMETRY_OPAQUE;
    assert!(try_update(&[opaque.geometry()], flags).is_err(), "changed geometry flags accepted");
    // Active → inactive.
    let mut nan = data.clone();
    nan.vertices[0..4].copy_from_slice(&f32::NAN.to_le_bytes());
    assert!(try_update(&[nan.geometry()], flags).is_err(), "active→inactive accepted");
    // Extra geometry.
    assert!(try_update(&[data.geometry(), data.geometry()], flags).is_err(), "changed geometry count accepted");
    // Source built without ALLOW_UPDATE.
    let noupd = build_blas(0, &[data.geometry()]);
    let mut dst = noupd.bytes.clone();
    let geoms = [data.geometry()];
    let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(0), geometries: &geoms };
    let mut scratch2 = scratch.clone();
    assert!(accel::update(&desc, &accel::NoDevice, Some(&noupd.bytes), &mut dst, &mut scratch2).is_err(), "update of a structure without ALLOW_UPDATE accepted");
    // The unchanged input still updates fine.
    let ok = try_update(&[data.geometry()], flags).expect("identical update");
    compare_blas(&ok, &[data.geometry()], &random_rays(m.bounds(), 100, 1), "identity update");
}

#[test]
fn clone_compact_serialize_round_trips() {
    let m = scene::load(data_path("dragon_vrip_res4.ply.gz")).unwrap();
    let data = TriData::from_mesh(&m, GEOMETRY_OPAQUE);
    let geoms = [data.geometry()];
    let rays = random_rays(m.bounds(), 300, 77);
    for tier in [FAST_TRACE | BuildFlags::ALLOW_COMPACTION, FAST_BUILD | BuildFlags::ALLOW_COMPACTION | BuildFlags::ALLOW_UPDATE] {
        let b = build_blas(tier, &geoms);
        let used_size = b.report.used_size as usize;
        // Clone into a region of the full size, placed at an odd offset inside a bigger buffer.
        let mut big = vec![0u8; b.bytes.len() + 3];
        accel::clone_into(&b.bytes, &mut big[3..]).expect("clone");
        compare_blas(&big[3..], &geoms, &rays, "clone");
        // Compact: into exactly used_size bytes; too small fails without panicking.
        let mut small = vec![0u8; used_size];
        accel::compact_into(&b.bytes, &mut small).expect("compact");
        accel::validate(&small).expect("validate compacted");
        compare_blas(&small, &geoms, &rays, "compacted");
        assert_eq!(accel::compacted_size(&small), Some(used_size as u64));
        let mut too_small = vec![0u8; used_size - 1];
        assert!(accel::compact_into(&b.bytes, &mut too_small).is_err());
        // Serialize → deserialize.
        let uuid = *b"driver-uuid-0123";
        let ser_size = accel::serialized_size(&b.bytes).unwrap();
        assert_eq!(accel::blas_references(&b.bytes).len(), 0, "a BLAS refers to no BLAS");
        let mut ser = vec![0u8; ser_size as usize];
        let written = accel::serialize(&b.bytes, uuid, &mut ser).expect("serialize");
        assert_eq!(written, ser_size);
        assert_eq!(&ser[0..16], &uuid);
        assert_eq!(&ser[16..32], &accel::ACCEL_FORMAT_UUID);
        assert_eq!(u64::from_le_bytes(ser[32..40].try_into().unwrap()), ser_size);
        let deser_size = u64::from_le_bytes(ser[40..48].try_into().unwrap());
        assert!(deser_size >= used_size as u64);
        assert_eq!(u64::from_le_bytes(ser[48..56].try_into().unwrap()), 0);
        let version: [u8; 32] = ser[0..32].try_into().unwrap();
        assert!(accel::compatible(&version, uuid));
        assert!(!accel::compatible(&version, *b"another-driver!!"));
        let mut back = vec![0u8; deser_size as usize];
        accel::deserialize(&ser, uuid, &mut back).expect("deserialize");
        accel::validate(&back).expect("validate deserialized");
        compare_blas(&back, &geoms, &rays, "deserialized");
        assert!(accel::deserialize(&ser, *b"another-driver!!", &mut back.clone()).is_err());
        let mut corrupt = ser.clone();
        corrupt[20] ^= 0xFF;
        assert!(accel::deserialize(&corrupt, uuid, &mut back.clone()).is_err());
        assert!(accel::deserialize(&ser[..ser.len() / 2], uuid, &mut back.clone()).is_err());
    }
}

#[test]
fn tlas_serialize_rewrites_blas_references() {
    // Two BLASes, a TLAS over them; serialize; "move" the BLASes to new addresses by rewriting
    // the header's address list; deserialize; traversal with the moved BLASes matches brute force.
    let m1 = scene::random_soup(300, 1);
    let m2 = scene::terrain(8);
    let d1 = TriData::from_mesh(&m1, GEOMETRY_OPAQUE);
    let d2 = TriData::from_mesh(&m2, 0);
    let g1 = [d1.geometry()];
    let g2 = [d2.geometry()];
    let (b1, b2) = (build_blas(0, &g1), build_blas(0, &g2));
    let (a1, a2) = (0x1_0000_0000u64, 0x2_0000_0000u64);
    let mut view = MapView::new();
    view.insert(a1, b1.bytes.clone());
    view.insert(a2, b2.bytes.clone());
    let mut insts = scene::instance_records(30, &[a1, a2], 6);
    insts[3].reference = 0;
    let packed = InstanceRecord::pack(&insts);
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: 30, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
    let tlas = build(AsType::TopLevel, FAST_TRACE | BuildFlags::ALLOW_COMPACTION, &g, &view);
    // Clone and compaction of a TLAS: same traversal results as the original.
    let mut cloned = vec![0u8; tlas.bytes.len()];
    accel::clone_into(&tlas.bytes, &mut cloned).unwrap();
    let mut compact = vec![0u8; tlas.report.used_size as usize];
    accel::compact_into(&tlas.bytes, &mut compact).unwrap();
    accel::validate(&compact).expect("validate compacted TLAS");
    {
        let blases: HashMap<u64, &[Geometry]> = [(a1, &g1[..]), (a2, &g2[..])].into_iter().collect();
        let scene = RefScene::Tlas { instances: insts.clone(), blases };
        let b = union_bounds(insts.iter().map(|r| [r.transform[3], r.transform[7], r.transform[11]]));
        let bounds = [b[0] - 2.0, b[1] - 2.0, b[2] - 2.0, b[3] + 2.0, b[4] + 2.0, b[5] + 2.0];
        for (i, ray) in random_rays(bounds, 200, 8).iter().enumerate() {
            for (name, s) in [("original", &tlas.bytes), ("clone", &cloned), ("compacted", &compact)] {
                compare_ray(s, &view, &scene, ray, 0, 0xFF, Tolerance { exact: false }, &format!("{name} TLAS ray {i}"));
            }
        }
    }
    let mut refs = accel::blas_references(&tlas.bytes);
    refs.sort();
    refs.dedup();
    assert_eq!(refs, vec![a1, a2]);
    let uuid = [7u8; 16];
    let mut ser = vec![0u8; accel::serialized_size(&tlas.bytes).unwrap() as usize];
    accel::serialize(&tlas.bytes, uuid, &mut ser).unwrap();
    let n = u64::from_le_bytes(ser[48..56].try_into().unwrap()) as usize;
    assert!(n >= 2);
    let (n1, n2) = (0x30_0000_0000u64, 0x40_0000_0000u64);
    for k in 0..n {
        let o = 56 + 8 * k;
        let old = u64::from_le_bytes(ser[o..o + 8].try_into().unwrap());
        let new = if old == a1 { n1 } else if old == a2 { n2 } else { panic!("unexpected reference {old:#x}") };
        ser[o..o + 8].copy_from_slice(&new.to_le_bytes());
    }
    let deser_size = u64::from_le_bytes(ser[40..48].try_into().unwrap());
    let mut back = vec![0u8; deser_size as usize];
    accel::deserialize(&ser, uuid, &mut back).unwrap();
    let mut newrefs = accel::blas_references(&back);
    newrefs.sort();
    newrefs.dedup();
    assert_eq!(newrefs, vec![n1, n2]);
    let mut moved_view = MapView::new();
    moved_view.insert(n1, b1.bytes.clone());
    moved_view.insert(n2, b2.bytes.clone());
    let moved: Vec<InstanceRecord> = insts
        .iter()
        .map(|r| InstanceRecord { reference: if r.reference == a1 { n1 } else if r.reference == a2 { n2 } else { 0 }, ..*r })
        .collect();
    let blases: HashMap<u64, &[Geometry]> = [(n1, &g1[..]), (n2, &g2[..])].into_iter().collect();
    let scene = RefScene::Tlas { instances: moved.clone(), blases };
    let bounds = union_bounds(moved.iter().map(|r| [r.transform[3], r.transform[7], r.transform[11]]));
    let bounds = [bounds[0] - 2.0, bounds[1] - 2.0, bounds[2] - 2.0, bounds[3] + 2.0, bounds[4] + 2.0, bounds[5] + 2.0];
    let mut hits = 0;
    for (i, ray) in random_rays(bounds, 300, 2).iter().enumerate() {
        hits += compare_ray(&back, &moved_view, &scene, ray, 0, 0xFF, Tolerance { exact: false }, &format!("deserialized TLAS ray {i}"));
    }
    assert!(hits > 30, "{hits}");
}

fn degenerate_case(name: &str, positions: Vec<[f32; 3]>, indices: Vec<[u32; 3]>, rays: &[Ray]) {
    let m = Mesh { positions, indices };
    let data = TriData::from_mesh(&m, 0);
    let geoms = [data.geometry()];
    for tier in TIERS.iter().copied().chain([BuildFlags::ALLOW_UPDATE]) {
        let b = build_blas(tier, &geoms);
        let active = (0..m.indices.len() as u32).filter(|&p| accel::fetch_triangle(&geoms[0], p).is_some()).count();
        let h = accel::header(&b.bytes).unwrap();
        assert_eq!(h.geometry_count, 1, "{name}");
        assert!(b.report.primitive_count as usize <= active, "{name}: stores {} of {active} active", b.report.primitive_count);
        compare_blas(&b.bytes, &geoms, rays, &format!("{name} tier {tier:#x}"));
    }
}

#[test]
fn degenerate_inputs_do_not_panic_and_match_brute_force() {
    let unit_rays = random_rays([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 200, 4);
    degenerate_case("empty", vec![], vec![], &unit_rays);
    degenerate_case("one", vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], vec![[0, 1, 2]], &unit_rays);
    degenerate_case("one point", vec![[0.25, 0.25, 0.25]; 3], (0..1000).map(|_| [0, 1, 2]).collect(), &unit_rays);
    let p = [0.3f32, -0.2, 0.1];
    degenerate_case("all at one point", vec![p; 3000], (0..1000).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect(), &unit_rays);
    // Zero area: collinear triangles on a line and repeated indices, among good ones.
    let mut rng = Rng::new(3);
    let mut pos = Vec::new();
    let mut idx = Vec::new();
    for i in 0..2000u32 {
        let a = [rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)];
        let d = [rng.range(-0.1, 0.1), rng.range(-0.1, 0.1), rng.range(-0.1, 0.1)];
        let line = i % 3 == 0;
        pos.push(a);
        pos.push([a[0] + d[0], a[1] + d[1], a[2] + d[2]]);
        pos.push(if line { [a[0] + 2.0 * d[0], a[1] + 2.0 * d[1], a[2] + 2.0 * d[2]] } else { [a[0] + d[1], a[1] - d[2], a[2] + d[0]] });
        idx.push(if i % 7 == 1 { [3 * i, 3 * i, 3 * i + 1] } else { [3 * i, 3 * i + 1, 3 * i + 2] });
    }
    degenerate_case("zero area mix", pos.clone(), idx.clone(), &unit_rays);
    // NaN (inactive), NaN everywhere in x, and infinities mixed in.
    let mut nanpos = pos.clone();
    for (i, p) in nanpos.iter_mut().enumerate() {
        match i % 13 {
            0 => p[0] = f32::NAN,
            5 => p[0] = -f32::NAN,
            7 => p[1] = f32::INFINITY,
            11 => p[2] = f32::NEG_INFINITY,
            _ => {}
        }
    }
    degenerate_case("nan and inf", nanpos, idx.clone(), &unit_rays);
    degenerate_case("all nan", vec![[f32::NAN, 0.0, 0.0]; 30], (0..10).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect(), &unit_rays);
    // Huge and tiny coordinates.
    for scale in [1e30f32, 1e-30, 1e18, 1e-18] {
        let m = scene::random_soup(2000, 9);
        let scaled: Vec<[f32; 3]> = m.positions.iter().map(|p| [(p[0] - 0.5) * scale, (p[1] - 0.5) * scale, (p[2] - 0.5) * scale]).collect();
        let s = 0.5 * scale;
        let rays = random_rays([-s, -s, -s, s, s, s], 200, 10);
        degenerate_case(&format!("scale {scale:e}"), scaled, m.indices.clone(), &rays);
    }
    // Mixed: one triangle at 1e30 and the rest near 0.
    let m = scene::random_soup(1000, 12);
    let mut mixed = m.positions.clone();
    mixed[0] = [1e30, 1e30, 1e30];
    mixed[1] = [-1e30, 1e30, 0.0];
    degenerate_case("mixed huge", mixed, m.indices.clone(), &random_rays([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 200, 13));
}

#[test]
fn degenerate_aabbs_and_instances() {
    let nan = f32::NAN;
    let boxes = vec![
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [nan, 0.0, 0.0, 1.0, 1.0, 1.0],
        [0.1, 0.1, 0.1, 0.5, 0.5, 0.5],
        [-1e30, -1e30, -1e30, 1e30, 1e30, 1e30],
        [0.2, 0.2, 0.2, 0.2, 0.9, 0.2],
    ];
    let a = AabbData::new(&boxes, 24, 0);
    let geoms = [a.geometry()];
    let b = build_blas(0, &geoms);
    compare_blas(&b.bytes, &geoms, &random_rays([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 200, 3), "degenerate aabbs");
    // A TLAS of only inactive instances, of instances over an empty BLAS, and of none.
    let empty = build_blas(0, &[TriData::from_mesh(&Mesh::default(), 0).geometry()]);
    let mut view = MapView::new();
    view.insert(0x5000, empty.bytes);
    for (n, reference) in [(0u32, 0x5000u64), (10, 0), (10, 0x5000)] {
        let recs = scene::instance_records(n as usize, &[reference], 1);
        let packed = InstanceRecord::pack(&recs);
        let g = [Geometry { flags: GeometryFlags(0), primitive_count: n, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
        let t = build(AsType::TopLevel, 0, &g, &view);
        for ray in random_rays([-5.0, -5.0, -5.0, 5.0, 5.0, 5.0], 50, 2) {
            assert!(accel::closest_hit(&t.bytes, &view, ray, RayFlags(0), 0xFF).is_none());
        }
    }
}

#[test]
fn build_errors_are_typed_and_write_nothing_outside() {
    let m = scene::random_soup(1000, 4);
    let data = TriData::from_mesh(&m, 0);
    let geoms = [data.geometry()];
    let sizes = accel::build_sizes(AsType::BottomLevel, BuildFlags(0), &[shape_of(&geoms[0])], &[1000]);
    let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(0), geometries: &geoms };
    let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
    let mut dst = vec![0u8; 64];
    assert!(matches!(accel::build(&desc, &accel::NoDevice, &mut dst, &mut scratch), Err(BuildError::DestinationTooSmall { .. })));
    let mut dst = vec![0u8; sizes.acceleration_structure_size as usize];
    if sizes.build_scratch_size > 0 {
        let mut tiny = vec![0u8; 8];
        assert!(matches!(accel::build(&desc, &accel::NoDevice, &mut dst, &mut tiny), Err(BuildError::ScratchTooSmall { .. })));
        assert!(accel::header(&dst).is_none(), "failed build must leave dst invalid");
    }
    // Index out of range (max_vertex says 999 vertices... the index says more).
    let mut bad = data.clone();
    bad.indices[12..16].copy_from_slice(&(m.positions.len() as u32 + 10).to_le_bytes());
    let r = try_build(AsType::BottomLevel, 0, &[bad.geometry()], &accel::NoDevice);
    assert!(matches!(r, Err(BuildError::IndexOutOfRange { .. })), "{:?}", r.err());
    // Index data too short.
    let mut short = data.clone();
    short.indices.truncate(100);
    assert!(try_build(AsType::BottomLevel, 0, &[short.geometry()], &accel::NoDevice).is_err());
    // Vertex data too short.
    let mut shortv = data.clone();
    shortv.vertices.truncate(shortv.vertices.len() - 12);
    assert!(try_build(AsType::BottomLevel, 0, &[shortv.geometry()], &accel::NoDevice).is_err());
    // Instances in a BLAS, triangles in a TLAS.
    let insts = [0u8; 64];
    let ig = [Geometry { flags: GeometryFlags(0), primitive_count: 1, data: GeometryData::Instances { array_of_pointers: false, data: &insts } }];
    assert!(try_build(AsType::BottomLevel, 0, &ig, &accel::NoDevice).is_err());
    assert!(try_build(AsType::TopLevel, 0, &geoms, &accel::NoDevice).is_err());
    // Array of pointers with an unresolvable address.
    let ptrs = 0xDEAD_0000u64.to_le_bytes();
    let pg = [Geometry { flags: GeometryFlags(0), primitive_count: 1, data: GeometryData::Instances { array_of_pointers: true, data: &ptrs } }];
    assert!(try_build(AsType::TopLevel, 0, &pg, &accel::NoDevice).is_err());
}

#[test]
fn invalid_and_garbage_structures_are_harmless() {
    let m = scene::random_soup(2000, 4);
    let data = TriData::from_mesh(&m, 0);
    let b = build_blas(0, &[data.geometry()]);
    let rays = random_rays(m.bounds(), 50, 1);
    let mut inv = b.bytes.clone();
    accel::mark_invalid(&mut inv);
    assert!(accel::header(&inv).is_none());
    assert!(accel::validate(&inv).is_err());
    for r in &rays {
        assert!(accel::closest_hit(&inv, &accel::NoDevice, copy_ray(r), RayFlags(0), 0xFF).is_none());
        assert!(accel::all_hits(&inv, &accel::NoDevice, copy_ray(r), RayFlags(0), 0xFF).is_empty());
    }
    // Random corruption of a valid structure: no panic anywhere (results may be anything).
    let mut rng = Rng::new(77);
    for round in 0..200 {
        let mut c = b.bytes.clone();
        for _ in 0..1 + round % 8 {
            let i = rng.below(c.len().min(4096) as u32) as usize;
            c[i] = rng.next_u32() as u8;
        }
        let _ = accel::header(&c);
        let _ = accel::validate(&c);
        let _ = accel::metrics(&c);
        let _ = accel::compacted_size(&c);
        let _ = accel::serialized_size(&c);
        let mut out = vec![0u8; c.len()];
        let _ = accel::clone_into(&c, &mut out);
        for r in rays.iter().take(5) {
            let _ = accel::closest_hit(&c, &accel::NoDevice, copy_ray(r), RayFlags(0), 0xFF);
        }
    }
    for len in [0usize, 1, 7, 64, 200] {
        let junk = vec![0xFFu8; len];
        assert!(accel::header(&junk).is_none());
        assert!(accel::closest_hit(&junk, &accel::NoDevice, copy_ray(&rays[0]), RayFlags(0), 0xFF).is_none());
    }
}

#[test]
fn metrics_are_consistent() {
    let m = scene::load(data_path("dragon_vrip_res4.ply.gz")).unwrap();
    let data = TriData::from_mesh(&m, 0);
    let mut costs = Vec::new();
    for tier in [FAST_TRACE, FAST_BUILD] {
        let b = build_blas(tier, &[data.geometry()]);
        let mt = accel::metrics(&b.bytes).unwrap();
        let h = accel::header(&b.bytes).unwrap();
        assert_eq!(mt.sah_cost, h.sah_cost);
        assert_eq!(mt.leaf_count, b.report.leaf_count);
        assert_eq!(mt.node_count, b.report.node_count);
        // SAH ≥ 1 (the root's own intersection cost) and far below a flat list (N).
        assert!(mt.sah_cost > 1.0 && mt.sah_cost < 200.0, "{}", mt.sah_cost);
        assert!(mt.bytes_per_primitive > 0.0 && mt.bytes_per_primitive * m.indices.len() as f32 <= b.report.used_size as f32 * 1.01);
        assert!(mt.max_depth >= 4 && mt.max_depth < 64);
        costs.push(mt.sah_cost);
    }
    assert!(costs[0] <= costs[1] * 1.05, "FAST_TRACE SAH {} worse than FAST_BUILD {}", costs[0], costs[1]);
}

/// 2^22 triangles: built without panic, valid, and brute-force equal on a few rays.
#[cfg(not(debug_assertions))]
#[test]
fn four_million_primitives() {
    let n = 1usize << 22;
    let m = scene::random_soup(n, 22);
    let data = TriData::from_mesh(&m, GEOMETRY_OPAQUE);
    let geoms = [data.geometry()];
    let b = build_blas(FAST_BUILD, &geoms);
    assert!(b.report.primitive_count as usize <= n && b.report.primitive_count as usize > n - 1000);
    compare_blas(&b.bytes, &geoms, &random_rays([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 6, 1), "2^22");
}

#[test]
fn deterministic_aabbs_multi_geometry_and_pointer_tlas() {
    let boxes = boxes_of(&scene::random_soup(40_000, 17));
    let (a, b) = (AabbData::new(&boxes[..25_000], 24, GEOMETRY_OPAQUE), AabbData::new(&boxes[25_000..], 48, 0));
    let geoms = [a.geometry(), b.geometry()];
    for tier in [FAST_TRACE, FAST_BUILD, BuildFlags::ALLOW_UPDATE] {
        let one = with_threads(1, || build_blas(tier, &geoms));
        let eight = with_threads(8, || build_blas(tier, &geoms));
        assert!(used(&one) == used(&eight), "AABB tier {tier:#x}: bytes differ");
    }
    // Array-of-pointers TLAS: the same bytes whatever the thread count, and the same
    // traversal results as the packed layout of the same instances.
    let blas = build_blas(FAST_TRACE, &[TriData::from_mesh(&scene::random_soup(300, 3), GEOMETRY_OPAQUE).geometry()]);
    let n = 5000usize;
    let recs = scene::instance_records(n, &[0x1000_0000], 5);
    let mut view = MapView::new();
    view.insert(0x1000_0000, blas.bytes);
    let base = 0x2000_0000u64;
    view.insert(base, InstanceRecord::pack(&recs));
    let ptrs: Vec<u8> = (0..n as u64).flat_map(|i| (base + 64 * i).to_le_bytes()).collect();
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: n as u32, data: GeometryData::Instances { array_of_pointers: true, data: &ptrs } }];
    let one = with_threads(1, || build(AsType::TopLevel, FAST_TRACE, &g, &view));
    let eight = with_threads(8, || build(AsType::TopLevel, FAST_TRACE, &g, &view));
    assert!(used(&one) == used(&eight), "pointer TLAS bytes differ");
    let packed = InstanceRecord::pack(&recs);
    let gp = [Geometry { flags: GeometryFlags(0), primitive_count: n as u32, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
    let p = build(AsType::TopLevel, FAST_TRACE, &gp, &view);
    let ext = 2.0 * (n as f32).cbrt() + 2.0;
    for ray in random_rays([-1.0, -1.0, -1.0, ext, ext, ext], 300, 6) {
        let x = accel::closest_hit(&one.bytes, &view, copy_ray(&ray), RayFlags(0), 0xFF).map(|h| (h.t, hit_id(&h)));
        let y = accel::closest_hit(&p.bytes, &view, copy_ray(&ray), RayFlags(0), 0xFF).map(|h| (h.t, hit_id(&h)));
        assert_eq!(x, y);
    }
}

/// Spec: degenerate primitives may become non-degenerate in an update, so a build with
/// ALLOW_UPDATE must keep them. Build with zero-area triangles (points and lines) and
/// infinite-vertex triangles, refit to proper triangles, compare with brute force.
#[test]
fn refit_revives_degenerate_primitives() {
    let good = scene::random_soup(3000, 71);
    let mut degen = good.clone();
    for (i, t) in good.indices.iter().enumerate() {
        match i % 4 {
            0 => {
                let p = good.positions[t[0] as usize];
                for &k in t {
                    degen.positions[k as usize] = p; // a point
                }
            }
            1 => {
                let (a, b) = (good.positions[t[0] as usize], good.positions[t[1] as usize]);
                degen.positions[t[2] as usize] = [2.0 * b[0] - a[0], 2.0 * b[1] - a[1], 2.0 * b[2] - a[2]]; // a line
            }
            2 => degen.positions[t[1] as usize][1] = f32::INFINITY, // active, infinite
            _ => {}
        }
    }
    let d = TriData::from_mesh(&degen, 0);
    let flags = BuildFlags::ALLOW_UPDATE | FAST_TRACE;
    let mut built = build_blas(flags, &[d.geometry()]);
    let g = TriData::from_mesh(&good, 0);
    let geoms = [g.geometry()];
    let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &geoms };
    let mut scratch = vec![0u8; built.sizes.update_scratch_size as usize];
    accel::update(&desc, &accel::NoDevice, None, &mut built.bytes, &mut scratch).expect("update");
    accel::validate(&built.bytes).expect("validate after update");
    let hits = compare_blas(&built.bytes, &geoms, &random_rays([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 500, 72), "revived");
    assert!(hits > 200, "{hits}");
}

#[test]
fn hostile_rays_and_instance_transforms_do_not_panic() {
    let blas = build_blas(0, &[TriData::from_mesh(&scene::random_soup(200, 1), 0).geometry()]);
    let mut view = MapView::new();
    view.insert(0x1000, blas.bytes.clone());
    let mut recs = scene::instance_records(40, &[0x1000], 2);
    let nan = f32::NAN;
    let inf = f32::INFINITY;
    recs[0].transform = [0.0; 12]; // singular
    recs[1].transform = [nan; 12];
    recs[2].transform = [inf, 0.0, 0.0, 0.0, 0.0, inf, 0.0, 0.0, 0.0, 0.0, inf, 0.0];
    recs[3].transform = [1e30, 0.0, 0.0, 1e30, 0.0, 1e-30, 0.0, 0.0, 0.0, 0.0, 1.0, -1e30];
    recs[4].transform[3] = nan;
    let packed = InstanceRecord::pack(&recs);
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: 40, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
    let t = build(AsType::TopLevel, FAST_TRACE, &g, &view);
    let v = glam::Vec3::new;
    let odd = [
        Ray { origin: v(nan, 0.0, 0.0), direction: v(1.0, 0.0, 0.0), tmin: 0.0, tmax: inf },
        Ray { origin: v(0.0, 0.0, 0.0), direction: v(0.0, 0.0, 0.0), tmin: 0.0, tmax: inf },
        Ray { origin: v(0.0, 0.0, 0.0), direction: v(nan, 1.0, 0.0), tmin: 0.0, tmax: inf },
        Ray { origin: v(-inf, 0.5, 0.5), direction: v(1.0, 0.0, 0.0), tmin: 0.0, tmax: inf },
        Ray { origin: v(0.5, 0.5, -5.0), direction: v(0.0, 0.0, inf), tmin: 0.0, tmax: inf },
        Ray { origin: v(0.5, 0.5, -5.0), direction: v(0.0, 0.0, 1.0), tmin: nan, tmax: inf },
        Ray { origin: v(0.5, 0.5, -5.0), direction: v(0.0, 0.0, 1.0), tmin: -inf, tmax: nan },
        Ray { origin: v(0.5, 0.5, -5.0), direction: v(1e-38, 1e-38, 1e-38), tmin: 0.0, tmax: inf },
    ];
    for (i, r) in odd.iter().enumerate() {
        for s in [&t.bytes, &blas.bytes] {
            let _ = accel::closest_hit(s, &view, copy_ray(r), RayFlags(0), 0xFF);
            let _ = accel::any_hit(s, &view, copy_ray(r), RayFlags(0), 0xFF);
            let all = accel::all_hits(s, &view, copy_ray(r), RayFlags(0), 0xFF);
            for h in all {
                assert!(h.t.is_finite() || h.t == f32::INFINITY, "ray {i}: hit with t {}", h.t);
            }
        }
    }
    // Normal rays still agree with brute force on the healthy instances (5..40), since the
    // reference skips instances whose transform it cannot invert and traverses the rest.
    let healthy: Vec<InstanceRecord> = recs.iter().enumerate().map(|(i, r)| if i < 5 { InstanceRecord { reference: 0, ..*r } } else { *r }).collect();
    let hp = InstanceRecord::pack(&healthy);
    let hg = [Geometry { flags: GeometryFlags(0), primitive_count: 40, data: GeometryData::Instances { array_of_pointers: false, data: &hp } }];
    let ht = build(AsType::TopLevel, FAST_TRACE, &hg, &view);
    let geoms = [TriData::from_mesh(&scene::random_soup(200, 1), 0)];
    let gg: Vec<Geometry> = geoms.iter().map(|d| d.geometry()).collect();
    let blases: HashMap<u64, &[Geometry]> = [(0x1000u64, gg.as_slice())].into_iter().collect();
    let scene = RefScene::Tlas { instances: healthy.clone(), blases };
    let ext = 2.0 * 40f32.cbrt() + 2.0;
    for (i, ray) in random_rays([-1.0, -1.0, -1.0, ext, ext, ext], 200, 9).iter().enumerate() {
        compare_ray(&ht.bytes, &view, &scene, ray, 0, 0xFF, Tolerance { exact: false }, &format!("healthy ray {i}"));
    }
}

/// Pathological distributions that make deep or lopsided trees: geometric spacing along a line
/// (down to subnormals), a dense cluster with a few far outliers, many copies of one triangle.
#[test]
fn pathological_distributions_match_brute_force() {
    let mut cases: Vec<(&str, Mesh, [f32; 6])> = Vec::new();
    // Geometric: triangle k at x = 0.7^k (k < 300 reaches subnormals and zero).
    let mut m = Mesh::default();
    for k in 0..300u32 {
        let x = 0.7f32.powi(k as i32);
        let s = x * 0.1;
        let b = m.positions.len() as u32;
        m.positions.extend([[x, 0.0, 0.0], [x + s, 1.0, 0.0], [x, 0.0, 1.0]]);
        m.indices.push([b, b + 1, b + 2]);
    }
    cases.push(("geometric", m, [0.0, 0.0, 0.0, 1.1, 1.0, 1.0]));
    // Cluster + outliers.
    let mut c = scene::random_soup(20_000, 3);
    for p in c.positions.iter_mut() {
        for x in p.iter_mut() {
            *x = 0.5 + (*x - 0.5) * 1e-3;
        }
    }
    for (i, far) in [1e6f32, -1e6, 3e5].iter().enumerate() {
        c.positions[3 * i] = [*far, 0.5, 0.5];
    }
    cases.push(("cluster+outliers", c, [0.499, 0.499, 0.499, 0.501, 0.501, 0.501]));
    // 5000 copies of the same triangle (distinct vertices, same positions) plus a few others.
    let mut d = Mesh::default();
    for k in 0..5000u32 {
        d.positions.extend([[0.2, 0.2, 0.5], [0.8, 0.3, 0.5], [0.4, 0.9, 0.5]]);
        d.indices.push([3 * k, 3 * k + 1, 3 * k + 2]);
    }
    cases.push(("copies", d, [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]));
    for (name, mesh, bounds) in cases {
        let data = TriData::from_mesh(&mesh, 0);
        let geoms = [data.geometry()];
        let rays = random_rays(bounds, 300, 5);
        for tier in TIERS {
            let b = build_blas(tier, &geoms);
            let m = accel::metrics(&b.bytes).unwrap();
            assert!(m.max_depth < 200, "{name}: depth {}", m.max_depth);
            compare_blas(&b.bytes, &geoms, &rays, &format!("{name} tier {tier:#x}"));
        }
    }
}

#[test]
fn odd_descriptions_do_not_panic() {
    // No geometries at all, BLAS and TLAS.
    for ty in [AsType::BottomLevel, AsType::TopLevel] {
        let b = build(ty, 0, &[], &accel::NoDevice);
        assert!(accel::closest_hit(&b.bytes, &accel::NoDevice, Ray { origin: glam::Vec3::ZERO, direction: glam::Vec3::X, tmin: 0.0, tmax: 1e30 }, RayFlags(0), 0xFF).is_none());
    }
    // Instances referring to nothing known, and to a TLAS, must not panic at build or trace.
    let blas = build_blas(0, &[TriData::from_mesh(&scene::random_soup(100, 1), 0).geometry()]);
    let mut view = MapView::new();
    view.insert(0x1000, blas.bytes);
    let recs = scene::instance_records(8, &[0x1000], 1);
    let packed = InstanceRecord::pack(&recs);
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: 8, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
    let tlas = build(AsType::TopLevel, 0, &g, &view);
    view.insert(0x9000, tlas.bytes);
    let bad = scene::instance_records(8, &[0x1000, 0xBAD0, 0x9000], 2);
    let bp = InstanceRecord::pack(&bad);
    let bg = [Geometry { flags: GeometryFlags(0), primitive_count: 8, data: GeometryData::Instances { array_of_pointers: false, data: &bp } }];
    if let Ok(t) = try_build(AsType::TopLevel, 0, &bg, &view) {
        for r in random_rays([-2.0, -2.0, -2.0, 6.0, 6.0, 6.0], 100, 3) {
            let _ = accel::closest_hit(&t.bytes, &view, copy_ray(&r), RayFlags(0), 0xFF);
            let _ = accel::all_hits(&t.bytes, &view, r, RayFlags(0), 0xFF);
        }
    }
    // Update scratch too small / destination too small: typed errors.
    let data = TriData::from_mesh(&scene::random_soup(5000, 2), 0);
    let geoms = [data.geometry()];
    let built = build_blas(BuildFlags::ALLOW_UPDATE, &geoms);
    let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(BuildFlags::ALLOW_UPDATE), geometries: &geoms };
    if built.sizes.update_scratch_size > 0 {
        let mut s = vec![0u8; 4];
        let mut dst = built.bytes.clone();
        assert!(accel::update(&desc, &accel::NoDevice, None, &mut dst, &mut s).is_err());
    }
    let mut small = vec![0u8; 100];
    let mut s = vec![0u8; built.sizes.update_scratch_size as usize];
    assert!(accel::update(&desc, &accel::NoDevice, Some(&built.bytes), &mut small, &mut s).is_err());
}

/// Refit and serialization are deterministic too: update with 1 and 8 threads gives the same
/// bytes, and serializing twice gives the same blob.
#[test]
fn refit_and_serialize_are_deterministic() {
    let base = scene::random_soup(50_000, 91);
    let moved = Mesh { positions: base.positions.iter().map(|p| [p[0] * 1.3, p[1] + 0.2 * p[0], p[2]]).collect(), indices: base.indices.clone() };
    let (d0, d1) = (TriData::from_mesh(&base, 0), TriData::from_mesh(&moved, 0));
    let flags = BuildFlags::ALLOW_UPDATE | FAST_TRACE;
    let built = build_blas(flags, &[d0.geometry()]);
    let g1 = [d1.geometry()];
    let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &g1 };
    let run = |threads| {
        with_threads(threads, || {
            let mut dst = vec![0u8; built.bytes.len()];
            let mut scratch = vec![0u8; built.sizes.update_scratch_size as usize];
            let r = accel::update(&desc, &accel::NoDevice, Some(&built.bytes), &mut dst, &mut scratch).expect("update");
            dst.truncate(r.used_size as usize);
            dst
        })
    };
    let one = run(1);
    assert!(one == run(8), "refit bytes differ between 1 and 8 threads");
    assert!(one == run(2), "refit bytes differ between 1 and 2 threads");
    let ser = |s: &[u8]| {
        let mut out = vec![0u8; accel::serialized_size(s).unwrap() as usize];
        accel::serialize(s, [1; 16], &mut out).unwrap();
        out
    };
    assert!(ser(&built.bytes) == ser(&built.bytes));
    // Deserializing into too small a destination is an error, not a panic.
    let blob = ser(&built.bytes);
    let mut tiny = vec![0u8; 64];
    assert!(accel::deserialize(&blob, [1; 16], &mut tiny).is_err());
}

/// Inactive (NaN) and zero-area triangles spread through 150k primitives: the parallel
/// compaction after ingest keeps the survivors in input order, so the structure is the same
/// for 1, 2 and 8 threads, valid, and brute-force equal.
#[test]
fn dropped_primitives_compact_deterministically() {
    let mut m = scene::random_soup(150_000, 31);
    for (t, tri) in m.indices.clone().iter().enumerate() {
        if t % 7 == 3 {
            m.positions[tri[0] as usize][0] = f32::NAN; // inactive
        } else if t % 11 == 5 {
            let p = m.positions[tri[0] as usize];
            m.positions[tri[1] as usize] = p; // zero area: dropped when updates are not allowed
        }
    }
    let data = TriData::from_mesh(&m, GEOMETRY_OPAQUE);
    let geoms = [data.geometry()];
    for tier in [FAST_TRACE, FAST_BUILD] {
        let one = with_threads(1, || build_blas(tier, &geoms));
        assert!((one.report.primitive_count as usize) < 150_000 * 6 / 7, "drops happened: {}", one.report.primitive_count);
        for threads in [2, 8] {
            let again = with_threads(threads, || build_blas(tier, &geoms));
            assert!(used(&again) == used(&one), "tier {tier:#x}: bytes differ with {threads} threads");
        }
        compare_blas(&one.bytes, &geoms, &random_rays([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 300, 9), "dropped");
    }
}

/// Large nodes without an SAH split: 100k copies of one triangle (equal centroids: no bin
/// grid, median splits all the way down through the parallel and sampled paths), then the
/// same copies mixed with 70k random triangles. Valid and brute-force equal for every tier.
#[cfg(not(debug_assertions))]
#[test]
fn large_coincident_inputs_take_the_fallback_paths() {
    let rays = random_rays([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 40, 8);
    let tri = [[0.1f32, 0.2, 0.3], [0.6, 0.1, -0.2], [-0.3, 0.5, 0.4]];
    degenerate_case("100k identical", tri.to_vec(), vec![[0, 1, 2]; 100_000], &rays);
    let soup = scene::random_soup(70_000, 12);
    let mut pos = tri.to_vec();
    pos.extend(soup.positions.iter().map(|p| [p[0] * 2.0 - 1.0, p[1] * 2.0 - 1.0, p[2] * 2.0 - 1.0]));
    let mut idx = vec![[0u32, 1, 2]; 100_000];
    idx.extend(soup.indices.iter().map(|t| [t[0] + 3, t[1] + 3, t[2] + 3]));
    degenerate_case("100k identical + 70k random", pos, idx, &rays);
}

//! Traversal equals brute force: closest hit (t bit-equal for BLAS, primitive identity),
//! any hit, and the any-hit candidate sets of `all_hits`, on real meshes and random soups,
//! for triangles and AABBs, several geometries, index types, vertex formats, two-level
//! structures with instance transforms/masks/flags, and every ray/instance flag combination.

mod reference;

use arbor::accel::{self, AsType, BuildFlags, Geometry, GeometryData, GeometryFlags, IndexType, MapView, Ray, VertexFormat};
use arbor_scene::{self as scene, InstanceRecord, Mesh, Rng};
use reference::brute_force::*;
use reference::*;
use std::collections::HashMap;

const FAST_TRACE: u32 = BuildFlags::PREFER_FAST_TRACE;
const FAST_BUILD: u32 = BuildFlags::PREFER_FAST_BUILD;
const TIERS: [u32; 3] = [FAST_TRACE, 0, FAST_BUILD];
const EXACT: Tolerance = Tolerance { exact: true };
const TLAS_TOL: Tolerance = Tolerance { exact: false };

fn check_blas_mesh(name: &str, mesh: &Mesh, rays: usize, tiers: &[u32]) {
    let data = TriData::from_mesh(mesh, GEOMETRY_OPAQUE);
    let geoms = [data.geometry()];
    let scene = RefScene::Blas(&geoms);
    let rays = random_rays(mesh.bounds(), rays, 42);
    for &tier in tiers {
        let built = build_blas(tier, &geoms);
        // Zero-area triangles (and repeated indices) may be dropped: count them independently.
        let zero_area = (0..mesh.indices.len())
            .filter(|&i| {
                let [a, b, c] = mesh.triangle(i).map(|p| p.map(|x| x as f64));
                let (e1, e2) = ([b[0] - a[0], b[1] - a[1], b[2] - a[2]], [c[0] - a[0], c[1] - a[1], c[2] - a[2]]);
                let n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
                n == [0.0; 3]
            })
            .count();
        let stored = built.report.primitive_count as usize;
        assert!(stored <= mesh.indices.len() && stored >= mesh.indices.len() - zero_area, "{name}: stores {stored} of {} ({zero_area} zero-area)", mesh.indices.len());
        let mut hit_rays = 0;
        for (i, ray) in rays.iter().enumerate() {
            let n = compare_ray(&built.bytes, &accel::NoDevice, &scene, ray, 0, 0xFF, EXACT, &format!("{name} tier {tier:#x} ray {i}"));
            hit_rays += (n > 0) as usize;
        }
        // The rays must actually exercise hits (most are aimed at the object).
        assert!(hit_rays * 5 > rays.len(), "{name}: only {hit_rays} of {} rays hit", rays.len());
    }
}

#[test]
fn blas_bunny_matches_brute_force() {
    let m = scene::load(data_path("bunny.ply")).unwrap();
    check_blas_mesh("bunny", &m, 1500, &TIERS);
}

#[test]
fn blas_dragon_res4_matches_brute_force() {
    let m = scene::load(data_path("dragon_vrip_res4.ply.gz")).unwrap();
    check_blas_mesh("dragon res4", &m, 800, &TIERS);
}

#[test]
fn blas_dragon_res3_matches_brute_force() {
    let m = scene::load(data_path("dragon_vrip_res3.ply.gz")).unwrap();
    check_blas_mesh("dragon res3", &m, 250, &[FAST_TRACE, FAST_BUILD]);
}

/// 202,520 triangles: large enough that the top nodes bin a sample (nodes of 2^16 or more
/// references) and take the parallel partition, whose exact child boxes `validate` checks.
#[cfg(not(debug_assertions))]
#[test]
fn blas_dragon_res2_matches_brute_force() {
    let m = scene::load(data_path("dragon_vrip_res2.ply.gz")).unwrap();
    check_blas_mesh("dragon res2", &m, 60, &TIERS);
}

#[test]
fn blas_random_soups_match_brute_force() {
    for (n, seed) in [(1usize, 1u64), (7, 2), (100, 3), (5000, 4), (30_000, 5)] {
        let m = scene::random_soup(n, seed);
        check_blas_mesh(&format!("soup {n}"), &m, if n > 10_000 { 300 } else { 600 }, &TIERS);
    }
    check_blas_mesh("terrain 64", &scene::terrain(64), 600, &TIERS);
}

/// Opaque and non-opaque triangle geometries, one with a transform, U16/U32/NONE indices and
/// several vertex formats, in one BLAS.
// One function: one BLAS of mixed geometries, described geometry by geometry, then checked once.
#[test]
fn blas_several_geometries_formats_index_types_transforms() {
    let soup = scene::random_soup(400, 77);
    let terr = scene::terrain(12);
    let bunny = scene::load(data_path("bunny.ply")).unwrap();
    // Bunny scaled into [-1,1] so that SNORM can hold it.
    let bb = bunny.bounds();
    let scale = 2.0 / (bb[3] - bb[0]).max(bb[4] - bb[1]).max(bb[5] - bb[2]);
    let bunny_unit: Vec<[f32; 3]> = bunny
        .positions
        .iter()
        .map(|p| [(p[0] - (bb[0] + bb[3]) / 2.0) * scale, (p[1] - (bb[1] + bb[4]) / 2.0) * scale, (p[2] - (bb[2] + bb[5]) / 2.0) * scale])
        .collect();

    let mut datas = Vec::new();
    // 0: f32, U32, opaque.
    datas.push(TriData::from_mesh(&soup, GEOMETRY_OPAQUE));
    // 1: half floats, U16 indices, non-opaque, with a transform.
    let (vb, _) = encode_vertices(&terr.positions, VertexFormat::R16G16B16A16Sfloat, 8);
    datas.push(TriData {
        vertices: vb,
        stride: 8,
        format: VertexFormat::R16G16B16A16Sfloat,
        indices: terr.index_bytes_u16().unwrap(),
        index_type: IndexType::U16,
        max_vertex: terr.max_index(),
        count: terr.indices.len() as u32,
        transform: Some([0.0, 0.0, 1.5, -0.5, 0.0, 2.0, 0.0, 0.25, -1.0, 0.0, 0.0, 1.0]),
        flags: 0,
    });
    // 2: SNORM16 with a stride of 12, U32 indices, opaque.
    let (vb, _) = encode_vertices(&bunny_unit, VertexFormat::R16G16B16A16Snorm, 12);
    datas.push(TriData {
        vertices: vb,
        stride: 12,
        format: VertexFormat::R16G16B16A16Snorm,
        indices: bunny.index_bytes(),
        index_type: IndexType::U32,
        max_vertex: bunny.max_index(),
        count: bunny.indices.len() as u32,
        transform: None,
        flags: GEOMETRY_OPAQUE,
    });
    // 3: non-indexed f32 with stride 16 (RGBA32F), non-opaque, transformed.
    let small = scene::random_soup(200, 5);
    let unindexed: Vec<[f32; 3]> = (0..small.indices.len()).flat_map(|i| small.triangle(i)).collect();
    let (vb, _) = encode_vertices(&unindexed, VertexFormat::R32G32B32A32Sfloat, 16);
    datas.push(TriData {
        vertices: vb,
        stride: 16,
        format: VertexFormat::R32G32B32A32Sfloat,
        indices: Vec::new(),
        index_type: IndexType::None,
        max_vertex: unindexed.len() as u32 - 1,
        count: small.indices.len() as u32,
        transform: Some([1.0, 0.2, 0.0, 0.1, 0.0, 1.0, 0.0, -0.3, 0.0, 0.0, 1.0, 0.2]),
        flags: 0,
    });
    // 4: 2-component half floats (z = 0), U16.
    let (vb, _) = encode_vertices(&soup.positions[..300], VertexFormat::R16G16Sfloat, 4);
    let idx: Vec<[u32; 3]> = (0..100).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
    datas.push(TriData {
        vertices: vb,
        stride: 4,
        format: VertexFormat::R16G16Sfloat,
        indices: idx.iter().flatten().flat_map(|&i| (i as u16).to_le_bytes()).collect(),
        index_type: IndexType::U16,
        max_vertex: 299,
        count: 100,
        transform: None,
        flags: GEOMETRY_OPAQUE,
    });
    let geoms: Vec<Geometry> = datas.iter().map(|d| d.geometry()).collect();
    let scene = RefScene::Blas(&geoms);
    let mut all_points = Vec::new();
    for g in &geoms {
        for p in 0..g.primitive_count {
            if let Some(t) = accel::fetch_triangle(g, p) {
                all_points.extend(t.iter().map(|v| v.to_array()));
            }
        }
    }
    let bounds = union_bounds(all_points);
    let rays = random_rays(bounds, 600, 8);
    for tier in TIERS {
        let built = build_blas(tier, &geoms);
        let h = accel::header(&built.bytes).unwrap();
        assert_eq!(h.geometry_count, 5);
        let mut seen_geoms = std::collections::BTreeSet::new();
        for (i, ray) in rays.iter().enumerate() {
            compare_ray(&built.bytes, &accel::NoDevice, &scene, ray, 0, 0xFF, EXACT, &format!("multi tier {tier:#x} ray {i}"));
            if let Some(hh) = accel::closest_hit(&built.bytes, &accel::NoDevice, copy_ray(ray), accel::RayFlags(0), 0xFF) {
                seen_geoms.insert(hh.geometry_index);
            }
        }
        assert!(seen_geoms.len() >= 4, "rays reached only geometries {seen_geoms:?}");
    }
}

#[test]
fn blas_aabbs_match_brute_force() {
    let m = scene::random_soup(3000, 21);
    let boxes = boxes_of(&m);
    let half = boxes.len() / 2;
    let a = AabbData::new(&boxes[..half], 24, GEOMETRY_OPAQUE);
    let b = AabbData::new(&boxes[half..], 40, 0);
    let geoms = [a.geometry(), b.geometry()];
    let scene = RefScene::Blas(&geoms);
    let rays = random_rays([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 400, 3);
    for tier in TIERS {
        let built = build_blas(tier, &geoms);
        for (i, ray) in rays.iter().enumerate() {
            for flags in [0, OPAQUE, CULL_OPAQUE, CULL_NO_OPAQUE, SKIP_AABBS, TERMINATE_ON_FIRST_HIT] {
                compare_ray(&built.bytes, &accel::NoDevice, &scene, ray, flags, 0xFF, EXACT, &format!("aabb tier {tier:#x} ray {i} flags {flags:#x}"));
            }
        }
    }
}

/// A BLAS of triangles: half opaque, half not, both windings present.
fn flag_test_triangles() -> Vec<TriData> {
    let m = scene::random_soup(600, 31);
    let mut a = m.clone();
    a.indices.truncate(300);
    let mut b = m;
    b.indices.drain(..300);
    vec![TriData::from_mesh(&a, GEOMETRY_OPAQUE), TriData::from_mesh(&b, 0)]
}

#[test]
fn blas_every_ray_flag_combination() {
    let datas = flag_test_triangles();
    let geoms: Vec<Geometry> = datas.iter().map(|d| d.geometry()).collect();
    let scene = RefScene::Blas(&geoms);
    let boxes = AabbData::new(&boxes_of(&scene::random_soup(300, 32)), 24, GEOMETRY_OPAQUE);
    let boxes_nop = AabbData::new(&boxes_of(&scene::random_soup(300, 33)), 24, 0);
    let bgeoms = [boxes.geometry(), boxes_nop.geometry()];
    let bscene = RefScene::Blas(&bgeoms);
    let built = build_blas(FAST_TRACE, &geoms);
    let bbuilt = build_blas(FAST_BUILD, &bgeoms);
    let rays = random_rays([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 40, 17);
    for flags in all_ray_flag_combinations() {
        for (i, ray) in rays.iter().enumerate() {
            compare_ray(&built.bytes, &accel::NoDevice, &scene, ray, flags, 0xFF, EXACT, &format!("tri flags {flags:#x} ray {i}"));
            compare_ray(&bbuilt.bytes, &accel::NoDevice, &bscene, ray, flags, 0xFF, EXACT, &format!("aabb flags {flags:#x} ray {i}"));
        }
    }
}

/// Everything a TLAS test needs: BLASes placed in a MapView, instance records, the reference.
struct TlasFixture {
    view: MapView,
    instances: Vec<InstanceRecord>,
    blas_geoms: Vec<(u64, Vec<TriData>, Vec<AabbData>)>,
    bounds: [f32; 6],
}

const BLAS_BASE: u64 = 0x10_0000_0000;

fn tlas_fixture(n_instances: usize, seed: u64, tier: u32) -> TlasFixture {
    let mut view = MapView::new();
    let mut blas_geoms = Vec::new();
    let mut blas_bounds = Vec::new();
    // BLAS 0: triangles, opaque + non-opaque. BLAS 1: bunny-ish soup, transformed geometry.
    // BLAS 2: AABBs (opaque + non-opaque). BLAS 3: an empty BLAS (no primitives).
    let tri0 = flag_test_triangles();
    let mut t1 = TriData::from_mesh(&scene::terrain(10), 0);
    t1.transform = Some([1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.3, 0.0, 0.0, 1.0, 0.0]);
    let a2 = vec![
        AabbData::new(&boxes_of(&scene::random_soup(200, seed + 1)), 24, GEOMETRY_OPAQUE),
        AabbData::new(&boxes_of(&scene::random_soup(100, seed + 2)), 32, 0),
    ];
    let configs: Vec<(Vec<TriData>, Vec<AabbData>)> = vec![(tri0, vec![]), (vec![t1], vec![]), (vec![], a2), (vec![TriData::from_mesh(&Mesh::default(), 0)], vec![])];
    for (k, (tris, boxes)) in configs.into_iter().enumerate() {
        let address = BLAS_BASE * (k as u64 + 1);
        let geoms: Vec<Geometry> = tris.iter().map(|d| d.geometry()).chain(boxes.iter().map(|b| b.geometry())).collect();
        let built = build_blas(tier, &geoms);
        let h = accel::header(&built.bytes).unwrap();
        blas_bounds.push(h.bounds);
        view.insert(address, built.bytes);
        blas_geoms.push((address, tris, boxes));
    }
    let refs: Vec<u64> = blas_geoms.iter().map(|b| b.0).collect();
    let mut instances = scene::instance_records(n_instances, &refs, seed);
    let mut rng = Rng::new(seed);
    let flag_combos = all_instance_flag_combinations();
    for (i, inst) in instances.iter_mut().enumerate() {
        // Random (not i % k: the BLAS is chosen round robin, and the periods must not line up).
        inst.flags = flag_combos[rng.below(flag_combos.len() as u32) as usize];
        inst.mask = [0xFF, 0x01, 0x02, 0x80, 0x0F, 0xF0][rng.below(6) as usize];
        inst.custom_index = rng.next_u32() & 0xFF_FFFF;
        inst.sbt_offset = rng.next_u32() & 0xFF_FFFF;
        if i % 11 == 5 {
            inst.reference = 0; // inactive
        }
    }
    let mut corners = Vec::new();
    for inst in &instances {
        let k = blas_geoms.iter().position(|b| b.0 == inst.reference);
        let Some(k) = k else { continue };
        let b = blas_bounds[k];
        if !b.iter().all(|c| c.is_finite()) {
            continue;
        }
        let m: [f64; 12] = inst.transform.map(|x| x as f64);
        for c in 0..8 {
            let p = [b[if c & 1 == 0 { 0 } else { 3 }], b[if c & 2 == 0 { 1 } else { 4 }], b[if c & 4 == 0 { 2 } else { 5 }]];
            corners.push(xform_point(&m, p.map(|x| x as f64)).map(|x| x as f32));
        }
    }
    TlasFixture { view, instances, blas_geoms, bounds: union_bounds(corners) }
}

fn geoms_of(f: &TlasFixture) -> Vec<(u64, Vec<Geometry<'_>>)> {
    f.blas_geoms
        .iter()
        .map(|(a, t, b)| (*a, t.iter().map(|d| d.geometry()).chain(b.iter().map(|x| x.geometry())).collect()))
        .collect()
}

fn build_tlas(f: &TlasFixture, tier: u32, pointers: bool) -> (Built, Option<MapView>) {
    let packed = InstanceRecord::pack(&f.instances);
    if !pointers {
        let g = [Geometry {
            flags: GeometryFlags(0),
            primitive_count: f.instances.len() as u32,
            data: GeometryData::Instances { array_of_pointers: false, data: &packed },
        }];
        (build(AsType::TopLevel, tier, &g, &f.view), None)
    } else {
        // Instances in a device buffer in reverse order, addressed through pointers.
        let base = 0x7_0000_0000u64;
        let n = f.instances.len();
        let mut buf = vec![0u8; 64 * n];
        let mut ptrs = Vec::with_capacity(8 * n);
        for (i, r) in f.instances.iter().enumerate() {
            let slot = n - 1 - i;
            buf[64 * slot..64 * slot + 64].copy_from_slice(&r.to_bytes());
            ptrs.extend_from_slice(&(base + 64 * slot as u64).to_le_bytes());
        }
        let mut view = MapView::new();
        for (a, _, _) in &f.blas_geoms {
            view.insert(*a, f.view.acceleration_structure(*a).unwrap().to_vec());
        }
        view.insert(base, buf);
        let g = [Geometry {
            flags: GeometryFlags(0),
            primitive_count: n as u32,
            data: GeometryData::Instances { array_of_pointers: true, data: &ptrs },
        }];
        let built = build(AsType::TopLevel, tier, &g, &view);
        (built, Some(view))
    }
}

use arbor::accel::DeviceView;

#[test]
fn tlas_matches_brute_force() {
    for (tier, pointers) in [(FAST_TRACE, false), (FAST_BUILD, false), (0, true)] {
        let f = tlas_fixture(60, 9, tier);
        let geoms = geoms_of(&f);
        let blases: HashMap<u64, &[Geometry]> = geoms.iter().map(|(a, g)| (*a, g.as_slice())).collect();
        let scene = RefScene::Tlas { instances: f.instances.clone(), blases };
        let (tlas, pview) = build_tlas(&f, tier, pointers);
        let view: &dyn DeviceView = pview.as_ref().map(|v| v as &dyn DeviceView).unwrap_or(&f.view);
        let h = accel::header(&tlas.bytes).unwrap();
        assert_eq!(h.ty, AsType::TopLevel);
        let rays = random_rays(f.bounds, 500, 99);
        let mut hits = 0;
        for (i, ray) in rays.iter().enumerate() {
            for mask in [0xFF, 0x01, 0x70] {
                hits += compare_ray(&tlas.bytes, view, &scene, ray, 0, mask, TLAS_TOL, &format!("tlas tier {tier:#x} ptrs {pointers} ray {i} mask {mask:#x}"));
            }
        }
        assert!(hits > 500, "only {hits} reference hits: the rays miss the scene");
        // Masks: 0 finds nothing.
        for ray in rays.iter().take(50) {
            assert!(accel::closest_hit(&tlas.bytes, view, copy_ray(ray), accel::RayFlags(0), 0).is_none());
        }
    }
}

#[test]
fn tlas_every_ray_flag_combination() {
    let f = tlas_fixture(40, 12, FAST_TRACE);
    let geoms = geoms_of(&f);
    let blases: HashMap<u64, &[Geometry]> = geoms.iter().map(|(a, g)| (*a, g.as_slice())).collect();
    let scene = RefScene::Tlas { instances: f.instances.clone(), blases };
    let (tlas, _) = build_tlas(&f, FAST_TRACE, false);
    let rays = random_rays(f.bounds, 25, 5);
    for flags in all_ray_flag_combinations() {
        for (i, ray) in rays.iter().enumerate() {
            compare_ray(&tlas.bytes, &f.view, &scene, ray, flags, 0xFF, TLAS_TOL, &format!("tlas flags {flags:#x} ray {i}"));
        }
    }
}

#[test]
fn tlas_hit_reports_instance_attributes_and_object_ray() {
    // One instance with a non-trivial transform over one triangle: check object-space ray,
    // transforms and instance fields of the hit against values computed here.
    let tri = Mesh { positions: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], indices: vec![[0, 1, 2]] };
    let data = TriData::from_mesh(&tri, GEOMETRY_OPAQUE);
    let blas = build_blas(0, &[data.geometry()]);
    let mut view = MapView::new();
    view.insert(BLAS_BASE, blas.bytes);
    let transform = [0.0, -2.0, 0.0, 5.0, 2.0, 0.0, 0.0, 1.0, 0.0, 0.0, 2.0, -3.0];
    let inactive = InstanceRecord { transform, custom_index: 1, mask: 0xFF, sbt_offset: 0, flags: 0, reference: 0 };
    let inst = InstanceRecord { transform, custom_index: 0xABCDE, mask: 0x3, sbt_offset: 0x1234, flags: 0, reference: BLAS_BASE };
    let packed = InstanceRecord::pack(&[inactive, inst]);
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: 2, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
    let tlas = build(AsType::TopLevel, 0, &g, &view);
    // Object point (0.25, 0.25, 0) maps to world (5 - 0.5, 1 + 0.5, -3) = (4.5, 1.5, -3).
    let ray = Ray { origin: glam::Vec3::new(4.5, 1.5, 1.0), direction: glam::Vec3::new(0.0, 0.0, -2.0), tmin: 0.0, tmax: 100.0 };
    let h = accel::closest_hit(&tlas.bytes, &view, copy_ray(&ray), accel::RayFlags(0), 0xFF).expect("hit");
    assert_eq!(h.instance_index, 1, "InstanceId counts the inactive instance before it");
    assert_eq!(h.instance_custom_index, 0xABCDE);
    assert_eq!(h.sbt_record_offset, 0x1234);
    assert_eq!((h.geometry_index, h.primitive_index), (0, 0));
    assert!((h.t - 2.0).abs() < 1e-5, "t {}", h.t);
    assert!((h.barycentrics[0] - 0.25).abs() < 1e-5 && (h.barycentrics[1] - 0.25).abs() < 1e-5, "{:?}", h.barycentrics);
    let inv = invert_3x4(&transform).unwrap();
    let o = xform_point(&inv, [4.5, 1.5, 1.0]);
    let d = xform_vector(&inv, [0.0, 0.0, -2.0]);
    for k in 0..3 {
        assert!((h.object_ray_origin[k] as f64 - o[k]).abs() < 1e-5);
        assert!((h.object_ray_direction[k] as f64 - d[k]).abs() < 1e-5);
    }
    assert_eq!(h.object_to_world, transform);
    for (got, want) in h.world_to_object.iter().zip(&inv) {
        assert!((*got as f64 - want).abs() < 1e-6, "world_to_object {:?}", h.world_to_object);
    }
    // Object-space direction (0,0,-1)·n where n = (0,0,1): n·d < 0 → front facing.
    assert!(h.front_face);
    // Cull mask that shares no bit with the instance's mask (0x3).
    assert!(accel::closest_hit(&tlas.bytes, &view, copy_ray(&ray), accel::RayFlags(0), 0xFC).is_none());
    assert!(accel::closest_hit(&tlas.bytes, &view, copy_ray(&ray), accel::RayFlags(0), 0x02).is_some());
    // BLAS traversal: instance fields zero, identity transforms.
    let bray = Ray { origin: glam::Vec3::new(0.25, 0.25, 1.0), direction: glam::Vec3::new(0.0, 0.0, -1.0), tmin: 0.0, tmax: 10.0 };
    let bh = accel::closest_hit(view.acceleration_structure(BLAS_BASE).unwrap(), &accel::NoDevice, bray, accel::RayFlags(0), 0xFF).unwrap();
    assert_eq!((bh.instance_index, bh.instance_custom_index, bh.sbt_record_offset), (0, 0, 0));
    assert_eq!(bh.object_to_world, InstanceRecord::IDENTITY);
    assert_eq!(bh.world_to_object, InstanceRecord::IDENTITY);
}

#[test]
fn ray_query_protocol_candidates_and_commits() {
    // Non-opaque triangles and AABBs come back as candidates; committing the nearest one of
    // them leaves it as committed(); opaque triangles are committed internally.
    let datas = flag_test_triangles();
    let geoms: Vec<Geometry> = datas.iter().map(|d| d.geometry()).collect();
    let scene = RefScene::Blas(&geoms);
    let built = build_blas(FAST_TRACE, &geoms);
    let rays = random_rays([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 300, 23);
    for (i, ray) in rays.iter().enumerate() {
        let r = reference(&scene, ray, 0, 0xFF);
        let mut q = accel::RayQuery::new(&built.bytes, &accel::NoDevice, copy_ray(ray), accel::RayFlags(0), 0xFF);
        let mut best: Option<(f32, PrimId)> = None;
        while let Some(c) = q.proceed() {
            assert!(!c.opaque, "ray {i}: opaque triangle returned as a candidate");
            let id = hit_id(&c);
            let rh = r.hits.iter().find(|h| h.id == id).unwrap_or_else(|| panic!("ray {i}: candidate {id:?} not a reference hit"));
            assert_eq!(c.t, rh.t);
            // Confirm every other candidate, so that commits happen in arbitrary order.
            if id.primitive.is_multiple_of(2) {
                if let Some(cur) = q.committed() {
                    assert!(c.t <= cur.t, "ray {i}: candidate beyond committed t");
                }
                q.confirm();
                if best.is_none_or(|(t, _)| c.t < t) {
                    best = Some((c.t, id));
                }
            }
        }
        // The committed hit is the nearest of: opaque reference hits and confirmed candidates.
        let opaque_best = r.hits.iter().filter(|h| h.opaque).map(|h| (h.t, h.id)).min_by(|a, b| a.0.total_cmp(&b.0));
        let want = match (best, opaque_best) {
            (Some(a), Some(b)) => Some(if a.0 <= b.0 { a } else { b }),
            (a, b) => a.or(b),
        };
        let got = q.committed().map(|h| (h.t, hit_id(&h)));
        assert_eq!(got.map(|g| g.0), want.map(|w| w.0), "ray {i}: committed t");
    }
}

/// Axis-aligned rays (zero and negative-zero direction components) through the exact grid
/// vertices and edges of a terrain, and rays along its grid lines: these lie exactly in the
/// face planes of node boxes (0 x inf = NaN in a slab test).
#[test]
fn axis_aligned_rays_in_box_planes() {
    let terr = scene::terrain(32);
    let data = TriData::from_mesh(&terr, GEOMETRY_OPAQUE);
    let geoms = [data.geometry()];
    let scene = RefScene::Blas(&geoms);
    let v = glam::Vec3::new;
    let mut rays = Vec::new();
    for i in 0..=64 {
        for j in (0..=64).step_by(4) {
            let (x, z) = (i as f32 / 64.0, j as f32 / 64.0);
            rays.push(Ray { origin: v(x, 1.0, z), direction: v(0.0, -1.0, 0.0), tmin: 0.0, tmax: f32::INFINITY });
            rays.push(Ray { origin: v(x, 1.0, z), direction: v(-0.0, -2.0, 0.0), tmin: 0.0, tmax: f32::INFINITY });
            rays.push(Ray { origin: v(x, -1.0, z), direction: v(0.0, 1.0, -0.0), tmin: 0.0, tmax: f32::INFINITY });
        }
        // Horizontal rays along grid lines at a few heights.
        for y in [-0.05f32, 0.0, 0.03] {
            let c = i as f32 / 64.0;
            rays.push(Ray { origin: v(-1.0, y, c), direction: v(1.0, 0.0, 0.0), tmin: 0.0, tmax: f32::INFINITY });
            rays.push(Ray { origin: v(c, y, 2.0), direction: v(0.0, 0.0, -1.0), tmin: 0.0, tmax: f32::INFINITY });
            rays.push(Ray { origin: v(c, y, 2.0), direction: v(-0.0, -0.0, -1.0), tmin: 0.0, tmax: 1.5 });
        }
    }
    for tier in TIERS {
        let built = build_blas(tier, &geoms);
        let mut hits = 0;
        for (i, ray) in rays.iter().enumerate() {
            hits += compare_ray(&built.bytes, &accel::NoDevice, &scene, ray, 0, 0xFF, EXACT, &format!("axis tier {tier:#x} ray {i} {:?} dir {:?}", ray.origin, ray.direction));
        }
        assert!(hits > rays.len() / 2, "{hits}");
    }
}

/// Empty, inverted and single-point [tmin, tmax] intervals, and tmin/tmax equal to a hit's t:
/// the interval is inclusive on both ends.
#[test]
fn interval_rays_are_inclusive() {
    let m = scene::load(data_path("bunny.ply")).unwrap();
    let data = TriData::from_mesh(&m, GEOMETRY_OPAQUE);
    let geoms = [data.geometry()];
    let scene = RefScene::Blas(&geoms);
    let rays = random_rays(m.bounds(), 600, 4);
    for tier in TIERS {
        let built = build_blas(tier, &geoms);
        let mut pinned = 0;
        for (i, ray) in rays.iter().enumerate() {
            let Some(h) = accel::closest_hit(&built.bytes, &accel::NoDevice, copy_ray(ray), accel::RayFlags(0), 0xFF) else { continue };
            let t = h.t;
            for (tmin, tmax) in [(t, t), (0.0, t), (t, f32::INFINITY), (t + 1e-3, t - 1e-3), (0.0, 0.0), (f32::INFINITY, f32::INFINITY)] {
                let r = Ray { tmin, tmax, ..copy_ray(ray) };
                let n = compare_ray(&built.bytes, &accel::NoDevice, &scene, &r, 0, 0xFF, EXACT, &format!("tier {tier:#x} interval [{tmin}, {tmax}] ray {i}"));
                if tmin == t && tmax >= t {
                    assert!(n > 0, "ray {i}: hit at t = tmin = {t} not reported (interval is inclusive)");
                    pinned += 1;
                }
                if tmin == 0.0 && tmax == t {
                    assert!(n > 0, "ray {i}: hit at t = tmax = {t} not reported (interval is inclusive)");
                }
            }
        }
        assert!(pinned > 200, "{pinned}");
    }
}

/// TLAS update: new transforms, masks, flags, custom indices (instance definitions may change),
/// same active set; and a BLAS of AABBs refitted to moved boxes. Brute-force equal afterwards.
#[test]
fn tlas_and_aabb_refit_match_brute_force() {
    let f = tlas_fixture(50, 41, FAST_TRACE);
    let geoms = geoms_of(&f);
    let blases: HashMap<u64, &[Geometry]> = geoms.iter().map(|(a, g)| (*a, g.as_slice())).collect();
    let flags = FAST_TRACE | BuildFlags::ALLOW_UPDATE;
    let packed = InstanceRecord::pack(&f.instances);
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: f.instances.len() as u32, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
    let mut tlas = build(AsType::TopLevel, flags, &g, &f.view);
    // Move every active instance: new rotation/translation from another seed; shuffle masks/flags.
    let refs: Vec<u64> = f.blas_geoms.iter().map(|b| b.0).collect();
    let fresh = scene::instance_records(f.instances.len(), &refs, 4242);
    let mut rng = Rng::new(8);
    let combos = all_instance_flag_combinations();
    let moved: Vec<InstanceRecord> = f
        .instances
        .iter()
        .zip(&fresh)
        .map(|(old, new)| InstanceRecord {
            transform: new.transform,
            mask: [0xFF, 0x01, 0x0F][rng.below(3) as usize],
            flags: combos[rng.below(combos.len() as u32) as usize],
            custom_index: rng.next_u32() & 0xFF_FFFF,
            ..*old
        })
        .collect();
    let mpacked = InstanceRecord::pack(&moved);
    let mg = [Geometry { flags: GeometryFlags(0), primitive_count: moved.len() as u32, data: GeometryData::Instances { array_of_pointers: false, data: &mpacked } }];
    let desc = accel::BuildDesc { ty: AsType::TopLevel, flags: BuildFlags(flags), geometries: &mg };
    let mut scratch = vec![0u8; tlas.sizes.update_scratch_size as usize];
    accel::update(&desc, &f.view, None, &mut tlas.bytes, &mut scratch).expect("TLAS update");
    accel::validate(&tlas.bytes).expect("validate after TLAS update");
    let scene = RefScene::Tlas { instances: moved.clone(), blases };
    let mut corners = Vec::new();
    for r in &moved {
        corners.push([r.transform[3], r.transform[7], r.transform[11]]);
    }
    let b = union_bounds(corners);
    let bounds = [b[0] - 2.0, b[1] - 2.0, b[2] - 2.0, b[3] + 2.0, b[4] + 2.0, b[5] + 2.0];
    let mut hits = 0;
    for (i, ray) in random_rays(bounds, 400, 3).iter().enumerate() {
        hits += compare_ray(&tlas.bytes, &f.view, &scene, ray, 0, 0xFF, TLAS_TOL, &format!("refit TLAS ray {i}"));
    }
    assert!(hits > 100, "{hits}");
    // Making an active instance inactive is an update rule violation.
    let mut bad = moved.clone();
    let k = bad.iter().position(|r| r.reference != 0).unwrap();
    bad[k].reference = 0;
    let bpacked = InstanceRecord::pack(&bad);
    let bg = [Geometry { flags: GeometryFlags(0), primitive_count: bad.len() as u32, data: GeometryData::Instances { array_of_pointers: false, data: &bpacked } }];
    let bdesc = accel::BuildDesc { ty: AsType::TopLevel, flags: BuildFlags(flags), geometries: &bg };
    let mut copy = tlas.bytes.clone();
    assert!(accel::update(&bdesc, &f.view, None, &mut copy, &mut scratch).is_err(), "TLAS update making an instance inactive accepted");

    // AABB BLAS refit.
    let boxes = boxes_of(&scene::random_soup(2000, 5));
    let a = AabbData::new(&boxes, 32, 0);
    let ag = [a.geometry()];
    let mut built = build_blas(flags, &ag);
    let moved_boxes: Vec<[f32; 6]> = boxes.iter().map(|b| [b[0] * 2.0, b[1] + b[0], b[2], b[3] * 2.0, b[4] + b[3], b[5] + 0.1]).collect();
    let ma = AabbData::new(&moved_boxes, 32, 0);
    let mag = [ma.geometry()];
    let mdesc = accel::BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &mag };
    let mut scratch = vec![0u8; built.sizes.update_scratch_size as usize];
    accel::update(&mdesc, &accel::NoDevice, None, &mut built.bytes, &mut scratch).expect("AABB update");
    let scene = RefScene::Blas(&mag);
    for (i, ray) in random_rays([0.0, 0.0, 0.0, 2.0, 2.0, 1.1], 300, 9).iter().enumerate() {
        compare_ray(&built.bytes, &accel::NoDevice, &scene, ray, 0, 0xFF, EXACT, &format!("refit AABB ray {i}"));
    }
}

/// AABB candidates through the RayQuery protocol: generate_intersection commits at the given t
/// only within [tmin, current tmax]; terminate() ends the query keeping the committed hit.
#[test]
fn ray_query_aabb_generate_intersection_and_terminate() {
    let boxes = boxes_of(&scene::random_soup(800, 61));
    let a = AabbData::new(&boxes, 24, 0);
    let geoms = [a.geometry()];
    let scene = RefScene::Blas(&geoms);
    let built = build_blas(FAST_TRACE, &geoms);
    let rays = random_rays([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 300, 62);
    let mut checked = 0;
    for (i, ray) in rays.iter().enumerate() {
        let r = reference(&scene, ray, 0, 0xFF);
        // Commit each candidate at the midpoint of its (reference) entry t and tmax cap 2.0:
        // t_commit = entry + 0.5 (farther than the entry, so order matters).
        let mut q = accel::RayQuery::new(&built.bytes, &accel::NoDevice, copy_ray(ray), accel::RayFlags(0), 0xFF);
        let mut want: Option<f32> = None;
        let mut seen = 0;
        while let Some(c) = q.proceed() {
            assert!(matches!(c.kind, accel::HitKind::Aabb));
            let id = hit_id(&c);
            let rh = r.hits.iter().find(|h| h.id == id);
            assert!(rh.is_some() || EXACT.near_miss(&r, id), "ray {i}: candidate {id:?} not a reference box");
            seen += 1;
            let tc = ray.tmin + (id.primitive % 7) as f32 * 0.1;
            // Valid only within [tmin, committed t].
            let limit = q.committed().map_or(ray.tmax, |h| h.t);
            q.generate_intersection(tc);
            if tc >= ray.tmin && tc <= limit {
                want = Some(want.map_or(tc, |w: f32| w.min(tc)));
            }
            // Outside the interval: ignored.
            q.generate_intersection(ray.tmin - 1.0);
        }
        assert_eq!(q.committed().map(|h| h.t), want, "ray {i}: committed t after generate_intersection");
        if seen > 1 {
            checked += 1;
            // terminate() after the first candidate: that one stays committed, nothing else comes.
            let mut q = accel::RayQuery::new(&built.bytes, &accel::NoDevice, copy_ray(ray), accel::RayFlags(0), 0xFF);
            let first = q.proceed().unwrap();
            q.generate_intersection(ray.tmin);
            q.terminate();
            assert!(q.proceed().is_none(), "ray {i}: candidates after terminate()");
            let c = q.committed().expect("committed before terminate");
            assert_eq!((c.t, hit_id(&c)), (ray.tmin, hit_id(&first)));
        }
    }
    assert!(checked > 30, "{checked}");
}

/// Grid-aligned AABB primitives (touching voxels) and instances with identity/axis-permuting
/// transforms at integer offsets, hit by axis-aligned rays along the lattice planes.
#[test]
fn axis_aligned_rays_on_voxel_aabbs_and_instances() {
    let mut boxes = Vec::new();
    for x in 0..6 {
        for y in 0..6 {
            for z in 0..6 {
                if (x + 2 * y + 3 * z) % 4 != 0 {
                    let (x, y, z) = (x as f32 * 0.25, y as f32 * 0.25, z as f32 * 0.25);
                    boxes.push([x, y, z, x + 0.25, y + 0.25, z + 0.25]);
                }
            }
        }
    }
    let a = AabbData::new(&boxes, 24, 0);
    let geoms = [a.geometry()];
    let scene = RefScene::Blas(&geoms);
    let v = glam::Vec3::new;
    let mut rays = Vec::new();
    for i in 0..=12 {
        for j in 0..=12 {
            let (p, q) = (i as f32 * 0.125, j as f32 * 0.125);
            rays.push(Ray { origin: v(p, q, -1.0), direction: v(0.0, 0.0, 1.0), tmin: 0.0, tmax: f32::INFINITY });
            rays.push(Ray { origin: v(-1.0, p, q), direction: v(1.0, -0.0, 0.0), tmin: 0.0, tmax: f32::INFINITY });
            rays.push(Ray { origin: v(p, 3.0, q), direction: v(0.0, -1.0, 0.0), tmin: 0.5, tmax: 3.5 });
        }
    }
    for tier in TIERS {
        let built = build_blas(tier, &geoms);
        let mut hits = 0;
        for (i, ray) in rays.iter().enumerate() {
            hits += compare_ray(&built.bytes, &accel::NoDevice, &scene, ray, 0, 0xFF, EXACT, &format!("voxel tier {tier:#x} ray {i} {:?} {:?}", ray.origin, ray.direction));
        }
        assert!(hits > rays.len(), "{hits}");
    }
    // Instances of a unit-grid terrain at integer offsets, axis-permuting transforms.
    let terr = TriData::from_mesh(&scene::terrain(8), GEOMETRY_OPAQUE);
    let tg = [terr.geometry()];
    let blas = build_blas(FAST_TRACE, &tg);
    let mut view = MapView::new();
    view.insert(BLAS_BASE, blas.bytes);
    let perms: [[f32; 9]; 3] = [[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0]];
    let mut insts = Vec::new();
    for k in 0..27u32 {
        let m = perms[(k % 3) as usize];
        let t = [(k % 3) as f32, ((k / 3) % 3) as f32, (k / 9) as f32];
        insts.push(InstanceRecord {
            transform: [m[0], m[1], m[2], t[0], m[3], m[4], m[5], t[1], m[6], m[7], m[8], t[2]],
            custom_index: k,
            mask: 0xFF,
            sbt_offset: 0,
            flags: 0,
            reference: BLAS_BASE,
        });
    }
    let packed = InstanceRecord::pack(&insts);
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: 27, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
    let tlas = build(AsType::TopLevel, FAST_TRACE, &g, &view);
    let blases: HashMap<u64, &[Geometry]> = [(BLAS_BASE, &tg[..])].into_iter().collect();
    let scene = RefScene::Tlas { instances: insts, blases };
    let mut rays = Vec::new();
    for i in 0..=24 {
        for j in 0..=24 {
            let (p, q) = (i as f32 * 0.125, j as f32 * 0.125);
            rays.push(Ray { origin: v(p, q, -1.0), direction: v(0.0, 0.0, 1.0), tmin: 0.0, tmax: f32::INFINITY });
            rays.push(Ray { origin: v(-1.0, p, q), direction: v(1.0, 0.0, 0.0), tmin: 0.0, tmax: f32::INFINITY });
            rays.push(Ray { origin: v(p, 4.0, q), direction: v(0.0, -1.0, 0.0), tmin: 0.0, tmax: f32::INFINITY });
        }
    }
    let mut hits = 0;
    for (i, ray) in rays.iter().enumerate() {
        hits += compare_ray(&tlas.bytes, &view, &scene, ray, 0, 0xFF, EXACT, &format!("grid TLAS ray {i} {:?} {:?}", ray.origin, ray.direction));
    }
    assert!(hits > rays.len() / 2, "{hits}");
}

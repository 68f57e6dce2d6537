//! Inputs of every kind: vertex formats and their decoding, indices and transforms, AABBs,
//! degenerate, hostile and huge inputs, typed errors; traversal against brute force.
use super::*;

#[test]
fn half_and_norm_decode() {
    use super::input::half_to_f32;
    assert_eq!(half_to_f32(0x3c00), 1.0);
    assert_eq!(half_to_f32(0xc000), -2.0);
    assert_eq!(half_to_f32(0x0001), 5.960_464_5e-8);
    assert!(half_to_f32(0x7e00).is_nan());
    assert_eq!(half_to_f32(0x7c00), f32::INFINITY);
    assert_eq!(half_to_f32(0x7bff), 65504.0);
    let d = |f: VertexFormat, b: &[u8]| super::input::decode_vertex(f, b).unwrap();
    assert_eq!(d(VertexFormat::R16G16Snorm, &[0xff, 0x7f, 0x00, 0x80]), Vec3::new(1.0, -1.0, 0.0));
    assert_eq!(d(VertexFormat::R8G8B8A8Snorm, &[0x7f, 0x81, 0x80, 0x00]), Vec3::new(1.0, -1.0, -1.0));
    assert_eq!(d(VertexFormat::R8G8Unorm, &[255, 0]), Vec3::new(1.0, 0.0, 0.0));
    assert_eq!(d(VertexFormat::R16G16B16A16Unorm, &[0xff, 0xff, 0, 0, 0xff, 0xff, 9, 9]), Vec3::new(1.0, 0.0, 1.0));
    let w: u32 = 1023 | (1023 << 20) | (3 << 30); // G = 0
    assert_eq!(d(VertexFormat::A2B10G10R10UnormPack32, &w.to_le_bytes()), Vec3::new(1.0, 0.0, 1.0));
    assert_eq!(d(VertexFormat::R16G16B16A16Sfloat, &[0, 0x3c, 0, 0xc0, 0, 0x38, 0xff, 0xff]), Vec3::new(1.0, -2.0, 0.5));
    for f in VertexFormat::all() {
        assert_eq!(VertexFormat::from_vk(f.to_vk()), Some(*f));
        assert!(super::input::decode_vertex(*f, &vec![0u8; f.size() as usize]).is_some());
        assert!(f.size() % f.component_size() == 0);
    }
    assert_eq!(IndexType::from_vk(1000165000), Some(IndexType::None));
}

#[test]
fn every_format_builds_and_hits() {
    // One triangle in the z = 0.5 plane (z = 0 for 2-component formats) in every format.
    for &f in VertexFormat::all() {
        let comps: [[f32; 3]; 3] = [[0.0, 0.0, 0.5], [1.0, 0.0, 0.5], [0.0, 1.0, 0.5]];
        let mut bytes = Vec::new();
        for c in comps {
            let mut vb = vec![0u8; f.size() as usize];
            let n = f.size() / f.component_size();
            for k in 0..(n as usize).min(3) {
                let x = c[k];
                match f {
                    VertexFormat::R32G32Sfloat | VertexFormat::R32G32B32Sfloat | VertexFormat::R32G32B32A32Sfloat => vb[4 * k..4 * k + 4].copy_from_slice(&x.to_le_bytes()),
                    VertexFormat::R16G16Sfloat | VertexFormat::R16G16B16Sfloat | VertexFormat::R16G16B16A16Sfloat => {
                        let h: u16 = if x == 1.0 { 0x3c00 } else if x == 0.5 { 0x3800 } else { 0 };
                        vb[2 * k..2 * k + 2].copy_from_slice(&h.to_le_bytes())
                    }
                    VertexFormat::R16G16Snorm | VertexFormat::R16G16B16A16Snorm => vb[2 * k..2 * k + 2].copy_from_slice(&((x * 32767.0) as i16).to_le_bytes()),
                    VertexFormat::R16G16Unorm | VertexFormat::R16G16B16A16Unorm => vb[2 * k..2 * k + 2].copy_from_slice(&((x * 65535.0) as u16).to_le_bytes()),
                    VertexFormat::R8G8Snorm | VertexFormat::R8G8B8A8Snorm => vb[k] = (x * 127.0) as i8 as u8,
                    VertexFormat::R8G8Unorm | VertexFormat::R8G8B8A8Unorm => vb[k] = (x * 255.0) as u8,
                    VertexFormat::A2B10G10R10UnormPack32 => {}
                }
            }
            if f == VertexFormat::A2B10G10R10UnormPack32 {
                let q = |x: f32| (x * 1023.0).round() as u32;
                let w = q(c[0]) | q(c[1]) << 10 | q(c[2]) << 20;
                vb.copy_from_slice(&w.to_le_bytes());
            }
            bytes.extend(vb);
        }
        let g = Geometry {
            flags: GeometryFlags(1),
            primitive_count: 1,
            data: GeometryData::Triangles { format: f, vertices: &bytes, stride: f.size() as u64, max_vertex: 2, index_type: IndexType::None, indices: &[], transform: None },
        };
        let tri = fetch_triangle(&g, 0).unwrap();
        assert!((tri[1].x - 1.0).abs() < 1e-2 && (tri[2].y - 1.0).abs() < 1e-2, "{f:?} {tri:?}");
        let blas = build_ok(AsType::BottomLevel, 0, &[g], &NoDevice);
        let ray = Ray { origin: Vec3::new(0.25, 0.25, -1.0), direction: Vec3::Z, tmin: 0.0, tmax: 10.0 };
        let h = closest_hit(&blas, &NoDevice, ray, RayFlags(0), 0xff).unwrap_or_else(|| panic!("{f:?}"));
        assert!((h.t - (1.0 + tri[0].z)).abs() < 1e-2);
    }
}

#[test]
fn facing_matches_normal_rule() {
    let mut rng = Rng::new(7);
    let mut checked = 0;
    for _ in 0..5000 {
        let (a, b, c) = (rng.v3(1.0), rng.v3(1.0), rng.v3(1.0));
        let ray = Ray { origin: rng.v3(3.0), direction: rng.v3(1.0), tmin: 0.0, tmax: f32::INFINITY };
        let ray = Ray { direction: (a + b + c) / 3.0 - ray.origin, ..ray };
        if let Some((t, u, v, front)) = intersect_triangle(&ray, a, b, c) {
            let n = (b - a).cross(c - a);
            assert_eq!(front, n.dot(ray.direction) < 0.0);
            assert!(u >= 0.0 && v >= 0.0 && u + v <= 1.0 + 1e-5);
            let p = ray.origin + ray.direction * t;
            let q = a * (1.0 - u - v) + b * u + c * v;
            assert!((p - q).length() < 1e-3);
            checked += 1;
        }
    }
    assert!(checked > 4000);
    // The documented example: v0 (0,0), v1 (0,1), v2 (1,0) seen along +z is front-facing.
    let ray = Ray { origin: Vec3::new(0.2, 0.2, 0.0), direction: Vec3::Z, tmin: 0.0, tmax: 5.0 };
    assert!(intersect_triangle(&ray, Vec3::new(0.0, 0.0, 1.0), Vec3::new(0.0, 1.0, 1.0), Vec3::new(1.0, 0.0, 1.0)).unwrap().3);
}

#[test]
fn watertight_shared_edge() {
    // Rays through a shared edge must hit at least one of the two triangles.
    let a = Vec3::new(-1.0, -1.0, 1.0);
    let b = Vec3::new(1.0, 1.0, 1.0);
    let c = Vec3::new(1.0, -1.0, 1.0);
    let d = Vec3::new(-1.0, 1.0, 1.0);
    let mut rng = Rng::new(3);
    for _ in 0..2000 {
        let s = rng.range(-0.99, 0.99);
        let p = Vec3::new(s, s, 1.0);
        let o = rng.v3(0.5) - Vec3::Z * 2.0;
        let ray = Ray { origin: o, direction: p - o, tmin: 0.0, tmax: f32::INFINITY };
        let h1 = intersect_triangle(&ray, a, b, c);
        let h2 = intersect_triangle(&ray, a, d, b);
        assert!(h1.is_some() || h2.is_some());
    }
}

#[test]
fn random_soup_matches_brute_force() {
    for &flags in &[BuildFlags::PREFER_FAST_BUILD, 0, BuildFlags::PREFER_FAST_TRACE, BuildFlags::ALLOW_UPDATE] {
        let mut rng = Rng::new(11 + flags as u64);
        let v = random_soup(&mut rng, 3000, 10.0, 0.8);
        let vb = f32_bytes(&v);
        let g = tri_geom(&vb, v.len() as u32, &[], 3000, GeometryFlags::OPAQUE);
        let blas = build_ok(AsType::BottomLevel, flags, &[g], &NoDevice);
        let m = metrics(&blas).unwrap();
        assert!(m.sah_cost > 1.0 && m.wide_sah_cost > 0.0, "{m:?}");
        for k in 0..600 {
            let ray = random_ray(&mut rng, 10.0);
            let rf = [0, RayFlags::CULL_BACK_FACING_TRIANGLES, RayFlags::CULL_FRONT_FACING_TRIANGLES][k % 3];
            let h = closest_hit(&blas, &NoDevice, ray, RayFlags(rf), 0xff);
            let b = brute_closest(&v, &ray, rf);
            assert_eq!(h.map(|h| h.t), b.map(|b| b.0), "ray {ray:?}");
            if let (Some(h), Some(b)) = (h, b) {
                // Ties in t may pick either primitive; the t must match exactly.
                if v[3 * b.1 as usize] != v[3 * h.primitive_index as usize] {
                    let tri = &v[3 * h.primitive_index as usize..3 * h.primitive_index as usize + 3];
                    assert_eq!(intersect_triangle(&ray, tri[0], tri[1], tri[2]).unwrap().0, h.t);
                }
            }
            // all_hits equals the brute-force set.
            let mut all: Vec<u32> = all_hits(&blas, &NoDevice, ray, RayFlags(rf), 0xff).iter().map(|h| h.primitive_index).collect();
            all.sort_unstable();
            let mut bf: Vec<u32> = v
                .chunks_exact(3)
                .enumerate()
                .filter_map(|(i, t)| {
                    let (_, _, _, front) = intersect_triangle(&ray, t[0], t[1], t[2])?;
                    let culled = (rf & RayFlags::CULL_BACK_FACING_TRIANGLES != 0 && !front) || (rf & RayFlags::CULL_FRONT_FACING_TRIANGLES != 0 && front);
                    (!culled).then_some(i as u32)
                })
                .collect();
            bf.sort_unstable();
            assert_eq!(all, bf);
            assert_eq!(any_hit(&blas, &NoDevice, ray, RayFlags(rf), 0xff).is_some(), b.is_some());
        }
    }
}

#[test]
fn indexed_multi_geometry_transform_and_ids() {
    // Two geometries, indexed U16 and U32, one with a transform, with inactive triangles.
    let verts = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0), Vec3::new(f32::NAN, 0.0, 0.0)];
    let vb = f32_bytes(&verts);
    let idx16: Vec<u8> = [3u16, 1, 2, 0, 1, 2].iter().flat_map(|x| x.to_le_bytes()).collect();
    let idx32 = u32_bytes(&[0, 1, 2]);
    let tf = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 5.0];
    let g0 = Geometry {
        flags: GeometryFlags(1),
        primitive_count: 2,
        data: GeometryData::Triangles { format: VertexFormat::R32G32B32Sfloat, vertices: &vb, stride: 12, max_vertex: 3, index_type: IndexType::U16, indices: &idx16, transform: None },
    };
    let g1 = Geometry {
        flags: GeometryFlags(1),
        primitive_count: 1,
        data: GeometryData::Triangles { format: VertexFormat::R32G32B32Sfloat, vertices: &vb, stride: 12, max_vertex: 3, index_type: IndexType::U32, indices: &idx32, transform: Some(tf) },
    };
    assert!(fetch_triangle(&g0, 0).is_none());
    let blas = build_ok(AsType::BottomLevel, 0, &[g0, g1], &NoDevice);
    let h = header(&blas).unwrap();
    assert_eq!(h.primitive_count, 2);
    let ray = Ray { origin: Vec3::new(0.2, 0.2, -1.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 };
    let hit = closest_hit(&blas, &NoDevice, ray, RayFlags(0), 0xff).unwrap();
    assert_eq!((hit.geometry_index, hit.primitive_index, hit.t), (0, 1, 1.0));
    let ray2 = Ray { tmin: 2.0, ..ray };
    let hit = closest_hit(&blas, &NoDevice, ray2, RayFlags(0), 0xff).unwrap();
    assert_eq!((hit.geometry_index, hit.primitive_index, hit.t), (1, 0, 6.0));
    // tmin/tmax inclusive.
    let exact = Ray { tmin: 6.0, tmax: 6.0, ..ray };
    assert_eq!(closest_hit(&blas, &NoDevice, exact, RayFlags(0), 0xff).unwrap().t, 6.0);
}

#[test]
fn typed_errors_not_panics() {
    let verts = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let vb = f32_bytes(&verts);
    let bad_idx = u32_bytes(&[0, 1, 7]);
    let g = tri_geom(&vb, 3, &bad_idx, 1, 0);
    assert_eq!(try_build(AsType::BottomLevel, 0, &[g], &NoDevice).0, Err(BuildError::IndexOutOfRange { geometry: 0, primitive: 0, index: 7 }));
    let short_idx = u32_bytes(&[0, 1]);
    let g = tri_geom(&vb, 3, &short_idx, 1, 0);
    assert_eq!(try_build(AsType::BottomLevel, 0, &[g], &NoDevice).0, Err(BuildError::InputTooShort { geometry: 0 }));
    let g = tri_geom(&vb[..30], 3, &[], 1, 0);
    assert_eq!(try_build(AsType::BottomLevel, 0, &[g], &NoDevice).0, Err(BuildError::InputTooShort { geometry: 0 }));
    let aabb = Geometry { flags: GeometryFlags(0), primitive_count: 2, data: GeometryData::Aabbs { data: &[0u8; 40], stride: 24 } };
    assert_eq!(try_build(AsType::BottomLevel, 0, &[aabb], &NoDevice).0, Err(BuildError::InputTooShort { geometry: 0 }));
    let inst = Geometry { flags: GeometryFlags(0), primitive_count: 1, data: GeometryData::Instances { array_of_pointers: true, data: &[1u8; 8] } };
    assert_eq!(try_build(AsType::TopLevel, 0, &[inst], &NoDevice).0, Err(BuildError::InvalidAddress { geometry: 0, primitive: 0 }));
    // Too small destination/scratch: typed errors, dst marked invalid.
    let g = tri_geom(&vb, 3, &[], 1, 0);
    let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(0), geometries: &[g] };
    let mut dst = vec![0u8; 100];
    assert!(matches!(build(&desc, &NoDevice, &mut dst, &mut vec![0u8; 4096]), Err(BuildError::DestinationTooSmall { .. })));
    let mut dst = vec![0u8; 4096];
    assert!(matches!(build(&desc, &NoDevice, &mut dst, &mut [0u8; 8]), Err(BuildError::ScratchTooSmall { .. })));
    assert!(header(&dst).is_none());
    // Geometry type mismatch.
    assert!(matches!(try_build(AsType::TopLevel, 0, &[g], &NoDevice).0, Err(BuildError::WrongGeometryType { .. })));
}

#[test]
fn sizes_do_not_overflow() {
    let s = build_sizes(AsType::BottomLevel, BuildFlags(0), &[GeometryShape::Aabbs; 3], &[u32::MAX; 3]);
    assert!(s.acceleration_structure_size > 3 * u32::MAX as u64 * 36);
    let s = build_sizes(AsType::TopLevel, BuildFlags(0), &[GeometryShape::Instances], &[u32::MAX]);
    assert!(s.acceleration_structure_size > u32::MAX as u64 * 120 && s.build_scratch_size < u64::MAX);
    let z = build_sizes(AsType::BottomLevel, BuildFlags(0), &[], &[]);
    assert!(z.acceleration_structure_size >= 144);
}

#[test]
fn degenerate_inputs() {
    // Empty.
    let g = tri_geom(&[], 0, &[], 0, 0);
    let blas = build_ok(AsType::BottomLevel, 0, &[g], &NoDevice);
    let ray = Ray { origin: Vec3::ZERO, direction: Vec3::X, tmin: 0.0, tmax: 1.0 };
    assert!(closest_hit(&blas, &NoDevice, ray, RayFlags(0), 0xff).is_none());
    assert!(!build_ok(AsType::BottomLevel, 0, &[], &NoDevice).is_empty());
    // One triangle.
    let vb = f32_bytes(&[Vec3::new(0.0, 0.0, 1.0), Vec3::new(1.0, 0.0, 1.0), Vec3::new(0.0, 1.0, 1.0)]);
    let g = tri_geom(&vb, 3, &[], 1, 0);
    let blas = build_ok(AsType::BottomLevel, 0, &[g], &NoDevice);
    let ray = Ray { origin: Vec3::new(0.1, 0.1, 0.0), direction: Vec3::Z, tmin: 0.0, tmax: 10.0 };
    assert_eq!(closest_hit(&blas, &NoDevice, ray, RayFlags(0), 0xff).unwrap().t, 1.0);
    // 5000 identical triangles (kept with ALLOW_UPDATE), and 5000 points (dropped without).
    let same: Vec<Vec3> = (0..5000).flat_map(|_| [Vec3::new(0.0, 0.0, 1.0), Vec3::new(1.0, 0.0, 1.0), Vec3::new(0.0, 1.0, 1.0)]).collect();
    let sb = f32_bytes(&same);
    let g = tri_geom(&sb, 15000, &[], 5000, 0);
    let blas = build_ok(AsType::BottomLevel, BuildFlags::ALLOW_UPDATE, &[g], &NoDevice);
    assert_eq!(all_hits(&blas, &NoDevice, ray, RayFlags(0), 0xff).len(), 5000);
    let points = f32_bytes(&vec![Vec3::splat(2.0); 15000]);
    let g = tri_geom(&points, 15000, &[], 5000, 0);
    let blas = build_ok(AsType::BottomLevel, 0, &[g], &NoDevice);
    assert_eq!(header(&blas).unwrap().primitive_count, 0);
    let blas = build_ok(AsType::BottomLevel, BuildFlags::ALLOW_UPDATE, &[g], &NoDevice);
    assert_eq!(header(&blas).unwrap().primitive_count, 5000);
    // NaN/Inf/huge/tiny coordinates mixed with normal ones.
    let mut rng = Rng::new(9);
    let mut v = random_soup(&mut rng, 2000, 1.0, 0.1);
    v[0] = Vec3::new(f32::INFINITY, 0.0, 0.0);
    v[4] = Vec3::new(0.0, f32::NAN, 0.0);
    v[7] = Vec3::new(f32::MAX, -f32::MAX, 1e38);
    v[9] = Vec3::new(1e-40, -1e-42, 1e-45);
    v[10] = Vec3::new(-f32::INFINITY, f32::INFINITY, 0.0);
    v[13] = Vec3::new(f32::NAN, 0.0, 0.0);
    let vb = f32_bytes(&v);
    for flags in [0, BuildFlags::ALLOW_UPDATE, BuildFlags::PREFER_FAST_TRACE] {
        let g = tri_geom(&vb, v.len() as u32, &[], 2000, 0);
        let blas = build_ok(AsType::BottomLevel, flags, &[g], &NoDevice);
        for _ in 0..200 {
            let ray = random_ray(&mut rng, 1.0);
            let h = closest_hit(&blas, &NoDevice, ray, RayFlags(0), 0xff);
            let b = brute_closest(&v[15..], &ray, 0).map(|x| x.0);
            if let (Some(h), Some(b)) = (h, b) {
                assert!(h.t <= b);
            } else if b.is_some() {
                panic!("missed a hit");
            }
        }
    }
    // Huge coordinates only.
    let v: Vec<Vec3> = random_soup(&mut rng, 500, 1e37, 1e36);
    let vb = f32_bytes(&v);
    let g = tri_geom(&vb, v.len() as u32, &[], 500, 0);
    build_ok(AsType::BottomLevel, 0, &[g], &NoDevice);
    // Tiny coordinates only.
    let v: Vec<Vec3> = random_soup(&mut rng, 500, 1e-30, 1e-31);
    let vb = f32_bytes(&v);
    let g = tri_geom(&vb, v.len() as u32, &[], 500, 0);
    let blas = build_ok(AsType::BottomLevel, 0, &[g], &NoDevice);
    for _ in 0..100 {
        let ray = random_ray(&mut rng, 1e-30);
        assert_eq!(closest_hit(&blas, &NoDevice, ray, RayFlags(0), 0xff).map(|h| h.t), brute_closest(&v, &ray, 0).map(|b| b.0));
    }
}

#[test]
fn hostile_rays_and_blobs() {
    let mut rng = Rng::new(1);
    let v = random_soup(&mut rng, 500, 1.0, 0.2);
    let vb = f32_bytes(&v);
    let g = tri_geom(&vb, v.len() as u32, &[], 500, 0);
    let blas = build_ok(AsType::BottomLevel, 0, &[g], &NoDevice);
    let bad = [
        Ray { origin: Vec3::ZERO, direction: Vec3::ZERO, tmin: 0.0, tmax: 1.0 },
        Ray { origin: Vec3::NAN, direction: Vec3::X, tmin: 0.0, tmax: 1.0 },
        Ray { origin: Vec3::ZERO, direction: Vec3::new(f32::NAN, 1.0, 0.0), tmin: 0.0, tmax: 1.0 },
        Ray { origin: Vec3::ZERO, direction: Vec3::X, tmin: 2.0, tmax: 1.0 },
        Ray { origin: Vec3::ZERO, direction: Vec3::new(0.0, 0.0, 1.0), tmin: f32::NAN, tmax: 1.0 },
        Ray { origin: Vec3::splat(f32::INFINITY), direction: Vec3::X, tmin: 0.0, tmax: f32::INFINITY },
    ];
    for r in bad {
        assert!(closest_hit(&blas, &NoDevice, r, RayFlags(0), 0xff).is_none());
        let _ = all_hits(&blas, &NoDevice, r, RayFlags(0), 0xff);
    }
    // Axis-aligned rays (zero direction components) still find hits.
    let r = Ray { origin: Vec3::new(v[0].x * 0.34 + v[1].x * 0.33 + v[2].x * 0.33, v[0].y * 0.34 + v[1].y * 0.33 + v[2].y * 0.33, -5.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 };
    assert_eq!(closest_hit(&blas, &NoDevice, r, RayFlags(0), 0xff).map(|h| h.t), brute_closest(&v, &r, 0).map(|b| b.0));
    // Garbage: random bytes, truncated and bit-flipped structures.
    let ray = Ray { origin: Vec3::new(0.0, 0.0, -5.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 };
    for k in 0..300 {
        let mut g = blas.clone();
        let n = g.len();
        for _ in 0..(1 + k % 16) {
            let i = (rng.next_u32() as usize) % n.min(4096);
            g[i] ^= 1 << (rng.next_u32() % 8);
        }
        let _ = closest_hit(&g, &NoDevice, ray, RayFlags(0), 0xff);
        let _ = validate(&g);
        let _ = metrics(&g);
        let _ = closest_hit(&g[..(rng.next_u32() as usize % n)], &NoDevice, ray, RayFlags(0), 0xff);
        let junk: Vec<u8> = (0..(rng.next_u32() % 512)).map(|_| rng.next_u32() as u8).collect();
        assert!(header(&junk).is_none());
        let _ = closest_hit(&junk, &NoDevice, ray, RayFlags(0), 0xff);
    }
    let mut m = blas.clone();
    mark_invalid(&mut m);
    assert!(header(&m).is_none() && closest_hit(&m, &NoDevice, ray, RayFlags(0), 0xff).is_none());
}

#[test]
fn aabb_blas_matches_brute_force() {
    let mut rng = Rng::new(33);
    let n = 2000;
    let mut data = Vec::new();
    let mut boxes = Vec::new();
    for i in 0..n {
        let c = rng.v3(10.0);
        let e = rng.v3(0.5).abs();
        let b = if i % 97 == 0 { [f32::NAN, 0.0, 0.0, 0.0, 0.0, 0.0] } else { [c.x - e.x, c.y - e.y, c.z - e.z, c.x + e.x, c.y + e.y, c.z + e.z] };
        boxes.push(b);
        for x in b {
            data.extend(x.to_le_bytes());
        }
        data.extend([0u8; 8]); // stride 32
    }
    let g = Geometry { flags: GeometryFlags(0), primitive_count: n, data: GeometryData::Aabbs { data: &data, stride: 32 } };
    let blas = build_ok(AsType::BottomLevel, 0, &[g], &NoDevice);
    for _ in 0..300 {
        let ray = random_ray(&mut rng, 10.0);
        let mut got: Vec<u32> = all_hits(&blas, &NoDevice, ray, RayFlags(0), 0xff).iter().map(|h| h.primitive_index).collect();
        got.sort_unstable();
        let mut want: Vec<u32> = Vec::new();
        for (i, b) in boxes.iter().enumerate() {
            if b[0].is_nan() {
                continue;
            }
            let mut tn = ray.tmin as f64;
            let mut tf = ray.tmax as f64;
            for a in 0..3 {
                let (o, d) = (ray.origin[a] as f64, ray.direction[a] as f64);
                let t0 = (b[a] as f64 - o) / d;
                let t1 = (b[a + 3] as f64 - o) / d;
                tn = tn.max(t0.min(t1));
                tf = tf.min(t0.max(t1));
            }
            if tn <= tf {
                want.push(i as u32);
            }
        }
        assert_eq!(got, want);
    }
}

#[test]
fn axis_rays_on_box_planes() {
    // A 4x4 grid of quads in y = 0; axis rays whose origin lies exactly on node box planes
    // (x or z = 0 or 1) with zero direction components must still find the hits.
    let mut v = Vec::new();
    for i in 0..4 {
        for j in 0..4 {
            let (x0, z0, x1, z1) = (i as f32 / 4.0, j as f32 / 4.0, (i + 1) as f32 / 4.0, (j + 1) as f32 / 4.0);
            v.extend([Vec3::new(x0, 0.0, z0), Vec3::new(x1, 0.0, z0), Vec3::new(x1, 0.0, z1)]);
            v.extend([Vec3::new(x0, 0.0, z0), Vec3::new(x1, 0.0, z1), Vec3::new(x0, 0.0, z1)]);
        }
    }
    let vb = f32_bytes(&v);
    let g = tri_geom(&vb, v.len() as u32, &[], 32, GeometryFlags::OPAQUE);
    let blas = build_ok(AsType::BottomLevel, 0, &[g], &NoDevice);
    for i in 0..=8 {
        for j in 0..=8 {
            let o = Vec3::new(i as f32 / 8.0, 1.0, j as f32 / 8.0);
            let ray = Ray { origin: o, direction: Vec3::new(0.0, -1.0, -0.0), tmin: 0.0, tmax: f32::INFINITY };
            assert_eq!(closest_hit(&blas, &NoDevice, ray, RayFlags(0), 0xff).map(|h| h.t), brute_closest(&v, &ray, 0).map(|b| b.0), "{o:?}");
        }
    }
}

#[test]
fn dag_blob_terminates() {
    // Forge a structure whose node i has four internal children all pointing at node i+1:
    // without a visit budget a ray would do 4^depth work.
    let mut rng = Rng::new(2);
    let v = random_soup(&mut rng, 3000, 1.0, 0.3);
    let vb = f32_bytes(&v);
    let g = tri_geom(&vb, v.len() as u32, &[], 3000, 0);
    let mut blas = build_ok(AsType::BottomLevel, 0, &[g], &NoDevice);
    let p = layout::parse(&blas).unwrap().raw;
    let nc = p.node_count as usize;
    for i in 0..nc - 1 {
        let off = p.nodes_offset as usize + i * layout::NODE_SIZE;
        let mut n: layout::WideNode = bytemuck::pod_read_unaligned(&blas[off..off + layout::NODE_SIZE]);
        n.child_count = 4;
        n.child = [i as u32 + 1; 4];
        n.kind = [layout::CHILD_INTERNAL; 4];
        n.qlo = [[0; 4]; 3];
        n.qhi = [[255; 4]; 3];
        blas[off..off + layout::NODE_SIZE].copy_from_slice(bytemuck::bytes_of(&n));
    }
    let ray = Ray { origin: Vec3::new(0.0, 0.0, -5.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 };
    let t = std::time::Instant::now();
    let _ = closest_hit(&blas, &NoDevice, ray, RayFlags(0), 0xff);
    let _ = all_hits(&blas, &NoDevice, ray, RayFlags(0), 0xff);
    assert!(validate(&blas).is_err());
    assert!(t.elapsed().as_secs() < 5);
}

/// A triangle whose X coordinates are numbers but whose Y or Z is NaN is not inactive (only a
/// NaN X is); its box is the huge sanitised one, on every input path (plain f32 indexed input
/// takes the fast ingest), so the structure's bounds cover everything.
#[test]
fn nan_y_or_z_gets_the_huge_box() {
    for bad in [Vec3::new(1.0, f32::NAN, 0.0), Vec3::new(1.0, 0.0, f32::NAN)] {
        let v = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(2.0, 0.0, 0.0), Vec3::new(2.0, 1.0, 0.0), bad];
        let vb = f32_bytes(&v);
        // The bad vertex (5) first, second and third in the second triangle.
        for tri in [[5u32, 3, 4], [3, 5, 4], [3, 4, 5]] {
            let ib: Vec<u8> = [0u32, 1, 2].iter().chain(tri.iter()).flat_map(|i| i.to_le_bytes()).collect();
            let g = tri_geom(&vb, 6, &ib, 2, GeometryFlags::OPAQUE);
            for flags in [0, BuildFlags::PREFER_FAST_BUILD, BuildFlags::ALLOW_UPDATE] {
                let blas = build_ok(AsType::BottomLevel, flags, &[g], &NoDevice);
                let h = header(&blas).unwrap();
                assert_eq!(h.primitive_count, 2, "flags {flags}");
                assert_eq!(h.bounds, [-f32::MAX, -f32::MAX, -f32::MAX, f32::MAX, f32::MAX, f32::MAX], "flags {flags}, bad vertex {bad:?} in {tri:?}");
            }
        }
    }
}

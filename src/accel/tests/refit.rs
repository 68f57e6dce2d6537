//! Updates (refit): against rebuilds, the update rules, determinism, mixed geometry, TLAS.
use super::*;

#[test]
fn refit_matches_rebuild_and_checks_rules() {
    let mut rng = Rng::new(21);
    let n = 5000;
    let mut v = random_soup(&mut rng, n, 10.0, 0.5);
    let idx: Vec<u32> = (0..3 * n as u32).collect();
    let ib = u32_bytes(&idx);
    let vb = f32_bytes(&v);
    let flags = BuildFlags::ALLOW_UPDATE;
    let g = tri_geom(&vb, v.len() as u32, &ib, n as u32, 0);
    let blas = build_ok(AsType::BottomLevel, flags, &[g], &NoDevice);
    // Deform.
    for p in v.iter_mut() {
        *p = *p * 1.3 + Vec3::new(p.y.sin(), p.z.cos(), 0.5);
    }
    let vb2 = f32_bytes(&v);
    let g2 = tri_geom(&vb2, v.len() as u32, &ib, n as u32, 0);
    let sz = build_sizes(AsType::BottomLevel, BuildFlags(flags), &[shape_of(&g2)], &[n as u32]);
    let mut scratch = vec![0u8; sz.update_scratch_size as usize + 1];
    let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &[g2] };
    let mut dst = vec![0u8; blas.len()];
    update(&desc, &NoDevice, Some(&blas), &mut dst, &mut scratch[1..]).unwrap();
    validate(&dst).unwrap();
    let mut inplace = blas.clone();
    update(&desc, &NoDevice, None, &mut inplace, &mut scratch).unwrap();
    assert_eq!(inplace[..header(&dst).unwrap().used_size as usize], dst[..header(&dst).unwrap().used_size as usize]);
    for _ in 0..500 {
        let ray = random_ray(&mut rng, 13.0);
        assert_eq!(closest_hit(&dst, &NoDevice, ray, RayFlags(0), 0xff).map(|h| h.t), brute_closest(&v, &ray, 0).map(|b| b.0));
    }
    // Update from a compacted copy works too.
    let mut compact = vec![0u8; compacted_size(&blas).unwrap() as usize];
    compact_into(&blas, &mut compact).unwrap();
    update(&desc, &NoDevice, None, &mut compact, &mut scratch).unwrap();
    validate(&compact).unwrap();
    // Rule checks.
    let mut ib2 = idx.clone();
    ib2.swap(0, 1);
    let ibb = u32_bytes(&ib2);
    let g3 = tri_geom(&vb2, v.len() as u32, &ibb, n as u32, 0);
    let d3 = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &[g3] };
    assert_eq!(update(&d3, &NoDevice, Some(&blas), &mut dst, &mut scratch), Err(BuildError::UpdateMismatch("index values differ")));
    let g4 = tri_geom(&vb2, v.len() as u32, &ib, n as u32 - 1, 0);
    let d4 = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &[g4] };
    assert!(matches!(update(&d4, &NoDevice, Some(&blas), &mut dst, &mut scratch), Err(BuildError::UpdateMismatch(_))));
    let mut v5 = v.clone();
    v5[30].x = f32::NAN;
    let vb5 = f32_bytes(&v5);
    let g5 = tri_geom(&vb5, v.len() as u32, &ib, n as u32, 0);
    let d5 = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &[g5] };
    assert!(matches!(update(&d5, &NoDevice, Some(&blas), &mut dst, &mut scratch), Err(BuildError::UpdateMismatch(_))));
    // Not built with ALLOW_UPDATE.
    let g6 = tri_geom(&vb, v.len() as u32, &ib, n as u32, 0);
    let b6 = build_ok(AsType::BottomLevel, 0, &[g6], &NoDevice);
    let d6 = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(0), geometries: &[g6] };
    assert!(matches!(update(&d6, &NoDevice, Some(&b6), &mut dst, &mut scratch), Err(BuildError::UpdateMismatch(_))));
}

/// The refit runs subtree by subtree in parallel: the same bytes on 1 and 4 threads, each
/// structure's node order checked (a child index that breaks preorder is an invalid source,
/// not a panic or a write elsewhere).
#[test]
fn refit_is_the_same_on_any_thread_count_and_checks_node_order() {
    let mut rng = Rng::new(77);
    let v = random_soup(&mut rng, 6000, 10.0, 0.4);
    let n = v.len() / 3;
    let idx: Vec<u32> = (0..v.len() as u32).collect();
    let (vb, ib) = (f32_bytes(&v), u32_bytes(&idx));
    let flags = BuildFlags::ALLOW_UPDATE | BuildFlags::PREFER_FAST_TRACE;
    let blas = build_ok(AsType::BottomLevel, flags, &[tri_geom(&vb, v.len() as u32, &ib, n as u32, 0)], &NoDevice);
    assert!(header(&blas).unwrap().node_count as usize > 4 * 256, "too few nodes for the parallel refit");
    let v2: Vec<Vec3> = v.iter().enumerate().map(|(i, p)| *p + Vec3::new(0.01 * (i % 5) as f32, -0.02, 0.0)).collect();
    let vb2 = f32_bytes(&v2);
    let g2 = tri_geom(&vb2, v.len() as u32, &ib, n as u32, 0);
    let sz = build_sizes(AsType::BottomLevel, BuildFlags(flags), &[shape_of(&g2)], &[n as u32]);
    let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &[g2] };
    let mut outs = Vec::new();
    for threads in [1, 4] {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let mut dst = blas.clone();
        let mut scratch = vec![0u8; sz.update_scratch_size as usize];
        pool.install(|| update(&desc, &NoDevice, None, &mut dst, &mut scratch)).unwrap();
        validate(&dst).unwrap();
        outs.push(dst);
    }
    assert!(outs[0] == outs[1], "refit bytes differ between 1 and 4 threads");
    assert!(outs[0] != blas, "the refit changed nothing");
    for _ in 0..300 {
        let ray = random_ray(&mut rng, 13.0);
        assert_eq!(closest_hit(&outs[0], &NoDevice, ray, RayFlags(0), 0xff).map(|h| h.t), brute_closest(&v2, &ray, 0).map(|b| b.0));
    }
    // Break preorder: the root's first internal child points one node further.
    let at = super::layout::parse(&blas).unwrap().raw.nodes_offset as usize;
    let root: super::layout::WideNode = bytemuck::pod_read_unaligned(&blas[at..at + super::layout::NODE_SIZE]);
    let c = (0..4).find(|&c| root.kind[c] == super::layout::CHILD_INTERNAL).expect("an internal child");
    let mut bad = blas.clone();
    let o = at + 40 + 4 * c;
    bad[o..o + 4].copy_from_slice(&(root.child[c] + 1).to_le_bytes());
    let mut scratch = vec![0u8; sz.update_scratch_size as usize];
    assert_eq!(update(&desc, &NoDevice, None, &mut bad, &mut scratch), Err(BuildError::InvalidSource("node order")));
}

/// A BLAS mixing triangles and AABBs (Vulkan forbids it; the library builds it) refits each
/// primitive by its own geometry's kind: moved and moved back, it has the bytes of the original
/// build (node boxes are exact unions, so any looser leaf box would show), and in between the
/// moved boxes are hit where they now are.
#[test]
fn refit_of_mixed_triangles_and_aabbs() {
    let mut rng = Rng::new(78);
    let v = random_soup(&mut rng, 3000, 10.0, 0.4);
    let idx: Vec<u32> = (0..v.len() as u32).collect();
    let (vb, ib) = (f32_bytes(&v), u32_bytes(&idx));
    let boxes_at = |shift: f32| -> Vec<u8> {
        (0..500)
            .flat_map(|i| {
                let c = Vec3::new((i % 10) as f32 + shift, (i / 10 % 10) as f32, (i / 100) as f32 + 20.0);
                [c.x, c.y, c.z, c.x + 0.3, c.y + 0.3, c.z + 0.3].map(f32::to_le_bytes)
            })
            .flatten()
            .collect()
    };
    let (b0, b1) = (boxes_at(0.0), boxes_at(5.0));
    let aabbs = |data| Geometry { flags: GeometryFlags(0), primitive_count: 500, data: GeometryData::Aabbs { data, stride: 24 } };
    let flags = BuildFlags::ALLOW_UPDATE | BuildFlags::PREFER_FAST_TRACE;
    let g0 = [tri_geom(&vb, 3000, &ib, 1000, 0), aabbs(&b0)];
    let built = build_ok(AsType::BottomLevel, flags, &g0, &NoDevice);
    let v2: Vec<Vec3> = v.iter().map(|p| *p + Vec3::new(0.0, 3.0, 0.0)).collect();
    let vb2 = f32_bytes(&v2);
    let g1 = [tri_geom(&vb2, 3000, &ib, 1000, 0), aabbs(&b1)];
    let sz = build_sizes(AsType::BottomLevel, BuildFlags(flags), &[shape_of(&g1[0]), shape_of(&g1[1])], &[1000, 500]);
    let mut scratch = vec![0u8; sz.update_scratch_size as usize];
    let mut blas = built.clone();
    update(&BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &g1 }, &NoDevice, None, &mut blas, &mut scratch).unwrap();
    validate(&blas).unwrap();
    // A ray along +z through the moved box column (x in [5, 5.3], y in [0, 0.3]) hits AABB
    // primitives (geometry 1); at x = 0.1, where they were, it finds none of them.
    let hits = |s: &[u8], x: f32| all_hits(s, &NoDevice, Ray { origin: Vec3::new(x, 0.1, 0.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 }, RayFlags(0), 0xff).iter().filter(|h| h.geometry_index == 1).count();
    assert!(hits(&blas, 5.1) > 0, "the moved boxes are not found");
    assert_eq!(hits(&blas, 0.1), 0, "the old boxes are still found");
    update(&BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &g0 }, &NoDevice, None, &mut blas, &mut scratch).unwrap();
    assert!(blas == built, "moved back, the refit differs from the build");
}

/// TLAS refit (instance records and BLAS table in parallel, BLAS bounds memoised): the same bytes
/// on 1 and 4 threads, a valid structure, and moved (transforms and some BLAS references
/// changed) then moved back, the bytes of the original build.
#[test]
fn tlas_refit_is_deterministic_and_returns_to_the_build() {
    let mut view = MapView::new();
    let mut addrs = Vec::new();
    for k in 0..3u64 {
        let mut rng = Rng::new(5 + k);
        let v = random_soup(&mut rng, 300, 2.0 + k as f32, 0.3);
        let idx: Vec<u32> = (0..v.len() as u32).collect();
        let (vb, ib) = (f32_bytes(&v), u32_bytes(&idx));
        let blas = build_ok(AsType::BottomLevel, 0, &[tri_geom(&vb, v.len() as u32, &ib, 100, 0)], &NoDevice);
        view.insert(0x1000_0000 * (k + 1), blas);
        addrs.push(0x1000_0000 * (k + 1));
    }
    let m = 3000usize;
    let recs = arbor_scene::instance_records(m, &addrs, 4);
    let mut recs2 = recs.clone();
    for (i, r) in recs2.iter_mut().enumerate() {
        r.transform[3] += (i % 7) as f32;
        if i % 5 == 0 {
            r.reference = addrs[(i / 5) % 3];
        }
    }
    let (packed, packed2) = (arbor_scene::InstanceRecord::pack(&recs), arbor_scene::InstanceRecord::pack(&recs2));
    let geom = |data| [Geometry { flags: GeometryFlags(0), primitive_count: m as u32, data: GeometryData::Instances { array_of_pointers: false, data } }];
    let (g0, g1) = (geom(&packed), geom(&packed2));
    for tier in [BuildFlags::PREFER_FAST_TRACE, BuildFlags::PREFER_FAST_BUILD] {
        let flags = BuildFlags(tier | BuildFlags::ALLOW_UPDATE);
        let built = build_ok(AsType::TopLevel, flags.0, &g0, &view);
        let sz = build_sizes(AsType::TopLevel, flags, &[GeometryShape::Instances], &[m as u32]);
        let mut outs = Vec::new();
        for threads in [1, 4] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let mut dst = built.clone();
            let mut scratch = vec![0u8; sz.update_scratch_size as usize];
            pool.install(|| update(&BuildDesc { ty: AsType::TopLevel, flags, geometries: &g1 }, &view, None, &mut dst, &mut scratch)).unwrap();
            validate(&dst).unwrap();
            outs.push(dst);
        }
        assert!(outs[0] == outs[1], "TLAS refit bytes differ between 1 and 4 threads");
        assert!(outs[0] != built, "the refit changed nothing");
        let mut scratch = vec![0u8; sz.update_scratch_size as usize];
        let mut back = outs[0].clone();
        update(&BuildDesc { ty: AsType::TopLevel, flags, geometries: &g0 }, &view, None, &mut back, &mut scratch).unwrap();
        assert!(back == built, "moved back, the TLAS refit differs from the build");
    }
}

//! Instance trees: flags, masks and custom indices, the bounds memo, large TLAS builds, and
//! copies (clone, compaction, serialization).
use super::*;

/// Instance flags, masks, custom indices and SBT offsets through traversal, then clone,
/// compaction and serialization of the same TLAS.
// One function: every step reuses the structures the steps before it built.
#[test]
fn tlas_instances_flags_masks_and_copies() {
    // BLAS A: one triangle facing -z viewers (front for rays along +z), non-opaque geometry.
    let vb = f32_bytes(&[Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0), Vec3::new(1.0, 0.0, 0.0)]);
    let ga = tri_geom(&vb, 3, &[], 1, 0);
    let blas_a = build_ok(AsType::BottomLevel, 0, &[ga], &NoDevice);
    // BLAS B: one AABB.
    let ab: Vec<u8> = [0.0f32, 0.0, 0.0, 1.0, 1.0, 1.0].iter().flat_map(|x| x.to_le_bytes()).collect();
    let gb = Geometry { flags: GeometryFlags(1), primitive_count: 1, data: GeometryData::Aabbs { data: &ab, stride: 24 } };
    let blas_b = build_ok(AsType::BottomLevel, 0, &[gb], &NoDevice);
    let mut view = MapView::new();
    view.insert(0x1000, blas_a.clone());
    view.insert(0x9000, blas_b.clone());
    let mut inst = Vec::new();
    inst.extend(instance_bytes(translate(0.0, 0.0, 5.0), 7, 0x01, 3, 0, 0x1000)); // 0
    inst.extend(instance_bytes(translate(0.0, 0.0, 9.0), 8, 0x02, 4, 0, 0x9000)); // 1
    inst.extend(instance_bytes(translate(0.0, 0.0, 3.0), 9, 0xff, 5, 0, 0)); // 2 inactive
    inst.extend(instance_bytes(translate(0.0, 0.0, 7.0), 10, 0x04, 6, 2 | 4, 0x1000)); // 3 flipped, opaque
    let g = Geometry { flags: GeometryFlags(0), primitive_count: 4, data: GeometryData::Instances { array_of_pointers: false, data: &inst } };
    let tlas = build_ok(AsType::TopLevel, BuildFlags::ALLOW_UPDATE, &[g], &view);
    let h = header(&tlas).unwrap();
    // One reference per active instance, in instance order (instance 2 is inactive: none).
    assert_eq!((h.instance_count, h.blas_reference_count), (3, 3));
    assert_eq!(blas_references(&tlas), vec![0x1000, 0x9000, 0x1000]);
    let ray = Ray { origin: Vec3::new(0.2, 0.2, 0.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 };
    let hit = closest_hit(&tlas, &view, ray, RayFlags(0), 0xff).unwrap();
    assert_eq!((hit.t, hit.instance_index, hit.instance_custom_index, hit.sbt_record_offset, hit.front_face, hit.opaque), (5.0, 0, 7, 3, true, false));
    assert_eq!(hit.object_ray_origin, Vec3::new(0.2, 0.2, -5.0));
    // Mask 0x02 sees only the AABB instance.
    let hit = closest_hit(&tlas, &view, ray, RayFlags(0), 0x02).unwrap();
    assert_eq!((hit.kind, hit.t, hit.instance_index), (HitKind::Aabb, 9.0, 1));
    // Flipped instance: back face from this side, culled by CULL_BACK; cull disabled would keep it.
    let hit = closest_hit(&tlas, &view, ray, RayFlags(RayFlags::CULL_BACK_FACING_TRIANGLES), 0x04);
    assert!(hit.is_none());
    let hit = closest_hit(&tlas, &view, ray, RayFlags(RayFlags::CULL_FRONT_FACING_TRIANGLES), 0x04).unwrap();
    assert!(!hit.front_face && hit.opaque);
    // Ray query: non-opaque triangle comes back as a candidate; opaque one is committed internally.
    let mut q = RayQuery::new(&tlas, &view, ray, RayFlags(0), 0x05);
    let c = q.proceed().unwrap();
    assert_eq!((c.kind, c.t, c.instance_index), (HitKind::Triangle, 5.0, 0));
    assert!(q.proceed().is_none());
    assert_eq!(q.committed().unwrap().t, 7.0);
    // Ray flags override: OPAQUE makes everything committed internally; CULL_OPAQUE then drops all.
    assert!(closest_hit(&tlas, &view, ray, RayFlags(RayFlags::OPAQUE | RayFlags::CULL_OPAQUE), 0xff).is_none());
    assert_eq!(closest_hit(&tlas, &view, ray, RayFlags(RayFlags::SKIP_TRIANGLES), 0xff).unwrap().kind, HitKind::Aabb);
    assert!(closest_hit(&tlas, &view, ray, RayFlags(RayFlags::SKIP_TRIANGLES | RayFlags::SKIP_AABBS), 0xff).is_none());
    // Copies.
    let used = compacted_size(&tlas).unwrap() as usize;
    let mut c = vec![0u8; used];
    compact_into(&tlas, &mut c).unwrap();
    assert_eq!(closest_hit(&c, &view, ray, RayFlags(0), 0xff), closest_hit(&tlas, &view, ray, RayFlags(0), 0xff));
    let mut small = vec![0u8; used - 1];
    assert!(clone_into(&tlas, &mut small).is_err());
    let uuid = [7u8; 16];
    let ss = serialized_size(&tlas).unwrap() as usize;
    assert_eq!(ss, 56 + 24 + used);
    let mut ser = vec![0u8; ss];
    assert_eq!(serialize(&tlas, uuid, &mut ser).unwrap(), ss as u64);
    assert!(compatible(ser[..32].try_into().unwrap(), uuid));
    assert!(!compatible(ser[..32].try_into().unwrap(), [8u8; 16]));
    // Rewrite the addresses: BLASes moved.
    ser[56..64].copy_from_slice(&0x5000u64.to_le_bytes());
    ser[64..72].copy_from_slice(&0x7000u64.to_le_bytes());
    ser[72..80].copy_from_slice(&0x5000u64.to_le_bytes());
    let mut view2 = MapView::new();
    view2.insert(0x5000, blas_a.clone());
    view2.insert(0x7000, blas_b.clone());
    let mut de = vec![0u8; used];
    deserialize(&ser, uuid, &mut de).unwrap();
    assert_eq!(blas_references(&de), vec![0x5000, 0x7000, 0x5000]);
    assert_eq!(closest_hit(&de, &view2, ray, RayFlags(0), 0xff).map(|h| h.t), Some(5.0));
    assert!(deserialize(&ser, [1u8; 16], &mut de).is_err());
    assert!(deserialize(&ser[..100], uuid, &mut de).is_err());
    // TLAS update: move instance 0 and retarget it to BLAS B.
    let mut inst2 = inst.clone();
    inst2[..64].copy_from_slice(&instance_bytes(translate(0.0, 0.0, 2.0), 70, 0x01, 3, 0, 0x9000));
    let g2 = Geometry { flags: GeometryFlags(0), primitive_count: 4, data: GeometryData::Instances { array_of_pointers: false, data: &inst2 } };
    let sz = build_sizes(AsType::TopLevel, BuildFlags(BuildFlags::ALLOW_UPDATE), &[GeometryShape::Instances], &[4]);
    let mut scratch = vec![0u8; sz.update_scratch_size as usize];
    let desc = BuildDesc { ty: AsType::TopLevel, flags: BuildFlags(BuildFlags::ALLOW_UPDATE), geometries: &[g2] };
    let mut upd = tlas.clone();
    update(&desc, &view, None, &mut upd, &mut scratch).unwrap();
    validate(&upd).unwrap();
    assert_eq!(blas_references(&upd), vec![0x9000, 0x9000, 0x1000]);
    let hit = closest_hit(&upd, &view, ray, RayFlags(0), 0xff).unwrap();
    assert_eq!((hit.t, hit.instance_custom_index, hit.kind), (2.0, 70, HitKind::Aabb));
    // Activating the inactive instance is an update mismatch.
    let mut inst3 = inst.clone();
    inst3[128 + 56..128 + 64].copy_from_slice(&0x1000u64.to_le_bytes());
    let g3 = Geometry { flags: GeometryFlags(0), primitive_count: 4, data: GeometryData::Instances { array_of_pointers: false, data: &inst3 } };
    let desc = BuildDesc { ty: AsType::TopLevel, flags: BuildFlags(BuildFlags::ALLOW_UPDATE), geometries: &[g3] };
    let mut upd2 = vec![0u8; tlas.len()];
    assert!(matches!(update(&desc, &view, Some(&tlas), &mut upd2, &mut scratch), Err(BuildError::UpdateMismatch(_))));
    // So is swapping which one is inactive (the active count stays the same: the instance pass
    // finds the stored instance that went inactive).
    inst3[56..64].copy_from_slice(&0u64.to_le_bytes());
    let g3 = Geometry { flags: GeometryFlags(0), primitive_count: 4, data: GeometryData::Instances { array_of_pointers: false, data: &inst3 } };
    let desc = BuildDesc { ty: AsType::TopLevel, flags: BuildFlags(BuildFlags::ALLOW_UPDATE), geometries: &[g3] };
    assert_eq!(update(&desc, &view, Some(&tlas), &mut upd2, &mut scratch), Err(BuildError::UpdateMismatch("an active instance became inactive")));
    // Array of pointers.
    let mut pv = MapView::new();
    pv.insert(0x1000, blas_a.clone());
    pv.insert(0x9000, blas_b.clone());
    pv.insert(0x20000, inst.clone());
    let ptrs: Vec<u8> = [0x20000u64 + 64, 0x20000].iter().flat_map(|x| x.to_le_bytes()).collect();
    let gp = Geometry { flags: GeometryFlags(0), primitive_count: 2, data: GeometryData::Instances { array_of_pointers: true, data: &ptrs } };
    let tp = build_ok(AsType::TopLevel, 0, &[gp], &pv);
    let hit = closest_hit(&tp, &pv, ray, RayFlags(0), 0xff).unwrap();
    assert_eq!((hit.t, hit.instance_index), (5.0, 1));
}

/// Clone, compaction, serialization and deserialization of a structure large enough to be
/// copied in parallel chunks (`PAR_COPY_CHUNK`), on a 4-thread pool: the same bytes as plain
/// copies of the source's used bytes, and a deserialized copy traces like the source.
#[test]
fn large_copies_in_parallel_chunks_are_exact() {
    let mut rng = Rng::new(77);
    let n = 60_000;
    let v = random_soup(&mut rng, n, 10.0, 0.2);
    let idx: Vec<u32> = (0..3 * n as u32).collect();
    let (vb, ib) = (f32_bytes(&v), u32_bytes(&idx));
    let g = tri_geom(&vb, v.len() as u32, &ib, n as u32, 0);
    let blas = build_ok(AsType::BottomLevel, BuildFlags::ALLOW_COMPACTION, &[g], &NoDevice);
    let used = compacted_size(&blas).unwrap() as usize;
    assert!(used >= 3 * super::PAR_COPY_CHUNK, "the structure ({used} bytes) must span several chunks");
    let pool = rayon::ThreadPoolBuilder::new().num_threads(4).build().unwrap();
    pool.install(|| {
        let mut c = vec![0xAAu8; used];
        compact_into(&blas, &mut c).unwrap();
        assert!(c[..] == blas[..used], "compacted bytes");
        let mut k = vec![0x55u8; blas.len() + 7];
        clone_into(&blas, &mut k).unwrap();
        assert!(k[..used] == blas[..used] && k[used..].iter().all(|&b| b == 0x55), "clone: the used bytes and nothing past them");
        let uuid = [3u8; 16];
        let mut ser = vec![0u8; serialized_size(&blas).unwrap() as usize];
        serialize(&blas, uuid, &mut ser).unwrap();
        assert!(ser[ser.len() - used..] == blas[..used], "serialized payload");
        let mut de = vec![0u8; used];
        deserialize(&ser, uuid, &mut de).unwrap();
        assert!(de[..] == blas[..used], "deserialized bytes");
        for _ in 0..50 {
            let ray = random_ray(&mut rng, 13.0);
            assert_eq!(closest_hit(&de, &NoDevice, ray, RayFlags(0), 0xff).map(|h| h.t), brute_closest(&v, &ray, 0).map(|b| b.0));
        }
    });
}

/// The ingest's BLAS-bounds memo holds four references: seven BLASes (single triangles of
/// different sizes) instanced in a pseudo-random order make it evict and miss all the time.
/// Every instance must still get its own BLAS's bounds: a ray at the middle of each
/// instance's triangle hits that instance (a wrong box would hide it), and the TLAS bounds are
/// the union of the transformed triangles.
#[test]
fn tlas_over_more_blases_than_the_bounds_memo() {
    let mut view = MapView::new();
    let mut tris = Vec::new();
    for k in 0..7u64 {
        let s = 0.2 + 0.1 * k as f32;
        let v = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, s, 0.0), Vec3::new(s, 0.0, 0.0)];
        let vb = f32_bytes(&v);
        let g = tri_geom(&vb, 3, &[], 1, GeometryFlags::OPAQUE);
        view.insert(0x10000 * (k + 1), build_ok(AsType::BottomLevel, 0, &[g], &NoDevice));
        tris.push(v);
    }
    let mut rng = Rng::new(99);
    let mut inst = Vec::new();
    let mut placed = Vec::new();
    for i in 0..200u32 {
        let k = (rng.next_u32() % 7) as usize;
        let (x, y) = ((i % 20) as f32 * 2.0, (i / 20) as f32 * 2.0);
        inst.extend(instance_bytes(translate(x, y, 1.0 + (i % 3) as f32), i, 0xff, 0, 0, 0x10000 * (k as u64 + 1)));
        placed.push((x, y, k));
    }
    let g = Geometry { flags: GeometryFlags(0), primitive_count: 200, data: GeometryData::Instances { array_of_pointers: false, data: &inst } };
    for flags in [BuildFlags::PREFER_FAST_TRACE, BuildFlags::PREFER_FAST_BUILD] {
        let tlas = build_ok(AsType::TopLevel, flags, &[g], &view);
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for (i, &(x, y, k)) in placed.iter().enumerate() {
            let s = tris[k][1].y;
            let z = 1.0 + (i % 3) as f32;
            let ray = Ray { origin: Vec3::new(x + s * 0.3, y + s * 0.3, -1.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 };
            let hit = closest_hit(&tlas, &view, ray, RayFlags(0), 0xff).unwrap_or_else(|| panic!("instance {i} (BLAS {k}) not hit"));
            assert_eq!((hit.instance_index, hit.t), (i as u32, z + 1.0), "instance {i}");
            // The triangle spans (x, y, z) to (x + s, y + s, z).
            for (a, (l, h)) in [(x, x + s), (y, y + s), (z, z)].into_iter().enumerate() {
                lo[a] = lo[a].min(l);
                hi[a] = hi[a].max(h);
            }
        }
        let h = header(&tlas).unwrap();
        assert_eq!(h.bounds, [lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]]);
    }
}

/// A TLAS of 20,000 instances (several cut roots, instance ingest in many chunks) builds to
/// the same bytes on 1, 3 and 16 threads in every tier, and traverses to the instance placed
/// under each probe ray. `ARBOR_PRINT_DIGESTS=1` prints the digests (for checking that a
/// change to the build's scheduling leaves them alone).
#[test]
fn large_tlas_is_the_same_on_any_thread_count() {
    let fnv = |b: &[u8]| b.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &x| (h ^ x as u64).wrapping_mul(0x0000_0100_0000_01b3));
    let mut view = MapView::new();
    for k in 0..3u64 {
        let s = 0.3 + 0.2 * k as f32;
        let v = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, s, 0.0), Vec3::new(s, 0.0, 0.0)];
        let vb = f32_bytes(&v);
        let g = tri_geom(&vb, 3, &[], 1, GeometryFlags::OPAQUE);
        view.insert(0x10000 * (k + 1), build_ok(AsType::BottomLevel, 0, &[g], &NoDevice));
    }
    let mut rng = Rng::new(2024);
    let n = 20_000u32;
    let mut inst = Vec::new();
    for i in 0..n {
        let k = rng.next_u32() % 3;
        let (x, y) = ((i % 200) as f32 * 2.0, (i / 200) as f32 * 2.0);
        inst.extend(instance_bytes(translate(x, y, rng.f() * 4.0), i, 0xff, 0, 0, 0x10000 * (k as u64 + 1)));
    }
    let g = Geometry { flags: GeometryFlags(0), primitive_count: n, data: GeometryData::Instances { array_of_pointers: false, data: &inst } };
    let mut sah = Vec::new();
    for flags in [BuildFlags::PREFER_FAST_TRACE, BuildFlags::PREFER_FAST_BUILD, 0] {
        let mut outs = Vec::new();
        for threads in [1, 3, 16] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            outs.push(pool.install(|| build_ok(AsType::TopLevel, flags, &[g], &view)));
        }
        if std::env::var("ARBOR_PRINT_DIGESTS").is_ok() {
            println!("tlas digest flags {flags:#x}: {:016x}", fnv(&outs[0]));
        }
        assert!(outs[0] == outs[1] && outs[1] == outs[2], "TLAS bytes differ between thread counts (flags {flags:#x})");
        for i in (0..n).step_by(997) {
            let (x, y) = ((i % 200) as f32 * 2.0, (i / 200) as f32 * 2.0);
            let ray = Ray { origin: Vec3::new(x + 0.1, y + 0.05, -1.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 };
            let hit = closest_hit(&outs[0], &view, ray, RayFlags(0), 0xff).unwrap_or_else(|| panic!("instance {i} not hit"));
            assert_eq!(hit.instance_index, i, "the ray over instance {i}");
        }
        let m = metrics(&outs[0]).unwrap();
        sah.push((m.sah_cost, m.node_count));
    }
    // Instance trees bin all three axes in the default tier (its BLAS bins one axis below
    // 1,024 references) with the fast-trace tier's bins: the same tree as FAST_TRACE's.
    assert_eq!(sah[2], sah[0], "default-tier TLAS against FAST_TRACE's (SAH, nodes)");
    assert!(sah[1].0 > sah[0].0, "the fast-build TLAS bins one axis: {:?} against {:?}", sah[1], sah[0]);
}

/// Eight instances of one BLAS: the serialized header lists eight handles (one per instance, in
/// instance order), and each instance is relocated by its own handle: rewriting handle k to a
/// BLAS that exists only for even k leaves the odd instances absent after deserialization.
#[test]
fn serialized_header_lists_one_handle_per_instance() {
    let vb = f32_bytes(&[Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0), Vec3::new(1.0, 0.0, 0.0)]);
    let blas = build_ok(AsType::BottomLevel, 0, &[tri_geom(&vb, 3, &[], 1, GeometryFlags::OPAQUE)], &NoDevice);
    let mut view = MapView::new();
    view.insert(0x1000, blas.clone());
    let inst: Vec<u8> = (0..8).flat_map(|k| instance_bytes(translate(2.0 * k as f32, 0.0, 5.0), k, 0xff, 0, 0, 0x1000)).collect();
    let g = Geometry { flags: GeometryFlags(0), primitive_count: 8, data: GeometryData::Instances { array_of_pointers: false, data: &inst } };
    let tlas = build_ok(AsType::TopLevel, 0, &[g], &view);
    assert_eq!(blas_references(&tlas), vec![0x1000; 8]);
    let uuid = [3u8; 16];
    let mut ser = vec![0u8; serialized_size(&tlas).unwrap() as usize];
    serialize(&tlas, uuid, &mut ser).unwrap();
    assert_eq!(u64::from_le_bytes(ser[48..56].try_into().unwrap()), 8);
    let mut moved = MapView::new();
    for k in 0..8u64 {
        let a = 0x10_0000 * (k + 1);
        ser[56 + 8 * k as usize..64 + 8 * k as usize].copy_from_slice(&a.to_le_bytes());
        if k % 2 == 0 {
            moved.insert(a, blas.clone());
        }
    }
    let mut de = vec![0u8; tlas.len()];
    deserialize(&ser, uuid, &mut de).unwrap();
    for k in 0..8u32 {
        let ray = Ray { origin: Vec3::new(2.0 * k as f32 + 0.2, 0.2, 0.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 };
        let hit = closest_hit(&de, &moved, ray, RayFlags(0), 0xff);
        assert_eq!(hit.map(|h| (h.t, h.instance_custom_index)), (k % 2 == 0).then_some((5.0, k)), "instance {k}");
    }
}

/// The BLAS table and each instance record's table index, written by instance index when every
/// instance of the one geometry is active, against the ranked path (the same instances and an
/// inactive one after them) and against the input: the table lists the input's references in
/// instance order, and every instance reaches its own BLAS (each BLAS's triangle lies at its
/// own depth, so the hit distance names the BLAS).
#[test]
fn all_active_tlas_table_matches_the_ranked_path() {
    let mut view = MapView::new();
    for k in 0..3u64 {
        let z = k as f32;
        let v = [Vec3::new(0.0, 0.0, z), Vec3::new(0.0, 1.0, z), Vec3::new(1.0, 0.0, z)];
        let vb = f32_bytes(&v);
        let g = tri_geom(&vb, 3, &[], 1, GeometryFlags::OPAQUE);
        view.insert(0x10000 * (k + 1), build_ok(AsType::BottomLevel, 0, &[g], &NoDevice));
    }
    let mut rng = Rng::new(31);
    let n = 3000u32;
    let (mut inst, mut expect) = (Vec::new(), Vec::new());
    for i in 0..n {
        let k = (rng.next_u32() % 3) as u64;
        let (x, y) = ((i % 60) as f32 * 2.0, (i / 60) as f32 * 2.0);
        inst.extend(instance_bytes(translate(x, y, 0.0), i, 0xff, 0, 0, 0x10000 * (k + 1)));
        expect.push(0x10000 * (k + 1));
    }
    let mut with_inactive = inst.clone();
    with_inactive.extend(instance_bytes(translate(0.0, 0.0, 0.0), n, 0xff, 0, 0, 0));
    let all = Geometry { flags: GeometryFlags(0), primitive_count: n, data: GeometryData::Instances { array_of_pointers: false, data: &inst } };
    let ranked = Geometry { flags: GeometryFlags(0), primitive_count: n + 1, data: GeometryData::Instances { array_of_pointers: false, data: &with_inactive } };
    for flags in [BuildFlags::PREFER_FAST_BUILD, BuildFlags::PREFER_FAST_TRACE] {
        let a = build_ok(AsType::TopLevel, flags, &[all], &view);
        let b = build_ok(AsType::TopLevel, flags, &[ranked], &view);
        assert!(validate(&a).is_ok() && validate(&b).is_ok());
        assert_eq!(blas_references(&a), expect, "the table in instance order (all active)");
        assert_eq!(blas_references(&b), expect, "the table in instance order (ranked)");
        for i in (0..n).step_by(7) {
            let (x, y) = ((i % 60) as f32 * 2.0, (i / 60) as f32 * 2.0);
            let ray = Ray { origin: Vec3::new(x + 0.2, y + 0.2, -1.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 };
            let want = (expect[i as usize] / 0x10000) as f32;
            for s in [&a, &b] {
                let hit = closest_hit(s, &view, ray, RayFlags(0), 0xff).unwrap_or_else(|| panic!("instance {i} not hit"));
                assert_eq!((hit.instance_index, hit.t), (i, want), "instance {i}");
            }
        }
    }
}

/// The fast-build tier's linear BVH (`build::morton`) against brute force: 6,000 instances of
/// unit right triangles at random depths, a third of them stacked on 40 shared positions (equal
/// Morton codes: median splits), one in eleven inactive, in clusters far apart (codes that
/// differ in their top bits only). Every ray down the z axis finds the nearest instance over
/// its point, computed by scanning every instance; the bytes are the same on 1, 2 and 5
/// threads, and the structure passes every check a copy makes.
#[test]
fn fast_build_tlas_linear_bvh_matches_brute_force() {
    let vb = f32_bytes(&[Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0), Vec3::new(1.0, 0.0, 0.0)]);
    let mut view = MapView::new();
    view.insert(0x4000, build_ok(AsType::BottomLevel, 0, &[tri_geom(&vb, 3, &[], 1, GeometryFlags::OPAQUE)], &NoDevice));
    let mut rng = Rng::new(77);
    let n = 6000u32;
    let (mut inst, mut placed) = (Vec::new(), Vec::new());
    for i in 0..n {
        let cluster = [0.0, 500.0, 1.0e4][(rng.next_u32() % 3) as usize];
        let (x, y) = if i % 3 == 0 {
            let k = rng.next_u32() % 40;
            (cluster + (k % 8) as f32 * 0.7, (k / 8) as f32 * 0.7)
        } else {
            (cluster + rng.range(0.0, 60.0), rng.range(0.0, 60.0))
        };
        let z = rng.range(0.0, 50.0);
        let active = i % 11 != 5;
        inst.extend(instance_bytes(translate(x, y, z), i, 0xff, 0, 0, if active { 0x4000 } else { 0 }));
        placed.push((x, y, z, active));
    }
    let g = Geometry { flags: GeometryFlags(0), primitive_count: n, data: GeometryData::Instances { array_of_pointers: false, data: &inst } };
    let builds: Vec<Vec<u8>> = [1, 2, 5].iter().map(|&t| rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap().install(|| build_ok(AsType::TopLevel, BuildFlags::PREFER_FAST_BUILD, &[g], &view))).collect();
    assert!(builds[0] == builds[1] && builds[1] == builds[2], "fast-build TLAS bytes differ between thread counts");
    let tlas = &builds[0];
    assert!(validate(tlas).is_ok());
    for i in (0..n as usize).step_by(5) {
        let (x, y) = (placed[i].0 + 0.25, placed[i].1 + 0.3);
        let ray = Ray { origin: Vec3::new(x, y, -1.0), direction: Vec3::Z, tmin: 0.0, tmax: 1.0e3 };
        // The triangle of instance k covers (px, py) when 0 <= px - x_k, 0 <= py - y_k and
        // their sum <= 1; strictly inside by a margin, so no edge case decides.
        let inside = |&(px, py, _, active): &(f32, f32, f32, bool)| active && x - px > 1e-3 && y - py > 1e-3 && (x - px) + (y - py) < 1.0 - 1e-3;
        let near = |&(px, py, _, active): &(f32, f32, f32, bool)| active && x - px > -1e-3 && y - py > -1e-3 && (x - px) + (y - py) < 1.0 + 1e-3;
        if placed.iter().any(|p| near(p) && !inside(p)) {
            continue;
        }
        let want = placed.iter().filter(|p| inside(p)).map(|p| p.2 + 1.0).fold(f32::INFINITY, f32::min);
        let hit = closest_hit(tlas, &view, ray, RayFlags(0), 0xff);
        match hit {
            Some(h) => {
                assert_eq!(h.t, want, "ray over instance {i}");
                let (px, py, pz, _) = placed[h.instance_index as usize];
                assert!(inside(&(px, py, pz, true)) && pz + 1.0 == want, "ray over instance {i} hit instance {}", h.instance_index);
            }
            None => assert!(want.is_infinite(), "ray over instance {i}: no hit, brute force {want}"),
        }
    }
}

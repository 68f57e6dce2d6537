//! The same bytes for any thread count, through every path of the build (two-phase
//! scheduling, the planned top, compaction, drops), and the digest printer.
use super::*;

#[test]
fn determinism_across_thread_counts() {
    let mut rng = Rng::new(5);
    let v = random_soup(&mut rng, 40_000, 50.0, 1.0);
    let vb = f32_bytes(&v);
    let g = tri_geom(&vb, v.len() as u32, &[], 40_000, 0);
    for &flags in &[BuildFlags::PREFER_FAST_BUILD, 0, BuildFlags::PREFER_FAST_TRACE] {
        let out = builds_on(&[1, 2, 8], flags, &[g], |_, _| ());
        assert!(out.windows(2).all(|w| w[0].0 == w[1].0), "flags {flags}");
    }
}

/// The two-phase build of a large tree (`build::schedule::build_tree`: the top split by tasks that
/// spawn tasks, then every subtree below it as a task of its own, then the top's sums) gives
/// the bytes of the one-thread recursion, on a real mesh: over clusters (FAST_BUILD, the
/// default tier) and over triangles (FAST_TRACE with ALLOW_UPDATE), on 1, 3 and 16 threads.
#[test]
fn real_mesh_builds_are_the_same_on_any_thread_count() {
    let mesh = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/dragon_vrip_res2.ply.gz")).expect("mesh");
    let (vb, ib) = (mesh.vertex_bytes(), mesh.index_bytes());
    let ntri = mesh.triangle_count() as u32;
    let g = tri_geom(&vb, mesh.vertex_count() as u32, &ib, ntri, GeometryFlags::OPAQUE);
    for flags in [BuildFlags::PREFER_FAST_BUILD, 0, BuildFlags::PREFER_FAST_TRACE | BuildFlags::ALLOW_UPDATE] {
        let out = builds_on(&[1, 3, 16], flags, &[g], |blas, report| {
            validate(blas).unwrap();
            report.clusters.map_or(ntri as usize, |c| c as usize)
        });
        for &(_, refs) in &out {
            assert!(refs > 4 * params::SAMPLE_FROM, "flags {flags:#x}: {refs} references, a top of fewer than three levels on 16 threads");
        }
        assert!(out.windows(2).all(|w| w[0].0 == w[1].0), "flags {flags:#x}");
    }
}

/// Several geometries with dropped primitives through the two-phase build and the prefix
/// compaction of ingest: the res2 dragon cut into three geometries (one not opaque), every
/// 97th triangle of the first made degenerate and a run of the second made inactive by a NaN
/// vertex, in every tier: the same bytes on 1, 2, 7 and 16 threads, and a valid structure
/// that holds every triangle that was not dropped.
#[test]
fn multi_geometry_builds_with_drops_are_the_same_on_any_thread_count() {
    let mesh = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/dragon_vrip_res2.ply.gz")).expect("mesh");
    let mut v = mesh.positions.iter().map(|p| Vec3::from(*p)).collect::<Vec<_>>();
    let nv = v.len() as u32;
    let mut idx: Vec<u32> = mesh.indices.iter().flat_map(|t| t.iter().copied()).collect();
    let ntri = idx.len() / 3;
    let (a, b) = (ntri / 3, 2 * ntri / 3);
    let mut degenerate = 0;
    for t in (0..a).step_by(97) {
        idx[3 * t + 1] = idx[3 * t];
        degenerate += 1;
    }
    // Triangles of the second geometry that use vertex `bad` become inactive (NaN x).
    let bad = idx[3 * (a + 10)] as usize;
    v[bad].x = f32::NAN;
    let inactive = idx.chunks_exact(3).filter(|t| t.contains(&(bad as u32))).count();
    let vb = f32_bytes(&v);
    let (i0, i1, i2) = (u32_bytes(&idx[..3 * a]), u32_bytes(&idx[3 * a..3 * b]), u32_bytes(&idx[3 * b..]));
    let geoms = [tri_geom(&vb, nv, &i0, a as u32, GeometryFlags::OPAQUE), tri_geom(&vb, nv, &i1, (b - a) as u32, 0), tri_geom(&vb, nv, &i2, (ntri - b) as u32, GeometryFlags::OPAQUE)];
    for flags in [BuildFlags::PREFER_FAST_BUILD, 0, BuildFlags::PREFER_FAST_TRACE] {
        let out = builds_on(&[1, 2, 7, 16], flags, &geoms, |blas, _| {
            validate(blas).unwrap();
            header(blas).unwrap().primitive_count as usize
        });
        for &(_, prims) in &out {
            assert_eq!(prims, ntri - degenerate - inactive, "flags {flags:#x}");
        }
        assert!(out.windows(2).all(|w| w[0].0 == w[1].0), "flags {flags:#x}");
    }
}

/// A large build whose references all share one centroid: the sample of the planned top
/// (`build::plan`) cannot split, so the build takes the compaction ingest skipped and the
/// recursion's median splits. 70,000 copies of one triangle, every tenth degenerate (so the
/// chunks keep partial prefixes), in every tier: a valid structure with every triangle that
/// was not dropped, the same bytes on 1 and 4 threads.
#[test]
fn builds_whose_sample_cannot_split_still_hold_every_primitive() {
    let v = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0)];
    let vb = f32_bytes(&v);
    let ntri = 70_000usize;
    let idx: Vec<u32> = (0..ntri).flat_map(|t| if t % 10 == 3 { [0, 0, 1] } else { [0, 1, 2] }).collect();
    let ib = u32_bytes(&idx);
    let g = tri_geom(&vb, 3, &ib, ntri as u32, GeometryFlags::OPAQUE);
    for flags in [BuildFlags::PREFER_FAST_BUILD, 0, BuildFlags::PREFER_FAST_TRACE] {
        let out = builds_on(&[1, 4], flags, &[g], |blas, _| {
            validate(blas).unwrap();
            header(blas).unwrap().primitive_count as usize
        });
        for &(_, prims) in &out {
            assert_eq!(prims, ntri - ntri / 10, "flags {flags:#x}");
        }
        assert!(out.windows(2).all(|w| w[0].0 == w[1].0), "flags {flags:#x}");
    }
}

/// A planned build one of whose buckets is too large for one thread (half of the triangles
/// share one centroid, so the plan cannot split them; on 4 and 16 threads that bucket's subtree
/// splits further in parallel, `split_top`): the same bytes on 1, 4 and 16 threads, every
/// triangle once with its own vertices, in every tier.
#[test]
fn planned_builds_whose_bucket_splits_further_are_the_same_on_any_thread_count() {
    let mut rng = Rng::new(5);
    let n = 100_000usize;
    let mut v: Vec<Vec3> = Vec::with_capacity(3 * n);
    for t in 0..n {
        let c = if t % 2 == 0 { Vec3::new(rng.f(), rng.f(), rng.f()) } else { Vec3::splat(0.5) };
        let e = 0.004;
        v.extend([c, c + Vec3::new(e, 0.0, 0.0), c + Vec3::new(0.0, e, 0.0)]);
    }
    let vb = f32_bytes(&v);
    let ib = u32_bytes(&(0..3 * n as u32).collect::<Vec<u32>>());
    let g = tri_geom(&vb, v.len() as u32, &ib, n as u32, GeometryFlags::OPAQUE);
    for flags in [BuildFlags::PREFER_FAST_BUILD, 0, BuildFlags::PREFER_FAST_TRACE] {
        let out = builds_on(&[1, 4, 16], flags, &[g], |blas, report| {
            validate(blas).unwrap();
            (header(blas).unwrap().primitive_count as usize, report.top_planned, report.forked_buckets)
        });
        for (i, (_, (prims, planned, later))) in out.iter().enumerate() {
            assert_eq!((*prims, *planned), (n, TopPlanned::FromInput), "flags {flags:#x}");
            assert_eq!(*later > 0, i > 0, "flags {flags:#x}: {later} buckets split further on {} threads", [1, 4, 16][i]);
        }
        assert!(out.windows(2).all(|w| w[0].0 == w[1].0), "flags {flags:#x}");
        // Every triangle exactly once in the records, with its own vertices.
        let parsed = layout::parse(&out[0].0).unwrap();
        let mut seen = vec![false; n];
        for k in 0..n as u32 {
            let rec = parsed.record(k).unwrap();
            let p = rec.primitive as usize;
            assert_eq!(rec.geometry, 0);
            assert!(!std::mem::replace(&mut seen[p], true), "triangle {p} twice");
            let data = parsed.prim(k).unwrap();
            assert_eq!(data[..3], v[3 * p].to_array(), "triangle {p}'s first vertex");
        }
    }
}

/// A large build with extreme coordinates: most triangles in a unit cube, some spanning
/// ±3e38, some whole at x near +3e38 or -3e38 (the centroid box's x extent overflows to
/// infinity, which the planned top's grid and bins must survive) and some with an infinite vertex
/// (sanitised to ±f32::MAX). Every tier, the top planned from the references and from the
/// input: a valid structure holding every triangle, the same bytes on 1 and 4 threads.
#[test]
fn large_builds_with_extreme_coordinates_hold_every_primitive() {
    let mut rng = Rng::new(11);
    let ntri = 70_000usize;
    let mut v: Vec<Vec3> = Vec::with_capacity(3 * ntri);
    for t in 0..ntri {
        let c = Vec3::new(rng.f(), rng.f(), rng.f());
        let e = 0.01;
        let (mut a, mut b, mut c2) = (c, c + Vec3::new(e, 0.0, 0.0), c + Vec3::new(0.0, e, e));
        if t % 997 == 5 {
            a = Vec3::new(-3e38, -3e38, 3e38);
        }
        if t % 1301 == 7 {
            a = Vec3::new(f32::INFINITY, 0.5, 0.5);
        }
        if t % 1499 == 9 {
            // Whole triangles at x near +-3e38: centroids 6e38 apart in x, an infinite extent
            // there (x cannot be binned), y and z as the others.
            let s = if t % 2 == 0 { 3e38 } else { -3e38 };
            (a, b, c2) = (Vec3::new(s, c.y, c.z), Vec3::new(s * 0.97, c.y, c.z), Vec3::new(s, c.y + e, c.z + e));
        }
        v.extend([a, b, c2]);
    }
    let vb = f32_bytes(&v);
    // Without indices the top is planned from the references after ingest, with them from
    // the input beside ingest.
    let ib = u32_bytes(&(0..3 * ntri as u32).collect::<Vec<u32>>());
    for (idx, from) in [(&[][..], TopPlanned::FromReferences), (&ib[..], TopPlanned::FromInput)] {
        let g = tri_geom(&vb, v.len() as u32, idx, ntri as u32, GeometryFlags::OPAQUE);
        for flags in [BuildFlags::PREFER_FAST_BUILD, 0, BuildFlags::PREFER_FAST_TRACE] {
            let out = builds_on(&[1, 4], flags, &[g], |blas, report| {
                validate(blas).unwrap();
                (header(blas).unwrap().primitive_count as usize, report.top_planned)
            });
            for &(_, (prims, planned)) in &out {
                assert_eq!(prims, ntri, "flags {flags:#x}");
                // FAST_BUILD bins the widest axis only, the infinite one here: no plan.
                let want = if flags == BuildFlags::PREFER_FAST_BUILD { TopPlanned::No } else { from };
                assert_eq!(planned, want, "flags {flags:#x}: where the top was planned");
            }
            assert!(out.windows(2).all(|w| w[0].0 == w[1].0), "flags {flags:#x}");
        }
    }
}

/// Prints an FNV-1a digest of the structure bytes for a set of inputs (tiers, U32/U16 indices,
/// vertex strides 12/16, ALLOW_UPDATE, inactive and degenerate triangles, 1 and 2 threads):
/// run before and after a builder change that must not change any byte, and diff the output.
#[test]
#[ignore]
fn structure_digests() {
    let fnv = |b: &[u8]| b.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &x| (h ^ x as u64).wrapping_mul(0x0000_0100_0000_01b3));
    // ARBOR_DIGEST_MESHES: comma-separated paths relative to the crate (default: two small ones).
    let list = std::env::var("ARBOR_DIGEST_MESHES").unwrap_or_else(|_| "data/bunny.ply,data/dragon_vrip_res4.ply.gz".to_string());
    for path in list.split(',') {
        let mesh = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/").to_string() + path).expect("mesh");
        let nv = mesh.vertex_count() as u32;
        let ntri = mesh.triangle_count() as u32;
        let vb12 = mesh.vertex_bytes();
        // Stride 16 with a poisoned fourth float; a NaN X on vertex 5 (inactive triangles).
        let mut vb16 = Vec::new();
        for (i, c) in vb12.chunks_exact(12).enumerate() {
            let mut c = c.to_vec();
            if i == 5 {
                c[..4].copy_from_slice(&f32::NAN.to_le_bytes());
            }
            vb16.extend_from_slice(&c);
            vb16.extend_from_slice(&f32::NAN.to_le_bytes());
        }
        let mut ib32 = mesh.index_bytes();
        // Triangle 3 degenerate by repeated index.
        let i0 = ib32[36..40].to_vec();
        ib32[40..44].copy_from_slice(&i0);
        let ib16: Vec<u8> = ib32.chunks_exact(4).flat_map(|c| (u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as u16).to_le_bytes()).collect();
        let cases: Vec<(&str, Geometry)> = vec![
            ("u32 s12", tri_geom(&vb12, nv, &ib32, ntri, GeometryFlags::OPAQUE)),
            ("u32 s16", Geometry { flags: GeometryFlags(0), primitive_count: ntri, data: GeometryData::Triangles { format: VertexFormat::R32G32B32Sfloat, vertices: &vb16, stride: 16, max_vertex: nv - 1, index_type: IndexType::U32, indices: &ib32, transform: None } }),
            ("a32 s16", Geometry { flags: GeometryFlags(0), primitive_count: ntri, data: GeometryData::Triangles { format: VertexFormat::R32G32B32A32Sfloat, vertices: &vb16, stride: 16, max_vertex: nv - 1, index_type: IndexType::U32, indices: &ib32, transform: None } }),
            ("u16 s12", Geometry { flags: GeometryFlags(0), primitive_count: ntri, data: GeometryData::Triangles { format: VertexFormat::R32G32B32Sfloat, vertices: &vb12, stride: 12, max_vertex: nv - 1, index_type: IndexType::U16, indices: &ib16, transform: None } }),
            ("none", Geometry { flags: GeometryFlags(0), primitive_count: nv / 3, data: GeometryData::Triangles { format: VertexFormat::R32G32B32Sfloat, vertices: &vb12, stride: 12, max_vertex: nv - 1, index_type: IndexType::None, indices: &[], transform: None } }),
        ];
        for (name, g) in &cases {
            if name.starts_with("u16") && nv > 65536 {
                continue;
            }
            for flags in [BuildFlags::PREFER_FAST_BUILD, 0, BuildFlags::PREFER_FAST_TRACE, BuildFlags::PREFER_FAST_BUILD | BuildFlags::ALLOW_UPDATE, BuildFlags::ALLOW_UPDATE] {
                for threads in [1, 2] {
                    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
                    let blas = pool.install(|| build_ok(AsType::BottomLevel, flags, &[*g], &NoDevice));
                    println!("digest {path} {name} flags {flags:#x} threads {threads}: {:016x} len {}", fnv(&blas), blas.len());
                }
            }
        }
    }
}

#[test]
fn build_timed_builds_the_same_structure() {
    // build_timed is build plus a clock: same report, same bytes; its phases are a
    // breakdown of its total (each non-negative, together no more than the total).
    let mesh = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).expect("mesh");
    let (vb, ib) = (mesh.vertex_bytes(), mesh.index_bytes());
    let g = tri_geom(&vb, mesh.vertex_count() as u32, &ib, mesh.triangle_count() as u32, GeometryFlags::OPAQUE);
    for flags in [BuildFlags::PREFER_FAST_TRACE, BuildFlags::PREFER_FAST_BUILD] {
        let sz = build_sizes(AsType::BottomLevel, BuildFlags(flags), &[shape_of(&g)], &[g.primitive_count]);
        let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(flags), geometries: &[g] };
        let run = |timed: bool| {
            let mut dst = vec![0u8; sz.acceleration_structure_size as usize];
            let mut scratch = vec![0u8; sz.build_scratch_size as usize];
            let (report, phases) = if timed {
                build_timed(&desc, &NoDevice, &mut dst, &mut scratch).expect("build_timed")
            } else {
                (build(&desc, &NoDevice, &mut dst, &mut scratch).expect("build"), BuildPhases::default())
            };
            (report, phases, dst[..report.used_size as usize].to_vec())
        };
        let (r0, _, b0) = run(false);
        let (r1, p, b1) = run(true);
        assert_eq!(r0, r1);
        assert!(b0 == b1, "build_timed changed the bytes");
        let parts = [p.ingest_ms, p.sah_ms, p.leaf_data_ms, p.nodes_ms];
        assert!(parts.iter().all(|&x| x >= 0.0), "{p:?}");
        assert!(parts.iter().sum::<f64>() <= p.total_ms + 1e-6, "{p:?}");
        assert!(p.total_ms > 0.0, "{p:?}");
    }
}

//! VK_NV_cluster_acceleration_structure at the library level (`arbor::accel::clas`, no device):
//! the bunny cut into clusters of at most 128 triangles and 128 vertices, built as CLASes and a
//! cluster BLAS, traverses like a KHR BLAS over the same truncated triangles and like brute
//! force; templates instantiated with new vertices equal direct builds; size bounds hold; moves
//! (byte copies) preserve traversal; a TLAS instances a cluster BLAS.
mod reference;

use arbor::accel::clas::{self, args::*, SizeInput};
use arbor::accel::{self, AsType, DeviceView, Hit, MapView, Ray, RayFlags};
use glam::Vec3;
use reference::brute_force::{reference as brute, RefScene};
use reference::TriData;

const INDEX_BASE: u64 = 0x1_0000_0000;
const VERTEX_BASE: u64 = 0x2_0000_0000;
const GEOMETRY_BASE: u64 = 0x3_0000_0000;

/// A mesh cut into clusters: consecutive triangles while a cluster has at most 128 triangles
/// and 128 distinct vertices; each cluster's local vertices and 16-bit local indices.
struct Cut {
    clusters: Vec<(Vec<[f32; 3]>, Vec<u16>)>,
}

fn cut(m: &arbor_scene::Mesh) -> Cut {
    let mut clusters = Vec::new();
    let (mut verts, mut idx, mut map) = (Vec::new(), Vec::new(), std::collections::HashMap::new());
    for t in &m.indices {
        let new = t.iter().filter(|i| !map.contains_key(*i)).count();
        if idx.len() / 3 == 128 || map.len() + new > 128 {
            clusters.push((std::mem::take(&mut verts), std::mem::take(&mut idx)));
            map.clear();
        }
        for &i in t {
            let l = *map.entry(i).or_insert_with(|| {
                verts.push(m.positions[i as usize]);
                verts.len() - 1
            });
            idx.push(l as u16);
        }
    }
    clusters.push((verts, idx));
    Cut { clusters }
}

/// Device memory of the cluster inputs (indices, vertices, per-triangle geometry words) and the
/// argument records of one BUILD_TRIANGLE_CLUSTER per cluster.
struct Inputs {
    view: MapView,
    records: Vec<BuildTriangleClusterInfo>,
}

/// Cluster k: ID 1000 + k, base geometry index k, flags (k % 8); odd clusters add a
/// per-triangle word (geometry index i % 3, flag OPAQUE on every third triangle).
fn inputs(c: &Cut, bits: u32, scale: f32) -> Inputs {
    let (mut ib, mut vb, mut gb, mut records) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (k, (v, i)) in c.clusters.iter().enumerate() {
        let t = i.len() as u32 / 3;
        let per_triangle = k % 2 == 1;
        records.push(BuildTriangleClusterInfo {
            cluster_id: 1000 + k as u32,
            cluster_flags: 0,
            counts: pack_counts(t, v.len() as u32, bits, 2, 0),
            base_geometry_index_and_geometry_flags: GeometryIndexAndFlags::new(k as u32, k as u32 % 8),
            index_buffer: INDEX_BASE + ib.len() as u64,
            vertex_buffer: VERTEX_BASE + vb.len() as u64,
            geometry_index_and_flags_buffer: if per_triangle { GEOMETRY_BASE + gb.len() as u64 } else { 0 },
            ..Default::default()
        });
        ib.extend(i.iter().flat_map(|x| x.to_le_bytes()));
        vb.extend(v.iter().flatten().flat_map(|x| (x * scale).to_le_bytes()));
        if per_triangle {
            gb.extend((0..t).flat_map(|j| GeometryIndexAndFlags::new(j % 3, if j % 3 == 0 { GeometryIndexAndFlags::OPAQUE } else { 0 }).0.to_le_bytes()));
        }
    }
    let mut view = MapView::new();
    view.insert(INDEX_BASE, ib);
    view.insert(VERTEX_BASE, vb);
    view.insert(GEOMETRY_BASE, gb);
    Inputs { view, records }
}

fn build_clases(inp: &Inputs) -> Vec<Vec<u8>> {
    inp.records
        .iter()
        .map(|r| {
            let mut dst = vec![0u8; clas::clas_size(r.triangle_count() as u64) as usize];
            let n = clas::build_clas(r, accel::VertexFormat::R32G32B32Sfloat, &inp.view, &mut dst).unwrap();
            assert_eq!(n as usize, dst.len());
            dst
        })
        .collect()
}

fn cluster_blas(clases: &[(u64, &[u8])]) -> Vec<u8> {
    let mut dst = vec![0u8; clas::blas_size_bound(clases.len() as u64) as usize];
    let n = clas::build_cluster_blas(clases, 0, &mut dst).unwrap();
    dst.truncate(n as usize);
    dst
}

/// What the application expects of one cluster triangle, written from the spec: truncated
/// positions, geometry index base + own, flags base | own.
struct Expected {
    tris: Vec<[Vec3; 3]>,
    /// (cluster ID, index in cluster, geometry index, geometry flags)
    facts: Vec<(i32, u32, u32, u32)>,
}

fn expected(c: &Cut, bits: u32, scale: f32) -> Expected {
    let tr = |x: f32| f32::from_bits(if bits >= 32 { 0 } else { (x * scale).to_bits() >> bits << bits });
    let mut e = Expected { tris: Vec::new(), facts: Vec::new() };
    for (k, (v, i)) in c.clusters.iter().enumerate() {
        for (j, t) in i.chunks(3).enumerate() {
            e.tris.push([0, 1, 2].map(|a| Vec3::from_array(v[t[a] as usize].map(tr))));
            let (own_g, own_f) = if k % 2 == 1 { (j as u32 % 3, if j % 3 == 0 { 4 } else { 0 }) } else { (0, 0) };
            e.facts.push((1000 + k as i32, j as u32, k as u32 + own_g, (k as u32 % 8) | own_f));
        }
    }
    e
}

fn khr_of(e: &Expected) -> TriData {
    let verts: Vec<u8> = e.tris.iter().flatten().flat_map(|v| v.to_array()).flat_map(f32::to_le_bytes).collect();
    TriData {
        vertices: verts,
        stride: 12,
        format: accel::VertexFormat::R32G32B32Sfloat,
        indices: Vec::new(),
        index_type: accel::IndexType::None,
        max_vertex: (3 * e.tris.len() as u32).saturating_sub(1),
        count: e.tris.len() as u32,
        transform: None,
        flags: 0,
    }
}

fn rays(b: [f32; 6], n: usize) -> Vec<Ray> {
    arbor_scene::primary_rays(b, n, n).into_iter().map(|r| Ray { origin: r.origin, direction: r.direction, tmin: 0.0, tmax: f32::INFINITY }).collect()
}

/// (cluster ID, index in cluster) → global triangle number, from the expected facts.
fn global(e: &Expected, h: &Hit) -> usize {
    e.facts.iter().position(|f| f.0 == h.cluster_id && f.1 == h.primitive_index).expect("hit names a cluster triangle")
}

/// Whether a cluster triangle with `facts` that brute force hits (facing `front`) is a
/// candidate for ray flags `f`, and whether it is opaque: the spec's rules with the cluster's
/// per-triangle flags (OPAQUE 4, CULL_DISABLE 1), written here from the extension's text.
fn cluster_rules(f: u32, facts: (i32, u32, u32, u32), front: bool) -> Option<bool> {
    let mut opaque = facts.3 & 4 != 0;
    if f & RayFlags::OPAQUE != 0 {
        opaque = true;
    } else if f & RayFlags::NO_OPAQUE != 0 {
        opaque = false;
    }
    if (opaque && f & RayFlags::CULL_OPAQUE != 0) || (!opaque && f & RayFlags::CULL_NO_OPAQUE != 0) {
        return None;
    }
    let culled = (f & RayFlags::CULL_BACK_FACING_TRIANGLES != 0 && !front) || (f & RayFlags::CULL_FRONT_FACING_TRIANGLES != 0 && front);
    (!culled || facts.3 & 1 != 0).then_some(opaque)
}

const RAY_FLAGS: [u32; 8] = [
    0,
    RayFlags::CULL_BACK_FACING_TRIANGLES,
    RayFlags::CULL_FRONT_FACING_TRIANGLES,
    RayFlags::OPAQUE,
    RayFlags::NO_OPAQUE,
    RayFlags::CULL_OPAQUE,
    RayFlags::CULL_NO_OPAQUE,
    RayFlags::CULL_BACK_FACING_TRIANGLES | RayFlags::CULL_OPAQUE,
];

/// Every candidate of the cluster BLAS along `rays` (ray flags in turn from RAY_FLAGS), mapped
/// to global triangles, against brute force over the expected triangles with the cluster rules
/// applied by hand; and with ray flags 0 the closest hit against a KHR BLAS over the same
/// triangles (t and vertices bit for bit). Returns the closest hits found.
/// A view holding each CLAS at its address (what a cluster BLAS resolves while traced).
fn view_of(clases: &[(u64, &[u8])]) -> MapView {
    let mut v = MapView::new();
    for &(a, b) in clases {
        v.insert(a, b.to_vec());
    }
    v
}

fn check_blas(blas: &[u8], view: &MapView, e: &Expected, rays: &[Ray], what: &str) -> usize {
    let khr_data = khr_of(e);
    let khr = reference::build_blas(0, &[khr_data.geometry()]);
    let geoms = [khr_data.geometry()];
    let scene = RefScene::Blas(&geoms);
    let mut hits = 0;
    for (n, &ray) in rays.iter().enumerate() {
        let flags = RAY_FLAGS[n % RAY_FLAGS.len()];
        let mut got: Vec<(usize, u32, bool)> = accel::all_hits(blas, view as &dyn DeviceView, ray, RayFlags(flags), 0xff)
            .iter()
            .map(|h| {
                let g = global(e, h);
                assert_eq!((h.geometry_index, h.cluster_id), (e.facts[g].2, e.facts[g].0), "{what} ray {n}");
                assert_eq!(h.vertices, e.tris[g], "{what} ray {n}: truncated positions");
                (g, h.t.to_bits(), h.opaque)
            })
            .collect();
        got.sort();
        let reference = brute(&scene, &ray, 0, 0xff);
        let mut want: Vec<(usize, u32, bool)> = reference
            .hits
            .iter()
            .filter_map(|r| {
                let g = r.id.primitive as usize;
                cluster_rules(flags, e.facts[g], r.front).map(|opaque| (g, r.t.to_bits(), opaque))
            })
            .collect();
        want.sort();
        assert_eq!(got, want, "{what} ray {n} flags {flags:#x}");
        if flags == 0 {
            // The KHR BLAS holds the same triangles, all non-opaque: compare t and the triangle.
            let a = accel::closest_hit(blas, view as &dyn DeviceView, ray, RayFlags(0), 0xff);
            let b = accel::closest_hit(&khr.bytes, &accel::NoDevice, ray, RayFlags(0), 0xff);
            assert_eq!(a.map(|h| h.t.to_bits()), b.map(|h| h.t.to_bits()), "{what} ray {n}");
            if let (Some(a), Some(b)) = (a, b) {
                assert_eq!(a.vertices, b.vertices, "{what} ray {n}");
                assert_eq!(a.cluster_id, e.facts[global(e, &a)].0);
                assert_eq!(b.cluster_id, -1);
                hits += 1;
            }
        }
    }
    hits
}

fn check_mesh(mesh: &arbor_scene::Mesh, rays_per_side: usize, what: &str) {
    let c = cut(mesh);
    for bits in [0, 9] {
        let inp = inputs(&c, bits, 1.0);
        let clases = build_clases(&inp);
        let addrs: Vec<(u64, &[u8])> = clases.iter().enumerate().map(|(k, b)| (0x10_0000 * (k as u64 + 1), b.as_slice())).collect();
        let blas = cluster_blas(&addrs);
        let e = expected(&c, bits, 1.0);
        let mut rays = rays(mesh.bounds(), rays_per_side);
        rays.extend(reference::random_rays(mesh.bounds(), rays.len() / 4, 7 + bits as u64));
        let hits = check_blas(&blas, &view_of(&addrs), &e, &rays, &format!("{what} bits {bits}"));
        assert!(hits > rays.len() / 40, "the rays must hit the {what} ({hits})");
    }
}

#[test]
fn cluster_blas_of_the_bunny_traverses_like_khr_blas_and_brute_force() {
    check_mesh(&arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).unwrap(), 48, "bunny");
}

#[test]
fn cluster_blas_of_the_dragon_traverses_like_khr_blas_and_brute_force() {
    check_mesh(&arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/dragon_vrip_res3.ply.gz")).unwrap(), 32, "dragon res3");
}

/// Clusters of random triangles: sizes from 0 to 256 triangles over up to 256 shared vertices,
/// some degenerate (a repeated index), in overlapping boxes.
fn random_cut(seed: u64, clusters: usize) -> Cut {
    let mut rng = arbor_scene::Rng::new(seed);
    let mut out = Vec::new();
    for k in 0..clusters {
        let t = match k % 5 {
            0 => 256,
            1 => 0,
            _ => 1 + rng.below(200) as usize,
        };
        let nv = (3 * t).clamp(3, 256);
        let centre = Vec3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0));
        let size = rng.range(0.1, 0.8);
        let verts: Vec<[f32; 3]> = (0..nv).map(|_| (centre + size * Vec3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0))).to_array()).collect();
        let mut idx = Vec::new();
        for j in 0..t {
            let mut tri = [0, 1, 2].map(|_| rng.below(nv as u32) as u16);
            if j % 17 == 5 {
                tri[2] = tri[0];
            }
            idx.extend(tri);
        }
        out.push((verts, idx));
    }
    Cut { clusters: out }
}

#[test]
fn cluster_blas_of_random_clusters_and_every_flag_traverses_like_brute_force() {
    for (seed, bits) in [(1u64, 0u32), (2, 5), (3, 17)] {
        let c = random_cut(seed, 23);
        let inp = inputs(&c, bits, 1.0);
        let clases = build_clases(&inp);
        let addrs: Vec<(u64, &[u8])> = clases.iter().enumerate().map(|(k, b)| (0x10_0000 * (k as u64 + 1), b.as_slice())).collect();
        let blas = cluster_blas(&addrs);
        // Deterministic: the same inputs give the same bytes.
        assert_eq!(blas, cluster_blas(&addrs));
        let e = expected(&c, bits, 1.0);
        let rays = reference::random_rays([-2.0, -2.0, -2.0, 2.0, 2.0, 2.0], 600, seed);
        let hits = check_blas(&blas, &view_of(&addrs), &e, &rays, &format!("random seed {seed}"));
        assert!(hits > 20, "{hits}");
    }
    // One cluster alone, and a BLAS of empty clusters only.
    let c = random_cut(4, 1);
    let clases = build_clases(&inputs(&c, 0, 1.0));
    let one = cluster_blas(&[(0x1000, clases[0].as_slice())]);
    check_blas(&one, &view_of(&[(0x1000, clases[0].as_slice())]), &expected(&c, 0, 1.0), &reference::random_rays([-2.0, -2.0, -2.0, 2.0, 2.0, 2.0], 200, 4), "one cluster");
    let c = Cut { clusters: vec![(Vec::new(), Vec::new()); 3] };
    let clases = build_clases(&inputs(&c, 0, 1.0));
    let empty = cluster_blas(&clases.iter().map(|b| (0x1000, b.as_slice())).collect::<Vec<_>>());
    let ray = Ray { origin: Vec3::ZERO, direction: Vec3::X, tmin: 0.0, tmax: f32::INFINITY };
    assert_eq!(accel::closest_hit(&empty, &accel::NoDevice, ray, RayFlags(0), 0xff), None);
    assert_eq!(accel::header(&empty).map(|h| h.primitive_count), Some(0));
}

/// CLAS builds, template instantiations and the cluster BLAS over them give the same bytes in
/// a pool of one thread and of several (clusters of every size share each thread's working
/// arrays in turn), and the same as built one by one on this thread.
#[test]
fn cluster_builds_do_not_depend_on_the_thread_count() {
    use rayon::prelude::*;
    let c = random_cut(5, 60);
    let (old, new) = (inputs(&c, 3, 1.0), inputs(&c, 3, 1.25));
    let f = accel::VertexFormat::R32G32B32Sfloat;
    let run = || -> (Vec<Vec<u8>>, Vec<Vec<u8>>, Vec<u8>) {
        let clases: Vec<Vec<u8>> = old.records.par_iter().map(|r| {
            let mut dst = vec![0u8; clas::clas_size(r.triangle_count() as u64) as usize];
            clas::build_clas(r, f, &old.view, &mut dst).unwrap();
            dst
        }).collect();
        let inst: Vec<Vec<u8>> = old.records.par_iter().zip(&new.records).map(|(r, n)| {
            let mut tpl = vec![0u8; clas::template_size(r.triangle_count() as u64, true) as usize];
            clas::build_template(r, f, None, &old.view, &mut tpl).unwrap();
            let a = InstantiateClusterInfo { vertex_buffer: StridedDeviceAddress { start_address: n.vertex_buffer, stride_in_bytes: 0 }, ..Default::default() };
            let mut dst = vec![0u8; clas::clas_size(r.triangle_count() as u64) as usize];
            clas::instantiate(&tpl, &a, &new.view, &mut dst).unwrap();
            dst
        }).collect();
        let addrs: Vec<(u64, &[u8])> = inst.iter().enumerate().map(|(k, b)| (0x10_0000 * (k as u64 + 1), b.as_slice())).collect();
        let blas = cluster_blas(&addrs);
        (clases, inst, blas)
    };
    let pool = |n: usize| rayon::ThreadPoolBuilder::new().num_threads(n).build().unwrap();
    let one = pool(1).install(run);
    assert_eq!(one, pool(4).install(run), "1 thread against 4");
    assert_eq!(one.0, build_clases(&old), "the pool's CLASes against one-by-one builds");
    // Instantiation with new vertices is the direct build of the new vertices.
    assert_eq!(one.1, build_clases(&new));
}

// One function: each case builds on the template of the case before.
#[test]
fn templates_instantiated_with_new_vertices_equal_direct_builds() {
    let mesh = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).unwrap();
    let c = cut(&mesh);
    let old = inputs(&c, 5, 1.0);
    let new = inputs(&c, 5, 1.5);
    for (k, r) in old.records.iter().enumerate().step_by(7) {
        for with_vertices in [false, true] {
            let mut rec = *r;
            if !with_vertices {
                rec.vertex_buffer = 0;
            }
            let mut tpl = vec![0u8; clas::template_size(rec.triangle_count() as u64, true) as usize];
            clas::build_template(&rec, accel::VertexFormat::R32G32B32Sfloat, None, &old.view, &mut tpl).unwrap();
            let offset = if k % 2 == 0 { -3 } else { 5 };
            let inst = InstantiateClusterInfo {
                cluster_id_offset: 77,
                geometry_word: InstantiateClusterInfo::pack_geometry_index_offset(offset),
                cluster_template_address: 0,
                vertex_buffer: StridedDeviceAddress { start_address: new.records[k].vertex_buffer, stride_in_bytes: 0 },
            };
            let mut got = vec![0u8; clas::clas_size(rec.triangle_count() as u64) as usize];
            clas::instantiate(&tpl, &inst, &new.view, &mut got).unwrap();
            // The direct build of the same cluster with the new vertices, ID and geometry base.
            let mut direct = new.records[k];
            direct.cluster_id += 77;
            let base = direct.base_geometry_index_and_geometry_flags;
            direct.base_geometry_index_and_geometry_flags = GeometryIndexAndFlags::new(base.geometry_index().wrapping_add_signed(offset), base.geometry_flags());
            let mut want = vec![0u8; got.len()];
            clas::build_clas(&direct, accel::VertexFormat::R32G32B32Sfloat, &new.view, &mut want).unwrap();
            assert_eq!(got, want, "cluster {k}, template with vertices {with_vertices}");
            if with_vertices {
                // vertexBuffer 0: the template's own (old) vertices.
                let inst0 = InstantiateClusterInfo { vertex_buffer: StridedDeviceAddress::default(), ..inst };
                let mut from_tpl = vec![0u8; got.len()];
                clas::instantiate(&tpl, &inst0, &new.view, &mut from_tpl).unwrap();
                let mut old_direct = *r;
                old_direct.cluster_id = direct.cluster_id;
                old_direct.base_geometry_index_and_geometry_flags = direct.base_geometry_index_and_geometry_flags;
                let mut want0 = vec![0u8; got.len()];
                clas::build_clas(&old_direct, accel::VertexFormat::R32G32B32Sfloat, &old.view, &mut want0).unwrap();
                assert_eq!(from_tpl, want0, "cluster {k}: instantiation from the template's vertices");
            } else {
                let inst0 = InstantiateClusterInfo { vertex_buffer: StridedDeviceAddress::default(), ..inst };
                assert_eq!(clas::instantiate(&tpl, &inst0, &new.view, &mut vec![0u8; got.len()]), Err(clas::ClusterError::NoVertices));
            }
            // The template gives back its indices in its own index type.
            let mut idx = vec![0u8; clas::template_indices_size(&tpl).unwrap() as usize];
            clas::template_indices(&tpl, &mut idx).unwrap();
            let want_idx: Vec<u8> = c.clusters[k].1.iter().flat_map(|x| x.to_le_bytes()).collect();
            assert_eq!(idx, want_idx);
        }
    }
}

#[test]
fn size_query_bounds_every_build() {
    let mesh = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).unwrap();
    let c = cut(&mesh);
    let inp = inputs(&c, 0, 1.0);
    let clases = build_clases(&inp);
    let total_tris: u32 = inp.records.iter().map(|r| r.triangle_count()).sum();
    let q = |op, mode| {
        clas::cluster_build_sizes(&SizeInput {
            op,
            mode,
            max_count: clases.len() as u32,
            max_cluster_triangles: 128,
            max_total_triangles: total_tris,
            max_total_clusters: clases.len() as u32,
            max_clusters_per_blas: clases.len() as u32,
            max_moved_bytes: 0,
            move_type: ObjectType::TriangleCluster,
        })
    };
    let one = q(OpType::BuildTriangleCluster, OpMode::ExplicitDestinations).acceleration_structure_size;
    let all = q(OpType::BuildTriangleCluster, OpMode::ImplicitDestinations).acceleration_structure_size;
    assert!(clases.iter().all(|b| b.len() as u64 <= one));
    assert!(clases.iter().map(|b| (b.len() as u64).next_multiple_of(clas::CLAS_ALIGNMENT)).sum::<u64>() <= all);
    let sizes = q(OpType::BuildTriangleCluster, OpMode::ComputeSizes);
    assert_eq!(sizes.acceleration_structure_size, 0);
    assert!(sizes.build_scratch_size > 0);
    // Cluster BLASes over every split of the clusters into 1..4 BLASes.
    let addrs: Vec<(u64, &[u8])> = clases.iter().enumerate().map(|(k, b)| (0x1000 * (k as u64 + 1), b.as_slice())).collect();
    for parts in 1..=4usize {
        let per = addrs.len().div_ceil(parts);
        let built: Vec<Vec<u8>> = addrs.chunks(per).map(cluster_blas).collect();
        let s = |mode| {
            clas::cluster_build_sizes(&SizeInput {
                op: OpType::BuildClustersBottomLevel,
                mode,
                max_count: built.len() as u32,
                max_cluster_triangles: 0,
                max_total_triangles: 0,
                max_total_clusters: addrs.len() as u32,
                max_clusters_per_blas: per as u32,
                max_moved_bytes: 0,
                move_type: ObjectType::ClustersBottomLevel,
            })
            .acceleration_structure_size
        };
        assert!(built.iter().all(|b| b.len() as u64 <= s(OpMode::ExplicitDestinations)));
        assert!(built.iter().map(|b| (b.len() as u64).next_multiple_of(clas::BLAS_ALIGNMENT)).sum::<u64>() <= s(OpMode::ImplicitDestinations));
    }
}

#[test]
fn moves_are_byte_copies_and_a_tlas_instances_a_cluster_blas() {
    let mesh = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).unwrap();
    let c = cut(&mesh);
    let inp = inputs(&c, 3, 1.0);
    let clases = build_clases(&inp);
    let at = |base: u64| -> Vec<(u64, &[u8])> { clases.iter().enumerate().map(|(k, b)| (base + 0x1000 * k as u64, b.as_slice())).collect() };
    let blas = cluster_blas(&at(0x10_0000));
    // The CLASes moved elsewhere: the rebuilt BLAS differs only in its reference table.
    let moved = cluster_blas(&at(0x90_0000));
    assert_eq!(clas::cluster_references(&moved).unwrap()[1], 0x90_1000);
    let table = clas::HEADER_SIZE as usize..clas::HEADER_SIZE as usize + 8 * clases.len();
    assert_eq!(blas[..table.start], moved[..table.start]);
    assert_eq!(blas[table.end..], moved[table.end..]);
    // A moved cluster BLAS (copied to an unaligned place) traverses the same.
    let mut shifted = vec![0xAAu8; blas.len() + 3];
    shifted[3..].copy_from_slice(&blas);
    let e = expected(&c, 3, 1.0);
    let mut view = view_of(&at(0x10_0000));
    view.insert(0x4000_0000, blas.clone());
    let instance = arbor_scene::InstanceRecord {
        transform: [1.0, 0.0, 0.0, 5.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        custom_index: 9,
        mask: 0xff,
        sbt_offset: 0,
        flags: 0,
        reference: 0x4000_0000,
    };
    let inst_bytes = arbor_scene::InstanceRecord::pack(&[instance]);
    let tlas_geom = accel::Geometry { flags: accel::GeometryFlags(0), primitive_count: 1, data: accel::GeometryData::Instances { array_of_pointers: false, data: &inst_bytes } };
    let tlas = reference::build(AsType::TopLevel, 0, &[tlas_geom], &view);
    let mut n_hits = 0;
    for ray in rays(mesh.bounds(), 24) {
        let a = accel::closest_hit(&blas, &view as &dyn DeviceView, ray, RayFlags(0), 0xff);
        let b = accel::closest_hit(&shifted[3..], &view as &dyn DeviceView, ray, RayFlags(0), 0xff);
        assert_eq!(a, b);
        let shifted_ray = Ray { origin: ray.origin + Vec3::new(5.0, 0.0, 0.0), ..ray };
        let t = accel::closest_hit(&tlas.bytes, &view as &dyn DeviceView, shifted_ray, RayFlags(0), 0xff);
        assert_eq!(a.map(|h| (h.cluster_id, h.primitive_index, h.geometry_index)), t.map(|h| (h.cluster_id, h.primitive_index, h.geometry_index)));
        if let Some(h) = t {
            assert_eq!(h.instance_custom_index, 9);
            assert_eq!(e.facts[global(&e, &h)].2, h.geometry_index);
            n_hits += 1;
        }
    }
    assert!(n_hits > 50);
    assert_eq!(accel::header(&blas).map(|h| (h.ty, h.used_size)), Some((AsType::BottomLevel, blas.len() as u64)));
}

/// A cluster BLAS names its CLASes by address: with one freed and one overwritten after the
/// build, tracing skips those two clusters (hits elsewhere as with all CLASes alive), a ray
/// query that reaches one reports its address, and nothing panics.
#[test]
fn a_freed_or_overwritten_clas_is_a_contained_fault() {
    let c = random_cut(6, 12);
    let clases = build_clases(&inputs(&c, 0, 1.0));
    let addrs: Vec<(u64, &[u8])> = clases.iter().enumerate().map(|(k, b)| (0x10_0000 * (k as u64 + 1), b.as_slice())).collect();
    let blas = cluster_blas(&addrs);
    let (freed, garbage) = (2usize, 5usize);
    let mut view = MapView::new();
    for (k, &(a, b)) in addrs.iter().enumerate() {
        match k {
            _ if k == freed => {}
            _ if k == garbage => view.insert(a, vec![0xA5; b.len()]),
            _ => view.insert(a, b.to_vec()),
        }
    }
    let full = view_of(&addrs);
    let gone = [freed, garbage].map(|k| clas::open(&clases[k]).unwrap().header.cluster_id as i32);
    let keys = |v: &MapView, ray: Ray, keep: &dyn Fn(i32) -> bool| -> Vec<(i32, u32, u32)> {
        let mut k: Vec<_> = accel::all_hits(&blas, v as &dyn DeviceView, ray, RayFlags(0), 0xff).iter().filter(|h| keep(h.cluster_id)).map(|h| (h.cluster_id, h.primitive_index, h.t.to_bits())).collect();
        k.sort();
        k
    };
    let mut faults = 0;
    for (n, ray) in reference::random_rays([-2.0, -2.0, -2.0, 2.0, 2.0, 2.0], 400, 6).into_iter().enumerate() {
        let alive = |id: i32| !gone.contains(&id);
        assert_eq!(keys(&view, ray, &|_| true), keys(&full, ray, &alive), "ray {n}");
        let mut q = accel::RayQuery::new(&blas, &view, ray, RayFlags(0), 0xff);
        while q.proceed().is_some() {
            q.confirm();
        }
        // The closest hit of the intact BLAS in a lost cluster: its CLAS's root lies nearer than
        // every other hit, so the query reaches it.
        if accel::closest_hit(&blas, &full as &dyn DeviceView, ray, RayFlags(0), 0xff).is_some_and(|h| !alive(h.cluster_id)) {
            let lost = [addrs[freed].0, addrs[garbage].0];
            assert!(q.unresolved_reference().is_some_and(|a| lost.contains(&a)), "ray {n}: {:?}", q.unresolved_reference());
            faults += 1;
        }
    }
    assert!(faults > 5, "{faults}");
}

/// Instances of two cluster BLASes as (transform, custom index, BLAS address).
fn placements(a: u64, b: u64) -> Vec<([f32; 12], u32, u64)> {
    vec![
        ([1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0], 1, a),
        ([1.0, 0.0, 0.0, 0.3, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.05], 2, a),
        ([0.0, -1.5, 0.0, -0.1, 1.5, 0.0, 0.0, 0.1, 0.0, 0.0, 1.5, 0.0], 3, b),
    ]
}

fn khr_tlas(p: &[([f32; 12], u32, u64)], view: &MapView) -> Vec<u8> {
    let records: Vec<arbor_scene::InstanceRecord> =
        p.iter().map(|&(transform, custom_index, reference)| arbor_scene::InstanceRecord { transform, custom_index, mask: 0xff, sbt_offset: 0, flags: 0, reference }).collect();
    let bytes = arbor_scene::InstanceRecord::pack(&records);
    let g = accel::Geometry { flags: accel::GeometryFlags(0), primitive_count: p.len() as u32, data: accel::GeometryData::Instances { array_of_pointers: false, data: &bytes } };
    reference::build(AsType::TopLevel, 0, &[g], view).bytes
}

fn ptlas_of(p: &[([f32; 12], u32, u64)], view: &MapView) -> Vec<u8> {
    use arbor::accel::ptlas;
    let writes: Vec<ptlas::WriteInstance> = p
        .iter()
        .enumerate()
        .map(|(k, &(transform, id, blas))| ptlas::WriteInstance {
            transform,
            explicit_aabb: [0.0; 6],
            instance_id: id,
            instance_mask: 0xff,
            instance_contribution_to_hit_group_index: 0,
            instance_flags: 0,
            instance_index: k as u32,
            partition_index: k as u32 % 2,
            acceleration_structure: blas,
        })
        .collect();
    let input = ptlas::Input { flags: 0, instance_count: 4, max_instance_per_partition_count: 4, partition_count: 2, max_instance_in_global_partition_count: 1, translation: false };
    let sizes = ptlas::build_sizes(&input);
    let (mut dst, mut scratch) = (vec![0u8; sizes.acceleration_structure_size as usize], vec![0u8; sizes.build_scratch_size as usize]);
    let ops = ptlas::Ops { writes: ptlas::Strided { data: bytemuck::cast_slice(&writes), count: writes.len() as u32, stride: 0 }, ..Default::default() };
    ptlas::build(&input, &ops, view, ptlas::Source::Empty, &mut dst, &mut scratch).unwrap();
    dst
}

type HitKey = (u32, u32, i32, u32, u32, u32, bool);

fn hit_keys(top: &[u8], view: &MapView, ray: Ray, flags: u32) -> Vec<HitKey> {
    let mut v: Vec<HitKey> = accel::all_hits(top, view as &dyn DeviceView, ray, RayFlags(flags), 0xff)
        .iter()
        .map(|h| (h.instance_index, h.instance_custom_index, h.cluster_id, h.primitive_index, h.geometry_index, h.t.to_bits(), h.opaque))
        .collect();
    v.sort();
    v
}

// One function: the moved copies are checked against the structures built before the move.
#[test]
fn a_khr_tlas_and_a_ptlas_over_cluster_blases_trace_alike_before_and_after_moves() {
    let mesh = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).unwrap();
    let c = cut(&mesh);
    let inp = inputs(&c, 2, 1.0);
    let clases = build_clases(&inp);
    let half = clases.len() / 2;
    let at = |r: std::ops::Range<usize>| -> Vec<(u64, &[u8])> { clases[r.clone()].iter().enumerate().map(|(k, b)| (0x10_0000 + 0x1000 * (r.start + k) as u64, b.as_slice())).collect() };
    let (blas_a, blas_b) = (cluster_blas(&at(0..half)), cluster_blas(&at(half..clases.len())));
    let (addr_a, addr_b) = (0x4000_0000u64, 0x5000_0000u64);
    let mut view = view_of(&at(0..clases.len()));
    view.insert(addr_a, blas_a.clone());
    view.insert(addr_b, blas_b.clone());
    let p = placements(addr_a, addr_b);
    let (tlas, pt) = (khr_tlas(&p, &view), ptlas_of(&p, &view));
    // MOVE_OBJECTS is a byte copy: the BLASes at new addresses, the tops rebuilt over them.
    let (moved_a, moved_b) = (0x6000_0040u64, 0x6100_0000u64);
    let mut moved = view_of(&at(0..clases.len()));
    moved.insert(moved_a, blas_a.clone());
    moved.insert(moved_b, blas_b.clone());
    let q = placements(moved_a, moved_b);
    let (tlas2, pt2) = (khr_tlas(&q, &moved), ptlas_of(&q, &moved));
    let e = expected(&c, 2, 1.0);
    let b = mesh.bounds();
    let wide = [b[0] - 0.2, b[1] - 0.2, b[2] - 0.2, b[3] + 0.4, b[4] + 0.2, b[5] + 0.2];
    let mut hits = 0;
    for (n, ray) in reference::random_rays(wide, 400, 11).into_iter().enumerate() {
        let flags = RAY_FLAGS[n % RAY_FLAGS.len()];
        let want = hit_keys(&tlas, &view, ray, flags);
        assert_eq!(hit_keys(&pt, &view, ray, flags), want, "PTLAS ray {n}");
        assert_eq!(hit_keys(&tlas2, &moved, ray, flags), want, "moved, KHR TLAS ray {n}");
        assert_eq!(hit_keys(&pt2, &moved, ray, flags), want, "moved, PTLAS ray {n}");
        // The first instance is the identity: its hits are the BLAS's own.
        let own: Vec<HitKey> = hit_keys(&blas_a, &view_of(&at(0..half)), ray, flags).into_iter().map(|k| (0, 1, k.2, k.3, k.4, k.5, k.6)).collect();
        let first: Vec<HitKey> = want.iter().filter(|k| k.0 == 0).copied().collect();
        assert_eq!(first, own, "instance 0 ray {n}");
        for k in &want {
            let f = e.facts.iter().find(|f| f.0 == k.2 && f.1 == k.3).expect("a hit names a cluster triangle");
            assert_eq!(f.2, k.4);
        }
        hits += want.len();
    }
    assert!(hits > 100, "{hits}");
}

/// Throughput figures (not a test of speed: it asserts nothing about time). Run with
/// `cargo test --release --test clas_library -- --ignored --nocapture`.
#[test]
#[ignore]
fn figures() {
    let mesh = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).unwrap();
    let c = cut(&mesh);
    let inp = inputs(&c, 0, 1.0);
    let reps = 20;
    let t = std::time::Instant::now();
    let mut clases = Vec::new();
    for _ in 0..reps {
        clases = build_clases(&inp);
    }
    let clas_s = t.elapsed().as_secs_f64() / reps as f64;
    let tpls: Vec<Vec<u8>> = inp
        .records
        .iter()
        .map(|r| {
            let mut d = vec![0u8; clas::template_size(r.triangle_count() as u64, false) as usize];
            clas::build_template(&BuildTriangleClusterInfo { vertex_buffer: 0, ..*r }, accel::VertexFormat::R32G32B32Sfloat, None, &inp.view, &mut d).unwrap();
            d
        })
        .collect();
    let t = std::time::Instant::now();
    for _ in 0..reps {
        for (tpl, r) in tpls.iter().zip(&inp.records) {
            let inst = InstantiateClusterInfo { vertex_buffer: StridedDeviceAddress { start_address: r.vertex_buffer, stride_in_bytes: 12 }, ..Default::default() };
            let mut d = vec![0u8; clas::clas_size(r.triangle_count() as u64) as usize];
            clas::instantiate(tpl, &inst, &inp.view, &mut d).unwrap();
        }
    }
    let inst_s = t.elapsed().as_secs_f64() / reps as f64;
    let addrs: Vec<(u64, &[u8])> = clases.iter().enumerate().map(|(k, b)| (0x1000 * (k as u64 + 1), b.as_slice())).collect();
    let t = std::time::Instant::now();
    for _ in 0..reps {
        cluster_blas(&addrs);
    }
    let blas_s = t.elapsed().as_secs_f64() / reps as f64;
    let khr_data = khr_of(&expected(&c, 0, 1.0));
    let geoms = [khr_data.geometry()];
    let sizes = accel::build_sizes(AsType::BottomLevel, accel::BuildFlags(0), &[reference::shape_of(&geoms[0])], &[khr_data.count]);
    let (mut dst, mut scratch) = (vec![0u8; sizes.acceleration_structure_size as usize], vec![0u8; sizes.build_scratch_size as usize]);
    let desc = accel::BuildDesc { ty: AsType::BottomLevel, flags: accel::BuildFlags(0), geometries: &geoms };
    let t = std::time::Instant::now();
    for _ in 0..reps {
        accel::build(&desc, &accel::NoDevice, &mut dst, &mut scratch).unwrap();
    }
    let khr_s = t.elapsed().as_secs_f64() / reps as f64;
    let n = clases.len() as f64;
    println!("bunny: {} triangles in {} clusters (threads: {})", mesh.indices.len(), clases.len(), rayon::current_num_threads());
    println!("CLAS builds: {:.0}/s ({:.2} ms for all, one thread)", n / clas_s, clas_s * 1e3);
    println!("template instantiations: {:.0}/s ({:.2} ms for all, one thread)", n / inst_s, inst_s * 1e3);
    println!("cluster BLAS over all CLASes: {:.2} ms; instantiate + cluster BLAS: {:.2} ms", blas_s * 1e3, (inst_s + blas_s) * 1e3);
    println!("KHR BLAS build of the same triangles: {:.2} ms", khr_s * 1e3);
}

//! Where a TLAS build's time goes: the `instances` scene of arbor-bench (10,000 instances over
//! three BLASes: the bunny, a 64² terrain, 4,096 random triangles) built through the library
//! ARBOR_REPS times per tier and thread count; prints the fastest and median total and the
//! phases of the fastest build (`build_timed`) and a digest of the bytes (to compare commits
//! that should keep them), and checks that every thread count gives the same bytes.
//!
//!   cargo run --release --example tlas_phases
//!   ARBOR_THREADS=1,2      thread counts (default 1,2)
//!   ARBOR_TIER=FAST_BUILD  only this tier (FAST_BUILD, default or FAST_TRACE)
//!   ARBOR_REPS=N           builds per measurement (default 200)
//!   ARBOR_INSTANCES=N      instances (default 10000)
use arbor::accel::{self, AsType, BuildDesc, BuildFlags, Geometry, GeometryData, GeometryFlags, GeometryShape, IndexType, MapView, NoDevice, VertexFormat};

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|s| s.parse().ok()).unwrap_or(default)
}

/// The mesh scaled into the unit cube (as arbor-bench's `normalized`).
fn normalized(mesh: &arbor_scene::Mesh) -> arbor_scene::Mesh {
    let b = mesh.bounds();
    let ext = (b[3] - b[0]).max(b[4] - b[1]).max(b[5] - b[2]).max(1e-20);
    let positions = mesh.positions.iter().map(|p| [(p[0] - b[0]) / ext, (p[1] - b[1]) / ext, (p[2] - b[2]) / ext]).collect();
    arbor_scene::Mesh { positions, indices: mesh.indices.clone() }
}

fn blas(mesh: &arbor_scene::Mesh) -> Vec<u8> {
    let (vb, ib) = (mesh.vertex_bytes(), mesh.index_bytes());
    let data = GeometryData::Triangles { format: VertexFormat::R32G32B32Sfloat, vertices: &vb, stride: 12, max_vertex: mesh.vertex_count() as u32 - 1, index_type: IndexType::U32, indices: &ib, transform: None };
    let g = Geometry { flags: GeometryFlags(GeometryFlags::OPAQUE), primitive_count: mesh.triangle_count() as u32, data };
    let shape = GeometryShape::Triangles { format: VertexFormat::R32G32B32Sfloat, index_type: IndexType::U32, max_vertex: 0, has_transform: false };
    let sz = accel::build_sizes(AsType::BottomLevel, BuildFlags(0), &[shape], &[g.primitive_count]);
    let (mut dst, mut scratch) = (vec![0u8; sz.acceleration_structure_size as usize], vec![0u8; sz.build_scratch_size as usize]);
    accel::build(&BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(0), geometries: &[g] }, &NoDevice, &mut dst, &mut scratch).expect("BLAS build");
    dst
}

fn main() {
    let bunny = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).expect("bunny");
    let meshes = [normalized(&bunny), arbor_scene::terrain(64), arbor_scene::random_soup(4096, 7)];
    let mut view = MapView::new();
    let addresses = [0x1000_0000u64, 0x2000_0000, 0x3000_0000];
    for (m, &a) in meshes.iter().zip(&addresses) {
        view.insert(a, blas(m));
    }
    let n: usize = env_or("ARBOR_INSTANCES", 10_000);
    let records = arbor_scene::InstanceRecord::pack(&arbor_scene::instance_records(n, &addresses, 1));
    let g = Geometry { flags: GeometryFlags(0), primitive_count: n as u32, data: GeometryData::Instances { array_of_pointers: false, data: &records } };
    let reps: usize = env_or("ARBOR_REPS", 200).max(1);
    let only = std::env::var("ARBOR_TIER").ok();
    let threads: Vec<usize> = std::env::var("ARBOR_THREADS").ok().map(|s| s.split(',').filter_map(|x| x.trim().parse().ok()).collect()).unwrap_or(vec![1, 2]);
    for (name, flags) in [("FAST_BUILD", BuildFlags::PREFER_FAST_BUILD), ("default", 0), ("FAST_TRACE", BuildFlags::PREFER_FAST_TRACE)] {
        if only.as_deref().is_some_and(|o| o != name) {
            continue;
        }
        let flags = BuildFlags(flags);
        let sz = accel::build_sizes(AsType::TopLevel, flags, &[GeometryShape::Instances], &[n as u32]);
        let (mut dst, mut scratch) = (vec![0u8; sz.acceleration_structure_size as usize], vec![0u8; sz.build_scratch_size as usize]);
        let desc = BuildDesc { ty: AsType::TopLevel, flags, geometries: &[g] };
        let mut first: Option<Vec<u8>> = None;
        for &t in &threads {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().expect("pool");
            let mut runs = Vec::with_capacity(reps);
            let mut used = 0;
            pool.install(|| {
                for _ in 0..reps {
                    let (report, phases) = accel::build_timed(&desc, &view, &mut dst, &mut scratch).expect("TLAS build");
                    used = report.used_size as usize;
                    runs.push(phases);
                }
            });
            match &first {
                Some(f) => assert!(f[..] == dst[..used], "{name}: {t} threads gave other bytes"),
                None => first = Some(dst[..used].to_vec()),
            }
            runs.sort_by(|a, b| a.total_ms.total_cmp(&b.total_ms));
            let (best, median) = (&runs[0], runs[reps / 2].total_ms);
            let sah = accel::header(&dst).map_or(0.0, |h| h.sah_cost);
            // FNV-1a of the used bytes: equal across commits when a change keeps the bytes.
            let digest = dst[..used].iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3));
            println!(
                "{name:10} T={t}: min {:.3} ms, median {median:.3} ms | fastest: ingest {:.3}, tree {:.3}, leaf data {:.3}, nodes (TLAS: and sections, checksum parts) {:.3}, header {:.3} | SAH {sah:.2}, {used} B, bytes {digest:016x}",
                best.total_ms,
                best.ingest_ms,
                best.sah_ms,
                best.leaf_data_ms,
                best.nodes_ms,
                best.total_ms - best.ingest_ms - best.sah_ms - best.leaf_data_ms - best.nodes_ms
            );
        }
    }
}

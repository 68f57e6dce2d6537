//! What the integrity checksum costs a build: one-thread FAST_BUILD of a mesh (default the full
//! dragon) against the checksum of the finished structure on one thread (minimum of ARBOR_REPS
//! runs each). The build already includes its checksum; the figure is the share of it.
//!
//!   cargo bench --bench checksum_cost
//!   ARBOR_MESH=path  ARBOR_REPS=N (default 3)
use arbor::accel::{self, AsType, BuildDesc, BuildFlags, Geometry, GeometryData, GeometryFlags, IndexType, NoDevice, VertexFormat};
use std::time::Instant;

fn main() {
    let path = std::env::var("ARBOR_MESH").unwrap_or_else(|_| format!("{}/data/dragon_vrip.ply.gz", env!("CARGO_MANIFEST_DIR")));
    let reps: usize = std::env::var("ARBOR_REPS").ok().and_then(|s| s.parse().ok()).unwrap_or(3);
    let mesh = arbor_scene::load(&path).expect("mesh");
    let (vb, ib) = (mesh.vertex_bytes(), mesh.index_bytes());
    let data = GeometryData::Triangles { format: VertexFormat::R32G32B32Sfloat, vertices: &vb, stride: 12, max_vertex: mesh.vertex_count() as u32 - 1, index_type: IndexType::U32, indices: &ib, transform: None };
    let g = [Geometry { flags: GeometryFlags(GeometryFlags::OPAQUE), primitive_count: mesh.triangle_count() as u32, data }];
    let flags = BuildFlags(BuildFlags::PREFER_FAST_BUILD);
    let shape = accel::GeometryShape::Triangles { format: VertexFormat::R32G32B32Sfloat, index_type: IndexType::U32, max_vertex: 0, has_transform: false };
    let sz = accel::build_sizes(AsType::BottomLevel, flags, &[shape], &[g[0].primitive_count]);
    let (mut dst, mut scratch) = (vec![0u8; sz.acceleration_structure_size as usize], vec![0u8; sz.build_scratch_size as usize]);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let desc = BuildDesc { ty: AsType::BottomLevel, flags, geometries: &g };
    let mut build_ms = f64::MAX;
    let mut used = 0;
    for _ in 0..reps {
        let t = Instant::now();
        used = pool.install(|| accel::build(&desc, &NoDevice, &mut dst, &mut scratch)).expect("build").used_size;
        build_ms = build_ms.min(t.elapsed().as_secs_f64() * 1e3);
    }
    let mut sum_ms = f64::MAX;
    for _ in 0..reps.max(5) {
        let t = Instant::now();
        let c = pool.install(|| accel::structure_checksum(&dst));
        sum_ms = sum_ms.min(t.elapsed().as_secs_f64() * 1e3);
        assert!(c.is_some());
    }
    println!(
        "{} triangles, {used} bytes: FAST_BUILD on 1 thread {build_ms:.1} ms, checksum {sum_ms:.2} ms ({:.2} % of the build, {:.1} GB/s)",
        g[0].primitive_count,
        100.0 * sum_ms / build_ms,
        used as f64 / sum_ms / 1e6
    );
}

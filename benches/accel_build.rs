//! Build throughput (Mprims/s) of Arbor on the full Stanford dragon (871,414 triangles) and a
//! 1M random soup, FAST_TRACE and FAST_BUILD, 1 thread and all threads; SAH cost and bytes per
//! triangle printed beside. With `--features peers`, Embree 3 (rtcBuildBVH LOW/MEDIUM/HIGH,
//! binary, leaves 1–8) and obvhs (PLOC) are measured in the same run.
//!
//!   cargo bench --bench accel_build [--features peers] -- [filter]
//!   ARBOR_DATA_DIR=dir   where dragon_vrip.ply.gz is (default: data/ of the checkout)
//!   ARBOR_BENCH_SECS=N   measurement time per benchmark (default 3; 10 samples minimum)
//!   ARBOR_BENCH_SCENES=dragon,soup  which scenes (default both)
//!   ARBOR_BENCH_THREADS=1,4,16      thread counts (default: 1 and all)
//!   ARBOR_BENCH_PEERS=embree,obvhs  which peers with --features peers (default both)
//!   ARBOR_BENCH_EMBREE=low,medium,high,scene_low,scene_medium  which Embree builds (default:
//!                    the generic builder at all three qualities and the MEDIUM scene commit)

#[cfg(feature = "peers")]
mod peers;

use arbor::accel::{self, AsType, BuildDesc, BuildFlags, Geometry, GeometryData, GeometryFlags, IndexType, VertexFormat};
use arbor_scene::{self as scene, Mesh};
use criterion::{criterion_group, criterion_main, Criterion, SamplingMode, Throughput};
use std::time::Duration;

/// data/ of the checkout; ARBOR_DATA_DIR overrides it (a bench binary run on another machine).
fn data_dir() -> std::path::PathBuf {
    std::env::var_os("ARBOR_DATA_DIR").map(Into::into).unwrap_or_else(|| std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data"))
}

fn secs() -> u64 {
    std::env::var("ARBOR_BENCH_SECS").ok().and_then(|s| s.parse().ok()).unwrap_or(3)
}

fn scenes() -> Vec<(&'static str, Mesh)> {
    let want = std::env::var("ARBOR_BENCH_SCENES").unwrap_or_else(|_| "dragon,soup".into());
    let mut out = Vec::new();
    if want.contains("dragon") {
        let path = data_dir().join("dragon_vrip.ply.gz");
        out.push(("dragon", scene::load(path).expect("data/dragon_vrip.ply.gz")));
    }
    if want.contains("soup") {
        out.push(("soup1M", scene::random_soup(1_000_000, 1)));
    }
    out
}

struct Input {
    vertices: Vec<u8>,
    indices: Vec<u8>,
    max_vertex: u32,
    count: u32,
}

impl Input {
    fn geometry(&self) -> Geometry<'_> {
        Geometry {
            flags: GeometryFlags(1),
            primitive_count: self.count,
            data: GeometryData::Triangles {
                format: VertexFormat::R32G32B32Sfloat,
                vertices: &self.vertices,
                stride: 12,
                max_vertex: self.max_vertex,
                index_type: IndexType::U32,
                indices: &self.indices,
                transform: None,
            },
        }
    }
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap()
}

fn bench_build(c: &mut Criterion) {
    let all = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let thread_counts: Vec<usize> = match std::env::var("ARBOR_BENCH_THREADS") {
        Ok(list) => list.split(',').filter_map(|t| t.trim().parse().ok()).collect(),
        Err(_) if all > 1 => vec![1, all],
        Err(_) => vec![1],
    };
    for (name, mesh) in scenes() {
        let n = mesh.indices.len();
        let input = Input { vertices: mesh.vertex_bytes(), indices: mesh.index_bytes(), max_vertex: mesh.max_index(), count: n as u32 };
        let geoms = [input.geometry()];
        let mut group = c.benchmark_group(format!("build/{name}"));
        group.throughput(Throughput::Elements(n as u64));
        group.sample_size(10);
        group.sampling_mode(SamplingMode::Flat);
        group.warm_up_time(Duration::from_secs(1));
        group.measurement_time(Duration::from_secs(secs()));
        println!("\n{name}: {n} triangles, {} vertices", mesh.positions.len());
        for (tier_name, tier) in [("fast_trace", BuildFlags::PREFER_FAST_TRACE), ("fast_build", BuildFlags::PREFER_FAST_BUILD)] {
            let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(tier), geometries: &geoms };
            let sizes = accel::build_sizes(AsType::BottomLevel, BuildFlags(tier), &[accel::GeometryShape::Triangles {
                format: VertexFormat::R32G32B32Sfloat,
                index_type: IndexType::U32,
                max_vertex: input.max_vertex,
                has_transform: false,
            }], &[n as u32]);
            let mut dst = vec![0u8; sizes.acceleration_structure_size as usize];
            let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
            for &threads in &thread_counts {
                let p = pool(threads);
                let report = p.install(|| accel::build(&desc, &accel::NoDevice, &mut dst, &mut scratch)).expect("build");
                let m = accel::metrics(&dst).expect("metrics");
                println!(
                    "arbor {tier_name} {threads}t: SAH {:.2} (wide {:.2}), {:.1} B/tri used ({:.1} B/tri size query), {} nodes, {} leaves, depth {}",
                    m.sah_cost,
                    m.wide_sah_cost,
                    report.used_size as f64 / n as f64,
                    sizes.acceleration_structure_size as f64 / n as f64,
                    m.node_count,
                    m.leaf_count,
                    m.max_depth
                );
                group.bench_function(format!("arbor/{tier_name}/{threads}t"), |b| {
                    b.iter(|| p.install(|| accel::build(&desc, &accel::NoDevice, &mut dst, &mut scratch)).expect("build"))
                });
            }
        }
        #[cfg(feature = "peers")]
        peer_benches(&mut group, &mesh, &thread_counts);
        group.finish();
    }
}

#[cfg(feature = "peers")]
fn peer_benches(group: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>, mesh: &Mesh, thread_counts: &[usize]) {
    use peers::{embree, obvhs_peer};
    let n = mesh.indices.len();
    let want = std::env::var("ARBOR_BENCH_PEERS").unwrap_or_else(|_| "embree,obvhs".into());
    let builds = std::env::var("ARBOR_BENCH_EMBREE").unwrap_or_else(|_| "low,medium,high,scene_medium".into());
    let wanted = |name: &str| builds.split(',').any(|b| b.trim() == name);
    let prims = embree::primitives(mesh, 2 * n);
    for &threads in thread_counts.iter().filter(|_| want.contains("embree")) {
        let dev = embree::Device::new(threads);
        for (qname, q) in [("low", 0u32), ("medium", 1), ("high", 2)].into_iter().filter(|(q, _)| wanted(q)) {
            let mut copy = prims.clone();
            let sah = dev.build(q, mesh, &mut copy, n).sah();
            println!("embree {qname} {threads}t: SAH {sah:.2}");
            group.bench_function(format!("embree/{qname}/{threads}t"), |b| {
                // Primitive copy (setup) and BVH release (output drop) are outside the timing.
                b.iter_batched_ref(|| prims.clone(), |p| dev.build(q, mesh, p, n), criterion::BatchSize::PerIteration)
            });
        }
        // Embree's own scene build (its BVH8 for tracing: LOW is its Morton builder, MEDIUM
        // its binned SAH builder); SAH not exposed. Includes copying the mesh into the shared
        // buffers (a few ms).
        for (qname, q) in [("low", 0u32), ("medium", 1)].into_iter().filter(|(q, _)| wanted(&format!("scene_{q}"))) {
            group.bench_function(format!("embree/scene_commit_{qname}/{threads}t"), |b| b.iter_with_large_drop(|| embree::Scene::new(&dev, mesh, q)));
        }
    }
    let tris = obvhs_peer::triangles(mesh);
    for &threads in thread_counts.iter().filter(|_| want.contains("obvhs")) {
        let p = pool(threads);
        let bvh = p.install(|| obvhs_peer::build(&tris));
        println!("obvhs ploc-fastest {threads}t: SAH {:.2}", obvhs_peer::sah(&bvh));
        drop(bvh);
        group.bench_function(format!("obvhs/ploc_fastest/{threads}t"), |b| b.iter_with_large_drop(|| p.install(|| obvhs_peer::build(&tris))));
    }
}

criterion_group!(benches, bench_build);
criterion_main!(benches);

//! Where a build's time goes, per tier and thread count (a bench binary, not criterion): the
//! wall time (minimum and median) and the process CPU time of ARBOR_REPS builds of one mesh,
//! the mean of each phase `build_timed` reports (ingest, tree, leaf data, nodes), and the
//! structure's SAH and size. Then the small-build hand-off: the same small build inside an
//! N-thread pool's `install` from a foreign thread against on a thread that is itself a
//! one-thread pool's worker (as the driver's queue threads are).
//!
//!   cargo bench --bench accel_phases
//!   ARBOR_MESH=path        the mesh of the phase runs (default data/dragon_vrip.ply.gz)
//!   ARBOR_SMALL_MESH=path  the mesh of the hand-off runs (default data/bunny.ply)
//!   ARBOR_THREADS=1,2,4    thread counts of the phase runs (default 1,2)
//!   ARBOR_TIER=FAST_BUILD  only this tier (FAST_BUILD, default or FAST_TRACE)
//!   ARBOR_REPS=N           builds per measurement (default 5; 200 for the hand-off)
use arbor::accel::{self, AsType, BuildDesc, BuildFlags, Geometry, GeometryData, GeometryFlags, IndexType, NoDevice, VertexFormat};

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|s| s.parse().ok()).unwrap_or(default)
}

fn mesh(var: &str, default: &str) -> arbor_scene::Mesh {
    let path = std::env::var(var).unwrap_or_else(|_| format!("{}/{default}", env!("CARGO_MANIFEST_DIR")));
    arbor_scene::load(&path).unwrap_or_else(|e| panic!("{path}: {e:?}"))
}

fn triangles<'a>(vertices: &'a [u8], indices: &'a [u8], mesh: &arbor_scene::Mesh) -> Geometry<'a> {
    let data = GeometryData::Triangles { format: VertexFormat::R32G32B32Sfloat, vertices, stride: 12, max_vertex: mesh.vertex_count() as u32 - 1, index_type: IndexType::U32, indices, transform: None };
    Geometry { flags: GeometryFlags(GeometryFlags::OPAQUE), primitive_count: mesh.triangle_count() as u32, data }
}

/// Destination and scratch for building `g` with `flags`, from the size query.
fn buffers(g: &Geometry, flags: BuildFlags) -> (Vec<u8>, Vec<u8>) {
    let sz = accel::build_sizes(AsType::BottomLevel, flags, &[accel::GeometryShape::Triangles { format: VertexFormat::R32G32B32Sfloat, index_type: IndexType::U32, max_vertex: 0, has_transform: false }], &[g.primitive_count]);
    (vec![0u8; sz.acceleration_structure_size as usize], vec![0u8; sz.build_scratch_size as usize])
}

/// Process CPU time in ms (utime + stime, clock ticks of 10 ms): on a shared machine wall time
/// includes waiting for a CPU.
fn cpu_ms() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let f: Vec<&str> = s.rsplit(')').next().unwrap_or("").split_whitespace().collect();
    let t = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0);
    (t(11) + t(12)) * 10.0
}

fn phases() {
    let mesh = mesh("ARBOR_MESH", "data/dragon_vrip.ply.gz");
    let (vb, ib) = (mesh.vertex_bytes(), mesh.index_bytes());
    let g = triangles(&vb, &ib, &mesh);
    let reps: usize = env_or("ARBOR_REPS", 5).max(1);
    let only = std::env::var("ARBOR_TIER").ok();
    let threads: Vec<usize> = std::env::var("ARBOR_THREADS").ok().map(|s| s.split(',').filter_map(|x| x.trim().parse().ok()).collect()).unwrap_or(vec![1, 2]);
    for (name, flags) in [("FAST_BUILD", BuildFlags::PREFER_FAST_BUILD), ("default", 0), ("FAST_TRACE", BuildFlags::PREFER_FAST_TRACE)] {
        if only.as_deref().is_some_and(|o| o != name) {
            continue;
        }
        let flags = BuildFlags(flags);
        let (mut dst, mut scratch) = buffers(&g, flags);
        let desc = BuildDesc { ty: AsType::BottomLevel, flags, geometries: &[g] };
        for &t in &threads {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().expect("pool");
            let (mut wall, mut phase) = (Vec::new(), [0f64; 4]);
            let c0 = cpu_ms();
            for _ in 0..reps {
                let start = std::time::Instant::now();
                let (_, p) = pool.install(|| accel::build_timed(&desc, &NoDevice, &mut dst, &mut scratch)).expect("build");
                wall.push(start.elapsed().as_secs_f64() * 1e3);
                for (a, b) in phase.iter_mut().zip([p.ingest_ms, p.sah_ms, p.leaf_data_ms, p.nodes_ms]) {
                    *a += b / reps as f64;
                }
            }
            let cpu = (cpu_ms() - c0) / reps as f64;
            wall.sort_by(f64::total_cmp);
            let m = accel::metrics(&dst).expect("metrics");
            let prims = accel::header(&dst).expect("header").primitive_count.max(1);
            println!(
                "{name:10} threads {t:2}: wall min {:.1} ms median {:.1} ms, CPU {cpu:.0} ms/build | SAH {:.2} wide {:.2} | {:.1} B/tri | nodes {} leaves {} depth {}",
                wall[0], wall[wall.len() / 2], m.sah_cost, m.wide_sah_cost, m.bytes_per_primitive * prims as f32 / mesh.triangle_count() as f32, m.node_count, m.leaf_count, m.max_depth
            );
            println!("{:10} phases (mean ms): ingest {:.2} tree {:.2} leaf data {:.2} nodes {:.2}", "", phase[0], phase[1], phase[2], phase[3]);
        }
    }
}

fn handoff() {
    let mesh = mesh("ARBOR_SMALL_MESH", "data/bunny.ply");
    let (vb, ib) = (mesh.vertex_bytes(), mesh.index_bytes());
    let g = triangles(&vb, &ib, &mesh);
    let flags = BuildFlags(BuildFlags::PREFER_FAST_BUILD);
    let (mut dst, mut scratch) = buffers(&g, flags);
    let desc = BuildDesc { ty: AsType::BottomLevel, flags, geometries: &[g] };
    let reps: usize = env_or("ARBOR_REPS", 200).max(1);
    let stats = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        (v[0], v[v.len() / 2])
    };
    let all = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    for threads in [1usize, all.max(2)] {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
        let mut t = Vec::new();
        for _ in 0..reps {
            let s = std::time::Instant::now();
            pool.install(|| accel::build(&desc, &NoDevice, &mut dst, &mut scratch)).expect("build");
            t.push(s.elapsed().as_secs_f64() * 1e3);
        }
        let (min, med) = stats(&mut t);
        println!("small build installed into a {threads}-thread pool: min {min:.3} ms median {med:.3} ms");
    }
    let here = rayon::ThreadPoolBuilder::new().num_threads(1).use_current_thread().build().expect("pool");
    let mut t = Vec::new();
    here.install(|| {
        for _ in 0..reps {
            let s = std::time::Instant::now();
            accel::build(&desc, &NoDevice, &mut dst, &mut scratch).expect("build");
            t.push(s.elapsed().as_secs_f64() * 1e3);
        }
    });
    let (min, med) = stats(&mut t);
    println!("small build on this thread (a one-thread pool's worker): min {min:.3} ms median {med:.3} ms");
}

fn main() {
    // `cargo test --benches` runs bench binaries with `--test`-style arguments: nothing to do.
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return;
    }
    phases();
    handoff();
}

//! Arbor's library called directly (`arbor::accel::build`, no Vulkan): the library's share of the
//! driver's build time, its phases and, on request, its parallel efficiency.
use std::time::Instant;

use arbor::accel::{self, AsType, BuildDesc, BuildFlags, Geometry, GeometryData, GeometryFlags, GeometryShape, IndexType, VertexFormat};

use super::{Options, Row, Scene, SceneKind, Stats, Status, Workload};
use crate::vkctx::Gpu;

/// `arbor::accel::build` on the host, in this process's rayon pool (RAYON_NUM_THREADS follows
/// --threads): the library's share of Arbor's build time.
pub(super) fn library_build(gpu: &Gpu, scene: &Scene, w: Workload, opts: &Options, row: &mut Row) -> Result<(), String> {
    if gpu.label != "arbor" {
        row.status = Status::NotSupported("Arbor's library, called directly".into());
        return Ok(());
    }
    let SceneKind::Mesh(mesh) = &scene.kind else {
        row.status = Status::NotSupported("library rows for mesh scenes only".into());
        return Ok(());
    };
    let vb = mesh.vertex_bytes();
    let ib = mesh.index_bytes();
    let max_vertex = mesh.vertex_count().saturating_sub(1) as u32;
    let flags = BuildFlags(
        BuildFlags::ALLOW_COMPACTION | if w == Workload::LibFastBuild { BuildFlags::PREFER_FAST_BUILD } else { BuildFlags::PREFER_FAST_TRACE },
    );
    let shape = GeometryShape::Triangles { format: VertexFormat::R32G32B32Sfloat, index_type: IndexType::U32, max_vertex, has_transform: false };
    let n = mesh.triangle_count() as u32;
    let sizes = accel::build_sizes(AsType::BottomLevel, flags, &[shape], &[n]);
    let geoms = [Geometry {
        flags: GeometryFlags(GeometryFlags::OPAQUE),
        primitive_count: n,
        data: GeometryData::Triangles {
            format: VertexFormat::R32G32B32Sfloat,
            vertices: &vb,
            stride: 12,
            max_vertex,
            index_type: IndexType::U32,
            indices: &ib,
            transform: None,
        },
    }];
    let desc = BuildDesc { ty: AsType::BottomLevel, flags, geometries: &geoms };
    let mut dst = vec![0u8; sizes.acceleration_structure_size as usize];
    let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
    let Timed { times, phases, report } = timed_builds(&desc, opts, &mut dst, &mut scratch)?;
    row.time = Stats::of(&times);
    row.wall = row.time;
    row.timing = "host";
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.build_scratch_size;
    row.compacted_size = report.map(|r| r.used_size);
    row.threads = rayon_threads();
    if let Some(m) = accel::metrics(&dst) {
        row.sah = Some(m.sah_cost as f64);
        row.nodes = Some(m.node_count as u64);
        row.leaves = Some(m.leaf_count as u64);
    }
    row.note = phases_note(&phases);
    if opts.efficiency {
        let lens = (sizes.acceleration_structure_size as usize, sizes.build_scratch_size as usize);
        if let Some(note) = efficiency_note(&desc, lens, opts, row.time)? {
            row.note.push_str(&note);
        }
    }
    Ok(())
}

/// The timed runs' milliseconds and phases, and the last build's report.
struct Timed {
    times: Vec<f64>,
    phases: Vec<accel::BuildPhases>,
    report: Option<accel::BuildReport>,
}

/// `warmup + repeat` builds in the current pool.
fn timed_builds(desc: &BuildDesc, opts: &Options, dst: &mut [u8], scratch: &mut [u8]) -> Result<Timed, String> {
    let mut times = Vec::new();
    let mut phases = Vec::new();
    let mut report = None;
    for k in 0..opts.warmup + opts.repeat {
        let t0 = Instant::now();
        let (r, ph) = accel::build_timed(desc, &accel::NoDevice, dst, scratch).map_err(|e| format!("arbor::accel::build: {e:?}"))?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        if k >= opts.warmup {
            times.push(ms);
            phases.push(ph);
        }
        report = Some(r);
    }
    Ok(Timed { times, phases, report })
}

/// The row's note: the median of each phase over the timed runs (accel::BuildPhases).
fn phases_note(phases: &[accel::BuildPhases]) -> String {
    let med = |f: fn(&accel::BuildPhases) -> f64| {
        let mut v: Vec<f64> = phases.iter().map(f).collect();
        v.sort_by(|a, b| a.total_cmp(b));
        v.get(v.len() / 2).copied().unwrap_or(0.0)
    };
    format!(
        "arbor::accel::build called directly (no Vulkan); median phases ms: ingest {:.2}; sah {:.2}; leaf data {:.2}; nodes {:.2}",
        med(|p| p.ingest_ms),
        med(|p| p.sah_ms),
        med(|p| p.leaf_data_ms),
        med(|p| p.nodes_ms)
    )
}

/// N builds at once, one per thread, each on its own 1-thread pool with its own buffers
/// (`dst_len`, `scratch_len`): what one core gives while all N are busy (load, power, shared
/// caches), measured now. Returns the note's efficiency clause, against the pool's median `time`.
fn efficiency_note(desc: &BuildDesc, (dst_len, scratch_len): (usize, usize), opts: &Options, time: Option<Stats>) -> Result<Option<String>, String> {
    let n = rayon::current_num_threads().max(1);
    let medians: Vec<Result<f64, String>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..n)
            .map(|_| {
                s.spawn(move || -> Result<f64, String> {
                    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().map_err(|e| e.to_string())?;
                    let (mut dst, mut scratch) = (vec![0u8; dst_len], vec![0u8; scratch_len]);
                    let mut t = Vec::new();
                    for k in 0..opts.warmup + opts.repeat {
                        let t0 = Instant::now();
                        pool.install(|| accel::build(desc, &accel::NoDevice, &mut dst, &mut scratch)).map_err(|e| format!("arbor::accel::build: {e:?}"))?;
                        if k >= opts.warmup {
                            t.push(t0.elapsed().as_secs_f64() * 1e3);
                        }
                    }
                    Stats::of(&t).map(|s| s.median).ok_or_else(|| "no timed runs".to_string())
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap_or_else(|_| Err("a baseline build panicked".into()))).collect()
    });
    let medians = medians.into_iter().collect::<Result<Vec<f64>, String>>()?;
    Ok(match (Stats::of(&medians), time) {
        (Some(base), Some(t)) => Some(format!(
            "; efficiency {:.0} % against {n} concurrent 1-thread builds (median of their medians {:.2} ms, min {:.2}, max {:.2})",
            100.0 * base.median / (n as f64 * t.median),
            base.median,
            base.min,
            base.max
        )),
        _ => None,
    })
}

fn rayon_threads() -> String {
    std::env::var("RAYON_NUM_THREADS").ok().unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get().to_string()).unwrap_or_default())
}

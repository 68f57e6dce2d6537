//! Ray throughput (rays/s) of Arbor's traversal on the full Stanford dragon (FAST_TRACE BLAS):
//! primary camera rays and random rays (closest hit), random rays with any hit (shadow-like),
//! on 1 thread and on all threads (rayon over the batch).
//!
//! With `--features peers`, Embree 3 (rtcIntersect1/rtcOccluded1 on its own MEDIUM scene BVH)
//! traces the same rays in the same run, after a check that both find the same hits.
//!
//!   cargo bench --bench accel_trace [--features peers]
//!   ARBOR_DATA_DIR=dir   where dragon_vrip.ply.gz is (default: data/ of the checkout)
//!   ARBOR_BENCH_SECS=N   measurement time per benchmark (default 3)
//!   ARBOR_TRACE_ONLY=W   no timing: W = digest prints a digest of every hit field for the
//!                        bench's rays under several ray flags (equal digests = equal results);
//!                        W = primary_closest, random_closest or random_any traces that batch
//!                        once (a short program for `valgrind --tool=callgrind`);
//!                        W = cputime times each workload on Arbor and (with `peers`) Embree
//!                        alternately, ARBOR_BENCH_REPS times (default 7), in on-CPU time of
//!                        the thread (/proc/thread-self/schedstat), and prints the medians:
//!                        on a box shared with other work, wall time counts the time the
//!                        scheduler gives to others

#[cfg(feature = "peers")]
mod peers;

use arbor::accel::{self, AsType, BuildDesc, BuildFlags, Geometry, GeometryData, GeometryFlags, IndexType, Ray, RayFlags, VertexFormat};
use arbor_scene::{self as scene, Rng};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use glam::Vec3;
use rayon::prelude::*;
use std::hint::black_box;
use std::time::Duration;

const BATCH: usize = 65_536;

fn random_rays(b: [f32; 6], n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = Rng::new(seed);
    let lo = Vec3::new(b[0], b[1], b[2]);
    let ext = Vec3::new(b[3] - b[0], b[4] - b[1], b[5] - b[2]);
    (0..n)
        .map(|i| {
            let p = lo + ext * Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            if i % 2 == 0 {
                // From outside the box towards a random point in it.
                let o = lo + ext * 0.5 + Vec3::from(rng.unit_vector()) * ext.length();
                Ray { origin: o, direction: (p - o).normalize(), tmin: 0.0, tmax: f32::INFINITY }
            } else {
                // From inside in a random direction.
                Ray { origin: p, direction: Vec3::from(rng.unit_vector()), tmin: 0.0, tmax: f32::INFINITY }
            }
        })
        .collect()
}

/// data/ of the checkout; ARBOR_DATA_DIR overrides it (a bench binary run on another machine).
fn data_dir() -> std::path::PathBuf {
    std::env::var_os("ARBOR_DATA_DIR").map(Into::into).unwrap_or_else(|| std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data"))
}

fn copy(r: &Ray) -> Ray {
    Ray { origin: r.origin, direction: r.direction, tmin: r.tmin, tmax: r.tmax }
}

fn bench_trace(c: &mut Criterion) {
    let path = data_dir().join("dragon_vrip.ply.gz");
    let mesh = scene::load(path).expect("dragon");
    let dst = fast_trace_blas(&mesh);
    let bvh = &dst[..];
    let b = mesh.bounds();
    let primary: Vec<Ray> = scene::primary_rays(b, 256, 256).into_iter().map(|r| Ray { origin: r.origin, direction: r.direction, tmin: 0.0, tmax: f32::INFINITY }).collect();
    let random = random_rays(b, BATCH, 7);
    if let Ok(what) = std::env::var("ARBOR_TRACE_ONLY") {
        trace_only(&what, &mesh, bvh, &primary, &random);
        return;
    }
    let hit_rate = |rays: &[Ray]| rays.iter().filter(|r| accel::closest_hit(bvh, &accel::NoDevice, copy(r), RayFlags(0), 0xFF).is_some()).count() as f64 / rays.len() as f64;
    println!("\ndragon {} triangles; primary rays hit {:.1}%, random rays hit {:.1}%", mesh.indices.len(), 100.0 * hit_rate(&primary), 100.0 * hit_rate(&random));

    let secs = std::env::var("ARBOR_BENCH_SECS").ok().and_then(|s| s.parse().ok()).unwrap_or(3);
    let mut group = c.benchmark_group("trace/dragon");
    group.throughput(Throughput::Elements(BATCH as u64));
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(1));
    group.measurement_time(Duration::from_secs(secs));
    let all = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    for (name, rays, any) in [("primary_closest", &primary, false), ("random_closest", &random, false), ("random_any", &random, true)] {
        let flags = RayFlags(if any { 4 } else { 0 });
        group.bench_function(format!("arbor/{name}/1t"), |bn| {
            bn.iter(|| {
                let mut hits = 0usize;
                for r in rays.iter() {
                    hits += accel::closest_hit(bvh, &accel::NoDevice, copy(r), RayFlags(flags.0), 0xFF).is_some() as usize;
                }
                black_box(hits)
            })
        });
        if all > 1 {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(all).build().unwrap();
            group.bench_function(format!("arbor/{name}/{all}t"), |bn| {
                bn.iter(|| {
                    pool.install(|| {
                        rays.par_chunks(1024)
                            .map(|c| c.iter().filter(|r| accel::closest_hit(bvh, &accel::NoDevice, copy(r), RayFlags(flags.0), 0xFF).is_some()).count())
                            .sum::<usize>()
                    })
                })
            });
        }
    }
    #[cfg(feature = "peers")]
    bench_embree(&mut group, &mesh, bvh, &primary, &random, all);
    group.finish();
}

/// FNV-1a over words.
fn fnv(h: &mut u64, words: &[u32]) {
    for w in words {
        for b in w.to_le_bytes() {
            *h = (*h ^ b as u64).wrapping_mul(0x100_0000_01b3);
        }
    }
}

fn hit_words(h: &accel::Hit) -> Vec<u32> {
    let mut w = vec![h.t.to_bits(), h.barycentrics[0].to_bits(), h.barycentrics[1].to_bits(), h.front_face as u32, h.opaque as u32];
    w.extend([h.instance_index, h.instance_custom_index, h.sbt_record_offset, h.geometry_index, h.primitive_index, (h.kind == accel::HitKind::Aabb) as u32]);
    w.extend(h.object_ray_origin.to_array().map(f32::to_bits));
    w.extend(h.object_ray_direction.to_array().map(f32::to_bits));
    w.extend(h.object_to_world.iter().chain(&h.world_to_object).map(|x| x.to_bits()));
    w.extend(h.vertices.iter().flat_map(|v| v.to_array()).map(f32::to_bits));
    w
}

/// The digest mode and the one-batch profiling mode (see the module doc).
fn trace_only(what: &str, mesh: &scene::Mesh, bvh: &[u8], primary: &[Ray], random: &[Ray]) {
    let batch = |rays: &[Ray], flags: u32| rays.iter().filter(|r| accel::closest_hit(bvh, &accel::NoDevice, copy(r), RayFlags(flags), 0xFF).is_some()).count();
    match what {
        "primary_closest" => println!("hits {}", batch(primary, 0)),
        "random_closest" => println!("hits {}", batch(random, 0)),
        "random_any" => println!("hits {}", batch(random, RayFlags::TERMINATE_ON_FIRST_HIT)),
        "cputime" => cpu_times(mesh, bvh, primary, random),
        _ => {
            let (b, f, o) = (RayFlags::CULL_BACK_FACING_TRIANGLES, RayFlags::CULL_FRONT_FACING_TRIANGLES, RayFlags::OPAQUE);
            for flags in [0, RayFlags::TERMINATE_ON_FIRST_HIT, b, f, o | f, RayFlags::NO_OPAQUE | b, RayFlags::CULL_OPAQUE] {
                for (name, rays) in [("primary", primary), ("random", random)] {
                    let (mut hc, mut ha, mut hq, mut n) = (0xcbf2_9ce4_8422_2325u64, 0xcbf2_9ce4_8422_2325u64, 0xcbf2_9ce4_8422_2325u64, 0);
                    for r in rays.iter() {
                        let c = accel::closest_hit(bvh, &accel::NoDevice, copy(r), RayFlags(flags), 0xFF);
                        n += c.is_some() as usize;
                        fnv(&mut hc, &c.map_or(vec![u32::MAX], |h| hit_words(&h)));
                        let a = accel::any_hit(bvh, &accel::NoDevice, copy(r), RayFlags(flags), 0xFF);
                        fnv(&mut ha, &a.map_or(vec![u32::MAX], |h| hit_words(&h)));
                        // The resumable query, every candidate confirmed.
                        let mut q = accel::RayQuery::new(bvh, &accel::NoDevice, copy(r), RayFlags(flags), 0xFF);
                        while let Some(h) = q.proceed() {
                            fnv(&mut hq, &hit_words(&h));
                            q.confirm();
                        }
                        fnv(&mut hq, &q.committed().map_or(vec![u32::MAX], |h| hit_words(&h)));
                    }
                    println!("flags {flags:#05x} {name:7}: {n:6} hits, closest {hc:016x}, any {ha:016x}, query {hq:016x}");
                }
            }
        }
    }
}

/// Nanoseconds this thread has run on a CPU; None where the kernel does not say.
fn thread_cpu_ns() -> Option<u64> {
    std::fs::read_to_string("/proc/thread-self/schedstat").ok()?.split_whitespace().next()?.parse().ok()
}

fn median_ms(mut v: Vec<u64>) -> f64 {
    v.sort_unstable();
    v.get(v.len() / 2).map_or(f64::NAN, |&ns| ns as f64 / 1e6)
}

/// The cputime mode (see the module doc): one thread, Arbor and Embree alternating per batch.
fn cpu_times(mesh: &scene::Mesh, bvh: &[u8], primary: &[Ray], random: &[Ray]) {
    let _ = mesh;
    let reps: usize = std::env::var("ARBOR_BENCH_REPS").ok().and_then(|s| s.parse().ok()).unwrap_or(7);
    let Some(_) = thread_cpu_ns() else {
        println!("no /proc/thread-self/schedstat here");
        return;
    };
    let timed = |f: &mut dyn FnMut() -> usize| {
        let t0 = thread_cpu_ns().unwrap_or(0);
        black_box(f());
        thread_cpu_ns().unwrap_or(0).saturating_sub(t0)
    };
    #[cfg(feature = "peers")]
    let dev = peers::embree::Device::new(1);
    #[cfg(feature = "peers")]
    let scene = peers::embree::Scene::new(&dev, mesh, 1);
    for (name, rays, any) in [("primary_closest", primary, false), ("random_closest", random, false), ("random_any", random, true)] {
        let flags = if any { RayFlags::TERMINATE_ON_FIRST_HIT } else { 0 };
        let mut arbor = Vec::new();
        #[cfg_attr(not(feature = "peers"), allow(unused_mut))]
        let mut embree = Vec::new();
        for _ in 0..reps {
            arbor.push(timed(&mut || rays.iter().filter(|r| accel::closest_hit(bvh, &accel::NoDevice, copy(r), RayFlags(flags), 0xFF).is_some()).count()));
            #[cfg(feature = "peers")]
            embree.push(timed(&mut || {
                rays.iter()
                    .filter(|r| {
                        let (o, d) = (r.origin.to_array(), r.direction.to_array());
                        if any { scene.occluded(o, d, r.tmin, r.tmax) } else { scene.intersect(o, d, r.tmin, r.tmax).is_some() }
                    })
                    .count()
            }));
        }
        let (a, e) = (median_ms(arbor), median_ms(embree));
        println!("{name:16} on-CPU ms per {} rays, median of {reps}: arbor {a:8.2}  embree {e:8.2}  arbor/embree {:.2}", rays.len(), a / e);
    }
}

/// The mesh's FAST_TRACE BLAS, built by the library on the host.
fn fast_trace_blas(mesh: &scene::Mesh) -> Vec<u8> {
    let (vb, ib) = (mesh.vertex_bytes(), mesh.index_bytes());
    let geoms = [Geometry {
        flags: GeometryFlags(1),
        primitive_count: mesh.indices.len() as u32,
        data: GeometryData::Triangles { format: VertexFormat::R32G32B32Sfloat, vertices: &vb, stride: 12, max_vertex: mesh.max_index(), index_type: IndexType::U32, indices: &ib, transform: None },
    }];
    let flags = BuildFlags(BuildFlags::PREFER_FAST_TRACE);
    let sizes = accel::build_sizes(AsType::BottomLevel, flags, &[accel::GeometryShape::Triangles {
        format: VertexFormat::R32G32B32Sfloat,
        index_type: IndexType::U32,
        max_vertex: mesh.max_index(),
        has_transform: false,
    }], &[mesh.indices.len() as u32]);
    let mut dst = vec![0u8; sizes.acceleration_structure_size as usize];
    let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
    accel::build(&BuildDesc { ty: AsType::BottomLevel, flags, geometries: &geoms }, &accel::NoDevice, &mut dst, &mut scratch).expect("build");
    dst
}

/// Embree 3 on the same rays, on 1 and `all` threads, after a check that it finds the same hits.
#[cfg(feature = "peers")]
fn bench_embree(group: &mut criterion::BenchmarkGroup<criterion::measurement::WallTime>, mesh: &scene::Mesh, bvh: &[u8], primary: &[Ray], random: &[Ray], all: usize) {
    use peers::embree;
    let dev = embree::Device::new(all);
    let scene = embree::Scene::new(&dev, mesh, 1);
    // Agreement check: same hit/miss and t within 1e-4 relative on nearly every ray.
    for (name, rays) in [("primary", primary), ("random", random)] {
        let mut agree = 0;
        for r in rays.iter() {
            let a = accel::closest_hit(bvh, &accel::NoDevice, copy(r), RayFlags(0), 0xFF).map(|h| h.t);
            let e = scene.intersect(r.origin.to_array(), r.direction.to_array(), r.tmin, r.tmax).map(|h| h.0);
            agree += match (a, e) {
                (None, None) => 1,
                (Some(x), Some(y)) => ((x - y).abs() <= 1e-4 * x.abs().max(1e-3)) as usize,
                _ => 0,
            };
        }
        println!("arbor vs embree, {name} rays: {:.3}% agree (hit/miss and t)", 100.0 * agree as f64 / rays.len() as f64);
    }
    for (name, rays, any) in [("primary_closest", primary, false), ("random_closest", random, false), ("random_any", random, true)] {
        let trace = |r: &Ray| {
            let (o, d) = (r.origin.to_array(), r.direction.to_array());
            if any { scene.occluded(o, d, r.tmin, r.tmax) } else { scene.intersect(o, d, r.tmin, r.tmax).is_some() }
        };
        group.bench_function(format!("embree/{name}/1t"), |bn| bn.iter(|| rays.iter().filter(|r| trace(r)).count()));
        if all > 1 {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(all).build().unwrap();
            group.bench_function(format!("embree/{name}/{all}t"), |bn| {
                bn.iter(|| pool.install(|| rays.par_chunks(1024).map(|c| c.iter().filter(|r| trace(r)).count()).sum::<usize>()))
            });
        }
    }
}

criterion_group!(benches, bench_trace);
criterion_main!(benches);

//! The acceleration-structure API path against src/accel alone, on the full Stanford dragon
//! (871,414 triangles): device, indirect and host builds through the Vulkan loader, host builds
//! under a deferred operation joined by 1, 2 and all threads. The overhead of the API path is
//! the ratio of the device build to `accel_only`.
//!
//! Run: `cargo build --release --workspace && cargo bench --bench accel_api`
//! (set ARBOR_BENCH_MESH to use another mesh).
use std::time::Duration;

use ash::vk;
use criterion::measurement::WallTime;
use criterion::{criterion_group, criterion_main, BenchmarkGroup, Criterion, Throughput};

// The loader harness of the API tests (it allows its own dead code).
#[path = "../tests/harness/mod.rs"]
mod support;

use support::accel::{triangles, Accel};

fn mesh() -> arbor_scene::Mesh {
    let path = std::env::var("ARBOR_BENCH_MESH").unwrap_or_else(|_| concat!(env!("CARGO_MANIFEST_DIR"), "/data/dragon_vrip.ply.gz").into());
    arbor_scene::load(&path).expect("mesh")
}

fn bench(c: &mut Criterion) {
    let mesh = mesh();
    let n = mesh.triangle_count() as u32;
    let vbytes = mesh.vertex_bytes();
    let ibytes = mesh.index_bytes();
    let mut g = c.benchmark_group("api_dragon");
    g.sample_size(10).measurement_time(Duration::from_secs(8)).warm_up_time(Duration::from_secs(1));
    g.throughput(Throughput::Elements(n as u64));
    bench_accel_only(&mut g, &mesh, &vbytes, &ibytes);

    let ctx = support::Context::new(support::Options { validation: false, acceleration_structure: true, ..Default::default() });
    let a = Accel::new(&ctx);
    let vb = a.upload(&vbytes);
    let ib = a.upload(&ibytes);
    let geoms = [triangles(a.buf(vb).address, a.buf(ib).address, mesh.vertex_count() as u32 - 1)];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &[n]);
    let (s, _) = a.structure(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, sizes.acceleration_structure_size);
    let scratch = a.buffer(sizes.build_scratch_size);
    let records = a.buffer(16);
    a.buf(records).write(0, &n.to_le_bytes());
    let dinfo = info.dst_acceleration_structure(s).scratch_data(vk::DeviceOrHostAddressKHR { device_address: a.buf(scratch).address });
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(n)];
    let raddr = a.buf(records).address;

    g.bench_function("device_build", |b| {
        b.iter(|| {
            a.submit(|cb| {
                // SAFETY: valid infos.
                unsafe { a.ext.cmd_build_acceleration_structures(cb, &[dinfo], &[&range]) };
            })
        })
    });
    g.bench_function("indirect_build", |b| {
        b.iter(|| {
            a.submit(|cb| {
                // SAFETY: valid infos.
                unsafe { a.ext.cmd_build_acceleration_structures_indirect(cb, &[dinfo], &[raddr], &[16], &[&[n]]) };
            })
        })
    });

    // Host builds: inputs by host pointer.
    let hgeoms = [triangles(vbytes.as_ptr() as u64, ibytes.as_ptr() as u64, mesh.vertex_count() as u32 - 1)];
    let mut hscratch = vec![0u8; sizes.build_scratch_size as usize];
    let hinfo = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&hgeoms)
        .dst_acceleration_structure(s)
        .scratch_data(vk::DeviceOrHostAddressKHR { host_address: hscratch.as_mut_ptr().cast() });
    g.bench_function("host_build", |b| {
        b.iter(|| {
            // SAFETY: valid infos; host memory alive.
            unsafe { a.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[hinfo], &[&range]) }.unwrap()
        })
    });
    bench_host_deferred(&mut g, &ctx, &a, &hinfo, &range);
    g.finish();
    drop(hscratch);
    a.destroy();
    ctx.finish();
}

/// src/accel alone, on Arbor's pool (same thread count as the driver).
fn bench_accel_only(g: &mut BenchmarkGroup<WallTime>, mesh: &arbor_scene::Mesh, vbytes: &[u8], ibytes: &[u8]) {
    let n = mesh.triangle_count() as u32;
    let geometry = arbor::accel::Geometry {
        flags: arbor::accel::GeometryFlags(1),
        primitive_count: n,
        data: arbor::accel::GeometryData::Triangles {
            format: arbor::accel::VertexFormat::R32G32B32Sfloat,
            vertices: vbytes,
            stride: 12,
            max_vertex: mesh.vertex_count() as u32 - 1,
            index_type: arbor::accel::IndexType::U32,
            indices: ibytes,
            transform: None,
        },
    };
    let shape = [arbor::accel::GeometryShape::Triangles {
        format: arbor::accel::VertexFormat::R32G32B32Sfloat,
        index_type: arbor::accel::IndexType::U32,
        max_vertex: mesh.vertex_count() as u32 - 1,
        has_transform: false,
    }];
    let flags = arbor::accel::BuildFlags(0);
    let sizes = arbor::accel::build_sizes(arbor::accel::AsType::BottomLevel, flags, &shape, &[n]);
    let mut dst = vec![0u8; sizes.acceleration_structure_size as usize];
    let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
    let geoms = [geometry];
    let desc = arbor::accel::BuildDesc { ty: arbor::accel::AsType::BottomLevel, flags, geometries: &geoms };
    g.bench_function("accel_only", |b| {
        b.iter(|| arbor::threads::pool().install(|| arbor::accel::build(&desc, &arbor::accel::NoDevice, &mut dst, &mut scratch).unwrap()))
    });
}

/// Host builds (`hinfo`, inputs by host pointer) under a deferred operation joined by 1, 2 and
/// all threads.
fn bench_host_deferred(
    g: &mut BenchmarkGroup<WallTime>,
    ctx: &support::Context,
    a: &Accel,
    hinfo: &vk::AccelerationStructureBuildGeometryInfoKHR,
    range: &[vk::AccelerationStructureBuildRangeInfoKHR],
) {
    let all = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let mut joiner_counts = vec![1, 2, all];
    joiner_counts.dedup();
    for joiners in joiner_counts {
        g.bench_function(format!("host_deferred_{joiners}_joiners"), |b| {
            b.iter(|| {
                // SAFETY: valid infos; the operation completes before the iteration ends.
                unsafe {
                    let op = a.deferred.create_deferred_operation(None).unwrap();
                    let r = (a.ext.fp().build_acceleration_structures_khr)(ctx.device.handle(), op, 1, hinfo, [range.as_ptr()].as_ptr());
                    if r == vk::Result::OPERATION_DEFERRED_KHR {
                        let dev = ctx.device.handle();
                        let join = a.deferred.fp().deferred_operation_join_khr;
                        let raw = vk::Handle::as_raw(op);
                        std::thread::scope(|sc| {
                            for _ in 0..joiners {
                                sc.spawn(move || while join(dev, vk::Handle::from_raw(raw)) == vk::Result::THREAD_IDLE_KHR {});
                            }
                        });
                    }
                    a.deferred.destroy_deferred_operation(op, None);
                }
            })
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);

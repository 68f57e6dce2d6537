//! VK_KHR_acceleration_structure through the real loader with validation on: builds of every
//! kind, copies, serialization, queries, deferred joins — checked against an independent
//! brute-force intersection over the application's input and against each other.
mod harness;

use arbor::accel::{self, NoDevice, Ray, RayFlags};
use ash::vk;
use glam::Vec3;
use harness::accel::{instance_record, instances, payload, triangles, Accel};

fn as_context() -> harness::Context {
    harness::Context::new(harness::Options { acceleration_structure: true, ..Default::default() })
}

fn bunny() -> arbor_scene::Mesh {
    arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).unwrap()
}

/// Deterministic rays through the mesh's bounds (xorshift).
fn rays(bounds: [f32; 6], n: usize, seed: u64) -> Vec<Ray> {
    let mut s = seed | 1;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let lo = Vec3::new(bounds[0], bounds[1], bounds[2]);
    let hi = Vec3::new(bounds[3], bounds[4], bounds[5]);
    let ext = hi - lo;
    (0..n)
        .map(|_| {
            let target = lo + Vec3::new(next(), next(), next()) * ext;
            let dir = Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5).normalize_or(Vec3::X);
            Ray { origin: target - dir * ext.length() * 2.0, direction: dir, tmin: 0.0, tmax: f32::INFINITY }
        })
        .collect()
}

/// Closest hit by brute force over the mesh (the library's watertight test, every triangle).
fn brute_closest(mesh: &arbor_scene::Mesh, ray: &Ray) -> Option<(f32, u32)> {
    let mut best: Option<(f32, u32)> = None;
    for i in 0..mesh.triangle_count() {
        let t = mesh.triangle(i);
        if let Some((d, _, _, _)) = accel::intersect_triangle(ray, Vec3::from(t[0]), Vec3::from(t[1]), Vec3::from(t[2])) {
            if d >= ray.tmin && d <= ray.tmax && best.is_none_or(|(bd, _)| d < bd) {
                best = Some((d, i as u32));
            }
        }
    }
    best
}

struct MeshInput {
    vertices: usize,
    indices: usize,
    max_vertex: u32,
    count: u32,
}

fn upload_mesh(a: &Accel, mesh: &arbor_scene::Mesh) -> MeshInput {
    MeshInput {
        vertices: a.upload(&mesh.vertex_bytes()),
        indices: a.upload(&mesh.index_bytes()),
        max_vertex: mesh.vertex_count() as u32 - 1,
        count: mesh.triangle_count() as u32,
    }
}

fn blas_info<'a>(
    geoms: &'a [vk::AccelerationStructureGeometryKHR<'static>],
    flags: vk::BuildAccelerationStructureFlagsKHR,
) -> vk::AccelerationStructureBuildGeometryInfoKHR<'a> {
    vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL)
        .flags(flags)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(geoms)
}

/// Device build of a mesh BLAS; returns the structure.
fn device_blas(a: &Accel, m: &MeshInput, flags: vk::BuildAccelerationStructureFlagsKHR) -> vk::AccelerationStructureKHR {
    let geoms = [triangles(a.buf(m.vertices).address, a.buf(m.indices).address, m.max_vertex)];
    let info = blas_info(&geoms, flags);
    let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &[m.count]);
    let (s, _) = a.structure(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, sizes.acceleration_structure_size);
    let scratch = a.buffer(sizes.build_scratch_size);
    let info = info.dst_acceleration_structure(s).scratch_data(vk::DeviceOrHostAddressKHR { device_address: a.buf(scratch).address });
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(m.count)];
    a.submit(|cb| {
        // SAFETY: valid infos and ranges; buffers live until the wait inside submit.
        unsafe { a.ext.cmd_build_acceleration_structures(cb, &[info], &[&range]) };
    });
    s
}

#[test]
fn device_build_of_the_bunny_traverses_like_brute_force() {
    let ctx = as_context();
    let a = Accel::new(&ctx);
    let mesh = bunny();
    let m = upload_mesh(&a, &mesh);
    let s = device_blas(&a, &m, vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE);
    let ser = a.serialize(s);
    let blob = payload(&ser);
    let h = accel::header(blob).expect("a valid structure");
    assert_eq!(h.primitive_count as usize, mesh.triangle_count());
    let mut hits = 0;
    for ray in rays(mesh.bounds(), 2000, 7) {
        let got = accel::closest_hit(blob, &NoDevice, ray, RayFlags(0), 0xFF).map(|h| (h.t, h.primitive_index));
        let want = brute_closest(&mesh, &ray);
        assert_eq!(got, want, "ray {ray:?}");
        hits += want.is_some() as u32;
    }
    assert!(hits > 200, "too few rays hit the bunny ({hits}): the test would prove little");
    a.destroy();
    ctx.finish();
}

/// The same build through every path: device, indirect (records written by vkCmdUpdateBuffer
/// earlier in the same command buffer), host, and host under a deferred operation joined by
/// 1, 2 and 8 threads — byte-identical serializations, for FAST_TRACE and FAST_BUILD.
// One function: one scenario, every build path compared against the same device build.
#[test]
fn host_device_indirect_and_deferred_builds_are_byte_identical() {
    let ctx = as_context();
    let a = Accel::new(&ctx);
    let mesh = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/dragon_vrip_res4.ply.gz")).unwrap();
    let m = upload_mesh(&a, &mesh);
    // FAST_TRACE, and FAST_BUILD (built over primitive pairs: res4 has 11,102 triangles).
    for tier in [vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE, vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD] {
        let flags = tier | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION;
        let device = a.serialize(device_blas(&a, &m, flags));

        // Indirect: the range record is written by vkCmdUpdateBuffer in the same command buffer.
        let geoms = [triangles(a.buf(m.vertices).address, a.buf(m.indices).address, m.max_vertex)];
        let info = blas_info(&geoms, flags);
        let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &[m.count]);
        let (s, _) = a.structure(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, sizes.acceleration_structure_size);
        let scratch = a.buffer(sizes.build_scratch_size);
        let records = a.buffer(64);
        let info = info.dst_acceleration_structure(s).scratch_data(vk::DeviceOrHostAddressKHR { device_address: a.buf(scratch).address });
        let mut record = [0u8; 16];
        record[..4].copy_from_slice(&m.count.to_le_bytes());
        let (rb, raddr) = (a.buf(records).buffer, a.buf(records).address);
        a.submit(|cb| {
            // SAFETY: recording command buffer; valid buffers and infos.
            unsafe {
                ctx.device.cmd_update_buffer(cb, rb, 16, &record);
                let barrier = vk::MemoryBarrier::default()
                    .src_access_mask(vk::AccessFlags::TRANSFER_WRITE)
                    .dst_access_mask(vk::AccessFlags::INDIRECT_COMMAND_READ);
                ctx.device.cmd_pipeline_barrier(
                    cb,
                    vk::PipelineStageFlags::TRANSFER,
                    vk::PipelineStageFlags::ACCELERATION_STRUCTURE_BUILD_KHR,
                    vk::DependencyFlags::empty(),
                    &[barrier],
                    &[],
                    &[],
                );
                a.ext.cmd_build_acceleration_structures_indirect(cb, &[info], &[raddr + 16], &[16], &[&[m.count]]);
            }
        });
        let indirect = a.serialize(s);
        assert_eq!(device, indirect, "indirect build differs from the device build ({flags:?})");

        // Host builds: inputs by host pointer.
        let vbytes = mesh.vertex_bytes();
        let ibytes = mesh.index_bytes();
        let host_build = |deferred: Option<usize>| -> Vec<u8> {
            let geoms = [triangles(vbytes.as_ptr() as u64, ibytes.as_ptr() as u64, m.max_vertex)];
            let info = blas_info(&geoms, flags);
            let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::HOST, &info, &[m.count]);
            let (s, _) = a.structure(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, sizes.acceleration_structure_size);
            let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
            let info = info.dst_acceleration_structure(s).scratch_data(vk::DeviceOrHostAddressKHR { host_address: scratch.as_mut_ptr().cast() });
            let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(m.count)];
            // SAFETY: valid infos; host memory outlives the build (joined below before returning).
            unsafe {
                match deferred {
                    None => a.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[info], &[&range]).unwrap(),
                    Some(joiners) => {
                        let op = a.deferred.create_deferred_operation(None).unwrap();
                        let r = (a.ext.fp().build_acceleration_structures_khr)(ctx.device.handle(), op, 1, &info, [range.as_ptr()].as_ptr());
                        assert!(r == vk::Result::OPERATION_DEFERRED_KHR || r == vk::Result::OPERATION_NOT_DEFERRED_KHR, "{r:?}");
                        if r == vk::Result::OPERATION_DEFERRED_KHR {
                            assert_eq!(a.deferred.get_deferred_operation_result(op), Err(vk::Result::NOT_READY));
                            assert!(a.deferred.get_deferred_operation_max_concurrency(op) >= 1);
                            let dev = ctx.device.handle();
                            let join = a.deferred.fp().deferred_operation_join_khr;
                            let op_raw = vk::Handle::as_raw(op);
                            let results: Vec<vk::Result> = std::thread::scope(|sc| {
                                let hs: Vec<_> = (0..joiners)
                                    .map(|_| sc.spawn(move || loop {
                                        let op = <vk::DeferredOperationKHR as vk::Handle>::from_raw(op_raw);
                                        let r = join(dev, op);
                                        if r != vk::Result::THREAD_IDLE_KHR {
                                            break r;
                                        }
                                    }))
                                    .collect();
                                hs.into_iter().map(|h| h.join().unwrap()).collect()
                            });
                            assert!(results.contains(&vk::Result::SUCCESS), "no joiner saw completion: {results:?}");
                            assert!(results.iter().all(|r| *r == vk::Result::SUCCESS || *r == vk::Result::THREAD_DONE_KHR), "{results:?}");
                        }
                        assert_eq!(a.deferred.get_deferred_operation_result(op), Ok(()));
                        assert_eq!(a.deferred.get_deferred_operation_max_concurrency(op), 0);
                        a.deferred.destroy_deferred_operation(op, None);
                    }
                }
            }
            drop(scratch);
            a.serialize(s)
        };
        assert_eq!(device, host_build(None), "host build differs from the device build ({flags:?})");
        for joiners in [1, 2, 8] {
            assert_eq!(device, host_build(Some(joiners)), "deferred host build joined by {joiners} threads differs ({flags:?})");
        }
    }
    a.destroy();
    ctx.finish();
}

/// Compaction shrinks (or keeps) the size and traversal stays identical; clone is identical;
/// serialize → deserialize → serialize round-trips; compatibility says COMPATIBLE for our header
/// and INCOMPATIBLE for a changed UUID; host and device property queries agree.
// One function: one scenario, each copy checked against the structure built first.
#[test]
fn compaction_clone_serialization_round_trip_and_queries() {
    let ctx = as_context();
    let a = Accel::new(&ctx);
    let mesh = bunny();
    let m = upload_mesh(&a, &mesh);
    let flags = vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION;
    let s = device_blas(&a, &m, flags);
    let original = a.serialize(s);

    let compacted = a.query(s, vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR);
    let size = a.query(s, vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR);
    let ser_size = a.query(s, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR);
    let blas_ptrs = a.query(s, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_BOTTOM_LEVEL_POINTERS_KHR);
    assert!(compacted > 0 && compacted <= size, "compacted {compacted} size {size}");
    assert_eq!(ser_size as usize, original.len());
    assert_eq!(blas_ptrs, 0, "a BLAS references no BLAS");
    // Host queries agree with the command form.
    let mut host = [0u64; 3];
    // SAFETY: valid structure; data is 3 u64s with stride 8 each call.
    unsafe {
        for (k, ty) in [
            vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR,
            vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR,
            vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR,
        ]
        .into_iter()
        .enumerate()
        {
            let mut v = [0u8; 8];
            a.ext.write_acceleration_structures_properties(&[s], ty, &mut v, 8).unwrap();
            host[k] = u64::from_le_bytes(v);
        }
    }
    assert_eq!(host, [compacted, size, ser_size]);

    // Compact into a structure of exactly the compacted size.
    let (c, _) = a.structure(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, compacted);
    let (cl, _) = a.structure(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, size);
    a.submit(|cb| {
        // SAFETY: recording command buffer; valid structures.
        unsafe {
            a.ext.cmd_copy_acceleration_structure(
                cb,
                &vk::CopyAccelerationStructureInfoKHR::default().src(s).dst(c).mode(vk::CopyAccelerationStructureModeKHR::COMPACT),
            );
            a.ext.cmd_copy_acceleration_structure(
                cb,
                &vk::CopyAccelerationStructureInfoKHR::default().src(s).dst(cl).mode(vk::CopyAccelerationStructureModeKHR::CLONE),
            );
        }
    });
    let comp_ser = a.serialize(c);
    assert_eq!(a.serialize(cl), original, "clone differs");
    for ray in rays(mesh.bounds(), 500, 11) {
        let x = accel::closest_hit(payload(&original), &NoDevice, ray, RayFlags(0), 0xFF).map(|h| (h.t, h.primitive_index));
        let y = accel::closest_hit(payload(&comp_ser), &NoDevice, ray, RayFlags(0), 0xFF).map(|h| (h.t, h.primitive_index));
        assert_eq!(x, y);
    }

    // Deserialize into a new structure of the size the header names, then serialize again.
    let deser_size = u64::from_le_bytes(original[40..48].try_into().unwrap());
    let src_buf = a.upload(&original);
    let (d, _) = a.structure(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, deser_size);
    let src_addr = a.buf(src_buf).address;
    a.submit(|cb| {
        let info = vk::CopyMemoryToAccelerationStructureInfoKHR::default()
            .src(vk::DeviceOrHostAddressConstKHR { device_address: src_addr })
            .dst(d)
            .mode(vk::CopyAccelerationStructureModeKHR::DESERIALIZE);
        // SAFETY: recording command buffer; valid info.
        unsafe { a.ext.cmd_copy_memory_to_acceleration_structure(cb, &info) };
    });
    assert_eq!(a.serialize(d), original, "serialize → deserialize → serialize changed the bytes");

    // Compatibility of our header; a changed UUID is incompatible.
    let check = |data: &[u8]| {
        let v = vk::AccelerationStructureVersionInfoKHR::default().version_data(data[..32].try_into().unwrap());
        // SAFETY: 32 bytes of version data.
        unsafe { a.ext.get_device_acceleration_structure_compatibility(&v) }
    };
    assert_eq!(check(&original), vk::AccelerationStructureCompatibilityKHR::COMPATIBLE);
    let mut changed = original.clone();
    changed[20] ^= 0xFF;
    assert_eq!(check(&changed), vk::AccelerationStructureCompatibilityKHR::INCOMPATIBLE);
    let mut changed = original.clone();
    changed[3] ^= 0xFF;
    assert_eq!(check(&changed), vk::AccelerationStructureCompatibilityKHR::INCOMPATIBLE);
    // The header carries the driverUUID the device reports.
    let mut id = vk::PhysicalDeviceIDProperties::default();
    let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut id);
    // SAFETY: plain query.
    unsafe { ctx.instance.get_physical_device_properties2(ctx.physical, &mut p2) };
    assert_eq!(&original[..16], &id.driver_uuid);
    a.destroy();
    ctx.finish();
}

/// Builds a TLAS over `n` instances with `flags` twice: on the device from `dev_records` (BLAS
/// device addresses) and with vkBuildAccelerationStructuresKHR from `host_records` (BLAS
/// handles). Returns the device-built structure and both serializations.
fn tlas_device_and_host(a: &Accel, dev_records: &[u8], host_records: &[u8], n: u32, flags: vk::BuildAccelerationStructureFlagsKHR) -> (vk::AccelerationStructureKHR, Vec<u8>, Vec<u8>) {
    let inst = a.upload(dev_records);
    let geoms = [instances(a.buf(inst).address)];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(vk::AccelerationStructureTypeKHR::TOP_LEVEL)
        .flags(flags)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &[n]);
    let (t, _) = a.structure(vk::AccelerationStructureTypeKHR::TOP_LEVEL, sizes.acceleration_structure_size);
    let scratch = a.buffer(sizes.build_scratch_size);
    let dinfo = info.dst_acceleration_structure(t).scratch_data(vk::DeviceOrHostAddressKHR { device_address: a.buf(scratch).address });
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(n)];
    a.submit(|cb| {
        // SAFETY: valid infos.
        unsafe { a.ext.cmd_build_acceleration_structures(cb, &[dinfo], &[&range]) };
    });
    let device = a.serialize(t);
    let hgeoms = [vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::INSTANCES)
        .geometry(vk::AccelerationStructureGeometryDataKHR {
            instances: vk::AccelerationStructureGeometryInstancesDataKHR::default()
                .data(vk::DeviceOrHostAddressConstKHR { host_address: host_records.as_ptr().cast() }),
        })];
    let (th, _) = a.structure(vk::AccelerationStructureTypeKHR::TOP_LEVEL, sizes.acceleration_structure_size);
    let mut hscratch = vec![0u8; sizes.build_scratch_size as usize];
    let hinfo = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(vk::AccelerationStructureTypeKHR::TOP_LEVEL)
        .flags(flags)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&hgeoms)
        .dst_acceleration_structure(th)
        .scratch_data(vk::DeviceOrHostAddressKHR { host_address: hscratch.as_mut_ptr().cast() });
    // SAFETY: valid infos, host memory alive for the call.
    unsafe { a.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[hinfo], &[&range]) }.unwrap();
    (t, device, a.serialize(th))
}

/// Host builds name BLASes by handle and remember a few handle lookups per thread: a TLAS over
/// more BLASes than that memo holds, named in an order that keeps evicting it, builds to the
/// same bytes on the host as on the device (where instances hold addresses), twice with
/// different assignments, in the default tier and at PREFER_FAST_BUILD (its own tree builder).
#[test]
fn host_tlas_over_many_blases_matches_the_device_build() {
    let ctx = as_context();
    let a = Accel::new(&ctx);
    let mesh = bunny();
    let m = upload_mesh(&a, &mesh);
    let blases: Vec<_> = (0..7).map(|_| device_blas(&a, &m, vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD)).collect();
    let n = 300u32;
    let transform = |i: u32| [1.0, 0.0, 0.0, (i % 20) as f32 * 0.3, 0.0, 1.0, 0.0, (i / 20) as f32 * 0.3, 0.0, 0.0, 1.0, 0.0];
    let fast_build = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD;
    for (pattern, flags) in [((3u32, 1u32), vk::BuildAccelerationStructureFlagsKHR::empty()), ((5, 4), vk::BuildAccelerationStructureFlagsKHR::empty()), ((3, 1), fast_build)] {
        let pick = |i: u32| ((i * pattern.0 + pattern.1) % 7) as usize;
        let records = |reference: &dyn Fn(usize) -> u64| -> Vec<u8> { (0..n).flat_map(|i| instance_record(transform(i), i, 0xFF, 0, 0, reference(pick(i)))).collect() };
        let dev_records = records(&|k| a.address_of(blases[k]));
        let host_records = records(&|k| vk::Handle::as_raw(blases[k]));
        let (t, device, host) = tlas_device_and_host(&a, &dev_records, &host_records, n, flags);
        // One handle per instance (all 300 active), not per distinct BLAS.
        assert_eq!(a.query(t, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_BOTTOM_LEVEL_POINTERS_KHR), n as u64);
        assert_eq!(host, device, "host TLAS build over 7 BLASes differs from the device build (pattern {pattern:?}, flags {flags:?})");
    }
    a.destroy();
    ctx.finish();
}

/// A two-level structure: TLAS over instances of two BLASes, device and host builds identical,
/// traversal (BLASes found by device address) equal to brute force over the transformed triangles.
// One function: one scenario, the BLASes, the TLAS over them and its check against brute force.
#[test]
fn tlas_over_blases_device_and_host_builds_match_brute_force() {
    let ctx = as_context();
    let a = Accel::new(&ctx);
    let mesh = bunny();
    let m = upload_mesh(&a, &mesh);
    let b0 = device_blas(&a, &m, vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE);
    let b1 = device_blas(&a, &m, vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD);
    let (a0, a1) = (a.address_of(b0), a.address_of(b1));
    let transforms: Vec<[f32; 12]> = (0..6)
        .map(|i| {
            let (s, c) = (i as f32 * 0.7).sin_cos();
            [c * 0.8, 0.0, s * 0.8, i as f32 * 0.25, 0.0, 0.8, 0.0, 0.05 * i as f32, -s * 0.8, 0.0, c * 0.8, 0.0]
        })
        .collect();
    let records = |refs: [u64; 2]| -> Vec<u8> {
        transforms.iter().enumerate().flat_map(|(i, t)| instance_record(*t, 100 + i as u32, 0xFF, i as u32, 0, refs[i % 2])).collect()
    };
    let n = transforms.len() as u32;
    // Host build: references are handles.
    let (t, device, host) = tlas_device_and_host(&a, &records([a0, a1]), &records([vk::Handle::as_raw(b0), vk::Handle::as_raw(b1)]), n, vk::BuildAccelerationStructureFlagsKHR::empty());
    assert_eq!(a.query(t, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_BOTTOM_LEVEL_POINTERS_KHR), n as u64);
    assert_eq!(host, device, "host TLAS build differs from the device build");

    // Traverse: BLASes found at their device addresses.
    let mut view = accel::MapView::new();
    view.insert(a0, payload(&a.serialize(b0)).to_vec());
    view.insert(a1, payload(&a.serialize(b1)).to_vec());
    let tlas = payload(&device);
    let meshr = &mesh;
    let world: Vec<[[f32; 3]; 3]> = transforms
        .iter()
        .flat_map(|t| {
            (0..meshr.triangle_count()).map(move |i| {
                let tri = meshr.triangle(i);
                tri.map(|p| {
                    [
                        t[0] * p[0] + t[1] * p[1] + t[2] * p[2] + t[3],
                        t[4] * p[0] + t[5] * p[1] + t[6] * p[2] + t[7],
                        t[8] * p[0] + t[9] * p[1] + t[10] * p[2] + t[11],
                    ]
                })
            })
        })
        .collect();
    let mut b = [f32::MAX, f32::MAX, f32::MAX, f32::MIN, f32::MIN, f32::MIN];
    for tri in &world {
        for p in tri {
            for k in 0..3 {
                b[k] = b[k].min(p[k]);
                b[k + 3] = b[k + 3].max(p[k]);
            }
        }
    }
    let per = mesh.triangle_count();
    let mut agree = 0;
    let mut hits = 0;
    for ray in rays(b, 300, 3) {
        let got = accel::closest_hit(tlas, &view, ray, RayFlags(0), 0xFF);
        // Brute force in world space: t differs in the last bits from the object-space test,
        // so compare the identity of the hit and t within a relative tolerance.
        let mut best: Option<(f32, usize)> = None;
        for (k, tri) in world.iter().enumerate() {
            if let Some((d, _, _, _)) = accel::intersect_triangle(&ray, Vec3::from(tri[0]), Vec3::from(tri[1]), Vec3::from(tri[2])) {
                if best.is_none_or(|(bd, _)| d < bd) {
                    best = Some((d, k));
                }
            }
        }
        match (got, best) {
            (None, None) => agree += 1,
            (Some(h), Some((d, k))) => {
                hits += 1;
                assert!((h.t - d).abs() <= 1e-3 * d.abs().max(1.0), "t {} vs {d}", h.t);
                if h.instance_index as usize == k / per && h.primitive_index as usize == k % per {
                    agree += 1;
                } else {
                    // A different triangle at (almost) the same distance: only near-ties allowed.
                    assert!((h.t - d).abs() <= 1e-4 * d.abs().max(1.0), "different hit {h:?} vs ({d}, {k})");
                    agree += 1;
                }
                assert_eq!(h.instance_custom_index, 100 + h.instance_index);
            }
            (g, w) => panic!("ray {ray:?}: traversal {g:?} brute force {w:?}"),
        }
    }
    assert_eq!(agree, 300);
    assert!(hits > 30, "too few hits ({hits})");
    a.destroy();
    ctx.finish();
}

/// Several threads build different structures at once, each on its own queue.
#[test]
fn concurrent_builds_from_several_threads() {
    let ctx = as_context();
    let mesh = bunny();
    let reference = {
        let a = Accel::new(&ctx);
        let m = upload_mesh(&a, &mesh);
        let s = a.serialize(device_blas(&a, &m, vk::BuildAccelerationStructureFlagsKHR::empty()));
        a.destroy();
        s
    };
    std::thread::scope(|sc| {
        for q in 1..4 {
            let (ctx, mesh, reference) = (&ctx, &mesh, &reference);
            sc.spawn(move || {
                let mut a = Accel::new(ctx);
                a.queue = q;
                let m = upload_mesh(&a, mesh);
                let s = a.serialize(device_blas(&a, &m, vk::BuildAccelerationStructureFlagsKHR::empty()));
                assert_eq!(&s, reference);
                a.destroy();
            });
        }
    });
    ctx.finish();
}

/// Refit: move the vertices, UPDATE in place and from src into another structure; both equal
/// and traversal equals brute force over the moved mesh.
#[test]
fn update_refits_in_place_and_into_another_structure() {
    let ctx = as_context();
    let a = Accel::new(&ctx);
    let mut mesh = bunny();
    let m = upload_mesh(&a, &mesh);
    let flags = vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE | vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE;
    let s = device_blas(&a, &m, flags);
    // Move every vertex (a smooth deformation) and upload the new positions.
    for p in mesh.positions.iter_mut() {
        p[1] += 0.02 * (p[0] * 40.0).sin();
        p[0] *= 1.1;
    }
    a.buf(m.vertices).write(0, &mesh.vertex_bytes());
    let geoms = [triangles(a.buf(m.vertices).address, a.buf(m.indices).address, m.max_vertex)];
    let info = blas_info(&geoms, flags);
    let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &[m.count]);
    assert!(sizes.update_scratch_size > 0);
    let scratch = a.buffer(sizes.update_scratch_size.max(sizes.build_scratch_size));
    let (s2, _) = a.structure(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, sizes.acceleration_structure_size);
    let saddr = a.buf(scratch).address;
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(m.count)];
    // src → dst first (src keeps the old geometry), then in place.
    let into_other = info
        .mode(vk::BuildAccelerationStructureModeKHR::UPDATE)
        .src_acceleration_structure(s)
        .dst_acceleration_structure(s2)
        .scratch_data(vk::DeviceOrHostAddressKHR { device_address: saddr });
    a.submit(|cb| {
        // SAFETY: valid infos.
        unsafe { a.ext.cmd_build_acceleration_structures(cb, &[into_other], &[&range]) };
    });
    let in_place = info
        .mode(vk::BuildAccelerationStructureModeKHR::UPDATE)
        .src_acceleration_structure(s)
        .dst_acceleration_structure(s)
        .scratch_data(vk::DeviceOrHostAddressKHR { device_address: saddr });
    a.submit(|cb| {
        // SAFETY: valid infos.
        unsafe { a.ext.cmd_build_acceleration_structures(cb, &[in_place], &[&range]) };
    });
    let x = a.serialize(s);
    let y = a.serialize(s2);
    assert_eq!(x, y, "in-place and src→dst updates differ");
    let blob = payload(&x);
    let mut hits = 0;
    for ray in rays(mesh.bounds(), 1500, 5) {
        let got = accel::closest_hit(blob, &NoDevice, ray, RayFlags(0), 0xFF).map(|h| (h.t, h.primitive_index));
        let want = brute_closest(&mesh, &ray);
        assert_eq!(got, want, "after refit, ray {ray:?}");
        hits += want.is_some() as u32;
    }
    assert!(hits > 100);
    a.destroy();
    ctx.finish();
}

/// Limits meet the spec's minimums (maxPrimitiveCount 2^29-1, which lavapipe misses) and the
/// size query answers for the maximum counts without overflowing.
#[test]
fn limits_and_size_queries_for_maximum_counts() {
    let ctx = as_context();
    let a = Accel::new(&ctx);
    let mut asp = vk::PhysicalDeviceAccelerationStructurePropertiesKHR::default();
    let mut asf = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default();
    // SAFETY: plain queries.
    unsafe {
        let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut asp);
        ctx.instance.get_physical_device_properties2(ctx.physical, &mut p2);
        let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut asf);
        ctx.instance.get_physical_device_features2(ctx.physical, &mut f2);
    }
    assert!(asp.max_geometry_count >= (1 << 24) - 1);
    assert!(asp.max_instance_count >= (1 << 24) - 1);
    assert!(asp.max_primitive_count >= (1 << 29) - 1);
    assert!(asp.max_per_stage_descriptor_update_after_bind_acceleration_structures >= 500_000);
    assert!(asp.max_descriptor_set_update_after_bind_acceleration_structures >= 500_000);
    assert!(asp.min_acceleration_structure_scratch_offset_alignment.is_power_of_two());
    assert!(asp.min_acceleration_structure_scratch_offset_alignment <= 256);
    for f in [
        asf.acceleration_structure,
        asf.acceleration_structure_capture_replay,
        asf.acceleration_structure_indirect_build,
        asf.acceleration_structure_host_commands,
        asf.descriptor_binding_acceleration_structure_update_after_bind,
    ] {
        assert_eq!(f, vk::TRUE, "every optional feature is on");
    }
    let geoms = [triangles(0, 0, u32::MAX)];
    let info = blas_info(&geoms, vk::BuildAccelerationStructureFlagsKHR::empty());
    let max = asp.max_primitive_count as u32;
    let small = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &[1 << 20]);
    let big = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &[max]);
    let big1 = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &[max - 1]);
    // Linear in the count: no 32-bit wrap anywhere (a wrapped size would be far smaller).
    assert!(big.acceleration_structure_size >= small.acceleration_structure_size * 500);
    assert!(big.acceleration_structure_size > big1.acceleration_structure_size);
    assert!(big.build_scratch_size >= small.build_scratch_size * 500);
    assert!(big.acceleration_structure_size >= max as u64 * 36, "at least the triangles' vertices");
    let tgeoms = [instances(0)];
    let tinfo = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(vk::AccelerationStructureTypeKHR::TOP_LEVEL)
        .geometries(&tgeoms);
    let t = a.sizes(vk::AccelerationStructureBuildTypeKHR::HOST_OR_DEVICE, &tinfo, &[asp.max_instance_count as u32]);
    assert!(t.acceleration_structure_size >= asp.max_instance_count * 64);
    a.destroy();
    ctx.finish();
}

/// accelerationStructureCaptureReplay: a structure created with a captured deviceAddress on a
/// replay device gets exactly that address (its memory replayed at the captured address); a
/// deviceAddress that cannot be honoured is refused with VK_ERROR_INVALID_OPAQUE_CAPTURE_ADDRESS.
#[test]
fn capture_replay_reproduces_structure_addresses() {
    let usage = harness::accel::ALL_USAGE;
    let flags = vk::MemoryAllocateFlags::DEVICE_ADDRESS | vk::MemoryAllocateFlags::DEVICE_ADDRESS_CAPTURE_REPLAY;
    let size = 1u64 << 20;
    // Returns (memory capture address, structure address, serialization of a build into it).
    let capture_run = |replay: Option<(u64, u64)>| -> (u64, u64, Vec<u8>) {
        let ctx = as_context();
        let a = Accel::new(&ctx);
        let mesh = bunny();
        let m = upload_mesh(&a, &mesh);
        // SAFETY: valid create infos; everything is destroyed before the context.
        let out = unsafe {
            let d = &ctx.device;
            let b = d
                .create_buffer(&vk::BufferCreateInfo::default().size(size).usage(usage).flags(vk::BufferCreateFlags::DEVICE_ADDRESS_CAPTURE_REPLAY), None)
                .unwrap();
            let mut f = vk::MemoryAllocateFlagsInfo::default().flags(flags);
            let mut opaque = vk::MemoryOpaqueCaptureAddressAllocateInfo::default().opaque_capture_address(replay.map_or(0, |r| r.0));
            let ai = vk::MemoryAllocateInfo::default().allocation_size(size).memory_type_index(0).push_next(&mut f).push_next(&mut opaque);
            let mem = d.allocate_memory(&ai, None).unwrap();
            d.bind_buffer_memory(b, mem, 0).unwrap();
            let mem_addr = a.bda.get_device_memory_opaque_capture_address(&vk::DeviceMemoryOpaqueCaptureAddressInfo::default().memory(mem));
            let ci = vk::AccelerationStructureCreateInfoKHR::default()
                .buffer(b)
                .offset(256)
                .size(size - 256)
                .ty(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL)
                .create_flags(vk::AccelerationStructureCreateFlagsKHR::DEVICE_ADDRESS_CAPTURE_REPLAY)
                .device_address(replay.map_or(0, |r| r.1));
            let s = a.ext.create_acceleration_structure(&ci, None).unwrap();
            let addr = a.address_of(s);
            if let Some((_, wanted)) = replay {
                assert_eq!(addr, wanted, "replayed structure address");
                let bad = ci.device_address(wanted + 256);
                assert_eq!(a.ext.create_acceleration_structure(&bad, None).err(), Some(vk::Result::ERROR_INVALID_OPAQUE_CAPTURE_ADDRESS_KHR));
            }
            let geoms = [triangles(a.buf(m.vertices).address, a.buf(m.indices).address, m.max_vertex)];
            let info = blas_info(&geoms, vk::BuildAccelerationStructureFlagsKHR::empty());
            let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &[m.count]);
            assert!(sizes.acceleration_structure_size <= size - 256);
            let scratch = a.buffer(sizes.build_scratch_size);
            let info = info.dst_acceleration_structure(s).scratch_data(vk::DeviceOrHostAddressKHR { device_address: a.buf(scratch).address });
            let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(m.count)];
            a.submit(|cb| a.ext.cmd_build_acceleration_structures(cb, &[info], &[&range]));
            let ser = a.serialize(s);
            a.ext.destroy_acceleration_structure(s, None);
            d.destroy_buffer(b, None);
            d.free_memory(mem, None);
            (mem_addr, addr, ser)
        };
        a.destroy();
        ctx.finish();
        out
    };
    let (mem_addr, addr, captured) = capture_run(None);
    assert_eq!(addr % 256, 0);
    let (_, replayed_addr, replayed) = capture_run(Some((mem_addr, addr)));
    assert_eq!(replayed_addr, addr);
    assert_eq!(replayed, captured, "the same build at the same address gives the same bytes");
}

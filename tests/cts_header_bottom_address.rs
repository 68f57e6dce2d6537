//! The Vulkan CTS group `dEQP-VK.ray_tracing_pipeline.acceleration_structures.header_bottom_address`
//! (VK-GL-CTS, external/vulkancts/modules/vulkan/ray_tracing/vktRayTracingAccelerationStructuresTests.cpp:
//! `addUpdateHeaderBottomAddressTests`, `RayTracingHeaderBottomAddressTestInstance`; later CTS
//! versions put the same cases under a `traditional_structures` level), followed step by step
//! through the loader with the validation layer on. Its six cases are
//! `{cpu_built,gpu_built}.{the_same_instances,different_instances,mix_same_diff_instances}`, with
//! width RTAS_DEFAULT_SIZE = 8:
//!
//! - `the_same_instances` (IDENTICAL_INSTANCES): 8 instances of one BLAS;
//! - `different_instances` (DIFFERENT_INSTANCES): 8 instances, each of its own BLAS;
//! - `mix_same_diff_instances` (MIX_INSTANCES): 16 instances, two fresh BLASes per step, as the
//!   CTS builds them (so, despite the name, no BLAS is shared);
//! - `cpu_built` (every build, query, serialization and deserialization a host command) and
//!   `gpu_built` (device commands).
//!
//! Instance i is translated by (i, i, 0), as in the CTS. The steps: build; read the per-instance
//! BLAS addresses; "deep" serialization (the TLAS and every BLAS it refers to); deserialize each
//! BLAS into a new structure and the TLAS, its header handles rewritten to the new BLASes, into a
//! new TLAS; "shallow" serialization of the new TLAS. The CTS then checks that the new TLAS and
//! BLAS addresses all differ from the old ones and that the shallow header lists one handle per
//! instance whose set equals the new BLAS addresses. Here, besides, each handle is checked in
//! instance order, the header's UUIDs, sizes and count against the device and the queries, and
//! the deserialized TLAS is traversed (through `arbor::accel` over the new BLASes' bytes): every
//! instance is hit where its transform puts it, with its custom index.
//! The CTS's BLAS is one triangle; here it is the harness grid (the unit square), which keeps
//! instances apart at (i, i). Lavapipe is not covered here (its host commands are absent, and the
//! traversal check reads the structure's bytes through the Arbor library).
mod harness;

use std::collections::{BTreeSet, HashMap};
use std::ffi::c_void;

use arbor::accel::{self, MapView, Ray, RayFlags};
use ash::vk;
use ash::vk::Handle;
use glam::Vec3;
use harness::vuid::*;

const WIDTH: u32 = 8;

#[derive(Clone, Copy, Debug)]
enum Layout {
    Same,
    Different,
    Mix,
}

impl Layout {
    /// Distinct BLASes to build and, per instance, the BLAS it refers to.
    fn plan(self) -> (usize, Vec<usize>) {
        match self {
            Layout::Same => (1, vec![0; WIDTH as usize]),
            Layout::Different => (WIDTH as usize, (0..WIDTH as usize).collect()),
            Layout::Mix => (2 * WIDTH as usize, (0..2 * WIDTH as usize).collect()),
        }
    }
}

fn translated(i: usize) -> [f32; 12] {
    let d = i as f32;
    [1.0, 0.0, 0.0, d, 0.0, 1.0, 0.0, d, 0.0, 0.0, 1.0, 0.0]
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

/// Builds one structure on the host or the device from `geoms` with `count` primitives.
fn build(a: &Accel, ty: vk::AccelerationStructureTypeKHR, geoms: &[Geom], count: u32, host: bool) -> Dst {
    let inf = info(ty, NO_FLAGS, geoms);
    let kind = if host { vk::AccelerationStructureBuildTypeKHR::HOST } else { DEVICE };
    let sizes = a.sizes(kind, &inf, &[count]);
    let dst = guarded_structure(a, ty, sizes.acceleration_structure_size);
    if host {
        let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
        let inf = inf
            .dst_acceleration_structure(dst.s)
            .scratch_data(vk::DeviceOrHostAddressKHR { host_address: scratch.as_mut_ptr() as *mut c_void });
        // SAFETY: host pointers into live buffers and Vecs, valid for the call.
        unsafe { a.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[inf], &[&[range(count)]]) }.unwrap();
    } else {
        let scratch = guarded(a, sizes.build_scratch_size);
        cmd_build(a, &[inf.dst_acceleration_structure(dst.s).scratch_data(madr(scratch.address(a)))], &[&[range(count)]]);
    }
    dst
}

fn build_blas(a: &Accel, m: &Mesh, host: bool) -> Dst {
    let geom = if host { host_grid_geom(a, m) } else { mesh_geom(a, m) };
    build(a, BLAS, &[geom], m.count, host)
}

/// Instance i refers to `refs[i]`: a structure handle for a host build, a device address for a
/// device build (the spec's two meanings of accelerationStructureReference).
fn build_tlas(a: &Accel, refs: &[u64], host: bool) -> Dst {
    let records: Vec<u8> = refs.iter().enumerate().flat_map(|(i, &r)| instance_record(translated(i), i as u32, 0xFF, 0, 0, r)).collect();
    let n = refs.len() as u32;
    if host {
        build(a, TLAS, &[instances_geom(records.as_ptr() as u64, false)], n, true)
    } else {
        let data = guarded_data(a, &records);
        build(a, TLAS, &[instances_geom(data.address(a), false)], n, false)
    }
}

/// One property of one structure: vkWriteAccelerationStructuresPropertiesKHR on the host side,
/// a query pool written by vkCmdWriteAccelerationStructuresPropertiesKHR on the device side.
fn property(a: &Accel, s: &Dst, ty: vk::QueryType, host: bool) -> u64 {
    if !host {
        return a.query(s.s, ty);
    }
    let mut out = [0u8; 8];
    // SAFETY: one live structure, an 8-byte slot.
    unsafe { a.ext.write_acceleration_structures_properties(&[s.s], ty, &mut out, 8) }.unwrap();
    u64::from_le_bytes(out)
}

/// vkCopyAccelerationStructureToMemoryKHR into a host Vec, or the device command into a buffer.
fn serialize(a: &Accel, s: &Dst, host: bool) -> Vec<u8> {
    let size = property(a, s, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR, host) as usize;
    let out = if host {
        let mut out = vec![0u8; size + 16];
        let at = out.as_ptr().align_offset(16);
        let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
            .src(s.s)
            .dst(vk::DeviceOrHostAddressKHR { host_address: out[at..].as_mut_ptr() as *mut c_void })
            .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
        // SAFETY: a host pointer to enough bytes, aligned to 16.
        unsafe { a.ext.copy_acceleration_structure_to_memory(vk::DeferredOperationKHR::null(), &info) }.unwrap();
        out[at..at + size].to_vec()
    } else {
        let dst = guarded(a, size as u64);
        let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
            .src(s.s)
            .dst(madr(dst.address(a)))
            .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
        // SAFETY: recording command buffer, valid info.
        a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) });
        let bytes = dst.read(a);
        assert_guards(a, dst);
        bytes
    };
    assert_eq!(u64_at(&out, 32), size as u64, "header: serialized size differs from the query");
    out
}

/// Deserializes `blob` into a new structure of the size its header names.
fn deserialize(a: &Accel, ty: vk::AccelerationStructureTypeKHR, blob: &[u8], host: bool) -> Dst {
    let dst = guarded_structure(a, ty, u64_at(blob, 40));
    if host {
        let mut copy = vec![0u8; blob.len() + 16];
        let at = copy.as_ptr().align_offset(16);
        copy[at..at + blob.len()].copy_from_slice(blob);
        let info = vk::CopyMemoryToAccelerationStructureInfoKHR::default()
            .src(vk::DeviceOrHostAddressConstKHR { host_address: copy[at..].as_ptr() as *const c_void })
            .dst(dst.s)
            .mode(vk::CopyAccelerationStructureModeKHR::DESERIALIZE);
        // SAFETY: a host pointer to the serialized bytes, aligned to 16.
        unsafe { a.ext.copy_memory_to_acceleration_structure(vk::DeferredOperationKHR::null(), &info) }.unwrap();
    } else {
        let data = guarded_data(a, blob);
        let info = vk::CopyMemoryToAccelerationStructureInfoKHR::default()
            .src(cadr(data.address(a)))
            .dst(dst.s)
            .mode(vk::CopyAccelerationStructureModeKHR::DESERIALIZE);
        // SAFETY: recording command buffer, valid info.
        a.submit(|cb| unsafe { a.ext.cmd_copy_memory_to_acceleration_structure(cb, &info) });
    }
    assert!(header_of(a, &dst).is_some(), "the deserialized structure does not read as valid");
    dst
}

/// The header's UUIDs: the driver UUID is the device's, and the device calls the pair compatible.
fn check_uuids(a: &Accel, blob: &[u8]) {
    let mut id = vk::PhysicalDeviceIDProperties::default();
    let mut props = vk::PhysicalDeviceProperties2::default().push_next(&mut id);
    // SAFETY: a live physical device; the chain lives for the call.
    unsafe { a.ctx.instance.get_physical_device_properties2(a.ctx.physical, &mut props) };
    assert_eq!(blob[..16], id.driver_uuid, "header: driver UUID");
    let v = vk::AccelerationStructureVersionInfoKHR::default().version_data(blob[..32].try_into().unwrap());
    // SAFETY: 32 bytes of version data.
    let compat = unsafe { a.ext.get_device_acceleration_structure_compatibility(&v) };
    assert_eq!(compat, vk::AccelerationStructureCompatibilityKHR::COMPATIBLE);
}

/// The header of a serialized TLAS: UUIDs, sizes, and one handle per instance, equal to `expect`.
fn check_header(a: &Accel, blob: &[u8], tlas: &Dst, expect: &[u64], host: bool) {
    check_uuids(a, blob);
    let pointers = vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_BOTTOM_LEVEL_POINTERS_KHR;
    assert_eq!(property(a, tlas, pointers, host), expect.len() as u64, "BOTTOM_LEVEL_POINTERS query");
    assert_eq!(u64_at(blob, 48), expect.len() as u64, "header: handle count");
    assert!(blob.len() >= 56 + 8 * expect.len(), "the handles run past the blob");
    let handles: Vec<u64> = (0..expect.len()).map(|k| u64_at(blob, 56 + 8 * k)).collect();
    assert_eq!(handles, expect, "header: handles in instance order");
}

/// Every instance i of `tlas` shows the grid at (i + x, i + y) with custom index i.
fn assert_instances_hit(tlas: &[u8], view: &MapView, n: usize) {
    for i in 0..n {
        let d = i as f32;
        let ray = Ray { origin: Vec3::new(d + 0.3, d + 0.6, 1.0), direction: Vec3::new(0.0, 0.0, -1.0), tmin: 0.0, tmax: 10.0 };
        let hit = accel::closest_hit(tlas, view, ray, RayFlags(0), 0xFF).unwrap_or_else(|| panic!("instance {i} missed"));
        assert_eq!((hit.t, hit.instance_index, hit.instance_custom_index), (1.0, i as u32, i as u32), "instance {i}");
    }
}

// One function: the CTS case is one sequence of build, deep serialization, deserialization and
// shallow serialization, checked at each step; split up, its state would travel in a struct.
fn header_bottom_address(layout: Layout, host: bool) {
    let ctx = harness::Context::new(harness::Options { acceleration_structure: true, ..Default::default() });
    let a = Accel::new(&ctx);
    let m = upload_grid(&a);
    let (distinct, refs) = layout.plan();
    let blases: Vec<Dst> = (0..distinct).map(|_| build_blas(&a, &m, host)).collect();
    let old: Vec<u64> = blases.iter().map(|b| a.address_of(b.s)).collect();
    let in_addrs: Vec<u64> = refs.iter().map(|&r| old[r]).collect();
    let references: Vec<u64> = if host { refs.iter().map(|&r| blases[r].s.as_raw()).collect() } else { in_addrs.clone() };
    let src = build_tlas(&a, &references, host);
    let mut view = MapView::new();
    for (b, &addr) in blases.iter().zip(&old) {
        view.insert(addr, b.r.read(&a));
    }
    assert_instances_hit(&src.r.read(&a), &view, refs.len());

    // Deep serialization: the TLAS, then each BLAS it refers to.
    let mut tlas_blob = serialize(&a, &src, host);
    check_header(&a, &tlas_blob, &src, &in_addrs, host);
    let blas_blobs: Vec<Vec<u8>> = blases.iter().map(|b| serialize(&a, b, host)).collect();
    for blob in &blas_blobs {
        check_uuids(&a, blob);
        assert_eq!(u64_at(blob, 48), 0, "a BLAS header lists handles");
    }

    // Deserialize each BLAS into a new structure, point the TLAS header at them, deserialize it.
    let new_blases: Vec<Dst> = blas_blobs.iter().map(|b| deserialize(&a, BLAS, b, host)).collect();
    let new: Vec<u64> = new_blases.iter().map(|b| a.address_of(b.s)).collect();
    let moved: HashMap<u64, u64> = old.iter().copied().zip(new.iter().copied()).collect();
    let out_addrs: Vec<u64> = in_addrs.iter().map(|h| moved[h]).collect();
    for (k, h) in out_addrs.iter().enumerate() {
        tlas_blob[56 + 8 * k..64 + 8 * k].copy_from_slice(&h.to_le_bytes());
    }
    let dst = deserialize(&a, TLAS, &tlas_blob, host);

    // The CTS's checks: every address differs from the old ones, and the shallow serialization's
    // header lists one handle per instance whose set is the new BLAS addresses.
    assert_ne!(a.address_of(dst.s), a.address_of(src.s), "the TLAS address did not change");
    let old_set: BTreeSet<u64> = old.iter().copied().collect();
    assert!(new.iter().all(|n| !old_set.contains(n)), "a new BLAS has an old address");
    let shallow = serialize(&a, &dst, host);
    check_header(&a, &shallow, &dst, &out_addrs, host);
    let listed: BTreeSet<u64> = (0..refs.len()).map(|k| u64_at(&shallow, 56 + 8 * k)).collect();
    assert_eq!(listed, new.iter().copied().collect::<BTreeSet<u64>>(), "the header's handle set");

    // The deserialized TLAS is usable: it traverses over the new BLASes.
    let mut new_view = MapView::new();
    for (b, &addr) in new_blases.iter().zip(&new) {
        new_view.insert(addr, b.r.read(&a));
    }
    assert_instances_hit(&dst.r.read(&a), &new_view, refs.len());
    for d in blases.into_iter().chain(new_blases).chain([src, dst]) {
        assert_guards(&a, d.r);
    }
    a.destroy();
    ctx.finish();
}

#[test]
fn gpu_built_the_same_instances() {
    header_bottom_address(Layout::Same, false);
}

#[test]
fn cpu_built_the_same_instances() {
    header_bottom_address(Layout::Same, true);
}

#[test]
fn gpu_built_different_instances() {
    header_bottom_address(Layout::Different, false);
}

#[test]
fn cpu_built_different_instances() {
    header_bottom_address(Layout::Different, true);
}

#[test]
fn gpu_built_mix_same_diff_instances() {
    header_bottom_address(Layout::Mix, false);
}

#[test]
fn cpu_built_mix_same_diff_instances() {
    header_bottom_address(Layout::Mix, true);
}

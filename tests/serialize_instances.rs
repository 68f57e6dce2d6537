//! Serialization of a TLAS whose instances share BLASes, through the loader (the Vulkan CTS
//! `header_bottom_address.*.the_same_instances` scenario): the serialized header lists one
//! handle per active instance, duplicates included, in instance order; the
//! SERIALIZATION_BOTTOM_LEVEL_POINTERS query reports the same count; the application rewrites
//! every handle and deserialization relocates each instance by its own handle.
mod harness;

use std::ffi::c_void;

use arbor::accel::{self, MapView, Ray, RayFlags};
use ash::vk;
use ash::vk::Handle;
use glam::Vec3;
use harness::vuid::*;

const INSTANCES: u32 = 8;

fn translated(x: f32) -> [f32; 12] {
    [1.0, 0.0, 0.0, x, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
}

/// Eight instances of `reference` side by side (instance k at x = 2k, custom index k), and a
/// ninth, inactive one in the middle (reference 0), which contributes no handle.
fn instance_bytes(reference: u64) -> Vec<u8> {
    let mut out = Vec::new();
    for k in 0..INSTANCES {
        if k == 4 {
            out.extend(instance_record(translated(100.0), 99, 0xFF, 0, 0, 0));
        }
        out.extend(instance_record(translated(2.0 * k as f32), k, 0xFF, 0, 0, reference));
    }
    out
}

/// Every instance k of `tlas` (bytes) shows the grid at x in [2k, 2k + 1], with its custom
/// index, when `view` holds the BLAS it refers to.
fn assert_instances_hit(tlas: &[u8], view: &MapView) {
    for k in 0..INSTANCES {
        let ray = Ray { origin: Vec3::new(2.0 * k as f32 + 0.3, 0.4, 1.0), direction: Vec3::new(0.0, 0.0, -1.0), tmin: 0.0, tmax: 10.0 };
        let hit = accel::closest_hit(tlas, view, ray, RayFlags(0), 0xFF).unwrap_or_else(|| panic!("instance {k} missed"));
        assert_eq!((hit.t, hit.instance_custom_index), (1.0, k));
    }
}

/// Builds the TLAS on the device or the host; returns it.
fn build_tlas(a: &Accel, blas: &Dst, host: bool) -> Dst {
    let count = INSTANCES + 1;
    if host {
        let insts = instance_bytes(blas.s.as_raw());
        let geoms = [instances_geom(insts.as_ptr() as u64, false)];
        let inf = info(TLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::HOST, &inf, &[count]);
        let tlas = guarded_structure(a, TLAS, sizes.acceleration_structure_size);
        let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
        let inf = inf
            .dst_acceleration_structure(tlas.s)
            .scratch_data(vk::DeviceOrHostAddressKHR { host_address: scratch.as_mut_ptr() as *mut c_void });
        // SAFETY: host pointers into live Vecs, valid for the call.
        unsafe { a.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[inf], &[&[range(count)]]) }.unwrap();
        tlas
    } else {
        let insts = guarded_data(a, &instance_bytes(a.address_of(blas.s)));
        let geoms = [instances_geom(insts.address(a), false)];
        let inf = info(TLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(DEVICE, &inf, &[count]);
        let tlas = guarded_structure(a, TLAS, sizes.acceleration_structure_size);
        let scratch = guarded(a, sizes.build_scratch_size);
        cmd_build(a, &[inf.dst_acceleration_structure(tlas.s).scratch_data(madr(scratch.address(a)))], &[&[range(count)]]);
        tlas
    }
}

/// One property through vkWriteAccelerationStructuresPropertiesKHR.
fn host_property(a: &Accel, s: &Dst, ty: vk::QueryType) -> u64 {
    let mut out = [0u8; 8];
    // SAFETY: one live structure, an 8-byte slot.
    unsafe { a.ext.write_acceleration_structures_properties(&[s.s], ty, &mut out, 8) }.unwrap();
    u64::from_le_bytes(out)
}

fn serialize(a: &Accel, s: &Dst, host: bool) -> Vec<u8> {
    if !host {
        return a.serialize(s.s);
    }
    let size = [host_property(a, s, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR)];
    let mut out = vec![0u8; size[0] as usize + 16];
    let at = out.as_ptr().align_offset(16);
    let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
        .src(s.s)
        .dst(vk::DeviceOrHostAddressKHR { host_address: out[at..].as_mut_ptr() as *mut c_void })
        .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
    // SAFETY: a host pointer to enough bytes, aligned to 16.
    unsafe { a.ext.copy_acceleration_structure_to_memory(vk::DeferredOperationKHR::null(), &info) }.unwrap();
    out[at..at + size[0] as usize].to_vec()
}

fn deserialize(a: &Accel, blob: &[u8], dst: &Dst, host: bool) {
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
}

fn the_same_instances(host: bool) {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let address = a.address_of(blas.s);
        let tlas = build_tlas(a, &blas, host);
        let mut view = MapView::new();
        view.insert(address, blas.r.read(a));
        assert_instances_hit(&tlas.r.read(a), &view);
        // The count: the query (device and host forms) and the header agree, one per active instance.
        let pointers = vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_BOTTOM_LEVEL_POINTERS_KHR;
        assert_eq!(a.query(tlas.s, pointers), INSTANCES as u64);
        assert_eq!(host_property(a, &tlas, pointers), INSTANCES as u64);
        let mut blob = serialize(a, &tlas, host);
        assert_eq!(u64::from_le_bytes(blob[48..56].try_into().unwrap()), INSTANCES as u64);
        for k in 0..INSTANCES as usize {
            assert_eq!(u64::from_le_bytes(blob[56 + 8 * k..64 + 8 * k].try_into().unwrap()), address, "handle {k}");
        }
        // A new BLAS (created and built) replaces the old one in every handle.
        let (moved, _) = valid_blas(a, m, NO_FLAGS);
        let moved_address = a.address_of(moved.s);
        for k in 0..INSTANCES as usize {
            blob[56 + 8 * k..64 + 8 * k].copy_from_slice(&moved_address.to_le_bytes());
        }
        let size = u64::from_le_bytes(blob[40..48].try_into().unwrap());
        let copy = guarded_structure(a, TLAS, size);
        deserialize(a, &blob, &copy, host);
        let bytes = copy.r.read(a);
        assert!(accel::header(&bytes).is_some(), "the rewritten blob was rejected");
        assert_eq!(accel::blas_references(&bytes), vec![moved_address; INSTANCES as usize]);
        let mut moved_view = MapView::new();
        moved_view.insert(moved_address, moved.r.read(a));
        assert_instances_hit(&bytes, &moved_view);
        assert_guards(a, copy.r);
    });
}

#[test]
fn device_built_tlas_lists_one_handle_per_instance() {
    the_same_instances(false);
}

#[test]
fn host_built_tlas_lists_one_handle_per_instance() {
    the_same_instances(true);
}

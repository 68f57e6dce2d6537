//! The handle list of serialized TLAS data, rewritten by the application: each handle must
//! name a bottom-level structure. Garbage (16 TiB, a freed BLAS, a TLAS, the destination
//! itself, 0, an address inside a BLAS, a vertex buffer) is rejected by VUID on the device and
//! the host paths, and only the destination's invalid mark is written.
mod harness;

use std::ffi::c_void;

use arbor::accel::{self, MapView};
use ash::vk;
use harness::vuid::*;

const VUID: &str = "VUID-VkCopyMemoryToAccelerationStructureInfoKHR-src-04960";

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
        let r = unsafe { a.ext.copy_memory_to_acceleration_structure(vk::DeferredOperationKHR::null(), &info) };
        assert_eq!(r, Ok(()), "outside strict mode an invalid host copy is reported, not failed");
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

fn garbage_handles(host: bool) {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let (tlas, _) = prebuilt_tlas(a, &blas, 0, 0);
        let blob = a.serialize(tlas.s);
        assert_eq!(u64::from_le_bytes(blob[48..56].try_into().unwrap()), 1);
        let (victim, _) = prebuilt_tlas(a, &blas, tlas.r.len, 0);
        let freed = freed_address(a, 4096);
        let plain = guarded_with(a, 4096, without(vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR));
        plain.write(a, 0, &m.vertex_bytes[..256]);
        let cases: [(u64, &str); 7] = [
            (1 << 44, "does not address live memory"),
            (freed, "does not address live memory"),
            (a.address_of(tlas.s), "is a top-level structure"),
            (a.address_of(victim.s), "addresses the destination itself"),
            (0, "is 0"),
            (a.address_of(blas.s) + 64, "not 256-aligned"),
            (plain.address(a), if host { "is neither a built structure" } else { "ACCELERATION_STRUCTURE_STORAGE" }),
        ];
        for (handle, needle) in cases {
            let mut bad = blob.clone();
            bad[56..64].copy_from_slice(&handle.to_le_bytes());
            if header_of(a, &victim).is_none() {
                // Rebuild the victim so each case starts from a valid destination.
                let good = blob.clone();
                deserialize(a, &good, &victim, host);
            }
            expect_invalid(
                a,
                Expect {
                    command: if host { "vkCopyMemoryToAccelerationStructureKHR" } else { "vkCmdCopyMemoryToAccelerationStructureKHR" },
                    vuid: VUID.into(),
                    needles: &["handle 0 (", needle],
                    writable: &[victim.r],
                    invalidated: &[&victim],
                },
                || deserialize(a, &bad, &victim, host),
            );
            assert_guards(a, victim.r);
        }
        // The real handle deserializes and traces.
        deserialize(a, &blob, &victim, host);
        let mut view = MapView::new();
        view.insert(a.address_of(blas.s), blas.r.read(a));
        assert_grid_hits(&victim.r.read(a), &view);
        // Traversal never follows a reference that resolves to no BLAS: the instance is absent
        // and the query names the reference once.
        let bytes = victim.r.read(a);
        let ray = accel::Ray { origin: glam::Vec3::new(0.3, 0.3, 1.0), direction: glam::Vec3::new(0.0, 0.0, -1.0), tmin: 0.0, tmax: 10.0 };
        let mut q = accel::RayQuery::new(&bytes, &accel::NoDevice, ray, accel::RayFlags(0), 0xFF);
        assert!(q.proceed().is_none() && q.committed().is_none());
        assert_eq!(q.unresolved_reference(), Some(a.address_of(blas.s)));
    });
}

#[test]
fn garbage_handles_on_the_device_path_04960() {
    garbage_handles(false);
}

#[test]
fn garbage_handles_on_the_host_path_04960() {
    garbage_handles(true);
}

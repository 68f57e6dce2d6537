//! Valid usage of vkBuildAccelerationStructuresKHR, the host build, with and without a deferred
//! operation: an invalid host build is reported and skipped, and returns success outside strict
//! mode.
mod harness;

use std::ffi::c_void;

use ash::vk;
use harness::vuid::*;

#[test]
fn host_build_into_a_structure_of_another_type_03700() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let host_geoms = [tri(m.v.host_ptr(a) as u64, m.i.host_ptr(a) as u64, m.max_vertex, 0)];
        let inf = info(BLAS, NO_FLAGS, &host_geoms);
        let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::HOST, &inf, &[m.count]);
        let (victim, _) = prebuilt_tlas(a, &blas, sizes.acceleration_structure_size, 0);
        let mut host_scratch = vec![FILL; sizes.build_scratch_size as usize + 2 * GUARD as usize];
        let scratch_ptr = host_scratch[GUARD as usize..].as_mut_ptr() as *mut c_void;
        let inf = inf
            .dst_acceleration_structure(victim.s)
            .scratch_data(vk::DeviceOrHostAddressKHR { host_address: scratch_ptr });
        let mut result = Ok(());
        expect_invalid(
            a,
            Expect {
                command: HOST,
                vuid: format!("VUID-{HOST}-pInfos-03700"),
                needles: &["pInfos[0]: dstAccelerationStructure was created with another type"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            // SAFETY: host pointers into mapped memory and a live Vec, valid for the call.
            || result = unsafe { a.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[inf], &[&[range(m.count)]]) },
        );
        assert_eq!(result, Ok(()), "outside strict mode an invalid host build is reported, not failed");
        let n = host_scratch.len();
        assert!(host_scratch[..GUARD as usize].iter().chain(&host_scratch[n - GUARD as usize..]).all(|&b| b == FILL));
    });
}

#[test]
fn deferred_host_build_into_a_structure_of_another_type_03700() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [host_grid_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::HOST, &inf, &[m.count]);
        let (victim, _) = prebuilt_tlas(a, &blas, sizes.acceleration_structure_size, 0);
        let mut host_scratch = vec![0u8; sizes.build_scratch_size as usize];
        let inf = inf
            .dst_acceleration_structure(victim.s)
            .scratch_data(vk::DeviceOrHostAddressKHR { host_address: host_scratch.as_mut_ptr() as *mut c_void });
        // SAFETY: plain create; destroyed below after completion.
        let op = unsafe { a.deferred.create_deferred_operation(None) }.unwrap();
        let mut joined = vk::Result::SUCCESS;
        expect_invalid(
            a,
            Expect {
                command: HOST,
                vuid: format!("VUID-{HOST}-pInfos-03700"),
                needles: &["pInfos[0]: dstAccelerationStructure was created with another type"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || {
                // SAFETY: host pointers valid until the operation completes (joined here).
                let r = unsafe { a.ext.build_acceleration_structures(op, &[inf], &[&[range(m.count)]]) };
                assert!(matches!(r, Ok(()) | Err(vk::Result::OPERATION_DEFERRED_KHR) | Err(vk::Result::OPERATION_NOT_DEFERRED_KHR)), "{r:?}");
                if r == Err(vk::Result::OPERATION_DEFERRED_KHR) {
                    loop {
                        // SAFETY: live operation.
                        match unsafe { a.deferred.deferred_operation_join(op) } {
                            Ok(()) => break,
                            Err(vk::Result::THREAD_DONE_KHR) | Err(vk::Result::THREAD_IDLE_KHR) => std::thread::yield_now(),
                            Err(e) => panic!("join: {e:?}"),
                        }
                    }
                }
                // SAFETY: live operation.
                joined = unsafe { a.deferred.get_deferred_operation_result(op) }.err().unwrap_or(vk::Result::SUCCESS);
            },
        );
        assert_eq!(joined, vk::Result::SUCCESS, "outside strict mode an invalid deferred build completes with SUCCESS");
        // SAFETY: complete operation.
        unsafe { a.deferred.destroy_deferred_operation(op, None) };
    });
}

#[test]
fn host_build_into_a_destroyed_handle_03800() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let stale = destroyed_handle(a, &victim);
        let geoms = [host_grid_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::HOST, &inf, &[m.count]);
        let mut host_scratch = vec![FILL; sizes.build_scratch_size as usize];
        let inf = inf
            .dst_acceleration_structure(stale)
            .scratch_data(vk::DeviceOrHostAddressKHR { host_address: host_scratch.as_mut_ptr() as *mut c_void });
        let mut result = Ok(());
        expect_invalid(
            a,
            Expect {
                command: HOST,
                vuid: format!("VUID-{HOST}-dstAccelerationStructure-03800"),
                needles: &["pInfos[0]: dstAccelerationStructure", "is not a valid handle"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: host pointers into mapped memory and a live Vec, valid for the call.
            || result = unsafe { a.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[inf], &[&[range(m.count)]]) },
        );
        assert_eq!(result, Ok(()));
        assert!(host_scratch.iter().all(|&b| b == FILL), "the skipped host build wrote its scratch");
        assert!(header_of(a, &victim).is_some());
    });
}

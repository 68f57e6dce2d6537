//! Valid usage of the property queries: vkCmdWriteAccelerationStructuresPropertiesKHR (into a
//! query pool) and vkWriteAccelerationStructuresPropertiesKHR (into host memory).
mod harness;

use ash::vk;
use harness::vuid::*;

#[test]
fn property_query_of_a_structure_never_built_04964() {
    scenario(|a, m| {
        let _ = m;
        let unbuilt = guarded_structure(a, BLAS, 4096);
        let d = &a.ctx.device;
        let ty = vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR;
        // SAFETY: valid create info; destroyed below.
        let pool = unsafe { d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(ty).query_count(1), None) }.unwrap();
        const WRITE: &str = "vkCmdWriteAccelerationStructuresPropertiesKHR";
        expect_invalid(
            a,
            Expect {
                command: WRITE,
                vuid: format!("VUID-{WRITE}-pAccelerationStructures-04964"),
                needles: &["element 0 has not been built"],
                writable: &[],
                invalidated: &[],
            },
            || {
                a.submit(|cb| {
                    // SAFETY: recording command buffer, valid pool and structure.
                    unsafe {
                        d.cmd_reset_query_pool(cb, pool, 0, 1);
                        a.ext.cmd_write_acceleration_structures_properties(cb, &[unbuilt.s], ty, pool, 0);
                    }
                })
            },
        );
        // The command executed, so its query is available, with 0 (tests/no_hang.rs waits on it).
        let mut out = [0xA5u64; 1];
        // SAFETY: valid pool.
        let r = unsafe { d.get_query_pool_results(pool, 0, &mut out, vk::QueryResultFlags::TYPE_64) };
        assert_eq!((r, out), (Ok(()), [0]));
        // SAFETY: the pool is idle.
        unsafe { d.destroy_query_pool(pool, None) };

        // The host command reports the same and leaves the output alone.
        const HOST_WRITE: &str = "vkWriteAccelerationStructuresPropertiesKHR";
        let mut data = [0xA5u8; 8];
        expect_invalid(
            a,
            Expect {
                command: HOST_WRITE,
                vuid: format!("VUID-{HOST_WRITE}-pAccelerationStructures-04964"),
                needles: &["element 0 has not been built"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: 8 bytes of output for one query with stride 8.
            || {
                // SAFETY: valid handles of this test; the data slice outlives the call.
                let _ = unsafe { a.ext.write_acceleration_structures_properties(&[unbuilt.s], ty, &mut data, 8) };
            },
        );
        assert_eq!(data, [0xA5u8; 8]);
    });
}

#[test]
fn compacted_size_query_without_allow_compaction_03431() {
    scenario(|a, m| {
        let (s, _) = valid_blas(a, m, NO_FLAGS);
        const HOST_WRITE: &str = "vkWriteAccelerationStructuresPropertiesKHR";
        let mut data = [0xA5u8; 8];
        expect_invalid(
            a,
            Expect {
                command: HOST_WRITE,
                vuid: format!("VUID-{HOST_WRITE}-accelerationStructures-03431"),
                needles: &["element 0 was not built with ALLOW_COMPACTION"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: 8 bytes of output for one query with stride 8.
            || {
                // SAFETY: valid handles of this test; the data slice outlives the call.
                let _ = unsafe {
                    a.ext.write_acceleration_structures_properties(&[s.s], vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR, &mut data, 8)
                };
            },
        );
        assert_eq!(data, [0xA5u8; 8]);
    });
}

#[test]
fn host_property_write_with_a_stride_not_a_multiple_of_8_03448() {
    scenario(|a, m| {
        let (s, _) = valid_blas(a, m, NO_FLAGS);
        const HOST_WRITE: &str = "vkWriteAccelerationStructuresPropertiesKHR";
        let mut data = [0xA5u8; 24];
        expect_invalid(
            a,
            Expect { command: HOST_WRITE, vuid: format!("VUID-{HOST_WRITE}-queryType-03448"), needles: &["stride must be a multiple of 8"], writable: &[], invalidated: &[] },
            // SAFETY: 24 bytes of output for one query; the stride is the invalid part.
            || {
                // SAFETY: valid handles of this test; the data slice outlives the call.
                let _ = unsafe { a.ext.write_acceleration_structures_properties(&[s.s], vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR, &mut data, 12) };
            },
        );
        assert_eq!(data, [0xA5u8; 24]);
    });
}

#[test]
fn host_property_write_with_data_too_small_03452() {
    scenario(|a, m| {
        let (s0, _) = valid_blas(a, m, NO_FLAGS);
        const HOST_WRITE: &str = "vkWriteAccelerationStructuresPropertiesKHR";
        let mut data = [0xA5u8; 8];
        expect_invalid(
            a,
            Expect { command: HOST_WRITE, vuid: format!("VUID-{HOST_WRITE}-dataSize-03452"), needles: &["dataSize is smaller than"], writable: &[], invalidated: &[] },
            // SAFETY: two structures with stride 8 need 16 bytes; 8 are given (the invalid part).
            || {
                // SAFETY: valid handles of this test; the data slice outlives the call.
                let _ = unsafe { a.ext.write_acceleration_structures_properties(&[s0.s, s0.s], vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR, &mut data, 8) };
            },
        );
        assert_eq!(data, [0xA5u8; 8]);
    });
}

#[test]
fn property_write_into_a_pool_of_another_type_02493() {
    scenario(|a, m| {
        let (s, _) = valid_blas(a, m, NO_FLAGS);
        let d = &a.ctx.device;
        // SAFETY: valid create info; destroyed below.
        let pool = unsafe {
            d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR).query_count(1), None)
        }
        .unwrap();
        const WRITE: &str = "vkCmdWriteAccelerationStructuresPropertiesKHR";
        expect_invalid(
            a,
            Expect { command: WRITE, vuid: format!("VUID-{WRITE}-queryPool-02493"), needles: &["queryPool was created with another queryType"], writable: &[], invalidated: &[] },
            || {
                a.submit(|cb| {
                    // SAFETY: recording command buffer, valid pool and structure.
                    unsafe {
                        d.cmd_reset_query_pool(cb, pool, 0, 1);
                        a.ext.cmd_write_acceleration_structures_properties(cb, &[s.s], vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR, pool, 0);
                    }
                })
            },
        );
        let mut out = [0u64; 1];
        // SAFETY: valid pool.
        let r = unsafe { d.get_query_pool_results(pool, 0, &mut out, vk::QueryResultFlags::TYPE_64) };
        assert_eq!(r, Err(vk::Result::NOT_READY));
        // SAFETY: idle pool.
        unsafe { d.destroy_query_pool(pool, None) };
    });
}

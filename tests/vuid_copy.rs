//! Valid usage of the copy commands: clone and compaction (vkCmdCopyAccelerationStructureKHR and
//! its host form), serialization (vkCmdCopyAccelerationStructureToMemoryKHR) and deserialization
//! (vkCmdCopyMemoryToAccelerationStructureKHR).
mod harness;

use arbor::accel::NoDevice;
use ash::vk;
use harness::vuid::*;

fn cmd_copy(a: &Accel, src: &Dst, dst: &Dst, mode: vk::CopyAccelerationStructureModeKHR) {
    let info = vk::CopyAccelerationStructureInfoKHR::default().src(src.s).dst(dst.s).mode(mode);
    // SAFETY: recording command buffer, valid info.
    a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure(cb, &info) });
}

fn cmd_deserialize(a: &Accel, src: u64, dst: &Dst) {
    let info = vk::CopyMemoryToAccelerationStructureInfoKHR::default()
        .src(cadr(src))
        .dst(dst.s)
        .mode(vk::CopyAccelerationStructureModeKHR::DESERIALIZE);
    // SAFETY: recording command buffer, valid info.
    a.submit(|cb| unsafe { a.ext.cmd_copy_memory_to_acceleration_structure(cb, &info) });
}

// ---------------------------------------------------------------------------------------------
// Clone and compaction

#[test]
fn compact_without_allow_compaction_03411() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-src-03411".into(),
                needles: &["src was not built with ALLOW_COMPACTION"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_copy(a, &src, &victim, vk::CopyAccelerationStructureModeKHR::COMPACT),
        );
        assert_grid_hits(&src.r.read(a), &NoDevice);
    });
}

#[test]
fn host_compact_without_allow_compaction_03411() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let info = vk::CopyAccelerationStructureInfoKHR::default().src(src.s).dst(victim.s).mode(vk::CopyAccelerationStructureModeKHR::COMPACT);
        let mut result = Ok(());
        expect_invalid(
            a,
            Expect {
                command: "vkCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-src-03411".into(),
                needles: &["src was not built with ALLOW_COMPACTION"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            // SAFETY: valid info, no deferred operation.
            || result = unsafe { a.ext.copy_acceleration_structure(vk::DeferredOperationKHR::null(), &info) },
        );
        assert_eq!(result, Ok(()));
    });
}

#[test]
fn compact_into_a_destination_too_small_12285() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION);
        let compacted = a.query(src.s, vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR);
        let (victim, _) = prebuilt_blas(a, m, 0, 0, 2, NO_FLAGS);
        assert!(victim.r.len < compacted, "test setup: {} < {compacted}", victim.r.len);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-dst-12285".into(),
                needles: &["dst size", "is below the"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_copy(a, &src, &victim, vk::CopyAccelerationStructureModeKHR::COMPACT),
        );
        assert_guards(a, victim.r);
    });
}

#[test]
fn clone_into_a_destination_too_small_12284() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let (victim, _) = prebuilt_blas(a, m, 0, 0, 8, NO_FLAGS);
        assert!(victim.r.len < src.r.len);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-dst-12284".into(),
                needles: &["dst size", "is below the"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_copy(a, &src, &victim, vk::CopyAccelerationStructureModeKHR::CLONE),
        );
        assert_guards(a, victim.r);
    });
}

#[test]
fn clone_from_a_structure_never_built_04963() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let src = guarded_structure(a, BLAS, victim.r.len);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-src-04963".into(),
                needles: &["src has not been built"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_copy(a, &src, &victim, vk::CopyAccelerationStructureModeKHR::CLONE),
        );
    });
}

#[test]
fn clone_between_overlapping_structures_07791() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let size = sizes.acceleration_structure_size;
        let both = guarded(a, size + 256);
        let src = structure_in(a, both.buf, GUARD, size, BLAS);
        let dst = structure_in(a, both.buf, GUARD + 256, size, BLAS);
        let sc = guarded(a, sizes.build_scratch_size);
        build_grid_into(a, m, &src, sc.address(a), m.count, NO_FLAGS);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-dst-07791".into(),
                needles: &["the memory of src and dst overlap"],
                writable: &[dst.r],
                invalidated: &[],
            },
            || cmd_copy(a, &src, &dst, vk::CopyAccelerationStructureModeKHR::CLONE),
        );
        assert!(header_of(a, &src).is_some());
    });
}

#[test]
fn copy_with_an_invalid_mode_03410() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-mode-03410".into(),
                needles: &["mode must be CLONE or COMPACT"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_copy(a, &src, &victim, vk::CopyAccelerationStructureModeKHR::SERIALIZE),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Serialization

#[test]
fn serialize_a_structure_never_built_04959() {
    scenario(|a, m| {
        let _ = m;
        let unbuilt = guarded_structure(a, BLAS, 4096);
        let out = guarded(a, 4096);
        let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
            .src(unbuilt.s)
            .dst(madr(out.address(a)))
            .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureToMemoryKHR",
                vuid: "VUID-VkCopyAccelerationStructureToMemoryInfoKHR-src-04959".into(),
                needles: &["src has not been built"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: recording command buffer, valid info.
            || a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) }),
        );
    });
}

#[test]
fn serialize_to_a_misaligned_address_03740() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let size = a.query(src.s, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR);
        let out = guarded(a, size + 16);
        let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
            .src(src.s)
            .dst(madr(out.address(a) + 16))
            .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureToMemoryKHR",
                // The spec's name is VUID-vkCmdCopyAccelerationStructureToMemoryKHR-pInfo-03740;
                // the driver says VkCopyAccelerationStructureToMemoryInfoKHR-dst-03740.
                vuid: "-03740".into(),
                needles: &["is not aligned to 256"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: recording command buffer, valid info.
            || a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) }),
        );
    });
}

#[test]
fn serialize_to_memory_too_small_03561() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let size = a.query(src.s, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR);
        // Half the serialization size, at the start of a buffer of that size.
        let b = a.buffer(size / 2);
        a.fill(b, FILL);
        let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
            .src(src.s)
            .dst(madr(a.buf(b).address))
            .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureToMemoryKHR",
                vuid: "VUID-VkCopyAccelerationStructureToMemoryInfoKHR-dst-03561".into(),
                needles: &["is not writable device memory"],
                writable: &[],
                invalidated: &[],
            },
            // SAFETY: recording command buffer, valid info.
            || a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) }),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Deserialization

#[test]
fn deserialize_data_of_another_driver_03749() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let mut blob = a.serialize(src.s);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        blob[0] ^= 0xFF; // driver UUID
        let data = guarded_data(a, &blob);
        let deserialize = |a: &Accel| {
            let info = vk::CopyMemoryToAccelerationStructureInfoKHR::default()
                .src(cadr(data.address(a)))
                .dst(victim.s)
                .mode(vk::CopyAccelerationStructureModeKHR::DESERIALIZE);
            // SAFETY: recording command buffer, valid info.
            a.submit(|cb| unsafe { a.ext.cmd_copy_memory_to_acceleration_structure(cb, &info) });
        };
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyMemoryToAccelerationStructureKHR",
                vuid: "VUID-VkCopyMemoryToAccelerationStructureInfoKHR-pInfo-03749".into(),
                needles: &["not compatible with this device"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || deserialize(a),
        );
        // The same data with the right UUID deserializes.
        blob[0] ^= 0xFF;
        data.write(a, 0, &blob);
        deserialize(a);
        assert_grid_hits(&victim.r.read(a), &NoDevice);
    });
}

#[test]
fn deserialize_into_a_destination_too_small_03746() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let blob = a.serialize(src.s);
        let data = guarded_data(a, &blob);
        let (victim, _) = prebuilt_blas(a, m, 0, 0, 2, NO_FLAGS);
        assert!(victim.r.len < src.r.len);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyMemoryToAccelerationStructureKHR",
                vuid: "VUID-VkCopyMemoryToAccelerationStructureInfoKHR-dst-03746".into(),
                needles: &["cannot deserialize into dst"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_deserialize(a, data.address(a), &victim),
        );
        assert_guards(a, victim.r);
    });
}

#[test]
fn deserialize_from_a_misaligned_address_03743() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let blob = a.serialize(src.s);
        let data = guarded(a, blob.len() as u64 + 16);
        data.write(a, 16, &blob);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyMemoryToAccelerationStructureKHR",
                // The spec's name is VUID-vkCmdCopyMemoryToAccelerationStructureKHR-pInfo-03743;
                // the driver says VkCopyMemoryToAccelerationStructureInfoKHR-src-03743.
                vuid: "-03743".into(),
                needles: &["is not aligned to 256"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_deserialize(a, data.address(a) + 16, &victim),
        );
    });
}

#[test]
fn deserialize_from_unmapped_memory_03742() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let gone = freed_address(a, 4096);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyMemoryToAccelerationStructureKHR",
                // The spec's name is VUID-vkCmdCopyMemoryToAccelerationStructureKHR-pInfo-03742;
                // the driver says VkCopyMemoryToAccelerationStructureInfoKHR-src-03742.
                vuid: "-03742".into(),
                needles: &["does not address a serialized structure"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_deserialize(a, gone, &victim),
        );
    });
}

#[test]
fn deserialize_with_a_length_past_the_buffer_03742() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let mut blob = a.serialize(src.s);
        // The header's total size claims far more than the buffer holds.
        blob[32..40].copy_from_slice(&(1u64 << 40).to_le_bytes());
        let data = guarded_data(a, &blob);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyMemoryToAccelerationStructureKHR",
                vuid: "-03742".into(),
                needles: &["is not readable"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_deserialize(a, data.address(a), &victim),
        );
    });
}

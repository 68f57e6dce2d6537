//! Corrupted structures and serialized data: every copy verifies its source (the checksum Arbor
//! keeps in its own header and the structure's consistency) and rejects a bad one by VUID,
//! writing nothing but the destination's invalid mark.
mod harness;

use arbor::accel::NoDevice;
use ash::vk;
use harness::vuid::*;

const FROM_MEMORY: &str = "vkCmdCopyMemoryToAccelerationStructureKHR";

fn cmd_deserialize(a: &Accel, src: u64, dst: &Dst) {
    let info = vk::CopyMemoryToAccelerationStructureInfoKHR::default()
        .src(cadr(src))
        .dst(dst.s)
        .mode(vk::CopyAccelerationStructureModeKHR::DESERIALIZE);
    // SAFETY: recording command buffer, valid info.
    a.submit(|cb| unsafe { a.ext.cmd_copy_memory_to_acceleration_structure(cb, &info) });
}

/// Sixty random bit flips in the payload of a serialized BLAS: each is rejected with
/// src-04960 and leaves only the invalid mark in the destination; the untouched data then
/// deserializes into a structure that traces like the grid.
#[test]
fn bit_flips_in_a_serialized_payload_04960() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let blob = a.serialize(src.s);
        let data = guarded_data(a, &blob);
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        for flip in 0..60 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let at = 56 + (state % (blob.len() as u64 - 56)) as usize;
            let mut bad = blob.clone();
            bad[at] ^= 1 << (state >> 60 & 7);
            data.write(a, 0, &bad);
            let (victim, _) = valid_blas(a, m, NO_FLAGS);
            expect_invalid(
                a,
                Expect {
                    command: FROM_MEMORY,
                    vuid: "VUID-VkCopyMemoryToAccelerationStructureInfoKHR-src-04960".into(),
                    needles: &["failed check"],
                    writable: &[victim.r],
                    invalidated: &[&victim],
                },
                || cmd_deserialize(a, data.address(a), &victim),
            );
            assert_guards(a, victim.r);
            let _ = flip;
        }
        data.write(a, 0, &blob);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        cmd_deserialize(a, data.address(a), &victim);
        assert_grid_hits(&victim.r.read(a), &NoDevice);
    });
}

/// A structure written over in device memory after its build: a clone refuses it (src-04963)
/// and a serialization refuses it (src-04959).
#[test]
fn copies_of_a_structure_written_over_04963_04959() {
    scenario(|a, m| {
        let (src, _) = valid_blas(a, m, NO_FLAGS);
        let used = header_of(a, &src).unwrap().used_size;
        src.r.write(a, used - 5, &[0x77]);
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let info = vk::CopyAccelerationStructureInfoKHR::default().src(src.s).dst(victim.s).mode(vk::CopyAccelerationStructureModeKHR::CLONE);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureKHR",
                vuid: "VUID-VkCopyAccelerationStructureInfoKHR-src-04963".into(),
                needles: &["failed check: checksum"],
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            // SAFETY: recording command buffer, valid info.
            || a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure(cb, &info) }),
        );
        let out = guarded(a, 1 << 16);
        let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
            .src(src.s)
            .dst(madr(out.address(a)))
            .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
        expect_invalid(
            a,
            Expect {
                command: "vkCmdCopyAccelerationStructureToMemoryKHR",
                vuid: "VUID-VkCopyAccelerationStructureToMemoryInfoKHR-src-04959".into(),
                needles: &["failed check: checksum"],
                writable: &[out],
                invalidated: &[],
            },
            // SAFETY: recording command buffer, valid info.
            || a.submit(|cb| unsafe { a.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) }),
        );
    });
}

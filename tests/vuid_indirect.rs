//! Valid usage of vkCmdBuildAccelerationStructuresIndirectKHR: the indirect records (their
//! buffer, usage, alignment, stride), their primitive counts against the maxima given at record
//! time, and the destination size for those maxima.
mod harness;

use arbor::accel::NoDevice;
use ash::vk;
use harness::vuid::*;

#[test]
fn indirect_primitive_count_above_max_03653() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let records = guarded(a, 16);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        let needle = format!("pInfos[0]: geometry 0: indirect primitiveCount {} exceeds ppMaxPrimitiveCounts 64", m.count);
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-ppMaxPrimitiveCounts-03653"),
                needles: &[&needle],
                // The record itself is written by the vkCmdUpdateBuffer of the same submission.
                writable: &[victim.r, scratch, records],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, records.address(a), 16, 64, Some((records, [m.count, 0, 0, 0]))),
        );
        assert_eq!(records.read(a), record(m.count));
        assert_guards(a, records);
        // The same record within its maximum builds: the indirect path itself works.
        cmd_build_indirect(a, &inf, records.address(a), 16, m.count, None);
        assert_grid_hits(&victim.r.read(a), &NoDevice);
    });
}

#[test]
fn indirect_records_outside_their_buffer_03646() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        // A 64-byte buffer: a 16-byte record at offset 56 runs 8 bytes past its end.
        let b = a.buffer(64);
        a.fill(b, FILL);
        let address = a.buf(b).address + 56;
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-pIndirectDeviceAddresses-03646"),
                needles: &["pInfos[0]: indirect records", "are not inside one buffer"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, address, 16, m.count, None),
        );
    });
}

#[test]
fn indirect_buffer_without_indirect_usage_03647() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let records = guarded_with(a, 16, without(vk::BufferUsageFlags::INDIRECT_BUFFER));
        records.write(a, 0, &record(m.count));
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-pIndirectDeviceAddresses-03647"),
                needles: &["pInfos[0]: the buffer of the indirect records lacks INDIRECT_BUFFER usage"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, records.address(a), 16, m.count, None),
        );
    });
}

#[test]
fn indirect_address_not_a_multiple_of_4_03648() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let records = guarded(a, 18);
        records.write(a, 2, &record(m.count));
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-pIndirectDeviceAddresses-03648"),
                needles: &["pInfos[0]: indirect address", "is not a multiple of 4"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, records.address(a) + 2, 16, m.count, None),
        );
    });
}

#[test]
fn indirect_stride_not_a_multiple_of_4_03787() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let records = guarded_data(a, &record(m.count));
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-pIndirectStrides-03787"),
                needles: &["pInfos[0]: indirect stride 18 is not a multiple of 4"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, records.address(a), 18, m.count, None),
        );
    });
}

#[test]
fn indirect_destination_smaller_than_the_size_query_03652() {
    scenario(|a, m| {
        // Sized (and validly built) for 8 triangles; the indirect build allows the whole grid.
        let (victim, scratch) = prebuilt_blas(a, m, 0, 0, 8, NO_FLAGS);
        let records = guarded_data(a, &record(8));
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        assert!(a.sizes(DEVICE, &inf, &[m.count]).acceleration_structure_size > victim.r.len);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD_INDIRECT,
                vuid: format!("VUID-{CMD_INDIRECT}-pInfos-03652"),
                needles: &["pInfos[0]: dstAccelerationStructure size", "the size query requires"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build_indirect(a, &inf, records.address(a), 16, m.count, None),
        );
    });
}

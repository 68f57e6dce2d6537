//! The VUID harness itself (`harness::vuid`): each check the negative tests rely on must be able
//! to fail.
mod harness;

use harness::vuid::*;

#[test]
#[should_panic(expected = "outside destination and scratch")]
fn harness_catches_a_write_outside_destination_and_scratch() {
    scenario(|a, m| {
        let snap = snapshot(a);
        // One guard byte before the vertex data.
        a.buf(m.v.buf).write((m.v.offset - 1) as usize, &[0]);
        verify(a, &snap, &[]);
    });
}

#[test]
#[should_panic(expected = "expected a line starting with")]
fn harness_catches_a_missing_diagnostic() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        expect_invalid(
            a,
            Expect { command: CMD, vuid: cmd_vuid("pInfos-03675"), needles: &[], writable: &[victim.r, scratch], invalidated: &[] },
            || build_grid_into(a, m, &victim, scratch.address(a), m.count, NO_FLAGS),
        );
    });
}

#[test]
#[should_panic(expected = "still reads as a valid structure")]
fn harness_catches_a_destination_left_valid() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let (bystander, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a) + 64));
        expect_invalid(
            a,
            Expect { command: CMD, vuid: cmd_vuid("pInfos-03710"), needles: &[], writable: &[victim.r, scratch], invalidated: &[&bystander] },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
#[should_panic(expected = "unexpected diagnostic besides")]
fn harness_catches_a_second_violation() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let geoms = [tri(m.v.address(a) + 2, m.i.address(a), m.max_vertex, 0)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a) + 64));
        expect_invalid(
            a,
            Expect { command: CMD, vuid: cmd_vuid("pInfos-03710"), needles: &[], writable: &[victim.r, scratch], invalidated: &[&victim] },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

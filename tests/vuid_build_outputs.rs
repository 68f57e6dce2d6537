//! Valid usage of vkCmdBuildAccelerationStructuresKHR: what a build writes — its destination
//! (handle, type, size, memory) and scratch (range, alignment, usage), and the overlaps between
//! the destinations, scratch and inputs of the elements of one command.
mod harness;

use ash::vk;
use harness::vuid::*;

// ---------------------------------------------------------------------------------------------
// Destination handles and types

#[test]
fn build_into_a_destroyed_handle_03800() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        // A second handle viewing the victim's memory, destroyed before the build.
        let stale = destroyed_handle(a, &victim);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(stale).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-dstAccelerationStructure-03800"),
                needles: &["pInfos[0]: dstAccelerationStructure", "is not a valid handle"],
                writable: &[],
                invalidated: &[],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        // The handle lookup fails: nothing is written, not even the memory the handle viewed.
        assert!(header_of(a, &victim).is_some());
    });
}

#[test]
fn top_level_build_into_a_bottom_level_structure_03699() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(a.address_of(blas.s)));
        let geoms = [instances_geom(inst.address(a), false)];
        let inf = info(TLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(DEVICE, &inf, &[1]);
        let (victim, scratch) = prebuilt_blas(a, m, sizes.acceleration_structure_size, sizes.build_scratch_size, m.count, NO_FLAGS);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03699"),
                needles: &["pInfos[0]: dstAccelerationStructure was created with another type"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(1)]]),
        );
    });
}

#[test]
fn bottom_level_build_into_a_top_level_structure_03700() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(DEVICE, &inf, &[m.count]);
        let (victim, scratch) = prebuilt_tlas(a, &blas, sizes.acceleration_structure_size, sizes.build_scratch_size);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03700"),
                needles: &["pInfos[0]: dstAccelerationStructure was created with another type"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn destination_without_memory_03707() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let unbound = unbound_structure(a, sizes.acceleration_structure_size, BLAS);
        let scratch = guarded(a, sizes.build_scratch_size);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(unbound.1).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-03707"),
                needles: &["pInfos[0]: dstAccelerationStructure is not bound to device memory"],
                writable: &[],
                invalidated: &[],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        unbound_done(a, unbound);
    });
}

// ---------------------------------------------------------------------------------------------
// Destination sizes

#[test]
fn destination_smaller_than_the_size_query_03675() {
    scenario(|a, m| {
        // Sized (and validly built) for 8 triangles; the build is of the whole grid. The guard
        // right after the destination is in the same buffer.
        let (victim, scratch) = prebuilt_blas(a, m, 0, 0, 8, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        assert!(a.sizes(DEVICE, &inf, &[m.count]).acceleration_structure_size > victim.r.len);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03675"),
                needles: &["pInfos[0]: dstAccelerationStructure size", "the size query requires"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        assert_guards(a, victim.r);
    });
}

#[test]
fn primitive_count_of_u32_max_03675() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        let mark = harness::diagnostics().len();
        let snap = snapshot(a);
        cmd_build(a, &[inf], &[&[range(u32::MAX)]]);
        let tail = harness::diagnostics()[mark..].to_string();
        assert!(tail.contains(&format!("[VUID-{CMD}-pInfos-03675] pInfos[0]")), "{tail}");
        assert!(!tail.contains("panic") && !tail.contains("internal error"), "{tail}");
        verify(a, &snap, &[victim.r, scratch]);
        assert!(header_of(a, &victim).is_none());
    });
}

// ---------------------------------------------------------------------------------------------
// Scratch

#[test]
fn scratch_running_past_its_buffer_12258() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let need = a.sizes(DEVICE, &inf, &[m.count]).build_scratch_size;
        assert!(need >= 256, "the grid needs scratch ({need})");
        // Half the scratch the build needs, at the start of a buffer of that size.
        let b = a.buffer(need / 2);
        a.fill(b, FILL);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(a.buf(b).address));
        let short = Region { buf: b, offset: 0, len: need / 2 };
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-12258"),
                needles: &["pInfos[0]: scratch", "(buildScratchSize) is not inside one buffer"],
                writable: &[victim.r, short],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn scratch_misaligned_03710() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        // Enough scratch, inside its buffer, but 64 bytes past a 128-byte boundary.
        let scratch = guarded(a, a.sizes(DEVICE, &inf, &[m.count]).build_scratch_size + 64);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a) + 64));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03710"),
                needles: &["pInfos[0]: scratchData", "is not a multiple of 128"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn scratch_without_storage_usage_12261() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, NO_FLAGS);
        let scratch = guarded_with(a, grid_sizes(a, m).build_scratch_size, without(vk::BufferUsageFlags::STORAGE_BUFFER));
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-12261"),
                needles: &["pInfos[0]: the scratch buffer lacks STORAGE_BUFFER usage"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Overlaps between the elements of one command

#[test]
fn destinations_overlap_03702() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let size = sizes.acceleration_structure_size;
        // Two structures 256 bytes apart in one buffer.
        let both = guarded(a, size + 256);
        let s0 = structure_in(a, both.buf, GUARD, size, BLAS);
        let s1 = structure_in(a, both.buf, GUARD + 256, size, BLAS);
        let sc0 = guarded(a, sizes.build_scratch_size);
        let sc1 = guarded(a, sizes.build_scratch_size);
        build_grid_into(a, m, &s0, sc0.address(a), m.count, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s0.s).scratch_data(madr(sc0.address(a)));
        let i1 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s1.s).scratch_data(madr(sc1.address(a)));
        let r = [range(m.count)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-dstAccelerationStructure-03702"),
                needles: &["pInfos[0]: dst overlaps the dst of pInfos[1]", "pInfos[1]: dst overlaps the dst of pInfos[0]"],
                writable: &[both, sc0, sc1],
                invalidated: &[&s0],
            },
            || cmd_build(a, &[i0, i1], &[&r, &r]),
        );
        assert!(header_of(a, &s1).is_none());
        assert_guards(a, both);
    });
}

#[test]
fn destination_overlaps_the_scratch_of_another_element_03703() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        // Element 0's destination, in a buffer large enough to also hold element 1's scratch
        // starting at the same byte.
        let shared = guarded(a, sizes.acceleration_structure_size.max(sizes.build_scratch_size));
        let s0 = structure_in(a, shared.buf, GUARD, sizes.acceleration_structure_size, BLAS);
        let sc0 = guarded(a, sizes.build_scratch_size);
        build_grid_into(a, m, &s0, sc0.address(a), m.count, NO_FLAGS);
        let s1 = guarded_structure(a, BLAS, sizes.acceleration_structure_size);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s0.s).scratch_data(madr(sc0.address(a)));
        let i1 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s1.s).scratch_data(madr(shared.address(a)));
        let r = [range(m.count)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-dstAccelerationStructure-03703"),
                needles: &["pInfos[0]: dst overlaps the scratch of pInfos[1]"],
                writable: &[shared, sc0, s1.r],
                invalidated: &[&s0],
            },
            || cmd_build(a, &[i0, i1], &[&r, &r]),
        );
        assert_guards(a, shared);
    });
}

#[test]
fn destination_overlaps_its_own_scratch_03703() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let shared = guarded(a, sizes.acceleration_structure_size.max(sizes.build_scratch_size));
        let s0 = structure_in(a, shared.buf, GUARD, sizes.acceleration_structure_size, BLAS);
        let sc0 = guarded(a, sizes.build_scratch_size);
        build_grid_into(a, m, &s0, sc0.address(a), m.count, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s0.s).scratch_data(madr(shared.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-dstAccelerationStructure-03703"),
                needles: &["pInfos[0]: dst overlaps its own scratch memory"],
                writable: &[shared],
                invalidated: &[&s0],
            },
            || cmd_build(a, &[i0], &[&[range(m.count)]]),
        );
        assert_guards(a, shared);
    });
}

#[test]
fn scratch_regions_overlap_03704() {
    scenario(|a, m| {
        let (s0, sc) = valid_blas(a, m, NO_FLAGS);
        let (s1, _) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s0.s).scratch_data(madr(sc.address(a)));
        let i1 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(s1.s).scratch_data(madr(sc.address(a)));
        let r = [range(m.count)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-scratchData-03704"),
                needles: &["pInfos[0]: scratch overlaps the scratch of pInfos[1]", "pInfos[1]: scratch overlaps the scratch of pInfos[0]"],
                writable: &[s0.r, s1.r, sc],
                invalidated: &[&s0, &s1],
            },
            || cmd_build(a, &[i0, i1], &[&r, &r]),
        );
    });
}

#[test]
fn destination_referenced_by_an_instance_of_another_element_03706() {
    scenario(|a, m| {
        // Element 0 rebuilds `victim`; element 1 builds a TLAS over an instance of `victim`.
        let (victim, sc0) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(a.address_of(victim.s)));
        let tgeoms = [instances_geom(inst.address(a), false)];
        let tsizes = a.sizes(DEVICE, &info(TLAS, NO_FLAGS, &tgeoms), &[1]);
        let tlas = guarded_structure(a, TLAS, tsizes.acceleration_structure_size);
        let sc1 = guarded(a, tsizes.build_scratch_size);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(sc0.address(a)));
        let i1 = info(TLAS, NO_FLAGS, &tgeoms).dst_acceleration_structure(tlas.s).scratch_data(madr(sc1.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("dstAccelerationStructure-03706"),
                needles: &["pInfos[0]: dst is referenced by an instance of pInfos[1]"],
                writable: &[victim.r, sc0, tlas.r, sc1],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[i0, i1], &[&[range(m.count)], &[range(1)]]),
        );
    });
}

/// No VUID names it, but a build whose vertex input lies inside its own scratch would read what
/// it writes (and Arbor would alias a shared and a mutable view): reported and skipped.
#[test]
fn vertex_input_inside_the_scratch_is_reported() {
    scenario(|a, m| {
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(DEVICE, &inf, &[m.count]);
        let (victim, scratch) = prebuilt_blas(a, m, sizes.acceleration_structure_size, sizes.build_scratch_size, m.count, NO_FLAGS);
        // Put the vertices at the start of the scratch region and point the geometry there.
        scratch.write(a, 0, &m.vertex_bytes);
        let geoms = [tri(scratch.address(a), m.i.address(a), m.max_vertex, 0)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: "ARBOR-build-input-aliases-output".into(),
                needles: &["pInfos[0]: a geometry input overlaps the dst or scratch memory of pInfos[0]"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

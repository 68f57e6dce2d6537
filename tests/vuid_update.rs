//! Valid usage of vkCmdBuildAccelerationStructuresKHR in UPDATE mode: the source structure, what
//! must match its last build (checked at record time or when the update runs), and aliasing of
//! the source with the destination, the scratch and the other elements of the command.
mod harness;

use arbor::accel::NoDevice;
use ash::vk;
use harness::vuid::*;

/// Build the grid with ALLOW_UPDATE into a victim, then update it in place with `geom` and
/// `range`: checks `vuid`.
fn invalid_update(a: &Accel, m: &Mesh, geom: Geom, r: Range, vuid: &str, needles: &[&str]) {
    let (victim, scratch) = valid_blas(a, m, ALLOW_UPDATE);
    let geoms = [geom];
    let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &victim, &victim, scratch.address(a));
    expect_invalid(
        a,
        Expect { command: CMD, vuid: cmd_vuid(vuid), needles, writable: &[victim.r, scratch], invalidated: &[&victim] },
        || cmd_build(a, &[inf], &[&[r]]),
    );
}

// ---------------------------------------------------------------------------------------------
// The source

#[test]
fn update_of_a_structure_built_without_allow_update_03667() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, NO_FLAGS, &geoms, &victim, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03667"),
                needles: &["pInfos[0]: srcAccelerationStructure was not built with ALLOW_UPDATE"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn update_from_a_structure_never_built_03667() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, ALLOW_UPDATE);
        let src = guarded_structure(a, BLAS, victim.r.len);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &src, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03667"),
                needles: &["pInfos[0]: srcAccelerationStructure has not been built"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        assert_guards(a, src.r);
    });
}

#[test]
fn update_source_without_memory_03708() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, ALLOW_UPDATE);
        let unbound = unbound_structure(a, victim.r.len, BLAS);
        let src = Dst { s: unbound.1, r: victim.r };
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &src, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-03708"),
                needles: &["pInfos[0]: srcAccelerationStructure is not bound to device memory"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        unbound_done(a, unbound);
    });
}

#[test]
fn update_from_a_destroyed_source_04630() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, ALLOW_UPDATE);
        let stale = destroyed_handle(a, &victim);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &Dst { s: stale, r: victim.r }, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-04630"),
                needles: &["pInfos[0]: mode is UPDATE but srcAccelerationStructure", "is not valid"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// What must match the last build

#[test]
fn update_with_another_geometry_count_03758() {
    scenario(|a, m| {
        let (victim, _) = valid_blas(a, m, ALLOW_UPDATE);
        let geoms = [mesh_geom(a, m), mesh_geom(a, m)];
        let sizes = a.sizes(DEVICE, &info(BLAS, ALLOW_UPDATE, &geoms), &[m.count, m.count]);
        let scratch = guarded(a, sizes.update_scratch_size.max(sizes.build_scratch_size));
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &victim, &victim, scratch.address(a));
        let r = [range(m.count), range(m.count)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03758"),
                needles: &["pInfos[0]: geometryCount differs from the last build of srcAccelerationStructure"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&r]),
        );
    });
}

#[test]
fn update_with_other_flags_03759() {
    scenario(|a, m| {
        let built = ALLOW_UPDATE | vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE;
        let (victim, scratch) = valid_blas(a, m, built);
        let geoms = [mesh_geom(a, m)];
        let flags = ALLOW_UPDATE | vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD;
        let inf = update_info(BLAS, flags, &geoms, &victim, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03759"),
                needles: &["pInfos[0]: flags differ from the last build of srcAccelerationStructure"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

#[test]
fn update_with_another_type_03760() {
    scenario(|a, m| {
        // Source: a BLAS built with ALLOW_UPDATE. Update: a TLAS (same flags, one geometry) into
        // a TOP_LEVEL destination that holds a valid TLAS.
        let (src, _) = valid_blas(a, m, ALLOW_UPDATE);
        let inst = guarded_data(a, &instance(a.address_of(src.s)));
        let geoms = [instances_geom(inst.address(a), false)];
        let sizes = a.sizes(DEVICE, &info(TLAS, ALLOW_UPDATE, &geoms), &[1]);
        // Large enough for the TLAS and for the source's size (an update writes that much).
        let (victim, scratch) = prebuilt_tlas(a, &src, sizes.acceleration_structure_size.max(src.r.len), sizes.update_scratch_size);
        let inf = update_info(TLAS, ALLOW_UPDATE, &geoms, &src, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: format!("VUID-{CMD}-pInfos-03760"),
                needles: &["pInfos[0]: type differs from the last build of srcAccelerationStructure"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(1)]]),
        );
        // The source was only read.
        assert_grid_hits(&src.r.read(a), &NoDevice);
    });
}

// ---------------------------------------------------------------------------------------------
// What must match the last build, checked when the update runs

#[test]
fn update_with_changed_indices_03768() {
    scenario(|a, m| {
        let mut indices = m.index_bytes.clone();
        // The first triangle's indices rotated: same triangle, other index values.
        let first: Vec<u8> = indices[..12].to_vec();
        indices[..4].copy_from_slice(&first[4..8]);
        indices[4..8].copy_from_slice(&first[8..12]);
        indices[8..12].copy_from_slice(&first[..4]);
        let i = guarded_data(a, &indices);
        let g = tri(m.v.address(a), i.address(a), m.max_vertex, 0);
        invalid_update(a, m, g, range(m.count), "pInfos-03768", &["pInfos[0]: update does not match the last build"]);
    });
}

#[test]
fn update_with_another_primitive_count_03769() {
    scenario(|a, m| {
        invalid_update(a, m, mesh_geom(a, m), range(m.count - 1), "primitiveCount-03769", &["pInfos[0]"]);
    });
}

#[test]
fn update_with_other_geometry_flags_03762() {
    scenario(|a, m| {
        let g = mesh_geom(a, m).flags(vk::GeometryFlagsKHR::NO_DUPLICATE_ANY_HIT_INVOCATION);
        invalid_update(a, m, g, range(m.count), "pInfos-03762", &["pInfos[0]"]);
    });
}

#[test]
fn update_with_another_max_vertex_03764() {
    scenario(|a, m| {
        let g = tri(m.v.address(a), m.i.address(a), m.max_vertex + 1, 0);
        invalid_update(a, m, g, range(m.count), "pInfos-03764", &["pInfos[0]"]);
    });
}

#[test]
fn update_into_a_destination_too_small_03675() {
    scenario(|a, m| {
        let (src, scratch) = valid_blas(a, m, ALLOW_UPDATE);
        let (victim, _) = prebuilt_blas(a, m, 0, 0, 2, ALLOW_UPDATE);
        assert!(victim.r.len < src.r.len);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &src, &victim, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-03675"),
                needles: &["pInfos[0]"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        assert_guards(a, victim.r);
        assert_grid_hits(&src.r.read(a), &NoDevice);
    });
}

// ---------------------------------------------------------------------------------------------
// Aliasing with the source

#[test]
fn update_source_and_destination_alias_03668() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let size = sizes.acceleration_structure_size;
        let both = guarded(a, size + 256);
        let src = structure_in(a, both.buf, GUARD, size, BLAS);
        let dst = structure_in(a, both.buf, GUARD + 256, size, BLAS);
        let scratch = guarded(a, sizes.build_scratch_size.max(sizes.update_scratch_size));
        build_grid_into(a, m, &src, scratch.address(a), m.count, ALLOW_UPDATE);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &src, &dst, scratch.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("pInfos-03668"),
                needles: &["pInfos[0]: srcAccelerationStructure and dstAccelerationStructure alias without being the same"],
                writable: &[dst.r, scratch],
                invalidated: &[],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        assert!(header_of(a, &dst).is_none());
        // Marking dst invalid writes only dst's own first bytes: src's header is intact.
        assert!(header_of(a, &src).is_some());
    });
}

#[test]
fn update_scratch_overlaps_its_source_03705() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        // The source, in a buffer large enough to also hold the update scratch from its start.
        let region = guarded(a, sizes.acceleration_structure_size.max(sizes.update_scratch_size));
        let src = structure_in(a, region.buf, GUARD, sizes.acceleration_structure_size, BLAS);
        let sc = guarded(a, sizes.build_scratch_size);
        build_grid_into(a, m, &src, sc.address(a), m.count, ALLOW_UPDATE);
        let (victim, _) = valid_blas(a, m, ALLOW_UPDATE);
        let geoms = [mesh_geom(a, m)];
        let inf = update_info(BLAS, ALLOW_UPDATE, &geoms, &src, &victim, region.address(a));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("scratchData-03705"),
                needles: &["pInfos[0]: scratch overlaps its own srcAccelerationStructure"],
                // The build is skipped: not even the (aliased) scratch is written.
                writable: &[victim.r],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
        assert_grid_hits(&src.r.read(a), &NoDevice);
    });
}

#[test]
fn destination_overlaps_the_source_of_another_update_03701() {
    scenario(|a, m| {
        let sizes = grid_sizes(a, m);
        let size = sizes.acceleration_structure_size;
        // Element 0 builds into d0 at GUARD; element 1 updates s1 (at GUARD + 256, overlapping
        // d0's tail) into d1.
        let both = guarded(a, size + 256);
        let d0 = structure_in(a, both.buf, GUARD, size, BLAS);
        let s1 = structure_in(a, both.buf, GUARD + 256, size, BLAS);
        let (sc0, sc1) = (guarded(a, sizes.build_scratch_size), guarded(a, sizes.update_scratch_size.max(sizes.build_scratch_size)));
        build_grid_into(a, m, &s1, sc1.address(a), m.count, ALLOW_UPDATE);
        let d1 = guarded_structure(a, BLAS, size);
        let geoms = [mesh_geom(a, m)];
        let i0 = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(d0.s).scratch_data(madr(sc0.address(a)));
        let i1 = update_info(BLAS, ALLOW_UPDATE, &geoms, &s1, &d1, sc1.address(a));
        let r = [range(m.count)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: cmd_vuid("dstAccelerationStructure-03701"),
                needles: &["pInfos[0]: dst overlaps the src of pInfos[1]"],
                writable: &[d0.r, sc0, d1.r, sc1],
                invalidated: &[],
            },
            || cmd_build(a, &[i0, i1], &[&r, &r]),
        );
        assert!(header_of(a, &d0).is_none());
        // Element 1 was valid: its update ran from an intact source.
        assert_grid_hits(&s1.r.read(a), &NoDevice);
        assert_grid_hits(&d1.r.read(a), &NoDevice);
    });
}

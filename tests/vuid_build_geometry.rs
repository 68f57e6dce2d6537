//! Valid usage of vkCmdBuildAccelerationStructuresKHR: the geometry of a build — geometry types
//! and arrays, formats, strides and offsets, alignment of every input, the memory the inputs
//! address, and what the inputs contain (indices, instance references).
mod harness;

use ash::vk;
use harness::vuid::*;

/// A BLAS build of `geoms` (one range of `count` each) into a prebuilt victim: checks `vuid`.
fn invalid_blas_build(a: &Accel, m: &Mesh, geoms: &[Geom], count: u32, vuid: &str, needles: &[&str]) {
    let inf = info(BLAS, NO_FLAGS, geoms);
    let counts = vec![count; geoms.len()];
    let sizes = a.sizes(DEVICE, &inf, &counts);
    let (victim, scratch) = prebuilt_blas(a, m, sizes.acceleration_structure_size, sizes.build_scratch_size, m.count, NO_FLAGS);
    let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
    let ranges = vec![range(count); geoms.len()];
    expect_invalid(
        a,
        Expect { command: CMD, vuid: cmd_vuid(vuid), needles, writable: &[victim.r, scratch], invalidated: &[&victim] },
        || cmd_build(a, &[inf], &[&ranges]),
    );
}

/// `n` thin AABB records (24 bytes each) side by side over the unit square.
fn boxes(n: usize) -> Vec<u8> {
    (0..n)
        .flat_map(|k| {
            let x = k as f32 / n as f32;
            [x, 0.0, -0.1, x + 0.5 / n as f32, 1.0, 0.1].into_iter().flat_map(f32::to_le_bytes)
        })
        .collect()
}

/// A TLAS build over `geom` (one range of `count`) into a prebuilt TLAS victim: checks `vuid`.
fn invalid_tlas_build(a: &Accel, blas: &Dst, geom: Geom, count: u32, vuid: &str, needles: &[&str]) {
    let geoms = [geom];
    let inf = info(TLAS, NO_FLAGS, &geoms);
    let sizes = a.sizes(DEVICE, &inf, &[count]);
    let (victim, scratch) = prebuilt_tlas(a, blas, sizes.acceleration_structure_size, sizes.build_scratch_size);
    let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
    expect_invalid(
        a,
        Expect { command: CMD, vuid: cmd_vuid(vuid), needles, writable: &[victim.r, scratch], invalidated: &[&victim] },
        || cmd_build(a, &[inf], &[&[range(count)]]),
    );
}

// ---------------------------------------------------------------------------------------------
// Geometry types and arrays

#[test]
fn top_level_build_with_two_geometries_03789() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(a.address_of(blas.s)));
        let geoms = [instances_geom(inst.address(a), false), instances_geom(inst.address(a), false)];
        let inf = info(TLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(DEVICE, &inf, &[1, 1]);
        let (victim, scratch) = prebuilt_tlas(a, &blas, sizes.acceleration_structure_size, sizes.build_scratch_size);
        let inf = inf.dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: "-type-03789".into(),
                needles: &["pInfos[0]: a top-level build must have exactly one geometry of type INSTANCES"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&[range(1), range(1)]]),
        );
    });
}

#[test]
fn bottom_level_build_with_instances_03790() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(a.address_of(blas.s)));
        let geoms = [instances_geom(inst.address(a), false)];
        invalid_blas_build(a, m, &geoms, 1, "-type-03790", &["pInfos[0]: a bottom-level build must not have INSTANCES geometry"]);
    });
}

#[test]
fn bottom_level_build_mixing_triangles_and_aabbs_03791() {
    scenario(|a, m| {
        let data = guarded_data(a, &boxes(4));
        let geoms = [mesh_geom(a, m), aabbs_geom(data.address(a), 24)];
        invalid_blas_build(a, m, &geoms, 4, "-type-03791", &["pInfos[0]: all geometries of a bottom-level build must have the same type"]);
    });
}

#[test]
fn geometry_arrays_both_null_03788() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let mut inf = info(BLAS, NO_FLAGS, &[]).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        // Both NULL (an empty slice's pointer is dangling, not NULL).
        inf.p_geometries = std::ptr::null();
        inf.pp_geometries = std::ptr::null();
        inf.geometry_count = 1;
        expect_invalid(
            a,
            Expect { command: CMD, vuid: "-pGeometries-03788".into(), needles: &["pInfos[0]"], writable: &[victim.r, scratch], invalidated: &[&victim] },
            || cmd_build(a, &[inf], &[&[range(m.count)]]),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Formats, strides, offsets

#[test]
fn unsupported_vertex_format_03797() {
    scenario(|a, m| {
        let mut g = mesh_geom(a, m);
        g.geometry.triangles.vertex_format = vk::Format::R64G64B64_SFLOAT;
        invalid_blas_build(a, m, &[g], m.count, "-vertexFormat-03797", &["pInfos[0]"]);
    });
}

#[test]
fn vertex_stride_not_a_multiple_of_the_component_size_03735() {
    scenario(|a, m| {
        let mut g = mesh_geom(a, m);
        g.geometry.triangles.vertex_stride = 6;
        invalid_blas_build(a, m, &[g], m.count, "-vertexStride-03735", &["pInfos[0]: geometry 0: vertexStride 6"]);
    });
}

#[test]
fn aabb_stride_not_a_multiple_of_8_03545() {
    scenario(|a, m| {
        let data = guarded_data(a, &boxes(4));
        invalid_blas_build(a, m, &[aabbs_geom(data.address(a), 12)], 4, "-stride-03545", &["pInfos[0]: geometry 0: aabbs.stride 12 is not a multiple of 8"]);
    });
}

#[test]
fn primitive_offset_not_a_multiple_of_the_index_size_03656() {
    scenario(|a, m| {
        let (victim, scratch) = valid_blas(a, m, NO_FLAGS);
        let geoms = [mesh_geom(a, m)];
        let inf = info(BLAS, NO_FLAGS, &geoms).dst_acceleration_structure(victim.s).scratch_data(madr(scratch.address(a)));
        let r = [Range::default().primitive_count(m.count - 1).primitive_offset(2)];
        expect_invalid(
            a,
            Expect {
                command: CMD,
                vuid: "-primitiveOffset-03656".into(),
                needles: &["pInfos[0]: geometry 0: primitiveOffset 2"],
                writable: &[victim.r, scratch],
                invalidated: &[&victim],
            },
            || cmd_build(a, &[inf], &[&r]),
        );
    });
}

// ---------------------------------------------------------------------------------------------
// Alignment

#[test]
fn vertex_data_misaligned_03711() {
    scenario(|a, m| {
        let v = guarded(a, m.vertex_bytes.len() as u64 + 2);
        v.write(a, 2, &m.vertex_bytes);
        let geoms = [tri(v.address(a) + 2, m.i.address(a), m.max_vertex, 0)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03711", &["pInfos[0]: geometry 0: vertexData", "is not aligned to 4"]);
    });
}

#[test]
fn index_data_misaligned_03712() {
    scenario(|a, m| {
        let i = guarded(a, m.index_bytes.len() as u64 + 2);
        i.write(a, 2, &m.index_bytes);
        let geoms = [tri(m.v.address(a), i.address(a) + 2, m.max_vertex, 0)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03712", &["pInfos[0]: geometry 0: indexData", "is not aligned to 4"]);
    });
}

#[test]
fn transform_data_misaligned_03810() {
    scenario(|a, m| {
        let t = guarded(a, 48 + 4);
        let bytes: Vec<u8> = IDENTITY.iter().flat_map(|f| f.to_le_bytes()).collect();
        t.write(a, 4, &bytes);
        let geoms = [tri(m.v.address(a), m.i.address(a), m.max_vertex, t.address(a) + 4)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03810", &["pInfos[0]: geometry 0: transformData", "is not aligned to 16"]);
    });
}

#[test]
fn aabb_data_misaligned_03714() {
    scenario(|a, m| {
        let data = boxes(4);
        let r = guarded(a, data.len() as u64 + 4);
        r.write(a, 4, &data);
        let geoms = [aabbs_geom(r.address(a) + 4, 24)];
        invalid_blas_build(a, m, &geoms, 4, "pInfos-03714", &["pInfos[0]: geometry 0: aabbs.data", "is not aligned to 8"]);
    });
}

#[test]
fn instance_array_misaligned_03715() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let r = guarded(a, 64 + 8);
        r.write(a, 8, &instance(a.address_of(blas.s)));
        invalid_tlas_build(a, &blas, instances_geom(r.address(a) + 8, false), 1, "pInfos-03715", &["pInfos[0]: geometry 0: instances.data", "is not aligned to 16"]);
    });
}

#[test]
fn instance_pointer_array_misaligned_03716() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(a.address_of(blas.s)));
        let pointers = guarded(a, 8 + 4);
        pointers.write(a, 4, &inst.address(a).to_le_bytes());
        invalid_tlas_build(a, &blas, instances_geom(pointers.address(a) + 4, true), 1, "pInfos-03716", &["pInfos[0]: geometry 0: instances.data", "is not aligned to 8"]);
    });
}

#[test]
fn instance_pointer_element_misaligned_03717() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded(a, 64 + 8);
        inst.write(a, 8, &instance(a.address_of(blas.s)));
        let pointers = guarded_data(a, &(inst.address(a) + 8).to_le_bytes());
        invalid_tlas_build(a, &blas, instances_geom(pointers.address(a), true), 1, "pInfos-03717", &["pInfos[0]: geometry 0: instance pointer 0", "is not aligned to 16"]);
    });
}

// ---------------------------------------------------------------------------------------------
// The memory the inputs address

#[test]
fn vertex_data_not_mapped_03804() {
    scenario(|a, m| {
        let gone = freed_address(a, 4096);
        let geoms = [tri(gone, m.i.address(a), m.max_vertex, 0)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03804", &["pInfos[0]: geometry 0: [0x"]);
    });
}

#[test]
fn index_data_not_mapped_03806() {
    scenario(|a, m| {
        let gone = freed_address(a, 4096);
        let geoms = [tri(m.v.address(a), gone, m.max_vertex, 0)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03806", &["pInfos[0]: geometry 0: [0x"]);
    });
}

#[test]
fn transform_data_not_mapped_03808() {
    scenario(|a, m| {
        let gone = freed_address(a, 4096);
        let geoms = [tri(m.v.address(a), m.i.address(a), m.max_vertex, gone)];
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03808", &["pInfos[0]: geometry 0: [0x"]);
    });
}

#[test]
fn aabb_data_not_mapped_03811() {
    scenario(|a, m| {
        let gone = freed_address(a, 4096);
        invalid_blas_build(a, m, &[aabbs_geom(gone, 24)], 4, "pInfos-03811", &["pInfos[0]: geometry 0: [0x"]);
    });
}

#[test]
fn instance_data_not_mapped_03813() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let gone = freed_address(a, 4096);
        invalid_tlas_build(a, &blas, instances_geom(gone, false), 1, "pInfos-03813", &["pInfos[0]: geometry 0: [0x"]);
    });
}

#[test]
fn instance_pointer_not_mapped_03813() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let gone = freed_address(a, 4096);
        let pointers = guarded_data(a, &gone.to_le_bytes());
        invalid_tlas_build(a, &blas, instances_geom(pointers.address(a), true), 1, "pInfos-03813", &["pInfos[0]: geometry 0: instance pointer 0", "does not address 64 valid bytes"]);
    });
}

#[test]
fn vertex_buffer_without_build_input_usage_03673() {
    scenario(|a, m| {
        let v = guarded_with(a, m.vertex_bytes.len() as u64, without(vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR));
        v.write(a, 0, &m.vertex_bytes);
        let geoms = [tri(v.address(a), m.i.address(a), m.max_vertex, 0)];
        invalid_blas_build(a, m, &geoms, m.count, "geometry-03673", &["pInfos[0]: geometry 0: the buffer at", "lacks ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY usage"]);
    });
}

// ---------------------------------------------------------------------------------------------
// What the inputs contain

#[test]
fn index_above_max_vertex_03651() {
    scenario(|a, m| {
        let mut indices = m.index_bytes.clone();
        let n = indices.len();
        indices[n - 4..].copy_from_slice(&(m.max_vertex + 1).to_le_bytes());
        let i = guarded_data(a, &indices);
        let geoms = [tri(m.v.address(a), i.address(a), m.max_vertex, 0)];
        let needle = format!("pInfos[0]: geometry 0 primitive {}: index {} exceeds maxVertex", m.count - 1, m.max_vertex + 1);
        invalid_blas_build(a, m, &geoms, m.count, "pInfos-03651", &[&needle]);
    });
}

#[test]
fn instance_reference_to_plain_memory_12281() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let inst = guarded_data(a, &instance(m.v.address(a)));
        invalid_tlas_build(a, &blas, instances_geom(inst.address(a), false), 1, "pInfos-12281", &["pInfos[0]: geometry 0: instance 0: accelerationStructureReference", "is neither 0 nor a built bottom-level structure"]);
    });
}

#[test]
fn instance_reference_to_a_top_level_structure_12281() {
    scenario(|a, m| {
        let (blas, _) = valid_blas(a, m, NO_FLAGS);
        let (other_tlas, _) = prebuilt_tlas(a, &blas, 0, 0);
        let inst = guarded_data(a, &instance(a.address_of(other_tlas.s)));
        invalid_tlas_build(a, &blas, instances_geom(inst.address(a), false), 1, "pInfos-12281", &["pInfos[0]: geometry 0: instance 0: accelerationStructureReference", "is neither 0 nor a built bottom-level structure"]);
        assert_tlas_hits(a, &other_tlas, &blas);
    });
}

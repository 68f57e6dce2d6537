//! Ray queries in a compute dispatch through the loader (validation on, zero messages): a BLAS
//! of the grid and a TLAS of two instances of it built with vkCmdBuildAccelerationStructuresKHR,
//! tests/shaders/rq_closest.comp traces a handful of rays through the TLAS descriptor, and each
//! committed hit matches `arbor::accel::closest_hit` on the structures read back. A BLAS gone
//! after the TLAS build leaves its instances absent, reported once per dispatch.
mod harness;

use arbor::accel::{self, MapView, Ray, RayFlags};
use ash::vk;
use glam::Vec3;
use harness::vuid::*;

fn translated(x: f32) -> [f32; 12] {
    [1.0, 0.0, 0.0, x, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
}

/// Instance k shows the grid at x in [2k, 2k + 1], custom index 10 + k.
fn build_tlas(a: &Accel, blas: &Dst) -> Dst {
    let reference = a.address_of(blas.s);
    let records: Vec<u8> = (0..2).flat_map(|k| instance_record(translated(2.0 * k as f32), 10 + k, 0xFF, 0, 0, reference)).collect();
    let insts = guarded_data(a, &records);
    let geoms = [instances_geom(insts.address(a), false)];
    let inf = info(TLAS, NO_FLAGS, &geoms);
    let sizes = a.sizes(DEVICE, &inf, &[2]);
    let tlas = guarded_structure(a, TLAS, sizes.acceleration_structure_size);
    let scratch = guarded(a, sizes.build_scratch_size);
    cmd_build(a, &[inf.dst_acceleration_structure(tlas.s).scratch_data(madr(scratch.address(a)))], &[&[range(2)]]);
    tlas
}

/// Runs rq_closest.comp over `rays` against `tlas`; returns the hits buffer.
fn trace(a: &Accel, tlas: vk::AccelerationStructureKHR, rays: &[Ray]) -> Vec<u8> {
    harness::trace::trace_tlas(a, &harness::compute::glsl("rq_closest.comp"), tlas, &harness::trace::ray_bytes(rays), rays.len(), 16)
}

#[test]
fn rq_closest_through_a_tlas_descriptor_matches_closest_hit() {
    let mut exts = harness::default_device_extensions();
    exts.push("VK_KHR_ray_query");
    let ctx = harness::Context::new(harness::Options { acceleration_structure: true, device_extensions: exts, ..Default::default() });
    let a = Accel::new(&ctx);
    let mesh = upload_grid(&a);
    let (blas, _) = valid_blas(&a, &mesh, NO_FLAGS);
    let tlas = build_tlas(&a, &blas);
    // Down onto both instances, between them (a miss), slanted, and one stopped short by tmax.
    let mut rays: Vec<Ray> = [(0.3, 0.4), (0.91, 0.07), (1.5, 0.5), (2.2, 0.8), (2.93, 0.31), (4.0, 0.5)]
        .iter()
        .map(|&(x, y)| Ray { origin: Vec3::new(x, y, 1.0), direction: Vec3::new(0.0, 0.0, -1.0), tmin: 0.0, tmax: 10.0 })
        .collect();
    rays.push(Ray { origin: Vec3::new(-1.0, 0.5, 1.0), direction: Vec3::new(1.7, 0.05, -1.0), tmin: 0.01, tmax: 10.0 });
    rays.push(Ray { origin: Vec3::new(0.5, 0.5, 1.0), direction: Vec3::new(0.0, 0.0, -1.0), tmin: 0.0, tmax: 0.5 });
    let out = trace(&a, tlas.s, &rays);
    let mut view = MapView::new();
    view.insert(a.address_of(blas.s), blas.r.read(&a));
    let tlas_bytes = tlas.r.read(&a);
    let mut hits = 0;
    for (i, (ray, got)) in rays.iter().zip(out.chunks(16)).enumerate() {
        let word = |k: usize| u32::from_le_bytes(got[4 * k..4 * k + 4].try_into().unwrap());
        match accel::closest_hit(&tlas_bytes, &view, *ray, RayFlags(RayFlags::OPAQUE), 0xFF) {
            Some(h) => {
                hits += 1;
                assert_eq!(word(3), 1, "ray {i}: committed kind (triangle)");
                assert_eq!((f32::from_bits(word(0)), word(1), word(2)), (h.t, h.primitive_index, h.instance_index), "ray {i}: t, primitive, instance (InstanceId is the index)");
            }
            None => assert_eq!((word(3), word(1), word(2)), (0, u32::MAX, u32::MAX), "ray {i}: miss"),
        }
    }
    assert!(hits >= 5 && hits < rays.len(), "the rays cover hits and misses ({hits} hits)");
    a.destroy();
    ctx.finish();
}

#[test]
fn an_instance_whose_blas_is_gone_is_reported_once_per_dispatch() {
    let mut exts = harness::default_device_extensions();
    exts.push("VK_KHR_ray_query");
    let ctx = harness::Context::new(harness::Options { acceleration_structure: true, device_extensions: exts, ..Default::default() });
    let a = Accel::new(&ctx);
    let mesh = upload_grid(&a);
    let (blas, _) = valid_blas(&a, &mesh, NO_FLAGS);
    let tlas = build_tlas(&a, &blas);
    // Clearing the BLAS's header after the TLAS build: its address names no built structure.
    let address = a.address_of(blas.s);
    blas.r.write(&a, 0, &[0u8; 64]);
    assert!(header_of(&a, &blas).is_none());
    // 130 rays (three workgroups), each down onto one of the two instances of the gone BLAS.
    let rays: Vec<Ray> = (0..130).map(|i| Ray { origin: Vec3::new(0.5 + 2.0 * (i % 2) as f32, 0.5, 1.0), direction: Vec3::new(0.0, 0.0, -1.0), tmin: 0.0, tmax: 10.0 }).collect();
    let out = trace(&a, tlas.s, &rays);
    for (i, got) in out.chunks(16).enumerate() {
        assert_eq!(u32::from_le_bytes(got[12..16].try_into().unwrap()), 0, "ray {i}: the instance is absent, nothing is hit");
    }
    let diag = harness::diagnostics();
    let lines: Vec<&str> = diag.lines().filter(|l| l.contains("no built bottom-level structure") && l.contains("reported once per dispatch")).collect();
    assert_eq!(lines.len(), 1, "one diagnostic for the dispatch, not one per ray:\n{diag}");
    assert!(lines[0].contains(&format!("{address:#x}")), "names the reference: {}", lines[0]);
    assert!(!diag.contains("contained memory fault"), "not a memory fault:\n{diag}");
    a.destroy();
    ctx.finish();
}

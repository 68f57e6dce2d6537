//! Ray queries through the loader (validation on) against the brute-force reference, ray by
//! ray: tests/shaders/rq_api.comp over structures built with vkCmdBuildAccelerationStructuresKHR
//! from the bunny and the dragon (data/dragon_vrip_res3.ply.gz, 47,794 triangles: the full
//! dragon's brute force would take minutes), with triangles opaque and not, spheres in AABB
//! geometries opaque and not, every instance flag combination, instance masks, rotations with
//! non-uniform scales; rays with every valid ray flag combination (on the bunny), cull masks,
//! and an alpha rule the shader applies to non-opaque triangles.
mod harness;
mod reference;

use harness::compute::glsl;
use harness::rq::{BuildPath, Built, RqGpu, Scene};
use reference::brute_force::RefResult;
use reference::rq::{check_record, ray_bytes, records, sphere_bytes, Record, RqRay, RqScene};
use reference::*;

/// rq_api.comp over `rays` on `gpu`.
fn trace(gpu: &RqGpu, built: &Built, s: &RqScene, rays: &[RqRay]) -> Vec<Record> {
    let n = rays.len();
    let push: Vec<u8> = [n as u32, s.stride].iter().flat_map(|w| w.to_le_bytes()).collect();
    let out = gpu.trace(&glsl("rq_api.comp"), &built.tlas, &[ray_bytes(rays), vec![0xEE; 64 * n], sphere_bytes(&s.spheres)], &push, n.div_ceil(32) as u32);
    records(&out[1])
}

/// Builds `s` on Arbor's device, traces `rays`, checks every record; returns (hits, hits per
/// committed type).
fn check_scene(s: &RqScene, rays: &[RqRay], what: &str) -> (usize, [usize; 3]) {
    let gpu = RqGpu::arbor();
    let geoms = s.geoms();
    let built = gpu.build(&Scene { blases: geoms.clone(), instances: s.instances.clone() }, BuildPath::Device);
    let recs = trace(&gpu, &built, s, rays);
    let refs: Vec<RefResult> = s.references(rays);
    let mut kinds = [0usize; 3];
    for (i, ((rec, r), ray)) in recs.iter().zip(&refs).zip(rays).enumerate() {
        let ctx = format!("{what}: ray {i} flags {:#x} cull {:#x} mode {}", ray.flags, ray.cull, ray.mode);
        check_record(rec, r, ray, &ctx);
        kinds[rec.kind as usize] += 1;
    }
    gpu.finish();
    (kinds[1] + kinds[2], kinds)
}

#[test]
fn bunny_every_ray_flag_cull_mask_and_instance_flag_match_brute_force() {
    let bunny = arbor_scene::load(data_path("bunny.ply")).expect("data/bunny.ply");
    let s = RqScene::new(&bunny, 14, 11);
    let rays = s.rays(&all_ray_flag_combinations(), 6, 5);
    let (hits, kinds) = check_scene(&s, &rays, "bunny");
    assert!(hits > rays.len() / 4 && kinds[1] > 100 && kinds[2] > 30, "{hits} of {} rays hit ({kinds:?}): the rays miss the scene", rays.len());
}

#[test]
fn dragon_selected_ray_flags_match_brute_force() {
    let dragon = arbor_scene::load(data_path("dragon_vrip_res3.ply.gz")).expect("data/dragon_vrip_res3.ply.gz");
    let s = RqScene::new(&dragon, 8, 21);
    let rays = s.rays(&reference::rq::selected_flag_sets(), 12, 9);
    let (hits, kinds) = check_scene(&s, &rays, "dragon");
    assert!(hits > rays.len() / 4 && kinds[1] > 30 && kinds[2] > 5, "{hits} of {} rays hit ({kinds:?}): the rays miss the scene", rays.len());
}

//! Ray queries through the loader (validation on) on the full-resolution dragon
//! (data/dragon_vrip.ply.gz, 871,414 triangles), ray by ray against the brute-force reference:
//! tests/shaders/rq_api.comp over structures built with vkCmdBuildAccelerationStructuresKHR,
//! the dragon non-opaque (with a triangle soup) and opaque in two BLASes, spheres in a third,
//! instanced with flags, masks, rotations and non-uniform scales. The rays carry the selected
//! flag sets and cull masks, and several share a lane group across workgroups: the queries a
//! lane group restarts from one ray to the next (and the structures they keep opened) must
//! give what a fresh query on each ray gives, which is what the reference says.
//!
//! A few hundred rays: the reference tests every triangle of every instance a ray can reach.
mod harness;
mod reference;

use harness::compute::glsl;
use harness::rq::{BuildPath, RqGpu, Scene};
use reference::rq::{check_record, ray_bytes, records, selected_flag_sets, sphere_bytes, RqScene};
use reference::*;

#[test]
fn full_dragon_rays_match_brute_force() {
    let dragon = arbor_scene::load(data_path("dragon_vrip.ply.gz")).expect("data/dragon_vrip.ply.gz");
    assert!(dragon.indices.len() > 800_000, "the full dragon, not a reduced one");
    let s = RqScene::new(&dragon, 4, 29);
    let rays = s.rays(&selected_flag_sets(), 16, 31);
    let refs = s.references(&rays);
    let gpu = RqGpu::arbor();
    let built = gpu.build(&Scene { blases: s.geoms(), instances: s.instances.clone() }, BuildPath::Device);
    let n = rays.len();
    let push: Vec<u8> = [n as u32, s.stride].iter().flat_map(|w| w.to_le_bytes()).collect();
    // rq_api.comp runs 32 invocations per workgroup: several workgroups per lane group.
    let out = gpu.trace(&glsl("rq_api.comp"), &built.tlas, &[ray_bytes(&rays), vec![0xEE; 64 * n], sphere_bytes(&s.spheres)], &push, n.div_ceil(32) as u32);
    gpu.finish();
    let recs = records(&out[1]);
    assert_eq!(recs.len(), n);
    let mut kinds = [0usize; 3];
    for (i, ((rec, r), ray)) in recs.iter().zip(&refs).zip(&rays).enumerate() {
        check_record(rec, r, ray, &format!("full dragon: ray {i} flags {:#x} cull {:#x} mode {}", ray.flags, ray.cull, ray.mode));
        kinds[rec.kind as usize] += 1;
    }
    println!("full dragon: {n} rays, committed per type (none, triangle, generated) {kinds:?}");
    assert!(kinds[1] + kinds[2] > n / 5 && kinds[1] > n / 8 && kinds[2] > 2, "{kinds:?} of {n} rays: the rays miss the scene");
}

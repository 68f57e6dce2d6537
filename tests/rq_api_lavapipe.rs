//! Arbor against lavapipe (Mesa 25, VK_KHR_ray_query), ray by ray, through one loader with
//! validation on: the same scenes (bunny; dragon at data/dragon_vrip_res3.ply.gz), built with
//! vkCmdBuildAccelerationStructuresKHR on each driver (lavapipe has no host or indirect builds),
//! the same rays and tests/shaders/rq_api.comp. Each driver's records are checked against the
//! brute-force reference, then against each other: hit or miss, committed type, instance,
//! geometry and primitive exactly (except exact ties in t), t and barycentrics within 1e-5
//! relative; only rays the reference calls ambiguous (a decision within rounding) may differ.
//! The naga-compiled WGSL twin of rq_closest runs on both too. Skipped, with a message, when
//! lavapipe or its ray queries are missing.
mod harness;
mod reference;

use harness::compute::{glsl, wgsl};
use harness::rq::{BuildPath, RqGpu, Scene};
use reference::brute_force::RefResult;
use reference::rq::{check_record, compare_drivers, ray_bytes, records, selected_flag_sets, sphere_bytes, Record, RqRay, RqScene};
use reference::*;

/// Relative tolerance of t and barycentrics between the drivers.
const REL: f32 = 1e-5;

fn run(gpu: RqGpu, s: &RqScene, rays: &[RqRay], spirv: &[u32]) -> Vec<Record> {
    let built = gpu.build(&Scene { blases: s.geoms(), instances: s.instances.clone() }, BuildPath::Device);
    let n = rays.len();
    let push: Vec<u8> = [n as u32, s.stride].iter().flat_map(|w| w.to_le_bytes()).collect();
    let out = gpu.trace(spirv, &built.tlas, &[ray_bytes(rays), vec![0xEE; 64 * n], sphere_bytes(&s.spheres)], &push, n.div_ceil(32) as u32);
    gpu.finish();
    records(&out[1])
}

fn check_all(recs: &[Record], refs: &[RefResult], rays: &[RqRay], what: &str) {
    for (i, ((rec, r), ray)) in recs.iter().zip(refs).zip(rays).enumerate() {
        check_record(rec, r, ray, &format!("{what}: ray {i} flags {:#x} cull {:#x} mode {}", ray.flags, ray.cull, ray.mode));
    }
}

fn compare(mesh: &str, instances: usize, flag_sets: &[u32], per_flags: usize) {
    let Some(lvp) = RqGpu::lavapipe() else { return };
    let s = RqScene::new(&arbor_scene::load(data_path(mesh)).expect(mesh), instances, 41);
    let rays = s.rays(flag_sets, per_flags, 13);
    let refs = s.references(&rays);
    let spirv = glsl("rq_api.comp");
    let theirs = run(lvp, &s, &rays, &spirv);
    let ours = run(RqGpu::arbor(), &s, &rays, &spirv);
    check_all(&ours, &refs, &rays, &format!("{mesh} on Arbor"));
    check_all(&theirs, &refs, &rays, &format!("{mesh} on lavapipe"));
    let geoms = s.geoms();
    let bary_tol = |i: usize, r: &Record| s.bary_tolerance(&geoms, r, &rays[i].ray, REL);
    let forgiven = compare_drivers(&ours, &theirs, &rays, &refs, REL, &bary_tol, mesh);
    let hits = ours.iter().filter(|r| r.kind != 0).count();
    let generated = ours.iter().filter(|r| r.kind == 2).count();
    println!("{mesh}: {} rays, {hits} hits on Arbor ({generated} generated), {forgiven} differ on ambiguous rays", rays.len());
    assert!(hits > rays.len() / 5 && generated > 2, "{hits} of {} rays hit ({generated} generated): the rays miss the scene", rays.len());
    assert!(forgiven * 20 <= rays.len(), "{forgiven} of {} rays differ between the drivers", rays.len());
}

#[test]
fn bunny_every_ray_flag_on_lavapipe_and_arbor_agree_ray_by_ray() {
    compare("bunny.ply", 14, &all_ray_flag_combinations(), 3);
}

#[test]
fn dragon_on_lavapipe_and_arbor_agree_ray_by_ray() {
    compare("dragon_vrip_res3.ply.gz", 8, &selected_flag_sets(), 12);
}

#[test]
fn naga_rq_closest_gives_the_same_records_on_lavapipe_and_arbor() {
    let Some(lvp) = RqGpu::lavapipe() else { return };
    let s = RqScene::new(&arbor_scene::load(data_path("bunny.ply")).expect("bunny"), 10, 43);
    let rays = s.rays(&[0], 64, 17);
    let bytes: Vec<u8> = rays.iter().flat_map(|r| [r.ray.origin.x, r.ray.origin.y, r.ray.origin.z, r.ray.tmin, r.ray.direction.x, r.ray.direction.y, r.ray.direction.z, r.ray.tmax]).flat_map(f32::to_le_bytes).collect();
    let push: Vec<u8> = [rays.len() as u32, 0].iter().flat_map(|w| w.to_le_bytes()).collect();
    let spirv = wgsl("rq_closest.wgsl");
    let trace = |gpu: RqGpu| {
        let built = gpu.build(&Scene { blases: s.geoms(), instances: s.instances.clone() }, BuildPath::Device);
        let out = gpu.trace(&spirv, &built.tlas, &[bytes.clone(), vec![0xEE; 16 * rays.len()]], &push, rays.len().div_ceil(64) as u32);
        gpu.finish();
        out[1].chunks(16).map(|h| h.chunks(4).map(|w| u32::from_le_bytes(w.try_into().unwrap())).collect::<Vec<u32>>()).collect::<Vec<_>>()
    };
    let theirs = trace(lvp);
    let ours = trace(RqGpu::arbor());
    let refs = s.references(&rays.iter().map(|r| RqRay { flags: OPAQUE, cull: 0xFF, mode: 0, ..*r }).collect::<Vec<_>>());
    let mut hits = 0;
    for (i, ((a, b), r)) in ours.iter().zip(&theirs).zip(&refs).enumerate() {
        hits += (a[3] != 0) as usize;
        let same = a[3] == b[3] && (a[3] == 0 || ((a[1], a[2]) == (b[1], b[2]) || f32::from_bits(a[0]) == f32::from_bits(b[0])) && (f32::from_bits(a[0]) - f32::from_bits(b[0])).abs() <= REL * f32::from_bits(a[0]).abs().max(1.0));
        assert!(same || reference::rq::ambiguous(r), "ray {i}: Arbor {a:?}, lavapipe {b:?}");
    }
    assert!(hits > rays.len() / 5, "{hits} of {} rays hit", rays.len());
}


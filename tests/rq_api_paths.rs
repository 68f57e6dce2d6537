//! Every build path traces identically through the loader (validation on): the same scene
//! (bunny, soup and spheres, every instance flag, non-uniform instance transforms) built on the
//! host (vkBuildAccelerationStructuresKHR from host memory), on the device
//! (vkCmdBuildAccelerationStructuresKHR), indirectly (vkCmdBuildAccelerationStructuresIndirectKHR),
//! and as compacted and as deserialized copies of device builds gives bit-identical records
//! from tests/shaders/rq_api.comp, and the device build's records match the brute-force
//! reference. Also: rq_closest compiled by glslang, by `spirv-opt -O` and by naga (its WGSL
//! twin) gives the same records through the API, and they match the reference.
mod harness;
mod reference;

use harness::compute::{glsl, optimized, wgsl};
use harness::rq::{BuildPath, Built, RqGpu, Scene, ALL_PATHS};
use reference::rq::{check_record, ray_bytes, records, selected_flag_sets, sphere_bytes, Record, RqRay, RqScene};
use reference::*;

fn trace(gpu: &RqGpu, built: &Built, s: &RqScene, rays: &[RqRay]) -> Vec<u8> {
    let n = rays.len();
    let push: Vec<u8> = [n as u32, s.stride].iter().flat_map(|w| w.to_le_bytes()).collect();
    gpu.trace(&glsl("rq_api.comp"), &built.tlas, &[ray_bytes(rays), vec![0xEE; 64 * n], sphere_bytes(&s.spheres)], &push, n.div_ceil(32) as u32).swap_remove(1)
}

fn bunny_scene() -> RqScene {
    RqScene::new(&arbor_scene::load(data_path("bunny.ply")).expect("data/bunny.ply"), 14, 31)
}

#[test]
fn host_device_indirect_compacted_and_deserialized_structures_trace_bit_identically() {
    let s = bunny_scene();
    let rays = s.rays(&selected_flag_sets(), 16, 3);
    let gpu = RqGpu::arbor();
    assert!(gpu.host_commands && gpu.indirect_build, "Arbor advertises host commands and indirect builds");
    let scene = Scene { blases: s.geoms(), instances: s.instances.clone() };
    let device = trace(&gpu, &gpu.build(&scene, BuildPath::Device), &s, &rays);
    let refs = s.references(&rays);
    let recs: Vec<Record> = records(&device);
    let mut hits = 0;
    for (i, ((rec, r), ray)) in recs.iter().zip(&refs).zip(&rays).enumerate() {
        hits += check_record(rec, r, ray, &format!("device build: ray {i} flags {:#x} cull {:#x} mode {}", ray.flags, ray.cull, ray.mode)) as usize;
    }
    assert!(hits > rays.len() / 4 && recs.iter().any(|r| r.kind == 2), "{hits} of {} rays hit: the rays miss the scene", rays.len());
    for path in ALL_PATHS.into_iter().filter(|&p| p != BuildPath::Device) {
        let got = trace(&gpu, &gpu.build(&scene, path), &s, &rays);
        if got != device {
            let other = records(&got);
            let i = (0..rays.len()).find(|&i| other[i] != recs[i]).unwrap();
            panic!("{path:?}: ray {i} traces differently from the device build: {:?} vs {:?}", other[i], recs[i]);
        }
    }
    gpu.finish();
}

/// rq_closest.comp's rays buffer: origin, tmin, direction, tmax.
fn closest_rays(rays: &[RqRay]) -> Vec<u8> {
    rays.iter().flat_map(|r| [r.ray.origin.x, r.ray.origin.y, r.ray.origin.z, r.ray.tmin, r.ray.direction.x, r.ray.direction.y, r.ray.direction.z, r.ray.tmax]).flat_map(f32::to_le_bytes).collect()
}

/// rq_closest's hit records (t, primitive, instance, committed type) as rq_api records, for
/// the same reference check: it traverses opaque, so a committed triangle was never a candidate.
fn closest_records(bytes: &[u8]) -> Vec<Record> {
    let w: Vec<u32> = bytes.chunks(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
    w.chunks(4)
        .map(|h| Record { kind: h[3], t: if h[3] == 0 { 0.0 } else { f32::from_bits(h[0]) }, primitive: if h[3] == 0 { 0 } else { h[1] }, instance: if h[3] == 0 { 0 } else { h[2] }, ..Record::default() })
        .collect()
}

#[test]
fn rq_closest_from_glslang_spirv_opt_and_naga_traces_identically_through_the_api() {
    let s = bunny_scene();
    // rq_closest adds OPAQUE itself and takes one flag word for every ray: flags that leave
    // the opacity alone, cull mask 0xFF.
    let flags = CULL_BACK | SKIP_AABBS;
    let rays: Vec<RqRay> = s.rays(&[flags], 96, 7).into_iter().map(|r| RqRay { cull: 0xFF, mode: 0, ..r }).collect();
    let gpu = RqGpu::arbor();
    let built = gpu.build(&Scene { blases: s.geoms(), instances: s.instances.clone() }, BuildPath::Device);
    let glslang = glsl("rq_closest.comp");
    let shaders = [("glslang", glslang.clone()), ("spirv-opt -O", optimized(&glslang)), ("naga", wgsl("rq_closest.wgsl"))];
    let push: Vec<u8> = [rays.len() as u32, flags].iter().flat_map(|w| w.to_le_bytes()).collect();
    let outs: Vec<Vec<u8>> = shaders
        .iter()
        .map(|(_, spirv)| gpu.trace(spirv, &built.tlas, &[closest_rays(&rays), vec![0xEE; 16 * rays.len()]], &push, rays.len().div_ceil(64) as u32).swap_remove(1))
        .collect();
    let opaque: Vec<RqRay> = rays.iter().map(|r| RqRay { flags: r.flags | OPAQUE, ..*r }).collect();
    let refs = s.references(&opaque);
    let recs = closest_records(&outs[0]);
    let mut hits = 0;
    for (i, ((rec, r), ray)) in recs.iter().zip(&refs).zip(&opaque).enumerate() {
        let ctx = format!("rq_closest (glslang): ray {i}");
        // Without a committed hit the shader writes t -1 and ~0 for primitive and instance.
        let raw = &outs[0][16 * i..16 * i + 16];
        if rec.kind == 0 {
            assert_eq!(raw[..12], [(-1.0f32).to_le_bytes(), [0xFF; 4], [0xFF; 4]].concat()[..], "{ctx}: miss record");
        }
        // rq_closest writes no custom index, SBT offset or geometry: take the reference's.
        let filled = reference::rq::hit_of(rec).and_then(|h| r.hits.iter().find(|x| (x.id.instance, x.id.primitive) == (h.instance_index, h.primitive_index)));
        let rec = Record { custom: filled.map_or(0, |x| x.custom_index), sbt: filled.map_or(0, |x| x.sbt_offset), geometry: filled.map_or(0, |x| x.id.geometry), front: filled.is_some_and(|x| x.front), bary: filled.map_or([0.0; 2], |x| x.uv), ..*rec };
        hits += check_record(&rec, r, ray, &ctx) as usize;
    }
    assert!(hits > rays.len() / 4, "{hits} of {} rays hit", rays.len());
    for ((what, _), out) in shaders.iter().zip(&outs).skip(1) {
        assert!(*out == outs[0], "rq_closest from {what} traces differently from glslang's");
    }
    gpu.finish();
}

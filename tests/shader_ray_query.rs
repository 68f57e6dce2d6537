//! Ray queries in the shader library (`arbor::shader`), no Vulkan device: the milestone shaders
//! (tests/shaders/rq_*.comp, compiled by glslang and again through `spirv-opt -O`, and their
//! WGSL twins through the naga crate) run over structures built with
//! `arbor::accel::build` in host memory, and every record is compared with the brute-force
//! reference of the Vulkan traversal rules in tests/reference (written from the specification,
//! not from the library's traversal).
mod harness;
mod reference;

use std::collections::HashMap;
use std::path::PathBuf;
use std::process::Command;

use arbor::accel::{self, AsType, DeviceView, Geometry, GeometryData, GeometryFlags, Hit, HitKind, MapView, Ray};
use arbor::shader::{dispatch, DispatchReport, FaultKind, FaultSpace, HostMemory, Memory, Module, Pipeline, Region, Watchdog};
use arbor_scene::{self as scene, InstanceRecord, Mesh, Rng};
use glam::Vec3;
use reference::brute_force::{check_closest, reference, PrimId, RefResult, RefScene, Tolerance};
use reference::*;

// ---------------------------------------------------------------------------------------------
// Shaders

fn words_of(path: &std::path::Path) -> Vec<u32> {
    let bytes = std::fs::read(path).unwrap();
    bytes.chunks(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

fn scratch_dir() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("arbor-rq-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// tests/shaders/`name`.comp through glslang (`defines` as -D), then through `spirv-opt -O`.
fn glsl(name: &str, defines: &[&str]) -> Vec<(String, Vec<u32>)> {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/shaders").join(format!("{name}.comp"));
    let dir = scratch_dir();
    let tag = defines.join("_");
    let (spv, opt) = (dir.join(format!("{name}{tag}.spv")), dir.join(format!("{name}{tag}.opt.spv")));
    let mut cmd = Command::new("glslangValidator");
    cmd.args(["-V", "--target-env", "vulkan1.2"]);
    for d in defines {
        cmd.arg(format!("-D{d}"));
    }
    let out = cmd.arg("-o").arg(&spv).arg(&src).output().expect("glslangValidator (Debian: glslang-tools)");
    assert!(out.status.success(), "glslang failed on {name}: {}", String::from_utf8_lossy(&out.stdout));
    let out = Command::new("spirv-opt").arg("-O").arg(&spv).arg("-o").arg(&opt).output().expect("spirv-opt (Debian: spirv-tools)");
    assert!(out.status.success(), "spirv-opt failed on {name}: {}", String::from_utf8_lossy(&out.stderr));
    vec![(format!("{name} (glslang)"), words_of(&spv)), (format!("{name} (spirv-opt -O)"), words_of(&opt))]
}

/// tests/shaders/`name`.wgsl through the naga crate (WGSL in, SPIR-V out: the compute
/// harness's compiler), a second front end beside glslang.
fn wgsl(name: &str) -> (String, Vec<u32>) {
    (format!("{name} (naga)"), harness::compute::wgsl(&format!("{name}.wgsl")))
}

fn pipeline(what: &str, words: &[u32]) -> Pipeline {
    let module = Module::parse(words).unwrap_or_else(|e| panic!("{what}: parse: {e}"));
    Pipeline::compute(&module, "main", &[]).unwrap_or_else(|e| panic!("{what}: pipeline: {e}"))
}

// ---------------------------------------------------------------------------------------------
// Memory: host buffers plus structures in a MapView

/// The test's device memory: buffers in `HostMemory`, structures (and instance buffers) in a
/// `MapView` at their device addresses, one structure descriptor at (0, 0).
struct RqMemory {
    host: HostMemory,
    view: MapView,
    tlas: Option<u64>,
}

impl Memory for RqMemory {
    fn binding(&self, set: u32, binding: u32) -> Option<Region> {
        self.host.binding(set, binding)
    }
    fn address(&self, address: u64, len: u64) -> Option<Region> {
        self.host.address(address, len)
    }
    fn read(&self, buffer: u64, offset: u64, out: &mut [u8]) -> bool {
        self.host.read(buffer, offset, out)
    }
    fn write(&self, buffer: u64, offset: u64, data: &[u8]) -> bool {
        self.host.write(buffer, offset, data)
    }
    fn atomic(&self, buffer: u64, offset: u64, size: usize, update: &dyn Fn(u64) -> u64) -> Option<u64> {
        self.host.atomic(buffer, offset, size, update)
    }
    fn acceleration_structure(&self, set: u32, binding: u32) -> Option<u64> {
        ((set, binding) == (0, 0)).then_some(self.tlas).flatten()
    }
    fn acceleration_structures(&self) -> Option<&dyn DeviceView> {
        Some(&self.view)
    }
}

/// Binds `buffers` at set 0, bindings `first..`, dispatches, returns the report and the final
/// contents of the buffers.
fn run(p: &Pipeline, mem: &mut RqMemory, first: u32, buffers: &[Vec<u8>], push: &[u8], groups: [u32; 3]) -> (DispatchReport, Vec<Vec<u8>>) {
    let idx: Vec<usize> = buffers.iter().map(|b| mem.host.add_buffer(b)).collect();
    for (k, &i) in idx.iter().enumerate() {
        mem.host.bind(0, first + k as u32, i);
    }
    let report = dispatch(p, mem, push, groups, [0; 3], &Watchdog::default());
    (report, idx.iter().map(|&i| mem.host.bytes(i)).collect())
}

fn u32s(b: &[u8]) -> Vec<u32> {
    b.chunks(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

fn bytes_of(words: &[u32]) -> Vec<u8> {
    words.iter().flat_map(|w| w.to_le_bytes()).collect()
}

fn ray_bytes(rays: &[Ray]) -> Vec<u8> {
    let mut out = Vec::new();
    for r in rays {
        for v in [r.origin.x, r.origin.y, r.origin.z, r.tmin, r.direction.x, r.direction.y, r.direction.z, r.tmax] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Scenes

const BLAS_BASE: u64 = 0x10_0000_0000;
/// Above every BLAS address (BLAS_BASE * (k + 1) for the few BLASes of a scene).
const TLAS_ADDRESS: u64 = 0x7F_0000_0000;

/// A TLAS over several BLASes in a `MapView`, with what the reference needs.
struct Scene {
    view: MapView,
    instances: Vec<InstanceRecord>,
    blas_geoms: Vec<(u64, Vec<TriData>, Vec<AabbData>)>,
    bounds: [f32; 6],
}

impl Scene {
    /// BLASes: each entry's triangle and AABB geometries; `n` instances over them with random
    /// transforms, instance flags, masks, custom indices and SBT offsets (some inactive).
    fn new(blases: Vec<(Vec<TriData>, Vec<AabbData>)>, n: usize, seed: u64) -> Scene {
        let mut view = MapView::new();
        let mut blas_geoms = Vec::new();
        let mut blas_bounds = HashMap::new();
        for (k, (tris, boxes)) in blases.into_iter().enumerate() {
            let address = BLAS_BASE * (k as u64 + 1);
            let geoms: Vec<Geometry> = tris.iter().map(|d| d.geometry()).chain(boxes.iter().map(|b| b.geometry())).collect();
            let built = build_blas(0, &geoms);
            blas_bounds.insert(address, accel::header(&built.bytes).unwrap().bounds);
            view.insert(address, built.bytes);
            blas_geoms.push((address, tris, boxes));
        }
        let refs: Vec<u64> = blas_geoms.iter().map(|b| b.0).collect();
        let mut instances = scene::instance_records(n, &refs, seed);
        let mut rng = Rng::new(seed);
        let flag_combos = all_instance_flag_combinations();
        for (i, inst) in instances.iter_mut().enumerate() {
            inst.flags = flag_combos[rng.below(flag_combos.len() as u32) as usize];
            inst.mask = [0xFF, 0x01, 0x02, 0x80, 0x0F, 0xF0][rng.below(6) as usize];
            inst.custom_index = rng.next_u32() & 0xFF_FFFF;
            inst.sbt_offset = rng.next_u32() & 0xFF_FFFF;
            if i % 11 == 5 {
                inst.reference = 0;
            }
        }
        let mut corners = Vec::new();
        for inst in instances.iter().filter(|i| i.reference != 0) {
            let b = blas_bounds[&inst.reference];
            let m: [f64; 12] = inst.transform.map(|x| x as f64);
            for c in 0..8 {
                let p = [b[if c & 1 == 0 { 0 } else { 3 }], b[if c & 2 == 0 { 1 } else { 4 }], b[if c & 4 == 0 { 2 } else { 5 }]];
                corners.push(xform_point(&m, p.map(|x| x as f64)).map(|x| x as f32));
            }
        }
        let mut s = Scene { view, instances, blas_geoms, bounds: union_bounds(corners) };
        let packed = InstanceRecord::pack(&s.instances);
        let g = [Geometry {
            flags: GeometryFlags(0),
            primitive_count: s.instances.len() as u32,
            data: GeometryData::Instances { array_of_pointers: false, data: &packed },
        }];
        let tlas = build(AsType::TopLevel, 0, &g, &s.view);
        s.view.insert(TLAS_ADDRESS, tlas.bytes);
        s
    }

    fn geoms(&self) -> Vec<(u64, Vec<Geometry<'_>>)> {
        self.blas_geoms
            .iter()
            .map(|(a, t, b)| (*a, t.iter().map(|d| d.geometry()).chain(b.iter().map(|x| x.geometry())).collect()))
            .collect()
    }

    /// The memory a dispatch sees: a copy of the structures, the TLAS bound at (0, 0).
    fn memory(&self) -> RqMemory {
        let mut view = MapView::new();
        for a in self.blas_geoms.iter().map(|b| b.0).chain([TLAS_ADDRESS]) {
            view.insert(a, self.view.acceleration_structure(a).unwrap().to_vec());
        }
        RqMemory { host: HostMemory::new(), view, tlas: Some(TLAS_ADDRESS) }
    }
}

fn bunny() -> Mesh {
    let m = scene::load(data_path("bunny.ply")).expect("data/bunny.ply");
    // Into the unit cube, where `instance_records` expects objects.
    let b = m.bounds();
    let s = 1.0 / (b[3] - b[0]).max(b[4] - b[1]).max(b[5] - b[2]);
    let positions = m.positions.iter().map(|p| [(p[0] - b[0]) * s, (p[1] - b[1]) * s, (p[2] - b[2]) * s]).collect();
    Mesh { positions, ..m }
}

/// Bunny (non-opaque and opaque), a triangle soup with a geometry transform, soup boxes
/// (opaque and not), and a unit box around the origin (the any-hit shader's sphere).
fn mixed_scene(seed: u64) -> Scene {
    let bunny = bunny();
    let soup = scene::random_soup(300, seed);
    let mut soup_tris = TriData::from_mesh(&soup, 0);
    soup_tris.transform = Some([1.0, 0.0, 0.0, 0.1, 0.0, 0.8, 0.0, 0.0, 0.0, 0.0, 1.0, 0.2]);
    let boxes = boxes_of(&scene::random_soup(150, seed + 1));
    let blases = vec![
        (vec![TriData::from_mesh(&bunny, 0)], vec![]),
        (vec![TriData::from_mesh(&bunny, GEOMETRY_OPAQUE)], vec![]),
        (vec![soup_tris, TriData::from_mesh(&scene::random_soup(100, seed + 2), GEOMETRY_OPAQUE)], vec![]),
        (vec![], vec![AabbData::new(&boxes, 24, GEOMETRY_OPAQUE), AabbData::new(&boxes[..60], 32, 0)]),
        (vec![], vec![AabbData::new(&[[-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]], 24, 0)]),
    ];
    Scene::new(blases, 24, seed)
}

fn reference_scene<'a>(s: &Scene, geoms: &'a [(u64, Vec<Geometry<'a>>)]) -> RefScene<'a> {
    let blases = geoms.iter().map(|(a, g)| (*a, g.as_slice())).collect();
    RefScene::Tlas { instances: s.instances.clone(), blases }
}

// ---------------------------------------------------------------------------------------------
// Comparing records with the reference

/// A hit the shader may commit, from the reference.
#[derive(Clone, Copy, Debug)]
struct Expect {
    id: PrimId,
    t: f32,
    /// Committed type: 1 triangle, 2 generated.
    kind: u32,
    /// Distance from a decision flipping; below `AMBIGUOUS` a disagreement is rounding.
    margin: f64,
}

const AMBIGUOUS: f64 = 1e-5;

fn t_close(a: f32, b: f32) -> bool {
    (a - b).abs() <= 1e-4 * a.abs().max(b.abs()).max(1.0)
}

/// What a shader wrote about its committed hit. `geometry: None` when it does not write it.
struct Record {
    kind: u32,
    t: f32,
    inst: u32,
    geometry: Option<u32>,
    prim: u32,
}

/// One record against the hits the reference accepts. With `any`, any acceptable hit will do
/// (TERMINATE_ON_FIRST_HIT); else the nearest, up to ties and rounding-ambiguous decisions.
/// Returns whether something was committed.
fn check_record(rec: Record, ok: &[Expect], near: &[(PrimId, bool)], any: bool, ctx: &str) -> bool {
    let Record { kind, t, inst, geometry, prim } = rec;
    let same = |id: &PrimId| id.instance == inst && id.primitive == prim && geometry.is_none_or(|g| g == id.geometry);
    let forgivable = |e: &Expect| e.margin < AMBIGUOUS;
    if kind == 0 {
        assert!(ok.iter().all(forgivable), "{ctx}: nothing committed, reference accepts {:?}", ok.iter().find(|e| !forgivable(e)));
        return false;
    }
    let found = ok.iter().find(|e| same(&e.id));
    match found {
        Some(e) => {
            assert_eq!(kind, e.kind, "{ctx}: committed type of {:?}", e.id);
            assert!(t_close(t, e.t) || forgivable(e), "{ctx}: t {t} vs reference {} for {:?}", e.t, e.id);
        }
        None => assert!(near.iter().any(|(id, _)| same(id)), "{ctx}: committed inst {inst} prim {prim} (t {t}) is no reference hit"),
    }
    if !any {
        let best = ok.iter().min_by(|a, b| a.t.total_cmp(&b.t)).expect("a committed hit with no reference hit");
        let tie = found.is_some_and(|e| t_close(e.t, best.t) || forgivable(e));
        assert!(t_close(t, best.t) || forgivable(best) || tie, "{ctx}: committed t {t} ({inst}/{prim}), reference nearest {:?} at {}", best.id, best.t);
    }
    true
}

/// Flag sets the milestone closest-hit shader can take (it adds OPAQUE itself, and the spec
/// allows one opacity flag only).
fn closest_flag_sets() -> Vec<u32> {
    let mut v: Vec<u32> = all_ray_flag_combinations().into_iter().filter(|f| f & (OPAQUE | NO_OPAQUE | CULL_OPAQUE | CULL_NO_OPAQUE) == 0).collect();
    v.retain(|f| f & SKIP_CLOSEST_HIT == 0 || f & CULL_BACK != 0);
    v
}

#[test]
fn rq_closest_matches_brute_force() {
    let s = mixed_scene(3);
    let geoms = s.geoms();
    let rscene = reference_scene(&s, &geoms);
    let rays = random_rays(s.bounds, 96, 41);
    let mut shaders = glsl("rq_closest", &[]);
    shaders.push(wgsl("rq_closest"));
    let pipelines: Vec<(String, Pipeline)> = shaders.iter().map(|(w, words)| (w.clone(), pipeline(w, words))).collect();
    let mut hits = 0;
    for flags in closest_flag_sets() {
        let refs: Vec<RefResult> = rays.iter().map(|ray| reference(&rscene, ray, flags | OPAQUE, 0xFF)).collect();
        for (what, p) in &pipelines {
            let mut mem = s.memory();
            let push = bytes_of(&[rays.len() as u32, flags]);
            let out = vec![0xEEu8; 16 * rays.len()];
            let (report, bufs) = run(p, &mut mem, 1, &[ray_bytes(&rays), out], &push, [rays.len().div_ceil(64) as u32, 1, 1]);
            assert!(report.is_clean(), "{what}: {report:?}");
            let rec = u32s(&bufs[1]);
            for (i, r) in refs.iter().enumerate() {
                // Opaque traversal: AABB candidates are never generated by this shader.
                let ok: Vec<Expect> = r.hits.iter().filter(|h| h.triangle).map(|h| Expect { id: h.id, t: h.t, kind: 1, margin: h.margin }).collect();
                let [t, prim, inst, kind] = [0, 1, 2, 3].map(|k| rec[4 * i + k]);
                let ctx = format!("{what} flags {flags:#x} ray {i}");
                if kind == 0 {
                    assert_eq!((f32::from_bits(t), prim, inst), (-1.0, !0, !0), "{ctx}: miss record");
                }
                hits += check_record(Record { kind, t: f32::from_bits(t), inst, geometry: None, prim }, &ok, &r.near_misses, flags & TERMINATE_ON_FIRST_HIT != 0, &ctx) as u32;
            }
        }
    }
    assert!(hits > 200, "only {hits} committed hits: the rays miss the scene");
}

/// Triangles (non-opaque, and opaque with a geometry transform) and boxes (opaque and not)
/// without the bunny: small enough for every ray flag combination.
fn small_scene(seed: u64) -> Scene {
    let mut opaque = TriData::from_mesh(&scene::random_soup(150, seed + 3), GEOMETRY_OPAQUE);
    opaque.transform = Some([0.9, 0.1, 0.0, 0.0, 0.0, 1.0, 0.0, 0.1, 0.0, 0.0, 1.1, 0.0]);
    let boxes = boxes_of(&scene::random_soup(80, seed + 4));
    let blases = vec![
        (vec![TriData::from_mesh(&scene::random_soup(150, seed), 0), opaque], vec![]),
        (vec![], vec![AabbData::new(&boxes[..40], 24, GEOMETRY_OPAQUE), AabbData::new(&boxes[40..], 24, 0)]),
    ];
    Scene::new(blases, 16, seed)
}

fn f32_at(rec: &[u32], k: usize) -> f32 {
    f32::from_bits(rec[k])
}

fn vec3_at(rec: &[u32], k: usize) -> Vec3 {
    Vec3::new(f32_at(rec, k), f32_at(rec, k + 1), f32_at(rec, k + 2))
}

/// The committed hit of one rq_getters record as an `accel::Hit`, for the reference's own
/// comparison; opacity is what the shader saw (a confirmed triangle was a candidate, so not
/// opaque; a generated box reports its candidate opacity).
fn hit_of(rec: &[u32]) -> Option<Hit> {
    let kind = match rec[0] {
        0 => return None,
        1 => HitKind::Triangle,
        _ => HitKind::Aabb,
    };
    let opaque = if kind == HitKind::Triangle { rec[19] == 0 } else { rec[20] != 0 };
    let mut o2w = [0f32; 12];
    let mut w2o = [0f32; 12];
    for c in 0..4 {
        for r in 0..3 {
            o2w[4 * r + c] = f32_at(rec, 27 + 3 * c + r);
            w2o[4 * r + c] = f32_at(rec, 39 + 3 * c + r);
        }
    }
    Some(Hit {
        t: f32_at(rec, 10),
        kind,
        barycentrics: [f32_at(rec, 17), f32_at(rec, 18)],
        front_face: rec[16] != 0,
        opaque,
        instance_index: rec[11],
        instance_custom_index: rec[14],
        sbt_record_offset: rec[15],
        geometry_index: rec[12],
        primitive_index: rec[13],
        object_ray_origin: vec3_at(rec, 21),
        object_ray_direction: vec3_at(rec, 24),
        object_to_world: o2w,
        world_to_object: w2o,
        vertices: [Vec3::ZERO; 3], // not read by rq_getters (position fetch has its own test)
        cluster_id: -1,
    })
}

fn close3(a: Vec3, b: [f64; 3], scale: f64) -> bool {
    (0..3).all(|k| (a[k] as f64 - b[k]).abs() <= 1e-4 * scale.max(b[k].abs()).max(1.0))
}

/// The getters of the ray itself, and the instance-derived ones of a committed hit.
fn check_ray_and_instance(rec: &[u32], ray: &Ray, flags: u32, s: &Scene, hit: Option<&Hit>, ctx: &str) {
    assert_eq!(rec[2], flags, "{ctx}: ray flags");
    assert_eq!(f32_at(rec, 3), ray.tmin, "{ctx}: tmin");
    assert_eq!((vec3_at(rec, 4), vec3_at(rec, 7)), (ray.origin, ray.direction), "{ctx}: world ray");
    let Some(h) = hit else {
        assert_eq!(f32_at(rec, 10), ray.tmax, "{ctx}: committed t with nothing committed is tmax");
        return;
    };
    let inst = &s.instances[h.instance_index as usize];
    assert_eq!(h.object_to_world, inst.transform, "{ctx}: object-to-world");
    let inv = invert_3x4(&inst.transform).expect("invertible instance transform");
    for (k, (&got, &want)) in h.world_to_object.iter().zip(&inv).enumerate() {
        assert!((got as f64 - want).abs() <= 1e-4 * want.abs().max(1.0), "{ctx}: world-to-object {k}");
    }
    let f = |v: Vec3| [v.x as f64, v.y as f64, v.z as f64];
    let scale = ray.origin.abs().max_element() as f64 * 4.0;
    assert!(close3(h.object_ray_origin, xform_point(&inv, f(ray.origin)), scale), "{ctx}: object ray origin");
    assert!(close3(h.object_ray_direction, xform_vector(&inv, f(ray.direction)), 1.0), "{ctx}: object ray direction");
}

#[test]
fn rq_getters_every_flag_and_cull_mask_match_brute_force() {
    let s = small_scene(7);
    let geoms = s.geoms();
    let rscene = reference_scene(&s, &geoms);
    let rays = random_rays(s.bounds, 16, 23);
    let shaders: Vec<(String, Pipeline)> = glsl("rq_getters", &[]).into_iter().map(|(w, words)| {
        let p = pipeline(&w, &words);
        (w, p)
    }).collect();
    let mut hits = 0;
    for flags in all_ray_flag_combinations() {
        for cull in [0xFFu32, 0x01, 0x70, 0x100] {
            let refs: Vec<RefResult> = rays.iter().map(|ray| reference(&rscene, ray, flags, cull as u8)).collect();
            for (what, p) in &shaders {
                let mut mem = s.memory();
                let push = bytes_of(&[rays.len() as u32, flags, cull]);
                let out = vec![0u8; 256 * rays.len()];
                let (report, bufs) = run(p, &mut mem, 1, &[ray_bytes(&rays), out], &push, [rays.len().div_ceil(16) as u32, 1, 1]);
                assert!(report.is_clean(), "{what}: {report:?}");
                let recs = u32s(&bufs[1]);
                for (i, ray) in rays.iter().enumerate() {
                    let rec = &recs[64 * i..64 * (i + 1)];
                    let ctx = format!("{what} flags {flags:#x} cull {cull:#x} ray {i}");
                    let hit = hit_of(rec);
                    check_closest(hit.as_ref(), &refs[i], flags, Tolerance { exact: false }, &ctx);
                    check_ray_and_instance(rec, ray, flags, &s, hit.as_ref(), &ctx);
                    hits += hit.is_some() as u32;
                }
            }
        }
    }
    assert!(hits > 1000, "only {hits} committed hits");
}

/// The any-hit shader's camera: origin (w = tmin), lower-left corner of the image plane (w =
/// tmax), pixel steps, image size; and the world-space ray of each pixel as the shader
/// computes it.
struct Camera {
    origin: Vec3,
    lower_left: Vec3,
    du: Vec3,
    dv: Vec3,
    tmin: f32,
    tmax: f32,
    size: [u32; 2],
}

impl Camera {
    fn looking_at(b: [f32; 6], size: [u32; 2]) -> Camera {
        let centre = Vec3::new(b[0] + b[3], b[1] + b[4], b[2] + b[5]) * 0.5;
        let ext = Vec3::new(b[3] - b[0], b[4] - b[1], b[5] - b[2]);
        let origin = centre + Vec3::new(0.1 * ext.x, 0.2 * ext.y, 1.5 * ext.x.max(ext.y).max(ext.z));
        let forward = (centre - origin).normalize();
        let right = forward.cross(Vec3::Y).normalize();
        let up = right.cross(forward);
        let half = 0.45 * ext.x.max(ext.y);
        let (du, dv) = (right * (2.0 * half / size[0] as f32), up * (2.0 * half / size[1] as f32));
        let lower_left = centre - right * half - up * half;
        Camera { origin, lower_left, du, dv, tmin: 0.01, tmax: 1e4, size }
    }

    fn ubo(&self, mask_address: u64) -> Vec<u8> {
        let mut out = Vec::new();
        for (v, w) in [(self.origin, self.tmin), (self.lower_left, self.tmax), (self.du, 0.0), (self.dv, 0.0)] {
            for x in [v.x, v.y, v.z, w] {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        out.extend_from_slice(&self.size[0].to_le_bytes());
        out.extend_from_slice(&self.size[1].to_le_bytes());
        out.extend_from_slice(&mask_address.to_le_bytes());
        out
    }

    fn ray(&self, x: u32, y: u32) -> Ray {
        let p = self.lower_left + (x as f32 + 0.5) * self.du + (y as f32 + 0.5) * self.dv - self.origin;
        Ray { origin: self.origin, direction: p.normalize(), tmin: self.tmin, tmax: self.tmax }
    }
}

/// What rq_anyhit may commit for `ray`: opaque triangles, non-opaque ones passing its alpha
/// test (mask bit, or barycentric x < 0.5), and boxes whose object-space unit sphere the ray
/// enters within [tmin, tmax] (generated at the sphere's t). Also an upper bound on the
/// candidates Proceed may stop at.
fn anyhit_reference(r: &RefResult, s: &Scene, ray: &Ray, mask: &[u32]) -> (Vec<Expect>, usize) {
    let mut ok = Vec::new();
    let mut candidates = r.near_misses.len();
    for h in &r.hits {
        if h.triangle {
            let bit = (mask[(h.id.primitive >> 5) as usize] >> (h.id.primitive & 31)) & 1 != 0;
            if h.opaque {
                ok.push(Expect { id: h.id, t: h.t, kind: 1, margin: h.margin });
                continue;
            }
            candidates += 1;
            let alpha_margin = if bit { f64::INFINITY } else { (h.uv[0] as f64 - 0.5).abs() };
            if bit || h.uv[0] < 0.5 || alpha_margin < AMBIGUOUS {
                ok.push(Expect { id: h.id, t: h.t, kind: 1, margin: h.margin.min(alpha_margin) });
            }
            continue;
        }
        candidates += 1;
        let inv = invert_3x4(&s.instances[h.id.instance as usize].transform).expect("invertible");
        let f = |v: Vec3| [v.x as f64, v.y as f64, v.z as f64];
        let (o, d) = (xform_point(&inv, f(ray.origin)), xform_vector(&inv, f(ray.direction)));
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let (a, b, c) = (dot(d, d), dot(o, d), dot(o, o) - 1.0);
        let disc = b * b - a * c;
        let t = (-b - disc.max(0.0).sqrt()) / a;
        let margin = h.margin.min(disc.abs() / (b * b).max(a)).min((t - ray.tmin as f64).abs() / t.abs().max(1.0));
        if (disc >= 0.0 && t >= ray.tmin as f64 && t <= ray.tmax as f64) || margin < AMBIGUOUS {
            ok.push(Expect { id: h.id, t: t as f32, kind: 2, margin });
        }
    }
    (ok, candidates)
}

#[test]
fn rq_anyhit_alpha_mask_spheres_generate_confirm_terminate() {
    let s = mixed_scene(5);
    let geoms = s.geoms();
    let rscene = reference_scene(&s, &geoms);
    let cam = Camera::looking_at(s.bounds, [24, 24]);
    let mut rng = Rng::new(77);
    let mask: Vec<u32> = (0..bunny().indices.len().div_ceil(32) + 16).map(|_| rng.next_u32()).collect();
    let mut shaders = glsl("rq_anyhit", &[]);
    shaders.push(wgsl("rq_anyhit"));
    let n = (cam.size[0] * cam.size[1]) as usize;
    let refs: Vec<(Ray, RefResult)> = (0..n as u32)
        .map(|i| {
            let ray = cam.ray(i % cam.size[0], i / cam.size[0]);
            let r = reference(&rscene, &ray, 0, 0xFF);
            (ray, r)
        })
        .collect();
    let (mut generated, mut alpha) = (0, 0);
    for (what, words) in &shaders {
        let p = pipeline(what, words);
        let mut mem = s.memory();
        let naga = what.contains("naga");
        let mask_buffer = mem.host.add_buffer(&bytes_of(&mask));
        let ubo = cam.ubo(mem.host.device_address(mask_buffer));
        let mut bufs = vec![ubo, vec![0u8; 32 * n]];
        if naga {
            bufs.push(bytes_of(&mask)); // WGSL has no buffer device address: a binding instead
        }
        let (report, out) = run(&p, &mut mem, 1, &bufs, &[], [cam.size[0] / 8, cam.size[1] / 8, 1]);
        assert!(report.is_clean(), "{what}: {report:?}");
        let rec = u32s(&out[1]);
        for (i, (ray, r)) in refs.iter().enumerate() {
            let o = &rec[8 * i..8 * i + 8];
            let (t, prim, geom, custom, kind, candidates) = (f32::from_bits(o[0]), o[1], o[5], o[6], o[7], o[4] as usize);
            let ctx = format!("{what} pixel {i}");
            let (ok, max_candidates) = anyhit_reference(r, &s, ray, &mask);
            let inst = s.instances.iter().position(|x| x.custom_index == custom).unwrap_or(usize::MAX) as u32;
            // naga's committed-intersection struct reads t only when something is committed
            // (else 0), so the WGSL twin generates a sphere hit only below an earlier commit:
            // which spheres it keeps depends on traversal order. There, a sphere may be missed
            // and any acceptable hit will do.
            let spheres = naga && ok.iter().any(|e| e.kind == 2);
            let committed = if spheres && kind == 0 {
                assert!(ok.iter().all(|e| e.kind == 2 || e.margin < AMBIGUOUS), "{ctx}: nothing committed, reference accepts {ok:?}");
                false
            } else {
                check_record(Record { kind, t, inst, geometry: Some(geom), prim }, &ok, &r.near_misses, spheres, &ctx)
            };
            if committed {
                let h = ok.iter().find(|e| e.id.instance == inst && e.id.primitive == prim);
                let was_candidate = kind == 2 || h.is_some_and(|h| r.hits.iter().any(|x| x.id == h.id && !x.opaque));
                assert!(!was_candidate || candidates >= 1, "{ctx}: committed a candidate, counted none");
                generated += (kind == 2) as u32;
                alpha += (kind == 1 && was_candidate) as u32;
            } else {
                assert_eq!((t, prim, geom, custom), (-1.0, !0, !0, !0), "{ctx}: miss record");
            }
            assert!(candidates <= max_candidates, "{ctx}: {candidates} candidates, the reference has {max_candidates}");
            if kind == 1 {
                let bary = [f32::from_bits(o[2]), f32::from_bits(o[3])];
                let e = r.hits.iter().find(|x| x.id.instance == inst && x.id.primitive == prim && x.id.geometry == geom);
                if let Some(e) = e.filter(|e| e.margin > 1e-3) {
                    assert!((bary[0] - e.uv[0]).abs() < 1e-3 && (bary[1] - e.uv[1]).abs() < 1e-3, "{ctx}: barycentrics {bary:?} vs {:?}", e.uv);
                }
            }
        }
    }
    assert!(generated > 20 && alpha > 20, "generated {generated}, alpha-tested {alpha}: the camera misses the scene");
}

/// A unit quad in z = 0 over [0, 1]², non-opaque (so Proceed stops at it once).
fn quad_blas() -> Vec<u8> {
    let m = Mesh { positions: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]], indices: vec![[0, 1, 2], [0, 2, 3]] };
    build_blas(0, &[TriData::from_mesh(&m, 0).geometry()]).bytes
}

/// Runs rq_negative (8 invocations) with `address` pushed; returns the report and the
/// records (type, t, primitive, candidates).
fn run_negative(p: &Pipeline, mem: &mut RqMemory, address: u64) -> (DispatchReport, Vec<[u32; 4]>) {
    let (report, out) = run(p, mem, 0, &[vec![0xEEu8; 128]], &address.to_le_bytes(), [1, 1, 1]);
    let w = u32s(&out[0]);
    (report, (0..8).map(|i| [w[4 * i], w[4 * i + 1], w[4 * i + 2], w[4 * i + 3]]).collect())
}

#[test]
fn rq_on_garbage_destroyed_and_unbound_structures_faults_and_finds_nothing() {
    const QUAD: u64 = 0x20_0000_0000;
    const GARBAGE_BYTES: u64 = 0x30_0000_0000;
    const DESTROYED: u64 = 0x31_0000_0000;
    let mut view = MapView::new();
    view.insert(QUAD, quad_blas());
    view.insert(GARBAGE_BYTES, vec![0x55; 4096]);
    let mut destroyed = quad_blas();
    accel::mark_invalid(&mut destroyed);
    view.insert(DESTROYED, destroyed);
    let mut mem = RqMemory { host: HostMemory::new(), view, tlas: None };
    for (what, words) in glsl("rq_negative", &[]) {
        let p = pipeline(&what, &words);
        // The structure named by a 64-bit address (OpConvertUToAccelerationStructureKHR).
        let (report, recs) = run_negative(&p, &mut mem, QUAD);
        assert!(report.is_clean(), "{what}: {report:?}");
        for (i, r) in recs.iter().enumerate() {
            assert_eq!((r[0], f32::from_bits(r[1]), r[3]), (1, 1.0, 1), "{what}: lane {i} hits the quad");
        }
        for (address, kind) in [
            (0xDEAD_BEEF_0000u64, FaultKind::Unmapped),
            (0, FaultKind::Unmapped),
            (GARBAGE_BYTES, FaultKind::InvalidStructure),
            (DESTROYED, FaultKind::InvalidStructure),
        ] {
            let (report, recs) = run_negative(&p, &mut mem, address);
            assert_eq!(report.fault_count, 8, "{what} {address:#x}: one fault per invocation: {report:?}");
            for f in &report.faults {
                assert_eq!((f.kind, f.space, f.at), (kind, FaultSpace::RayQuery, address), "{what}: {f}");
            }
            for r in &recs {
                // Nothing found: committed type none, t the ray's tmax, no candidates.
                assert_eq!((r[0], f32::from_bits(r[1]), r[2], r[3]), (0, 100.0, 0, 0), "{what} {address:#x}");
            }
        }
    }
    // A memory without structures at all (the trait's defaults): faults, nothing found.
    let words = &glsl("rq_negative", &[])[0].1;
    let mut host = HostMemory::new();
    let out = host.add_buffer(&[0xEE; 128]);
    host.bind(0, 0, out);
    let report = dispatch(&pipeline("rq_negative", words), &host, &QUAD.to_le_bytes(), [1, 1, 1], [0; 3], &Watchdog::default());
    assert_eq!((report.fault_count, report.faults[0].kind), (8, FaultKind::Unmapped));
    assert_eq!(u32s(&host.bytes(out))[..4], [0, 100f32.to_bits(), 0, 0]);
}

#[test]
fn rq_getters_on_an_uninitialised_query_fault_and_read_zero() {
    let mut mem = RqMemory { host: HostMemory::new(), view: MapView::new(), tlas: None };
    for (what, words) in glsl("rq_negative", &["UNINITIALIZED"]) {
        let p = pipeline(&what, &words);
        let (report, recs) = run_negative(&p, &mut mem, 0);
        // Three committed getters per invocation, each a fault naming the query variable.
        assert_eq!(report.fault_count, 24, "{what}: {report:?}");
        assert!(report.faults.iter().all(|f| f.kind == FaultKind::Uninitialized && f.space == FaultSpace::RayQuery), "{what}: {report:?}");
        for r in &recs {
            assert_eq!(r[..3], [0, 0, 0], "{what}");
        }
    }
}

#[test]
fn rq_unbound_descriptor_faults_and_finds_nothing() {
    let s = small_scene(1);
    let mut mem = s.memory();
    mem.tlas = None;
    let rays = random_rays(s.bounds, 16, 3);
    for (what, words) in glsl("rq_closest", &[]) {
        let p = pipeline(&what, &words);
        let (report, bufs) = run(&p, &mut mem, 1, &[ray_bytes(&rays), vec![0u8; 16 * rays.len()]], &bytes_of(&[16, 0]), [1, 1, 1]);
        assert_eq!(report.fault_count, 16, "{what}: {report:?}");
        assert!(report.faults.iter().all(|f| (f.kind, f.at) == (FaultKind::Unmapped, 0)), "{what}");
        assert!(u32s(&bufs[1]).chunks(4).all(|r| r[3] == 0 && r[1] == !0), "{what}: records say nothing was hit");
    }
}

/// tests/shaders/rq_position_fetch.spvasm assembled, with the stand-in opcode patched to
/// OpRayQueryGetIntersectionTriangleVertexPositionsKHR and the capability and extension added
/// (see the file's header for why).
fn position_fetch_module() -> Vec<u32> {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/shaders/rq_position_fetch.spvasm");
    let spv = scratch_dir().join("rq_position_fetch.spv");
    let out = Command::new("spirv-as").args(["--target-env", "vulkan1.2"]).arg(&src).arg("-o").arg(&spv).output().expect("spirv-as (Debian: spirv-tools)");
    assert!(out.status.success(), "spirv-as: {}", String::from_utf8_lossy(&out.stderr));
    let words = words_of(&spv);
    let (mut body, mut at) = (Vec::new(), 5);
    let mut patched = 0;
    while at < words.len() {
        let n = (words[at] >> 16) as usize;
        let mut inst = words[at..at + n].to_vec();
        if inst[0] & 0xFFFF == spirv::Op::RayQueryGetIntersectionBarycentricsKHR as u32 {
            inst[0] = (inst[0] & 0xFFFF_0000) | spirv::Op::RayQueryGetIntersectionTriangleVertexPositionsKHR as u32;
            patched += 1;
        }
        if inst[0] & 0xFFFF == spirv::Op::Extension as u32 && !body.iter().any(|&w: &u32| w & 0xFFFF == spirv::Op::Extension as u32) {
            let mut name = b"SPV_KHR_ray_tracing_position_fetch".to_vec();
            name.resize(name.len() / 4 * 4 + 4, 0);
            body.push(((1 + name.len() / 4) as u32) << 16 | spirv::Op::Extension as u32);
            body.extend(name.chunks(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])));
        }
        body.extend(inst);
        at += n;
    }
    assert_eq!(patched, 1);
    let cap = [2 << 16 | spirv::Op::Capability as u32, spirv::Capability::RayQueryPositionFetchKHR as u32];
    words[..5].iter().chain(&cap).chain(&body).copied().collect()
}

#[test]
fn rq_position_fetch_returns_the_object_space_vertices_in_application_order() {
    // Eight quads over [0, 1]² split along alternating diagonals, with a geometry transform;
    // one instance that moves them (positions stay in object space).
    let mut positions = Vec::new();
    let mut indices = Vec::new();
    for q in 0..8u32 {
        let (x0, x1) = (q as f32 / 8.0, (q + 1) as f32 / 8.0);
        positions.extend([[x0, 0.0, 0.0], [x1, 0.0, 0.1 * q as f32], [x1, 1.0, 0.0], [x0, 1.0, 0.05]]);
        let b = 4 * q;
        indices.extend(if q % 2 == 0 { [[b, b + 1, b + 2], [b + 2, b + 3, b]] } else { [[b + 1, b + 2, b + 3], [b, b + 1, b + 3]] });
    }
    let mut tri = TriData::from_mesh(&Mesh { positions, indices }, GEOMETRY_OPAQUE);
    tri.transform = Some([1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.25, 1.0, 0.5]);
    let geoms = [tri.geometry()];
    let blas = build(AsType::BottomLevel, accel::BuildFlags::ALLOW_DATA_ACCESS, &geoms, &accel::NoDevice);
    let mut view = MapView::new();
    view.insert(BLAS_BASE, blas.bytes);
    let inst = InstanceRecord { transform: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 2.0], custom_index: 0, mask: 0xFF, sbt_offset: 0, flags: 0, reference: BLAS_BASE };
    let packed = InstanceRecord::pack(&[inst]);
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: 1, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
    let tlas = build(AsType::TopLevel, 0, &g, &view);
    view.insert(TLAS_ADDRESS, tlas.bytes);
    let rscene = RefScene::Tlas { instances: vec![inst], blases: HashMap::from([(BLAS_BASE, &geoms[..])]) };
    let p = pipeline("rq_position_fetch", &position_fetch_module());
    let mut mem = RqMemory { host: HostMemory::new(), view, tlas: None };
    let (report, out) = run(&p, &mut mem, 0, &[vec![0u8; 9 * 4 * 8]], &TLAS_ADDRESS.to_le_bytes(), [1, 1, 1]);
    assert!(report.is_clean(), "{report:?}");
    let got: Vec<f32> = u32s(&out[0]).into_iter().map(f32::from_bits).collect();
    for i in 0..8 {
        let ray = Ray { origin: Vec3::new(0.0625 + 0.125 * i as f32, 0.3, -1.0), direction: Vec3::Z, tmin: 0.0, tmax: 100.0 };
        let r = reference(&rscene, &ray, 0, 0xFF);
        let best = r.hits.iter().min_by(|a, b| a.t.total_cmp(&b.t)).expect("every ray hits a quad");
        let want = accel::fetch_triangle(&geoms[0], best.id.primitive).unwrap();
        let want: Vec<f32> = want.iter().flat_map(|v| v.to_array()).collect();
        assert_eq!(got[9 * i..9 * i + 9], want[..], "lane {i}: primitive {}", best.id.primitive);
    }
}

#[test]
fn compacted_and_deserialized_structures_trace_identically() {
    let s = small_scene(9);
    let rays = random_rays(s.bounds, 32, 8);
    let (what, words) = &glsl("rq_getters", &[])[1];
    let p = pipeline(what, words);
    let trace = |mem: &mut RqMemory, flags: u32| {
        let push = bytes_of(&[rays.len() as u32, flags, 0xFF]);
        let (report, bufs) = run(&p, mem, 1, &[ray_bytes(&rays), vec![0u8; 256 * rays.len()]], &push, [2, 1, 1]);
        assert!(report.is_clean(), "{report:?}");
        bufs[1].clone()
    };
    // Every structure compacted (exactly its used bytes), and the TLAS also serialized and
    // deserialized to another address.
    let mut compact = s.memory();
    for a in s.blas_geoms.iter().map(|b| b.0).chain([TLAS_ADDRESS]) {
        let src = s.view.acceleration_structure(a).unwrap();
        let mut dst = vec![0u8; accel::compacted_size(src).unwrap() as usize];
        accel::compact_into(src, &mut dst).unwrap();
        compact.view.insert(a, dst);
    }
    let mut copied = s.memory();
    let tlas = s.view.acceleration_structure(TLAS_ADDRESS).unwrap();
    let mut ser = vec![0u8; accel::serialized_size(tlas).unwrap() as usize];
    accel::serialize(tlas, [7; 16], &mut ser).unwrap();
    let mut de = vec![0u8; tlas.len()];
    accel::deserialize(&ser, [7; 16], &mut de).unwrap();
    copied.view.insert(TLAS_ADDRESS + 0x1000_0000, de);
    copied.tlas = Some(TLAS_ADDRESS + 0x1000_0000);
    for flags in [0, CULL_BACK | SKIP_AABBS, NO_OPAQUE, TERMINATE_ON_FIRST_HIT | CULL_FRONT] {
        let original = trace(&mut s.memory(), flags);
        assert!(u32s(&original).chunks(64).filter(|r| r[0] != 0).count() > 4, "flags {flags:#x}: the rays miss the scene");
        assert!(trace(&mut compact, flags) == original, "flags {flags:#x}: compacted structures trace differently");
        assert!(trace(&mut copied, flags) == original, "flags {flags:#x}: the deserialized TLAS traces differently");
    }
}

//! VK_KHR_acceleration_structure through the real loader with validation on: builds of every
//! kind, copies, serialization, queries, deferred joins — checked against an independent
//! brute-force intersection over the application's input and against each other.
mod support;

use arbor::accel::{self, NoDevice, Ray, RayFlags};
use ash::vk;
use glam::Vec3;
use support::accel::{instance_record, instances, payload, triangles, Accel};

fn as_context() -> support::Context {
    support::Context::new(support::Options { acceleration_structure: true, ..Default::default() })
}

fn bunny() -> arbor::scene::Mesh {
    arbor::scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).unwrap()
}

/// Deterministic rays through the mesh's bounds (xorshift).
fn rays(bounds: [f32; 6], n: usize, seed: u64) -> Vec<Ray> {
    let mut s = seed | 1;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let lo = Vec3::new(bounds[0], bounds[1], bounds[2]);
    let hi = Vec3::new(bounds[3], bounds[4], bounds[5]);
    let ext = hi - lo;
    (0..n)
        .map(|_| {
            let target = lo + Vec3::new(next(), next(), next()) * ext;
            let dir = Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5).normalize_or(Vec3::X);
            Ray { origin: target - dir * ext.length() * 2.0, direction: dir, tmin: 0.0, tmax: f32::INFINITY }
        })
        .collect()
}

/// Closest hit by brute force over the mesh (the library's watertight test, every triangle).
fn brute_closest(mesh: &arbor::scene::Mesh, ray: &Ray) -> Option<(f32, u32)> {
    let mut best: Option<(f32, u32)> = None;
    for i in 0..mesh.triangle_count() {
        let t = mesh.triangle(i);
        if let Some((d, _, _, _)) = accel::intersect_triangle(ray, Vec3::from(t[0]), Vec3::from(t[1]), Vec3::from(t[2])) {
            if d >= ray.tmin && d <= ray.tmax && best.is_none_or(|(bd, _)| d < bd) {
                best = Some((d, i as u32));
            }
        }
    }
    best
}

struct MeshInput {
    vertices: usize,
    indices: usize,
    max_vertex: u32,
    count: u32,
}

fn upload_mesh(a: &Accel, mesh: &arbor::scene::Mesh) -> MeshInput {
    MeshInput {
        vertices: a.upload(&mesh.vertex_bytes()),
        indices: a.upload(&mesh.index_bytes()),
        max_vertex: mesh.vertex_count() as u32 - 1,
        count: mesh.triangle_count() as u32,
    }
}

fn blas_info<'a>(
    geoms: &'a [vk::AccelerationStructureGeometryKHR<'static>],
    flags: vk::BuildAccelerationStructureFlagsKHR,
) -> vk::AccelerationStructureBuildGeometryInfoKHR<'a> {
    vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL)
        .flags(flags)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(geoms)
}

/// Device build of a mesh BLAS; returns the structure.
fn device_blas(a: &Accel, m: &MeshInput, flags: vk::BuildAccelerationStructureFlagsKHR) -> vk::AccelerationStructureKHR {
    let geoms = [triangles(a.buf(m.vertices).address, a.buf(m.indices).address, m.max_vertex)];
    let info = blas_info(&geoms, flags);
    let sizes = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &[m.count]);
    let (s, _) = a.structure(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, sizes.acceleration_structure_size);
    let scratch = a.buffer(sizes.build_scratch_size);
    let info = info.dst_acceleration_structure(s).scratch_data(vk::DeviceOrHostAddressKHR { device_address: a.buf(scratch).address });
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(m.count)];
    a.submit(|cb| {
        // SAFETY: valid infos and ranges; buffers live until the wait inside submit.
        unsafe { a.ext.cmd_build_acceleration_structures(cb, &[info], &[&range]) };
    });
    s
}

#[test]
fn device_build_of_the_bunny_traverses_like_brute_force() {
    let ctx = as_context();
    let a = Accel::new(&ctx);
    let mesh = bunny();
    let m = upload_mesh(&a, &mesh);
    let s = device_blas(&a, &m, vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE);
    let ser = a.serialize(s);
    let blob = payload(&ser);
    let h = accel::header(blob).expect("a valid structure");
    assert_eq!(h.primitive_count as usize, mesh.triangle_count());
    let mut hits = 0;
    for ray in rays(mesh.bounds(), 2000, 7) {
        let got = accel::closest_hit(blob, &NoDevice, ray, RayFlags(0), 0xFF).map(|h| (h.t, h.primitive_index));
        let want = brute_closest(&mesh, &ray);
        assert_eq!(got, want, "ray {ray:?}");
        hits += want.is_some() as u32;
    }
    assert!(hits > 200, "too few rays hit the bunny ({hits}): the test would prove little");
    a.destroy();
    ctx.finish();
}

//! OpRayQueryGetIntersectionClusterIdNV through the loader with validation on: CLASes, a cluster
//! BLAS and a KHR TLAS over it and an ordinary grid BLAS, all built by the driver; a compute
//! shader (tests/shaders/rq_cluster.comp, patched to the NV opcode) traces rays at triangle
//! centroids and reads the committed and candidate cluster IDs, primitive and geometry indices,
//! which must equal a double-precision brute force over the same triangles (ordinary geometry
//! and misses: -1).
mod harness;
mod reference;

use arbor::accel::clas::args::*;
use arbor::accel::clas::truncate;
use ash::vk;
use harness::accel::{instance_record, instances, Accel};
use harness::clas::*;
use reference::brute_force::intersect_f64;

/// tests/shaders/rq_cluster.comp with its stand-in getter patched to
/// OpRayQueryGetIntersectionClusterIdNV, the capability and the extension added.
fn cluster_module() -> Vec<u32> {
    let words = harness::compute::glsl("rq_cluster.comp");
    let (mut body, mut at, mut patched) = (Vec::new(), 5, 0);
    let stand_in = spirv::Op::RayQueryGetIntersectionInstanceShaderBindingTableRecordOffsetKHR as u32;
    while at < words.len() {
        let n = (words[at] >> 16) as usize;
        let mut inst = words[at..at + n].to_vec();
        if inst[0] & 0xFFFF == stand_in {
            inst[0] = (inst[0] & 0xFFFF_0000) | spirv::Op::RayQueryGetIntersectionClusterIdNV as u32;
            patched += 1;
        }
        if inst[0] & 0xFFFF == spirv::Op::Extension as u32 && !body.iter().any(|&w: &u32| w & 0xFFFF == spirv::Op::Extension as u32) {
            let mut name = b"SPV_NV_cluster_acceleration_structure".to_vec();
            name.resize(name.len() / 4 * 4 + 4, 0);
            body.push(((1 + name.len() / 4) as u32) << 16 | spirv::Op::Extension as u32);
            body.extend(name.chunks(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])));
        }
        body.extend(inst);
        at += n;
    }
    assert_eq!(patched, 2, "the shader's two stand-in getters");
    let cap = [2 << 16 | spirv::Op::Capability as u32, spirv::Capability::RayTracingClusterAccelerationStructureNV as u32];
    words[..5].iter().chain(&cap).chain(&body).copied().collect()
}

/// One cluster of the scene: its triangles as the CLAS stores them (truncated), cluster ID,
/// per-triangle geometry index.
struct Cluster {
    id: u32,
    triangles: Vec<[[f32; 3]; 3]>,
    geometry: Vec<u32>,
}

/// Twelve 4 × 4 grid clusters side by side at varying heights, truncated by 3 bits; every third
/// with a per-triangle geometry index buffer, every fourth opaque (no candidates).
fn build_clusters(a: &Accel, api: &Nv, ctx: &harness::Context) -> (Vec<Cluster>, Vec<u64>, usize) {
    let n = 12u32;
    let (mut ib, mut vb, mut gb, mut records, mut expected) = (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let words: Vec<u32> = (0..32).map(|i| GeometryIndexAndFlags::new(i % 4, 0).0).collect();
    gb.extend(bytes_of(&words));
    let mut locals = Vec::new();
    for k in 0..n {
        let (v, i) = grid_cluster(4, 1.25 * k as f32, 0.05 * (k % 3) as f32 + 0.3);
        locals.push((ib.len() as u64, vb.len() as u64));
        ib.extend(bytes_of(&i));
        vb.extend(bytes_of(&v.iter().flatten().copied().collect::<Vec<f32>>()));
        let own = k % 3 == 0;
        let flags = if k % 4 == 1 { GeometryIndexAndFlags::OPAQUE } else { 0 };
        records.push((k, own, flags, i.len() as u32 / 3, v.len() as u32));
        let tri = |t: &[u16]| -> [[f32; 3]; 3] { std::array::from_fn(|c| v[t[c] as usize].map(|x| truncate(x, 3))) };
        let triangles: Vec<[[f32; 3]; 3]> = i.chunks(3).map(tri).collect();
        let geometry = (0..triangles.len() as u32).map(|t| k + 2 + if own { t % 4 } else { 0 }).collect();
        expected.push(Cluster { id: 40 + 7 * k, triangles, geometry });
    }
    let (ibuf, vbuf, gbuf) = (a.upload(&ib), a.upload(&vb), a.upload(&gb));
    let (ia, va, ga) = (a.buf(ibuf).address, a.buf(vbuf).address, a.buf(gbuf).address);
    let infos: Vec<BuildTriangleClusterInfo> = records
        .iter()
        .zip(&locals)
        .map(|(&(k, own, flags, t, v), &(io, vo))| BuildTriangleClusterInfo {
            cluster_id: 40 + 7 * k,
            counts: pack_counts(t, v, 3, 2, 0),
            base_geometry_index_and_geometry_flags: GeometryIndexAndFlags::new(k + 2, flags),
            index_buffer: ia + io,
            vertex_buffer: va + vo,
            geometry_index_and_flags_buffer: if own { ga } else { 0 },
            ..Default::default()
        })
        .collect();
    let tri_input = triangle_input(32, 32 * n, 3);
    let tri_ptr = &tri_input as *const TriangleInput as *const std::ffi::c_void;
    let total = api.sizes(ctx, &input(OpType::BuildTriangleCluster, OpMode::ImplicitDestinations, n, tri_ptr));
    let (dst, addrs, scratch) = (a.buffer(total.acceleration_structure_size), a.buffer(8 * n as u64), a.buffer(total.build_scratch_size));
    let src = a.upload(&bytes_of(&infos));
    let mut info = commands(input(OpType::BuildTriangleCluster, OpMode::ImplicitDestinations, n, tri_ptr));
    info.dst_implicit_data = a.buf(dst).address;
    info.scratch_data = a.buf(scratch).address;
    info.dst_addresses_array = region(a.buf(addrs).address, 8, 8 * n as u64);
    info.src_infos_array = region(a.buf(src).address, 64, 64 * n as u64);
    // SAFETY: valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    (expected, collect(&a.buf(addrs).read(0, 8 * n as usize)), scratch)
}

/// A cluster BLAS over `clases`; returns its address.
fn build_cluster_blas(a: &Accel, api: &Nv, ctx: &harness::Context, clases: &[u64], scratch: usize) -> u64 {
    let n = clases.len() as u32;
    let bl_input = bottom_level_input(n, n);
    let bl_ptr = &bl_input as *const BottomLevelInput as *const std::ffi::c_void;
    let size = api.sizes(ctx, &input(OpType::BuildClustersBottomLevel, OpMode::ImplicitDestinations, 1, bl_ptr)).acceleration_structure_size;
    let (out, at) = (a.buffer(size), a.buffer(8));
    let refs = a.upload(&bytes_of(clases));
    let cluster_references = a.buf(refs).address;
    let args = a.upload(bytemuck::bytes_of(&BuildClustersBottomLevelInfo { cluster_references_count: n, cluster_references_stride: 8, cluster_references }));
    let mut info = commands(input(OpType::BuildClustersBottomLevel, OpMode::ImplicitDestinations, 1, bl_ptr));
    info.dst_implicit_data = a.buf(out).address;
    info.scratch_data = a.buf(scratch).address;
    info.dst_addresses_array = region(a.buf(at).address, 8, 8);
    info.src_infos_array = region(a.buf(args).address, 16, 16);
    // SAFETY: valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    u64::from_le_bytes(a.buf(at).read(0, 8).try_into().unwrap())
}

/// A TLAS of the given (transform, reference) instances, built by the driver.
fn build_tlas(a: &Accel, insts: &[([f32; 12], u64)]) -> vk::AccelerationStructureKHR {
    let records: Vec<u8> = insts.iter().flat_map(|&(t, r)| instance_record(t, 0, 0xFF, 0, 0, r)).collect();
    let inst_buf = a.upload(&records);
    let geom = [instances(a.buf(inst_buf).address)];
    let mut build = vk::AccelerationStructureBuildGeometryInfoKHR::default().ty(vk::AccelerationStructureTypeKHR::TOP_LEVEL).geometries(&geom);
    let count = insts.len() as u32;
    let s = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &build, &[count]);
    let (tlas, _) = a.structure(vk::AccelerationStructureTypeKHR::TOP_LEVEL, s.acceleration_structure_size);
    let tscratch = a.buffer(s.build_scratch_size);
    build = build.dst_acceleration_structure(tlas).scratch_data(vk::DeviceOrHostAddressKHR { device_address: a.buf(tscratch).address });
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(count)];
    // SAFETY: valid build.
    a.submit(|cb| unsafe { a.ext.cmd_build_acceleration_structures(cb, &[build], &[&range]) });
    tlas
}

/// Runs the patched shader over `rays` ([origin, tmin, direction, tmax]) against `tlas`.
fn trace(a: &Accel, tlas: vk::AccelerationStructureKHR, rays: &[[f32; 8]]) -> Vec<i32> {
    let ray_bytes: Vec<u8> = rays.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
    collect(&harness::trace::trace_tlas(a, &cluster_module(), tlas, &ray_bytes, rays.len(), 24))
}

/// The brute force's answer for one ray: (t, cluster ID or -1, primitive, geometry index,
/// opaque), nearest over the clusters and the grid (its triangles shifted by `grid_y`).
fn brute(ray: &[f32; 8], clusters: &[Cluster], grid: &[[[f32; 3]; 3]], grid_y: f32) -> Option<(f64, i32, u32, u32)> {
    let o = [ray[0] as f64, ray[1] as f64, ray[2] as f64];
    let d = [ray[4] as f64, ray[5] as f64, ray[6] as f64];
    let f = |v: [f32; 3], dy: f32| [v[0] as f64, (v[1] + dy) as f64, v[2] as f64];
    let mut best: Option<(f64, i32, u32, u32)> = None;
    let mut consider = |tri: &[[f32; 3]; 3], dy: f32, id: i32, prim: u32, geometry: u32| {
        if let Some((t, u, v)) = intersect_f64(o, d, f(tri[0], dy), f(tri[1], dy), f(tri[2], dy)) {
            let inside = u >= 0.0 && v >= 0.0 && u + v <= 1.0 && t >= ray[3] as f64 && t <= ray[7] as f64;
            if inside && best.is_none_or(|b| t < b.0) {
                best = Some((t, id, prim, geometry));
            }
        }
    };
    for c in clusters {
        for (i, tri) in c.triangles.iter().enumerate() {
            consider(tri, 0.0, c.id as i32, i as u32, c.geometry[i]);
        }
    }
    for (i, tri) in grid.iter().enumerate() {
        consider(tri, grid_y, -1, i as u32, 0);
    }
    best
}

#[test]
fn ray_queries_read_the_cluster_ids_of_brute_force() {
    let mut opts = harness::Options { acceleration_structure: true, ..Default::default() };
    opts.device_extensions.extend(["VK_KHR_ray_query", EXT]);
    let ctx = harness::Context::new(opts);
    let api = nv(&ctx);
    let a = Accel::new(&ctx);
    let (clusters, clases, scratch) = build_clusters(&a, &api, &ctx);
    let blas = build_cluster_blas(&a, &api, &ctx, &clases, scratch);
    // An ordinary (opaque) grid BLAS beside it, moved up by 3.
    let mesh = harness::vuid::upload_grid(&a);
    let (grid_blas, _) = harness::vuid::valid_blas(&a, &mesh, vk::BuildAccelerationStructureFlagsKHR::empty());
    let grid_y = 3.0;
    let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
    let moved = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, grid_y, 0.0, 0.0, 1.0, 0.0];
    let tlas = build_tlas(&a, &[(identity, blas), (moved, a.address_of(grid_blas.s))]);
    let grid: Vec<[[f32; 3]; 3]> = {
        let v: Vec<f32> = collect(&mesh.vertex_bytes);
        let i: Vec<u32> = collect(&mesh.index_bytes);
        i.chunks(3).map(|t| std::array::from_fn(|c| [v[3 * t[c] as usize], v[3 * t[c] as usize + 1], v[3 * t[c] as usize + 2]])).collect()
    };
    // Straight down through centroids: of cluster triangles, of grid triangles, and misses.
    let down = |p: [f32; 3]| [p[0], p[1], 5.0, 0.0, 0.0, 0.0, -1.0, 100.0];
    let centroid = |t: &[[f32; 3]; 3], dy: f32| [(t[0][0] + t[1][0] + t[2][0]) / 3.0, (t[0][1] + t[1][1] + t[2][1]) / 3.0 + dy, 0.0];
    let mut rays: Vec<[f32; 8]> = clusters.iter().flat_map(|c| [0, 5, 17, 31].map(|i| down(centroid(&c.triangles[i], 0.0)))).collect();
    rays.extend([3, 40, 101].map(|i| down(centroid(&grid[i], grid_y))));
    rays.extend([down([-4.0, 0.5, 0.0]), down([0.5, 2.0, 0.0])]);
    let hits = trace(&a, tlas, &rays);
    let (mut cluster_hits, mut candidates) = (0, 0);
    for (r, (ray, h)) in rays.iter().zip(hits.chunks(6)).enumerate() {
        match brute(ray, &clusters, &grid, grid_y) {
            Some((t, id, prim, geometry)) => {
                assert_eq!(h[4], 1, "ray {r}: a triangle is committed");
                assert!((f32::from_bits(h[5] as u32) as f64 - t).abs() < 1e-4, "ray {r}: t {} against {t}", f32::from_bits(h[5] as u32));
                assert_eq!((h[0], h[2] as u32, h[3] as u32), (id, prim, geometry), "ray {r}: committed cluster ID, primitive, geometry index");
                let opaque = id < 0 || clusters.iter().position(|c| c.id as i32 == id).is_some_and(|k| k % 4 == 1);
                // The nearest candidate is the committed triangle (opaque ones are no candidates).
                assert_eq!(h[1], if opaque { -2 } else { id }, "ray {r}: the candidate's cluster ID");
                cluster_hits += (id >= 0) as usize;
                candidates += (h[1] >= 0) as usize;
            }
            None => assert_eq!((h[4], h[0], h[1]), (0, -1, -2), "ray {r}: a miss reads no cluster"),
        }
    }
    assert!(cluster_hits == 48 && candidates > 24, "{cluster_hits} cluster hits, {candidates} through candidates");
    a.destroy();
    ctx.finish();
}

//! VK_NV_cluster_acceleration_structure through the real loader with validation on: limits in
//! the `*2` chains, the size query, and vkCmdBuildClusterAccelerationStructureIndirectNV building
//! CLASes (count read from device memory when the command executes), templates and their
//! instantiation, a cluster BLAS, moves (overlapping) and template indices, in implicit,
//! explicit and compute-sizes modes; the bytes are compared with the library's own builds of the
//! same input, and a KHR TLAS built through the driver over the cluster BLAS is traced.
mod harness;

use std::ffi::c_void;

use arbor::accel::clas::{self, args::*};
use arbor::accel::{self, MapView, Ray, RayFlags};
use ash::vk;
use glam::Vec3;
use harness::accel::{instance_record, instances, Accel};
use harness::clas::{commands, input, nv, region, BottomLevelInput, MoveInput, TriangleInput, EXT};

// The host struct the harness lacks, written here from the registry (not imported from the driver).
#[repr(C)]
struct Properties {
    s_type: i32,
    p_next: *mut c_void,
    values: [u32; 8],
}

/// The first `n` clusters of the bunny: consecutive triangles, at most 128 triangles and 128
/// distinct vertices each; local vertices and 16-bit local indices.
fn clusters(n: usize) -> Vec<(Vec<[f32; 3]>, Vec<u16>)> {
    let m = arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/data/bunny.ply")).unwrap();
    let mut out = Vec::new();
    let (mut verts, mut idx, mut map) = (Vec::new(), Vec::new(), std::collections::HashMap::new());
    for t in &m.indices {
        let new = t.iter().filter(|i| !map.contains_key(*i)).count();
        if idx.len() / 3 == 128 || map.len() + new > 128 {
            out.push((std::mem::take(&mut verts), std::mem::take(&mut idx)));
            map.clear();
            if out.len() == n {
                return out;
            }
        }
        for &i in t {
            let l = *map.entry(i).or_insert_with(|| {
                verts.push(m.positions[i as usize]);
                verts.len() - 1
            });
            idx.push(l as u16);
        }
    }
    out.push((verts, idx));
    out
}

/// Little-endian values read back from bytes.
fn collect<T: bytemuck::Pod>(bytes: &[u8]) -> Vec<T> {
    bytes.chunks_exact(std::mem::size_of::<T>()).map(bytemuck::pod_read_unaligned).collect()
}

fn bytes_of<T: bytemuck::Pod>(v: &[T]) -> Vec<u8> {
    bytemuck::cast_slice(v).to_vec()
}

// One function: each step reads what the one before wrote into device memory.
#[test]
fn cluster_commands_through_the_loader() {
    let mut opts = harness::Options { acceleration_structure: true, ..Default::default() };
    opts.device_extensions.push(EXT);
    let ctx = harness::Context::new(opts);
    // Limits in VkPhysicalDeviceProperties2.
    let mut props = Properties { s_type: 1_000_569_001, p_next: std::ptr::null_mut(), values: [0; 8] };
    let mut p2 = vk::PhysicalDeviceProperties2 { p_next: &mut props as *mut Properties as *mut c_void, ..Default::default() };
    // SAFETY: a valid chain.
    unsafe { ctx.instance.get_physical_device_properties2(ctx.physical, &mut p2) };
    assert!(props.values[0] >= 128 && props.values[1] >= 128, "{:?}", props.values);
    let (clas_align, blas_align) = (props.values[3] as u64, props.values[5] as u64);
    let api = nv(&ctx);
    let a = Accel::new(&ctx);

    // Inputs: 24 clusters, truncated by 4 bits, per-cluster geometry index (from 1, so the
    // instantiation's offset of -1 stays in range: VUID 10510) and flags.
    let cl = clusters(24);
    let (mut ib, mut vb) = (Vec::new(), Vec::new());
    let mut offsets = Vec::new();
    for (v, i) in &cl {
        offsets.push((ib.len() as u64, vb.len() as u64));
        ib.extend(bytes_of(i));
        vb.extend(bytes_of(&v.iter().flatten().copied().collect::<Vec<f32>>()));
    }
    let (ibuf, vbuf) = (a.upload(&ib), a.upload(&vb));
    let (ia, va) = (a.buf(ibuf).address, a.buf(vbuf).address);
    let records: Vec<BuildTriangleClusterInfo> = cl
        .iter()
        .zip(&offsets)
        .enumerate()
        .map(|(k, ((v, i), (io, vo)))| BuildTriangleClusterInfo {
            cluster_id: 500 + k as u32,
            counts: pack_counts(i.len() as u32 / 3, v.len() as u32, 4, 2, 0),
            base_geometry_index_and_geometry_flags: GeometryIndexAndFlags::new(k as u32 + 1, if k % 2 == 0 { GeometryIndexAndFlags::OPAQUE } else { 0 }),
            index_buffer: ia + io,
            vertex_buffer: va + vo,
            ..Default::default()
        })
        .collect();
    let n = records.len() as u32;
    let src = a.upload(&bytes_of(&records));
    let tri_input = TriangleInput {
        s_type: 1_000_569_003,
        p_next: std::ptr::null_mut(),
        vertex_format: vk::Format::R32G32B32_SFLOAT.as_raw(),
        max_geometry_index_value: n,
        max_cluster_unique_geometry_count: 1,
        max_cluster_triangle_count: 128,
        max_cluster_vertex_count: 128,
        max_total_triangle_count: 128 * n,
        max_total_vertex_count: 128 * n,
        min_position_truncate_bit_count: 4,
    };
    let tri_ptr = &tri_input as *const TriangleInput as *const c_void;
    let query = |op, mode, count, p| {
        let mut s = vk::AccelerationStructureBuildSizesInfoKHR::default();
        // SAFETY: valid structs.
        unsafe { (api.get_sizes)(ctx.device.handle(), &input(op, mode, count, p), &mut s) };
        s
    };
    let total = query(OpType::BuildTriangleCluster, OpMode::ImplicitDestinations, n, tri_ptr);
    assert!(total.build_scratch_size > 0);
    assert_eq!(query(OpType::BuildTriangleCluster, OpMode::ComputeSizes, n, tri_ptr).acceleration_structure_size, 0);

    // CLASes, implicit; the count is written after recording, before submission.
    let dst = a.buffer(total.acceleration_structure_size);
    let (addrs, sizes, count, scratch) = (a.buffer(8 * n as u64), a.buffer(4 * n as u64), a.buffer(4), a.buffer(total.build_scratch_size));
    let mut info = commands(input(OpType::BuildTriangleCluster, OpMode::ImplicitDestinations, n, tri_ptr));
    info.dst_implicit_data = a.buf(dst).address;
    info.scratch_data = a.buf(scratch).address;
    info.dst_addresses_array = region(a.buf(addrs).address, 8, 8 * n as u64);
    info.dst_sizes_array = region(a.buf(sizes).address, 4, 4 * n as u64);
    info.src_infos_array = region(a.buf(src).address, 64, 64 * n as u64);
    info.src_infos_count = a.buf(count).address;
    a.buf(count).write(0, &0u32.to_le_bytes());
    a.submit(|cb| {
        // SAFETY: valid command buffer and info.
        unsafe { (api.cmd_build)(cb, &info) };
        a.buf(count).write(0, &n.to_le_bytes());
    });
    let got_addrs: Vec<u64> = collect(&a.buf(addrs).read(0, 8 * n as usize));
    let got_sizes: Vec<u32> = collect(&a.buf(sizes).read(0, 4 * n as usize));
    // The library's build of the same records, from the same memory contents.
    let mut view = MapView::new();
    view.insert(ia, ib.clone());
    view.insert(va, vb.clone());
    let dst_base = a.buf(dst).address;
    for (k, r) in records.iter().enumerate() {
        let mut want = vec![0u8; clas::clas_size(r.triangle_count() as u64) as usize];
        clas::build_clas(r, accel::VertexFormat::R32G32B32Sfloat, &view, &mut want).unwrap();
        assert_eq!(got_sizes[k] as usize, want.len());
        assert_eq!(got_addrs[k] % clas_align, 0);
        assert_eq!(a.buf(dst).read((got_addrs[k] - dst_base) as usize, want.len()), want, "CLAS {k}");
    }

    // A cluster BLAS over them (references read from the address array the build wrote).
    let bl_input = BottomLevelInput { s_type: 1_000_569_002, p_next: std::ptr::null_mut(), max_total_cluster_count: n, max_cluster_count_per_acceleration_structure: n };
    let bl_ptr = &bl_input as *const BottomLevelInput as *const c_void;
    let blas_size = query(OpType::BuildClustersBottomLevel, OpMode::ImplicitDestinations, 1, bl_ptr).acceleration_structure_size;
    let blas_buf = a.buffer(blas_size);
    let references = a.buf(addrs).address;
    let bl_args = a.upload(bytemuck::bytes_of(&BuildClustersBottomLevelInfo { cluster_references_count: n, cluster_references_stride: 8, cluster_references: references }));
    let (blas_addr, blas_len) = (a.buffer(8), a.buffer(4));
    let mut info = commands(input(OpType::BuildClustersBottomLevel, OpMode::ImplicitDestinations, 1, bl_ptr));
    info.dst_implicit_data = a.buf(blas_buf).address;
    info.scratch_data = a.buf(scratch).address;
    info.dst_addresses_array = region(a.buf(blas_addr).address, 8, 8);
    info.dst_sizes_array = region(a.buf(blas_len).address, 4, 4);
    info.src_infos_array = region(a.buf(bl_args).address, 0, 16);
    // SAFETY: valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    let blas_at = u64::from_le_bytes(a.buf(blas_addr).read(0, 8).try_into().unwrap());
    let blas_used = u32::from_le_bytes(a.buf(blas_len).read(0, 4).try_into().unwrap()) as usize;
    assert_eq!(blas_at % blas_align, 0);
    let blas_bytes = a.buf(blas_buf).read((blas_at - a.buf(blas_buf).address) as usize, blas_used);
    let lib_clases: Vec<Vec<u8>> = got_addrs.iter().zip(&got_sizes).map(|(&ad, &s)| a.buf(dst).read((ad - dst_base) as usize, s as usize)).collect();
    let refs: Vec<(u64, &[u8])> = got_addrs.iter().copied().zip(lib_clases.iter().map(|v| v.as_slice())).collect();
    let mut want = vec![0u8; clas::blas_size_bound(n as u64) as usize];
    let used = clas::build_cluster_blas(&refs, 0, &mut want).unwrap() as usize;
    assert_eq!(blas_bytes, want[..used], "cluster BLAS bytes");

    // A KHR TLAS built through the driver over the cluster BLAS, traced by the library.
    let inst = instance_record([1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0], 3, 0xff, 0, 0, blas_at);
    let inst_buf = a.upload(&inst);
    let geom = [instances(a.buf(inst_buf).address)];
    let mut build = vk::AccelerationStructureBuildGeometryInfoKHR::default().ty(vk::AccelerationStructureTypeKHR::TOP_LEVEL).geometries(&geom);
    let s = a.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &build, &[1]);
    let (tlas, tlas_buf) = a.structure(vk::AccelerationStructureTypeKHR::TOP_LEVEL, s.acceleration_structure_size);
    let tscratch = a.buffer(s.build_scratch_size);
    build = build.dst_acceleration_structure(tlas).scratch_data(vk::DeviceOrHostAddressKHR { device_address: a.buf(tscratch).address });
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(1)];
    // SAFETY: valid build.
    a.submit(|cb| unsafe { a.ext.cmd_build_acceleration_structures(cb, &[build], &[&range]) });
    let tlas_bytes = a.buf(tlas_buf).read(0, s.acceleration_structure_size as usize);
    let mut tview = MapView::new();
    tview.insert(blas_at, blas_bytes.clone());
    // The cluster BLAS names its CLASes by address: the view holds them where they were built.
    for (&at, c) in got_addrs.iter().zip(&lib_clases) {
        tview.insert(at, c.clone());
    }
    let b = accel::header(&blas_bytes).unwrap().bounds;
    let mut hits = 0;
    for k in 0..64 {
        let x = b[0] + (b[3] - b[0]) * (k % 8) as f32 / 8.0;
        let y = b[1] + (b[4] - b[1]) * (k / 8) as f32 / 8.0;
        let ray = Ray { origin: Vec3::new(x, y, b[5] + 1.0), direction: Vec3::new(0.0, 0.0, -1.0), tmin: 0.0, tmax: 100.0 };
        let direct = accel::closest_hit(&blas_bytes, &tview, ray, RayFlags(0), 0xff);
        let through = accel::closest_hit(&tlas_bytes, &tview, ray, RayFlags(0), 0xff);
        assert_eq!(direct.map(|h| (h.t, h.cluster_id, h.primitive_index, h.geometry_index)), through.map(|h| (h.t, h.cluster_id, h.primitive_index, h.geometry_index)));
        if let Some(h) = through {
            assert!((500..500 + n as i32).contains(&h.cluster_id) && h.geometry_index == (h.cluster_id - 500) as u32 + 1);
            assert_eq!(h.instance_custom_index, 3);
            hits += 1;
        }
    }
    assert!(hits > 0);

    // MOVE the CLASes, overlapping: implicit, packed from the start of the same buffer.
    let mv_input = MoveInput { s_type: 1_000_569_004, p_next: std::ptr::null_mut(), ty: ObjectType::TriangleCluster as i32, no_move_overlap: 0, max_moved_bytes: total.acceleration_structure_size };
    let mv_ptr = &mv_input as *const MoveInput as *const c_void;
    let mv_args = a.upload(&bytes_of(&got_addrs));
    let (mv_addrs, mv_sizes) = (a.buffer(8 * n as u64), a.buffer(4 * n as u64));
    let mut info = commands(input(OpType::MoveObjects, OpMode::ImplicitDestinations, n, mv_ptr));
    info.dst_implicit_data = dst_base + 16;
    info.scratch_data = a.buf(scratch).address;
    info.dst_addresses_array = region(a.buf(mv_addrs).address, 8, 8 * n as u64);
    info.dst_sizes_array = region(a.buf(mv_sizes).address, 4, 4 * n as u64);
    info.src_infos_array = region(a.buf(mv_args).address, 8, 8 * n as u64);
    // SAFETY: valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    let moved: Vec<u64> = collect(&a.buf(mv_addrs).read(0, 8 * n as usize));
    for (k, want) in lib_clases.iter().enumerate() {
        assert_eq!(a.buf(dst).read((moved[k] - dst_base) as usize, want.len()), *want, "moved CLAS {k}");
    }

    // Templates (explicit, sized by COMPUTE_SIZES), instantiated with new vertices (explicit)
    // against direct builds; and the template indices.
    let tpl_records: Vec<BuildTriangleClusterTemplateInfo> = records.iter().map(|r| BuildTriangleClusterTemplateInfo { cluster: BuildTriangleClusterInfo { vertex_buffer: 0, ..*r }, instantiation_bounding_box_limit: 0 }).collect();
    let tsrc = a.upload(&bytes_of(&tpl_records));
    let tsizes = a.buffer(4 * n as u64);
    let mut info = commands(input(OpType::BuildTriangleClusterTemplate, OpMode::ComputeSizes, n, tri_ptr));
    info.scratch_data = a.buf(scratch).address;
    info.dst_sizes_array = region(a.buf(tsizes).address, 4, 4 * n as u64);
    info.src_infos_array = region(a.buf(tsrc).address, 72, 72 * n as u64);
    // SAFETY: valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    let tpl_sizes: Vec<u32> = collect(&a.buf(tsizes).read(0, 4 * n as usize));
    let tpl_total: u64 = tpl_sizes.iter().map(|&s| (s as u64).next_multiple_of(32)).sum();
    let tpl_buf = a.buffer(tpl_total);
    let mut at = a.buf(tpl_buf).address;
    let tpl_addrs: Vec<u64> = tpl_sizes
        .iter()
        .map(|&s| {
            let here = at;
            at += (s as u64).next_multiple_of(32);
            here
        })
        .collect();
    let tpl_addr_buf = a.upload(&bytes_of(&tpl_addrs));
    let mut info = commands(input(OpType::BuildTriangleClusterTemplate, OpMode::ExplicitDestinations, n, tri_ptr));
    info.scratch_data = a.buf(scratch).address;
    info.dst_addresses_array = region(a.buf(tpl_addr_buf).address, 8, 8 * n as u64);
    info.dst_sizes_array = region(a.buf(tsizes).address, 4, 4 * n as u64);
    info.src_infos_array = region(a.buf(tsrc).address, 72, 72 * n as u64);
    // SAFETY: valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    let new_vb: Vec<u8> = bytes_of(&vb.chunks(4).map(|c| f32::from_le_bytes(c.try_into().unwrap()) * 2.0 + 0.25).collect::<Vec<f32>>());
    let nvbuf = a.upload(&new_vb);
    let inst_records: Vec<InstantiateClusterInfo> = (0..n as usize)
        .map(|k| InstantiateClusterInfo {
            cluster_id_offset: 1000,
            geometry_word: InstantiateClusterInfo::pack_geometry_index_offset(-1),
            cluster_template_address: tpl_addrs[k],
            vertex_buffer: StridedDeviceAddress { start_address: a.buf(nvbuf).address + offsets[k].1, stride_in_bytes: 12 },
        })
        .collect();
    let isrc = a.upload(&bytes_of(&inst_records));
    let one = query(OpType::InstantiateTriangleCluster, OpMode::ExplicitDestinations, n, tri_ptr).acceleration_structure_size;
    let ibuf2 = a.buffer(one * n as u64);
    let inst_addrs: Vec<u64> = (0..n as u64).map(|k| a.buf(ibuf2).address + k * one).collect();
    let iaddr_buf = a.upload(&bytes_of(&inst_addrs));
    let isizes = a.buffer(4 * n as u64);
    let mut info = commands(input(OpType::InstantiateTriangleCluster, OpMode::ExplicitDestinations, n, tri_ptr));
    info.scratch_data = a.buf(scratch).address;
    info.dst_addresses_array = region(a.buf(iaddr_buf).address, 8, 8 * n as u64);
    info.dst_sizes_array = region(a.buf(isizes).address, 4, 4 * n as u64);
    info.src_infos_array = region(a.buf(isrc).address, 32, 32 * n as u64);
    // SAFETY: valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    let mut nview = MapView::new();
    nview.insert(ia, ib.clone());
    nview.insert(a.buf(nvbuf).address, new_vb.clone());
    for (k, r) in records.iter().enumerate() {
        let direct = BuildTriangleClusterInfo {
            cluster_id: r.cluster_id + 1000,
            vertex_buffer: a.buf(nvbuf).address + offsets[k].1,
            base_geometry_index_and_geometry_flags: GeometryIndexAndFlags::new(r.base_geometry_index_and_geometry_flags.geometry_index().wrapping_sub(1), r.base_geometry_index_and_geometry_flags.geometry_flags()),
            ..*r
        };
        let mut want = vec![0u8; clas::clas_size(r.triangle_count() as u64) as usize];
        clas::build_clas(&direct, accel::VertexFormat::R32G32B32Sfloat, &nview, &mut want).unwrap();
        assert_eq!(a.buf(ibuf2).read(k * one as usize, want.len()), want, "instantiated CLAS {k}");
    }
    // GET_CLUSTER_TEMPLATE_INDICES, implicit: the 16-bit indices back.
    let gsrc = a.upload(&bytes_of(&tpl_addrs));
    let gbuf = a.buffer(query(OpType::GetClusterTemplateIndices, OpMode::ImplicitDestinations, n, tri_ptr).acceleration_structure_size);
    let gaddrs = a.buffer(8 * n as u64);
    let mut info = commands(input(OpType::GetClusterTemplateIndices, OpMode::ImplicitDestinations, n, tri_ptr));
    info.dst_implicit_data = a.buf(gbuf).address;
    info.scratch_data = a.buf(scratch).address;
    info.dst_addresses_array = region(a.buf(gaddrs).address, 8, 8 * n as u64);
    info.src_infos_array = region(a.buf(gsrc).address, 8, 8 * n as u64);
    // SAFETY: valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    let g: Vec<u64> = collect(&a.buf(gaddrs).read(0, 8 * n as usize));
    for (k, (_, idx)) in cl.iter().enumerate() {
        assert_eq!(a.buf(gbuf).read((g[k] - a.buf(gbuf).address) as usize, 2 * idx.len()), bytes_of(idx), "template indices {k}");
    }
    a.destroy();
    ctx.finish();
}

/// A failing element is reported and skipped while the others complete, nothing is written
/// outside the results (guard bytes), and the process lives; the source array is reached through
/// an INDIRECTED_SRC_INFOS_ARRAY address.
#[test]
fn failing_elements_are_contained() {
    let mut opts = harness::Options { acceleration_structure: true, ..Default::default() };
    opts.device_extensions.push(EXT);
    let ctx = harness::Context::new(opts);
    let api = nv(&ctx);
    let a = Accel::new(&ctx);
    let cl = clusters(2);
    let (v, i) = &cl[0];
    let (ibuf, vbuf) = (a.upload(&bytes_of(i)), a.upload(&bytes_of(&v.iter().flatten().copied().collect::<Vec<f32>>())));
    let (ia, va) = (a.buf(ibuf).address, a.buf(vbuf).address);
    let good = BuildTriangleClusterInfo { cluster_id: 7, counts: pack_counts(i.len() as u32 / 3, v.len() as u32, 0, 2, 0), index_buffer: ia, vertex_buffer: va, ..Default::default() };
    // 300 triangles: over maxTrianglesPerCluster (256), though it fits the 9-bit field.
    let bad = BuildTriangleClusterInfo { counts: pack_counts(300, v.len() as u32, 0, 2, 0), ..good };
    let src = a.upload(&bytes_of(&[good, bad]));
    let src_at = a.buf(src).address;
    let src_ptr = a.upload(&src_at.to_le_bytes());
    let tri_input = TriangleInput {
        s_type: 1_000_569_003,
        p_next: std::ptr::null_mut(),
        vertex_format: vk::Format::R32G32B32_SFLOAT.as_raw(),
        max_geometry_index_value: 0,
        max_cluster_unique_geometry_count: 1,
        max_cluster_triangle_count: 256,
        max_cluster_vertex_count: 256,
        max_total_triangle_count: 512,
        max_total_vertex_count: 512,
        min_position_truncate_bit_count: 0,
    };
    let tri_ptr = &tri_input as *const TriangleInput as *const c_void;
    let mut s = vk::AccelerationStructureBuildSizesInfoKHR::default();
    // SAFETY: valid structs.
    unsafe { (api.get_sizes)(ctx.device.handle(), &input(OpType::BuildTriangleCluster, OpMode::ImplicitDestinations, 2, tri_ptr), &mut s) };
    let dst = a.buffer(s.acceleration_structure_size);
    a.fill(dst, 0xAB);
    let (addrs, sizes, scratch) = (a.buffer(16), a.buffer(8), a.buffer(s.build_scratch_size + 16));
    a.fill(sizes, 0xFF);
    let mut info = commands(input(OpType::BuildTriangleCluster, OpMode::ImplicitDestinations, 2, tri_ptr));
    info.dst_implicit_data = a.buf(dst).address;
    info.scratch_data = a.buf(scratch).address;
    info.dst_addresses_array = region(a.buf(addrs).address, 8, 16);
    info.dst_sizes_array = region(a.buf(sizes).address, 4, 8);
    info.src_infos_array = region(a.buf(src_ptr).address, 64, 128);
    info.address_resolution_flags = 0x10;
    // SAFETY: valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    let got: Vec<u32> = collect(&a.buf(sizes).read(0, 8));
    let mut view = MapView::new();
    view.insert(ia, bytes_of(i));
    view.insert(va, bytes_of(&v.iter().flatten().copied().collect::<Vec<f32>>()));
    let mut want = vec![0u8; clas::clas_size(good.triangle_count() as u64) as usize];
    clas::build_clas(&good, accel::VertexFormat::R32G32B32Sfloat, &view, &mut want).unwrap();
    assert_eq!(got, [want.len() as u32, u32::MAX], "the failing element's size is not written");
    let all = a.buf(dst).read(0, s.acceleration_structure_size as usize);
    assert_eq!(all[..want.len()], want[..]);
    assert!(all[want.len()..].iter().all(|&b| b == 0xAB), "nothing written past the one result");
    assert!(harness::diagnostics().contains("element 1: triangleCount 300 exceeds maxTrianglesPerCluster 256"), "{}", harness::diagnostics());

    // A cluster BLAS over an address that holds no CLAS: reported, nothing written.
    let inside = a.buf(dst).address + 8;
    let refs = a.upload(&inside.to_le_bytes());
    let args = a.upload(bytemuck::bytes_of(&BuildClustersBottomLevelInfo { cluster_references_count: 1, cluster_references_stride: 8, cluster_references: 0 }));
    let refs_at = a.buf(refs).address;
    a.buf(args).write(8, &refs_at.to_le_bytes());
    let bl_input = BottomLevelInput { s_type: 1_000_569_002, p_next: std::ptr::null_mut(), max_total_cluster_count: 1, max_cluster_count_per_acceleration_structure: 1 };
    let bl_ptr = &bl_input as *const BottomLevelInput as *const c_void;
    let out = a.buffer(1 << 16);
    a.fill(out, 0xCD);
    let mut info = commands(input(OpType::BuildClustersBottomLevel, OpMode::ImplicitDestinations, 1, bl_ptr));
    info.dst_implicit_data = a.buf(out).address;
    // Misaligned scratch: reported (10447); Arbor needs none of it, so the command runs.
    info.scratch_data = a.buf(scratch).address + 4;
    info.src_infos_array = region(a.buf(args).address, 16, 16);
    // SAFETY: valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    assert!(a.buf(out).read(0, 1 << 16).iter().all(|&b| b == 0xCD));
    assert!(harness::diagnostics().contains("element 0: cluster reference"), "{}", harness::diagnostics());
    assert!(harness::diagnostics().contains("scratchData-10447"), "{}", harness::diagnostics());
    assert!(!harness::diagnostics().contains("scratchData-10446"), "{}", harness::diagnostics());
    a.destroy();
    ctx.finish();
}

//! Cluster workloads (VK_NV_cluster_acceleration_structure) through the API, over a mesh cut
//! into clusters of at most 128 triangles and 256 vertices, consecutive in the Morton order of
//! the triangle centroids: CLAS builds (`clas-build`), instantiation of templates with new
//! vertices (`clas-instantiate`), the animated-mesh pipeline of instantiation followed by a
//! cluster BLAS over the new CLASes (`cluster-blas`), a move that packs the CLASes tightly
//! (`clas-move-compact`). The KHR BLAS build of the same triangles (`khr-blas`) runs in
//! `device`. Drivers without the extension read "not supported".
use std::ffi::{c_void, CStr};

use arbor::accel::clas::args::{BuildClustersBottomLevelInfo, BuildTriangleClusterInfo, BuildTriangleClusterTemplateInfo, GeometryIndexAndFlags, InstantiateClusterInfo, ObjectType, OpMode, OpType, StridedDeviceAddress, pack_counts};
use arbor_scene::Mesh;
use ash::vk;

use super::{Options, Row, Scene, SceneKind, Stats, Status, Workload};
use crate::vkctx::{Arena, Buf, Gpu, Place};

pub const EXTENSION: &CStr = c"VK_NV_cluster_acceleration_structure";
const MAX_TRIANGLES: usize = 128;
const MAX_VERTICES: usize = 256;

// The host structs of the extension, written from the registry.
#[repr(C)]
#[derive(Clone, Copy)]
struct InputInfo {
    s_type: i32,
    p_next: *const c_void,
    max_acceleration_structure_count: u32,
    flags: u32,
    op_type: i32,
    op_mode: i32,
    op_input: *const c_void,
}
#[repr(C)]
struct TriangleInput {
    s_type: i32,
    p_next: *const c_void,
    vertex_format: i32,
    max_geometry_index_value: u32,
    max_cluster_unique_geometry_count: u32,
    max_cluster_triangle_count: u32,
    max_cluster_vertex_count: u32,
    max_total_triangle_count: u32,
    max_total_vertex_count: u32,
    min_position_truncate_bit_count: u32,
}
#[repr(C)]
struct BottomLevelInput {
    s_type: i32,
    p_next: *const c_void,
    max_total_cluster_count: u32,
    max_cluster_count_per_acceleration_structure: u32,
}
#[repr(C)]
struct MoveInput {
    s_type: i32,
    p_next: *const c_void,
    ty: i32,
    no_move_overlap: u32,
    max_moved_bytes: u64,
}
#[repr(C)]
struct CommandsInfo {
    s_type: i32,
    p_next: *const c_void,
    input: InputInfo,
    dst_implicit_data: u64,
    scratch_data: u64,
    dst_addresses_array: vk::StridedDeviceAddressRegionKHR,
    dst_sizes_array: vk::StridedDeviceAddressRegionKHR,
    src_infos_array: vk::StridedDeviceAddressRegionKHR,
    src_infos_count: u64,
    address_resolution_flags: u32,
}
type GetSizes = unsafe extern "system" fn(vk::Device, *const InputInfo, *mut vk::AccelerationStructureBuildSizesInfoKHR);
type CmdBuild = unsafe extern "system" fn(vk::CommandBuffer, *const CommandsInfo);

struct Nv {
    get_sizes: GetSizes,
    cmd_build: CmdBuild,
}

/// The extension's commands, when the device has it enabled.
fn nv(gpu: &Gpu) -> Option<Nv> {
    let f = |name: &CStr| {
        // SAFETY: a live device and a NUL-terminated command name.
        unsafe { (gpu.get_device_proc_addr)(gpu.device.handle(), name.as_ptr()) }
    };
    let (s, b) = (f(c"vkGetClusterAccelerationStructureBuildSizesNV")?, f(c"vkCmdBuildClusterAccelerationStructureIndirectNV")?);
    // SAFETY: the PFN types of these commands (vk.xml).
    unsafe { Some(Nv { get_sizes: std::mem::transmute::<unsafe extern "system" fn(), GetSizes>(s), cmd_build: std::mem::transmute::<unsafe extern "system" fn(), CmdBuild>(b) }) }
}

/// A mesh cut into clusters: each cluster's local vertices and 16-bit local indices.
pub fn cut(m: &Mesh) -> Vec<(Vec<[f32; 3]>, Vec<u16>)> {
    let b = m.bounds();
    let centre = |t: &[u32; 3]| -> [f32; 3] { std::array::from_fn(|a| t.iter().map(|&i| m.positions[i as usize][a]).sum::<f32>() / 3.0) };
    let spread = |x: u32| -> u64 {
        let mut v = x as u64 & 0x3ff;
        v = (v | v << 16) & 0x0300_00ff;
        v = (v | v << 8) & 0x0300_f00f;
        v = (v | v << 4) & 0x030c_30c3;
        (v | v << 2) & 0x0924_9249
    };
    let code = |p: [f32; 3]| -> u64 {
        let q = |a: usize| (((p[a] - b[a]) / (b[a + 3] - b[a]).max(f32::MIN_POSITIVE)).clamp(0.0, 1.0) * 1023.0) as u32;
        spread(q(0)) | spread(q(1)) << 1 | spread(q(2)) << 2
    };
    let mut order: Vec<(u64, u32)> = m.indices.iter().enumerate().map(|(k, t)| (code(centre(t)), k as u32)).collect();
    order.sort_unstable();
    let mut clusters = Vec::new();
    let (mut verts, mut idx, mut map) = (Vec::new(), Vec::new(), std::collections::HashMap::new());
    for &(_, k) in &order {
        let t = &m.indices[k as usize];
        let new = t.iter().filter(|i| !map.contains_key(*i)).count();
        if idx.len() / 3 == MAX_TRIANGLES || map.len() + new > MAX_VERTICES {
            clusters.push((std::mem::take(&mut verts), std::mem::take(&mut idx)));
            map.clear();
        }
        for &i in t {
            let l = *map.entry(i).or_insert_with(|| {
                verts.push(m.positions[i as usize]);
                verts.len() - 1
            });
            idx.push(l as u16);
        }
    }
    if !idx.is_empty() {
        clusters.push((verts, idx));
    }
    clusters
}

/// The clusters in device memory: indices, vertices, the vertices of the next animation frame
/// (moved by 1 %), and one BUILD_TRIANGLE_CLUSTER record per cluster.
struct Clusters {
    count: u32,
    triangles: u32,
    vertices: u32,
    records: Vec<BuildTriangleClusterInfo>,
    /// Each cluster's first vertex in the animated vertex buffer.
    next_frame: Vec<u64>,
}

fn upload(a: &Arena, m: &Mesh) -> Result<Clusters, String> {
    let cl = cut(m);
    let (mut ib, mut vb, mut nb, mut at) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (v, i) in &cl {
        at.push((ib.len() as u64, vb.len() as u64));
        ib.extend(i.iter().flat_map(|x| x.to_le_bytes()));
        vb.extend(v.iter().flatten().flat_map(|x| x.to_le_bytes()));
        nb.extend(v.iter().flatten().flat_map(|x| (x * 1.01).to_le_bytes()));
    }
    let (ibuf, vbuf, nbuf) = (a.upload(&ib)?, a.upload(&vb)?, a.upload(&nb)?);
    let records = cl
        .iter()
        .zip(&at)
        .enumerate()
        .map(|(k, ((v, i), (io, vo)))| BuildTriangleClusterInfo {
            cluster_id: k as u32,
            counts: pack_counts(i.len() as u32 / 3, v.len() as u32, 0, 2, 0),
            base_geometry_index_and_geometry_flags: GeometryIndexAndFlags::new(0, GeometryIndexAndFlags::OPAQUE),
            index_buffer: ibuf.address + io,
            vertex_buffer: vbuf.address + vo,
            ..Default::default()
        })
        .collect();
    Ok(Clusters {
        count: cl.len() as u32,
        triangles: cl.iter().map(|c| c.1.len() as u32 / 3).sum(),
        vertices: cl.iter().map(|c| c.0.len() as u32).sum(),
        records,
        next_frame: at.iter().map(|&(_, vo)| nbuf.address + vo).collect(),
    })
}

/// The row's times: queue timestamps where every run has one, else fence wall times.
fn fill_times(row: &mut Row, times: &[(Option<f64>, f64)]) {
    let wall: Vec<f64> = times.iter().map(|t| t.1).collect();
    let ts: Vec<f64> = times.iter().filter_map(|t| t.0).collect();
    row.wall = Stats::of(&wall);
    let stamped = ts.len() == times.len() && !ts.is_empty() && ts.iter().all(|&t| t > 0.0);
    (row.time, row.timing) = if stamped { (Stats::of(&ts), "timestamp") } else { (row.wall, "fence") };
}

/// The bytes of argument records (the registry's `#[repr(C)]` layouts, which have no padding:
/// arbor asserts their sizes).
fn as_bytes<T: Copy>(v: &[T]) -> &[u8] {
    // SAFETY: `v` is a live slice of plain-old-data records; its bytes are initialised.
    unsafe { std::slice::from_raw_parts(v.as_ptr() as *const u8, std::mem::size_of_val(v)) }
}

fn region(address: u64, stride: u64, size: u64) -> vk::StridedDeviceAddressRegionKHR {
    vk::StridedDeviceAddressRegionKHR { device_address: address, stride, size }
}

/// One op over `count` elements: its size query and the buffers an IMPLICIT command writes.
struct Op {
    input: InputInfo,
    dst: Buf,
    addresses: Buf,
    sizes: Buf,
    scratch: Buf,
}

impl Op {
    fn new(a: &Arena, nv: &Nv, op: OpType, count: u32, op_input: *const c_void) -> Result<Op, String> {
        let input = InputInfo { s_type: 1_000_569_005, p_next: std::ptr::null(), max_acceleration_structure_count: count, flags: 0, op_type: op as i32, op_mode: OpMode::ImplicitDestinations as i32, op_input };
        let mut s = vk::AccelerationStructureBuildSizesInfoKHR::default();
        // SAFETY: valid structs; op_input points at the op's input struct, alive for the call.
        unsafe { (nv.get_sizes)(a.gpu.device.handle(), &input, &mut s) };
        Ok(Op {
            input,
            dst: a.buffer(s.acceleration_structure_size, Place::Device)?,
            addresses: a.buffer(8 * count as u64, Place::Host)?,
            sizes: a.buffer(4 * count as u64, Place::Host)?,
            scratch: a.buffer(s.build_scratch_size, Place::Device)?,
        })
    }

    /// The command info reading `count` records of `stride` bytes at `src`.
    fn info(&self, src: u64, stride: u64) -> CommandsInfo {
        let n = self.input.max_acceleration_structure_count as u64;
        CommandsInfo {
            s_type: 1_000_569_006,
            p_next: std::ptr::null(),
            input: self.input,
            dst_implicit_data: self.dst.address,
            scratch_data: self.scratch.address,
            dst_addresses_array: region(self.addresses.address, 8, 8 * n),
            dst_sizes_array: region(self.sizes.address, 4, 4 * n),
            src_infos_array: region(src, stride, stride * n),
            src_infos_count: 0,
            address_resolution_flags: 0,
        }
    }

    fn addresses(&self) -> Vec<u64> {
        let n = self.input.max_acceleration_structure_count as usize;
        self.addresses.read(0, 8 * n).chunks_exact(8).map(|c| u64::from_le_bytes(c.try_into().unwrap_or([0; 8]))).collect()
    }
    fn total_size(&self) -> u64 {
        let n = self.input.max_acceleration_structure_count as usize;
        self.sizes.read(0, 4 * n).chunks_exact(4).map(|c| u32::from_le_bytes(c.try_into().unwrap_or([0; 4])) as u64).sum()
    }
}

fn record(nv: &Nv, cb: vk::CommandBuffer, info: &CommandsInfo) {
    // SAFETY: a recording command buffer; every address the info names is a live buffer.
    unsafe { (nv.cmd_build)(cb, info) };
}

/// Builds written by one command are read by the next.
fn barrier(gpu: &Gpu, cb: vk::CommandBuffer) {
    let stage = vk::PipelineStageFlags::ACCELERATION_STRUCTURE_BUILD_KHR;
    let m = [vk::MemoryBarrier::default()
        .src_access_mask(vk::AccessFlags::ACCELERATION_STRUCTURE_WRITE_KHR)
        .dst_access_mask(vk::AccessFlags::ACCELERATION_STRUCTURE_READ_KHR | vk::AccessFlags::ACCELERATION_STRUCTURE_WRITE_KHR)];
    // SAFETY: a recording command buffer.
    unsafe { gpu.device.cmd_pipeline_barrier(cb, stage, stage, vk::DependencyFlags::empty(), &m, &[], &[]) };
}

fn triangle_input(c: &Clusters) -> TriangleInput {
    TriangleInput {
        s_type: 1_000_569_003,
        p_next: std::ptr::null(),
        vertex_format: vk::Format::R32G32B32_SFLOAT.as_raw(),
        max_geometry_index_value: 0,
        max_cluster_unique_geometry_count: 1,
        max_cluster_triangle_count: MAX_TRIANGLES as u32,
        max_cluster_vertex_count: MAX_VERTICES as u32,
        max_total_triangle_count: c.triangles,
        max_total_vertex_count: c.vertices,
        min_position_truncate_bit_count: 0,
    }
}

/// Runs one cluster workload into `row` (the row's primitives are the scene's triangles).
pub fn run(gpu: &Gpu, scene: &Scene, w: Workload, opts: &Options, row: &mut Row) -> Result<(), String> {
    let SceneKind::Mesh(mesh) = &scene.kind else {
        row.status = Status::NotSupported("cluster workloads run on mesh scenes".into());
        return Ok(());
    };
    let Some(nv) = nv(gpu) else {
        row.status = Status::NotSupported(format!("no {}", EXTENSION.to_string_lossy()));
        return Ok(());
    };
    let a = Arena::new(gpu);
    let c = upload(&a, mesh)?;
    let tri = triangle_input(&c);
    let tri_ptr = &tri as *const TriangleInput as *const c_void;
    let records = a.upload(as_bytes(&c.records))?;
    let n = c.count;
    let per_s = |ms: f64| n as f64 / (ms * 1e-3);
    match w {
        Workload::ClasBuild => {
            let op = Op::new(&a, &nv, OpType::BuildTriangleCluster, n, tri_ptr)?;
            let info = op.info(records.address, 64);
            fill_times(row, &gpu.timed(opts.warmup, opts.repeat, |cb| record(&nv, cb, &info))?);
            row.as_size = op.total_size();
            row.note = format!("{n} CLASes; {:.0} CLAS builds/s", row.time.map_or(0.0, |t| per_s(t.median)));
        }
        Workload::ClasInstantiate | Workload::ClusterBlas => {
            let inst = instantiation(&a, &nv, &c, tri_ptr)?;
            let info = inst.op.info(inst.records.address, 32);
            if w == Workload::ClasInstantiate {
                fill_times(row, &gpu.timed(opts.warmup, opts.repeat, |cb| record(&nv, cb, &info))?);
                row.as_size = inst.op.total_size();
                row.note = format!("{n} templates; {:.0} instantiations/s", row.time.map_or(0.0, |t| per_s(t.median)));
            } else {
                cluster_blas(&a, &nv, &inst.op, &info, n, opts, row)?;
            }
        }
        Workload::ClasMoveCompact => {
            let op = Op::new(&a, &nv, OpType::BuildTriangleCluster, n, tri_ptr)?;
            let info = op.info(records.address, 64);
            gpu.submit(|cb| record(&nv, cb, &info))?;
            let moved = op.total_size();
            let mv = MoveInput { s_type: 1_000_569_004, p_next: std::ptr::null(), ty: ObjectType::TriangleCluster as i32, no_move_overlap: 1, max_moved_bytes: moved };
            let packed = Op::new(&a, &nv, OpType::MoveObjects, n, &mv as *const MoveInput as *const c_void)?;
            // The addresses the build wrote are the move's source records (one address each).
            let minfo = packed.info(op.addresses.address, 8);
            fill_times(row, &gpu.timed(opts.warmup, opts.repeat, |cb| record(&nv, cb, &minfo))?);
            row.as_size = packed.total_size();
            row.compacted_size = Some(packed.addresses().iter().zip(packed.sizes.read(0, 4 * n as usize).chunks_exact(4)).map(|(&ad, s)| ad + u32::from_le_bytes(s.try_into().unwrap_or([0; 4])) as u64).max().unwrap_or(0) - packed.dst.address);
            row.note = format!("{n} CLASes, {moved} bytes moved from a {} byte region", op.dst.size);
        }
        _ => return Err(format!("{} is not a cluster workload", w.name())),
    }
    // The rates the table has no column for, beside the progress lines.
    eprintln!("arbor-bench: {} {} {}: {}", row.driver, scene.name, w.name(), row.note);
    Ok(())
}

/// Templates built once (untimed) and the records instantiating each with the next frame's
/// vertices.
struct Instantiation {
    op: Op,
    records: Buf,
}

fn instantiation(a: &Arena, nv: &Nv, c: &Clusters, tri_ptr: *const c_void) -> Result<Instantiation, String> {
    let n = c.count;
    let tpl_records: Vec<BuildTriangleClusterTemplateInfo> = c.records.iter().map(|r| BuildTriangleClusterTemplateInfo { cluster: *r, instantiation_bounding_box_limit: 0 }).collect();
    let tpl_src = a.upload(as_bytes(&tpl_records))?;
    let tpl = Op::new(a, nv, OpType::BuildTriangleClusterTemplate, n, tri_ptr)?;
    let tinfo = tpl.info(tpl_src.address, 72);
    a.gpu.submit(|cb| record(nv, cb, &tinfo))?;
    let inst: Vec<InstantiateClusterInfo> = tpl
        .addresses()
        .iter()
        .zip(&c.next_frame)
        .map(|(&t, &v)| InstantiateClusterInfo { cluster_template_address: t, vertex_buffer: StridedDeviceAddress { start_address: v, stride_in_bytes: 12 }, ..Default::default() })
        .collect();
    let inst_src = a.upload(as_bytes(&inst))?;
    // The templates live in the arena, as long as the instantiation op.
    let op = Op::new(a, nv, OpType::InstantiateTriangleCluster, n, tri_ptr)?;
    Ok(Instantiation { op, records: inst_src })
}

/// The animated-mesh pipeline: instantiation, then one cluster BLAS over all the new CLASes
/// (its references are the addresses the instantiation wrote). The BLAS alone is timed too.
fn cluster_blas(a: &Arena, nv: &Nv, inst: &Op, inst_info: &CommandsInfo, n: u32, opts: &Options, row: &mut Row) -> Result<(), String> {
    let gpu = a.gpu;
    let bl = BottomLevelInput { s_type: 1_000_569_002, p_next: std::ptr::null(), max_total_cluster_count: n, max_cluster_count_per_acceleration_structure: n };
    let blas = Op::new(a, nv, OpType::BuildClustersBottomLevel, 1, &bl as *const BottomLevelInput as *const c_void)?;
    let args = a.upload(as_bytes(&[BuildClustersBottomLevelInfo { cluster_references_count: n, cluster_references_stride: 8, cluster_references: inst.addresses.address }]))?;
    let binfo = blas.info(args.address, 16);
    fill_times(row, &gpu.timed(opts.warmup, opts.repeat, |cb| {
        record(nv, cb, inst_info);
        barrier(gpu, cb);
        record(nv, cb, &binfo);
    })?);
    let pipeline = row.time;
    let mut alone = row.clone();
    fill_times(&mut alone, &gpu.timed(opts.warmup, opts.repeat, |cb| record(nv, cb, &binfo))?);
    row.as_size = blas.total_size();
    row.scratch_size = blas.scratch.size;
    row.note = format!("{n} CLASes; cluster BLAS alone {:.2} ms", alone.time.map_or(0.0, |t| t.median));
    row.time = pipeline;
    Ok(())
}

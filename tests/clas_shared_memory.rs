//! In-place and copying results of vkCmdBuildClusterAccelerationStructureIndirectNV agree: CLASes
//! built (IMPLICIT) into a buffer of their own are written in place; built into a buffer that
//! also holds their indices and vertices, they are made in host memory and copied (a destination
//! must not be written while the command reads it). A cluster BLAS likewise, in its own buffer
//! and in the buffer of its CLASes. Both are compared with the library's builds of the same input;
//! CLASes moved into a buffer of their own (in place) are byte copies.
mod harness;

use std::ffi::c_void;

use arbor::accel::clas::{self, args::*};
use arbor::accel::{self, MapView};
use ash::vk;
use harness::accel::Accel;

const EXT: &str = "VK_NV_cluster_acceleration_structure";

// The host structs, written here from the registry (not imported from the driver).
#[repr(C)]
#[derive(Clone, Copy)]
struct InputInfo {
    s_type: i32,
    p_next: *mut c_void,
    max_acceleration_structure_count: u32,
    flags: u32,
    op_type: i32,
    op_mode: i32,
    op_input: *const c_void,
}
#[repr(C)]
struct TriangleInput {
    s_type: i32,
    p_next: *mut c_void,
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
    p_next: *mut c_void,
    max_total_cluster_count: u32,
    max_cluster_count_per_acceleration_structure: u32,
}
#[repr(C)]
struct MoveInput {
    s_type: i32,
    p_next: *mut c_void,
    ty: i32,
    no_move_overlap: u32,
    max_moved_bytes: u64,
}
#[repr(C)]
struct CommandsInfo {
    s_type: i32,
    p_next: *mut c_void,
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

fn nv(ctx: &harness::Context) -> Nv {
    let f = |name: &std::ffi::CStr| {
        // SAFETY: a device-level command name.
        unsafe { ctx.instance.get_device_proc_addr(ctx.device.handle(), name.as_ptr()) }.expect("the command resolves when the extension is enabled")
    };
    // SAFETY: the PFN types of these commands (vk.xml).
    unsafe {
        Nv {
            get_sizes: std::mem::transmute::<unsafe extern "system" fn(), GetSizes>(f(c"vkGetClusterAccelerationStructureBuildSizesNV")),
            cmd_build: std::mem::transmute::<unsafe extern "system" fn(), CmdBuild>(f(c"vkCmdBuildClusterAccelerationStructureIndirectNV")),
        }
    }
}

fn region(address: u64, stride: u64, size: u64) -> vk::StridedDeviceAddressRegionKHR {
    vk::StridedDeviceAddressRegionKHR { device_address: address, stride, size }
}

fn input(op: OpType, mode: OpMode, count: u32, op_input: *const c_void) -> InputInfo {
    InputInfo { s_type: 1_000_569_005, p_next: std::ptr::null_mut(), max_acceleration_structure_count: count, flags: 0, op_type: op as i32, op_mode: mode as i32, op_input }
}

fn commands(input: InputInfo) -> CommandsInfo {
    CommandsInfo {
        s_type: 1_000_569_006,
        p_next: std::ptr::null_mut(),
        input,
        dst_implicit_data: 0,
        scratch_data: 0,
        dst_addresses_array: region(0, 0, 0),
        dst_sizes_array: region(0, 0, 0),
        src_infos_array: region(0, 0, 0),
        src_infos_count: 0,
        address_resolution_flags: 0,
    }
}

/// `n` small clusters: a 6 × 6 vertex grid each (50 triangles), 16-bit local indices, bent so
/// each cluster has its own shape.
fn clusters(n: usize) -> Vec<(Vec<f32>, Vec<u16>)> {
    (0..n)
        .map(|k| {
            let verts = (0..36).flat_map(|v| {
                let (x, y) = ((v % 6) as f32, (v / 6) as f32);
                [x + 7.0 * k as f32, y, ((x * 1.3 + y * 0.7 + k as f32) * 0.9).sin()]
            });
            let idx = (0..25u16).flat_map(|c| {
                let (x, y) = (c % 5, c / 5);
                let v = y * 6 + x;
                [v, v + 1, v + 6, v + 1, v + 7, v + 6]
            });
            (verts.collect(), idx.collect())
        })
        .collect()
}

/// What one command wrote: the result addresses and sizes.
struct Written {
    addresses: Vec<u64>,
    sizes: Vec<u32>,
}

/// Runs one IMPLICIT command of `n` records (at `src`, `stride` apart) writing into `dst`.
fn run(a: &Accel<'_>, api: &Nv, info_input: InputInfo, dst: u64, src: (u64, u64), n: u32) -> Written {
    let (addrs, sizes, scratch) = (a.buffer(8 * n as u64), a.buffer(4 * n as u64), a.buffer(256));
    let mut info = commands(info_input);
    info.dst_implicit_data = dst;
    info.scratch_data = a.buf(scratch).address;
    info.dst_addresses_array = region(a.buf(addrs).address, 8, 8 * n as u64);
    info.dst_sizes_array = region(a.buf(sizes).address, 4, 4 * n as u64);
    info.src_infos_array = region(src.0, src.1, src.1 * n as u64);
    // SAFETY: a valid command buffer and info.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    let addresses = a.buf(addrs).read(0, 8 * n as usize).chunks_exact(8).map(bytemuck::pod_read_unaligned).collect();
    let sizes = a.buf(sizes).read(0, 4 * n as usize).chunks_exact(4).map(bytemuck::pod_read_unaligned).collect();
    Written { addresses, sizes }
}

/// The bytes `w` names inside buffer `buf`.
fn results(a: &Accel<'_>, buf: usize, w: &Written) -> Vec<Vec<u8>> {
    let base = a.buf(buf).address;
    w.addresses.iter().zip(&w.sizes).map(|(&at, &s)| a.buf(buf).read((at - base) as usize, s as usize)).collect()
}

// One function: the two placements of the same builds, each step reading the one before.
#[test]
fn in_place_and_copied_results_agree() {
    let mut opts = harness::Options { acceleration_structure: true, ..Default::default() };
    opts.device_extensions.push(EXT);
    let ctx = harness::Context::new(opts);
    let api = nv(&ctx);
    let a = Accel::new(&ctx);
    let cl = clusters(12);
    let n = cl.len() as u32;
    let tri_input = TriangleInput {
        s_type: 1_000_569_003,
        p_next: std::ptr::null_mut(),
        vertex_format: vk::Format::R32G32B32_SFLOAT.as_raw(),
        max_geometry_index_value: 0,
        max_cluster_unique_geometry_count: 1,
        max_cluster_triangle_count: 64,
        max_cluster_vertex_count: 64,
        max_total_triangle_count: 64 * n,
        max_total_vertex_count: 64 * n,
        min_position_truncate_bit_count: 0,
    };
    let tri = input(OpType::BuildTriangleCluster, OpMode::ImplicitDestinations, n, &tri_input as *const TriangleInput as *const c_void);
    let mut total = vk::AccelerationStructureBuildSizesInfoKHR::default();
    // SAFETY: valid structs.
    unsafe { (api.get_sizes)(ctx.device.handle(), &tri, &mut total) };
    let room = total.acceleration_structure_size.next_multiple_of(256);
    let data_len: usize = cl.iter().map(|(v, i)| 4 * v.len() + 2 * i.len() + 16).sum();
    // Placement 0: the data in a buffer of its own (and room for a cluster BLAS after the
    // CLASes); placement 1: the data after the results' room, in the destination's buffer.
    let own = (a.buffer(room + clas::blas_size_bound(n as u64) + 4096), a.buffer(data_len as u64));
    let shared = a.buffer(room + data_len as u64);
    let mut built = Vec::new();
    for (dst, data, data_at) in [(own.0, own.1, 0), (shared, shared, room)] {
        let base = a.buf(data).address + data_at;
        let (mut bytes, mut records) = (Vec::new(), Vec::new());
        for (k, (v, i)) in cl.iter().enumerate() {
            let (ia, va) = (bytes.len() as u64, bytes.len() as u64 + 2 * i.len() as u64);
            bytes.extend(bytemuck::cast_slice::<u16, u8>(i));
            bytes.extend(bytemuck::cast_slice::<f32, u8>(v));
            bytes.resize(bytes.len().next_multiple_of(16), 0);
            let counts = pack_counts(i.len() as u32 / 3, v.len() as u32 / 3, 0, 2, 0);
            records.push(BuildTriangleClusterInfo { cluster_id: k as u32, counts, index_buffer: base + ia, vertex_buffer: base + va, ..Default::default() });
        }
        a.buf(data).write(data_at as usize, &bytes);
        let src = a.upload(bytemuck::cast_slice(&records));
        let (dst_at, src_at) = (a.buf(dst).address, a.buf(src).address);
        let w = run(&a, &api, tri, dst_at, (src_at, 64), n);
        // The library's builds of the same memory contents.
        let mut view = MapView::new();
        view.insert(base, bytes.clone());
        let got = results(&a, dst, &w);
        for (k, r) in records.iter().enumerate() {
            let mut want = vec![0u8; clas::clas_size(r.triangle_count() as u64) as usize];
            clas::build_clas(r, accel::VertexFormat::R32G32B32Sfloat, &view, &mut want).unwrap();
            assert_eq!(got[k], want, "CLAS {k}, data in the destination's buffer: {}", dst == data);
        }
        built.push((dst, w, got));
    }
    assert_eq!(built[0].1.addresses.iter().map(|x| x - a.buf(own.0).address).collect::<Vec<_>>(), built[1].1.addresses.iter().map(|x| x - a.buf(shared).address).collect::<Vec<_>>());
    assert_eq!(built[0].2, built[1].2);

    // A cluster BLAS over the CLASes of placement 0: in a buffer of its own (in place), and in
    // the CLASes' buffer after them (copied).
    let bl_input = BottomLevelInput { s_type: 1_000_569_002, p_next: std::ptr::null_mut(), max_total_cluster_count: n, max_cluster_count_per_acceleration_structure: n };
    let bl = input(OpType::BuildClustersBottomLevel, OpMode::ImplicitDestinations, 1, &bl_input as *const BottomLevelInput as *const c_void);
    let mut s = vk::AccelerationStructureBuildSizesInfoKHR::default();
    // SAFETY: valid structs.
    unsafe { (api.get_sizes)(ctx.device.handle(), &bl, &mut s) };
    let refs_buf = a.upload(bytemuck::cast_slice(&built[0].1.addresses));
    let refs_at = a.buf(refs_buf).address;
    let args = a.upload(bytemuck::bytes_of(&BuildClustersBottomLevelInfo { cluster_references_count: n, cluster_references_stride: 8, cluster_references: refs_at }));
    let args_at = a.buf(args).address;
    let refs: Vec<(u64, &[u8])> = built[0].1.addresses.iter().copied().zip(built[0].2.iter().map(Vec::as_slice)).collect();
    let mut want = vec![0u8; clas::blas_size_bound(n as u64) as usize];
    let used = clas::build_cluster_blas(&refs, 0, &mut want).unwrap() as usize;
    let alone = a.buffer(s.acceleration_structure_size);
    let places = [(alone, a.buf(alone).address), (own.0, a.buf(own.0).address + total.acceleration_structure_size.next_multiple_of(64))];
    for (buf, at) in places {
        let w = run(&a, &api, bl, at, (args_at, 16), 1);
        assert_eq!(w.addresses[0], at);
        assert_eq!(results(&a, buf, &w)[0], want[..used], "cluster BLAS, in the CLASes' buffer: {}", buf == own.0);
    }

    // The CLASes of placement 0 moved into a buffer of their own (in place): byte copies.
    let mv_input = MoveInput { s_type: 1_000_569_004, p_next: std::ptr::null_mut(), ty: ObjectType::TriangleCluster as i32, no_move_overlap: 1, max_moved_bytes: total.acceleration_structure_size };
    let mv = input(OpType::MoveObjects, OpMode::ImplicitDestinations, n, &mv_input as *const MoveInput as *const c_void);
    let mut ms = vk::AccelerationStructureBuildSizesInfoKHR::default();
    // SAFETY: valid structs.
    unsafe { (api.get_sizes)(ctx.device.handle(), &mv, &mut ms) };
    let packed = a.buffer(ms.acceleration_structure_size);
    let packed_at = a.buf(packed).address;
    let w = run(&a, &api, mv, packed_at, (refs_at, 8), n);
    assert_eq!(results(&a, packed, &w), built[0].2, "moved CLASes");
}

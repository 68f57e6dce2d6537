//! The recorded command run in pools of 1, 2, 5 and 16 threads: IMPLICIT instantiations written
//! in place give the same bytes, addresses and sizes whatever the pool, and each CLAS equals the
//! library's instantiation of the same template and vertices read through a map (no device
//! memory, no command).
use std::sync::Arc;

use ash::vk;

use super::{ClusterCommand, InputBounds, Strided};
use crate::accel::clas::args::{pack_counts, BuildTriangleClusterInfo, GeometryIndexAndFlags, InstantiateClusterInfo, ObjectType, OpMode, OpType, StridedDeviceAddress};
use crate::accel::clas;
use crate::accel::{MapView, VertexFormat};
use crate::memory::{AddressSpace, Buffer, Memory};

const F: VertexFormat = VertexFormat::R32G32B32Sfloat;

/// A deterministic pseudo-random stream (xorshift).
fn rng(seed: u64) -> impl FnMut() -> u32 {
    let mut s = seed | 1;
    move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 16) as u32
    }
}

/// A buffer over all of `memory`, filled with `bytes`.
fn buffer(memory: &Arc<Memory>, bytes: &[u8]) -> Arc<Buffer> {
    let usage = vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR | vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR;
    let b = Arc::new(Buffer::new(memory.size, usage, vk::BufferCreateFlags::empty()));
    b.bind(memory.clone(), 0).expect("bind");
    memory.write(0, bytes).expect("write");
    b
}

struct Input {
    templates: Vec<Vec<u8>>,
    /// Each cluster's vertices (fp32 xyz).
    vertices: Vec<Vec<u8>>,
}

fn input(clusters: usize) -> Input {
    let mut r = rng(0x5eed);
    let (mut templates, mut vertices) = (Vec::new(), Vec::new());
    for k in 0..clusters {
        let nv = 3 + r() % 254;
        let t = r() % 257;
        let v: Vec<u8> = (0..3 * nv).flat_map(|_| ((r() % 20_000) as f32 / 1000.0 - 10.0).to_le_bytes()).collect();
        let idx: Vec<u8> = (0..3 * t).flat_map(|_| ((r() % nv) as u16).to_le_bytes()).collect();
        let mut map = MapView::new();
        map.insert(0x1000, idx);
        map.insert(0x10_0000, v);
        let rec = BuildTriangleClusterInfo {
            cluster_id: k as u32,
            counts: pack_counts(t, nv, 0, 2, 0),
            base_geometry_index_and_geometry_flags: GeometryIndexAndFlags::new(k as u32, 0),
            index_buffer: 0x1000,
            ..Default::default()
        };
        let mut tpl = vec![0u8; clas::template_size(t as u64, false) as usize];
        clas::build_template(&rec, F, None, &map, &mut tpl).expect("template");
        templates.push(tpl);
        // The instantiation's vertices: new positions.
        vertices.push((0..3 * nv).flat_map(|_| ((r() % 20_000) as f32 / 1000.0 - 10.0).to_le_bytes()).collect());
    }
    Input { templates, vertices }
}

/// Runs one IMPLICIT instantiation of every template in a pool of `threads`; returns the
/// implicit data, the addresses and the sizes written.
fn run(inp: &Input, threads: usize) -> (Vec<u8>, Vec<u64>, Vec<u32>) {
    let n = inp.templates.len();
    let space = AddressSpace::new(1 << 30);
    let place = |parts: &[Vec<u8>]| -> (Vec<u8>, Vec<u64>) {
        let mut bytes = Vec::new();
        let mut at = Vec::new();
        for p in parts {
            bytes.resize(bytes.len().next_multiple_of(256), 0);
            at.push(bytes.len() as u64);
            bytes.extend_from_slice(p);
        }
        (bytes, at)
    };
    let (tb, tat) = place(&inp.templates);
    let (vb, vat) = place(&inp.vertices);
    let alloc = |size: u64| space.allocate(size.max(256), true, None).expect("allocate");
    let (tm, vm) = (alloc(tb.len() as u64), alloc(vb.len() as u64));
    let _t = buffer(&tm, &tb);
    let _v = buffer(&vm, &vb);
    let records: Vec<u8> = (0..n)
        .flat_map(|k| {
            let r = InstantiateClusterInfo { cluster_template_address: tm.address + tat[k], vertex_buffer: StridedDeviceAddress { start_address: vm.address + vat[k], stride_in_bytes: 12 }, ..Default::default() };
            bytemuck::bytes_of(&r).to_vec()
        })
        .collect();
    let rm = alloc(records.len() as u64 + 4);
    let mut rb = records.clone();
    rb.extend_from_slice(&(n as u32).to_le_bytes());
    let _r = buffer(&rm, &rb);
    let implicit: u64 = inp.templates.iter().map(|t| clas::clas_size(clas::open(t).map_or(0, |b| b.header.triangle_count) as u64) + clas::CLAS_ALIGNMENT).sum();
    let (dm, am, sm, xm) = (alloc(implicit), alloc(8 * n as u64), alloc(4 * n as u64), alloc(clas::SCRATCH_SIZE));
    let _bufs = [buffer(&dm, &[]), buffer(&am, &[]), buffer(&sm, &[]), buffer(&xm, &[])];
    let cmd = ClusterCommand {
        op: OpType::InstantiateTriangleCluster,
        mode: OpMode::ImplicitDestinations,
        max_count: n as u32,
        build_flags: 0,
        vertex_format: Some(F),
        move_type: ObjectType::TriangleCluster,
        dst_implicit_data: dm.address,
        scratch_data: xm.address,
        dst_addresses: Strided { address: am.address, stride: 8, size: 8 * n as u64 },
        dst_sizes: Strided { address: sm.address, stride: 4, size: 4 * n as u64 },
        src_infos: Strided { address: rm.address, stride: 32, size: records.len() as u64 },
        src_infos_count: rm.address + records.len() as u64,
        address_resolution: 0,
        bounds: InputBounds { vertex_format: vk::Format::R32G32B32_SFLOAT.as_raw(), max_cluster_triangles: 256, max_cluster_vertices: 256, max_total_triangles: u32::MAX, max_total_vertices: u32::MAX, ..Default::default() },
        queried_size: implicit,
    };
    rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool").install(|| cmd.run(&space));
    let read = |m: &Arc<Memory>, len: u64| {
        let mut out = vec![0u8; len as usize];
        m.read(0, &mut out).expect("read");
        out
    };
    // Addresses relative to the implicit data, so runs in different address spaces compare.
    let addresses = read(&am, 8 * n as u64).chunks_exact(8).map(|c| u64::from_le_bytes(c.try_into().unwrap_or([0; 8])).wrapping_sub(dm.address)).collect();
    let sizes = read(&sm, 4 * n as u64).chunks_exact(4).map(|c| u32::from_le_bytes(c.try_into().unwrap_or([0; 4]))).collect();
    (read(&dm, implicit), addresses, sizes)
}

#[test]
fn instantiations_in_place_do_not_depend_on_the_pool_and_equal_the_library() {
    let inp = input(300);
    let one = run(&inp, 1);
    for threads in [2, 5, 16] {
        assert!(one == run(&inp, threads), "1 thread against {threads}");
    }
    let (data, addresses, sizes) = one;
    for (k, (tpl, v)) in inp.templates.iter().zip(&inp.vertices).enumerate() {
        let mut map = MapView::new();
        map.insert(0x10_0000, v.clone());
        let a = InstantiateClusterInfo { vertex_buffer: StridedDeviceAddress { start_address: 0x10_0000, stride_in_bytes: 12 }, ..Default::default() };
        let t = clas::open(tpl).expect("template").header.triangle_count as u64;
        let mut want = vec![0u8; clas::clas_size(t) as usize];
        clas::instantiate(tpl, &a, &map, &mut want).expect("instantiate");
        assert_eq!(sizes[k] as usize, want.len(), "size of {k}");
        assert_eq!(&data[addresses[k] as usize..][..want.len()], &want[..], "CLAS {k}");
    }
}

//! A scene's inputs on one device, uploaded once for all its workloads: vertex and index buffers
//! (or the BLASes and instance records of a TLAS scene), the moved copy a refit reads, and the
//! host copies host builds read.
use arbor_scene::{InstanceRecord, Mesh};
use ash::vk;

use super::{Scene, SceneKind};
use crate::vkctx::{Arena, Gpu, Place};

/// Inputs of one scene on one device, uploaded once for all its workloads.
pub(super) struct Inputs {
    pub(super) ty: vk::AccelerationStructureTypeKHR,
    pub(super) count: u32,
    pub(super) geom: vk::AccelerationStructureGeometryKHR<'static>,
    /// Moved input for refit updates (vertices jittered / instances shifted).
    pub(super) moved: vk::AccelerationStructureGeometryKHR<'static>,
    /// Host copies for host builds: vertex + index bytes, or instance records with handles.
    pub(super) host_vertices: Vec<u8>,
    pub(super) host_indices: Vec<u8>,
    pub(super) host_instances: Vec<u8>,
    pub(super) max_vertex: u32,
    // For rendering.
    pub(super) blas_addresses: Vec<u64>,
    pub(super) blas_handles: Vec<vk::AccelerationStructureKHR>,
    pub(super) records: Vec<InstanceRecord>,
}

pub(super) fn triangles(v: vk::DeviceOrHostAddressConstKHR, i: vk::DeviceOrHostAddressConstKHR, max_vertex: u32) -> vk::AccelerationStructureGeometryKHR<'static> {
    vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::TRIANGLES)
        .flags(vk::GeometryFlagsKHR::OPAQUE)
        .geometry(vk::AccelerationStructureGeometryDataKHR {
            triangles: vk::AccelerationStructureGeometryTrianglesDataKHR::default()
                .vertex_format(vk::Format::R32G32B32_SFLOAT)
                .vertex_data(v)
                .vertex_stride(12)
                .max_vertex(max_vertex)
                .index_type(vk::IndexType::UINT32)
                .index_data(i),
        })
}

pub(super) fn instances(data: vk::DeviceOrHostAddressConstKHR) -> vk::AccelerationStructureGeometryKHR<'static> {
    vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::INSTANCES)
        .flags(vk::GeometryFlagsKHR::OPAQUE)
        .geometry(vk::AccelerationStructureGeometryDataKHR {
            instances: vk::AccelerationStructureGeometryInstancesDataKHR::default().array_of_pointers(false).data(data),
        })
}

pub(super) fn dev(a: u64) -> vk::DeviceOrHostAddressConstKHR {
    vk::DeviceOrHostAddressConstKHR { device_address: a }
}

pub(super) fn host(p: &[u8]) -> vk::DeviceOrHostAddressConstKHR {
    vk::DeviceOrHostAddressConstKHR { host_address: p.as_ptr().cast() }
}

/// Scale and move a mesh into the unit cube (instances assume objects of about that size).
pub fn normalized(mesh: &Mesh) -> Mesh {
    let b = mesh.bounds();
    let ext = (b[3] - b[0]).max(b[4] - b[1]).max(b[5] - b[2]).max(1e-20);
    Mesh {
        positions: mesh.positions.iter().map(|p| [(p[0] - b[0]) / ext, (p[1] - b[1]) / ext, (p[2] - b[2]) / ext]).collect(),
        indices: mesh.indices.clone(),
    }
}

/// Vertices moved a little (about 0.2% of the extent), deterministic: the refit's new input.
fn jittered(mesh: &Mesh) -> Vec<u8> {
    let b = mesh.bounds();
    let ext = (b[3] - b[0]).max(b[4] - b[1]).max(b[5] - b[2]);
    let mut out = Vec::with_capacity(mesh.positions.len() * 12);
    for (i, p) in mesh.positions.iter().enumerate() {
        let w = 0.002 * ext * ((i as f32) * 0.37).sin();
        for (k, c) in p.iter().enumerate() {
            out.extend_from_slice(&(c + w * (k as f32 - 1.0)).to_le_bytes());
        }
    }
    out
}

fn device_blas(a: &Arena, mesh: &Mesh) -> Result<(vk::AccelerationStructureKHR, u64), String> {
    let v = a.upload(&mesh.vertex_bytes())?;
    let i = a.upload(&mesh.index_bytes())?;
    let geoms = [triangles(dev(v.address), dev(i.address), mesh.vertex_count().saturating_sub(1) as u32)];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL)
        .flags(vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let n = mesh.triangle_count() as u32;
    let sizes = build_sizes(a.gpu, vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, n);
    let (s, _) = a.structure(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, sizes.acceleration_structure_size, Place::Device)?;
    let scratch = a.buffer(sizes.build_scratch_size, Place::Device)?;
    let info = info.dst_acceleration_structure(s).scratch_data(vk::DeviceOrHostAddressKHR { device_address: scratch.address });
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(n)];
    a.gpu.submit(|cb| {
        // SAFETY: valid infos; buffers live until the wait inside submit.
        unsafe { a.gpu.ext.cmd_build_acceleration_structures(cb, &[info], &[&range]) };
    })?;
    Ok((s, a.address_of(s)))
}

/// Sizes of a device build of `inp`, its destination structure and scratch (owned by `a`), and
/// `info` pointed at them.
pub(super) fn device_target<'i>(
    a: &Arena,
    inp: &Inputs,
    info: vk::AccelerationStructureBuildGeometryInfoKHR<'i>,
) -> Result<(vk::AccelerationStructureBuildSizesInfoKHR<'static>, vk::AccelerationStructureKHR, vk::AccelerationStructureBuildGeometryInfoKHR<'i>), String> {
    let sizes = build_sizes(a.gpu, vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, inp.count);
    let (s, _) = a.structure(inp.ty, sizes.acceleration_structure_size, Place::Device)?;
    let scratch = a.buffer(sizes.build_scratch_size, Place::Device)?;
    Ok((sizes, s, info.dst_acceleration_structure(s).scratch_data(vk::DeviceOrHostAddressKHR { device_address: scratch.address })))
}

pub(super) fn build_sizes(
    gpu: &Gpu,
    ty: vk::AccelerationStructureBuildTypeKHR,
    info: &vk::AccelerationStructureBuildGeometryInfoKHR,
    count: u32,
) -> vk::AccelerationStructureBuildSizesInfoKHR<'static> {
    let mut s = vk::AccelerationStructureBuildSizesInfoKHR::default();
    // SAFETY: valid info and one count per geometry.
    unsafe { gpu.ext.get_acceleration_structure_build_sizes(ty, info, &[count], &mut s) };
    s
}

pub(super) fn prepare(a: &Arena, scene: &Scene) -> Result<Inputs, String> {
    match &scene.kind {
        SceneKind::Mesh(mesh) => {
            let vb = mesh.vertex_bytes();
            let ib = mesh.index_bytes();
            let v = a.upload(&vb)?;
            let i = a.upload(&ib)?;
            let moved = a.upload(&jittered(mesh))?;
            let max_vertex = mesh.vertex_count().saturating_sub(1) as u32;
            Ok(Inputs {
                ty: vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
                count: mesh.triangle_count() as u32,
                geom: triangles(dev(v.address), dev(i.address), max_vertex),
                moved: triangles(dev(moved.address), dev(i.address), max_vertex),
                host_vertices: vb,
                host_indices: ib,
                host_instances: Vec::new(),
                max_vertex,
                blas_addresses: Vec::new(),
                blas_handles: Vec::new(),
                records: Vec::new(),
            })
        }
        SceneKind::Instances { blases, count, seed } => {
            let mut handles = Vec::new();
            let mut addresses = Vec::new();
            for m in blases {
                let (s, addr) = device_blas(a, m)?;
                handles.push(vk::Handle::as_raw(s));
                addresses.push(addr);
            }
            let records = arbor_scene::instance_records(*count, &addresses, *seed);
            let host_records: Vec<InstanceRecord> = records
                .iter()
                .map(|r| InstanceRecord { reference: handles[addresses.iter().position(|x| *x == r.reference).unwrap_or(0)], ..*r })
                .collect();
            let moved: Vec<InstanceRecord> = records
                .iter()
                .enumerate()
                .map(|(k, r)| {
                    let mut r = *r;
                    r.transform[3] += 0.05 * ((k as f32) * 0.7).sin();
                    r.transform[7] += 0.05 * ((k as f32) * 1.3).cos();
                    r
                })
                .collect();
            let d = a.upload(&InstanceRecord::pack(&records))?;
            let m = a.upload(&InstanceRecord::pack(&moved))?;
            Ok(Inputs {
                ty: vk::AccelerationStructureTypeKHR::TOP_LEVEL,
                count: *count as u32,
                geom: instances(dev(d.address)),
                moved: instances(dev(m.address)),
                host_vertices: Vec::new(),
                host_indices: Vec::new(),
                host_instances: InstanceRecord::pack(&host_records),
                max_vertex: 0,
                blas_addresses: addresses,
                blas_handles: handles.iter().map(|&h| vk::Handle::from_raw(h)).collect(),
                records,
            })
        }
    }
}

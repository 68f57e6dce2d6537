//! Scenes and acceleration-structure workloads: device builds (PREFER_FAST_TRACE,
//! PREFER_FAST_BUILD), refit updates, compaction, indirect builds, host builds (plain and deferred,
//! joined by N threads). Each returns one report row; features a driver lacks give a
//! "not supported" row.
use std::time::Instant;

use arbor_scene::{InstanceRecord, Mesh};
use ash::vk;

use crate::vkctx::{payload, Arena, Gpu, Place};

/// A scene: one mesh (a BLAS) or instances over a few meshes (a TLAS over BLASes).
pub struct Scene {
    pub name: String,
    pub kind: SceneKind,
}

pub enum SceneKind {
    Mesh(Mesh),
    Instances { blases: Vec<Mesh>, count: usize, seed: u64 },
}

impl Scene {
    pub fn primitives(&self) -> u64 {
        match &self.kind {
            SceneKind::Mesh(m) => m.triangle_count() as u64,
            SceneKind::Instances { count, .. } => *count as u64,
        }
    }
    pub fn describe(&self) -> String {
        match &self.kind {
            SceneKind::Mesh(m) => format!("{} triangles, {} vertices", m.triangle_count(), m.vertex_count()),
            SceneKind::Instances { blases, count, .. } => format!(
                "{count} instances over {} BLASes ({} triangles)",
                blases.len(),
                blases.iter().map(|m| m.triangle_count()).sum::<usize>()
            ),
        }
    }
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Workload {
    FastTrace,
    FastBuild,
    Update,
    Compact,
    Indirect,
    Host,
    HostDeferred,
    /// Arbor only, not through Vulkan: `arbor::accel::build` called directly (mesh scenes), to
    /// split the driver's time into library build and API overhead.
    LibFastTrace,
    LibFastBuild,
}

impl Workload {
    pub const ALL: [Workload; 7] = [
        Workload::FastTrace,
        Workload::FastBuild,
        Workload::Update,
        Workload::Compact,
        Workload::Indirect,
        Workload::Host,
        Workload::HostDeferred,
    ];
    pub fn name(self) -> &'static str {
        match self {
            Workload::FastTrace => "fast-trace",
            Workload::FastBuild => "fast-build",
            Workload::Update => "update",
            Workload::Compact => "compact",
            Workload::Indirect => "indirect",
            Workload::Host => "host",
            Workload::HostDeferred => "host-deferred",
            Workload::LibFastTrace => "lib-fast-trace",
            Workload::LibFastBuild => "lib-fast-build",
        }
    }
    pub fn parse(s: &str) -> Option<Workload> {
        Workload::ALL.iter().chain(&[Workload::LibFastTrace, Workload::LibFastBuild]).copied().find(|w| w.name() == s)
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stats {
    pub median: f64,
    pub min: f64,
    pub max: f64,
}

impl Stats {
    pub fn of(v: &[f64]) -> Option<Stats> {
        if v.is_empty() {
            return None;
        }
        let mut s = v.to_vec();
        s.sort_by(|a, b| a.total_cmp(b));
        let n = s.len();
        let median = if n % 2 == 1 { s[n / 2] } else { 0.5 * (s[n / 2 - 1] + s[n / 2]) };
        Some(Stats { median, min: s[0], max: s[n - 1] })
    }
}

#[derive(Clone, Debug, PartialEq)]
pub enum Status {
    Ok,
    NotSupported(String),
    Failed(String),
}

/// One line of the report: driver × scene × workload.
#[derive(Clone, Debug)]
pub struct Row {
    pub driver: String,
    pub device: String,
    pub threads: String,
    pub scene: String,
    pub workload: String,
    pub primitives: u64,
    pub status: Status,
    /// "timestamp" (queue timestamps), "fence" (submit → fence wall time) or "host" (host call).
    pub timing: &'static str,
    pub time: Option<Stats>,
    pub wall: Option<Stats>,
    pub repeat: usize,
    pub as_size: u64,
    pub compacted_size: Option<u64>,
    pub scratch_size: u64,
    pub sah: Option<f64>,
    pub nodes: Option<u64>,
    pub leaves: Option<u64>,
    pub note: String,
}

impl Row {
    pub fn mprims_per_s(&self) -> Option<f64> {
        let t = self.time?.median;
        (t > 0.0).then(|| self.primitives as f64 / (t * 1e-3) / 1e6)
    }
}

/// Everything the renderer needs from Arbor's fast-trace build of a scene.
pub struct RenderData {
    /// Payload of the top structure (the BLAS of a mesh scene, or the TLAS).
    pub top: Vec<u8>,
    /// (device address, payload) of each BLAS a TLAS references.
    pub blases: Vec<(u64, Vec<u8>)>,
    /// Meshes in BLAS order (one for a mesh scene).
    pub meshes: Vec<Mesh>,
    /// Instance records (TLAS scenes), references are the BLAS device addresses.
    pub records: Vec<InstanceRecord>,
}

pub struct Options {
    pub repeat: usize,
    pub warmup: usize,
    pub joiners: usize,
    pub metrics: bool,
    /// lib-* rows: also the loaded single-thread baseline and the parallel efficiency.
    pub efficiency: bool,
}

/// Inputs of one scene on one device, uploaded once for all its workloads.
struct Inputs {
    ty: vk::AccelerationStructureTypeKHR,
    count: u32,
    geom: vk::AccelerationStructureGeometryKHR<'static>,
    /// Moved input for refit updates (vertices jittered / instances shifted).
    moved: vk::AccelerationStructureGeometryKHR<'static>,
    /// Host copies for host builds: vertex + index bytes, or instance records with handles.
    host_vertices: Vec<u8>,
    host_indices: Vec<u8>,
    host_instances: Vec<u8>,
    max_vertex: u32,
    // For rendering.
    blas_addresses: Vec<u64>,
    blas_handles: Vec<vk::AccelerationStructureKHR>,
    records: Vec<InstanceRecord>,
}

fn triangles(v: vk::DeviceOrHostAddressConstKHR, i: vk::DeviceOrHostAddressConstKHR, max_vertex: u32) -> vk::AccelerationStructureGeometryKHR<'static> {
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

fn instances(data: vk::DeviceOrHostAddressConstKHR) -> vk::AccelerationStructureGeometryKHR<'static> {
    vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::INSTANCES)
        .flags(vk::GeometryFlagsKHR::OPAQUE)
        .geometry(vk::AccelerationStructureGeometryDataKHR {
            instances: vk::AccelerationStructureGeometryInstancesDataKHR::default().array_of_pointers(false).data(data),
        })
}

fn dev(a: u64) -> vk::DeviceOrHostAddressConstKHR {
    vk::DeviceOrHostAddressConstKHR { device_address: a }
}

fn host(p: &[u8]) -> vk::DeviceOrHostAddressConstKHR {
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
fn device_target<'i>(
    a: &Arena,
    inp: &Inputs,
    info: vk::AccelerationStructureBuildGeometryInfoKHR<'i>,
) -> Result<(vk::AccelerationStructureBuildSizesInfoKHR<'static>, vk::AccelerationStructureKHR, vk::AccelerationStructureBuildGeometryInfoKHR<'i>), String> {
    let sizes = build_sizes(a.gpu, vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, inp.count);
    let (s, _) = a.structure(inp.ty, sizes.acceleration_structure_size, Place::Device)?;
    let scratch = a.buffer(sizes.build_scratch_size, Place::Device)?;
    Ok((sizes, s, info.dst_acceleration_structure(s).scratch_data(vk::DeviceOrHostAddressKHR { device_address: scratch.address })))
}

fn build_sizes(
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

fn prepare(a: &Arena, scene: &Scene) -> Result<Inputs, String> {
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

/// Runs the chosen workloads of one scene on one device. `progress` is called before each.
// One call site (main), which passes its parsed options through.
#[allow(clippy::too_many_arguments)]
pub fn run_scene(
    gpu: &Gpu,
    threads: &str,
    scene: &Scene,
    workloads: &[Workload],
    opts: &Options,
    want_render: bool,
    progress: &mut dyn FnMut(&str),
    render: &mut Option<RenderData>,
) -> Vec<Row> {
    let base = Row {
        driver: gpu.label.clone(),
        device: gpu.name.clone(),
        threads: threads.to_string(),
        scene: scene.name.clone(),
        workload: String::new(),
        primitives: scene.primitives(),
        status: Status::Ok,
        timing: if gpu.caps.timestamps { "timestamp" } else { "fence" },
        time: None,
        wall: None,
        repeat: opts.repeat,
        as_size: 0,
        compacted_size: None,
        scratch_size: 0,
        sah: None,
        nodes: None,
        leaves: None,
        note: String::new(),
    };
    let mut rows = Vec::new();
    if let Some(why) = &gpu.caps.missing {
        for w in workloads {
            progress(w.name());
            rows.push(Row { workload: w.name().into(), status: Status::NotSupported(why.clone()), ..base.clone() });
        }
        return rows;
    }
    let limit = if scene.primitives() > 0 && matches!(scene.kind, SceneKind::Instances { .. }) {
        gpu.caps.max_instance_count
    } else {
        gpu.caps.max_primitive_count
    };
    if scene.primitives() > limit {
        for w in workloads {
            progress(w.name());
            rows.push(Row {
                workload: w.name().into(),
                status: Status::NotSupported(format!("{} primitives > the driver's limit {limit}", scene.primitives())),
                ..base.clone()
            });
        }
        return rows;
    }
    let arena = Arena::new(gpu);
    let inputs = match prepare(&arena, scene) {
        Ok(i) => i,
        Err(e) => {
            for w in workloads {
                progress(w.name());
                rows.push(Row { workload: w.name().into(), status: Status::Failed(format!("inputs: {e}")), ..base.clone() });
            }
            return rows;
        }
    };
    for &w in workloads {
        progress(w.name());
        let mut row = Row { workload: w.name().into(), ..base.clone() };
        let render_here = want_render && w == Workload::FastTrace && render.is_none();
        let r = match w {
            Workload::FastTrace | Workload::FastBuild => device_build(gpu, &inputs, w, opts, &mut row, render_here.then_some(&mut *render), scene),
            Workload::Update => update(gpu, &inputs, opts, &mut row),
            Workload::Compact => compact(gpu, &inputs, opts, &mut row),
            Workload::Indirect => {
                if gpu.caps.indirect_build {
                    indirect(gpu, &inputs, opts, &mut row)
                } else {
                    row.status = Status::NotSupported("accelerationStructureIndirectBuild = false".into());
                    Ok(())
                }
            }
            Workload::LibFastTrace | Workload::LibFastBuild => library_build(gpu, scene, w, opts, &mut row),
            Workload::Host | Workload::HostDeferred => {
                if !gpu.caps.host_commands {
                    row.status = Status::NotSupported("accelerationStructureHostCommands = false".into());
                    Ok(())
                } else if w == Workload::HostDeferred && !gpu.caps.deferred {
                    row.status = Status::NotSupported("no VK_KHR_deferred_host_operations".into());
                    Ok(())
                } else {
                    host_build(gpu, &inputs, w == Workload::HostDeferred, opts, &mut row)
                }
            }
        };
        if let Err(e) = r {
            row.status = Status::Failed(e);
        }
        rows.push(row);
    }
    drop(arena);
    rows
}

fn fill_times(row: &mut Row, times: &[(Option<f64>, f64)]) {
    let wall: Vec<f64> = times.iter().map(|t| t.1).collect();
    let ts: Vec<f64> = times.iter().filter_map(|t| t.0).collect();
    row.wall = Stats::of(&wall);
    if ts.len() == times.len() && !ts.is_empty() && ts.iter().all(|&t| t > 0.0) {
        row.time = Stats::of(&ts);
        row.timing = "timestamp";
    } else {
        row.time = row.wall;
        row.timing = "fence";
    }
}

fn metrics_into(a: &Arena, s: vk::AccelerationStructureKHR, row: &mut Row) -> Result<Vec<u8>, String> {
    let ser = a.serialize(s)?;
    let p = payload(&ser).ok_or("serialization shorter than its header")?;
    match arbor::accel::metrics(p) {
        Some(m) => {
            row.sah = Some(m.sah_cost as f64);
            row.nodes = Some(m.node_count as u64);
            row.leaves = Some(m.leaf_count as u64);
        }
        None => row.note = "serialized payload is not an Arbor structure".into(),
    }
    Ok(p.to_vec())
}

fn flags_of(w: Workload) -> vk::BuildAccelerationStructureFlagsKHR {
    match w {
        Workload::FastBuild => vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD,
        _ => vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE,
    }
}

fn device_build(
    gpu: &Gpu,
    inp: &Inputs,
    w: Workload,
    opts: &Options,
    row: &mut Row,
    render: Option<&mut Option<RenderData>>,
    scene: &Scene,
) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [inp.geom];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(flags_of(w) | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let (sizes, s, info) = device_target(&a, inp, info)?;
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(inp.count)];
    let times = gpu.timed(opts.warmup, opts.repeat, |cb| {
        // SAFETY: valid infos; buffers live until `timed` has waited.
        unsafe { gpu.ext.cmd_build_acceleration_structures(cb, &[info], &[&range]) };
    })?;
    fill_times(row, &times);
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.build_scratch_size;
    row.compacted_size = Some(a.query(s, vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR)?);
    if opts.metrics {
        let top = metrics_into(&a, s, row)?;
        if let Some(slot) = render {
            let meshes = match &scene.kind {
                SceneKind::Mesh(m) => vec![m.clone()],
                SceneKind::Instances { blases, .. } => blases.clone(),
            };
            // The BLASes built by `prepare`, serialized, keyed by the addresses the TLAS references.
            let mut blases = Vec::new();
            for (&h, &addr) in inp.blas_handles.iter().zip(&inp.blas_addresses) {
                let ser = a.serialize(h)?;
                blases.push((addr, payload(&ser).ok_or("short serialization")?.to_vec()));
            }
            *slot = Some(RenderData { top, blases, meshes, records: inp.records.clone() });
        }
    }
    Ok(())
}

fn update(gpu: &Gpu, inp: &Inputs, opts: &Options, row: &mut Row) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [inp.geom];
    let flags = vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE | vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE;
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(flags)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let sizes = build_sizes(gpu, vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, inp.count);
    let (s, _) = a.structure(inp.ty, sizes.acceleration_structure_size, Place::Device)?;
    let scratch = a.buffer(sizes.build_scratch_size.max(sizes.update_scratch_size), Place::Device)?;
    let sd = vk::DeviceOrHostAddressKHR { device_address: scratch.address };
    let build = info.dst_acceleration_structure(s).scratch_data(sd);
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(inp.count)];
    gpu.submit(|cb| {
        // SAFETY: valid infos; buffers live until the wait.
        unsafe { gpu.ext.cmd_build_acceleration_structures(cb, &[build], &[&range]) };
    })?;
    let moved = [inp.moved];
    let upd = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(flags)
        .mode(vk::BuildAccelerationStructureModeKHR::UPDATE)
        .geometries(&moved)
        .src_acceleration_structure(s)
        .dst_acceleration_structure(s)
        .scratch_data(sd);
    let times = gpu.timed(opts.warmup, opts.repeat, |cb| {
        // SAFETY: valid infos (in-place update of a structure built with ALLOW_UPDATE).
        unsafe { gpu.ext.cmd_build_acceleration_structures(cb, &[upd], &[&range]) };
    })?;
    fill_times(row, &times);
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.update_scratch_size;
    row.note = "in place, moved input".into();
    Ok(())
}

fn compact(gpu: &Gpu, inp: &Inputs, opts: &Options, row: &mut Row) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [inp.geom];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let (sizes, s, info) = device_target(&a, inp, info)?;
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(inp.count)];
    gpu.submit(|cb| {
        // SAFETY: valid infos; buffers live until the wait.
        unsafe { gpu.ext.cmd_build_acceleration_structures(cb, &[info], &[&range]) };
    })?;
    let compacted = a.query(s, vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR)?;
    let (c, _) = a.structure(inp.ty, compacted, Place::Device)?;
    let times = gpu.timed(opts.warmup, opts.repeat, |cb| {
        let ci = vk::CopyAccelerationStructureInfoKHR::default().src(s).dst(c).mode(vk::CopyAccelerationStructureModeKHR::COMPACT);
        // SAFETY: valid structures; dst has the compacted size.
        unsafe { gpu.ext.cmd_copy_acceleration_structure(cb, &ci) };
    })?;
    fill_times(row, &times);
    row.as_size = sizes.acceleration_structure_size;
    row.compacted_size = Some(compacted);
    row.scratch_size = 0;
    row.note = "copy COMPACT of the fast-trace structure".into();
    Ok(())
}

fn indirect(gpu: &Gpu, inp: &Inputs, opts: &Options, row: &mut Row) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [inp.geom];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let (sizes, s, info) = device_target(&a, inp, info)?;
    let mut record = [0u8; 16];
    record[..4].copy_from_slice(&inp.count.to_le_bytes());
    let rec = a.upload(&record)?;
    let max = [inp.count];
    let times = gpu.timed(opts.warmup, opts.repeat, |cb| {
        // SAFETY: valid infos; the range record lives in `rec`.
        unsafe { gpu.ext.cmd_build_acceleration_structures_indirect(cb, &[info], &[rec.address], &[16], &[&max]) };
    })?;
    fill_times(row, &times);
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.build_scratch_size;
    row.compacted_size = Some(a.query(s, vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR)?);
    Ok(())
}

fn host_build(gpu: &Gpu, inp: &Inputs, deferred: bool, opts: &Options, row: &mut Row) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [if inp.ty == vk::AccelerationStructureTypeKHR::TOP_LEVEL {
        instances(host(&inp.host_instances))
    } else {
        triangles(host(&inp.host_vertices), host(&inp.host_indices), inp.max_vertex)
    }];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let sizes = build_sizes(gpu, vk::AccelerationStructureBuildTypeKHR::HOST, &info, inp.count);
    let (s, _) = a.structure(inp.ty, sizes.acceleration_structure_size, Place::Host)?;
    let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
    let info = info
        .dst_acceleration_structure(s)
        .scratch_data(vk::DeviceOrHostAddressKHR { host_address: scratch.as_mut_ptr().cast() });
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(inp.count)];
    let mut times = Vec::new();
    // Deferred builds are joined by `joiners` threads started once for the workload (as an
    // application's job system would be), not per build: the timing then covers the driver's
    // deferred operation and its shared work, not thread creation.
    std::thread::scope(|sc| -> Result<(), String> {
        let joiners = deferred.then(|| Joiners::start(sc, gpu, opts.joiners.max(1)));
        for k in 0..opts.warmup + opts.repeat {
            let t0 = Instant::now();
            if let Some(j) = &joiners {
                join_deferred(gpu, &info, &range, j)?;
            } else {
                // SAFETY: valid infos; host memory alive for the call.
                unsafe { gpu.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[info], &[&range]) }
                    .map_err(|e| format!("vkBuildAccelerationStructuresKHR: {e}"))?;
            }
            let ms = t0.elapsed().as_secs_f64() * 1e3;
            if k >= opts.warmup {
                times.push(ms);
            }
        }
        Ok(())
    })?;
    drop(scratch);
    row.time = Stats::of(&times);
    row.wall = row.time;
    row.timing = "host";
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.build_scratch_size;
    let mut v = [0u8; 8];
    // SAFETY: valid structure built with ALLOW_COMPACTION; one u64.
    unsafe {
        gpu.ext
            .write_acceleration_structures_properties(&[s], vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR, &mut v, 8)
            .map_err(|e| format!("vkWriteAccelerationStructuresPropertiesKHR: {e}"))?;
    }
    row.compacted_size = Some(u64::from_le_bytes(v));
    if deferred {
        row.note = format!("deferred, joined by {} threads (started once)", opts.joiners.max(1));
    }
    Ok(())
}

/// Threads that join the deferred operations handed to them (`run`), started once.
struct Joiners {
    ops: Vec<std::sync::mpsc::Sender<u64>>,
    done: std::sync::mpsc::Receiver<()>,
}

impl Joiners {
    fn start<'s>(sc: &'s std::thread::Scope<'s, '_>, gpu: &Gpu, n: usize) -> Joiners {
        let dev = gpu.device.handle();
        let join = gpu.deferred.fp().deferred_operation_join_khr;
        let (done_tx, done) = std::sync::mpsc::channel();
        let ops = (0..n)
            .map(|_| {
                let (tx, rx) = std::sync::mpsc::channel::<u64>();
                let done_tx = done_tx.clone();
                sc.spawn(move || {
                    // Until `Joiners` is dropped: join each operation until it has no more work.
                    for raw in rx {
                        let op = <vk::DeferredOperationKHR as vk::Handle>::from_raw(raw);
                        // SAFETY: a live deferred operation of `dev` (destroyed only after every
                        // joiner reported back).
                        while unsafe { join(dev, op) } == vk::Result::THREAD_IDLE_KHR {}
                        let _ = done_tx.send(());
                    }
                });
                tx
            })
            .collect();
        Joiners { ops, done }
    }

    /// Every thread joins `op`; returns when all of them have come back.
    fn run(&self, op: vk::DeferredOperationKHR) {
        let raw = vk::Handle::as_raw(op);
        let sent = self.ops.iter().filter(|tx| tx.send(raw).is_ok()).count();
        for _ in 0..sent {
            let _ = self.done.recv();
        }
    }
}

/// vkBuildAccelerationStructuresKHR under a deferred operation joined by `joiners`.
fn join_deferred(
    gpu: &Gpu,
    info: &vk::AccelerationStructureBuildGeometryInfoKHR,
    range: &[vk::AccelerationStructureBuildRangeInfoKHR],
    joiners: &Joiners,
) -> Result<(), String> {
    // SAFETY: valid infos; host memory outlives the operation (joined before returning).
    unsafe {
        let op = gpu.deferred.create_deferred_operation(None).map_err(|e| format!("vkCreateDeferredOperationKHR: {e}"))?;
        let ranges = [range.as_ptr()];
        let r = (gpu.ext.fp().build_acceleration_structures_khr)(gpu.device.handle(), op, 1, info, ranges.as_ptr());
        let result = match r {
            vk::Result::OPERATION_DEFERRED_KHR => {
                joiners.run(op);
                gpu.deferred.get_deferred_operation_result(op).map_err(|e| format!("deferred build: {e}"))
            }
            vk::Result::OPERATION_NOT_DEFERRED_KHR | vk::Result::SUCCESS => Ok(()),
            e => Err(format!("vkBuildAccelerationStructuresKHR (deferred): {e}")),
        };
        gpu.deferred.destroy_deferred_operation(op, None);
        result
    }
}

/// `arbor::accel::build` on the host, in this process's rayon pool (RAYON_NUM_THREADS follows
/// --threads): the library's share of Arbor's build time.
fn library_build(gpu: &Gpu, scene: &Scene, w: Workload, opts: &Options, row: &mut Row) -> Result<(), String> {
    use arbor::accel::{self, AsType, BuildDesc, BuildFlags, Geometry, GeometryData, GeometryFlags, GeometryShape, IndexType, VertexFormat};
    if gpu.label != "arbor" {
        row.status = Status::NotSupported("Arbor's library, called directly".into());
        return Ok(());
    }
    let SceneKind::Mesh(mesh) = &scene.kind else {
        row.status = Status::NotSupported("library rows for mesh scenes only".into());
        return Ok(());
    };
    let vb = mesh.vertex_bytes();
    let ib = mesh.index_bytes();
    let max_vertex = mesh.vertex_count().saturating_sub(1) as u32;
    let flags = BuildFlags(
        BuildFlags::ALLOW_COMPACTION | if w == Workload::LibFastBuild { BuildFlags::PREFER_FAST_BUILD } else { BuildFlags::PREFER_FAST_TRACE },
    );
    let shape = GeometryShape::Triangles { format: VertexFormat::R32G32B32Sfloat, index_type: IndexType::U32, max_vertex, has_transform: false };
    let n = mesh.triangle_count() as u32;
    let sizes = accel::build_sizes(AsType::BottomLevel, flags, &[shape], &[n]);
    let geoms = [Geometry {
        flags: GeometryFlags(GeometryFlags::OPAQUE),
        primitive_count: n,
        data: GeometryData::Triangles {
            format: VertexFormat::R32G32B32Sfloat,
            vertices: &vb,
            stride: 12,
            max_vertex,
            index_type: IndexType::U32,
            indices: &ib,
            transform: None,
        },
    }];
    let desc = BuildDesc { ty: AsType::BottomLevel, flags, geometries: &geoms };
    let mut dst = vec![0u8; sizes.acceleration_structure_size as usize];
    let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
    let mut times = Vec::new();
    let mut phases = Vec::new();
    let mut report = None;
    for k in 0..opts.warmup + opts.repeat {
        let t0 = Instant::now();
        let (r, ph) = accel::build_timed(&desc, &accel::NoDevice, &mut dst, &mut scratch).map_err(|e| format!("arbor::accel::build: {e:?}"))?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        if k >= opts.warmup {
            times.push(ms);
            phases.push(ph);
        }
        report = Some(r);
    }
    row.time = Stats::of(&times);
    row.wall = row.time;
    row.timing = "host";
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.build_scratch_size;
    row.compacted_size = report.map(|r| r.used_size);
    row.threads = rayon_threads();
    if let Some(m) = accel::metrics(&dst) {
        row.sah = Some(m.sah_cost as f64);
        row.nodes = Some(m.node_count as u64);
        row.leaves = Some(m.leaf_count as u64);
    }
    // Median of each phase over the timed runs (accel::BuildPhases).
    let med = |f: fn(&accel::BuildPhases) -> f64| {
        let mut v: Vec<f64> = phases.iter().map(f).collect();
        v.sort_by(|a, b| a.total_cmp(b));
        v.get(v.len() / 2).copied().unwrap_or(0.0)
    };
    row.note = format!(
        "arbor::accel::build called directly (no Vulkan); median phases ms: ingest {:.2}; sah {:.2}; leaf data {:.2}; nodes {:.2}",
        med(|p| p.ingest_ms),
        med(|p| p.sah_ms),
        med(|p| p.leaf_data_ms),
        med(|p| p.nodes_ms)
    );
    if opts.efficiency {
        // N builds at once, one per thread, each on its own 1-thread pool with its own buffers:
        // what one core gives while all N are busy (load, power, shared caches), measured now.
        let n = rayon::current_num_threads().max(1);
        let (dst_len, scratch_len) = (sizes.acceleration_structure_size as usize, sizes.build_scratch_size as usize);
        let desc = &desc;
        let medians: Vec<Result<f64, String>> = std::thread::scope(|s| {
            let handles: Vec<_> = (0..n)
                .map(|_| {
                    s.spawn(move || -> Result<f64, String> {
                        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().map_err(|e| e.to_string())?;
                        let (mut dst, mut scratch) = (vec![0u8; dst_len], vec![0u8; scratch_len]);
                        let mut t = Vec::new();
                        for k in 0..opts.warmup + opts.repeat {
                            let t0 = Instant::now();
                            pool.install(|| accel::build(desc, &accel::NoDevice, &mut dst, &mut scratch)).map_err(|e| format!("arbor::accel::build: {e:?}"))?;
                            if k >= opts.warmup {
                                t.push(t0.elapsed().as_secs_f64() * 1e3);
                            }
                        }
                        Stats::of(&t).map(|s| s.median).ok_or_else(|| "no timed runs".to_string())
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap_or_else(|_| Err("a baseline build panicked".into()))).collect()
        });
        let medians = medians.into_iter().collect::<Result<Vec<f64>, String>>()?;
        if let (Some(base), Some(t)) = (Stats::of(&medians), row.time) {
            row.note.push_str(&format!(
                "; efficiency {:.0} % against {n} concurrent 1-thread builds (median of their medians {:.2} ms, min {:.2}, max {:.2})",
                100.0 * base.median / (n as f64 * t.median),
                base.median,
                base.min,
                base.max
            ));
        }
    }
    Ok(())
}

fn rayon_threads() -> String {
    std::env::var("RAYON_NUM_THREADS").ok().unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get().to_string()).unwrap_or_default())
}

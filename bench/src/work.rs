//! Scenes and acceleration-structure workloads: device builds (PREFER_FAST_TRACE,
//! PREFER_FAST_BUILD), refit updates, compaction, indirect builds, host builds (plain and deferred,
//! joined by N threads), Arbor's library called directly, ray-query trace workloads and
//! compute-shader workloads. Each returns one report row; features a driver lacks give a
//! "not supported" row.
pub mod clusters;
pub mod compute;
mod device;
mod host;
mod inputs;
mod library;
mod ptlas;
pub mod trace;

use arbor_scene::{InstanceRecord, Mesh};

use crate::vkctx::{Arena, Gpu};

pub use inputs::normalized;

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
    /// Ray queries from a compute shader over the scene's TLAS: primary camera rays, random rays.
    TracePrimary,
    TraceRandom,
    /// Compute shaders (once per device, no scene): see `compute`.
    ComputeAlu,
    ComputeMemory,
    ComputeDivergent,
    ComputeFirstDispatch,
    /// VK_NV_cluster_acceleration_structure over the mesh cut into clusters (`clusters`), and
    /// the KHR BLAS build (PREFER_FAST_BUILD) of the same triangles to compare with.
    ClasBuild,
    ClasInstantiate,
    ClusterBlas,
    ClasMoveCompact,
    KhrBlas,
    /// VK_NV_partitioned_acceleration_structure (instance scenes): see `ptlas`.
    PtlasBuild,
    PtlasUpdate1pct,
    PtlasKhrTlas,
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
    /// The trace workloads (not in ALL: they measure rays, not builds).
    pub const TRACE: [Workload; 2] = [Workload::TracePrimary, Workload::TraceRandom];
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
            Workload::TracePrimary => "trace-primary",
            Workload::TraceRandom => "trace-random",
            Workload::ComputeAlu => "compute-alu",
            Workload::ComputeMemory => "compute-memory",
            Workload::ComputeDivergent => "compute-divergent",
            Workload::ComputeFirstDispatch => "compute-first-dispatch",
            Workload::ClasBuild => "clas-build",
            Workload::ClasInstantiate => "clas-instantiate",
            Workload::ClusterBlas => "cluster-blas",
            Workload::ClasMoveCompact => "clas-move-compact",
            Workload::KhrBlas => "khr-blas",
            Workload::PtlasBuild => "ptlas-build",
            Workload::PtlasUpdate1pct => "ptlas-update-1pct",
            Workload::PtlasKhrTlas => "ptlas-khr-tlas",
        }
    }
    pub fn parse(s: &str) -> Option<Workload> {
        Workload::ALL
            .iter()
            .chain(&[Workload::LibFastTrace, Workload::LibFastBuild])
            .chain(&Workload::TRACE)
            .chain(&Workload::COMPUTE)
            .chain(&Workload::CLUSTERS)
            .chain(&Workload::PTLAS)
            .copied()
            .find(|w| w.name() == s)
    }
    /// The compute-shader workloads ("--workloads compute").
    pub const COMPUTE: [Workload; 4] = [Workload::ComputeAlu, Workload::ComputeMemory, Workload::ComputeDivergent, Workload::ComputeFirstDispatch];
    /// The cluster workloads ("--workloads clusters").
    pub const CLUSTERS: [Workload; 5] = [Workload::ClasBuild, Workload::ClasInstantiate, Workload::ClusterBlas, Workload::ClasMoveCompact, Workload::KhrBlas];
    /// The partitioned-TLAS workloads ("--workloads ptlas"; not in ALL).
    pub const PTLAS: [Workload; 3] = [Workload::PtlasBuild, Workload::PtlasUpdate1pct, Workload::PtlasKhrTlas];
    pub fn is_compute(self) -> bool {
        Workload::COMPUTE.contains(&self)
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
    /// Trace workloads: rays per dispatch (0 for the others).
    pub rays: u64,
    /// Trace workloads under --compare: the rays and their hits.
    pub hits: Option<std::sync::Arc<trace::Capture>>,
}

impl Row {
    pub fn mprims_per_s(&self) -> Option<f64> {
        let t = self.time?.median;
        (t > 0.0 && self.rays == 0).then(|| self.primitives as f64 / (t * 1e-3) / 1e6)
    }
    pub fn mrays_per_s(&self) -> Option<f64> {
        let t = self.time?.median;
        (t > 0.0 && self.rays > 0).then(|| self.rays as f64 / (t * 1e-3) / 1e6)
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
    /// Trace workloads: rays per dispatch; keep the hits in the row (--compare).
    pub rays: usize,
    pub keep_hits: bool,
    /// Invocations of compute-alu and compute-divergent.
    pub compute_invocations: u64,
    /// Bytes compute-memory streams through.
    pub compute_memory_bytes: u64,
    /// Partitions of the ptlas workloads.
    pub partitions: u32,
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
    let base = base_row(gpu, threads, scene, opts);
    if let Some(why) = &gpu.caps.missing {
        return same_status(workloads, progress, &base, Status::NotSupported(why.clone()));
    }
    let limit = if scene.primitives() > 0 && matches!(scene.kind, SceneKind::Instances { .. }) {
        gpu.caps.max_instance_count
    } else {
        gpu.caps.max_primitive_count
    };
    if scene.primitives() > limit {
        let why = format!("{} primitives > the driver's limit {limit}", scene.primitives());
        return same_status(workloads, progress, &base, Status::NotSupported(why));
    }
    let arena = Arena::new(gpu);
    let inputs = match inputs::prepare(&arena, scene) {
        Ok(i) => i,
        Err(e) => return same_status(workloads, progress, &base, Status::Failed(format!("inputs: {e}"))),
    };
    let mut rows = Vec::new();
    for &w in workloads {
        progress(w.name());
        let mut row = Row { workload: w.name().into(), ..base.clone() };
        let render_here = want_render && w == Workload::FastTrace && render.is_none();
        if let Err(e) = run_workload(gpu, &inputs, scene, w, opts, &mut row, render_here.then_some(&mut *render)) {
            row.status = Status::Failed(e);
        }
        rows.push(row);
    }
    drop(arena);
    rows
}

/// The compute workloads among `workloads` on one device: one row each, scene "-".
pub fn run_compute(gpu: &Gpu, threads: &str, workloads: &[Workload], opts: &Options, progress: &mut dyn FnMut(&str)) -> Vec<Row> {
    let scene = Scene { name: "-".into(), kind: SceneKind::Instances { blases: Vec::new(), count: 0, seed: 0 } };
    let base = Row { timing: "fence", ..base_row(gpu, threads, &scene, opts) };
    let mut rows = Vec::new();
    for &w in workloads.iter().filter(|w| w.is_compute()) {
        progress(w.name());
        let mut row = Row { workload: w.name().into(), ..base.clone() };
        if let Some(status) = compute::unsupported(gpu) {
            row.status = status;
        } else if let Err(e) = compute::run(gpu, w, opts, &mut row) {
            row.status = Status::Failed(e);
        }
        rows.push(row);
    }
    rows
}

/// The row every workload of this scene and device starts from.
fn base_row(gpu: &Gpu, threads: &str, scene: &Scene, opts: &Options) -> Row {
    Row {
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
        rays: 0,
        hits: None,
    }
}

/// One row per workload, all with `status`: the scene cannot run on this device at all.
fn same_status(workloads: &[Workload], progress: &mut dyn FnMut(&str), base: &Row, status: Status) -> Vec<Row> {
    workloads
        .iter()
        .map(|w| {
            progress(w.name());
            Row { workload: w.name().into(), status: status.clone(), ..base.clone() }
        })
        .collect()
}

/// One workload into `row`; a feature the driver lacks sets the row's status instead.
fn run_workload(
    gpu: &Gpu,
    inputs: &inputs::Inputs,
    scene: &Scene,
    w: Workload,
    opts: &Options,
    row: &mut Row,
    render: Option<&mut Option<RenderData>>,
) -> Result<(), String> {
    match w {
        Workload::FastTrace | Workload::FastBuild => device::device_build(gpu, inputs, w, opts, row, render, scene),
        Workload::Update => device::update(gpu, inputs, opts, row),
        Workload::Compact => device::compact(gpu, inputs, opts, row),
        Workload::Indirect => {
            if gpu.caps.indirect_build {
                device::indirect(gpu, inputs, opts, row)
            } else {
                row.status = Status::NotSupported("accelerationStructureIndirectBuild = false".into());
                Ok(())
            }
        }
        Workload::LibFastTrace | Workload::LibFastBuild => library::library_build(gpu, scene, w, opts, row),
        Workload::TracePrimary | Workload::TraceRandom => trace::trace(gpu, inputs, scene, w, opts, row),
        Workload::ClasBuild | Workload::ClasInstantiate | Workload::ClusterBlas | Workload::ClasMoveCompact => clusters::run(gpu, scene, w, opts, row),
        Workload::KhrBlas => device::device_build(gpu, inputs, Workload::FastBuild, opts, row, None, scene),
        Workload::PtlasBuild | Workload::PtlasUpdate1pct | Workload::PtlasKhrTlas => ptlas::run(gpu, inputs, w, opts, row),
        Workload::ComputeAlu | Workload::ComputeMemory | Workload::ComputeDivergent | Workload::ComputeFirstDispatch => {
            Err("compute workloads run once per device (run_compute)".into())
        }
        Workload::Host | Workload::HostDeferred => {
            if !gpu.caps.host_commands {
                row.status = Status::NotSupported("accelerationStructureHostCommands = false".into());
                Ok(())
            } else if w == Workload::HostDeferred && !gpu.caps.deferred {
                row.status = Status::NotSupported("no VK_KHR_deferred_host_operations".into());
                Ok(())
            } else {
                host::host_build(gpu, inputs, w == Workload::HostDeferred, opts, row)
            }
        }
    }
}

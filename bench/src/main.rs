//! arbor-bench: runs acceleration-structure workloads through the Vulkan loader on any installed
//! driver (Arbor by default: the library built beside this program) and reports build times,
//! sizes and, for Arbor, SAH cost and node counts. `arbor-bench --help` lists the options.
mod compare;
mod png;
mod render;
mod report;
mod vkctx;
mod work;

use std::ffi::CStr;
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};

use ash::vk;

use work::{Scene, SceneKind, Workload};

const BUNNY_PLY: &[u8] = include_bytes!("../../data/bunny.ply");

const HELP: &str = "\
arbor-bench: acceleration-structure workloads through the Vulkan loader, on any installed driver

USAGE: arbor-bench [OPTIONS]

Drivers (default: arbor, the libvulkan_arbor.so beside this program):
  --driver LIST        arbor, lavapipe, nvidia or all (comma-separated or repeated);
                       drivers that are not installed are skipped with a message
  --icd PATH           another driver's manifest (repeatable)
  --threads N          ARBOR_THREADS for Arbor (its worker pool size)
  --list               list the devices found and exit
  --compare DRIVER     trace the same rays on arbor and on DRIVER (lavapipe, nvidia) and compare
                       them hit by hit (default workloads: trace-primary, trace-random); exits 3
                       when any ray mismatches (ties, equally close hits, and edge cases,
                       a hit within 1e-3 of an open edge, are no mismatch)
  --compare-show N     mismatching rays printed per comparison (default 10)
Scenes (default: bunny):
  --scene LIST         bunny (embedded Stanford bunny), soup (random triangle soup), terrain
                       (tessellated heightfield), instances (TLAS of instances over 3 BLASes),
                       clusters (the full dragon of data/, for the cluster workloads), all;
                       ptlas (the same BLASes, --ptlas-instances instances; not in all)
  --mesh FILE          a PLY (ASCII/binary) or OBJ mesh, gzip allowed (repeatable)
  --soup N             triangles of the soup (default 1000000)
  --terrain N          terrain grid cells per side, 2 triangles each (default 512)
  --instances N        instances of the TLAS scene (default 10000)
  --ptlas-instances N  instances of the ptlas scene (default 1000000)
  --partitions N       partitions of the ptlas workloads (default 1024)
Workloads (default: all; unsupported ones are reported as \"not supported\"):
  --workloads LIST     fast-trace, fast-build, update, compact, indirect, host, host-deferred;
                       also lib-fast-trace, lib-fast-build (Arbor: arbor::accel::build called
                       directly, no Vulkan: the library's share of the driver's time);
                       trace-primary, trace-random (ray queries from a compute shader over the
                       scene's TLAS, Mrays/s; not in the default set)
  --rays N             rays per trace workload (default 1000000)
                       clas-build, clas-instantiate, cluster-blas, clas-move-compact, khr-blas
                       or clusters (all five): VK_NV_cluster_acceleration_structure over the
                       mesh cut into 128-triangle clusters, and the KHR BLAS (PREFER_FAST_BUILD)
                       of the same triangles; not in the default set
                       ptlas-build, ptlas-update-1pct, ptlas-khr-tlas or ptlas (all three):
                       VK_NV_partitioned_acceleration_structure over an instance scene: a build
                       from scratch, 1 % of the instances rewritten in place, and the KHR TLAS
                       build of the same instances (not in the default set)
                       compute-alu, compute-memory, compute-divergent, compute-first-dispatch
                       or compute (all four): compute shaders, once per driver, no scene;
                       the Mprim/s column is then M invocations/s
  --invocations N      invocations of compute-alu and compute-divergent (default 262144)
  --memory-mib N       MiB compute-memory reads and writes (default 64)
  --repeat N           timed runs per workload (default 5), after --warmup N (default 1)
  --joiners N          threads joining deferred host builds (default: all cores)
  --no-metrics         skip Arbor's serialize + SAH/node metrics
  --efficiency         lib-* rows: also time N concurrent 1-thread builds (N = the pool size),
                       each with its own buffers, and note the parallel efficiency against
                       their median (the cores' speed under the same load; needs N times the
                       memory of one build)
Output:
  --json FILE          results as JSON        --csv FILE   results as CSV
  --svg FILE           chart: build time and compacted size by driver and scene
  --render FILE.png    Arbor only: primary rays through the built fast-trace structure
  --render-scene NAME  scene to render (default: the first)
  --render-size WxH    default 480x360
  --quiet              no progress on stderr
";

struct Args {
    drivers: Vec<String>,
    icds: Vec<PathBuf>,
    threads: Option<usize>,
    list: bool,
    compare: Option<String>,
    compare_show: usize,
    rays: usize,
    scenes: Vec<String>,
    meshes: Vec<PathBuf>,
    soup: usize,
    terrain: u32,
    instances: usize,
    ptlas_instances: usize,
    partitions: u32,
    workloads: Vec<Workload>,
    repeat: usize,
    warmup: usize,
    joiners: usize,
    metrics: bool,
    efficiency: bool,
    compute_invocations: u64,
    compute_memory_mib: u64,
    json: Option<PathBuf>,
    csv: Option<PathBuf>,
    svg: Option<PathBuf>,
    render: Option<PathBuf>,
    render_scene: Option<String>,
    render_size: (u32, u32),
    quiet: bool,
}

fn parse_args(argv: &[String]) -> Result<Args, String> {
    let mut a = Args::defaults();
    let mut it = argv.iter();
    while let Some(arg) = it.next() {
        let (flag, inline) = match arg.split_once('=') {
            Some((f, v)) if f.starts_with("--") => (f.to_string(), Some(v.to_string())),
            _ => (arg.clone(), None),
        };
        let mut value = |name: &str| -> Result<String, String> {
            inline.clone().or_else(|| it.next().cloned()).ok_or_else(|| format!("{name} needs a value"))
        };
        let known = a.driver_option(&flag, &mut value)?
            || a.scene_option(&flag, &mut value)?
            || a.workload_option(&flag, &mut value)?
            || a.output_option(&flag, &mut value)?;
        if !known {
            return Err(format!("unknown option {flag} (see --help)"));
        }
    }
    a.complete()?;
    Ok(a)
}

/// An option's value, from `--flag=value` or the next argument; the name is for the error.
type Value<'v> = dyn FnMut(&str) -> Result<String, String> + 'v;

fn list(v: &str) -> Vec<String> {
    v.split(',').map(|s| s.trim().to_string()).filter(|s| !s.is_empty()).collect()
}

fn num(name: &str, v: String) -> Result<usize, String> {
    v.parse::<usize>().map_err(|_| format!("{name}: not a number: {v}"))
}

// Each `*_option` takes the options of one group of --help: whether `flag` was one of them.
impl Args {
    fn defaults() -> Args {
        let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
        Args {
            drivers: Vec::new(),
            icds: Vec::new(),
            threads: None,
            list: false,
            compare: None,
            compare_show: 10,
            rays: 1_000_000,
            scenes: Vec::new(),
            meshes: Vec::new(),
            soup: 1_000_000,
            terrain: 512,
            instances: 10_000,
            ptlas_instances: 1_000_000,
            partitions: 1024,
            workloads: Vec::new(),
            repeat: 5,
            warmup: 1,
            joiners: cores,
            metrics: true,
            efficiency: false,
            compute_invocations: 1 << 18,
            compute_memory_mib: 64,
            json: None,
            csv: None,
            svg: None,
            render: None,
            render_scene: None,
            render_size: (480, 360),
            quiet: false,
        }
    }

    fn driver_option(&mut self, flag: &str, value: &mut Value) -> Result<bool, String> {
        match flag {
            "--driver" => self.drivers.extend(list(&value("--driver")?)),
            "--icd" => self.icds.push(PathBuf::from(value("--icd")?)),
            "--threads" => self.threads = Some(num("--threads", value("--threads")?)?.max(1)),
            "--list" => self.list = true,
            "--compare" => self.compare = Some(value("--compare")?),
            "--compare-show" => self.compare_show = num("--compare-show", value("--compare-show")?)?,
            _ => return Ok(false),
        }
        Ok(true)
    }

    fn scene_option(&mut self, flag: &str, value: &mut Value) -> Result<bool, String> {
        match flag {
            "--scene" => self.scenes.extend(list(&value("--scene")?)),
            "--mesh" => self.meshes.push(PathBuf::from(value("--mesh")?)),
            "--soup" => self.soup = num("--soup", value("--soup")?)?.max(1),
            "--terrain" => self.terrain = num("--terrain", value("--terrain")?)?.max(1) as u32,
            "--instances" => self.instances = num("--instances", value("--instances")?)?.max(1),
            "--ptlas-instances" => self.ptlas_instances = num("--ptlas-instances", value("--ptlas-instances")?)?.max(1),
            "--partitions" => self.partitions = num("--partitions", value("--partitions")?)?.clamp(1, u32::MAX as usize) as u32,
            _ => return Ok(false),
        }
        Ok(true)
    }

    fn workload_option(&mut self, flag: &str, value: &mut Value) -> Result<bool, String> {
        match flag {
            "--workloads" | "--workload" => {
                for w in list(&value("--workloads")?) {
                    if w == "all" {
                        self.workloads.extend(Workload::ALL);
                    } else if w == "compute" {
                        self.workloads.extend(Workload::COMPUTE);
                    } else if w == "clusters" {
                        self.workloads.extend(Workload::CLUSTERS);
                    } else if w == "ptlas" {
                        self.workloads.extend(Workload::PTLAS);
                    } else {
                        self.workloads.push(Workload::parse(&w).ok_or_else(|| format!("unknown workload {w}"))?);
                    }
                }
            }
            "--repeat" => self.repeat = num("--repeat", value("--repeat")?)?.max(1),
            "--warmup" => self.warmup = num("--warmup", value("--warmup")?)?,
            "--rays" => self.rays = num("--rays", value("--rays")?)?.max(1),
            "--joiners" => self.joiners = num("--joiners", value("--joiners")?)?.max(1),
            "--no-metrics" => self.metrics = false,
            "--efficiency" => self.efficiency = true,
            "--invocations" => self.compute_invocations = num("--invocations", value("--invocations")?)?.max(1) as u64,
            "--memory-mib" => self.compute_memory_mib = num("--memory-mib", value("--memory-mib")?)?.max(1) as u64,
            _ => return Ok(false),
        }
        Ok(true)
    }

    fn output_option(&mut self, flag: &str, value: &mut Value) -> Result<bool, String> {
        match flag {
            "-h" | "--help" => {
                print!("{HELP}");
                std::process::exit(0);
            }
            "--json" => self.json = Some(PathBuf::from(value("--json")?)),
            "--csv" => self.csv = Some(PathBuf::from(value("--csv")?)),
            "--svg" => self.svg = Some(PathBuf::from(value("--svg")?)),
            "--render" => self.render = Some(PathBuf::from(value("--render")?)),
            "--render-scene" => self.render_scene = Some(value("--render-scene")?),
            "--render-size" => {
                let v = value("--render-size")?;
                let (w, h) = v.split_once('x').ok_or("--render-size WxH")?;
                let w: u32 = w.parse().map_err(|_| "--render-size WxH")?;
                let h: u32 = h.parse().map_err(|_| "--render-size WxH")?;
                self.render_size = (w.clamp(1, 8192), h.clamp(1, 8192));
            }
            "--quiet" | "-q" => self.quiet = true,
            _ => return Ok(false),
        }
        Ok(true)
    }

    /// The defaults that depend on what was given (workloads, drivers, scenes), and "all".
    fn complete(&mut self) -> Result<(), String> {
        if let Some(other) = &self.compare {
            if other == "arbor" || !["lavapipe", "nvidia"].contains(&other.as_str()) {
                return Err(format!("--compare {other}: lavapipe or nvidia"));
            }
            for d in ["arbor".to_string(), other.clone()] {
                if !self.drivers.contains(&d) {
                    self.drivers.push(d);
                }
            }
            if self.workloads.is_empty() {
                self.workloads.extend(work::Workload::TRACE);
            }
        }
        if self.workloads.is_empty() {
            self.workloads.extend(Workload::ALL);
        }
        self.workloads.dedup();
        if self.drivers.is_empty() && self.icds.is_empty() {
            self.drivers.push("arbor".into());
        }
        if self.drivers.iter().any(|d| d == "all") {
            self.drivers = vec!["arbor".into(), "lavapipe".into(), "nvidia".into()];
        }
        for d in &self.drivers {
            if !["arbor", "lavapipe", "nvidia"].contains(&d.as_str()) {
                return Err(format!("unknown driver {d} (arbor, lavapipe, nvidia, all; or --icd PATH)"));
            }
        }
        if self.scenes.is_empty() && self.meshes.is_empty() {
            self.scenes.push("bunny".into());
        }
        if self.scenes.iter().any(|s| s == "all") {
            self.scenes = vec!["bunny".into(), "soup".into(), "terrain".into(), "instances".into()];
        }
        Ok(())
    }
}

/// Writes a manifest for the libvulkan_arbor.so beside this program (target/<profile>/).
fn arbor_manifest() -> Option<PathBuf> {
    let exe = std::env::current_exe().ok()?;
    let dir = exe.parent()?;
    let lib = dir.join("libvulkan_arbor.so");
    if !lib.exists() {
        return None;
    }
    let json = format!(
        "{{\"file_format_version\":\"1.0.1\",\"ICD\":{{\"library_path\":{},\"api_version\":\"1.1.281\",\"library_arch\":\"64\"}}}}",
        report::json_str(&lib.display().to_string())
    );
    [dir.join("arbor_icd.json"), std::env::temp_dir().join(format!("arbor_icd_{}.json", std::process::id()))]
        .into_iter()
        .find(|path| std::fs::write(path, &json).is_ok())
}

fn first_existing(paths: &[&str]) -> Option<PathBuf> {
    paths.iter().map(PathBuf::from).find(|p| p.exists())
}

fn manifest_for(driver: &str) -> Result<PathBuf, String> {
    match driver {
        "arbor" => arbor_manifest().ok_or_else(|| "libvulkan_arbor.so not found beside arbor-bench (cargo build --release --workspace)".to_string()),
        "lavapipe" => first_existing(&[
            "/usr/share/vulkan/icd.d/lvp_icd.json",
            "/usr/share/vulkan/icd.d/lvp_icd.x86_64.json",
            "/usr/local/share/vulkan/icd.d/lvp_icd.json",
            "/etc/vulkan/icd.d/lvp_icd.json",
        ])
        .ok_or_else(|| "lavapipe is not installed (apt-get install mesa-vulkan-drivers; see docs/BENCHMARKS.md)".to_string()),
        "nvidia" => first_existing(&[
            "/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json",
            "/usr/share/vulkan/icd.d/nvidia_icd.json",
            "/etc/vulkan/icd.d/nvidia_icd.json",
            "/usr/share/vulkan/icd.d/nvidia_icd.x86_64.json",
        ])
        .ok_or_else(|| "NVIDIA's Vulkan driver is not installed".to_string()),
        _ => Err(format!("unknown driver {driver}")),
    }
}

/// The report's name for a device.
fn classify(p: &vk::PhysicalDeviceProperties, name: &str) -> String {
    if name.contains("Arbor") {
        "arbor".into()
    } else if name.contains("llvmpipe") {
        "lavapipe".into()
    } else if p.vendor_id == 0x10DE {
        "nvidia".into()
    } else {
        name.split_whitespace().next().unwrap_or("device").to_ascii_lowercase()
    }
}

fn mesh_scene_name(path: &Path) -> String {
    let n = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "mesh".into());
    let n = n.strip_suffix(".gz").unwrap_or(&n).to_string();
    n.strip_suffix(".ply").or_else(|| n.strip_suffix(".obj")).unwrap_or(&n).to_string()
}

fn load_scenes(a: &Args) -> Result<Vec<Scene>, String> {
    let bunny = || arbor_scene::parse_ply(BUNNY_PLY).map_err(|e| format!("embedded bunny: {e}"));
    let mut out = Vec::new();
    for s in &a.scenes {
        let kind = match s.as_str() {
            "bunny" => SceneKind::Mesh(bunny()?),
            "soup" => SceneKind::Mesh(arbor_scene::random_soup(a.soup, 1)),
            "terrain" => SceneKind::Mesh(arbor_scene::terrain(a.terrain)),
            "instances" => SceneKind::Instances {
                blases: vec![work::normalized(&bunny()?), arbor_scene::terrain(64), arbor_scene::random_soup(4096, 7)],
                count: a.instances,
                seed: 1,
            },
            // The full dragon, for the cluster workloads (cut into clusters by those).
            "clusters" => SceneKind::Mesh(arbor_scene::load(concat!(env!("CARGO_MANIFEST_DIR"), "/../data/dragon_vrip.ply.gz")).map_err(|e| format!("dragon: {e}"))?),
            "ptlas" => SceneKind::Instances {
                blases: vec![work::normalized(&bunny()?), arbor_scene::terrain(64), arbor_scene::random_soup(4096, 7)],
                count: a.ptlas_instances,
                seed: 1,
            },
            other => return Err(format!("unknown scene {other} (bunny, soup, terrain, instances, clusters, ptlas, all; or --mesh FILE)")),
        };
        out.push(Scene { name: s.clone(), kind });
    }
    for p in &a.meshes {
        let m = arbor_scene::load(p).map_err(|e| format!("{}: {e}", p.display()))?;
        if m.triangle_count() == 0 {
            return Err(format!("{}: no triangles", p.display()));
        }
        out.push(Scene { name: mesh_scene_name(p), kind: SceneKind::Mesh(m) });
    }
    Ok(out)
}

fn main() {
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let args = match parse_args(&argv) {
        Ok(a) => a,
        Err(e) => {
            eprintln!("arbor-bench: {e}");
            std::process::exit(2);
        }
    };
    match run(&args, &argv) {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            eprintln!("arbor-bench: {e}");
            std::process::exit(1);
        }
    }
}

/// Returns the exit status: 1 when any workload failed, 3 when --compare found mismatches.
fn run(args: &Args, argv: &[String]) -> Result<i32, String> {
    let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let arbor_threads = set_threads(args, cores);
    let (joined, wanted) = select_drivers(args)?;
    let scene_work = args.workloads.iter().any(|w| !w.is_compute());
    let scenes = if args.list || !scene_work { Vec::new() } else { load_scenes(args)? };

    // SAFETY: loading the system Vulkan loader.
    let entry = unsafe { ash::Entry::load() }.map_err(|e| format!("cannot load libvulkan.so.1 ({e}); install libvulkan1"))?;
    // 1.2: the trace shader is SPIR-V 1.5, and VK_KHR_ray_query needs SPIR-V 1.4.
    let app = vk::ApplicationInfo::default().application_name(c"arbor-bench").api_version(vk::API_VERSION_1_2);
    // SAFETY: valid create info.
    let instance = unsafe { entry.create_instance(&vk::InstanceCreateInfo::default().application_info(&app), None) }
        .map_err(|e| format!("vkCreateInstance: {e} (manifests: {})", joined.to_string_lossy()))?;
    let devices = find_devices(&instance, &wanted)?;
    if args.list {
        for (label, pd) in &devices {
            println!("{label}: {}", device_name(&instance, *pd));
        }
        // SAFETY: no child objects.
        unsafe { instance.destroy_instance(None) };
        return Ok(0);
    }
    let mut meta = report::Meta {
        command: std::iter::once("arbor-bench".to_string()).chain(argv.iter().cloned()).collect::<Vec<_>>().join(" "),
        unix_time: std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0),
        host_cpus: cores,
        drivers: Vec::new(),
        scenes: scenes.iter().map(|s| (s.name.clone(), s.primitives(), s.describe())).collect(),
    };
    let render_scene = args.render_scene.clone().or_else(|| scenes.first().map(|s| s.name.clone()));
    let measured = measure(args, &instance, &devices, &scenes, arbor_threads, render_scene.as_ref(), &mut meta);
    // SAFETY: every device was destroyed.
    unsafe { instance.destroy_instance(None) };

    print!("{}", report::table(&measured.rows));
    let comparisons = match &args.compare {
        Some(other) => compare_drivers(&measured.rows, other, args.compare_show),
        None => Vec::new(),
    };
    let render_failed = write_outputs(args, &meta, &scenes, &measured, render_scene, &comparisons)?;
    Ok(if measured.failed || render_failed {
        1
    } else if comparisons.iter().any(|c| c.mismatches > 0) {
        3
    } else {
        0
    })
}

/// Arbor's trace rows against `other`'s of the same scene and workload, printed below the table.
fn compare_drivers(rows: &[work::Row], other: &str, show: usize) -> Vec<compare::Comparison> {
    let mut out = Vec::new();
    for a in rows.iter().filter(|r| r.driver == "arbor") {
        let Some(ha) = &a.hits else { continue };
        let Some(b) = rows.iter().find(|r| r.driver == other && r.scene == a.scene && r.workload == a.workload) else {
            println!("compare: no {other} row for {} {}", a.scene, a.workload);
            continue;
        };
        let Some(hb) = &b.hits else {
            println!("compare: {other} did not trace {} {} ({:?})", a.scene, a.workload, b.status);
            continue;
        };
        let mut c = compare::compare(&ha.rays, &ha.hits, &hb.hits, show);
        c.scene = a.scene.clone();
        c.workload = a.workload.clone();
        c.other = other.to_string();
        print!("{}", c.text());
        out.push(c);
    }
    out
}

/// --threads into the environment Arbor and this process's rayon pool read; returns the size of
/// Arbor's worker pool.
fn set_threads(args: &Args, cores: usize) -> usize {
    if let Some(t) = args.threads {
        // SAFETY: single-threaded here, before the loader and any driver are loaded.
        unsafe {
            std::env::set_var("ARBOR_THREADS", t.to_string());
            // The lib-* workloads call arbor::accel in this process's rayon pool.
            std::env::set_var("RAYON_NUM_THREADS", t.to_string());
        }
    }
    std::env::var("ARBOR_THREADS").ok().and_then(|v| v.parse::<usize>().ok()).unwrap_or(cores)
}

/// The manifests of the drivers asked for, set as the loader's only drivers: the joined list,
/// and the named drivers that were found, in their order.
fn select_drivers(args: &Args) -> Result<(std::ffi::OsString, Vec<String>), String> {
    let mut manifests = Vec::new();
    let mut wanted = Vec::new();
    for d in &args.drivers {
        match manifest_for(d) {
            Ok(m) => {
                manifests.push(m);
                wanted.push(d.clone());
            }
            Err(e) => eprintln!("arbor-bench: skipping {d}: {e}"),
        }
    }
    for m in &args.icds {
        if !m.exists() {
            return Err(format!("--icd {}: no such file", m.display()));
        }
        manifests.push(m.clone());
    }
    if manifests.is_empty() {
        return Err("no driver to run".into());
    }
    let joined = std::env::join_paths(&manifests).map_err(|e| e.to_string())?;
    // SAFETY: single-threaded here, before the loader is opened.
    unsafe {
        std::env::set_var("VK_ICD_FILENAMES", &joined);
        std::env::set_var("VK_DRIVER_FILES", &joined);
        // Mesa's implicit device-select layer reorders/filters devices: not under test.
        std::env::set_var("NODEVICE_SELECT", "1");
    }
    Ok((joined, wanted))
}

fn device_name(instance: &ash::Instance, pd: vk::PhysicalDevice) -> String {
    // SAFETY: plain query.
    let p = unsafe { instance.get_physical_device_properties(pd) };
    // SAFETY: NUL-terminated by the driver.
    unsafe { CStr::from_ptr(p.device_name.as_ptr()) }.to_string_lossy().into_owned()
}

/// The devices, labelled by driver and ordered as asked: named drivers first in their order,
/// then devices of --icd manifests.
fn find_devices(instance: &ash::Instance, wanted: &[String]) -> Result<Vec<(String, vk::PhysicalDevice)>, String> {
    // SAFETY: plain queries.
    let pds = unsafe { instance.enumerate_physical_devices() }.map_err(|e| format!("vkEnumeratePhysicalDevices: {e}"))?;
    let mut devices: Vec<(String, vk::PhysicalDevice)> = pds
        .iter()
        .map(|&pd| {
            // SAFETY: plain query.
            let p = unsafe { instance.get_physical_device_properties(pd) };
            (classify(&p, &device_name(instance, pd)), pd)
        })
        .collect();
    devices.sort_by_key(|(label, _)| wanted.iter().position(|w| w == label).unwrap_or(usize::MAX));
    for w in wanted {
        if !devices.iter().any(|(l, _)| l == w) {
            eprintln!("arbor-bench: {w}: its manifest loaded but no device of it was found");
        }
    }
    Ok(devices)
}

/// What the measuring loop gives the outputs.
struct Measured {
    rows: Vec<work::Row>,
    render_data: Option<work::RenderData>,
    failed: bool,
}

/// Every scene's workloads on every device, with progress on stderr.
fn measure(
    args: &Args,
    instance: &ash::Instance,
    devices: &[(String, vk::PhysicalDevice)],
    scenes: &[Scene],
    arbor_threads: usize,
    render_scene: Option<&String>,
    meta: &mut report::Meta,
) -> Measured {
    let opts = work::Options {
        repeat: args.repeat,
        warmup: args.warmup,
        joiners: args.joiners,
        metrics: args.metrics,
        efficiency: args.efficiency,
        rays: args.rays,
        keep_hits: args.compare.is_some(),
        compute_invocations: args.compute_invocations,
        compute_memory_bytes: args.compute_memory_mib << 20,
        partitions: args.partitions,
    };
    let (compute, scene_work): (Vec<work::Workload>, Vec<work::Workload>) = args.workloads.iter().partition(|w| w.is_compute());
    let total = devices.len() * (scenes.len() * scene_work.len() + compute.len());
    let mut step = 0usize;
    let tty = std::io::stderr().is_terminal();
    let mut out = Measured { rows: Vec::new(), render_data: None, failed: false };
    let started = std::time::Instant::now();
    for (label, pd) in devices {
        let gpu = match vkctx::Gpu::new(instance, *pd, label.clone()) {
            Ok(g) => g,
            Err(e) => {
                eprintln!("arbor-bench: {label}: {e}");
                out.failed = true;
                continue;
            }
        };
        let is_arbor = label == "arbor";
        let threads = if is_arbor { arbor_threads.to_string() } else { "-".to_string() };
        announce_driver(args, meta, label, &gpu);
        let mut progress = |scene: &str, w: &str| {
            step += 1;
            if !args.quiet {
                let msg = format!("[{step}/{total}] {:.1}s {label} {scene} {w}", started.elapsed().as_secs_f64());
                if tty {
                    eprint!("\r\x1b[K{msg}");
                } else {
                    eprintln!("{msg}");
                }
                let _ = std::io::stderr().flush();
            }
        };
        for scene in scenes.iter().filter(|_| !scene_work.is_empty()) {
            let want_render = args.render.is_some() && is_arbor && Some(&scene.name) == render_scene;
            let opts = work::Options { metrics: opts.metrics && is_arbor || want_render, ..opts };
            let mut progress = |w: &str| progress(&scene.name, w);
            let r = work::run_scene(&gpu, &threads, scene, &scene_work, &opts, want_render, &mut progress, &mut out.render_data);
            out.failed |= r.iter().any(|r| matches!(r.status, work::Status::Failed(_)));
            out.rows.extend(r);
        }
        let r = work::run_compute(&gpu, &threads, &compute, &opts, &mut |w: &str| progress("-", w));
        out.failed |= r.iter().any(|r| matches!(r.status, work::Status::Failed(_)));
        out.rows.extend(r);
        gpu.destroy();
    }
    if tty && !args.quiet {
        eprint!("\r\x1b[K");
    }
    out
}

/// The driver into the report's metadata and, unless --quiet, its name and version on stderr.
fn announce_driver(args: &Args, meta: &mut report::Meta, label: &str, gpu: &vkctx::Gpu) {
    meta.drivers.push((
        label.to_string(),
        gpu.name.clone(),
        gpu.driver_version.clone(),
        gpu.caps.host_commands,
        gpu.caps.indirect_build,
        gpu.caps.timestamps,
    ));
    if !args.quiet {
        eprintln!(
            "arbor-bench: {label}: {} (driver {}){}",
            gpu.name,
            gpu.driver_version,
            gpu.caps.missing.as_ref().map(|m| format!(": {m}")).unwrap_or_default()
        );
    }
}

/// The files asked for (JSON, CSV, SVG, PNG); returns whether --render had nothing to render.
fn write_outputs(
    args: &Args,
    meta: &report::Meta,
    scenes: &[Scene],
    measured: &Measured,
    render_scene: Option<String>,
    comparisons: &[compare::Comparison],
) -> Result<bool, String> {
    let rows = &measured.rows;
    let write = |path: &Path, data: &[u8]| -> Result<(), String> {
        std::fs::write(path, data).map_err(|e| format!("{}: {e}", path.display()))?;
        if !args.quiet {
            eprintln!("arbor-bench: wrote {}", path.display());
        }
        Ok(())
    };
    if let Some(p) = &args.json {
        let compared: Vec<String> = comparisons.iter().map(|c| c.json()).collect();
        let extra = if args.compare.is_some() { vec![("compare", compared)] } else { Vec::new() };
        write(p, report::json_with(meta, rows, &extra).as_bytes())?;
    }
    if let Some(p) = &args.csv {
        write(p, report::csv(rows).as_bytes())?;
    }
    if let Some(p) = &args.svg {
        let title = format!("arbor-bench: {} (repeat {})", scenes.iter().map(|s| s.name.as_str()).collect::<Vec<_>>().join(", "), args.repeat);
        write(p, report::svg(rows, &title).as_bytes())?;
    }
    if let Some(p) = &args.render {
        match &measured.render_data {
            Some(d) => {
                let (w, h) = args.render_size;
                let rgb = render::render(d, w, h)?;
                write(p, &png::encode_rgb(w, h, &rgb))?;
            }
            None => {
                eprintln!("arbor-bench: --render: no Arbor fast-trace build of scene {} to render", render_scene.unwrap_or_default());
                return Ok(true);
            }
        }
    }
    Ok(false)
}

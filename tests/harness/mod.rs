//! The loader harness of the API tests: Arbor through the real Vulkan loader (libvulkan1, via
//! ash's `loaded` feature) with VK_LAYER_KHRONOS_validation on and a debug messenger that records
//! every message; `Context::finish` (and Drop) fails the test on any validation message.
//! `accel` adds acceleration-structure helpers (buffers with device addresses, builds, read-back);
//! `vuid` the guarded-buffer scenario of the negative valid-usage tests (`tests/vuid_*.rs`).
//! (Tests of `arbor::accel` as a library, without a device, use `tests/reference` instead.)
// Each test binary uses a different part of the harness.
#![allow(dead_code)]

pub mod accel;
pub mod child;
pub mod clas;
pub mod compute;
pub mod compute_run;
pub mod ptlas;
pub mod rq;
pub mod trace;
pub mod vuid;

use std::ffi::{c_void, CStr, CString};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};

use ash::vk;

/// Messages the validation layer of Debian 12 (1.3.239) reports wrongly for current specs:
/// filtered exactly, nothing else.
const KNOWN_STALE_VUIDS: &[&str] = &[
    "VUID-vkGetAccelerationStructureBuildSizesKHR-rayTracingPipeline-03617",
    "VUID-vkGetDeviceAccelerationStructureCompatibilityKHR-rayTracingPipeline-03661",
];

/// What that layer (Vulkan header 239) says about the NV extensions, which postdate it: only that
/// it does not know them. Each entry is every phrase of one message, matched exactly: enabling the
/// device extension, and the cluster properties struct's sType in a VkPhysicalDeviceProperties2
/// chain. Any other message about the extensions still fails a test.
const LAYER_PREDATES: &[&[&str]] = &[
    &["Device Extension VK_NV_cluster_acceleration_structure is not supported by this layer"],
    &["Device Extension VK_NV_partitioned_acceleration_structure is not supported by this layer"],
    &["VUID-VkPhysicalDeviceProperties2-pNext-pNext", "unknown VkStructureType (1000569001)"],
    // The cluster feature struct in vkCreateDevice's chain (the layer then drops it).
    &["VUID-VkDeviceCreateInfo-pNext-pNext", "unknown VkStructureType (1000569000)"],
    // A shader using the cluster ID: its capability (5437, RayTracingClusterAccelerationStructureNV)
    // and extension, which the layer's SPIR-V tables lack.
    &["UNASSIGNED-CoreValidation-Shader-InconsistentSpirv", "Invalid capability operand: 5437"],
    &["VUID-VkShaderModuleCreateInfo-pCode-01090", "A SPIR-V Capability (Unhandled OpCapability) was declared"],
    &["VUID-VkShaderModuleCreateInfo-pCode-04146", "A SPIR-V Extension (SPV_NV_cluster_acceleration_structure) was declared"],
];

/// Path of the built driver for this test profile (target/<profile>/libvulkan_arbor.so).
pub fn driver_library() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    let profile_dir = exe.parent().and_then(|d| d.parent()).expect("target/<profile>");
    let lib = profile_dir.join("libvulkan_arbor.so");
    assert!(
        lib.exists(),
        "{} is missing: build the driver first (`cargo build --release --workspace`, as the README's test command does)",
        lib.display()
    );
    lib
}

/// A manifest pointing at the driver of this profile; VK_ICD_FILENAMES/VK_DRIVER_FILES set to it.
pub fn use_arbor_manifest() -> PathBuf {
    static MANIFEST: OnceLock<PathBuf> = OnceLock::new();
    MANIFEST
        .get_or_init(|| {
            let lib = driver_library();
            let dir = lib.parent().unwrap().join("arbor-test-icd");
            std::fs::create_dir_all(&dir).unwrap();
            let path = dir.join("icd.json");
            let json = format!(
                "{{\"file_format_version\":\"1.0.1\",\"ICD\":{{\"library_path\":\"{}\",\"api_version\":\"1.2.281\",\"library_arch\":\"64\"}}}}",
                lib.display()
            );
            // Every test process writes the same manifest: write a private file and rename it
            // over, so a concurrent reader never sees a half-written one.
            let tmp = dir.join(format!("icd.json.{}", std::process::id()));
            std::fs::write(&tmp, json).unwrap();
            std::fs::rename(&tmp, &path).unwrap();
            // SAFETY: set once, before any loader is opened in this process.
            unsafe {
                std::env::set_var("VK_ICD_FILENAMES", &path);
                std::env::set_var("VK_DRIVER_FILES", &path);
                // Mesa's implicit device-select layer may be installed; it is not under test.
                std::env::set_var("NODEVICE_SELECT", "1");
                // Arbor's diagnostics go to a file per test process, so tests can read them.
                std::env::set_var("ARBOR_DIAG_FILE", diagnostics_path());
            }
            path
        })
        .clone()
}

/// The file Arbor's diagnostics channel writes to in this test process.
pub fn diagnostics_path() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    let name = exe.file_name().unwrap().to_string_lossy().into_owned();
    exe.parent().unwrap().parent().unwrap().join("arbor-test-icd").join(format!("diag-{name}-{}.log", std::process::id()))
}

/// Everything Arbor's diagnostics channel reported in this test process so far.
pub fn diagnostics() -> String {
    std::fs::read_to_string(diagnostics_path()).unwrap_or_default()
}

pub type Messages = Arc<Mutex<Vec<String>>>;

unsafe extern "system" fn messenger_callback(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    user: *mut c_void,
) -> vk::Bool32 {
    // SAFETY: the layer passes valid callback data; `user` is the Messages we registered.
    unsafe {
        let msg = if data.is_null() || (*data).p_message.is_null() {
            String::from("(no message)")
        } else {
            CStr::from_ptr((*data).p_message).to_string_lossy().into_owned()
        };
        if severity.intersects(vk::DebugUtilsMessageSeverityFlagsEXT::WARNING | vk::DebugUtilsMessageSeverityFlagsEXT::ERROR)
            && !KNOWN_STALE_VUIDS.iter().any(|v| msg.contains(v))
            && !LAYER_PREDATES.iter().any(|phrases| phrases.iter().all(|p| msg.contains(p)))
        {
            let sink = &*(user as *const Mutex<Vec<String>>);
            sink.lock().unwrap().push(format!("{severity:?}: {msg}"));
        }
    }
    vk::FALSE
}

/// Warnings and errors of every message type go to `messenger_callback` with `sink` as user data.
fn messenger_info(sink: *mut c_void) -> vk::DebugUtilsMessengerCreateInfoEXT<'static> {
    vk::DebugUtilsMessengerCreateInfoEXT::default()
        .message_severity(vk::DebugUtilsMessageSeverityFlagsEXT::WARNING | vk::DebugUtilsMessageSeverityFlagsEXT::ERROR)
        .message_type(
            vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                | vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
                | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
        )
        .pfn_user_callback(Some(messenger_callback))
        .user_data(sink)
}

/// Options for a test context.
#[derive(Clone)]
pub struct Options {
    pub validation: bool,
    pub device_extensions: Vec<&'static str>,
    pub instance_extensions: Vec<&'static str>,
    pub queue_count: u32,
    /// Enable VK_KHR_acceleration_structure (+ deferred host operations, ray_tracing_maintenance1)
    /// with every optional feature.
    pub acceleration_structure: bool,
    /// Enable the core sparseBinding feature.
    pub sparse_binding: bool,
    /// With VK_NV_cluster_acceleration_structure: chain its feature struct with the feature off.
    pub cluster_feature_off: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options { validation: true, device_extensions: default_device_extensions(), instance_extensions: vec![], queue_count: 4, acceleration_structure: false, sparse_binding: false, cluster_feature_off: false }
    }
}

/// Extensions a typical test enables: everything Arbor advertises that the validation layer knows.
pub fn default_device_extensions() -> Vec<&'static str> {
    vec![
        "VK_KHR_buffer_device_address",
        "VK_KHR_timeline_semaphore",
        "VK_KHR_synchronization2",
        "VK_KHR_copy_commands2",
        "VK_EXT_host_query_reset",
    ]
}

pub struct Context {
    pub entry: ash::Entry,
    pub instance: ash::Instance,
    pub physical: vk::PhysicalDevice,
    pub device: ash::Device,
    pub queues: Vec<vk::Queue>,
    pub messages: Messages,
    messenger: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    finished: bool,
}

pub fn context() -> Context {
    Context::new(Options::default())
}

/// Held while an instance and device are created or destroyed: the tests of one binary run on
/// parallel threads, and without this lock the validation layer (Debian's 1.3.239) crashes now
/// and then: tests/memory.rs died of a SIGSEGV in 9 of 1,500 runs (0 of 1,500 with the
/// lock). The core dump: one thread inside the layer's vkCreateDevice (called from the
/// loader; no Arbor frame on the stack) copying 312 bytes to a member of a null object (offset
/// 0x12c0), while another thread was in the loader's vkDestroyDevice. Commands between stay
/// parallel.
fn lifecycle() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: Mutex<()> = Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// The instance: validation layer (if asked for), debug utils and the options' extensions, with
/// a messenger into `sink` that also covers vkCreateInstance itself.
fn create_instance(entry: &ash::Entry, opts: &Options, sink: *mut c_void) -> ash::Instance {
    let app = vk::ApplicationInfo::default().api_version(vk::API_VERSION_1_2);
    let layer = CString::new("VK_LAYER_KHRONOS_validation").unwrap();
    let ext_debug = ash::ext::debug_utils::NAME;
    let layers: Vec<*const i8> = if opts.validation {
        // SAFETY: plain query.
        let available = unsafe { entry.enumerate_instance_layer_properties() }.unwrap();
        assert!(
            available.iter().any(|l| l.layer_name_as_c_str().unwrap() == layer.as_c_str()),
            "VK_LAYER_KHRONOS_validation is not installed (apt-get install vulkan-validationlayers)"
        );
        vec![layer.as_ptr()]
    } else {
        vec![]
    };
    let inst_ext_c: Vec<CString> = opts.instance_extensions.iter().map(|e| CString::new(*e).unwrap()).collect();
    let mut exts = vec![ext_debug.as_ptr()];
    exts.extend(inst_ext_c.iter().map(|c| c.as_ptr()));
    let mut dbg_info = messenger_info(sink);
    let ci = vk::InstanceCreateInfo::default()
        .application_info(&app)
        .enabled_layer_names(&layers)
        .enabled_extension_names(&exts)
        .push_next(&mut dbg_info);
    // SAFETY: valid create info.
    unsafe { entry.create_instance(&ci, None) }.expect("vkCreateInstance")
}

/// Arbor's physical device among those the loader found.
fn arbor_physical_device(instance: &ash::Instance) -> vk::PhysicalDevice {
    // SAFETY: plain query.
    let pds = unsafe { instance.enumerate_physical_devices() }.expect("enumerate");
    *pds.iter()
        .find(|&&pd| {
            // SAFETY: plain query.
            let p = unsafe { instance.get_physical_device_properties(pd) };
            p.device_name_as_c_str().unwrap().to_str().unwrap() == "Arbor (software)"
        })
        .expect("Arbor's physical device")
}

#[repr(C)]
struct ClusterFeatures {
    s_type: i32,
    p_next: *const c_void,
    cluster_acceleration_structure: vk::Bool32,
}

/// The device: `queue_count` queues of family 0, the options' extensions (with the
/// acceleration-structure set if asked for) and the features those extensions bring.
fn create_device(instance: &ash::Instance, physical: vk::PhysicalDevice, opts: &Options) -> ash::Device {
    let prio = vec![1.0f32; opts.queue_count as usize];
    let qci = [vk::DeviceQueueCreateInfo::default().queue_family_index(0).queue_priorities(&prio)];
    let mut dev_exts = opts.device_extensions.clone();
    if opts.acceleration_structure {
        for e in ["VK_KHR_acceleration_structure", "VK_KHR_deferred_host_operations", "VK_EXT_descriptor_indexing", "VK_KHR_buffer_device_address", "VK_KHR_ray_tracing_maintenance1"] {
            if !dev_exts.contains(&e) {
                dev_exts.push(e);
            }
        }
    }
    let ext_c: Vec<CString> = dev_exts.iter().map(|e| CString::new(*e).unwrap()).collect();
    let ext_p: Vec<*const i8> = ext_c.iter().map(|c| c.as_ptr()).collect();
    let mut bda = vk::PhysicalDeviceBufferDeviceAddressFeatures::default()
        .buffer_device_address(true)
        .buffer_device_address_capture_replay(true);
    let mut tl = vk::PhysicalDeviceTimelineSemaphoreFeatures::default().timeline_semaphore(true);
    let mut s2 = vk::PhysicalDeviceSynchronization2Features::default().synchronization2(true);
    let mut hqr = vk::PhysicalDeviceHostQueryResetFeatures::default().host_query_reset(true);
    let core = vk::PhysicalDeviceFeatures::default().sparse_binding(opts.sparse_binding);
    let mut dci = vk::DeviceCreateInfo::default().queue_create_infos(&qci).enabled_extension_names(&ext_p).enabled_features(&core);
    let mut asf = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default()
        .acceleration_structure(true)
        .acceleration_structure_capture_replay(true)
        .acceleration_structure_indirect_build(true)
        .acceleration_structure_host_commands(true)
        .descriptor_binding_acceleration_structure_update_after_bind(true);
    let mut rtm1 = vk::PhysicalDeviceRayTracingMaintenance1FeaturesKHR::default().ray_tracing_maintenance1(true);
    let mut rq = vk::PhysicalDeviceRayQueryFeaturesKHR::default().ray_query(true);
    let has = |e: &str| dev_exts.contains(&e);
    if has("VK_KHR_ray_query") {
        dci = dci.push_next(&mut rq);
    }
    // VkPhysicalDeviceClusterAccelerationStructureFeaturesNV (ash 0.38 lacks it), linked by hand.
    let mut cluster = ClusterFeatures { s_type: 1_000_569_000, p_next: std::ptr::null(), cluster_acceleration_structure: (!opts.cluster_feature_off).into() };
    if has("VK_NV_cluster_acceleration_structure") {
        cluster.p_next = dci.p_next;
        dci.p_next = &cluster as *const ClusterFeatures as *const c_void;
    }
    if opts.acceleration_structure {
        dci = dci.push_next(&mut asf).push_next(&mut rtm1);
    }
    if has("VK_KHR_buffer_device_address") {
        dci = dci.push_next(&mut bda);
    }
    if has("VK_KHR_timeline_semaphore") {
        dci = dci.push_next(&mut tl);
    }
    if has("VK_KHR_synchronization2") {
        dci = dci.push_next(&mut s2);
    }
    if has("VK_EXT_host_query_reset") {
        dci = dci.push_next(&mut hqr);
    }
    // SAFETY: valid create info.
    unsafe { instance.create_device(physical, &dci, None) }.expect("vkCreateDevice")
}

impl Context {
    pub fn new(opts: Options) -> Context {
        use_arbor_manifest();
        let _serial = lifecycle();
        // SAFETY: loading the system Vulkan loader.
        let entry = unsafe { ash::Entry::load() }.expect("libvulkan.so.1 (install libvulkan1)");
        let messages: Messages = Arc::new(Mutex::new(Vec::new()));
        let sink_ptr = Arc::as_ptr(&messages) as *mut c_void;
        let instance = create_instance(&entry, &opts, sink_ptr);
        let du = ash::ext::debug_utils::Instance::new(&entry, &instance);
        let dbg_info2 = messenger_info(sink_ptr);
        // SAFETY: valid create info; the sink outlives the messenger (destroyed in Drop first).
        let messenger = unsafe { du.create_debug_utils_messenger(&dbg_info2, None) }.expect("messenger");
        let physical = arbor_physical_device(&instance);
        let device = create_device(&instance, physical, &opts);
        // SAFETY: queues created above.
        let queues = (0..opts.queue_count).map(|i| unsafe { device.get_device_queue(0, i) }).collect();
        Context { entry, instance, physical, device, queues, messages, messenger: Some((du, messenger)), finished: false }
    }

    /// Validation messages so far.
    pub fn messages(&self) -> Vec<String> {
        self.messages.lock().unwrap().clone()
    }

    /// Destroy device and instance, then fail if the validation layer said anything.
    pub fn finish(mut self) {
        self.teardown();
        let msgs = self.messages();
        self.finished = true;
        assert!(msgs.is_empty(), "validation messages:\n{}", msgs.join("\n"));
    }

    fn teardown(&mut self) {
        if let Some((du, m)) = self.messenger.take() {
            let _serial = lifecycle();
            // SAFETY: all objects created by the test were destroyed by it; device idle first.
            unsafe {
                let _ = self.device.device_wait_idle();
                self.device.destroy_device(None);
                du.destroy_debug_utils_messenger(m, None);
                self.instance.destroy_instance(None);
            }
        }
    }

    /// Find a memory type index with the given properties.
    pub fn memory_type(&self, bits: u32, flags: vk::MemoryPropertyFlags) -> u32 {
        // SAFETY: plain query.
        let mp = unsafe { self.instance.get_physical_device_memory_properties(self.physical) };
        (0..mp.memory_type_count)
            .find(|&i| bits & (1 << i) != 0 && mp.memory_types[i as usize].property_flags.contains(flags))
            .expect("memory type")
    }

    /// Create a buffer with bound host-visible memory (device-address capable). Returns
    /// (buffer, memory, mapped pointer).
    pub fn host_buffer(&self, size: u64, usage: vk::BufferUsageFlags) -> (vk::Buffer, vk::DeviceMemory, *mut u8) {
        // SAFETY: valid create infos; objects are returned to the test, which destroys them.
        unsafe {
            let buffer = self
                .device
                .create_buffer(&vk::BufferCreateInfo::default().size(size).usage(usage), None)
                .expect("vkCreateBuffer");
            let req = self.device.get_buffer_memory_requirements(buffer);
            let mut flags = vk::MemoryAllocateFlagsInfo::default().flags(vk::MemoryAllocateFlags::DEVICE_ADDRESS);
            let mut ai = vk::MemoryAllocateInfo::default()
                .allocation_size(req.size)
                .memory_type_index(self.memory_type(req.memory_type_bits, vk::MemoryPropertyFlags::HOST_VISIBLE));
            if usage.contains(vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS) {
                ai = ai.push_next(&mut flags);
            }
            let memory = self.device.allocate_memory(&ai, None).expect("vkAllocateMemory");
            self.device.bind_buffer_memory(buffer, memory, 0).expect("bind");
            let ptr = self.device.map_memory(memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()).expect("map") as *mut u8;
            (buffer, memory, ptr)
        }
    }
}

impl Drop for Context {
    fn drop(&mut self) {
        if !self.finished {
            self.teardown();
        }
    }
}

/// Run `f` on its own thread and fail the test if it has not finished within `secs` seconds, so
/// a call that hangs fails the test instead of stalling the run. A panic in `f` fails the test
/// with its message. (A hung thread is left behind; the process ends with the test binary.)
pub fn bounded<R: Send + 'static>(secs: u64, f: impl FnOnce() -> R + Send + 'static) -> R {
    let (tx, rx) = std::sync::mpsc::channel();
    let t = std::thread::spawn(move || {
        let r = f();
        let _ = tx.send(());
        r
    });
    match rx.recv_timeout(std::time::Duration::from_secs(secs)) {
        Ok(()) | Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => match t.join() {
            Ok(r) => r,
            Err(e) => std::panic::resume_unwind(e),
        },
        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => panic!("did not finish within {secs} s: a call hangs"),
    }
}

impl Context {
    /// Destroy device and instance without waiting for the device to be idle first (tests of
    /// vkDestroyDevice with work pending), then fail if the validation layer said anything.
    pub fn finish_without_wait(mut self) {
        if let Some((du, m)) = self.messenger.take() {
            let _serial = lifecycle();
            // SAFETY: the test destroys the device with work pending on purpose; nothing of it
            // is used afterwards.
            unsafe {
                self.device.destroy_device(None);
                du.destroy_debug_utils_messenger(m, None);
                self.instance.destroy_instance(None);
            }
        }
        self.finished = true;
        let msgs = self.messages();
        assert!(msgs.is_empty(), "validation messages:\n{}", msgs.join("\n"));
    }
}

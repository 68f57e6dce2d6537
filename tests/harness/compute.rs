//! Compute-shader helpers for the API tests: shaders compiled at test time (GLSL by
//! glslangValidator for Vulkan 1.2, optionally through `spirv-opt -O`; WGSL by naga), a device
//! on Arbor or on lavapipe (through the same loader, validation on), and [`Job`]: buffers in,
//! one dispatch (direct, base or indirect), buffers out.
use std::ffi::{c_void, CString};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};

use ash::vk;

use super::{lifecycle, messenger_info, use_arbor_manifest, Messages};

/// Where lavapipe's manifest is on Debian/Ubuntu (either name).
const LAVAPIPE_MANIFESTS: &[&str] = &["/usr/share/vulkan/icd.d/lvp_icd.x86_64.json", "/usr/share/vulkan/icd.d/lvp_icd.json"];

fn shader_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/shaders")
}

fn scratch_dir() -> PathBuf {
    let d = std::env::temp_dir().join(format!("arbor-compute-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn words(bytes: &[u8]) -> Vec<u32> {
    assert_eq!(bytes.len() % 4, 0, "SPIR-V is whole words");
    bytes.chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect()
}

/// A number no other call in this process gets: test threads that compile the same shader at once
/// must not write one output file (a reader could see the other's half-written module).
fn unique() -> u64 {
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
}

/// tests/shaders/`name` compiled by glslangValidator for Vulkan 1.2 (SPIR-V 1.5).
pub fn glsl(name: &str) -> Vec<u32> {
    let out = scratch_dir().join(format!("{name}.{}.spv", unique()));
    let r = std::process::Command::new("glslangValidator")
        .args(["-V", "--target-env", "vulkan1.2", "-o"])
        .arg(&out)
        .arg(shader_dir().join(name))
        .output()
        .expect("glslangValidator (apt-get install glslang-tools)");
    assert!(r.status.success(), "glslang failed on {name}:\n{}", String::from_utf8_lossy(&r.stdout));
    words(&std::fs::read(&out).unwrap())
}

/// `spirv` through `spirv-opt -O` (phis, switch-wrapped returns, inlined calls).
pub fn optimized(spirv: &[u32]) -> Vec<u32> {
    let dir = scratch_dir();
    let n = spirv.iter().fold(0u64, |h, w| h.wrapping_mul(31).wrapping_add(*w as u64));
    let u = unique();
    let (src, dst) = (dir.join(format!("{n:x}.{u}.in.spv")), dir.join(format!("{n:x}.{u}.opt.spv")));
    std::fs::write(&src, spirv.iter().flat_map(|w| w.to_le_bytes()).collect::<Vec<u8>>()).unwrap();
    let r = std::process::Command::new("spirv-opt")
        .args(["-O", "--target-env=vulkan1.2"])
        .arg(&src)
        .arg("-o")
        .arg(&dst)
        .output()
        .expect("spirv-opt (apt-get install spirv-tools)");
    assert!(r.status.success(), "spirv-opt failed:\n{}", String::from_utf8_lossy(&r.stderr));
    words(&std::fs::read(&dst).unwrap())
}

/// tests/shaders/`name` (WGSL) compiled by naga to SPIR-V 1.3, entry point `main`.
pub fn wgsl(name: &str) -> Vec<u32> {
    let text = std::fs::read_to_string(shader_dir().join(name)).unwrap();
    let module = naga::front::wgsl::parse_str(&text).unwrap_or_else(|e| panic!("naga cannot parse {name}: {}", e.emit_to_string(&text)));
    let info = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all())
        .validate(&module)
        .unwrap_or_else(|e| panic!("naga rejects {name}: {e:?}"));
    let options = naga::back::spv::Options { lang_version: (1, 3), ..Default::default() };
    let pipeline = naga::back::spv::PipelineOptions { shader_stage: naga::ShaderStage::Compute, entry_point: "main".into() };
    naga::back::spv::write_vec(&module, &info, &options, Some(&pipeline)).unwrap_or_else(|e| panic!("naga cannot write {name}: {e:?}"))
}

/// Which driver a [`Gpu`] runs on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Driver {
    Arbor,
    Lavapipe,
}

fn lavapipe_manifest() -> Option<&'static str> {
    LAVAPIPE_MANIFESTS.iter().copied().find(|p| std::path::Path::new(p).exists())
}

/// A Vulkan 1.2 instance with the validation layer on and a debug messenger collecting every
/// message into the returned list (also during instance creation and destruction).
pub(super) fn validated_instance(entry: &ash::Entry) -> (ash::Instance, ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT, Messages) {
    let messages: Messages = Arc::new(Mutex::new(Vec::new()));
    let app = vk::ApplicationInfo::default().api_version(vk::API_VERSION_1_2);
    let layer = CString::new("VK_LAYER_KHRONOS_validation").unwrap();
    let layers = [layer.as_ptr()];
    let exts = [ash::ext::debug_utils::NAME.as_ptr()];
    // The messenger writes through this pointer; the returned Arc keeps the list alive.
    let sink = Arc::as_ptr(&messages) as *mut c_void;
    let mut dbg = messenger_info(sink);
    let ci = vk::InstanceCreateInfo::default().application_info(&app).enabled_layer_names(&layers).enabled_extension_names(&exts).push_next(&mut dbg);
    // SAFETY: valid create infos; the caller destroys the messenger and the instance.
    unsafe {
        let instance = entry.create_instance(&ci, None).expect("vkCreateInstance");
        let du = ash::ext::debug_utils::Instance::new(entry, &instance);
        let messenger = du.create_debug_utils_messenger(&messenger_info(sink), None).expect("messenger");
        (instance, du, messenger, messages)
    }
}

/// Make both Arbor and (when installed) lavapipe visible to the loader: once per process,
/// before any instance exists (the compute and ray-query harnesses both go through here).
pub(super) fn use_drivers() {
    static ONCE: OnceLock<()> = OnceLock::new();
    ONCE.get_or_init(|| {
        let arbor = use_arbor_manifest();
        if let Some(lvp) = lavapipe_manifest() {
            let both = format!("{}:{lvp}", arbor.display());
            // SAFETY: set once, before any loader instance is created in this process (every
            // compute test goes through here first).
            unsafe {
                std::env::set_var("VK_ICD_FILENAMES", &both);
                std::env::set_var("VK_DRIVER_FILES", &both);
            }
        }
    });
}

/// One device with one compute queue, validation on, messages recorded.
pub struct Gpu {
    pub driver: Driver,
    pub entry: ash::Entry,
    pub instance: ash::Instance,
    pub physical: vk::PhysicalDevice,
    pub device: ash::Device,
    pub queue: vk::Queue,
    pub messages: Messages,
    messenger: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    pub subgroup_size: u32,
}

impl Gpu {
    pub fn arbor() -> Gpu {
        Gpu::new(Driver::Arbor).expect("Arbor's physical device")
    }

    /// lavapipe, or None (with a message saying the comparison is skipped) when not installed.
    pub fn lavapipe() -> Option<Gpu> {
        if lavapipe_manifest().is_none() {
            println!("lavapipe is not installed (no lvp_icd manifest): the comparison is skipped");
            return None;
        }
        let g = Gpu::new(Driver::Lavapipe);
        if g.is_none() {
            println!("lavapipe's manifest exists but the loader offers no llvmpipe device: the comparison is skipped");
        }
        g
    }

    fn new(driver: Driver) -> Option<Gpu> {
        use_drivers();
        let _serial = lifecycle();
        // SAFETY: loading the system Vulkan loader.
        let entry = unsafe { ash::Entry::load() }.expect("libvulkan.so.1");
        let (instance, du, messenger, messages) = validated_instance(&entry);
        // SAFETY: valid create infos; everything is destroyed in Drop.
        unsafe {
            let wanted = |name: &str| match driver {
                Driver::Arbor => name == "Arbor (software)",
                Driver::Lavapipe => name.starts_with("llvmpipe"),
            };
            let Some(physical) = instance.enumerate_physical_devices().unwrap().into_iter().find(|&pd| {
                let p = instance.get_physical_device_properties(pd);
                wanted(p.device_name_as_c_str().unwrap().to_str().unwrap())
            }) else {
                du.destroy_debug_utils_messenger(messenger, None);
                instance.destroy_instance(None);
                return None;
            };
            let mut sg = vk::PhysicalDeviceSubgroupProperties::default();
            let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut sg);
            instance.get_physical_device_properties2(physical, &mut p2);
            let subgroup_size = sg.subgroup_size;
            let prio = [1.0f32];
            let qci = [vk::DeviceQueueCreateInfo::default().queue_family_index(0).queue_priorities(&prio)];
            let features = vk::PhysicalDeviceFeatures::default()
                .shader_int64(true)
                .shader_float64(true)
                .shader_uniform_buffer_array_dynamic_indexing(true)
                .shader_storage_buffer_array_dynamic_indexing(true)
                .shader_storage_image_array_dynamic_indexing(true);
            let mut v12 = vk::PhysicalDeviceVulkan12Features::default()
                .runtime_descriptor_array(true)
                .shader_uniform_buffer_array_non_uniform_indexing(true)
                .shader_storage_buffer_array_non_uniform_indexing(true)
                .shader_storage_image_array_non_uniform_indexing(true)
                .shader_uniform_texel_buffer_array_dynamic_indexing(true)
                .shader_storage_texel_buffer_array_dynamic_indexing(true)
                .shader_uniform_texel_buffer_array_non_uniform_indexing(true)
                .shader_storage_texel_buffer_array_non_uniform_indexing(true)
                .buffer_device_address(true)
                .shader_buffer_int64_atomics(true)
                .shader_subgroup_extended_types(true);
            let dci = vk::DeviceCreateInfo::default().queue_create_infos(&qci).enabled_features(&features).push_next(&mut v12);
            let device = instance.create_device(physical, &dci, None).expect("vkCreateDevice");
            let queue = device.get_device_queue(0, 0);
            Some(Gpu { driver, entry, instance, physical, device, queue, messages, messenger: Some((du, messenger)), subgroup_size })
        }
    }

    /// Validation messages so far.
    pub fn messages(&self) -> Vec<String> {
        self.messages.lock().unwrap().clone()
    }

    /// Fail if the validation layer said anything.
    pub fn assert_quiet(&self) {
        let m = self.messages();
        assert!(m.is_empty(), "validation messages on {:?}:\n{}", self.driver, m.join("\n"));
    }

    fn memory_type(&self, bits: u32) -> u32 {
        let want = vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT;
        // SAFETY: plain query.
        let mp = unsafe { self.instance.get_physical_device_memory_properties(self.physical) };
        (0..mp.memory_type_count).find(|&i| bits & (1 << i) != 0 && mp.memory_types[i as usize].property_flags.contains(want)).expect("host-visible memory")
    }
}

impl Drop for Gpu {
    fn drop(&mut self) {
        if let Some((du, m)) = self.messenger.take() {
            let _serial = lifecycle();
            // SAFETY: the jobs destroyed what they created; device idle first.
            unsafe {
                let _ = self.device.device_wait_idle();
                self.device.destroy_device(None);
                du.destroy_debug_utils_messenger(m, None);
                self.instance.destroy_instance(None);
            }
        }
    }
}

/// A buffer (or storage image) a job binds: its initial bytes and how it is bound.
#[derive(Clone)]
pub struct Binding {
    /// The buffer's bytes, or the image's texels tightly packed (row after row).
    pub data: Vec<u8>,
    pub kind: vk::DescriptorType,
    /// For STORAGE_IMAGE: the 2D image's format and extent (optimal tiling, GENERAL layout).
    pub image: Option<(vk::Format, [u32; 2])>,
    /// For the _DYNAMIC kinds: the dynamic offset.
    pub dynamic_offset: u32,
    /// Descriptor range (WHOLE_SIZE by default).
    pub range: u64,
    /// Array elements of the binding (1 by default): `data` is split into this many equal
    /// parts, element e bound to the e-th part of the one buffer (offset e * part, range
    /// part); a dynamic offset applies to each element.
    pub elements: u32,
    /// For UNIFORM_/STORAGE_TEXEL_BUFFER: the buffer view's format (the view covers `data`).
    pub texel: Option<vk::Format>,
}

impl Binding {
    pub fn storage(data: Vec<u8>) -> Binding {
        Binding { data, kind: vk::DescriptorType::STORAGE_BUFFER, image: None, dynamic_offset: 0, range: vk::WHOLE_SIZE, elements: 1, texel: None }
    }
    pub fn uniform(data: Vec<u8>) -> Binding {
        Binding { data, kind: vk::DescriptorType::UNIFORM_BUFFER, image: None, dynamic_offset: 0, range: vk::WHOLE_SIZE, elements: 1, texel: None }
    }
    /// A 2D storage image of `format` and `extent` holding `texels` (tightly packed); the job
    /// returns its texels after the dispatch, packed the same way.
    pub fn storage_image(format: vk::Format, extent: [u32; 2], texels: Vec<u8>) -> Binding {
        Binding { data: texels, kind: vk::DescriptorType::STORAGE_IMAGE, image: Some((format, extent)), dynamic_offset: 0, range: vk::WHOLE_SIZE, elements: 1, texel: None }
    }
    /// A uniform texel buffer of `format` over `data`.
    pub fn uniform_texels(format: vk::Format, data: Vec<u8>) -> Binding {
        Binding { kind: vk::DescriptorType::UNIFORM_TEXEL_BUFFER, texel: Some(format), ..Binding::storage(data) }
    }
    /// A storage texel buffer of `format` over `data`.
    pub fn storage_texels(format: vk::Format, data: Vec<u8>) -> Binding {
        Binding { kind: vk::DescriptorType::STORAGE_TEXEL_BUFFER, texel: Some(format), ..Binding::storage(data) }
    }
    /// An array of `n` buffer (or texel-buffer) descriptors over equal parts of `data` (see
    /// `elements`).
    pub fn array(mut self, n: u32) -> Binding {
        assert!(n > 0 && self.data.len().is_multiple_of(n as usize) && self.image.is_none());
        self.elements = n;
        self
    }
    pub fn dynamic(mut self, offset: u32, range: u64) -> Binding {
        self.kind = match self.kind {
            vk::DescriptorType::UNIFORM_BUFFER => vk::DescriptorType::UNIFORM_BUFFER_DYNAMIC,
            _ => vk::DescriptorType::STORAGE_BUFFER_DYNAMIC,
        };
        self.dynamic_offset = offset;
        self.range = range;
        self
    }
}

/// How the dispatch is recorded.
#[derive(Clone, Copy, Debug)]
pub enum Size {
    Direct([u32; 3]),
    Base { base: [u32; 3], groups: [u32; 3] },
    /// vkCmdDispatchIndirect with this record, written into an indirect buffer at offset 16.
    Indirect([u32; 3]),
}

/// Write the device address of binding `of` (plus `plus` bytes) as 8 bytes at `at` of the
/// push constants (`into: None`) or of binding `into`'s buffer.
#[derive(Clone, Copy, Debug)]
pub struct AddressPatch {
    pub into: Option<usize>,
    pub at: usize,
    pub of: usize,
    pub plus: u64,
}

/// One dispatch of one shader: set 0 holds `bindings` at binding 0, 1, …
#[derive(Clone)]
pub struct Job {
    pub spirv: Vec<u32>,
    pub bindings: Vec<Binding>,
    pub push: Vec<u8>,
    /// Device addresses written before the dispatch (buffer device address).
    pub addresses: Vec<AddressPatch>,
    pub spec: Vec<(u32, Vec<u8>)>,
    pub size: Size,
}

impl Job {
    pub fn new(spirv: Vec<u32>, bindings: Vec<Binding>, size: Size) -> Job {
        Job { spirv, bindings, push: Vec::new(), addresses: Vec::new(), spec: Vec::new(), size }
    }
}

/// Why a job did not produce buffers.
#[derive(Debug, PartialEq, Eq)]
pub enum JobError {
    Pipeline(vk::Result),
    Submit(vk::Result),
}

pub fn u32s(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

pub fn as_u32(b: &[u8]) -> Vec<u32> {
    b.chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect()
}

pub fn f32s(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

pub fn as_f32(b: &[u8]) -> Vec<f32> {
    b.chunks(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
}

// Re-exported so tests write `compute::run`; binaries without compute tests leave it unused.
#[allow(unused_imports)]
pub use super::compute_run::run;

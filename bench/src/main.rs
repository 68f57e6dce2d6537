//! arbor-bench: goes through the Vulkan loader to a driver (Arbor by default: the manifest built
//! beside this program) and reports what it offers. The acceleration-structure workloads land
//! here as the AS API does (issue 5).
use std::ffi::CStr;
use std::path::PathBuf;

use ash::vk;

/// The icd.json of the checkout this program was built in (target/<profile>/arbor-bench →
/// <checkout>/icd.json), or a manifest next to the built driver.
fn arbor_manifest() -> Option<PathBuf> {
    let exe = std::env::current_exe().ok()?;
    let profile_dir = exe.parent()?;
    let lib = profile_dir.join("libvulkan_arbor.so");
    if !lib.exists() {
        return None;
    }
    let path = profile_dir.join("arbor_icd.json");
    let json = format!(
        "{{\"file_format_version\":\"1.0.1\",\"ICD\":{{\"library_path\":\"{}\",\"api_version\":\"1.1.281\",\"library_arch\":\"64\"}}}}",
        lib.display()
    );
    std::fs::write(&path, json).ok()?;
    Some(path)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let icd = args.iter().position(|a| a == "--icd").and_then(|i| args.get(i + 1)).map(PathBuf::from);
    let manifest = icd.or_else(arbor_manifest);
    match &manifest {
        // SAFETY: set before the loader is opened; single-threaded here.
        Some(m) => unsafe {
            std::env::set_var("VK_ICD_FILENAMES", m);
            std::env::set_var("VK_DRIVER_FILES", m);
        },
        None => eprintln!("arbor-bench: libvulkan_arbor.so not found beside this program; using the system's drivers"),
    }
    if let Err(e) = run() {
        eprintln!("arbor-bench: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), String> {
    // SAFETY: loading the system Vulkan loader.
    let entry = unsafe { ash::Entry::load() }.map_err(|e| format!("cannot load libvulkan.so.1 ({e}); install libvulkan1"))?;
    let app = vk::ApplicationInfo::default().api_version(vk::API_VERSION_1_1);
    // SAFETY: valid create info.
    let instance = unsafe { entry.create_instance(&vk::InstanceCreateInfo::default().application_info(&app), None) }
        .map_err(|e| format!("vkCreateInstance: {e}"))?;
    // SAFETY: plain queries on a live instance.
    unsafe {
        for pd in instance.enumerate_physical_devices().map_err(|e| e.to_string())? {
            let p = instance.get_physical_device_properties(pd);
            let name = CStr::from_ptr(p.device_name.as_ptr()).to_string_lossy();
            println!("device: {name} ({:?}), Vulkan {}.{}", p.device_type, vk::api_version_major(p.api_version), vk::api_version_minor(p.api_version));
            for (i, q) in instance.get_physical_device_queue_family_properties(pd).iter().enumerate() {
                println!("  queue family {i}: {:?} x{}", q.queue_flags, q.queue_count);
            }
            let mp = instance.get_physical_device_memory_properties(pd);
            for h in &mp.memory_heaps[..mp.memory_heap_count as usize] {
                println!("  memory heap: {:.1} GiB {:?}", h.size as f64 / (1u64 << 30) as f64, h.flags);
            }
            let exts = instance.enumerate_device_extension_properties(pd).map_err(|e| e.to_string())?;
            println!("  extensions ({}):", exts.len());
            for e in &exts {
                println!("    {}", CStr::from_ptr(e.extension_name.as_ptr()).to_string_lossy());
            }
        }
        instance.destroy_instance(None);
    }
    Ok(())
}

//! Every command that vk.xml lists for the API version and the extensions Arbor advertises
//! resolves, both through the real loader (vkGetInstanceProcAddr / vkGetDeviceProcAddr) and in
//! the driver's own table (vk_icdGetInstanceProcAddr on libvulkan_arbor.so opened directly).
//! vk.xml is parsed here independently of tools/gen_registry.py.
mod harness;

use std::collections::BTreeSet;
use std::ffi::{c_char, CString};

use ash::vk;

struct Required {
    /// (command name, is device-level)
    commands: BTreeSet<(String, bool)>,
}

/// Evaluate a vk.xml `depends` expression (',' = or, '+' = and, parentheses).
fn depends_ok(expr: &str, have: &BTreeSet<String>) -> bool {
    fn parse_or(s: &[u8], i: &mut usize, have: &BTreeSet<String>) -> bool {
        let mut v = parse_and(s, i, have);
        while *i < s.len() && s[*i] == b',' {
            *i += 1;
            let r = parse_and(s, i, have);
            v = v || r;
        }
        v
    }
    fn parse_and(s: &[u8], i: &mut usize, have: &BTreeSet<String>) -> bool {
        let mut v = parse_atom(s, i, have);
        while *i < s.len() && s[*i] == b'+' {
            *i += 1;
            let r = parse_atom(s, i, have);
            v = v && r;
        }
        v
    }
    fn parse_atom(s: &[u8], i: &mut usize, have: &BTreeSet<String>) -> bool {
        if s[*i] == b'(' {
            *i += 1;
            let v = parse_or(s, i, have);
            *i += 1; // ')'
            return v;
        }
        let start = *i;
        while *i < s.len() && !matches!(s[*i], b',' | b'+' | b')') {
            *i += 1;
        }
        have.contains(std::str::from_utf8(&s[start..*i]).unwrap())
    }
    let mut i = 0;
    parse_or(expr.as_bytes(), &mut i, have)
}

fn required(instance_exts: &[String], device_exts: &[String], minor: u32) -> Required {
    let xml = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/spec/vk.xml")).unwrap();
    let doc = roxmltree::Document::parse_with_options(&xml, roxmltree::ParsingOptions { allow_dtd: true, ..Default::default() }).unwrap();
    let registry = doc.root_element();
    let mut have: BTreeSet<String> = instance_exts.iter().chain(device_exts).cloned().collect();
    for m in 0..=minor {
        have.insert(format!("VK_VERSION_1_{m}"));
    }
    // Which commands take a dispatchable device-level first parameter.
    let mut first_param = std::collections::HashMap::new();
    let mut alias = std::collections::HashMap::new();
    for c in registry.children().filter(|n| n.has_tag_name("commands")).flat_map(|n| n.children()).filter(|n| n.has_tag_name("command")) {
        if let Some(a) = c.attribute("alias") {
            alias.insert(c.attribute("name").unwrap().to_string(), a.to_string());
            continue;
        }
        let name = c.descendants().find(|n| n.has_tag_name("proto")).unwrap().children().find(|n| n.has_tag_name("name")).unwrap().text().unwrap();
        let p = c.children().find(|n| n.has_tag_name("param")).and_then(|p| p.children().find(|n| n.has_tag_name("type"))).and_then(|t| t.text()).unwrap_or("");
        first_param.insert(name.to_string(), p.to_string());
    }
    let is_device = |name: &str| {
        let mut n = name.to_string();
        while let Some(a) = alias.get(&n) {
            n = a.clone();
        }
        matches!(first_param.get(&n).map(String::as_str), Some("VkDevice" | "VkQueue" | "VkCommandBuffer")) && n != "vkGetDeviceProcAddr"
    };
    let mut commands = BTreeSet::new();
    let mut take = |node: roxmltree::Node| {
        for req in node.children().filter(|n| n.has_tag_name("require")) {
            if let Some(d) = req.attribute("depends") {
                if !depends_ok(d, &have) {
                    continue;
                }
            }
            for c in req.children().filter(|n| n.has_tag_name("command")) {
                let n = c.attribute("name").unwrap();
                commands.insert((n.to_string(), is_device(n)));
            }
        }
    };
    for f in registry.children().filter(|n| n.has_tag_name("feature")) {
        let api = f.attribute("api").unwrap_or("");
        if !api.split(',').any(|a| a == "vulkan") {
            continue;
        }
        let name = f.attribute("name").unwrap();
        let version_ok = (0..=minor).any(|m| {
            [format!("VK_VERSION_1_{m}"), format!("VK_BASE_VERSION_1_{m}"), format!("VK_COMPUTE_VERSION_1_{m}"), format!("VK_GRAPHICS_VERSION_1_{m}")]
                .contains(&name.to_string())
        });
        if version_ok {
            take(f);
        }
    }
    for e in registry.children().filter(|n| n.has_tag_name("extensions")).flat_map(|n| n.children()).filter(|n| n.has_tag_name("extension")) {
        if have.contains(e.attribute("name").unwrap_or("")) {
            take(e);
        }
    }
    Required { commands }
}

fn names(props: &[vk::ExtensionProperties]) -> Vec<String> {
    props.iter().map(|p| p.extension_name_as_c_str().unwrap().to_str().unwrap().to_string()).collect()
}

#[test]
fn every_advertised_command_resolves_through_the_loader() {
    harness::use_arbor_manifest();
    // Enable every device extension Arbor advertises.
    let probe = harness::context();
    // SAFETY: plain queries.
    let dev_exts = names(&unsafe { probe.instance.enumerate_device_extension_properties(probe.physical) }.unwrap());
    // SAFETY: as above.
    let props = unsafe { probe.instance.get_physical_device_properties(probe.physical) };
    probe.finish();
    let opts = harness::Options {
        device_extensions: dev_exts.iter().map(|s| &*Box::leak(s.clone().into_boxed_str())).collect(),
        instance_extensions: vec!["VK_KHR_get_physical_device_properties2"],
        ..Default::default()
    };
    let ctx = harness::Context::new(opts);
    // Instance extensions: Arbor's own list (enumerated without layers through the loader would include the loader's).
    let inst_exts = vec!["VK_KHR_get_physical_device_properties2".to_string()];
    let req = required(&inst_exts, &dev_exts, vk::api_version_minor(props.api_version));
    assert!(req.commands.len() > 150, "vk.xml parse found only {} commands", req.commands.len());
    let mut missing = Vec::new();
    for (name, device_level) in &req.commands {
        let c = CString::new(name.as_str()).unwrap();
        // SAFETY: valid instance/device and name.
        let f = unsafe {
            if *device_level {
                (ctx.instance.fp_v1_0().get_device_proc_addr)(ctx.device.handle(), c.as_ptr())
            } else {
                (ctx.entry.static_fn().get_instance_proc_addr)(ctx.instance.handle(), c.as_ptr())
            }
        };
        if f.is_none() {
            missing.push(name.clone());
        }
    }
    assert!(missing.is_empty(), "commands missing through the loader: {missing:?}");
    ctx.finish();
}

type Gipa = unsafe extern "system" fn(vk::Instance, *const c_char) -> vk::PFN_vkVoidFunction;

#[test]
fn driver_table_has_every_command_and_gates_device_extensions() {
    let lib_path = harness::driver_library();
    // SAFETY: loading our own driver library; its initialisers are trivial.
    let lib = unsafe { libloading::Library::new(&lib_path) }.unwrap();
    // SAFETY: the exported symbol has this signature (vk_icd.h).
    unsafe {
        let negotiate: libloading::Symbol<unsafe extern "system" fn(*mut u32) -> vk::Result> =
            lib.get(b"vk_icdNegotiateLoaderICDInterfaceVersion").unwrap();
        let mut v = 7u32;
        assert_eq!(negotiate(&mut v), vk::Result::SUCCESS);
        assert_eq!(v, 7);
        let mut old = 4u32;
        assert_eq!(negotiate(&mut old), vk::Result::ERROR_INCOMPATIBLE_DRIVER, "interface < 5 is refused");
        let gipa: libloading::Symbol<Gipa> = lib.get(b"vk_icdGetInstanceProcAddr").unwrap();
        let gpdpa: libloading::Symbol<Gipa> = lib.get(b"vk_icdGetPhysicalDeviceProcAddr").unwrap();
        let get = |inst: vk::Instance, n: &str| {
            let c = CString::new(n).unwrap();
            gipa(inst, c.as_ptr())
        };
        // Global commands with a null instance; instance commands only with an instance.
        assert!(get(vk::Instance::null(), "vkCreateInstance").is_some());
        assert!(get(vk::Instance::null(), "vk_icdGetPhysicalDeviceProcAddr").is_some());
        assert!(get(vk::Instance::null(), "vkEnumeratePhysicalDevices").is_none());
        let create: vk::PFN_vkCreateInstance = std::mem::transmute(get(vk::Instance::null(), "vkCreateInstance").unwrap());
        let app = vk::ApplicationInfo::default().api_version(vk::API_VERSION_1_1);
        let ci = vk::InstanceCreateInfo::default().application_info(&app);
        let mut inst = vk::Instance::null();
        assert_eq!(create(&ci, std::ptr::null(), &mut inst), vk::Result::SUCCESS);
        // The loader's magic word is at offset 0 of the dispatchable object.
        assert_eq!(*(vk::Handle::as_raw(inst) as *const usize) & 0xFFFF_FFFF, 0x01CD_C0DE);

        let req = required(&["VK_KHR_get_physical_device_properties2".into()], &[], 1);
        let dev_req = required(&[], &all_device_extensions(&get, inst), 1);
        let mut missing: Vec<String> = req
            .commands
            .iter()
            .chain(dev_req.commands.iter())
            .filter(|(n, _)| get(inst, n).is_none())
            .map(|(n, _)| n.clone())
            .collect();
        missing.dedup();
        assert!(missing.is_empty(), "missing in the driver's table: {missing:?}");
        // Physical-device commands through vk_icdGetPhysicalDeviceProcAddr, and only those.
        let c = CString::new("vkGetPhysicalDeviceFeatures2KHR").unwrap();
        assert!(gpdpa(inst, c.as_ptr()).is_some());
        let c = CString::new("vkCreateDevice").unwrap();
        assert!(gpdpa(inst, c.as_ptr()).is_some());
        let c = CString::new("vkCmdCopyBuffer").unwrap();
        assert!(gpdpa(inst, c.as_ptr()).is_none());
        let c = CString::new("vkNotACommand").unwrap();
        assert!(gipa(inst, c.as_ptr()).is_none());

        // A device with no extensions enabled: vkGetDeviceProcAddr gates extension commands.
        let enum_pd: vk::PFN_vkEnumeratePhysicalDevices = std::mem::transmute(get(inst, "vkEnumeratePhysicalDevices").unwrap());
        let mut n = 1u32;
        let mut pd = vk::PhysicalDevice::null();
        assert_eq!(enum_pd(inst, &mut n, &mut pd), vk::Result::SUCCESS);
        let create_dev: vk::PFN_vkCreateDevice = std::mem::transmute(get(inst, "vkCreateDevice").unwrap());
        let prio = [1.0f32];
        let qci = [vk::DeviceQueueCreateInfo::default().queue_family_index(0).queue_priorities(&prio)];
        let dci = vk::DeviceCreateInfo::default().queue_create_infos(&qci);
        let mut dev = vk::Device::null();
        assert_eq!(create_dev(pd, &dci, std::ptr::null(), &mut dev), vk::Result::SUCCESS);
        let gdpa: vk::PFN_vkGetDeviceProcAddr = std::mem::transmute(get(inst, "vkGetDeviceProcAddr").unwrap());
        let dget = |n: &str| {
            let c = CString::new(n).unwrap();
            gdpa(dev, c.as_ptr())
        };
        assert!(dget("vkCmdCopyBuffer").is_some());
        assert!(dget("vkBindBufferMemory2").is_some(), "core 1.1");
        assert!(dget("vkBindBufferMemory2KHR").is_none(), "VK_KHR_bind_memory2 not enabled");
        assert!(dget("vkCmdCopyBuffer2KHR").is_none(), "VK_KHR_copy_commands2 not enabled");
        assert!(dget("vkGetPhysicalDeviceFeatures").is_none(), "not a device command");
        let destroy_dev: vk::PFN_vkDestroyDevice = std::mem::transmute(dget("vkDestroyDevice").unwrap());
        destroy_dev(dev, std::ptr::null());
        let destroy: vk::PFN_vkDestroyInstance = std::mem::transmute(get(inst, "vkDestroyInstance").unwrap());
        destroy(inst, std::ptr::null());
    }
}

/// # Safety
/// `get` resolves commands of the live instance `inst`.
unsafe fn all_device_extensions(get: &dyn Fn(vk::Instance, &str) -> vk::PFN_vkVoidFunction, inst: vk::Instance) -> Vec<String> {
    // SAFETY: signatures per vk.xml; valid instance.
    unsafe {
        let enum_pd: vk::PFN_vkEnumeratePhysicalDevices = std::mem::transmute(get(inst, "vkEnumeratePhysicalDevices").unwrap());
        let mut n = 1u32;
        let mut pd = vk::PhysicalDevice::null();
        assert_eq!(enum_pd(inst, &mut n, &mut pd), vk::Result::SUCCESS);
        let enum_ext: vk::PFN_vkEnumerateDeviceExtensionProperties =
            std::mem::transmute(get(inst, "vkEnumerateDeviceExtensionProperties").unwrap());
        let mut count = 0u32;
        assert_eq!(enum_ext(pd, std::ptr::null(), &mut count, std::ptr::null_mut()), vk::Result::SUCCESS);
        let mut props = vec![vk::ExtensionProperties::default(); count as usize];
        assert_eq!(enum_ext(pd, std::ptr::null(), &mut count, props.as_mut_ptr()), vk::Result::SUCCESS);
        names(&props)
    }
}

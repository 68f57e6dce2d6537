#!/usr/bin/env python3
"""Generate src/dispatch/registry.rs from spec/vk.xml.

The registry is data: every command of the Vulkan versions and extensions Arbor can expose
(with its aliases, dispatch level and origin), and a fallback for each that reports
"not supported" with the command's exact signature (ash's PFN type). The implementation
table in src/dispatch/table.rs overrides the fallbacks; lookups decide by this data.

Usage: python3 tools/gen_registry.py > src/dispatch/registry.rs
"""
import re
import sys
import xml.etree.ElementTree as ET

VERSIONS = ["1_0", "1_1", "1_2"]
INSTANCE_EXTENSIONS = ["VK_KHR_get_physical_device_properties2"]
DEVICE_EXTENSIONS = [
    "VK_KHR_buffer_device_address",
    "VK_EXT_descriptor_indexing",
    "VK_KHR_timeline_semaphore",
    "VK_KHR_synchronization2",
    "VK_KHR_copy_commands2",
    "VK_EXT_host_query_reset",
    "VK_KHR_deferred_host_operations",
    "VK_KHR_acceleration_structure",
    "VK_KHR_ray_tracing_maintenance1",
    "VK_KHR_ray_query",
    "VK_KHR_maintenance1",
    "VK_KHR_maintenance2",
    "VK_KHR_maintenance3",
    "VK_KHR_bind_memory2",
    "VK_KHR_get_memory_requirements2",
    "VK_KHR_dedicated_allocation",
    "VK_NV_cluster_acceleration_structure",
    "VK_NV_partitioned_acceleration_structure",
]

# Types and PFNs ash 0.38 lacks: the module of Arbor's own #[repr(C)] definitions.
LOCAL_TYPES = {
    "VkClusterAccelerationStructureInputInfoNV": "crate::dispatch::nv_cluster",
    "VkClusterAccelerationStructureCommandsInfoNV": "crate::dispatch::nv_cluster",
    "VkPartitionedAccelerationStructureInstancesInputNV": "crate::dispatch::nv_partitioned",
    "VkBuildPartitionedAccelerationStructureInfoNV": "crate::dispatch::nv_partitioned",
}
LOCAL_COMMANDS = {
    "vkGetClusterAccelerationStructureBuildSizesNV": "crate::dispatch::nv_cluster",
    "vkCmdBuildClusterAccelerationStructureIndirectNV": "crate::dispatch::nv_cluster",
    "vkGetPartitionedAccelerationStructuresBuildSizesNV": "crate::dispatch::nv_partitioned",
    "vkCmdBuildPartitionedAccelerationStructuresNV": "crate::dispatch::nv_partitioned",
}

root = ET.parse(sys.argv[1] if len(sys.argv) > 1 else "spec/vk.xml").getroot()
have = set(INSTANCE_EXTENSIONS + DEVICE_EXTENSIONS)
for v in VERSIONS:
    have.add("VK_VERSION_" + v)


def satisfied(expr):
    if expr is None:
        return True
    # ',' = or, '+' = and, parentheses group. Evaluate with Python.
    py = re.sub(r"[A-Za-z0-9_:]+", lambda m: "True" if m.group(0) in have else "False", expr)
    py = py.replace(",", " or ").replace("+", " and ")
    return eval(py)


commands = {}
aliases = {}
for c in root.find("commands"):
    api = c.get("api")
    if api and "vulkan" not in api.split(","):
        continue
    if "alias" in c.attrib:
        aliases[c.get("name")] = c.get("alias")
        continue
    commands[c.find("proto").find("name").text] = c

wanted = {}  # name -> origin
for f in root.findall("feature"):
    api = f.get("api", "")
    if "vulkan" not in api.split(","):
        continue
    m = re.match(r"VK_(?:BASE_|COMPUTE_|GRAPHICS_)?VERSION_(\d)_(\d)$", f.get("name"))
    if not m or f"{m.group(1)}_{m.group(2)}" not in VERSIONS:
        continue
    for req in f.findall("require"):
        if not satisfied(req.get("depends")):
            continue
        for cc in req.findall("command"):
            wanted.setdefault(cc.get("name"), ("core", int(m.group(2))))
ext_type = {}
for e in root.find("extensions"):
    name = e.get("name")
    if name not in have:
        continue
    ext_type[name] = e.get("type")
    for req in e.findall("require"):
        if not satisfied(req.get("depends")):
            continue
        for cc in req.findall("command"):
            wanted.setdefault(cc.get("name"), ("ext", name))


def canonical(n):
    while n in aliases:
        n = aliases[n]
    return n


def level(n):
    c = commands[canonical(n)]
    first = c.find("param").find("type").text
    if n in ("vkGetInstanceProcAddr", "vkGetDeviceProcAddr"):
        return "Global" if n == "vkGetInstanceProcAddr" else "Device"
    if first in ("VkInstance",):
        return "Instance"
    if first == "VkPhysicalDevice":
        return "PhysicalDevice"
    if first in ("VkDevice", "VkQueue", "VkCommandBuffer"):
        return "Device"
    return "Global"


def rust_type(ptype_text, full):
    """full: the param's text with the name removed, e.g. 'const VkFoo*'"""
    base = {
        "void": "c_void", "char": "c_char", "uint32_t": "u32", "int32_t": "i32", "uint64_t": "u64",
        "int64_t": "i64", "size_t": "usize", "float": "f32", "uint8_t": "u8", "uint16_t": "u16",
        "int": "i32", "VkBool32": "vk::Bool32", "VkDeviceSize": "vk::DeviceSize",
        "VkDeviceAddress": "vk::DeviceAddress", "VkSampleMask": "vk::SampleMask",
        "PFN_vkVoidFunction": "vk::PFN_vkVoidFunction",
    }.get(ptype_text)
    if base is None and ptype_text in LOCAL_TYPES:
        base = LOCAL_TYPES[ptype_text] + "::" + ptype_text[2:]
    if base is None:
        assert ptype_text.startswith("Vk"), ptype_text
        base = "vk::" + ptype_text[2:].replace("FlagBits", "Flags")
    t = full.strip()
    arr = re.search(r"\[(\w+)\]", t)
    stars = t.count("*")
    consts = t.split()
    if arr:
        n = arr.group(1)
        n = {"VK_UUID_SIZE": "16"}.get(n, n)
        return f"*const [{base}; {n}]"
    if stars == 0:
        return base
    if stars == 1:
        return ("*const " if t.startswith("const") else "*mut ") + base
    if stars == 2:
        # const T* const*  or  T**  or const T**
        inner = ("*const " if t.startswith("const") else "*mut ") + base
        outer = "*const " if re.search(r"\*\s*const\s*\*", t) else "*mut "
        return outer + inner
    raise ValueError(t)


def snake(name):
    s = name[2:]
    s = re.sub(r"([a-z0-9])([A-Z])", r"\1_\2", s)
    s = re.sub(r"([A-Z]+)([A-Z][a-z])", r"\1_\2", s)
    return s.lower()


def param_list(c):
    out = []
    for p in c.findall("param"):
        api = p.get("api")
        if api and "vulkan" not in api.split(","):
            continue
        pname = p.find("name").text
        ptype = p.find("type").text
        text = "".join(p.itertext())
        text = text.replace(pname, "", 1) if text.rstrip().endswith(pname) or "[" in text else text
        # remove the name occurrence precisely (last occurrence)
        full = "".join(p.itertext())
        idx = full.rfind(pname)
        full = full[:idx] + full[idx + len(pname):]
        full = full.replace(ptype, "", 1)
        out.append((snake("vk" + pname[0].upper() + pname[1:]), rust_type(ptype, (full.replace("struct", "")))))
    return out


def ret_type(c):
    t = c.find("proto").find("type").text
    return {"void": None}.get(t, rust_type(t, ""))


def pfn_of(can):
    return f"@local {LOCAL_COMMANDS[can]}::PFN_{can}" if can in LOCAL_COMMANDS else f"PFN_{can}"


names = sorted(wanted)
allnames = set(names)
print("// @generated by tools/gen_registry.py from spec/vk.xml — do not edit by hand.")
print("#![allow(clippy::all, unused_variables, non_snake_case)]")
print("//! The Vulkan commands Arbor can expose, from the registry: name, the command it aliases,")
print("//! dispatch level and origin, and a fallback entry that reports \"not supported\".")
print("use ash::vk;")
print("use std::ffi::{c_char, c_void};")
print()
print("use super::table::{void_fn, Level, Origin, RegistryEntry};")
print()
print("pub static REGISTRY: &[RegistryEntry] = &[")
for n in names:
    o = wanted[n]
    origin = f"Origin::Core({o[1]})" if o[0] == "core" else f'Origin::Extension("{o[1]}")'
    can = canonical(n)
    print(f'    RegistryEntry {{ name: "{n}", canonical: "{can}", level: Level::{level(n)}, origin: {origin}, fallback: void_fn!({pfn_of(can)} => fallback::{snake(can)}) }},')
print("];")
print()
print("/// One fallback per canonical command: reports the call through the diagnostics channel and")
print("/// returns VK_ERROR_FEATURE_NOT_PRESENT (or zero/nothing where the command returns no VkResult).")
print("pub mod fallback {")
print("    use super::*;")
done = set()
for n in names:
    can = canonical(n)
    if can in done:
        continue
    done.add(can)
    c = commands[can]
    params = ", ".join(f"_{pn}: {pt}" for pn, pt in param_list(c))
    rt = ret_type(c)
    sig = f"    pub unsafe extern \"system\" fn {snake(can)}({params})"
    if rt is None:
        print(sig + " {")
        print(f'        crate::diag::unsupported("{can}");')
        print("    }")
    elif rt == "vk::Result":
        print(sig + " -> vk::Result {")
        print(f'        crate::diag::unsupported("{can}");')
        print("        vk::Result::ERROR_FEATURE_NOT_PRESENT")
        print("    }")
    else:
        print(sig + f" -> {rt} {{")
        print(f'        crate::diag::unsupported("{can}");')
        print("        Default::default()" if rt != "vk::PFN_vkVoidFunction" else "        None")
        print("    }")
print("}")

//! The name → function table. The registry (generated from vk.xml) says which names exist,
//! what they alias, their dispatch level and origin; `IMPLEMENTED` says which canonical
//! commands Arbor implements. Lookups are decided by this data, not by code.
use std::collections::HashMap;
use std::sync::OnceLock;

use ash::vk;

use super::registry::REGISTRY;

pub type VoidFn = unsafe extern "system" fn();

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Level {
    Global,
    Instance,
    PhysicalDevice,
    Device,
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Origin {
    /// Core in Vulkan 1.<minor>.
    Core(u32),
    Extension(&'static str),
}

pub struct RegistryEntry {
    pub name: &'static str,
    pub canonical: &'static str,
    pub level: Level,
    pub origin: Origin,
    pub fallback: VoidFn,
}

/// An implemented command: its `PFN_vk*` type name (the function is coerced to it) and pointer.
pub struct Implemented {
    pub pfn: &'static str,
    pub f: VoidFn,
}

/// `void_fn!(PFN_vkFoo => path::to::function)`: the function coerced to `vk::PFN_vkFoo` (so the
/// compiler checks its signature against the registry's), stored as the table's opaque type.
macro_rules! void_fn {
    ($pfn:ident => $f:path) => {{
        let f: ash::vk::$pfn = $f;
        // SAFETY: function pointers of any signature have the same size; the loader casts back
        // to the command's PFN type before calling.
        unsafe { std::mem::transmute::<ash::vk::$pfn, $crate::dispatch::table::VoidFn>(f) }
    }};
    // A PFN type ash lacks, defined by Arbor (`@local path::PFN_vkFoo`).
    (@local $pfn:path => $f:path) => {{
        let f: $pfn = $f;
        // SAFETY: function pointers of any signature have the same size; the loader casts back
        // to the command's PFN type before calling.
        unsafe { std::mem::transmute::<$pfn, $crate::dispatch::table::VoidFn>(f) }
    }};
}
pub(crate) use void_fn;

/// `imp!(PFN_vkFoo => path::to::function)`: an implemented command (see `void_fn!`).
macro_rules! imp {
    ($pfn:ident => $f:path) => {
        $crate::dispatch::table::Implemented { pfn: stringify!($pfn), f: $crate::dispatch::table::void_fn!($pfn => $f) }
    };
}
pub(crate) use imp;

pub struct Resolved {
    pub entry: &'static RegistryEntry,
    pub f: VoidFn,
    pub implemented: bool,
}

/// Sorted by name and searched by halves: a plain vector, which a leak checker sees as
/// reachable for the life of the process (a hash map's table is pointed into, not at, and
/// showed as "possibly lost" under valgrind; docs/ROBUSTNESS.md, section 3).
fn table() -> &'static [(&'static str, Resolved)] {
    static T: OnceLock<Vec<(&'static str, Resolved)>> = OnceLock::new();
    T.get_or_init(|| {
        let mut implemented: HashMap<&'static str, VoidFn> = HashMap::new();
        for i in super::implemented() {
            implemented.insert(&i.pfn[4..], i.f);
        }
        let mut t: Vec<(&'static str, Resolved)> = REGISTRY
            .iter()
            .map(|e| {
                let (f, implemented) = match implemented.get(e.canonical) {
                    Some(f) => (*f, true),
                    None => (e.fallback, false),
                };
                (e.name, Resolved { entry: e, f, implemented })
            })
            .collect();
        t.sort_by_key(|(name, _)| *name);
        t.dedup_by_key(|(name, _)| *name);
        t
    })
}

pub fn lookup(name: &str) -> Option<&'static Resolved> {
    let t = table();
    t.binary_search_by(|(n, _)| (*n).cmp(name)).ok().map(|i| &t[i].1)
}

pub fn to_pfn(f: VoidFn) -> vk::PFN_vkVoidFunction {
    Some(f)
}

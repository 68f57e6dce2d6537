//! Handles: dispatchable objects carry the loader's word first; non-dispatchable handles are
//! ids in a registry, so a stale or garbage handle is detected instead of dereferenced.
use std::any::Any;
use std::cell::Cell;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock, RwLock};

/// A dispatchable object: `#[repr(C)]` with the loader's word at offset 0, then a type tag.
#[repr(C)]
pub struct Dispatchable<T> {
    /// Owned by the loader (it writes its dispatch table pointer here). Never read by Arbor.
    loader_data: usize,
    tag: u64,
    pub object: Arc<T>,
}

/// Type tags of dispatchable objects (checked on every handle conversion).
pub trait DispatchTag {
    const TAG: u64;
}

// The tags live here, with the handle representation they serve; the object model knows
// nothing of handles.
impl DispatchTag for crate::runtime::Instance {
    const TAG: u64 = 0x4152_424f_5249_4e53; // "ARBORINS"
}

impl DispatchTag for crate::runtime::PhysicalDevice {
    const TAG: u64 = 0x4152_424f_5250_4859; // "ARBORPHY"
}

impl DispatchTag for crate::runtime::Device {
    const TAG: u64 = 0x4152_424f_5244_4556; // "ARBORDEV"
}

impl DispatchTag for crate::runtime::Queue {
    const TAG: u64 = 0x4152_424f_5251_5545; // "ARBORQUE"
}

impl DispatchTag for crate::runtime::command::CommandBuffer {
    const TAG: u64 = 0x4152_424f_5243_4d44; // "ARBORCMD"
}

/// Allocate a dispatchable object and return its handle value (a pointer).
pub fn new_dispatchable<T: DispatchTag>(object: Arc<T>) -> *mut Dispatchable<T> {
    Box::into_raw(Box::new(Dispatchable { loader_data: crate::ICD_LOADER_MAGIC, tag: T::TAG, object }))
}

/// Resolve a dispatchable handle.
///
/// # Safety
/// `ptr` must be null or a handle returned by [`new_dispatchable`] for some type that is still
/// alive (the application's obligation under the Vulkan spec).
pub unsafe fn dispatchable<T: DispatchTag>(ptr: *mut Dispatchable<T>) -> Option<Arc<T>> {
    if ptr.is_null() {
        return None;
    }
    // SAFETY: the caller guarantees ptr came from new_dispatchable and is alive; every
    // Dispatchable<_> has the same layout up to `tag`, which we check before touching `object`.
    let d = unsafe { &*ptr };
    if d.tag != T::TAG {
        crate::diag::report(crate::diag::Level::Error, "handle", "dispatchable handle of the wrong type");
        return None;
    }
    Some(d.object.clone())
}

/// Free a dispatchable object.
///
/// # Safety
/// `ptr` must be null or a live handle from [`new_dispatchable`] not used afterwards.
pub unsafe fn free_dispatchable<T: DispatchTag>(ptr: *mut Dispatchable<T>) -> Option<Arc<T>> {
    // SAFETY: checked the tag first via `dispatchable` (same contract).
    let obj = unsafe { dispatchable(ptr) }?;
    // SAFETY: the handle is live and came from Box::into_raw; the application does not use it again.
    drop(unsafe { Box::from_raw(ptr) });
    Some(obj)
}

/// A registered object, the device it was created on and its Vulkan type name.
struct Entry {
    object: Arc<dyn Any + Send + Sync>,
    /// The owning device (its address; 0 for none).
    owner: usize,
    type_name: &'static str,
}

struct Registry {
    map: RwLock<HashMap<u64, Entry>>,
    next: AtomicU64,
}

fn registry() -> &'static Registry {
    static R: OnceLock<Registry> = OnceLock::new();
    R.get_or_init(|| Registry { map: RwLock::new(HashMap::new()), next: AtomicU64::new(0x1000) })
}

thread_local! {
    /// The device this thread resolved last ([`note_device`]).
    static CURRENT_DEVICE: Cell<usize> = const { Cell::new(0) };
}

/// Called when a command resolves its `VkDevice`: every vkCreate*/vkAllocate* command does so
/// before it registers what it creates, so [`register`] learns the owner without each call
/// site passing it (the leak report of `vkDestroyDevice` needs it).
pub fn note_device(device: &crate::runtime::Device) {
    CURRENT_DEVICE.with(|c| c.set(device as *const _ as usize));
}

/// The Vulkan name of a registered Rust type ("arbor::memory::Buffer" → "VkBuffer").
fn vk_type_name<T>() -> &'static str {
    let full = std::any::type_name::<T>();
    match full.rsplit("::").next().unwrap_or(full) {
        "AccelerationStructure" => "VkAccelerationStructureKHR",
        "DeferredOperation" => "VkDeferredOperationKHR",
        "Memory" => "VkDeviceMemory",
        "Buffer" => "VkBuffer",
        "Fence" => "VkFence",
        "Semaphore" => "VkSemaphore",
        "Event" => "VkEvent",
        "QueryPool" => "VkQueryPool",
        "CommandPool" => "VkCommandPool",
        _ => full,
    }
}

/// Register a non-dispatchable object; the returned id is its handle value (never 0, never reused).
pub fn register<T: Send + Sync + 'static>(object: Arc<T>) -> u64 {
    let r = registry();
    let id = r.next.fetch_add(0x10, Ordering::Relaxed);
    let owner = CURRENT_DEVICE.with(Cell::get);
    r.map.write().unwrap_or_else(|e| e.into_inner()).insert(id, Entry { object, owner, type_name: vk_type_name::<T>() });
    id
}

/// Look a non-dispatchable handle up; None for 0, unknown ids and ids of another type.
pub fn get<T: Send + Sync + 'static>(handle: u64) -> Option<Arc<T>> {
    if handle == 0 {
        return None;
    }
    let map = registry().map.read().unwrap_or_else(|e| e.into_inner());
    map.get(&handle).map(|e| e.object.clone()).and_then(|e| e.downcast::<T>().ok())
}

/// Remove a non-dispatchable handle (destroy). Returns the object if it was of type T.
pub fn unregister<T: Send + Sync + 'static>(handle: u64) -> Option<Arc<T>> {
    if handle == 0 {
        return None;
    }
    let mut map = registry().map.write().unwrap_or_else(|e| e.into_inner());
    let removed = match map.get(&handle) {
        Some(e) if e.object.is::<T>() => map.remove(&handle).and_then(|e| e.object.downcast::<T>().ok()),
        _ => None,
    };
    release_if_empty(&mut map);
    removed
}

/// An empty registry gives its table back, so nothing of it outlives the last object (a
/// leak checker would see the table of a hash map as "possibly lost").
fn release_if_empty(map: &mut HashMap<u64, Entry>) {
    if map.is_empty() {
        map.shrink_to_fit();
    }
}

/// Remove every handle still registered for `device` (it is being destroyed; its children
/// cannot be used any more) and return how many of each Vulkan type there were, sorted by name.
pub fn remove_children(device: &crate::runtime::Device) -> Vec<(&'static str, usize)> {
    let owner = device as *const _ as usize;
    let removed: Vec<Entry> = {
        let mut map = registry().map.write().unwrap_or_else(|e| e.into_inner());
        let ids: Vec<u64> = map.iter().filter(|(_, e)| e.owner == owner).map(|(id, _)| *id).collect();
        let removed = ids.iter().filter_map(|id| map.remove(id)).collect();
        release_if_empty(&mut map);
        removed
    };
    let mut counts: Vec<(&'static str, usize)> = Vec::new();
    for e in &removed {
        match counts.iter_mut().find(|(n, _)| *n == e.type_name) {
            Some((_, c)) => *c += 1,
            None => counts.push((e.type_name, 1)),
        }
    }
    counts.sort();
    // The objects drop here, outside the registry's lock (some hold device memory).
    drop(removed);
    counts
}

//! Which acceleration structures, buffers and memory objects pending submissions use, so that
//! destroying one of them while it is in use is reported at destroy time
//! (`VUID-vkDestroyAccelerationStructureKHR-accelerationStructure-02442`,
//! `VUID-vkDestroyBuffer-buffer-00922`, `VUID-vkFreeMemory-memory-00677`).
//!
//! At submission each batch collects the objects its command buffers name (by handle, and the
//! buffers that the device addresses of builds and copies fall in) into a [`Held`]: it keeps
//! an `Arc` of each and counts it in a process-wide table keyed by the object's address (a key
//! cannot be reused while the `Arc` is held). The batch drops its `Held` when its command
//! buffers have executed, before its semaphores and fence signal, so an application that waited
//! for the fence may destroy the objects without a report.
//!
//! What happens to the pending work: a destroyed structure or buffer stays alive through these
//! `Arc`s (and those the recorded commands hold), so the work finishes; freed memory stops
//! resolving at once (`memory::AddressSpace::free`) while its host backing stays alive, so the
//! work touching it is reported and skipped, never a use after free.
//!
//! This module only counts; reports are the destroy commands' (`dispatch`).
use std::collections::HashMap;
use std::sync::{Arc, LazyLock, Mutex, MutexGuard};

use super::accel::AccelerationStructure;
use super::Device;
use crate::diag;
use crate::memory::{AddressSpace, Buffer, Memory};

/// One object a pending batch uses.
enum Used {
    Structure(Arc<AccelerationStructure>),
    Buffer(Arc<Buffer>),
    Memory(Arc<Memory>),
}

impl Used {
    fn key(&self) -> usize {
        match self {
            Used::Structure(s) => key(&**s),
            Used::Buffer(b) => key(&**b),
            Used::Memory(m) => key(&**m),
        }
    }
}

fn key<T>(object: &T) -> usize {
    object as *const T as usize
}

fn table() -> MutexGuard<'static, HashMap<usize, u32>> {
    static TABLE: LazyLock<Mutex<HashMap<usize, u32>>> = LazyLock::new(Default::default);
    TABLE.lock().unwrap_or_else(|e| e.into_inner())
}

/// How many pending batches use `object` (a structure, buffer or memory object).
pub fn pending_uses<T>(object: &T) -> u32 {
    table().get(&key(object)).copied().unwrap_or(0)
}

/// What a batch's commands use, as they are submitted.
pub struct Collector<'a> {
    memory: &'a AddressSpace,
    used: Vec<Used>,
}

impl<'a> Collector<'a> {
    pub fn new(memory: &'a AddressSpace) -> Collector<'a> {
        Collector { memory, used: Vec::new() }
    }

    /// A structure, its buffer and the buffer's memory.
    pub fn structure(&mut self, s: &Arc<AccelerationStructure>) {
        self.used.push(Used::Structure(s.clone()));
        self.buffer(&s.buffer);
    }

    /// A buffer and its memory.
    pub fn buffer(&mut self, b: &Arc<Buffer>) {
        if let Some((m, _)) = b.memory() {
            self.used.push(Used::Memory(m.clone()));
        }
        self.used.push(Used::Buffer(b.clone()));
    }

    /// The buffer a device address falls in, if any (0 and unresolvable addresses are left to
    /// the command's own checks when it executes).
    pub fn address(&mut self, address: u64) {
        if address == 0 {
            return;
        }
        if let Ok(r) = self.memory.resolve(address, 1) {
            self.buffer(&r.buffer);
        }
    }

    /// Count what was collected as in use until the returned `Held` drops.
    pub fn hold(mut self) -> Held {
        self.used.sort_by_key(Used::key);
        self.used.dedup_by_key(|u| u.key());
        let mut t = table();
        for u in &self.used {
            *t.entry(u.key()).or_insert(0) += 1;
        }
        Held { used: self.used }
    }
}

/// The objects one pending batch uses; released when dropped.
pub struct Held {
    used: Vec<Used>,
}

impl Drop for Held {
    fn drop(&mut self) {
        if self.used.is_empty() {
            return;
        }
        let mut t = table();
        for u in &self.used {
            let k = u.key();
            if let Some(n) = t.get_mut(&k) {
                *n -= 1;
                if *n == 0 {
                    t.remove(&k);
                }
            }
        }
        // Nothing pending: give the table back (teardown leaves nothing behind).
        if t.is_empty() {
            t.shrink_to_fit();
        }
    }
}

/// At destroy time: report `object` (`what`, a handle for the message) if pending batches use
/// it, with `vuid` and what becomes of the work (`fate`). In strict mode the device is lost.
pub fn check_destroy<T>(device: Option<&Device>, object: &T, command: &str, vuid: &str, what: &str, fate: &str) {
    let n = pending_uses(object);
    if n == 0 {
        return;
    }
    diag::vuid(vuid, command, &format!("{what} is used by {n} pending batch(es) of submitted commands; {fate}"));
    if let Some(d) = device.filter(|_| diag::strict()) {
        diag::report(diag::Level::Error, command, "strict mode: device lost");
        d.mark_lost();
    }
}

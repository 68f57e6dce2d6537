//! Query pools: per query one u64 value and an availability bit, written by the queue that
//! executes the query's command (or reset by the host), read by vkGetQueryPoolResults and
//! vkCmdCopyQueryPoolResults.
//!
//! Supported: TIMESTAMP. The acceleration-structure query types are accepted by [`QueryKind`]
//! and written through [`QueryPool::write`] by the acceleration-structure commands
//! (vkCmdWriteAccelerationStructuresPropertiesKHR and its host twin); nothing else here needs
//! to change for them. Occlusion and pipeline-statistics queries need a graphics queue or a
//! feature Arbor does not offer: pools of those types can be created (occlusion is core) but
//! every command that would use them is diagnosed.
use std::sync::atomic::AtomicBool;
use std::sync::Mutex;

use ash::vk;

use super::sync::{self, Deadline, WaitOutcome};

/// What a pool's queries measure.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum QueryKind {
    Timestamp,
    /// One of the acceleration-structure property queries (compacted size, serialization size,
    /// size, bottom-level pointers): one u64 per query, written by the AS commands.
    AccelerationStructure(vk::QueryType),
    /// Occlusion / pipeline statistics / others: creatable, never written (diagnosed on use).
    Unsupported(vk::QueryType),
}

impl QueryKind {
    pub fn from_type(t: vk::QueryType) -> QueryKind {
        match t {
            vk::QueryType::TIMESTAMP => QueryKind::Timestamp,
            vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR
            | vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR
            | vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR
            | vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_BOTTOM_LEVEL_POINTERS_KHR => {
                QueryKind::AccelerationStructure(t)
            }
            t => QueryKind::Unsupported(t),
        }
    }

    /// Whether PARTIAL results are meaningful (not for timestamps nor AS properties).
    pub fn allows_partial(&self) -> bool {
        matches!(self, QueryKind::Unsupported(_))
    }
}

#[derive(Clone, Copy, Default, Debug)]
struct Slot {
    value: u64,
    available: bool,
}

/// One `VkQueryPool`.
pub struct QueryPool {
    pub query_type: vk::QueryType,
    pub kind: QueryKind,
    pub count: u32,
    slots: Mutex<Vec<Slot>>,
}

/// A range check failure (which bound, for the VUID).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum RangeError {
    /// firstQuery >= queryCount.
    First,
    /// firstQuery + count > queryCount.
    Count,
}

/// Results of reading queries (shared by the host read and the copy command).
pub struct ReadFlags {
    pub wide: bool,
    pub with_availability: bool,
    pub partial: bool,
    pub wait: bool,
}

impl ReadFlags {
    pub fn from_vk(f: vk::QueryResultFlags) -> ReadFlags {
        ReadFlags {
            wide: f.contains(vk::QueryResultFlags::TYPE_64),
            with_availability: f.contains(vk::QueryResultFlags::WITH_AVAILABILITY),
            partial: f.contains(vk::QueryResultFlags::PARTIAL),
            wait: f.contains(vk::QueryResultFlags::WAIT),
        }
    }

    /// Bytes one query's result occupies (value + optional availability).
    pub fn element_size(&self) -> u64 {
        let w = if self.wide { 8 } else { 4 };
        w * (1 + self.with_availability as u64)
    }
}

impl QueryPool {
    pub fn new(query_type: vk::QueryType, count: u32) -> QueryPool {
        QueryPool {
            query_type,
            kind: QueryKind::from_type(query_type),
            count,
            slots: Mutex::new(vec![Slot::default(); count as usize]),
        }
    }

    fn slots(&self) -> std::sync::MutexGuard<'_, Vec<Slot>> {
        self.slots.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub fn check_range(&self, first: u32, count: u32) -> Result<(), RangeError> {
        if first >= self.count {
            return Err(RangeError::First);
        }
        if first as u64 + count as u64 > self.count as u64 {
            return Err(RangeError::Count);
        }
        Ok(())
    }

    /// Reset queries to unavailable (host reset or vkCmdResetQueryPool executing).
    pub fn reset(&self, first: u32, count: u32) {
        let mut s = self.slots();
        let end = (first as usize + count as usize).min(s.len());
        for slot in s.iter_mut().take(end).skip(first as usize) {
            *slot = Slot::default();
        }
    }

    /// Record a query's result and make it available. The hook for every query type: the
    /// timestamp command and the acceleration-structure property commands write through it.
    /// Returns false when the query was already available (written twice without a reset).
    pub fn write(&self, query: u32, value: u64) -> bool {
        let was_available = {
            let mut s = self.slots();
            let Some(slot) = s.get_mut(query as usize) else { return false };
            let was = slot.available;
            *slot = Slot { value, available: true };
            was
        };
        sync::notify();
        !was_available
    }

    pub fn is_available(&self, query: u32) -> bool {
        self.slots().get(query as usize).is_some_and(|s| s.available)
    }

    /// Wait until the queries of the range are available (WAIT flag of a host read). `cancel`:
    /// stop early; [`WaitOutcome::Stalled`] when nothing pending can write them (`stall`).
    pub fn wait_available(&self, first: u32, count: u32, deadline: Deadline, cancel: Option<&AtomicBool>) -> WaitOutcome {
        let end = first as usize + count as usize;
        sync::wait_or_stall(deadline, cancel, || {
            let s = self.slots();
            s.get(first as usize..end).is_some_and(|r| r.iter().all(|q| q.available))
        })
    }

    /// Write the results of `[first, first + count)` into `out` (element `i` at `i * stride`),
    /// following the vkGetQueryPoolResults rules: values of unavailable queries are not
    /// written unless PARTIAL (then 0: no partial result exists for the supported types);
    /// availability is written as 0/1 after the value. Returns whether every query was
    /// available. The caller has checked that `out` is large enough.
    pub fn read_into(&self, first: u32, count: u32, stride: u64, flags: &ReadFlags, out: &mut [u8]) -> bool {
        let s = self.slots();
        let mut all = true;
        for i in 0..count as usize {
            let slot = s.get(first as usize + i).copied().unwrap_or_default();
            all &= slot.available;
            let base = i * stride as usize;
            let put = |out: &mut [u8], at: usize, v: u64| {
                if flags.wide {
                    if let Some(d) = out.get_mut(at..at + 8) {
                        d.copy_from_slice(&v.to_le_bytes());
                    }
                } else if let Some(d) = out.get_mut(at..at + 4) {
                    // A value wider than 32 bits wraps (the spec allows wrap or saturate).
                    d.copy_from_slice(&(v as u32).to_le_bytes());
                }
            };
            let w = if flags.wide { 8 } else { 4 };
            if slot.available {
                put(out, base, slot.value);
            } else if flags.partial {
                put(out, base, 0);
            }
            if flags.with_availability {
                put(out, base + w, slot.available as u64);
            }
        }
        all
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn read_rules() {
        let p = QueryPool::new(vk::QueryType::TIMESTAMP, 4);
        assert!(p.write(1, 0x1_0000_0005));
        assert!(!p.write(1, 7), "second write without reset is reported");
        let mut out = vec![0xAAu8; 64];
        let f = ReadFlags { wide: true, with_availability: true, partial: false, wait: false };
        assert!(!p.read_into(0, 2, 16, &f, &mut out));
        assert_eq!(&out[0..8], &[0xAA; 8], "unavailable value untouched");
        assert_eq!(u64::from_le_bytes(out[8..16].try_into().unwrap()), 0);
        assert_eq!(u64::from_le_bytes(out[16..24].try_into().unwrap()), 7);
        assert_eq!(u64::from_le_bytes(out[24..32].try_into().unwrap()), 1);
        let f32 = ReadFlags { wide: false, with_availability: false, partial: false, wait: false };
        p.write(2, 0x1_0000_0009);
        let mut out = vec![0u8; 8];
        assert!(p.read_into(1, 2, 4, &f32, &mut out));
        assert_eq!(u32::from_le_bytes(out[4..8].try_into().unwrap()), 9, "wraps to 32 bits");
        p.reset(0, 4);
        assert!(!p.is_available(1));
        assert_eq!(p.check_range(4, 0), Err(RangeError::First));
        assert_eq!(p.check_range(2, 3), Err(RangeError::Count));
    }
}

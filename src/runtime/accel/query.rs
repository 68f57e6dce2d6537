//! The properties of built structures that `vkCmdWriteAccelerationStructuresPropertiesKHR`
//! and `vkWriteAccelerationStructuresPropertiesKHR` report (compacted size, serialization
//! size, size, BLAS pointer count), read from each structure's header in device memory.
//!
//! This module only reads; where a value goes (a query pool, the application's array) is the
//! caller's.
use std::sync::Arc;

use ash::vk;

use super::AccelerationStructure;
use crate::accel::{self, BuildFlags};
use crate::diag;

/// One property of a structure for vkCmdWrite/vkWriteAccelerationStructuresPropertiesKHR.
/// None (reported) when the structure or query type is invalid.
pub fn property(s: Option<&AccelerationStructure>, query_type: vk::QueryType, command: &str, index: usize) -> Option<u64> {
    let Some(s) = s else {
        diag::vuid(&format!("VUID-{command}-pAccelerationStructures-parameter"), command, &format!("element {index} is not a valid acceleration structure"));
        return None;
    };
    let bytes = s.bytes().ok()?;
    let Some(h) = accel::header(bytes) else {
        diag::vuid(&format!("VUID-{command}-pAccelerationStructures-04964"), command, &format!("element {index} has not been built"));
        return None;
    };
    match query_type {
        vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR => {
            if !h.flags.contains(BuildFlags::ALLOW_COMPACTION) {
                diag::vuid(
                    &format!("VUID-{command}-accelerationStructures-03431"),
                    command,
                    &format!("element {index} was not built with ALLOW_COMPACTION"),
                );
                return None;
            }
            accel::compacted_size(bytes)
        }
        vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR => accel::serialized_size(bytes),
        vk::QueryType::ACCELERATION_STRUCTURE_SIZE_KHR => Some(h.used_size),
        vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_BOTTOM_LEVEL_POINTERS_KHR => Some(accel::blas_references(bytes).len() as u64),
        other => {
            diag::vuid(&format!("VUID-{command}-queryType-06742"), command, &format!("query type {other:?} is not an acceleration-structure property"));
            None
        }
    }
}

/// The properties of `structures`, in order: None (reported) for each invalid one.
pub fn properties(structures: &[Option<Arc<AccelerationStructure>>], query_type: vk::QueryType, command: &str) -> Vec<Option<u64>> {
    structures.iter().enumerate().map(|(i, s)| property(s.as_deref(), query_type, command, i)).collect()
}

//! Acceleration structures in the object model: the `VkAccelerationStructureKHR` view object
//! (with the checks of its creation) and the owned (lowered) descriptions of builds that
//! recorded commands keep until they run.
//! The submodules execute them, with the valid-usage checks the driver can see, including those
//! about data in device memory that no validation layer can check:
//!
//! - [`inputs`]: where a command reads (device memory, or application host memory for host
//!   commands) and the `accel::DeviceView` adapter over the address space;
//! - [`validate`]: the VUID checks of a build command, before anything is written;
//! - [`build`]: running the checked builds (and where: inline or on the pool);
//! - [`copy`]: clone, compaction, serialization and deserialization;
//! - [`query`]: the properties written by the property commands;
//! - [`command`]: the recorded commands a queue executes and the host commands' entry points.
//!
//! An acceleration structure is only a view (buffer, offset, size, type): its content lives in
//! device memory and is produced by `crate::accel`. Nothing about a structure's content is kept
//! here (principle 1). This module sees no raw application pointer and contains no `unsafe`:
//! mutable views of memory come from `crate::memory::region`, host addresses are read through
//! the `HostMemory` the dispatch layer vouched for, and handle values are resolved through the
//! lookup the dispatch layer passes (`inputs::StructureLookup`): the handle registry is not
//! touched from here.
use std::sync::Arc;

use ash::vk;

use crate::accel::{self, AsType, BuildFlags, GeometryShape, IndexType, VertexFormat};
use crate::diag;
use crate::memory::{AccessError, Buffer};
use crate::runtime::Device;

pub mod clas;
pub mod build;
pub mod command;
pub mod copy;
pub mod inputs;
pub mod ptlas;
pub mod query;
pub mod validate;

pub use build::execute_builds;
pub use command::{BuildCommand, BuildKind, CopyCommand, WritePropertiesCommand};
pub use copy::{execute_copy, Copy};
pub use inputs::{DeviceInputs, HostInputs, InputError, InputMemory};
pub use query::{properties, property};

/// Required alignment of scratch addresses (minAccelerationStructureScratchOffsetAlignment).
pub const SCRATCH_ALIGNMENT: u64 = 128;
/// Alignment of acceleration-structure offsets and addresses.
pub const STRUCTURE_ALIGNMENT: u64 = 256;

/// One `VkAccelerationStructureKHR`.
pub struct AccelerationStructure {
    pub buffer: Arc<Buffer>,
    pub offset: u64,
    pub size: u64,
    /// VkAccelerationStructureTypeKHR as created (TOP_LEVEL 0, BOTTOM_LEVEL 1, GENERIC 2).
    pub create_type: vk::AccelerationStructureTypeKHR,
    pub create_flags: vk::AccelerationStructureCreateFlagsKHR,
}

/// A `VkAccelerationStructureCreateInfoKHR`, lowered (the buffer handle resolved).
pub struct CreateInfo {
    pub buffer: Option<Arc<Buffer>>,
    pub offset: u64,
    pub size: u64,
    pub ty: vk::AccelerationStructureTypeKHR,
    pub create_flags: vk::AccelerationStructureCreateFlagsKHR,
    pub device_address: u64,
}

impl AccelerationStructure {
    /// vkCreateAccelerationStructureKHR: the view `info` describes, once the rules of the
    /// create info are checked (violations reported; the fatal ones return the error code).
    pub fn create(device: &Device, info: CreateInfo) -> Result<AccelerationStructure, vk::Result> {
        const CMD: &str = "vkCreateAccelerationStructureKHR";
        if !device.features.acceleration_structure {
            diag::vuid("VUID-vkCreateAccelerationStructureKHR-accelerationStructure-03611", CMD, "the accelerationStructure feature is not enabled");
        }
        let Some(buffer) = info.buffer else {
            diag::vuid("VUID-VkAccelerationStructureCreateInfoKHR-buffer-parameter", CMD, "buffer is not a valid VkBuffer");
            return Err(vk::Result::ERROR_INITIALIZATION_FAILED);
        };
        if !info.offset.is_multiple_of(STRUCTURE_ALIGNMENT) {
            diag::vuid("VUID-VkAccelerationStructureCreateInfoKHR-offset-03734", CMD, "offset must be a multiple of 256");
        }
        if info.offset.checked_add(info.size).is_none_or(|end| end > buffer.size) {
            diag::vuid("VUID-VkAccelerationStructureCreateInfoKHR-offset-03616", CMD, "offset + size exceeds the buffer size");
            return Err(vk::Result::ERROR_INITIALIZATION_FAILED);
        }
        if !buffer.usage.contains(vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR) {
            diag::vuid(
                "VUID-VkAccelerationStructureCreateInfoKHR-buffer-03614",
                CMD,
                "buffer lacks ACCELERATION_STRUCTURE_STORAGE_BIT_KHR usage",
            );
        }
        let replay = info.create_flags.contains(vk::AccelerationStructureCreateFlagsKHR::DEVICE_ADDRESS_CAPTURE_REPLAY);
        if replay && !device.features.acceleration_structure_capture_replay {
            diag::vuid(
                "VUID-VkAccelerationStructureCreateInfoKHR-createFlags-03613",
                CMD,
                "DEVICE_ADDRESS_CAPTURE_REPLAY needs the accelerationStructureCaptureReplay feature",
            );
        }
        if info.device_address != 0 {
            if !replay {
                diag::vuid(
                    "VUID-VkAccelerationStructureCreateInfoKHR-deviceAddress-03612",
                    CMD,
                    "deviceAddress is not 0 but CAPTURE_REPLAY is not set",
                );
            }
            // Addresses are buffer address + offset: a replayed address is honoured when the
            // buffer was placed where it was at capture time.
            if let Some(a) = buffer.device_address() {
                if a + info.offset != info.device_address {
                    return Err(vk::Result::ERROR_INVALID_OPAQUE_CAPTURE_ADDRESS_KHR);
                }
            }
        }
        Ok(AccelerationStructure {
            buffer,
            offset: info.offset,
            size: info.size,
            create_type: info.ty,
            create_flags: info.create_flags,
        })
    }

    /// Device address: the buffer's address plus the offset (buffers are placed on 256-aligned
    /// addresses, so this is 256-aligned too).
    pub fn address(&self) -> Option<u64> {
        self.buffer.device_address().map(|a| a + self.offset)
    }

    /// The structure's bytes (shared view).
    pub fn bytes(&self) -> Result<&[u8], AccessError> {
        self.buffer.bytes(self.offset, self.size)
    }

    /// Identity of the backing memory and the byte range, for overlap checks.
    pub fn memory_range(&self, len: u64) -> Option<(usize, u64, u64)> {
        self.buffer.memory_range(self.offset, len.min(self.size))
    }

    /// Whether the buffer is bound to host-visible memory (all Arbor memory is).
    pub fn host_visible(&self) -> bool {
        self.buffer.memory().is_some()
    }
}

/// Owned geometry description captured at record time (addresses, not data: the data is read
/// when the command executes).
#[derive(Clone, Debug)]
pub enum GeometryDesc {
    Triangles {
        vertex_format: vk::Format,
        vertex_data: u64,
        vertex_stride: u64,
        max_vertex: u32,
        index_type: vk::IndexType,
        index_data: u64,
        transform_data: u64,
    },
    Aabbs {
        data: u64,
        stride: u64,
    },
    Instances {
        array_of_pointers: bool,
        data: u64,
    },
    /// A geometry type Arbor does not support.
    Unsupported(vk::GeometryTypeKHR),
}

#[derive(Clone, Debug)]
pub struct GeometryInfo {
    pub desc: GeometryDesc,
    pub flags: vk::GeometryFlagsKHR,
}

/// One `VkAccelerationStructureBuildRangeInfoKHR`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RangeInfo {
    pub primitive_count: u32,
    pub primitive_offset: u32,
    pub first_vertex: u32,
    pub transform_offset: u32,
}

impl RangeInfo {
    pub fn from_bytes(b: &[u8]) -> RangeInfo {
        let w = |i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        RangeInfo { primitive_count: w(0), primitive_offset: w(4), first_vertex: w(8), transform_offset: w(12) }
    }
}

/// Where a build's range records come from.
#[derive(Clone, Debug)]
pub enum Ranges {
    /// Given by the application at record time (direct and host builds).
    Direct(Vec<RangeInfo>),
    /// Read from device memory when the command executes (indirect builds).
    Indirect { address: u64, stride: u32, max_primitive_counts: Vec<u32> },
}

/// Owned description of one element of `pInfos`.
#[derive(Clone)]
pub struct BuildInfo {
    pub ty: vk::AccelerationStructureTypeKHR,
    pub flags: vk::BuildAccelerationStructureFlagsKHR,
    pub mode: vk::BuildAccelerationStructureModeKHR,
    pub src: Option<Arc<AccelerationStructure>>,
    /// Handle value of src as given (to report a dangling handle).
    pub src_handle: u64,
    pub dst: Option<Arc<AccelerationStructure>>,
    pub dst_handle: u64,
    pub scratch: u64,
    /// geometryCount as given (the arrays may have been missing).
    pub geometry_count: u32,
    pub geometries: Vec<GeometryInfo>,
    pub ranges: Ranges,
}

/// Outcome of a command that checks valid usage: `Err(DeviceLost)` in strict mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeviceLost;

fn to_as_type(t: vk::AccelerationStructureTypeKHR) -> Option<AsType> {
    match t {
        vk::AccelerationStructureTypeKHR::TOP_LEVEL => Some(AsType::TopLevel),
        vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL => Some(AsType::BottomLevel),
        _ => None,
    }
}

/// The size-query shape of a geometry; None for unsupported formats/types.
pub fn shape_of(g: &GeometryInfo) -> Option<GeometryShape> {
    Some(match &g.desc {
        GeometryDesc::Triangles { vertex_format, max_vertex, index_type, transform_data, .. } => GeometryShape::Triangles {
            format: VertexFormat::from_vk(vertex_format.as_raw())?,
            index_type: IndexType::from_vk(index_type.as_raw())?,
            max_vertex: *max_vertex,
            has_transform: *transform_data != 0,
        },
        GeometryDesc::Aabbs { .. } => GeometryShape::Aabbs,
        GeometryDesc::Instances { .. } => GeometryShape::Instances,
        GeometryDesc::Unsupported(_) => return None,
    })
}

/// vkGetAccelerationStructureBuildSizesKHR.
pub fn build_sizes(
    ty: vk::AccelerationStructureTypeKHR,
    flags: vk::BuildAccelerationStructureFlagsKHR,
    geometries: &[GeometryInfo],
    max_primitive_counts: &[u32],
) -> Option<accel::BuildSizes> {
    let ty = to_as_type(ty)?;
    let shapes: Option<Vec<_>> = geometries.iter().map(shape_of).collect();
    Some(accel::build_sizes(ty, BuildFlags(flags.as_raw()), &shapes?, max_primitive_counts))
}

/// Whether two (memory id, start, end) ranges share a byte; an unknown range overlaps nothing.
fn overlaps(a: Option<(usize, u64, u64)>, b: Option<(usize, u64, u64)>) -> bool {
    match (a, b) {
        (Some((ma, sa, ea)), Some((mb, sb, eb))) => ma == mb && sa < eb && sb < ea,
        _ => false,
    }
}

/// Marks a destination invalid (a skipped build or copy): its first bytes are enough for the
/// header check every later use makes.
fn mark_invalid(dst: &AccelerationStructure) {
    let _ = dst.buffer.with_slice_mut(dst.offset, dst.size.min(4096), accel::mark_invalid);
}

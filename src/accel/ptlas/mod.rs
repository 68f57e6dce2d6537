//! Partitioned top-level structures (VK_NV_partitioned_acceleration_structure), as a pure
//! library: the sizes of a blob, a build that applies WRITE_INSTANCE, UPDATE_INSTANCE and
//! WRITE_PARTITION_TRANSLATION records to the state a blob holds (from scratch, in place or
//! from another blob), rebuilding only the partitions the records touch and then the top
//! level, and the hook that lets traversal walk a PTLAS exactly like a KHR TLAS.
//!
//! The blob (`layout`) holds every piece of persistent state, so a PTLAS is fully described by
//! its bytes; its traversable part is an ordinary top-level structure embedded in it, whose
//! top region points at per-partition subtrees (`tree`). The format is documented in
//! docs/PTLAS.md.
//!
//! Must not touch: device memory (the caller hands in the records' bytes and a `DeviceView` for
//! the BLAS bounds), diagnostics, anything of the driver.
mod build;
mod check;
mod layout;
mod tree;

#[cfg(test)]
mod tests;

use bytemuck::{Pod, Zeroable};

pub use check::{check_ops, RecordNotes, RecordViolation, INSTANCE_FLAGS_ALL};
pub use layout::{PtlasHeader, NO_ROOT, PTLAS_MAGIC, PTLAS_VERSION};

/// VK_PARTITIONED_ACCELERATION_STRUCTURE_PARTITION_INDEX_GLOBAL_NV.
pub const PARTITION_INDEX_GLOBAL: u32 = u32::MAX;
/// VK_PARTITIONED_ACCELERATION_STRUCTURE_INSTANCE_FLAG_ENABLE_EXPLICIT_BOUNDING_BOX_NV.
pub const INSTANCE_FLAG_EXPLICIT_BOUNDING_BOX: u32 = 0x10;
/// The instance flag bits a PTLAS shares with VkGeometryInstanceFlagBitsKHR (bits 0–3).
pub const INSTANCE_FLAGS_SHARED_WITH_KHR: u32 = 0xf;

/// Op types of VkBuildPartitionedAccelerationStructureIndirectCommandNV.
pub const OP_WRITE_INSTANCE: u32 = 0;
pub const OP_UPDATE_INSTANCE: u32 = 1;
pub const OP_WRITE_PARTITION_TRANSLATION: u32 = 2;

pub const WRITE_INSTANCE_SIZE: usize = 104;
pub const UPDATE_INSTANCE_SIZE: usize = 16;
pub const WRITE_TRANSLATION_SIZE: usize = 16;
pub const INDIRECT_COMMAND_SIZE: usize = 24;

/// VkPartitionedAccelerationStructureWriteInstanceDataNV as it lies in device memory.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct WriteInstance {
    pub transform: [f32; 12],
    pub explicit_aabb: [f32; 6],
    pub instance_id: u32,
    pub instance_mask: u32,
    pub instance_contribution_to_hit_group_index: u32,
    pub instance_flags: u32,
    pub instance_index: u32,
    pub partition_index: u32,
    pub acceleration_structure: u64,
}
const _: () = assert!(std::mem::size_of::<WriteInstance>() == WRITE_INSTANCE_SIZE);

/// VkPartitionedAccelerationStructureUpdateInstanceDataNV.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct UpdateInstance {
    pub instance_index: u32,
    pub instance_contribution_to_hit_group_index: u32,
    pub acceleration_structure: u64,
}
const _: () = assert!(std::mem::size_of::<UpdateInstance>() == UPDATE_INSTANCE_SIZE);

/// VkPartitionedAccelerationStructureWritePartitionTranslationDataNV.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct WriteTranslation {
    pub partition_index: u32,
    pub partition_translation: [f32; 3],
}
const _: () = assert!(std::mem::size_of::<WriteTranslation>() == WRITE_TRANSLATION_SIZE);

/// VkBuildPartitionedAccelerationStructureIndirectCommandNV.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq)]
pub struct IndirectCommand {
    pub op_type: u32,
    pub arg_count: u32,
    pub start_address: u64,
    pub stride_in_bytes: u64,
}
const _: () = assert!(std::mem::size_of::<IndirectCommand>() == INDIRECT_COMMAND_SIZE);

/// VkPartitionedAccelerationStructureInstancesInputNV with its translation flag.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Input {
    pub flags: u32,
    pub instance_count: u32,
    pub max_instance_per_partition_count: u32,
    pub partition_count: u32,
    pub max_instance_in_global_partition_count: u32,
    /// VkPartitionedAccelerationStructureFlagsNV::enablePartitionTranslation.
    pub translation: bool,
}

/// `count` records of `size` bytes each, `stride` apart from the start of `data`.
#[derive(Clone, Copy, Debug, Default)]
pub struct Strided<'a> {
    pub data: &'a [u8],
    pub count: u32,
    pub stride: u64,
}

impl<'a> Strided<'a> {
    /// Record k as T; None when it lies outside `data`.
    pub fn get<T: Pod>(&self, k: u32) -> Option<T> {
        let size = std::mem::size_of::<T>();
        let stride = if self.stride == 0 { size as u64 } else { self.stride };
        let off = usize::try_from((k as u64).checked_mul(stride)?).ok()?;
        Some(bytemuck::pod_read_unaligned(self.data.get(off..off.checked_add(size)?)?))
    }
    /// Bytes spanned by `count` records of T at `stride` (0 = packed).
    pub fn span<T>(count: u32, stride: u64) -> u64 {
        let size = std::mem::size_of::<T>() as u64;
        let stride = if stride == 0 { size } else { stride };
        if count == 0 {
            0
        } else {
            (count as u64 - 1).saturating_mul(stride).saturating_add(size)
        }
    }
}

/// The op records of one build, by type (the order in which they are applied).
#[derive(Clone, Copy, Debug, Default)]
pub struct Ops<'a> {
    pub writes: Strided<'a>,
    pub updates: Strided<'a>,
    pub translations: Strided<'a>,
}

/// Where a build starts from.
#[derive(Clone, Copy, Debug)]
pub enum Source<'a> {
    /// srcAccelerationStructureData = 0: every slot starts disabled.
    Empty,
    /// src == dst: the state dst holds.
    InPlace,
    /// Another blob, left unmodified.
    Other(&'a [u8]),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BuildSizes {
    pub acceleration_structure_size: u64,
    pub build_scratch_size: u64,
    pub update_scratch_size: u64,
}

#[derive(Clone, Debug, PartialEq)]
pub enum PtlasError {
    DestinationTooSmall { needed: u64, got: u64 },
    ScratchTooSmall { needed: u64, got: u64 },
    /// The source is not a valid PTLAS.
    InvalidSource,
    /// A record of op `op` (its index `record`) names an instance at or past instanceCount.
    InstanceIndex { op: u32, record: u32, index: u32 },
    /// A record names a partition at or past partitionCount (and not the global one).
    PartitionIndex { op: u32, record: u32, index: u32 },
    /// A partition would hold more instances than it was laid out for.
    PartitionFull { record: u32, partition: u32 },
    /// WRITE_PARTITION_TRANSLATION on a structure built without partition translation.
    TranslationNotEnabled { record: u32 },
    /// A record lies outside the bytes given for its op.
    RecordUnreadable { op: u32, record: u32 },
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BuildReport {
    pub used_size: u64,
    /// Partitions whose subtree was rebuilt (the global partition counts as one).
    pub rebuilt_partitions: u32,
    /// Partitions whose tree was refitted (only records of existing leaves changed).
    pub refitted_partitions: u32,
    pub active_instances: u32,
    /// UPDATE_INSTANCE records naming a slot never written (ignored).
    pub ignored_updates: u32,
    /// The source's capacities differed from this build's: the state was laid out anew.
    pub relaid: bool,
}

/// Sizes for `vkGetPartitionedAccelerationStructuresBuildSizesNV`: the blob for these counts
/// (which holds any smaller build) and the scratch a build uses (one dirty flag per partition,
/// never zero).
pub fn build_sizes(input: &Input) -> BuildSizes {
    let c = layout::Capacities::of(input);
    let s = layout::sections(&c);
    let scratch = build::scratch_size(&c);
    BuildSizes { acceleration_structure_size: s.end, build_scratch_size: scratch, update_scratch_size: scratch }
}

/// Apply `ops` to the state `source` names and write the result to `dst` (at least
/// `build_sizes(input).acceleration_structure_size` bytes). Deterministic: the bytes depend only
/// on the state reached and the capacities. On error dst is marked invalid.
pub fn build(input: &Input, ops: &Ops, view: &dyn super::DeviceView, source: Source, dst: &mut [u8], scratch: &mut [u8]) -> Result<BuildReport, PtlasError> {
    let r = build::build(input, ops, view, source, dst, scratch);
    if r.is_err() {
        mark_invalid(dst);
    }
    r
}

/// The embedded top-level structure traversal walks when `bytes` is a valid PTLAS.
pub fn traversable(bytes: &[u8]) -> Option<&[u8]> {
    layout::embedded(bytes)
}

/// The header at the start of `bytes` when it is a self-consistent PTLAS header (`bytes` may
/// hold the header alone: its `used_size` says how many bytes the whole blob spans).
pub fn header(bytes: &[u8]) -> Option<PtlasHeader> {
    layout::parse_header(bytes)
}

/// Bytes of the PTLAS header (what `header` needs to read).
pub const HEADER_SIZE: usize = layout::PTLAS_HEADER_SIZE;

/// Clears the header's identifying words: traversal then finds nothing.
pub fn mark_invalid(dst: &mut [u8]) {
    let n = dst.len().min(layout::PTLAS_HEADER_SIZE);
    dst[..n].fill(0);
}

//! Pure acceleration-structure library: no Vulkan handles, no FFI, no unsafe.
//!
//! Owns: geometry views → primitive references (in the caller's scratch) → binned-SAH binary BVH →
//! collapsed BVH4 with conservatively quantised child boxes → the bytes of the structure; refit;
//! copy/compact/serialize; traversal per the Vulkan ray traversal rules; metrics and validation.
//! Must not touch: device memory resolution (the driver passes slices and a `DeviceView`),
//! diagnostics, anything Vulkan-handle shaped, any other module of the driver (checked by
//! tests/layering.rs). The public contract is `docs/ACCEL_API.md`.
//!
//! Modules: `build` (the pipeline and its stages), `encode` (the bytes of nodes, leaves and
//! instances), `params` (every tuning number; evidence in docs/TUNING.md), `geometry` (boxes,
//! references, bounds), `primitive` (reading primitives from geometry), `tree` (the binary
//! tree in scratch and its collapse rule), `layout` (the stored format), `input` (decoding
//! vertices, indices, instances), `refit`, `copy`, `traverse`, `metrics`.
#![forbid(unsafe_code)]

mod build;
pub mod clas;
mod check;
mod checksum;
mod copy;
mod encode;
mod geometry;
mod input;
mod layout;
mod metrics;
mod params;
mod primitive;
pub mod ptlas;
mod refit;
mod traverse;
mod tree;

#[cfg(test)]
mod testing;
#[cfg(test)]
mod tests;

use std::collections::HashMap;

pub use copy::{
    blas_references, clone_into, compact_into, compacted_size, compatible, deserialize, deserialize_relocated, serialize,
    serialized_size, CopyError, ACCEL_FORMAT_UUID, PAR_COPY_CHUNK,
};
pub use input::{fetch_aabb, fetch_triangle};
pub use check::Reason as CheckReason;
pub use layout::{mark_invalid, Header};

/// The header of a valid structure; for a PTLAS (`ptlas`), that of the top-level structure it
/// embeds, which is what traversal walks.
pub fn header(bytes: &[u8]) -> Option<Header> {
    layout::header(ptlas::traversable(bytes).unwrap_or(bytes))
}
pub use metrics::{metrics, validate, Metrics};
pub use traverse::{all_hits, any_hit, closest_hit, intersect_triangle, Hit, HitKind, Ray, RayFlags, RayQuery};

/// Top or bottom level (VkAccelerationStructureTypeKHR values).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum AsType {
    TopLevel = 0,
    BottomLevel = 1,
}

/// VkBuildAccelerationStructureFlagBitsKHR values.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct BuildFlags(pub u32);
impl BuildFlags {
    pub const ALLOW_UPDATE: u32 = 1;
    pub const ALLOW_COMPACTION: u32 = 2;
    pub const PREFER_FAST_TRACE: u32 = 4;
    pub const PREFER_FAST_BUILD: u32 = 8;
    pub const LOW_MEMORY: u32 = 16;
    pub const ALLOW_DATA_ACCESS: u32 = 1 << 11;
    pub fn contains(self, bit: u32) -> bool {
        self.0 & bit != 0
    }
}

/// VkGeometryFlagBitsKHR: OPAQUE = 1, NO_DUPLICATE_ANY_HIT_INVOCATION = 2.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct GeometryFlags(pub u32);
impl GeometryFlags {
    pub const OPAQUE: u32 = 1;
    pub const NO_DUPLICATE_ANY_HIT_INVOCATION: u32 = 2;
}

/// Vertex formats accepted for triangle geometry (VkFormat numeric values via from_vk/to_vk).
/// 2-component formats give z = 0, a 4th component is ignored.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Hash)]
pub enum VertexFormat {
    R32G32Sfloat,
    R32G32B32Sfloat,
    R32G32B32A32Sfloat,
    R16G16Sfloat,
    R16G16B16Sfloat,
    R16G16B16A16Sfloat,
    R16G16Snorm,
    R16G16B16A16Snorm,
    R8G8Snorm,
    R8G8B8A8Snorm,
    R16G16Unorm,
    R16G16B16A16Unorm,
    R8G8Unorm,
    R8G8B8A8Unorm,
    A2B10G10R10UnormPack32,
}

impl VertexFormat {
    const ALL: [VertexFormat; 15] = [
        VertexFormat::R32G32Sfloat,
        VertexFormat::R32G32B32Sfloat,
        VertexFormat::R32G32B32A32Sfloat,
        VertexFormat::R16G16Sfloat,
        VertexFormat::R16G16B16Sfloat,
        VertexFormat::R16G16B16A16Sfloat,
        VertexFormat::R16G16Snorm,
        VertexFormat::R16G16B16A16Snorm,
        VertexFormat::R8G8Snorm,
        VertexFormat::R8G8B8A8Snorm,
        VertexFormat::R16G16Unorm,
        VertexFormat::R16G16B16A16Unorm,
        VertexFormat::R8G8Unorm,
        VertexFormat::R8G8B8A8Unorm,
        VertexFormat::A2B10G10R10UnormPack32,
    ];
    pub fn all() -> &'static [VertexFormat] {
        &Self::ALL
    }
    pub fn to_vk(self) -> i32 {
        match self {
            VertexFormat::R32G32Sfloat => 103,
            VertexFormat::R32G32B32Sfloat => 106,
            VertexFormat::R32G32B32A32Sfloat => 109,
            VertexFormat::R16G16Sfloat => 83,
            VertexFormat::R16G16B16Sfloat => 90,
            VertexFormat::R16G16B16A16Sfloat => 97,
            VertexFormat::R16G16Snorm => 78,
            VertexFormat::R16G16B16A16Snorm => 95,
            VertexFormat::R8G8Snorm => 17,
            VertexFormat::R8G8B8A8Snorm => 38,
            VertexFormat::R16G16Unorm => 77,
            VertexFormat::R16G16B16A16Unorm => 91,
            VertexFormat::R8G8Unorm => 16,
            VertexFormat::R8G8B8A8Unorm => 37,
            VertexFormat::A2B10G10R10UnormPack32 => 64,
        }
    }
    pub fn from_vk(value: i32) -> Option<Self> {
        Self::ALL.iter().copied().find(|f| f.to_vk() == value)
    }
    /// Bytes per vertex.
    pub fn size(self) -> u32 {
        match self {
            VertexFormat::R32G32Sfloat => 8,
            VertexFormat::R32G32B32Sfloat => 12,
            VertexFormat::R32G32B32A32Sfloat => 16,
            VertexFormat::R16G16Sfloat => 4,
            VertexFormat::R16G16B16Sfloat => 6,
            VertexFormat::R16G16B16A16Sfloat => 8,
            VertexFormat::R16G16Snorm => 4,
            VertexFormat::R16G16B16A16Snorm => 8,
            VertexFormat::R8G8Snorm => 2,
            VertexFormat::R8G8B8A8Snorm => 4,
            VertexFormat::R16G16Unorm => 4,
            VertexFormat::R16G16B16A16Unorm => 8,
            VertexFormat::R8G8Unorm => 2,
            VertexFormat::R8G8B8A8Unorm => 4,
            VertexFormat::A2B10G10R10UnormPack32 => 4,
        }
    }
    /// Size of one component (the whole size for packed formats): the alignment unit.
    pub fn component_size(self) -> u32 {
        match self {
            VertexFormat::R32G32Sfloat | VertexFormat::R32G32B32Sfloat | VertexFormat::R32G32B32A32Sfloat => 4,
            VertexFormat::R16G16Sfloat
            | VertexFormat::R16G16B16Sfloat
            | VertexFormat::R16G16B16A16Sfloat
            | VertexFormat::R16G16Snorm
            | VertexFormat::R16G16B16A16Snorm
            | VertexFormat::R16G16Unorm
            | VertexFormat::R16G16B16A16Unorm => 2,
            VertexFormat::R8G8Snorm | VertexFormat::R8G8B8A8Snorm | VertexFormat::R8G8Unorm | VertexFormat::R8G8B8A8Unorm => 1,
            VertexFormat::A2B10G10R10UnormPack32 => 4,
        }
    }
}

/// Index type of triangle geometry.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Hash)]
pub enum IndexType {
    None,
    U16,
    U32,
}
impl IndexType {
    /// NONE_KHR = 1000165000, UINT16 = 0, UINT32 = 1 (UINT8 is not allowed for AS builds).
    pub fn from_vk(value: i32) -> Option<Self> {
        match value {
            1000165000 => Some(IndexType::None),
            0 => Some(IndexType::U16),
            1 => Some(IndexType::U32),
            _ => None,
        }
    }
    pub fn to_vk(self) -> i32 {
        match self {
            IndexType::None => 1000165000,
            IndexType::U16 => 0,
            IndexType::U32 => 1,
        }
    }
    /// Bytes per index (0 for None).
    pub fn size(self) -> u32 {
        match self {
            IndexType::None => 0,
            IndexType::U16 => 2,
            IndexType::U32 => 4,
        }
    }
}

/// Where a TLAS build and traversal find other structures and pointed-to instances.
pub trait DeviceView: Sync {
    /// `len` bytes at device address `address`, or None when not inside one live buffer.
    fn bytes(&self, address: u64, len: u64) -> Option<&[u8]>;
    /// The bytes of the acceleration structure whose device address (or, for host builds,
    /// handle value) is `reference`; the slice starts at the structure and spans its size.
    fn acceleration_structure(&self, reference: u64) -> Option<&[u8]>;
    /// The reference a built structure stores for an instance's
    /// `accelerationStructureReference`: identity for device builds; host builds map the
    /// handle value to the structure's device address, so host and device builds of the same
    /// input are byte-identical. Called once per active instance; 0 is never passed.
    fn translate_reference(&self, reference: u64) -> u64 {
        reference
    }
}

/// A DeviceView over nothing (for BLAS-only use).
pub struct NoDevice;
impl DeviceView for NoDevice {
    fn bytes(&self, _address: u64, _len: u64) -> Option<&[u8]> {
        None
    }
    fn acceleration_structure(&self, _reference: u64) -> Option<&[u8]> {
        None
    }
}

/// A simple map-based DeviceView for tests: each inserted Vec is one "buffer" at its address;
/// structures are looked up by their exact start address.
#[derive(Default)]
pub struct MapView {
    regions: HashMap<u64, Vec<u8>>,
}
impl MapView {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn insert(&mut self, address: u64, data: Vec<u8>) {
        self.regions.insert(address, data);
    }
}
impl DeviceView for MapView {
    fn bytes(&self, address: u64, len: u64) -> Option<&[u8]> {
        for (&base, data) in &self.regions {
            if address >= base {
                let off = address - base;
                let end = off.checked_add(len)?;
                if end <= data.len() as u64 {
                    return data.get(off as usize..end as usize);
                }
            }
        }
        None
    }
    fn acceleration_structure(&self, reference: u64) -> Option<&[u8]> {
        self.regions.get(&reference).map(|v| v.as_slice())
    }
}

/// One geometry of a build with its build range already applied by the caller.
#[derive(Clone, Copy, Debug)]
pub struct Geometry<'a> {
    pub flags: GeometryFlags,
    pub primitive_count: u32,
    pub data: GeometryData<'a>,
}

#[derive(Clone, Copy, Debug)]
pub enum GeometryData<'a> {
    Triangles {
        format: VertexFormat,
        /// Starts at the vertex that index 0 refers to: vertexData + firstVertex*stride
        /// (non-indexed: vertexData + primitiveOffset + firstVertex*stride).
        vertices: &'a [u8],
        stride: u64,
        /// Highest valid vertex index into `vertices` (maxVertex - firstVertex).
        max_vertex: u32,
        /// Starts at indexData + primitiveOffset; 3*primitive_count entries (empty for None).
        index_type: IndexType,
        indices: &'a [u8],
        /// Row-major 3x4 (VkTransformMatrixKHR), already read from transformData+transformOffset.
        transform: Option<[f32; 12]>,
    },
    /// primitive_count records of VkAabbPositionsKHR (24 B) at k*stride from the slice start.
    Aabbs { data: &'a [u8], stride: u64 },
    /// Packed: primitive_count * 64 B VkAccelerationStructureInstanceKHR records.
    /// Pointers: primitive_count u64 addresses, each of a 64-byte instance read via DeviceView::bytes.
    Instances { array_of_pointers: bool, data: &'a [u8] },
}

/// Shape of a geometry for the size query (no data).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GeometryShape {
    Triangles { format: VertexFormat, index_type: IndexType, max_vertex: u32, has_transform: bool },
    Aabbs,
    Instances,
}

#[derive(Clone, Copy, Debug)]
pub struct BuildDesc<'a> {
    pub ty: AsType,
    pub flags: BuildFlags,
    pub geometries: &'a [Geometry<'a>],
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BuildSizes {
    pub acceleration_structure_size: u64,
    pub build_scratch_size: u64,
    pub update_scratch_size: u64,
}

#[derive(Debug, Clone, PartialEq)]
pub enum BuildError {
    DestinationTooSmall { needed: u64, got: u64 },
    ScratchTooSmall { needed: u64, got: u64 },
    IndexOutOfRange { geometry: u32, primitive: u32, index: u32 },
    InputTooShort { geometry: u32 },
    InvalidSource(&'static str),
    UpdateMismatch(&'static str),
    /// Geometry type does not fit the structure type (triangles/AABBs in a TLAS, instances in a BLAS),
    /// or a BLAS mixes triangles and AABBs.
    WrongGeometryType { geometry: u32 },
    /// An array-of-pointers instance address that does not resolve to 64 readable bytes.
    InvalidAddress { geometry: u32, primitive: u32 },
    /// More primitives or geometries than the format can address (2^32-1 in total).
    TooManyPrimitives,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BuildReport {
    /// Bytes of dst in use (= compacted size).
    pub used_size: u64,
    pub node_count: u32,
    pub leaf_count: u32,
    /// Primitives (or instances) stored, i.e. active ones.
    pub primitive_count: u32,
    /// Cluster references the tree was built over, when the build clustered neighbouring
    /// primitives (None: one reference per primitive, and for updates).
    pub clusters: Option<u32>,
    /// Where the top of the tree was planned (large BLAS builds).
    pub top_planned: TopPlanned,
    /// Buckets of a planned top too large for one thread, which split further in parallel.
    pub forked_buckets: u32,
}

/// Where a build planned the top levels of its tree from one sample (a diagnostic: the bytes
/// of the structure never depend on it beyond the tree the plan chose).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TopPlanned {
    /// No plan: the tree was built from its root (small builds, TLAS, updates).
    #[default]
    No,
    /// From a sample of the input triangles, beside ingest.
    FromInput,
    /// From a sample of the references after ingest.
    FromReferences,
}

/// Where a build's time went (wall clock of the calling thread, milliseconds): reading the
/// geometry into primitive references, the binned-SAH tree with the wide nodes of its cut
/// subtrees, the primitive data in leaf order, the final node pass (a TLAS: beside its instance
/// sections, each followed by the hash of its checksum part); `total_ms` includes the rest
/// (geometry table, header). For people measuring; not part of the structure.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BuildPhases {
    pub ingest_ms: f64,
    pub sah_ms: f64,
    pub leaf_data_ms: f64,
    pub nodes_ms: f64,
    pub total_ms: f64,
}

/// Exact worst-case sizes; u64 math that cannot overflow even for 2^32-1 primitives or geometries.
pub fn build_sizes(ty: AsType, flags: BuildFlags, shapes: &[GeometryShape], max_primitive_counts: &[u32]) -> BuildSizes {
    layout::build_sizes(ty, flags, shapes, max_primitive_counts)
}

/// Build into `dst` (the whole AS region; header at dst[0]). Working arrays live in `scratch`.
/// Runs on the current rayon pool. Deterministic: dst[..used_size] depends on the input only.
/// Never writes outside dst and scratch. On error dst is marked invalid.
pub fn build(desc: &BuildDesc, view: &dyn DeviceView, dst: &mut [u8], scratch: &mut [u8]) -> Result<BuildReport, BuildError> {
    build_timed(desc, view, dst, scratch).map(|(report, _)| report)
}

/// `build`, also saying where the time went (`BuildPhases`).
pub fn build_timed(desc: &BuildDesc, view: &dyn DeviceView, dst: &mut [u8], scratch: &mut [u8]) -> Result<(BuildReport, BuildPhases), BuildError> {
    let result = build::build(desc, view, dst, scratch);
    if result.is_err() {
        mark_invalid(dst);
    }
    result
}

/// Whether `structure` passes every check a copy makes of its source: header, section offsets,
/// checksum, counts, records and the node tree; Err names the first check that failed.
pub fn verify(structure: &[u8]) -> Result<(), CheckReason> {
    check::check(structure).map(|_| ())
}

/// The integrity checksum of a valid structure as computed now over its bytes (the header
/// stores the one computed when it was finished); None when `structure` has no valid header.
pub fn structure_checksum(structure: &[u8]) -> Option<u64> {
    layout::parse(structure).map(|p| checksum::structure_checksum(&p.raw, p.bytes))
}

/// Refit (UPDATE). `src: None` = in place (dst holds the structure). Same topology; checks the
/// update rules it can see (geometry count/type/flags, primitive counts, indices, active state).
pub fn update(
    desc: &BuildDesc,
    view: &dyn DeviceView,
    src: Option<&[u8]>,
    dst: &mut [u8],
    scratch: &mut [u8],
) -> Result<BuildReport, BuildError> {
    let result = refit::update(desc, view, src, dst, scratch);
    if result.is_err() {
        mark_invalid(dst);
    }
    result
}

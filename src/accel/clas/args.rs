//! The argument records of vkCmdBuildClusterAccelerationStructureIndirectNV as they lie in device
//! memory (VK_NV_cluster_acceleration_structure, spec version 4): `#[repr(C)]` + Pod, bitfield
//! words packed and unpacked by hand. They live in the library, not in dispatch, because the
//! recorded command reads them from device memory when it executes, below the dispatch layer.
use bytemuck::{Pod, Zeroable};

/// VkClusterAccelerationStructureGeometryIndexAndGeometryFlagsNV: geometryIndex:24,
/// reserved:5, geometryFlags:3.
#[repr(transparent)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq, Default)]
pub struct GeometryIndexAndFlags(pub u32);
impl GeometryIndexAndFlags {
    pub const CULL_DISABLE: u32 = 1;
    pub const NO_DUPLICATE_ANYHIT_INVOCATION: u32 = 2;
    pub const OPAQUE: u32 = 4;
    pub fn new(geometry_index: u32, geometry_flags: u32) -> Self {
        GeometryIndexAndFlags((geometry_index & 0x00ff_ffff) | ((geometry_flags & 7) << 29))
    }
    pub fn geometry_index(self) -> u32 {
        self.0 & 0x00ff_ffff
    }
    pub fn reserved(self) -> u32 {
        (self.0 >> 24) & 0x1f
    }
    pub fn geometry_flags(self) -> u32 {
        self.0 >> 29
    }
}

/// VkClusterAccelerationStructureBuildTriangleClusterInfoNV (64 bytes).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq, Default)]
pub struct BuildTriangleClusterInfo {
    pub cluster_id: u32,
    pub cluster_flags: u32,
    /// triangleCount:9, vertexCount:9, positionTruncateBitCount:6, indexType:4,
    /// opacityMicromapIndexType:4.
    pub counts: u32,
    pub base_geometry_index_and_geometry_flags: GeometryIndexAndFlags,
    pub index_buffer_stride: u16,
    pub vertex_buffer_stride: u16,
    pub geometry_index_and_flags_buffer_stride: u16,
    pub opacity_micromap_index_buffer_stride: u16,
    pub index_buffer: u64,
    pub vertex_buffer: u64,
    pub geometry_index_and_flags_buffer: u64,
    pub opacity_micromap_array: u64,
    pub opacity_micromap_index_buffer: u64,
}
const _: () = assert!(std::mem::size_of::<BuildTriangleClusterInfo>() == 64);

/// Packs the bitfield word at offset 8 (values wider than their fields are cut, as C does).
pub fn pack_counts(triangle_count: u32, vertex_count: u32, truncate_bits: u32, index_type: u32, omm_index_type: u32) -> u32 {
    (triangle_count & 0x1ff) | ((vertex_count & 0x1ff) << 9) | ((truncate_bits & 0x3f) << 18) | ((index_type & 0xf) << 24) | ((omm_index_type & 0xf) << 28)
}

impl BuildTriangleClusterInfo {
    pub fn triangle_count(&self) -> u32 {
        self.counts & 0x1ff
    }
    pub fn vertex_count(&self) -> u32 {
        (self.counts >> 9) & 0x1ff
    }
    pub fn position_truncate_bit_count(&self) -> u32 {
        (self.counts >> 18) & 0x3f
    }
    /// One VkClusterAccelerationStructureIndexFormatFlagBitsNV bit: 1, 2 or 4 (= bytes).
    pub fn index_type(&self) -> u32 {
        (self.counts >> 24) & 0xf
    }
    pub fn opacity_micromap_index_type(&self) -> u32 {
        self.counts >> 28
    }
}

/// VkClusterAccelerationStructureBuildTriangleClusterTemplateInfoNV (72 bytes): the CLAS record
/// (vertexBuffer optional) and the instantiation bounding-box limit.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq, Default)]
pub struct BuildTriangleClusterTemplateInfo {
    pub cluster: BuildTriangleClusterInfo,
    pub instantiation_bounding_box_limit: u64,
}
const _: () = assert!(std::mem::size_of::<BuildTriangleClusterTemplateInfo>() == 72);

/// VkStridedDeviceAddressNV (16 bytes; only the low 32 bits of the stride count).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq, Default)]
pub struct StridedDeviceAddress {
    pub start_address: u64,
    pub stride_in_bytes: u64,
}

/// VkClusterAccelerationStructureInstantiateClusterInfoNV (32 bytes).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq, Default)]
pub struct InstantiateClusterInfo {
    pub cluster_id_offset: u32,
    /// geometryIndexOffset:24 (a signed offset), reserved:8.
    pub geometry_word: u32,
    pub cluster_template_address: u64,
    pub vertex_buffer: StridedDeviceAddress,
}
const _: () = assert!(std::mem::size_of::<InstantiateClusterInfo>() == 32);

impl InstantiateClusterInfo {
    /// The 24-bit field sign-extended: the spec calls it a signed offset.
    pub fn geometry_index_offset(&self) -> i32 {
        ((self.geometry_word << 8) as i32) >> 8
    }
    pub fn reserved(&self) -> u32 {
        self.geometry_word >> 24
    }
    pub fn pack_geometry_index_offset(offset: i32) -> u32 {
        offset as u32 & 0x00ff_ffff
    }
}

/// VkClusterAccelerationStructureBuildClustersBottomLevelInfoNV (16 bytes).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq, Default)]
pub struct BuildClustersBottomLevelInfo {
    pub cluster_references_count: u32,
    pub cluster_references_stride: u32,
    pub cluster_references: u64,
}
const _: () = assert!(std::mem::size_of::<BuildClustersBottomLevelInfo>() == 16);

/// VkClusterAccelerationStructureMoveObjectsInfoNV and
/// VkClusterAccelerationStructureGetTemplateIndicesInfoNV (8 bytes each: one address).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq, Default)]
pub struct AddressInfo {
    pub address: u64,
}
const _: () = assert!(std::mem::size_of::<AddressInfo>() == 8);

/// VkClusterAccelerationStructureOpTypeNV.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OpType {
    MoveObjects = 0,
    BuildClustersBottomLevel = 1,
    BuildTriangleCluster = 2,
    BuildTriangleClusterTemplate = 3,
    InstantiateTriangleCluster = 4,
    GetClusterTemplateIndices = 5,
}
impl OpType {
    pub fn from_vk(v: i32) -> Option<Self> {
        use OpType::*;
        [MoveObjects, BuildClustersBottomLevel, BuildTriangleCluster, BuildTriangleClusterTemplate, InstantiateTriangleCluster, GetClusterTemplateIndices]
            .into_iter()
            .find(|o| *o as i32 == v)
    }
    /// Bytes of one srcInfosArray element (the packed stride).
    pub fn record_size(self) -> u64 {
        match self {
            OpType::MoveObjects | OpType::GetClusterTemplateIndices => 8,
            OpType::BuildClustersBottomLevel => 16,
            OpType::BuildTriangleCluster => 64,
            OpType::BuildTriangleClusterTemplate => 72,
            OpType::InstantiateTriangleCluster => 32,
        }
    }
}

/// VkClusterAccelerationStructureOpModeNV.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OpMode {
    ImplicitDestinations = 0,
    ExplicitDestinations = 1,
    ComputeSizes = 2,
}
impl OpMode {
    pub fn from_vk(v: i32) -> Option<Self> {
        [OpMode::ImplicitDestinations, OpMode::ExplicitDestinations, OpMode::ComputeSizes].into_iter().find(|o| *o as i32 == v)
    }
}

/// VkClusterAccelerationStructureTypeNV (what a move moves).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObjectType {
    ClustersBottomLevel = 0,
    TriangleCluster = 1,
    TriangleClusterTemplate = 2,
}
impl ObjectType {
    pub fn from_vk(v: i32) -> Option<Self> {
        [ObjectType::ClustersBottomLevel, ObjectType::TriangleCluster, ObjectType::TriangleClusterTemplate].into_iter().find(|o| *o as i32 == v)
    }
}

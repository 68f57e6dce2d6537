//! VK_NV_cluster_acceleration_structure as a pure library: triangle clusters (CLAS), cluster
//! templates and their instantiation, cluster BLAS over CLAS addresses, the size bounds of the
//! size query, and what traversal needs to walk a cluster BLAS.
//!
//! Owns the cluster blob formats (docs/CLUSTERS.md) and the device-memory argument records.
//! Must not touch: device memory resolution (inputs come through `DeviceView::bytes`, outputs
//! are slices), diagnostics, the KHR builder's internals (a cluster BLAS embeds an ordinary
//! BVH built through `accel::build`). Unrelated to `build/cluster.rs`, the KHR builder's stage
//! that groups neighbouring primitives.
pub mod args;
pub mod check;
mod blas;
mod build;
mod format;
mod sizes;
mod tree;

pub use blas::{blas_size_bound, blas_size_for, build_cluster_blas, cluster_references, open_walkable, Side, SideEntry, FLAG_CULL_DISABLE};
pub use build::{build_clas, build_template, instantiate, object_size, template_indices, template_indices_size};
pub use format::{clas_size, open, template_size, truncate, Blob, ClusterHeader, Kind, CLUSTER_FORMAT_VERSION, HEADER_SIZE};
pub use sizes::{cluster_build_sizes, SizeInput};

use super::BuildError;

/// Limits Arbor reports in VkPhysicalDeviceClusterAccelerationStructurePropertiesNV: the spec's
/// minimums for counts (256) and its maximums for alignments, which every layout here meets.
pub const MAX_TRIANGLES: u32 = 256;
pub const MAX_VERTICES: u32 = 256;
pub const MAX_GEOMETRY_INDEX: u32 = (1 << 24) - 1;
pub const CLAS_ALIGNMENT: u64 = 16;
pub const TEMPLATE_ALIGNMENT: u64 = 16;
pub const BLAS_ALIGNMENT: u64 = 64;
pub const SCRATCH_ALIGNMENT: u64 = 16;
pub const TEMPLATE_BOUNDS_ALIGNMENT: u64 = 16;
/// The scratch Arbor asks for: its working arrays live in host memory, but clients treat a
/// zero scratch size as an error, so every query reports this much.
pub const SCRATCH_SIZE: u64 = 256;

#[derive(Debug, Clone, PartialEq)]
pub enum ClusterError {
    DestinationTooSmall { needed: u64, got: u64 },
    TooManyTriangles(u32),
    TooManyVertices(u32),
    /// indexType is not exactly one of the 8-, 16- or 32-bit bits.
    BadIndexType(u32),
    BadTruncation(u32),
    /// An input the record names does not resolve to readable memory.
    Unreadable { what: &'static str, address: u64 },
    /// The source is not the kind of cluster object the operation needs.
    NotA(&'static str),
    /// A cluster BLAS reference that names no CLAS.
    NotAClas { address: u64 },
    /// Instantiation without vertices from a template built without them.
    NoVertices,
    Build(BuildError),
}

impl std::fmt::Display for ClusterError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ClusterError::DestinationTooSmall { needed, got } => write!(f, "destination holds {got} bytes, the result needs {needed}"),
            ClusterError::TooManyTriangles(n) => write!(f, "triangleCount {n} exceeds maxTrianglesPerCluster {MAX_TRIANGLES}"),
            ClusterError::TooManyVertices(n) => write!(f, "vertexCount {n} exceeds maxVerticesPerCluster {MAX_VERTICES}"),
            ClusterError::BadIndexType(v) => write!(f, "indexType {v:#x} is not one of the 8-, 16- or 32-bit index format bits"),
            ClusterError::BadTruncation(n) => write!(f, "positionTruncateBitCount {n} exceeds 32"),
            ClusterError::Unreadable { what, address } => write!(f, "the {what} at {address:#x} is not inside a live buffer"),
            ClusterError::NotA(what) => write!(f, "the source is not a {what}"),
            ClusterError::NotAClas { address } => write!(f, "cluster reference {address:#x} names no built CLAS"),
            ClusterError::NoVertices => write!(f, "vertexBuffer is 0 but the template was built without vertices"),
            ClusterError::Build(e) => write!(f, "embedded BVH build failed: {e:?}"),
        }
    }
}

#[cfg(test)]
mod tests;

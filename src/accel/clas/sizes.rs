//! vkGetClusterAccelerationStructureBuildSizesNV: EXPLICIT gives the worst case of one result,
//! IMPLICIT the total of all results with their alignment padding, COMPUTE_SIZES only scratch.
//! Scratch is never zero (SCRATCH_SIZE). Every bound is u64 arithmetic that saturates.
use super::args::{ObjectType, OpMode, OpType};
use super::blas::blas_size_bound;
use super::format::{clas_size, template_size, HEADER_SIZE, TRIANGLE_SIZE, WORD_SIZE};
use super::{BLAS_ALIGNMENT, CLAS_ALIGNMENT, MAX_TRIANGLES, SCRATCH_SIZE, TEMPLATE_ALIGNMENT};
use crate::accel::BuildSizes;

/// The upper bounds of VkClusterAccelerationStructureInputInfoNV and its op input.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SizeInput {
    pub op: OpType,
    pub mode: OpMode,
    pub max_count: u32,
    /// Triangle ops: maxClusterTriangleCount and maxTotalTriangleCount.
    pub max_cluster_triangles: u32,
    pub max_total_triangles: u32,
    /// BUILD_CLUSTERS_BOTTOM_LEVEL: maxTotalClusterCount and maxClusterCountPerAccelerationStructure.
    pub max_total_clusters: u32,
    pub max_clusters_per_blas: u32,
    /// MOVE_OBJECTS: maxMovedBytes and the type moved.
    pub max_moved_bytes: u64,
    pub move_type: ObjectType,
}

fn alignment_of(t: ObjectType) -> u64 {
    match t {
        ObjectType::ClustersBottomLevel => BLAS_ALIGNMENT,
        ObjectType::TriangleCluster => CLAS_ALIGNMENT,
        ObjectType::TriangleClusterTemplate => TEMPLATE_ALIGNMENT,
    }
}

/// (one result's worst case, all results' total) for the op.
fn bounds(s: &SizeInput) -> (u64, u64) {
    let count = s.max_count as u64;
    let per_cluster = (s.max_cluster_triangles.min(MAX_TRIANGLES)) as u64;
    let total_tris = (s.max_total_triangles as u64).min(count.saturating_mul(per_cluster));
    // Each result is a header plus a per-triangle part, padded to its alignment.
    let tri_op = |per_tri: u64, extra: u64, align: u64, one: u64| (one.next_multiple_of(align), count.saturating_mul(HEADER_SIZE + extra + align).saturating_add(total_tris.saturating_mul(per_tri)));
    match s.op {
        // A CLAS's tree: one order byte per triangle (padded to 4) and at most
        // ceil(T / 12) + 1 nodes of 64 bytes, under 6 T + 128.
        OpType::BuildTriangleCluster | OpType::InstantiateTriangleCluster => tri_op(TRIANGLE_SIZE + WORD_SIZE + 1 + 6, 3 + 128, CLAS_ALIGNMENT, clas_size(per_cluster)),
        OpType::BuildTriangleClusterTemplate => tri_op(12 + WORD_SIZE + TRIANGLE_SIZE, 0, TEMPLATE_ALIGNMENT, template_size(per_cluster, true)),
        OpType::GetClusterTemplateIndices => {
            let one = 12 * per_cluster;
            (one, count.saturating_mul(4).saturating_add(total_tris.saturating_mul(12)))
        }
        OpType::BuildClustersBottomLevel => {
            let per = (s.max_clusters_per_blas as u64).min(s.max_total_clusters as u64);
            let one = blas_size_bound(per).next_multiple_of(BLAS_ALIGNMENT);
            // The bound is affine in the cluster count up to section rounding, so k BLASes over
            // n clusters in all need at most k fixed parts (with rounding slack) plus the bound
            // of n clusters.
            let fixed = blas_size_bound(0) + 1024 + BLAS_ALIGNMENT;
            let total = count.saturating_mul(fixed).saturating_add(blas_size_bound(s.max_total_clusters as u64));
            (one, total.min(count.saturating_mul(one)))
        }
        OpType::MoveObjects => {
            let align = alignment_of(s.move_type);
            (s.max_moved_bytes, s.max_moved_bytes.saturating_add(count.saturating_mul(align)))
        }
    }
}

pub fn cluster_build_sizes(s: &SizeInput) -> BuildSizes {
    let (one, total) = bounds(s);
    let size = match s.mode {
        OpMode::ExplicitDestinations => one,
        OpMode::ImplicitDestinations => total,
        OpMode::ComputeSizes => 0,
    };
    BuildSizes { acceleration_structure_size: size, build_scratch_size: SCRATCH_SIZE, update_scratch_size: SCRATCH_SIZE }
}

//! Every tier parameter and tuning constant of the builder, one line each; docs/TUNING.md says
//! what each one trades, the values tried and what they measured.
//!
//! Owns: numbers. Must not touch: any logic beyond choosing a tier from the build flags.
use super::BuildFlags;

/// Builder settings of one tier (chosen from the build flags, `BuildParams::from_flags`).
#[derive(Clone, Copy, Debug)]
pub struct BuildParams {
    /// Bins per axis of a large binned node (at most MAX_BINS).
    pub bins: usize,
    /// Nodes of at least this many references bin (and sweep) all three axes, smaller ones only the widest.
    pub all_axes_from: usize,
    /// C_T relative to C_I in the leaf/split decision (the reported SAH always uses 1).
    pub traversal_cost: f32,
    /// The most references a leaf may hold.
    pub max_leaf: u32,
    /// Nodes up to this many references take the exact split (`small_split`) instead of binning (<= MAX_SMALL).
    pub exact_split_max: usize,
    /// Below this many references a subtree is built on the calling thread (never changes the bytes).
    pub parallel_cutoff: u32,
    /// Sampled nodes (at least SAMPLE_FROM references) bin a strided sample of about this many.
    pub sample_target: usize,
    /// Neighbours cluster when their union's half area is at most this many times the sum of theirs; 0: never.
    pub cluster_tau: f32,
    /// The most primitives per cluster reference (<= MAX_CLUSTER).
    pub max_cluster: u32,
    /// The most cluster references per leaf in clustered builds.
    pub max_cluster_leaf: u32,
    /// The fewest bins a binned node gets (it gets one per REFS_PER_BIN references, up to `bins`).
    pub min_bins: usize,
}

/// PREFER_FAST_TRACE: 32 bins on three axes above the exact splits, clusters of 3 in leaves of 3.
pub const FAST_TRACE: BuildParams = BuildParams { bins: 32, all_axes_from: SMALL_N + 1, traversal_cost: 1.0, max_leaf: 8, exact_split_max: SMALL_N, parallel_cutoff: 1024, sample_target: 2 * SAMPLE_TARGET, cluster_tau: FAST_TRACE_TAU, max_cluster: 3, max_cluster_leaf: 3, min_bins: 6 };
/// PREFER_FAST_BUILD: 12 bins on the widest axis, bigger leaves (C_T 2.5), clusters of 4 in leaves of 3.
pub const FAST_BUILD: BuildParams = BuildParams { bins: 12, all_axes_from: usize::MAX, traversal_cost: 2.5, max_leaf: 8, exact_split_max: SMALL_N, parallel_cutoff: 1024, sample_target: SAMPLE_TARGET, cluster_tau: FAST_BUILD_TAU, max_cluster: 4, max_cluster_leaf: 3, min_bins: 8 };
/// Neither flag: FAST_TRACE's bins and clusters, three axes only from 1,024 references.
pub const DEFAULT: BuildParams = BuildParams { bins: 32, all_axes_from: 1024, traversal_cost: 1.0, max_leaf: 8, exact_split_max: SMALL_N, parallel_cutoff: 1024, sample_target: 2 * SAMPLE_TARGET, cluster_tau: DEFAULT_TAU, max_cluster: 3, max_cluster_leaf: 3, min_bins: 6 };

impl BuildParams {
    /// The tier of `flags` (PREFER_FAST_TRACE wins over PREFER_FAST_BUILD).
    pub fn from_flags(flags: BuildFlags) -> Self {
        if flags.contains(BuildFlags::PREFER_FAST_TRACE) {
            FAST_TRACE
        } else if flags.contains(BuildFlags::PREFER_FAST_BUILD) {
            FAST_BUILD
        } else {
            DEFAULT
        }
    }
}

// Binning.
/// Capacity of a node's bins per axis.
pub const MAX_BINS: usize = 32;
/// Binned nodes get at most one bin per this many references.
pub const REFS_PER_BIN: usize = 4;
/// Below this many references single-axis binning uses one set of bins instead of two interleaved.
pub const ONE_BIN_SET_BELOW: usize = 64;
/// Below this many references three-axis binning uses one set of bins instead of two interleaved.
pub const ONE_BIN_SET_BELOW_3_AXES: usize = 512;
/// Depth after which splits become object medians: bounds the recursion to about 64 + log2(n).
pub const MAX_SAH_DEPTH: u32 = 64;
/// Nodes of at least this many references bin a strided sample (and always partition in parallel).
pub const SAMPLE_FROM: usize = 1 << 14;
/// The fast-build tier's sample per sampled node (the others take twice as many).
pub const SAMPLE_TARGET: usize = 1 << 12;
/// Samples per parallel binning task of a sampled node.
pub const SAMPLE_CHUNK: usize = 1 << 10;
/// References per parallel binning task of an unsampled node at the top of the tree.
pub const BIN_CHUNK: usize = 1 << 14;

// Exact splits of small nodes.
/// The tiers' largest node for the exact split.
pub const SMALL_N: usize = 8;
/// Capacity of the exact split (its sorting network sorts 8).
pub const MAX_SMALL: usize = 8;

// Partition.
/// Nodes of at least this many references partition in parallel chunks (or in one pass).
pub const PAR_PARTITION_FROM: usize = 1 << 14;
/// Chunks of a parallel partition: a fixed count, independent of the thread count.
pub const PARTITION_CHUNKS: usize = 64;
const _: () = assert!(SAMPLE_FROM >= PAR_PARTITION_FROM);

// Clusters (`build::cluster`).
/// The most primitives a cluster reference may hold in any tier.
pub const MAX_CLUSTER: u32 = 4;
/// Builds with fewer primitives do not cluster.
pub const CLUSTER_MIN: usize = 8192;
/// Geometries a clustered build may have (a table of first IDs on the stack).
pub const MAX_CLUSTER_GEOMETRIES: usize = 64;
/// The fast-build tier's cluster tightness.
pub const FAST_BUILD_TAU: f32 = 1.1;
/// The default tier's cluster tightness.
pub const DEFAULT_TAU: f32 = 0.7;
/// The fast-trace tier's cluster tightness.
pub const FAST_TRACE_TAU: f32 = 0.7;
/// Neighbour pairs tested by `worth_clustering`, evenly spaced over the input.
pub const CLUSTER_SAMPLE: u32 = 1024;
/// Clustering pays when at least one in this many sampled neighbours is tight.
pub const CLUSTER_WORTH: u32 = 8;

/// References per block of `cluster_in_place` (its areas and neighbour tests on the stack).
pub const CLUSTER_BLOCK: usize = 256;

// Ingest.
/// Primitives per ingest chunk (triangles, AABBs).
pub const INGEST_CHUNK: usize = 4096;
/// Primitives per ingest chunk of instance geometries (an instance costs far more than a triangle).
pub const INGEST_CHUNK_INSTANCES: usize = 256;
/// Prefetch distance (in primitives or records) of ingest's vertex reads and the leaf-data gathers.
pub const PREFETCH_AHEAD: usize = 32;

/// Leaf-order records per parallel task of the leaf-data passes.
pub const LEAF_DATA_CHUNK: usize = 4096;
/// References per parallel task of the cluster prefix and the cluster IDs in leaf order.
pub const PREFIX_CHUNK: usize = 1 << 14;
/// Instances per parallel task of the TLAS instance records.
pub const INSTANCE_CHUNK: usize = 1024;

// The planned top of large BLAS builds (`build::plan`).
/// BLAS builds with at least this many primitives plan their top (scratch permitting).
pub const PLAN_MIN: usize = 4 * SAMPLE_FROM;
/// Levels of the planned top at most.
pub const PLAN_LEVELS: usize = 6;
/// The root's sample is this many times the tier's `sample_target`.
pub const PLAN_ROOT_SAMPLE: usize = 4;
/// A top node splits while its sample holds at least `sample_target / PLAN_MIN_SAMPLE_DIV` references.
pub const PLAN_MIN_SAMPLE_DIV: usize = 8;
/// ...and it is estimated to hold at least this many references.
pub const PLAN_SPLIT_MIN: usize = SAMPLE_FROM / 2;
/// Input triangles sampled by a plan made beside ingest.
pub const PLAN_INPUT_SAMPLE: usize = 1 << 14;
/// Samples from which a top node's sample partitions in parallel.
pub const PLAN_PAR_PARTITION: usize = 8192;
/// Samples from which a top node splits its two children in parallel.
pub const PLAN_PAR_SPLIT: usize = 1024;
/// Sample positions per parallel task gathering a plan's sample from the references.
pub const PLAN_SAMPLE_BLOCK: usize = 1024;
/// How far ahead (in samples) a plan from the input prefetches index bytes (vertices half as far).
pub const PLAN_INPUT_PREFETCH: usize = 16;
/// Samples per parallel binning task of a top node.
pub const PLAN_BIN_CHUNK: usize = 2048;
/// Chunk groups of the scatter into buckets (fixed, whatever the thread count).
pub const PLAN_SCATTER_GROUPS: usize = 64;
/// Cells of an axis' grid in the bucket classification.
pub const PLAN_GRID: usize = 1024;

// Emission of the wide (BVH4) nodes.
/// Subtrees of at most this many primitives under a larger parent are encoded as soon as built.
pub const EMIT_CUT: u32 = 4096;
/// Bytes of the pre-emission area per primitive (a cut root over k primitives owns 24·k).
pub const PRE_BYTES_PER_PRIM: usize = 24;
/// Wide subtrees of at least this many nodes emit their children in parallel.
pub const PAR_EMIT_CUTOFF: u32 = 1024;
const _: () = assert!(SAMPLE_FROM as u64 > EMIT_CUT as u64);

// Refit (`refit`).
/// Primitives whose input reads the refit's primitive pass issues together.
pub const REFIT_BATCH: usize = 32;
/// Leaf-order primitives per parallel task of the refit's primitive pass.
pub const REFIT_CHUNK: usize = 1024;
/// Instances per parallel task of a TLAS refit.
pub const REFIT_INSTANCE_CHUNK: usize = 256;
/// Subtrees of at least this many nodes refit their children in parallel.
pub const PAR_REFIT_NODES: usize = 256;

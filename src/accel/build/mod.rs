//! The build pipeline, one stage per module: lower (types, counts, sizes) → ingest (geometry →
//! primitive references in scratch, `ingest`; neighbours clustered, `cluster`) → plan the top
//! of large BLAS trees from one sample (`plan`) → build the subtrees (binned SAH, `subtree`,
//! on the pool, `schedule`; fast-build instance trees: a linear BVH, `morton`) → encode into
//! dst (`crate::accel::encode`).
//!
//! Owns: the order of the stages and the split of dst and scratch between them. Host heap use
//! is O(threads): every array proportional to the input lives in scratch or dst.
pub mod bins;
pub mod cluster;
pub mod ingest;
pub mod morton;
pub mod partition;
pub mod plan;
pub mod schedule;
pub mod small_split;
pub mod subtree;

#[cfg(test)]
mod tests;

use super::encode::{self, LeafSource, Summary};
use super::geometry::{Aabb, PrimRef};
use super::layout::{self, STAGE_SIZE};
use super::params::{BuildParams, CLUSTER_MIN, MAX_CLUSTER, MAX_CLUSTER_GEOMETRIES, PRE_BYTES_PER_PRIM};
use super::primitive::{check_types, make_ref, total_primitives};
use super::tree::{node_refs_mut, BinNode};
use super::{AsType, BuildDesc, BuildError, BuildFlags, BuildPhases, BuildReport, DeviceView, TopPlanned};
use ingest::{compact_chunks, ingest, Clustering, IngestTarget, Ingested};
use plan::TopPlan;
use schedule::{build_tree, run_tasks, top_results, Root};
use std::time::Instant;
use subtree::{BuildContext, Subtree};

/// Builds `desc` into `dst` with its working arrays in `scratch`; see `crate::accel::build`.
pub fn build(desc: &BuildDesc, view: &dyn DeviceView, dst: &mut [u8], scratch: &mut [u8]) -> Result<(BuildReport, BuildPhases), BuildError> {
    let t_start = Instant::now();
    let lowered = lower(desc, dst.len(), scratch.len())?;
    let mut work = Work::carve(scratch, &lowered)?;
    let params = tier(desc);
    let firsts = first_ids(desc);
    let clustering = clustering(desc, view, &lowered, &params, firsts.as_slice());
    let (ingested, plan, top_planned) = ingest_and_plan(desc, view, &lowered, &params, clustering, &mut work, dst)?;
    let t_ingest = Instant::now();
    let ctx = context(desc, &params, clustering, &ingested);
    let pre_len = pre_len(&lowered, ingested.active);
    let (sah_sum, forked_buckets) = build_subtrees(desc, &ctx, plan, &ingested, &mut work, pre_len);
    let (references, active) = (ingested.references, ingested.active);
    let tree = &work.nodes[..(2 * references).saturating_sub(1)];
    let map = ctx.clustered.then(|| leaf_map(&work.refs[..references], &mut work.prefix[..=references]));
    let t_sah = Instant::now();
    if desc.ty != AsType::TopLevel {
        let source = match map {
            Some(map) => LeafSource::Clusters { map, firsts: firsts.as_slice() },
            None if lowered.staged => LeafSource::Staged,
            None => LeafSource::Input,
        };
        encode::leaf_data(desc, dst, &work.stage[..], lowered.total, work.refs, (references, active), source);
    }
    let t_leaf = Instant::now();
    let nodes_at = layout::sections(desc.ty, 0, active as u64, lowered.ngeo).nodes as usize;
    // A TLAS writes its instance sections beside its nodes (`encode::tlas`), the sort keys'
    // area of scratch ordering its BLAS addresses.
    let tlas = if desc.ty == AsType::TopLevel && active > 0 { Some(encode::tlas::write(desc, view, dst, tree, &work.refs[..active], work.pre)?) } else { None };
    let (node_count, leaf_count) = match &tlas {
        Some(w) => (w.node_count, w.leaf_count),
        None if active > 0 => encode::wide_nodes(tree, dst, nodes_at, &work.pre[..pre_len], map)?,
        None => (0, 0),
    };
    let t_nodes = Instant::now();
    let max_leaf_size = if ctx.clustered { ctx.params.max_leaf * params.max_cluster.clamp(1, MAX_CLUSTER) } else { params.max_leaf };
    let summary = Summary { active, total: lowered.total, node_count, leaf_count, bounds: ingested.bounds, sah_sum, max_leaf_size, nodes_at };
    let used = match &tlas {
        Some(w) => encode::finish_tlas(desc, dst, &summary, w)?,
        // The binary nodes are no longer needed: their bytes sort the TLAS's BLAS addresses.
        None => encode::finish(desc, view, dst, work.refs, bytemuck::cast_slice_mut(work.nodes), &summary)?,
    };
    let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3;
    let phases = BuildPhases { ingest_ms: ms(t_start, t_ingest), sah_ms: ms(t_ingest, t_sah), leaf_data_ms: ms(t_sah, t_leaf), nodes_ms: ms(t_leaf, t_nodes), total_ms: ms(t_start, Instant::now()) };
    let clusters = ctx.clustered.then_some(references as u32);
    let report = BuildReport { used_size: used, node_count, leaf_count, primitive_count: active as u32, clusters, top_planned, forked_buckets };
    Ok((report, phases))
}

/// A description checked against the sizes it was given, and whether it stages.
struct Lowered {
    /// Primitives (slots) of the build, inactive ones included.
    total: usize,
    ngeo: u64,
    need_scratch: u64,
    /// BLAS primitive data is staged in scratch during ingest (STAGE_SIZE per primitive at
    /// its global ID), so the leaf-order pass reads one record per primitive instead of
    /// indices and three vertices at random. Builds of one or two primitives read the input.
    staged: bool,
}

/// Checks types, counts and sizes before any work, so failure is cheap and independent of the
/// tree's shape.
fn lower(desc: &BuildDesc, dst_len: usize, scratch_len: usize) -> Result<Lowered, BuildError> {
    check_types(desc)?;
    let total = total_primitives(desc)?;
    let ngeo = desc.geometries.len() as u64;
    let need_scratch = layout::build_scratch_size(desc.ty, total);
    if (scratch_len as u64) < need_scratch {
        return Err(BuildError::ScratchTooSmall { needed: need_scratch, got: scratch_len as u64 });
    }
    let worst = layout::structure_size_bound(desc.ty, desc.flags, total, ngeo);
    if (dst_len as u64) < worst {
        return Err(BuildError::DestinationTooSmall { needed: worst, got: dst_len as u64 });
    }
    let total = total as usize;
    let staged = desc.ty != AsType::TopLevel && total >= 3;
    Ok(Lowered { total, ngeo, need_scratch, staged })
}

/// The build's arrays in scratch: a reference per primitive, two node slots per primitive,
/// a word per primitive (kept counts per ingest chunk, the plan's cells and bucket bytes,
/// then the prefix of primitives per cluster reference), the pre-emission area, and the
/// staging area of staged builds.
struct Work<'s> {
    refs: &'s mut [PrimRef],
    nodes: &'s mut [BinNode],
    prefix: &'s mut [u32],
    pre: &'s mut [u8],
    stage: &'s mut [u8],
}
impl<'s> Work<'s> {
    fn carve(scratch: &'s mut [u8], lowered: &Lowered) -> Result<Self, BuildError> {
        let short = BuildError::ScratchTooSmall { needed: lowered.need_scratch, got: 0 };
        let (refs, rest) = layout::carve::<PrimRef>(scratch, lowered.total).ok_or(short.clone())?;
        let (nodes, rest) = layout::carve::<BinNode>(rest, 2 * lowered.total).ok_or(short.clone())?;
        let (prefix, rest) = layout::carve::<u32>(rest, lowered.total + 1).ok_or(short.clone())?;
        let (pre, rest) = layout::carve::<u8>(rest, lowered.total * PRE_BYTES_PER_PRIM).ok_or(short.clone())?;
        let stage_len = if lowered.staged { lowered.total * STAGE_SIZE } else { 0 };
        let (stage, _) = layout::carve::<u8>(rest, stage_len).ok_or(short)?;
        Ok(Work { refs, nodes, prefix, pre, stage })
    }
}

/// The tier of the build flags; instance trees bin all three axes outside the fast-build tier
/// (few, overlapping boxes at the top of every ray's walk).
fn tier(desc: &BuildDesc) -> BuildParams {
    let mut params = BuildParams::from_flags(desc.flags);
    if desc.ty == AsType::TopLevel && params.all_axes_from != usize::MAX {
        params.all_axes_from = 0;
    }
    params
}

/// First global primitive ID of each of the first MAX_CLUSTER_GEOMETRIES geometries, then the
/// total (global IDs → geometries for clustered builds).
struct FirstIds {
    ids: [u32; MAX_CLUSTER_GEOMETRIES + 1],
    len: usize,
}
impl FirstIds {
    fn as_slice(&self) -> &[u32] {
        &self.ids[..self.len]
    }
}
fn first_ids(desc: &BuildDesc) -> FirstIds {
    let mut ids = [0u32; MAX_CLUSTER_GEOMETRIES + 1];
    for (gi, g) in desc.geometries.iter().enumerate().take(MAX_CLUSTER_GEOMETRIES) {
        ids[gi + 1] = ids[gi].saturating_add(g.primitive_count);
    }
    FirstIds { ids, len: desc.geometries.len().min(MAX_CLUSTER_GEOMETRIES) + 1 }
}

/// Every tier clusters staged BLAS builds of at least CLUSTER_MIN primitives over at most
/// MAX_CLUSTER_GEOMETRIES geometries whose neighbours cluster well in a sample.
fn clustering(desc: &BuildDesc, view: &dyn DeviceView, lowered: &Lowered, params: &BuildParams, firsts: &[u32]) -> Clustering {
    let eligible = lowered.staged && params.cluster_tau > 0.0 && lowered.total >= CLUSTER_MIN && desc.geometries.len() <= MAX_CLUSTER_GEOMETRIES;
    let allow_update = desc.flags.contains(BuildFlags::ALLOW_UPDATE);
    let read = |g: u32, p: u32| desc.geometries.get(g as usize).and_then(|geo| make_ref(g, geo, p, view, allow_update).ok().flatten());
    let tau = if eligible && cluster::worth_clustering(firsts, params.cluster_tau, read) { params.cluster_tau } else { 0.0 };
    Clustering { tau, max_cluster: params.max_cluster }
}

/// Ingest, and for large BLAS builds the plan of the top of the tree: from the input beside
/// ingest when it can, else from the references after it (ingest then leaves its chunks
/// uncompacted, and the scatter into the top's buckets moves them); without a plan the chunks
/// are compacted.
fn ingest_and_plan(desc: &BuildDesc, view: &dyn DeviceView, lowered: &Lowered, params: &BuildParams, clustering: Clustering, work: &mut Work<'_>, dst: &mut [u8]) -> Result<(Ingested, Option<TopPlan>, TopPlanned), BuildError> {
    let (total, chunks) = (lowered.total, plan::chunk_count(desc));
    let want_plan = plan::should_plan(desc, total, chunks, work.prefix.len());
    let (ingested, input_plan) = {
        // The node slots are unused until the tree is built: compaction's temporary, or the
        // planned top's sample.
        let slots = node_refs_mut(work.nodes, total).unwrap_or(&mut []);
        let goff = layout::sections(desc.ty, 0, 0, lowered.ngeo).geometries as usize;
        let geometry_table = dst.get_mut(goff..goff + desc.geometries.len() * layout::GEOMETRY_SIZE).unwrap_or(&mut []);
        let kept = if want_plan { &mut work.prefix[..chunks] } else { &mut *work.prefix };
        let stage = lowered.staged.then_some(&mut *work.stage);
        if want_plan {
            let target = IngestTarget { refs: work.refs, stage, geometry_table, kept, compact_into: None };
            rayon::join(|| ingest(desc, view, target, clustering), || plan::plan_from_input(desc, params, total, slots))
        } else if morton::applies(desc) && slots.len() == total {
            // The linear BVH sorts from the node slots: ingest writes there (compacted
            // references land in `refs`), so the references need no copy before the sort.
            let mut out = ingest(desc, view, IngestTarget { refs: slots, stage, geometry_table, kept, compact_into: Some(&mut *work.refs) }, clustering);
            if let Ok(i) = &mut out {
                i.in_temp = !i.in_temp;
            }
            (out, None)
        } else {
            (ingest(desc, view, IngestTarget { refs: work.refs, stage, geometry_table, kept, compact_into: Some(slots) }, clustering), None)
        }
    };
    let mut ingested = ingested?;
    let (plan, top_planned) = match input_plan {
        Some(plan) => (Some(plan), TopPlanned::FromInput),
        None if want_plan => {
            let room = node_refs_mut(work.nodes, total).unwrap_or(&mut []);
            let plan = plan::plan(desc, params, work.refs, &work.prefix[..chunks], ingested.references, ingested.centroid_bounds, room);
            let planned = if plan.is_some() { TopPlanned::FromReferences } else { TopPlanned::No };
            (plan, planned)
        }
        None => (None, TopPlanned::No),
    };
    if want_plan && plan.is_none() {
        // No top from the sample (it did not split): the compaction ingest skipped.
        let temp = node_refs_mut(work.nodes, total).unwrap_or(&mut []);
        (ingested.references, ingested.in_temp) = compact_chunks(desc, work.refs, temp, &mut work.prefix[..chunks], ingested.references);
    }
    Ok((ingested, plan, top_planned))
}

/// What every node shares. Clustered: leaves of up to `max_cluster_leaf` cluster references,
/// and C_T scaled by the references per primitive keeps the leaf/split balance of the tier.
fn context(desc: &BuildDesc, params: &BuildParams, clustering: Clustering, ingested: &Ingested) -> BuildContext {
    let clustered = clustering.tau > 0.0;
    let mut bparams = *params;
    if clustered {
        bparams.max_leaf = params.max_cluster_leaf.max(1);
        bparams.traversal_cost = (params.traversal_cost * ingested.references as f32 / ingested.active.max(1) as f32).max(1.0);
    }
    BuildContext { params: bparams, total: ingested.references, threads: rayon::current_num_threads().max(1), clustered, prim_traversal_cost: params.traversal_cost, pair_leaves: layout::pairs_leaves(desc.ty, desc.flags) }
}

/// Bytes of the pre-emission area (see `subtree::finish_split`) at the start of
/// `Work::pre`, in scratch, so that dst needs no room beyond the finished structure's worst
/// case. Whether a block fits there never changes the output bytes. Builds that stage nothing
/// (every TLAS) pre-emit nothing, as before the area moved to scratch (`a46ebe2`: their
/// blocks could not be used where the final nodes overlapped the area).
fn pre_len(lowered: &Lowered, active: usize) -> usize {
    if lowered.staged {
        PRE_BYTES_PER_PRIM * active
    } else {
        0
    }
}

/// Builds the binary tree over the ingested references into the node slots: below the
/// planned top's buckets when there is a plan that applies, else from the root. Returns the
/// tree's unnormalised SAH sum and how many buckets split further in parallel.
fn build_subtrees(desc: &BuildDesc, ctx: &BuildContext, plan: Option<TopPlan>, ingested: &Ingested, work: &mut Work<'_>, pre_len: usize) -> (f64, u32) {
    let built = ingested.references;
    if built == 0 {
        return (0.0, 0);
    }
    let chunks = plan::chunk_count(desc);
    let planned = plan.as_ref().and_then(|pl| {
        let (kept, rest) = work.prefix.split_at_mut(chunks);
        let (cells, rest) = rest.split_at_mut(chunks * pl.buckets * plan::CELL_WORDS);
        let cells: &mut [plan::BucketCell] = bytemuck::cast_slice_mut(cells);
        let ids = bytemuck::cast_slice_mut::<u32, u8>(rest).get_mut(..work.refs.len())?;
        plan::classify_chunks(pl, desc, work.refs, kept, cells, ids);
        let s = plan::bucket_sums(pl, cells).filter(|s| s.total() == built)?;
        // A bucket of one reference would be a leaf of one: trees that pair their leaves
        // build from the root instead.
        if ctx.pair_leaves && s.smallest_bucket(pl) == 1 {
            return None;
        }
        plan::scatter(pl, &s, desc, work.refs, plan::Classified { kept, cells, ids }, &mut work.nodes[..2 * built - 1])?;
        Some(s)
    });
    match (plan.as_ref(), planned) {
        (Some(pl), Some(s)) => {
            let mut tasks = Vec::new();
            let root = Subtree { refs: &mut work.refs[..built], nodes: &mut work.nodes[..2 * built - 1], start: 0, bounds: Aabb::EMPTY, bin_box: Aabb::EMPTY, depth: 0, in_nodes: true, pre_area: &mut work.pre[..pre_len], parent_count: u32::MAX, slot: 0 };
            plan::tasks(pl, &s, 0, root, &mut tasks);
            let forked = tasks.iter().filter(|t| ctx.threads > 1 && ctx.top(t.refs.len())).count() as u32;
            let done = run_tasks(ctx, tasks);
            (top_results(&mut work.nodes[..2 * built - 1], 0, &done).0, forked)
        }
        (plan, _) => {
            if plan.is_some() {
                // The plan did not apply after all: the compaction ingest skipped, in place.
                compact_chunks(desc, work.refs, &mut [], &mut work.prefix[..chunks], built);
            }
            if morton::applies(desc) {
                // Instance trees pre-emit nothing: the pre-emission area holds the sort keys.
                if let Some((sah, _)) = morton::build_tree(ctx, &mut work.refs[..built], &mut work.nodes[..2 * built - 1], &mut *work.pre, ingested.centroid_bounds, ingested.in_temp) {
                    return (sah, 0);
                }
            }
            let root = Root { bounds: ingested.bounds, bin_box: ingested.centroid_bounds, in_nodes: ingested.in_temp };
            (build_tree(ctx, &mut work.refs[..built], &mut work.nodes[..2 * built - 1], &mut work.pre[..pre_len], root).0, 0)
        }
    }
}

/// Clustered builds: leaves name references while building and primitives in the output,
/// through the prefix of primitives per reference in leaf order.
fn leaf_map<'p>(refs: &[PrimRef], prefix: &'p mut [u32]) -> &'p [u32] {
    encode::leaves::cluster_prefix(refs, prefix);
    prefix
}

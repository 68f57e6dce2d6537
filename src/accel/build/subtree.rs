//! The binned-SAH recursion over one subtree: each node decides leaf or split (`decide`: the
//! exact split of small nodes, binning with its partition, or an object median), writes its
//! binary node, recurses into its children (`rayon::join` above the tier's cutoff), and sizes
//! or pre-emits its wide subtree on the way back up.
//!
//! Owns: the node decisions and the node slots of one subtree. Must not touch: the top-level
//! scheduling (`schedule`), the stored format beyond pre-emitting cut roots.
use super::bins::{bin_count, bin_in_chunks, bin_one, bin_refs, node_binning, sweep_bins, Binning, Bins, Splitter};
use super::partition::{par_partition_from_nodes, par_partition_to_nodes, partition_out, partition_seq, restore, PRIMREF_BYTES};
use super::small_split::small_split_min;
use crate::accel::encode::nodes::{emit_seq, wide_count};
use crate::accel::geometry::{box_of, centroid, Aabb, PrimRef};
use crate::accel::params::{BuildParams, BIN_CHUNK, EMIT_CUT, MAX_BINS, MAX_SAH_DEPTH, MAX_SMALL, PAR_PARTITION_FROM, PRE_BYTES_PER_PRIM, SAMPLE_CHUNK, SAMPLE_FROM};
use crate::accel::tree::{is_cut, node_refs, wide_size_above_cut, BinNode};

/// What every node of one build shares.
pub struct BuildContext {
    /// The tier's settings, leaf size and C_T adjusted for clusters.
    pub params: BuildParams,
    /// References of the whole build and the pool's thread count (see `one_pass`).
    pub total: usize,
    pub threads: usize,
    /// The references are clusters (`cluster`): leaves cost their primitives.
    pub clustered: bool,
    /// The tier's C_T for costs counted in primitives (`params.traversal_cost` is scaled to
    /// references when clustered).
    pub prim_traversal_cost: f32,
    /// No split leaves a side of fewer than two primitives (`layout::pairs_leaves`): every
    /// leaf of a tree over two or more primitives holds two or more, which bounds the leaves,
    /// and with them the wide nodes, by half the primitives. Binned splits count references
    /// (each holds at least one primitive), exact splits of small nodes primitives.
    pub pair_leaves: bool,
}
impl BuildContext {
    /// The fewest references a side of a binned split may hold.
    #[inline]
    fn min_side(&self) -> usize {
        if self.pair_leaves {
            2
        } else {
            1
        }
    }
    /// Whether a node of `n` references partitions in one sequential pass rather than in
    /// parallel (statistics pass, then scatter): when there are likely at least as many nodes
    /// of its size as threads to keep them busy. Both ways are stable partitions with the same
    /// layout and the same side boxes, so the choice never changes the bytes.
    #[inline]
    pub fn one_pass(&self, n: usize) -> bool {
        n.saturating_mul(self.threads) <= self.total
    }
    /// Parallel partition (or its one-pass form) rather than `partition_out`: large nodes, and
    /// sampled ones always (their left count is not known before the partition).
    #[inline]
    fn big_partition(&self, n: usize) -> bool {
        n >= SAMPLE_FROM || (n >= PAR_PARTITION_FROM && !self.one_pass(n))
    }
    /// A node of the top of the tree (`schedule`): one whose binning and partition fork
    /// (sampled, and too few nodes of its size to keep the threads busy otherwise).
    #[inline]
    pub fn top(&self, n: usize) -> bool {
        n >= SAMPLE_FROM && !self.one_pass(n)
    }
    /// Primitives under these references (a cluster counts its members).
    fn prims_of(&self, refs: &[PrimRef]) -> u32 {
        if self.clustered {
            refs.iter().map(PrimRef::cluster_size).sum::<u32>()
        } else {
            refs.len() as u32
        }
    }
}

/// A node whose subtree is still to be built, and everything it owns: its references, its
/// node slots (a subtree over k references rooted at slot r owns r..r+2k-1), its share of the
/// pre-emission area.
pub struct Subtree<'a> {
    pub refs: &'a mut [PrimRef],
    pub nodes: &'a mut [BinNode],
    /// Its first reference in the whole build.
    pub start: u32,
    pub bounds: Aabb,
    /// The box its bins span (and whose widest axis single-axis tiers bin): the exact centroid
    /// bounds at the root, the node's own box below it. A child's box comes free from its
    /// parent's bins, where its centroid bounds cost every partition four vector min/max per
    /// reference (docs/TUNING.md).
    pub bin_box: Aabb,
    pub depth: u32,
    /// The references are not in `refs` yet but at the start of the node's own slots (where
    /// the parent's parallel partition put them); they reach `refs` through this node's own
    /// parallel partition, or by `restore` before anything else reads or writes them.
    pub in_nodes: bool,
    /// Its range of the pre-emission area (PRE_BYTES_PER_PRIM per reference).
    pub pre_area: &'a mut [u8],
    /// References of its parent (u32::MAX at the root): decides whether it is a cut root.
    pub parent_count: u32,
    /// Its slot in the whole tree's node array (used by the scheduler's tasks only).
    pub slot: usize,
}

/// A node's split: its left count and the two sides' boxes; `in_nodes` when the children find
/// their references at the start of their own node slots.
#[derive(Clone, Copy)]
struct Split {
    mid: usize,
    left: Aabb,
    right: Aabb,
    in_nodes: bool,
}

enum Decision {
    /// A leaf over this many primitives (its references are in `refs`).
    Leaf(u32),
    Split(Split),
}

/// Builds the subtree `t` into `t.nodes[0..2n-1]`; returns its unnormalised SAH sum
/// (Σ inner A + Σ leaf A·|l|, half areas) and its depth. With `sink` (a node of the top of the
/// tree) its children are pushed there as subtrees instead of built.
pub fn build_rec<'a>(ctx: &BuildContext, mut t: Subtree<'a>, bins: &mut Bins, sink: Option<&mut Vec<Subtree<'a>>>) -> (f64, u32) {
    match decide(ctx, &mut t, bins) {
        Decision::Leaf(prims) => {
            let area = t.bounds.half_area();
            if let Some(slot) = t.nodes.get_mut(0) {
                *slot = BinNode { lo: t.bounds.lo, start: t.start, hi: t.bounds.hi, count: t.refs.len() as u32, left_count: 0, wide_nodes: 0 };
            }
            (area as f64 * prims as f64, 1u32)
        }
        Decision::Split(split) => finish_split(ctx, t, split, bins, sink),
    }
}

/// Leaf or split for node `t`: the exact split of small nodes, binned SAH, or (all centroids
/// equal, no SAH split, the depth limit) an object median. On a leaf the references are in
/// `t.refs`; on a split they are partitioned as the split says.
fn decide(ctx: &BuildContext, t: &mut Subtree<'_>, bins: &mut Bins) -> Decision {
    let n = t.refs.len();
    let p = &ctx.params;
    // References still in the node slots come back to `refs` where the node will not
    // partition them: leaves, small nodes, the depth limit.
    if t.in_nodes && (t.depth >= MAX_SAH_DEPTH || n <= p.exact_split_max.clamp(1, MAX_SMALL)) {
        restore(t.refs, t.nodes);
        t.in_nodes = false;
    }
    if n <= 1 || (n as u32 <= p.max_leaf && n as f32 <= p.traversal_cost) {
        // A split costs at least 0 more than C_T·A: no sweep can beat this leaf (the same
        // decision as the SAH test, made without sorting).
        return Decision::Leaf(ctx.prims_of(t.refs));
    }
    if n <= p.exact_split_max.min(MAX_SMALL) && t.depth < MAX_SAH_DEPTH {
        return decide_small(ctx, t);
    }
    if t.depth < MAX_SAH_DEPTH {
        if let Some(d) = decide_binned(ctx, t, bins) {
            return d;
        }
    }
    if t.in_nodes {
        restore(t.refs, t.nodes);
        t.in_nodes = false;
    }
    if n as u32 <= p.max_leaf || n < 2 * ctx.min_side() {
        return Decision::Leaf(ctx.prims_of(t.refs));
    }
    // Object median along the widest axis of the bin box; select_nth_unstable is
    // deterministic and allocation-free.
    let cb = t.bin_box;
    let mut axis = 0;
    for a in 1..3 {
        if cb.hi[a] - cb.lo[a] > cb.hi[axis] - cb.lo[axis] {
            axis = a;
        }
    }
    let mid = n / 2;
    t.refs.select_nth_unstable_by(mid, |x, y| centroid(x)[axis].total_cmp(&centroid(y)[axis]).then(x.geom.cmp(&y.geom)).then(x.prim.cmp(&y.prim)));
    let (l, r) = t.refs.split_at(mid);
    Decision::Split(Split { mid, left: box_of(l), right: box_of(r), in_nodes: false })
}

/// The exact SAH split over sorted centroids of a small node (cheaper than binning for a
/// handful of references, and these nodes are most of the tree), or a leaf.
fn decide_small(ctx: &BuildContext, t: &mut Subtree<'_>) -> Decision {
    let (n, p, cb) = (t.refs.len(), &ctx.params, t.bin_box);
    let widest = (0..3).fold(0, |w, a| if cb.hi[a] - cb.lo[a] > cb.hi[w] - cb.lo[w] { a } else { w });
    let axes = if n >= p.all_axes_from { (0, 3) } else { (widest, widest + 1) };
    let min_w = if ctx.pair_leaves { 2.0 } else { 0.0 };
    let Some((mid, cost)) = small_split_min(t.refs, axes, ctx.clustered, min_w) else { return Decision::Leaf(ctx.prims_of(t.refs)) };
    // Clusters: the sweep's costs count primitives, so the leaf does too, with the tier's C_T.
    let (prims, ct) = (ctx.prims_of(t.refs), if ctx.clustered { ctx.prim_traversal_cost } else { p.traversal_cost });
    let area = t.bounds.half_area();
    if n as u32 <= p.max_leaf && area * prims as f32 <= area * ct + cost {
        return Decision::Leaf(prims);
    }
    let (l, r) = t.refs.split_at(mid);
    Decision::Split(Split { mid, left: box_of(l), right: box_of(r), in_nodes: false })
}

/// The binned SAH split of node `t` (bins over a sample for the largest nodes), partitioned
/// by whichever partition suits its size, or a leaf when the SAH says so. None: no usable
/// split (every binned axis flat, or everything on one side); the references are then in
/// `t.refs` or still in the node slots (`t.in_nodes`).
fn decide_binned(ctx: &BuildContext, t: &mut Subtree<'_>, bins: &mut Bins) -> Option<Decision> {
    let (n, p) = (t.refs.len(), &ctx.params);
    let (bn, scale, k) = bin_node(ctx, t, bins)?;
    let (a, b, lbox, rbox, cost) = sweep_bins(bins, k, &scale, ctx.min_side() as u32)?;
    // SAH termination: a leaf costs A·n, a split A·C_T + children.
    let area = t.bounds.half_area();
    if n as u32 <= p.max_leaf && area * n as f32 <= area * p.traversal_cost + cost {
        if t.in_nodes {
            restore(t.refs, t.nodes);
            t.in_nodes = false;
        }
        return Some(Decision::Leaf(ctx.prims_of(t.refs)));
    }
    let sp = bn.splitter(a, (b + 1) as f32);
    // Left count from the bins (exact: binning and the split test share their arithmetic),
    // except for sampled nodes, which take the parallel partition.
    let nl_bins = bins.count[a][..=b.min(MAX_BINS - 1)].iter().map(|&c| c as usize).sum::<usize>();
    partition_node(ctx, t, &sp, nl_bins, (lbox, rbox))
}

/// Fills `bins` for node `t` (a strided sample for the largest nodes, in parallel chunks at
/// the top of the tree): its binning, per-axis scales and bin count; None when every binned
/// axis is flat.
fn bin_node(ctx: &BuildContext, t: &Subtree<'_>, bins: &mut Bins) -> Option<(Binning, [f32; 3], usize)> {
    let (n, p) = (t.refs.len(), &ctx.params);
    let k = bin_count(p, n);
    let (bn, scale) = node_binning(p, &t.bin_box, k, n)?;
    let axes = bn.axes;
    bins.reset(k, axes);
    let src: &[PrimRef] = if t.in_nodes { node_refs(t.nodes, n).unwrap_or(&[]) } else { t.refs };
    if n >= SAMPLE_FROM {
        // Large nodes bin an evenly strided sample of about `sample_target` references (the
        // stride follows from n alone): the split choice needs only the relative costs, and
        // these nodes always take the parallel partition, which computes the exact boxes.
        let step = (n / p.sample_target.max(1)).max(1);
        let bin_sample = |c: &[PrimRef], b: &mut Bins| {
            if step == 1 {
                bin_refs(c, &bn, b);
            } else {
                for r in c.iter().step_by(step) {
                    bin_one(r, &bn, b);
                }
            }
        };
        if !ctx.top(n) {
            // One of at least as many nodes of its size as threads: sampled here, with no fork
            // to wait on (see `schedule`); the same bins as in chunks.
            bin_sample(src, bins);
        } else {
            bins.merge(&bin_in_chunks(src, if step == 1 { BIN_CHUNK } else { SAMPLE_CHUNK * step }, k, axes, bin_sample), k, axes);
        }
    } else {
        bin_refs(src, &bn, bins);
    }
    Some((bn, scale, k))
}

/// Partitions node `t` by `sp` (`nl_bins` lefts by the bins, the sides' boxes from them) with
/// the partition that suits its size and where its references are; None when everything ends
/// on one side.
fn partition_node(ctx: &BuildContext, t: &mut Subtree<'_>, sp: &Splitter, nl_bins: usize, (lbox, rbox): (Aabb, Aabb)) -> Option<Decision> {
    let n = t.refs.len();
    let split = |mid: usize, left: Aabb, right: Aabb, in_nodes: bool| (mid > 0 && mid < n).then_some(Decision::Split(Split { mid, left, right, in_nodes }));
    // Where the references end in `refs` a side below the minimum is no split either (the
    // bins' counts already exclude it: binning and the split test share their arithmetic, and
    // a sampled side holds at least the sample's count).
    let min = ctx.min_side();
    let split = |mid: usize, left: Aabb, right: Aabb, in_nodes: bool| if in_nodes || (mid >= min && n - mid.min(n) >= min) { split(mid, left, right, in_nodes) } else { None };
    if t.in_nodes {
        // Scatter from this node's slots straight into `refs` (no copy back); with everything
        // on one side that is a plain copy, as a restore would be.
        t.in_nodes = false;
        if ctx.big_partition(n) {
            match par_partition_from_nodes(t.refs, t.nodes, ctx.one_pass(n), |r| sp.left(r)) {
                Some((i, l, r)) if i > 0 && i < n => return split(i, l, r, false),
                Some(_) => {}
                None => restore(t.refs, t.nodes),
            }
        } else {
            let out = node_refs(t.nodes, n).and_then(|src| partition_out(src, bytemuck::cast_slice_mut(t.refs), nl_bins, PRIMREF_BYTES * nl_bins, sp));
            match out {
                Some(i) if i > 0 && i < n => return split(i, lbox, rbox, false),
                _ => restore(t.refs, t.nodes),
            }
        }
    } else if ctx.big_partition(n) {
        // Large node: stable partition through the (still unwritten) node slots of this
        // subtree, in parallel with fixed chunking or in one pass, the same order either way.
        if let Some((i, l, r)) = par_partition_to_nodes(t.refs, t.nodes, ctx.one_pass(n), |r| sp.left(r)) {
            if i > 0 && i < n {
                return split(i, l, r, true);
            }
        }
    } else if nl_bins > 0 && nl_bins < n {
        // Sequential out-of-place partition into the children's node slots (one read and one
        // write per reference); the children partition back into `refs`. `refs` is untouched
        // if it fails (in-place partition below).
        let rbase = (2 * nl_bins - 1) * std::mem::size_of::<BinNode>();
        if let Some(rest) = t.nodes.get_mut(1..) {
            if let Some(i) = partition_out(t.refs, bytemuck::cast_slice_mut(rest), nl_bins, rbase, sp) {
                if i > 0 && i < n {
                    return split(i, lbox, rbox, true);
                }
            }
        }
    }
    let i = partition_seq(t.refs, sp);
    // Bins of a sampled node do not bound every reference: exact boxes then.
    let (lbox, rbox) = if n >= SAMPLE_FROM && i > 0 && i < n { (box_of(&t.refs[..i]), box_of(&t.refs[i..])) } else { (lbox, rbox) };
    split(i, lbox, rbox, false)
}

/// Writes node `t` as split by `split` and builds both children (or, with `sink`, hands them
/// over as subtrees); then sizes the node's wide subtree, pre-emitting it when it is a cut root.
fn finish_split<'a>(ctx: &BuildContext, t: Subtree<'a>, split: Split, bins: &mut Bins, sink: Option<&mut Vec<Subtree<'a>>>) -> (f64, u32) {
    let Subtree { refs, nodes, start, bounds, depth, pre_area, parent_count, slot, .. } = t;
    let n = refs.len();
    if let Some(node) = nodes.get_mut(0) {
        *node = BinNode { lo: bounds.lo, start, hi: bounds.hi, count: n as u32, left_count: split.mid as u32, wide_nodes: 0 };
    }
    let kids = Children { split, start, depth: depth + 1, parent_count: n as u32 };
    if let Some(sink) = sink {
        // A node of the top of the tree (`schedule`): its children become tasks; their
        // results and this node's come later, in `top_results`.
        let (l, r) = kids.subtrees(refs, nodes, pre_area, (slot + 1, slot + 2 * kids.split.mid));
        sink.push(l);
        sink.push(r);
        return (0.0, 0);
    }
    let me = n as u32;
    let area = bounds.half_area() as f64;
    let (l, r) = kids.subtrees(&mut *refs, &mut *nodes, &mut *pre_area, (0, 0));
    let (a, b) = if me >= ctx.params.parallel_cutoff {
        rayon::join(|| build_rec(ctx, l, bins, None), || build_rec(ctx, r, &mut Bins::new(), None))
    } else {
        (build_rec(ctx, l, bins, None), build_rec(ctx, r, bins, None))
    };
    // Wide-subtree size if this node becomes a BVH4 node (kept in `wide_nodes`), needed above
    // the cut roots only: emission hands disjoint output ranges to threads from it. A cut
    // root's wide subtree is encoded now, while its binary nodes are in cache, sequentially
    // into its own range of the pre-emission area (the final pass copies the block into
    // place); its size is what that wrote, or a count when it did not fit.
    let w = if me > EMIT_CUT {
        wide_size_above_cut(nodes)
    } else if is_cut(parent_count, me) {
        let (mut cursor, mut leaves) = (0u32, 0u32);
        match emit_seq(nodes, 0, pre_area, 0, &mut cursor, &mut leaves, None) {
            Some(_) => cursor,
            None => wide_count(nodes, 0),
        }
    } else {
        0
    };
    if let Some(slot) = nodes.get_mut(0) {
        slot.wide_nodes = w;
    }
    (area + a.0 + b.0, 1 + a.1.max(b.1))
}

/// The children of a split node: where each one's references, node slots and pre-emission
/// range start, and the boxes they take from the split.
struct Children {
    split: Split,
    start: u32,
    depth: u32,
    parent_count: u32,
}
impl Children {
    /// The two children as subtrees over the parent's `refs`, node slots (`nodes[0]` is the
    /// parent) and pre-emission range, at the given slots of the whole tree.
    fn subtrees<'b>(&self, refs: &'b mut [PrimRef], nodes: &'b mut [BinNode], pre_area: &'b mut [u8], slots: (usize, usize)) -> (Subtree<'b>, Subtree<'b>) {
        let Split { mid, left, right, in_nodes } = self.split;
        let (lrefs, rrefs) = refs.split_at_mut(mid);
        let rest = nodes.get_mut(1..).unwrap_or(&mut []);
        let (lnodes, rnodes) = rest.split_at_mut((2 * mid - 1).min(rest.len()));
        let (lpre, rpre) = pre_area.split_at_mut((PRE_BYTES_PER_PRIM * mid).min(pre_area.len()));
        let (depth, parent_count) = (self.depth, self.parent_count);
        let l = Subtree { refs: lrefs, nodes: lnodes, start: self.start, bounds: left, bin_box: left, depth, in_nodes, pre_area: lpre, parent_count, slot: slots.0 };
        let r = Subtree { refs: rrefs, nodes: rnodes, start: self.start + mid as u32, bounds: right, bin_box: right, depth, in_nodes, pre_area: rpre, parent_count, slot: slots.1 };
        (l, r)
    }
}

//! Scheduling of a tree's subtrees on the pool: on one thread the plain recursion; on more, two
//! phases (the top of the tree split by tasks that spawn tasks, then every subtree below it as
//! a task of its own, largest first), and the top's sums afterwards (`top_results`). The task
//! decomposition depends on the input alone, so the bytes do not depend on the thread count.
//!
//! Owns: which thread builds which subtree, and when. Must not touch: node decisions.
use super::bins::Bins;
use super::subtree::{build_rec, BuildContext, Subtree};
use crate::accel::geometry::{Aabb, PrimRef};
use crate::accel::tree::{bin_children, wide_size_above_cut, BinNode};
use rayon::prelude::*;
use std::sync::Mutex;

/// The root of a tree for `build_tree`: its box, the box its bins span (the centroid box), and
/// whether its references wait at the start of its node slots.
pub struct Root {
    pub bounds: Aabb,
    pub bin_box: Aabb,
    pub in_nodes: bool,
}

/// (node slot, SAH sum and depth) of a subtree built as a task.
pub type Built = (usize, (f64, u32));

/// Builds the tree over `refs` (see `build_rec`): the same nodes in the same slots, the same
/// sums, for any thread count. On more than one thread it runs in two phases. First the top
/// of the tree (`BuildContext::top`: nodes that bin a sample and partition in parallel chunks, since
/// there are fewer nodes of their size than threads): each top node is a task that splits
/// its node and spawns its top children as tasks; its other children are set aside. Then
/// every set-aside subtree is built as a task of its own, largest first; none of their
/// nodes forks inside its binning or partition. The top nodes' SAH sums, depths and wide
/// sizes follow from their children's afterwards (`top_results`), added in the order
/// `finish_split` adds them.
///
/// Why not recursion all the way down: a thread waiting inside a top node's parallel
/// partition or sampled binning (`rayon::join`) steals whatever task is queued, and once
/// subtrees exist that is often a whole subtree, milliseconds of work; the top node's
/// partition, and with it the next subtrees, waits until that is done: the subtrees started
/// in waves, each when the last had ended, with a third of the threads idle. In the first
/// phase only top-node work is queued; in the second every thread has subtrees to take and
/// nothing waits on a fork but the joins that sum a subtree (figures in docs/TUNING.md).
pub fn build_tree(ctx: &BuildContext, refs: &mut [PrimRef], nodes: &mut [BinNode], pre_area: &mut [u8], root: Root) -> (f64, u32) {
    let Root { bounds, bin_box, in_nodes } = root;
    let top = ctx.threads > 1 && ctx.top(refs.len());
    let root = Subtree { refs, nodes: &mut *nodes, start: 0, bounds, bin_box, depth: 0, in_nodes, pre_area, parent_count: u32::MAX, slot: 0 };
    if !top {
        return build_rec(ctx, root, &mut Bins::new(), None);
    }
    let done = run_tasks(ctx, vec![root]);
    top_results(nodes, 0, &done)
}

/// Builds the subtrees of `tasks` (disjoint parts of one tree whose nodes above them are
/// written) and returns (node slot, SAH sum and depth) of each subtree root not split by
/// `split_top`, sorted by slot, for `top_results`: on one thread one after the other,
/// otherwise in `build_tree`'s two phases.
pub fn run_tasks(ctx: &BuildContext, tasks: Vec<Subtree<'_>>) -> Vec<Built> {
    let mut done: Vec<Built>;
    if ctx.threads <= 1 {
        done = tasks.into_iter().map(|t| (t.slot, t)).map(|(slot, t)| (slot, build_rec(ctx, t, &mut Bins::new(), None))).collect();
    } else {
        let finished = Mutex::new(Vec::new());
        let below = Mutex::new(Vec::new());
        let (fin, bel) = (&finished, &below);
        rayon::scope(|s| {
            for t in tasks {
                if ctx.top(t.refs.len()) {
                    s.spawn(move |s| split_top(s, ctx, t, fin, bel));
                } else if let Ok(mut b) = bel.lock() {
                    b.push(t);
                }
            }
        });
        let mut subtrees = below.into_inner().unwrap_or_default();
        subtrees.sort_by_key(|t| (std::cmp::Reverse(t.refs.len()), t.slot));
        // (node slot, SAH sum and depth) of every subtree not split in the first phase.
        done = finished.into_inner().unwrap_or_default();
        done.par_extend(subtrees.into_par_iter().with_max_len(1).map(|t| (t.slot, t)).map(|(slot, t)| (slot, build_rec(ctx, t, &mut Bins::new(), None))));
    }
    done.sort_by_key(|d| d.0);
    done
}

/// One top node of `build_tree`: splits it, spawns its top children as tasks, and sets the
/// others aside in `below` (a node that ends as a leaf goes to `finished` with its result).
pub fn split_top<'s, 'a: 's>(s: &rayon::Scope<'s>, ctx: &'s BuildContext, t: Subtree<'a>, finished: &'s Mutex<Vec<Built>>, below: &'s Mutex<Vec<Subtree<'a>>>) {
    let mut sink = Vec::new();
    let slot = t.slot;
    let r = build_rec(ctx, t, &mut Bins::new(), Some(&mut sink));
    if sink.is_empty() {
        if let Ok(mut f) = finished.lock() {
            f.push((slot, r));
        }
    }
    for c in sink {
        if ctx.top(c.refs.len()) {
            s.spawn(move |s| split_top(s, ctx, c, finished, below));
        } else if let Ok(mut b) = below.lock() {
            b.push(c);
        }
    }
}

/// SAH sum and depth of the subtree at slot `i` of a tree built by `build_tree`: a task's
/// result, or for a top node its area plus its children's, as `finish_split` adds them,
/// setting its wide size on the way.
pub fn top_results(nodes: &mut [BinNode], i: usize, done: &[Built]) -> (f64, u32) {
    if let Ok(k) = done.binary_search_by_key(&i, |d| d.0) {
        return done[k].1;
    }
    let Some((l, r)) = bin_children(nodes, i) else { return (0.0, 0) };
    let (a, b) = (top_results(nodes, l, done), top_results(nodes, r, done));
    let Some(sub) = nodes.get_mut(i..).filter(|s| !s.is_empty()) else { return (0.0, 0) };
    let w = wide_size_above_cut(sub);
    sub[0].wide_nodes = w;
    let area = Aabb { lo: sub[0].lo, hi: sub[0].hi }.half_area() as f64;
    (area + a.0 + b.0, 1 + a.1.max(b.1))
}

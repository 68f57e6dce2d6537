//! Emission of the wide (BVH4) nodes from the binary tree in scratch: preorder, child indices
//! from subtree sizes, subtrees in parallel; cut roots encoded while the tree is built
//! (`emit_seq` into the pre-emission area) are copied into place (`copy_block`).
//!
//! Owns: node emission and the leaf spans of clustered builds. Must not touch: how the binary
//! tree was built, primitive data.
use super::quantize::quantize_node;
use crate::accel::geometry::to_aabb;
use crate::accel::layout::{WideNode, CHILD_INTERNAL, NODE_SIZE};
use crate::accel::params::{PAR_EMIT_CUTOFF, PRE_BYTES_PER_PRIM};
use crate::accel::tree::{wide_children, wide_size, BinNode};
use glam::Vec3A;

/// The byte range of cut root `nd`'s pre-emitted block in the pre-emission area of `pre_len`
/// bytes, if it was pre-emitted (the same test `finish_split` made).
pub fn pre_block(nd: &BinNode, pre_len: usize) -> Option<std::ops::Range<usize>> {
    let lo = PRE_BYTES_PER_PRIM.checked_mul(nd.start as usize)?;
    let hi = PRE_BYTES_PER_PRIM.checked_mul(nd.start as usize + nd.count as usize)?.min(pre_len);
    let len = nd.wide_nodes as usize * NODE_SIZE;
    (nd.left_count != 0 && lo.checked_add(len)? <= hi).then_some(lo..lo + len)
}

/// Copies a pre-emitted block (local indices) to wide index `base`; returns its leaf children.
/// With `map` (clustered builds) leaf children are turned from references into primitives
/// (`leaf_span`), which the block was encoded without.
pub fn copy_block(src: &[u8], out: &mut [u8], base: u32, map: Option<&[u32]>) -> u32 {
    let mut leaves = 0;
    out.copy_from_slice(src);
    for node in out.chunks_exact_mut(NODE_SIZE) {
        for c in 0..4 {
            let kind = node[56 + c];
            let at = 40 + 4 * c;
            let v = u32::from_le_bytes([node[at], node[at + 1], node[at + 2], node[at + 3]]);
            if kind == CHILD_INTERNAL {
                node[at..at + 4].copy_from_slice(&v.wrapping_add(base).to_le_bytes());
            } else if kind != 0 {
                leaves += 1;
                if map.is_some() {
                    let (first, count) = leaf_span(v, kind as u32, map);
                    node[at..at + 4].copy_from_slice(&first.to_le_bytes());
                    node[56 + c] = count.min(254) as u8;
                }
            }
        }
    }
    leaves
}

/// A leaf's first primitive and primitive count from its first reference and reference count:
/// the same numbers unclustered, through the prefix `map` of primitives per reference when clustered.
#[inline]
pub fn leaf_span(start: u32, count: u32, map: Option<&[u32]>) -> (u32, u32) {
    match map {
        None => (start, count),
        Some(m) => {
            let a = m.get(start as usize).copied().unwrap_or(0);
            let b = m.get(start.saturating_add(count) as usize).copied().unwrap_or(a);
            (a, b.saturating_sub(a))
        }
    }
}

/// One pending subtree emission.
struct EmitTask<'a> {
    /// The binary subtree (the slice starts at its root).
    nodes: &'a [BinNode],
    /// Its root's wide node index.
    index: u32,
    /// Exactly its output range.
    out: &'a mut [u8],
    pre_emitted: Option<&'a [u8]>,
    /// A cut root, encoded sequentially (`emit_seq`: its inner nodes carry no sizes) rather
    /// than by `emit_wide`.
    cut_root: bool,
}

/// Emits `tasks` (halves in parallel while they hold at least PAR_EMIT_CUTOFF wide nodes);
/// returns their leaf children.
fn run_emit(tasks: &mut [Option<EmitTask<'_>>], map: Option<&[u32]>) -> u32 {
    match tasks.len() {
        0 => 0,
        1 => match tasks[0].take() {
            Some(EmitTask { nodes, index, out, cut_root: true, .. }) => {
                let (mut cursor, mut l) = (0u32, 0u32);
                let _ = emit_seq(nodes, 0, out, index, &mut cursor, &mut l, map);
                l
            }
            Some(EmitTask { nodes, index, out, pre_emitted, cut_root: false }) => emit_wide(nodes, index, out, pre_emitted, map),
            None => 0,
        },
        len => {
            let size: u32 = tasks.iter().map(|t| t.as_ref().map_or(0, |t| wide_size(t.nodes))).sum();
            let (a, b) = tasks.split_at_mut(len / 2);
            if size >= PAR_EMIT_CUTOFF {
                let (x, y) = rayon::join(|| run_emit(a, map), || run_emit(b, map));
                x + y
            } else {
                run_emit(a, map) + run_emit(b, map)
            }
        }
    }
}

/// The wide node made from binary node `i` (its children from `wide_children`): leaf children
/// point at their primitives, and `internal(slot, node, is_cut_root)` gives each internal
/// child's node index, in child order (emission in preorder). Returns the node and its leaf
/// children; None when `internal` does.
pub fn wide_node(nodes: &[BinNode], i: usize, map: Option<&[u32]>, mut internal: impl FnMut(usize, &BinNode, bool) -> Option<u32>) -> Option<(WideNode, u32)> {
    let (ch, cnt, cut) = wide_children(nodes, i);
    let cnt = cnt.min(4);
    // Child boxes as vectors loaded straight from the (long since written) binary nodes.
    let mut clo = [Vec3A::ZERO; 4];
    let mut chi = [Vec3A::ZERO; 4];
    let mut child = [0u32; 4];
    let mut kind = [0u8; 4];
    let (mut nlo, mut nhi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let mut leaves = 0u32;
    for k in 0..cnt {
        let nd = nodes.get(ch[k])?;
        (clo[k], chi[k]) = (Vec3A::from(nd.lo), Vec3A::from(nd.hi));
        nlo = nlo.min(clo[k]);
        nhi = nhi.max(chi[k]);
        if nd.left_count != 0 && ch[k] != i {
            kind[k] = CHILD_INTERNAL;
            child[k] = internal(ch[k], nd, cut >> k & 1 != 0)?;
        } else {
            let (first, count) = leaf_span(nd.start, nd.count, map);
            kind[k] = count.min(254) as u8;
            child[k] = first;
            leaves += 1;
        }
    }
    for k in cnt..4 {
        (clo[k], chi[k]) = (nlo, nlo);
    }
    Some((quantize_node(&to_aabb(nlo, nhi), &clo, &chi, cnt, &child, &kind), leaves))
}

/// Emits the wide subtree of binary node `i` (inside a cut subtree: no cut roots below it) in
/// preorder at local index `*cursor` onwards of `out`, child indices offset by `base`; the
/// same bytes `emit_wide` writes, without needing subtree sizes in advance. Counts leaf
/// children into `leaves`; None when `out` is too small (what was written is then garbage).
pub fn emit_seq(nodes: &[BinNode], i: usize, out: &mut [u8], base: u32, cursor: &mut u32, leaves: &mut u32, map: Option<&[u32]>) -> Option<u32> {
    let me = *cursor;
    *cursor += 1;
    let at = me as usize * NODE_SIZE;
    if at + NODE_SIZE > out.len() {
        return None;
    }
    let (wn, l) = wide_node(nodes, i, map, |slot, _, _| emit_seq(nodes, slot, out, base, cursor, leaves, map).map(|c| base + c))?;
    *leaves += l;
    out.get_mut(at..at + NODE_SIZE)?.copy_from_slice(bytemuck::bytes_of(&wn));
    Some(me)
}

/// Wide nodes of binary node `i`'s wide subtree (inside a cut subtree), by counting.
pub fn wide_count(nodes: &[BinNode], i: usize) -> u32 {
    let (ch, cnt, _) = wide_children(nodes, i);
    let mut w = 1u32;
    for &c in &ch[..cnt] {
        if nodes.get(c).is_some_and(|nd| nd.left_count != 0) && c != i {
            w = w.saturating_add(wide_count(nodes, c));
        }
    }
    w
}

/// Emits the wide node made from the binary subtree rooted at `nodes[0]` as node `me` into
/// `out[..64]` and its descendants (preorder) after it; returns the number of leaf children.
/// Child indices follow from subtree sizes, never from timing: same bytes for any thread count.
/// With `pre_emitted`, cut-root children whose blocks were pre-emitted are copied from there (the
/// same bytes the recursion would write).
pub fn emit_wide(nodes: &[BinNode], me: u32, out: &mut [u8], pre_emitted: Option<&[u8]>, map: Option<&[u32]>) -> u32 {
    let mut next = me + 1;
    let mut pending: [(usize, u32, u32, bool); 4] = [(0, 0, 0, false); 4];
    let mut np = 0;
    let Some((wn, mut leaves)) = wide_node(nodes, 0, map, |slot, nd, is_cut_root| {
        let idx = next;
        pending[np] = (slot, idx, nd.wide_nodes, is_cut_root);
        np += 1;
        next = next.saturating_add(nd.wide_nodes);
        Some(idx)
    }) else {
        return 0;
    };
    let (head, mut rest) = out.split_at_mut(NODE_SIZE.min(out.len()));
    if head.len() == NODE_SIZE {
        head.copy_from_slice(bytemuck::bytes_of(&wn));
    }
    let mut tasks: [Option<EmitTask<'_>>; 4] = [None, None, None, None];
    let mut nt = 0;
    for &(rel, idx, w, is_cut_root) in &pending[..np] {
        let len = (w as usize * NODE_SIZE).min(rest.len());
        let (mine, others) = std::mem::take(&mut rest).split_at_mut(len);
        rest = others;
        if is_cut_root {
            // Inner nodes of a cut subtree carry no sizes: its block is copied, or encoded
            // here sequentially into its exact range.
            if let (Some(pre_emitted), Some(nd)) = (pre_emitted, nodes.get(rel)) {
                if let Some(src) = pre_block(nd, pre_emitted.len()).and_then(|r| pre_emitted.get(r)) {
                    if src.len() == mine.len() {
                        leaves += copy_block(src, mine, idx, map);
                        continue;
                    }
                }
            }
            // Without a usable block (builds that stage nothing, such as every TLAS, have no
            // pre-emission area) it is a task like the others, so that sibling cut roots are
            // encoded in parallel.
            tasks[nt] = nodes.get(rel..).map(|n| EmitTask { nodes: n, index: idx, out: mine, pre_emitted, cut_root: true });
            nt += 1;
            continue;
        }
        tasks[nt] = nodes.get(rel..).map(|n| EmitTask { nodes: n, index: idx, out: mine, pre_emitted, cut_root: false });
        nt += 1;
    }
    leaves + run_emit(&mut tasks[..nt], map)
}

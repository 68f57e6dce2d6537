//! The binary tree in scratch (`BinNode`, preorder slots derived from primitive ranges) and
//! the rule that collapses it into wide nodes (`wide_children`, cut roots): shared by the
//! builder, which sizes wide subtrees while building, and the encoder, which emits them.
//!
//! Owns: slot arithmetic and the collapse rule. Must not touch: how splits are chosen, the
//! bytes of wide nodes.
use super::geometry::{Aabb, PrimRef};
use super::layout;
use super::params::EMIT_CUT;
use bytemuck::{Pod, Zeroable};

/// Binary node in scratch. A subtree over k primitives rooted at slot r owns slots r..r+2k-1:
/// left child at r+1, right child at r+2*left_count. Slots follow from primitive ranges, never
/// from timing, which is what makes the tree identical for every thread count.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct BinNode {
    pub lo: [f32; 3],
    pub start: u32,
    pub hi: [f32; 3],
    pub count: u32,
    /// 0 = leaf, else primitives in the left child.
    pub left_count: u32,
    /// Wide nodes of this node's wide subtree, for internal nodes above the cut and cut roots
    /// (emission hands out output ranges from it); 0 inside cut subtrees.
    pub wide_nodes: u32,
}
const _: () = assert!(std::mem::size_of::<BinNode>() == layout::BINNODE_SIZE as usize);

#[inline]
pub fn is_cut(parent_count: u32, count: u32) -> bool {
    count <= EMIT_CUT && parent_count > EMIT_CUT
}

/// Binary children of a binary node: (left slot, right slot), for an internal node.
#[inline]
pub fn bin_children(nodes: &[BinNode], i: usize) -> Option<(usize, usize)> {
    let n = nodes.get(i)?;
    if n.left_count == 0 {
        return None;
    }
    Some((i + 1, i + 2 * n.left_count as usize))
}

/// The ≤4 binary subtrees that become the children of the wide node made from binary node `i`:
/// repeatedly open the internal child with the largest area (ties: lowest slot), never a cut
/// root (`is_cut`). The mask has bit k set when child k is a cut root.
pub fn wide_children(nodes: &[BinNode], i: usize) -> ([usize; 4], usize, u8) {
    let mut ch = [0usize; 4];
    let Some((l, r)) = bin_children(nodes, i) else {
        ch[0] = i;
        return (ch, 1, 0);
    };
    let cnt_of = |s: usize| nodes.get(s).map_or(0, |n| n.count);
    let root_count = cnt_of(i);
    ch[0] = l;
    ch[1] = r;
    let mut cut = [is_cut(root_count, cnt_of(l)), is_cut(root_count, cnt_of(r)), false, false];
    let mut count = 2;
    while count < 4 {
        let mut best: Option<(usize, f32)> = None;
        for (k, &c) in ch[..count].iter().enumerate() {
            if let Some(nd) = nodes.get(c) {
                if nd.left_count != 0 && !cut[k] {
                    let a = Aabb { lo: nd.lo, hi: nd.hi }.half_area();
                    if best.is_none_or(|b| a > b.1) {
                        best = Some((k, a));
                    }
                }
            }
        }
        let Some((k, _)) = best else { break };
        let Some((l, r)) = bin_children(nodes, ch[k]) else { break };
        let pc = cnt_of(ch[k]);
        ch[k] = l;
        cut[k] = is_cut(pc, cnt_of(l));
        ch[count] = r;
        cut[count] = is_cut(pc, cnt_of(r));
        count += 1;
    }
    let mask = cut.iter().enumerate().fold(0u8, |m, (k, &c)| m | (c as u8) << k);
    (ch, count, mask)
}

/// The wide-subtree size of the node at `nodes[0]` above the cut roots (see `finish_split`):
/// one wide node plus its internal children's sizes.
pub fn wide_size_above_cut(nodes: &[BinNode]) -> u32 {
    let (ch, cnt, _) = wide_children(nodes, 0);
    let mut w = 1u32;
    for &c in &ch[..cnt] {
        if let Some(nd) = nodes.get(c) {
            if nd.left_count != 0 {
                w = w.saturating_add(nd.wide_nodes);
            }
        }
    }
    w
}

/// Wide nodes of a subtree in preorder; an internal binary node above the cut keeps it in `wide_nodes`.
pub fn wide_size(nodes: &[BinNode]) -> u32 {
    match nodes.first() {
        Some(n) if n.left_count != 0 => n.wide_nodes,
        Some(_) => 1,
        None => 0,
    }
}

/// The first `n` references' worth of bytes of `nodes`, viewed as references.
pub fn node_refs(nodes: &[BinNode], n: usize) -> Option<&[PrimRef]> {
    let bytes: &[u8] = bytemuck::cast_slice(nodes);
    bytemuck::try_cast_slice(bytes.get(..n * std::mem::size_of::<PrimRef>())?).ok()
}
pub fn node_refs_mut(nodes: &mut [BinNode], n: usize) -> Option<&mut [PrimRef]> {
    let bytes: &mut [u8] = bytemuck::cast_slice_mut(nodes);
    bytemuck::try_cast_slice_mut(bytes.get_mut(..n * std::mem::size_of::<PrimRef>())?).ok()
}


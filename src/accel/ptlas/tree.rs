//! The BVH4 of one partition (over its active instances) and of the top level (over partition
//! roots and global instances), in the node format of `accel::layout`, quantised by the same
//! encoder as every other structure. Median splits on the widest centroid axis, keyed by
//! (centroid, child) so the tree depends only on the set of entries, never on their order.
//!
//! Owns: the tree shape of partitions and the top level. Must not touch: instance records.
use glam::Vec3A;

use crate::accel::encode::quantize::quantize_node;
use crate::accel::geometry::Aabb;
use crate::accel::layout::{WideNode, CHILD_INTERNAL};

/// One child to place: a leaf of one instance slot (kind 1) or a subtree root (CHILD_INTERNAL).
#[derive(Clone, Copy, Debug)]
pub struct Entry {
    pub lo: [f32; 3],
    pub hi: [f32; 3],
    pub child: u32,
    pub kind: u8,
}

impl Entry {
    fn centroid(&self, a: usize) -> f32 {
        self.lo[a] * 0.5 + self.hi[a] * 0.5
    }
}

fn box_of(entries: &[Entry]) -> Aabb {
    let mut b = Aabb::EMPTY;
    for e in entries {
        b.grow(&e.lo, &e.hi);
    }
    b
}

fn key_cmp(a: &Entry, b: &Entry, axis: usize) -> std::cmp::Ordering {
    a.centroid(axis).total_cmp(&b.centroid(axis)).then(a.child.cmp(&b.child)).then(a.kind.cmp(&b.kind))
}

/// Splits at the median of the widest centroid axis: (lower half, upper half).
fn split(entries: &mut [Entry]) -> (&mut [Entry], &mut [Entry]) {
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for e in entries.iter() {
        for a in 0..3 {
            let c = e.centroid(a);
            lo[a] = lo[a].min(c);
            hi[a] = hi[a].max(c);
        }
    }
    let ext = |a: usize| (hi[a] - lo[a]).max(0.0);
    let axis = if ext(0) >= ext(1) && ext(0) >= ext(2) {
        0
    } else if ext(1) >= ext(2) {
        1
    } else {
        2
    };
    let mid = entries.len() / 2;
    entries.select_nth_unstable_by(mid, |a, b| key_cmp(a, b, axis));
    entries.split_at_mut(mid)
}

/// Builds the BVH4 over `entries` into `out` (appended), the root at node index `base +
/// out.len()` on entry; children always get larger indices than their parent. Returns the
/// root's bounds, or None (nothing appended) when `entries` is empty.
pub fn build(entries: &mut [Entry], base: u32, out: &mut Vec<WideNode>) -> Option<Aabb> {
    if entries.is_empty() {
        return None;
    }
    Some(node(entries, base, out))
}

fn node(entries: &mut [Entry], base: u32, out: &mut Vec<WideNode>) -> Aabb {
    let me = out.len();
    out.push(bytemuck::Zeroable::zeroed());
    let mut groups: Vec<&mut [Entry]> = Vec::with_capacity(4);
    if entries.len() <= 4 {
        entries.sort_unstable_by(|a, b| key_cmp(a, b, 0));
        groups.extend(entries.chunks_mut(1));
    } else {
        let (l, r) = split(entries);
        for half in [l, r] {
            let (a, b) = split(half);
            groups.push(a);
            groups.push(b);
        }
    }
    let mut child = [0u32; 4];
    let mut kind = [0u8; 4];
    let mut clo = [Vec3A::ZERO; 4];
    let mut chi = [Vec3A::ZERO; 4];
    let mut bounds = Aabb::EMPTY;
    for (c, g) in groups.into_iter().enumerate() {
        let b = if g.len() == 1 {
            child[c] = g[0].child;
            kind[c] = g[0].kind;
            box_of(g)
        } else {
            child[c] = base + out.len() as u32;
            kind[c] = CHILD_INTERNAL;
            node(g, base, out)
        };
        clo[c] = Vec3A::from(b.lo);
        chi[c] = Vec3A::from(b.hi);
        bounds.grow(&b.lo, &b.hi);
    }
    let cnt = kind.iter().filter(|&&k| k != 0).count();
    for c in cnt..4 {
        clo[c] = Vec3A::from(bounds.lo);
        chi[c] = Vec3A::from(bounds.lo);
    }
    out[me] = quantize_node(&bounds, &clo, &chi, cnt, &child, &kind);
    bounds
}

/// Why a partition tree cannot be refitted and must be rebuilt.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RefitRefused {
    /// The stored nodes do not form a tree of this region (a corrupted or foreign blob).
    Malformed,
}

/// The nodes a refit rewrote (node index, new node) and the new root bounds.
pub struct Refit {
    pub nodes: Vec<(u32, WideNode)>,
    pub bounds: Aabb,
}

/// One changed leaf: its slot and, when it was in the tree, the box it had there.
#[derive(Clone, Copy, Debug)]
pub struct Changed {
    pub slot: u32,
    pub previous: Option<Aabb>,
}

/// Refits the tree in `region` (its root at node index `base`, nodes in pre-order so children
/// follow their parent) after the leaves in `changed` (sorted by slot) moved: only the nodes on
/// paths from those leaves to the root are rewritten. The paths are found by descending along
/// child boxes that contain a leaf's previous box (a node's child box always contains the
/// current boxes of the leaves below it), or, when that misses a leaf (its BLAS changed
/// bounds meanwhile), by scanning every node. A rewritten node takes its leaf children's boxes
/// from `leaf_box` (exact, so siblings never drift) and an untouched internal child's box as
/// the union of that child's own decoded child boxes (stable while the child is untouched, so
/// slack does not accumulate across refits). Never panics on any bytes.
pub fn refit(region: &[WideNode], base: u32, changed: &[Changed], leaf_box: &mut dyn FnMut(u32) -> Aabb) -> Result<Refit, RefitRefused> {
    if region.is_empty() {
        return Err(RefitRefused::Malformed);
    }
    let dirty = match search(region, base, changed) {
        Some(d) => d,
        None => scan(region, base, changed)?,
    };
    let local = |child: u32| child.checked_sub(base).map(|k| k as usize).filter(|&k| k < region.len());
    let mut boxes = vec![Aabb::EMPTY; dirty.len()];
    let mut nodes = Vec::with_capacity(dirty.len());
    for (pos, &k) in dirty.iter().enumerate().rev() {
        let node = &region[k];
        let cnt = (node.child_count as usize).min(4);
        let mut clo = [Vec3A::ZERO; 4];
        let mut chi = [Vec3A::ZERO; 4];
        let mut bounds = Aabb::EMPTY;
        for c in 0..cnt {
            let b = if node.kind[c] == CHILD_INTERNAL {
                let j = local(node.child[c]).filter(|&j| j > k).ok_or(RefitRefused::Malformed)?;
                match dirty.binary_search(&j) {
                    Ok(q) => boxes[q],
                    Err(_) => decoded_union(&region[j]),
                }
            } else {
                leaf_box(node.child[c])
            };
            clo[c] = Vec3A::from(b.lo);
            chi[c] = Vec3A::from(b.hi);
            bounds.grow(&b.lo, &b.hi);
        }
        for c in cnt..4 {
            clo[c] = Vec3A::from(bounds.lo);
            chi[c] = Vec3A::from(bounds.lo);
        }
        boxes[pos] = bounds;
        nodes.push((base + k as u32, quantize_node(&bounds, &clo, &chi, cnt, &node.child, &node.kind)));
    }
    let bounds = if dirty.first() == Some(&0) { boxes[0] } else { decoded_union(&region[0]) };
    nodes.reverse();
    Ok(Refit { nodes, bounds })
}

fn contains(outer: &[f32; 6], inner: &Aabb) -> bool {
    (0..3).all(|a| outer[a] <= inner.lo[a] && inner.hi[a] <= outer[a + 3])
}

/// The nodes (local indices, sorted) on the paths from the root to every changed leaf that was
/// in the tree, found by descending along child boxes containing its previous box; None when a
/// leaf is not found so.
fn search(region: &[WideNode], base: u32, changed: &[Changed]) -> Option<Vec<usize>> {
    let mut dirty = Vec::new();
    for ch in changed {
        let Some(b) = ch.previous else { continue };
        if !descend(region, base, 0, ch.slot, &b, &mut dirty) {
            return None;
        }
    }
    dirty.sort_unstable();
    dirty.dedup();
    Some(dirty)
}

/// Whether `slot` lies below node k along boxes containing `b`; the path is appended to `dirty`.
fn descend(region: &[WideNode], base: u32, k: usize, slot: u32, b: &Aabb, dirty: &mut Vec<usize>) -> bool {
    let node = &region[k];
    for c in 0..(node.child_count as usize).min(4) {
        let hit = if node.kind[c] == CHILD_INTERNAL {
            // Children follow their parent: the descent ends on any bytes.
            let j = node.child[c].checked_sub(base).map(|j| j as usize).filter(|&j| j > k && j < region.len());
            j.is_some_and(|j| contains(&node.child_box(c), b) && descend(region, base, j, slot, b, dirty))
        } else {
            node.kind[c] != 0 && node.child[c] == slot
        };
        if hit {
            dirty.push(k);
            return true;
        }
    }
    false
}

/// The nodes (local indices, sorted) on the paths from the root to every changed leaf, by
/// scanning every node for the leaves and walking parent links up.
fn scan(region: &[WideNode], base: u32, changed: &[Changed]) -> Result<Vec<usize>, RefitRefused> {
    let n = region.len();
    let local = |child: u32| child.checked_sub(base).map(|k| k as usize).filter(|&k| k < n);
    let mut parent = vec![usize::MAX; n];
    let mut dirty = vec![false; n];
    for (k, node) in region.iter().enumerate() {
        for c in 0..(node.child_count as usize).min(4) {
            if node.kind[c] == CHILD_INTERNAL {
                // Children always follow their parent, and each node has one parent.
                let j = local(node.child[c]).filter(|&j| j > k && parent[j] == usize::MAX).ok_or(RefitRefused::Malformed)?;
                parent[j] = k;
            } else if node.kind[c] != 0 && changed.binary_search_by_key(&node.child[c], |ch| ch.slot).is_ok() {
                dirty[k] = true;
            }
        }
    }
    // Parents precede children: one backward pass marks every ancestor of a dirty node.
    for k in (1..n).rev() {
        if dirty[k] && parent[k] != usize::MAX {
            dirty[parent[k]] = true;
        }
    }
    Ok((0..n).filter(|&k| dirty[k]).collect())
}

/// The union of a node's decoded child boxes: a box holding everything below it.
fn decoded_union(node: &WideNode) -> Aabb {
    let mut b = Aabb::EMPTY;
    for c in 0..(node.child_count as usize).min(4) {
        let x = node.child_box(c);
        b.grow(&[x[0], x[1], x[2]], &[x[3], x[4], x[5]]);
    }
    b
}

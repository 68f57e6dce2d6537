//! The BVH4 pieces of the cluster formats: the small tree each CLAS stores over its own
//! triangles (built when the CLAS is built or instantiated), and the top tree a cluster BLAS
//! builds over its CLASes' boxes, whose bottom children are the CLAS trees' roots.
//!
//! A CLAS tree has a shape that depends on the triangle count alone (leaves of up to four
//! triangles, nodes filled four-wide from the left), so a CLAS's size is a function of its
//! triangle count and COMPUTE_SIZES stays exact; the Morton order of the centroids decides which
//! triangles share a leaf. The top tree uses recursive median splits of the CLAS box centres.
//! Nodes use the KHR node format (`layout::WideNode`) with local indices: internal children name
//! a node of the CLAS tree, leaves a slot of the CLAS's order table. Must not touch: the blob sections (format.rs) or the gathering of a BLAS (blas.rs).
use crate::accel::encode::quantize::quantize_node;
use crate::accel::geometry::{triangle_bounds, Aabb};
use crate::accel::layout::{WideNode, CHILD_INTERNAL};
use glam::{Vec3, Vec3A};

/// Triangles per leaf of a CLAS tree.
pub const LEAF: u32 = 4;

/// Leaves per child of a node over `leaves` leaves: the largest power of four below it, so the
/// first children are full subtrees.
fn child_capacity(leaves: u32) -> u32 {
    let mut cap = 1;
    while cap * 4 < leaves {
        cap *= 4;
    }
    cap
}

/// The leaf counts of a node's children (a node over `leaves` > 1 leaves, or the root).
fn children_of(leaves: u32) -> impl Iterator<Item = u32> {
    let cap = child_capacity(leaves);
    (0..leaves.div_ceil(cap)).map(move |k| cap.min(leaves - k * cap))
}

fn nodes_over(leaves: u32) -> u32 {
    1 + children_of(leaves).filter(|&m| m > 1).map(nodes_over).sum::<u32>()
}

/// Nodes of the tree of a CLAS with `triangles` triangles (0 for an empty CLAS).
pub fn local_node_count(triangles: u64) -> u64 {
    if triangles == 0 {
        return 0;
    }
    // Beyond MAX_TRIANGLES no CLAS exists; the linear bound keeps the function total.
    if triangles > 4096 {
        return triangles.div_ceil(12) + 1;
    }
    nodes_over((triangles as u32).div_ceil(LEAF)) as u64
}

/// A bound on the nodes of CLAS trees over `triangles` triangles in `clusters` CLASes, linear
/// in both (what the cluster BLAS size bounds need).
pub fn local_node_bound(clusters: u64, triangles: u64) -> u64 {
    triangles.div_ceil(12).saturating_add(clusters.saturating_mul(2))
}

/// A triangle's box for the tree: NaN coordinates never hit, so such a triangle adds nothing;
/// infinities are clamped to the largest finite values (as the KHR builder does).
fn tri_box(t: &[f32; 9]) -> Option<Aabb> {
    // A finite sum means every coordinate is finite (the common case, min/max exact).
    if t.iter().sum::<f32>().is_finite() {
        let lo = std::array::from_fn(|a| t[a].min(t[a + 3]).min(t[a + 6]));
        let hi = std::array::from_fn(|a| t[a].max(t[a + 3]).max(t[a + 6]));
        return Some(Aabb { lo, hi });
    }
    if t.iter().any(|x| x.is_nan()) {
        return None;
    }
    let v = [Vec3::new(t[0], t[1], t[2]), Vec3::new(t[3], t[4], t[5]), Vec3::new(t[6], t[7], t[8])];
    let (lo, hi) = triangle_bounds(&v);
    Some(Aabb { lo, hi })
}

/// A box that traversal can quantise: an empty one (only NaN triangles) becomes the origin.
fn finite_box(b: Aabb) -> Aabb {
    if b.lo[0] > b.hi[0] {
        Aabb { lo: [0.0; 3], hi: [0.0; 3] }
    } else {
        b
    }
}

fn centroid_of(b: &Option<Aabb>) -> [f32; 3] {
    b.map_or([0.0; 3], |b| [0, 1, 2].map(|a| b.lo[a] * 0.5 + b.hi[a] * 0.5))
}

/// Reorders `items` so the first `at` are those with the smallest centroid along the axis
/// where the centroids spread most (ties by item, so the result is a function of the input).
fn split_at_median(items: &mut [u32], centroids: &[[f32; 3]], at: usize) {
    if at == 0 || at >= items.len() {
        return;
    }
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for &i in items.iter() {
        for a in 0..3 {
            lo[a] = lo[a].min(centroids[i as usize][a]);
            hi[a] = hi[a].max(centroids[i as usize][a]);
        }
    }
    let ext = [0, 1, 2].map(|a| hi[a] - lo[a]);
    let axis = if ext[0] >= ext[1] && ext[0] >= ext[2] { 0 } else if ext[1] >= ext[2] { 1 } else { 2 };
    items.select_nth_unstable_by(at, |&x, &y| centroids[x as usize][axis].total_cmp(&centroids[y as usize][axis]).then(x.cmp(&y)));
}

/// Splits `items` into consecutive groups of the given sizes by recursive median splits.
fn partition(items: &mut [u32], centroids: &[[f32; 3]], sizes: &[usize]) {
    if sizes.len() < 2 {
        return;
    }
    let h = sizes.len() / 2;
    let at: usize = sizes[..h].iter().sum();
    split_at_median(items, centroids, at);
    let (a, b) = items.split_at_mut(at);
    partition(a, centroids, &sizes[..h]);
    partition(b, centroids, &sizes[h..]);
}

/// A CLAS's tree: `order[slot]` is the triangle in that slot, leaves are runs of slots.
pub struct LocalTree {
    pub order: Vec<u8>,
    pub nodes: Vec<WideNode>,
    /// Union of the triangles' boxes (the CLAS's bounds; zero for an empty CLAS).
    pub bounds: [f32; 6],
}

struct Local {
    order: Vec<u8>,
    /// Boxes in slot order.
    boxes: Vec<Option<Aabb>>,
    nodes: Vec<WideNode>,
}

impl Local {
    fn slots(&self, first_leaf: u32, leaves: u32) -> std::ops::Range<usize> {
        let n = self.order.len();
        (first_leaf * LEAF) as usize..(((first_leaf + leaves) * LEAF) as usize).min(n)
    }

    /// Emits the node over `leaves` leaves from `first_leaf`; returns its index and box.
    fn node(&mut self, first_leaf: u32, leaves: u32) -> (u32, Aabb) {
        let me = self.nodes.len() as u32;
        self.nodes.push(bytemuck::Zeroable::zeroed());
        let (mut clo, mut chi) = ([Vec3A::ZERO; 4], [Vec3A::ZERO; 4]);
        let (mut child, mut kind) = ([0u32; 4], [0u8; 4]);
        let mut whole = Aabb::EMPTY;
        let (mut f, mut count) = (first_leaf, 0);
        for (c, m) in children_of(leaves).enumerate() {
            let b = if m > 1 {
                let (i, b) = self.node(f, m);
                (child[c], kind[c]) = (i, CHILD_INTERNAL);
                b
            } else {
                let r = self.slots(f, 1);
                (child[c], kind[c]) = (r.start as u32, r.len() as u8);
                finite_box(self.boxes[r].iter().flatten().fold(Aabb::EMPTY, |a, b| a.union(b)))
            };
            (clo[c], chi[c]) = (Vec3A::from_array(b.lo), Vec3A::from_array(b.hi));
            whole = whole.union(&b);
            f += m;
            count = c + 1;
        }
        for c in count..4 {
            (clo[c], chi[c]) = (Vec3A::from_array(whole.lo), Vec3A::from_array(whole.lo));
        }
        self.nodes[me as usize] = quantize_node(&whole, &clo, &chi, count, &child, &kind);
        (me, whole)
    }
}

/// Spreads the low 10 bits of `x` to every third bit.
fn spread(x: u32) -> u32 {
    let mut v = x & 0x3ff;
    v = (v | v << 16) & 0x0300_00ff;
    v = (v | v << 8) & 0x0300_f00f;
    v = (v | v << 4) & 0x030c_30c3;
    (v | v << 2) & 0x0924_9249
}

/// The tree of a CLAS over `tris` (at most 256: slots are bytes). Slots follow the Morton order
/// of the centroids in the cluster's centroid box (ties by triangle index), cut into the fixed
/// shape: one sort per cluster, the cost instantiation pays for a BLAS that need not sort.
pub fn build_local(tris: &[[f32; 9]]) -> LocalTree {
    let boxes: Vec<Option<Aabb>> = tris.iter().map(tri_box).collect();
    let centroids: Vec<[f32; 3]> = boxes.iter().map(centroid_of).collect();
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for c in &centroids {
        for a in 0..3 {
            (lo[a], hi[a]) = (lo[a].min(c[a]), hi[a].max(c[a]));
        }
    }
    let scale: [f32; 3] = std::array::from_fn(|a| if hi[a] > lo[a] { 1023.0 / (hi[a] - lo[a]) } else { 0.0 });
    let cell = |c: &[f32; 3], a: usize| (((c[a] - lo[a]) * scale[a]).clamp(0.0, 1023.0)) as u32;
    let mut keys: Vec<u64> = centroids.iter().enumerate().map(|(i, c)| ((spread(cell(c, 0)) | spread(cell(c, 1)) << 1 | spread(cell(c, 2)) << 2) as u64) << 8 | i as u64).collect();
    keys.sort_unstable();
    let order: Vec<u8> = keys.iter().map(|&k| k as u8).collect();
    let mut l = Local { boxes: order.iter().map(|&i| boxes[i as usize]).collect(), order, nodes: Vec::with_capacity(local_node_count(tris.len() as u64) as usize) };
    let mut bounds = [0.0; 6];
    if !tris.is_empty() {
        let (_, b) = l.node(0, (tris.len() as u32).div_ceil(LEAF));
        bounds = [b.lo[0], b.lo[1], b.lo[2], b.hi[0], b.hi[1], b.hi[2]];
    }
    LocalTree { order: l.order, nodes: l.nodes, bounds }
}

/// A child of a top-tree node: another top node, or CLAS `k` of the input.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TopChild {
    Node(u32),
    Cluster(u32),
}

/// One top-tree node before quantisation: its children and their boxes.
pub struct TopNode {
    pub children: Vec<(TopChild, Aabb)>,
}

/// The top tree over CLAS boxes (at least two): four-way nodes by recursive median splits of
/// the box centres, in pre-order (children after their parent), root first.
pub fn build_top(boxes: &[Aabb]) -> Vec<TopNode> {
    let centroids: Vec<[f32; 3]> = boxes.iter().map(|b| centroid_of(&Some(*b))).collect();
    let mut items: Vec<u32> = (0..boxes.len() as u32).collect();
    let mut nodes = Vec::with_capacity(boxes.len() / 2 + 1);
    top_node(&mut items, boxes, &centroids, &mut nodes);
    nodes
}

fn top_node(items: &mut [u32], boxes: &[Aabb], centroids: &[[f32; 3]], nodes: &mut Vec<TopNode>) -> (u32, Aabb) {
    let me = nodes.len() as u32;
    nodes.push(TopNode { children: Vec::new() });
    let n = items.len();
    let k = n.min(4);
    let sizes: Vec<usize> = (0..k).map(|c| (c + 1) * n / k - c * n / k).collect();
    partition(items, centroids, &sizes);
    let mut children = Vec::with_capacity(k);
    let mut whole = Aabb::EMPTY;
    let mut at = 0;
    for &s in &sizes {
        let part = &mut items[at..at + s];
        let c = if s == 1 {
            (TopChild::Cluster(part[0]), boxes[part[0] as usize])
        } else {
            let (i, b) = top_node(part, boxes, centroids, nodes);
            (TopChild::Node(i), b)
        };
        whole = whole.union(&c.1);
        children.push(c);
        at += s;
    }
    nodes[me as usize].children = children;
    (me, whole)
}

/// The wide node of a top node, children resolved to global node indices by `index`.
pub fn quantize_top(node: &TopNode, index: impl Fn(TopChild) -> u32) -> WideNode {
    let (mut clo, mut chi) = ([Vec3A::ZERO; 4], [Vec3A::ZERO; 4]);
    let (mut child, kind) = ([0u32; 4], [CHILD_INTERNAL; 4]);
    let whole = node.children.iter().fold(Aabb::EMPTY, |a, c| a.union(&c.1));
    for c in 0..4 {
        match node.children.get(c) {
            Some(&(ch, b)) => {
                (clo[c], chi[c]) = (Vec3A::from_array(b.lo), Vec3A::from_array(b.hi));
                child[c] = index(ch);
            }
            None => (clo[c], chi[c]) = (Vec3A::from_array(whole.lo), Vec3A::from_array(whole.lo)),
        }
    }
    quantize_node(&whole, &clo, &chi, node.children.len(), &child, &kind[..node.children.len()])
}

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
const fn child_capacity(leaves: u32) -> u32 {
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

const fn nodes_over(leaves: u32) -> u32 {
    let cap = child_capacity(leaves);
    let (mut n, mut k) = (1, 0);
    while k * cap < leaves {
        let m = if cap < leaves - k * cap { cap } else { leaves - k * cap };
        if m > 1 {
            n += nodes_over(m);
        }
        k += 1;
    }
    n
}

/// Leaves of the largest tree `NODES` covers (4096 triangles).
const TABLE_LEAVES: usize = 1024;
/// `nodes_over` of every leaf count up to TABLE_LEAVES: sizes are asked for per element.
const NODES: [u16; TABLE_LEAVES + 1] = {
    let mut t = [0u16; TABLE_LEAVES + 1];
    let mut l = 1;
    while l <= TABLE_LEAVES {
        t[l] = nodes_over(l as u32) as u16;
        l += 1;
    }
    t
};

/// Nodes of the tree of a CLAS with `triangles` triangles (0 for an empty CLAS).
pub fn local_node_count(triangles: u64) -> u64 {
    if triangles == 0 {
        return 0;
    }
    // Beyond MAX_TRIANGLES no CLAS exists; the linear bound keeps the function total.
    if triangles > 4096 {
        return triangles.div_ceil(12) + 1;
    }
    NODES[triangles.div_ceil(LEAF as u64) as usize] as u64
}

/// A bound on the nodes of CLAS trees over `triangles` triangles in `clusters` CLASes, linear
/// in both (what the cluster BLAS size bounds needed before it referenced its CLASes).
#[cfg(test)]
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
#[cfg(test)]
pub struct LocalTree {
    pub order: Vec<u8>,
    pub nodes: Vec<WideNode>,
    /// Union of the triangles' boxes (the CLAS's bounds; zero for an empty CLAS).
    pub bounds: [f32; 6],
}

/// A box as two SIMD corners; the empty box (+inf, -inf) is what a NaN triangle adds.
#[derive(Clone, Copy)]
struct Bx {
    lo: Vec3A,
    hi: Vec3A,
}
const EMPTY: Bx = Bx { lo: Vec3A::INFINITY, hi: Vec3A::NEG_INFINITY };

impl Bx {
    fn union(self, o: Bx) -> Bx {
        Bx { lo: self.lo.min(o.lo), hi: self.hi.max(o.hi) }
    }
    fn aabb(self) -> Aabb {
        Aabb { lo: self.lo.to_array(), hi: self.hi.to_array() }
    }
}

/// A triangle's box and centroid (`tri_box`; the centroid of a NaN triangle is the origin).
#[inline(always)]
fn tri_bx(t: &[f32; 9]) -> (Bx, Vec3A) {
    let (a, b, c) = (Vec3A::new(t[0], t[1], t[2]), Vec3A::new(t[3], t[4], t[5]), Vec3A::new(t[6], t[7], t[8]));
    // Every coordinate finite (the common case): the SIMD min and max are exact.
    if (a + b + c).is_finite() {
        let (lo, hi) = (a.min(b).min(c), a.max(b).max(c));
        return (Bx { lo, hi }, lo * 0.5 + hi * 0.5);
    }
    match tri_box(t) {
        Some(x) => {
            let bx = Bx { lo: Vec3A::from_array(x.lo), hi: Vec3A::from_array(x.hi) };
            (bx, bx.lo * 0.5 + bx.hi * 0.5)
        }
        None => (EMPTY, Vec3A::ZERO),
    }
}

/// Where a CLAS tree is built: the triangle boxes in slot order and the node bytes it writes
/// in pre-order.
struct Local<'a> {
    boxes: &'a [Bx],
    nodes: &'a mut [u8],
    emitted: usize,
}

/// A thread's working arrays for CLAS trees, reused: a command builds thousands of trees.
#[derive(Default)]
struct Scratch {
    boxes: Vec<Bx>,
    slot_boxes: Vec<Bx>,
    centroids: Vec<Vec3A>,
    keys: Vec<u32>,
}


thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
}

/// Runs `f` with this thread's `T` (a fresh one if it is in use).
pub(super) fn with_scratch<T: Default, R>(key: &'static std::thread::LocalKey<std::cell::RefCell<T>>, f: impl FnOnce(&mut T) -> R) -> R {
    key.with(|c| match c.try_borrow_mut() {
        Ok(mut s) => f(&mut s),
        Err(_) => f(&mut T::default()),
    })
}

impl Local<'_> {
    /// Emits the node over `leaves` leaves from `first_leaf`; returns its index and box.
    fn node(&mut self, first_leaf: u32, leaves: u32) -> (u32, Bx) {
        let me = self.emitted as u32;
        self.emitted += 1;
        let (mut clo, mut chi) = ([Vec3A::ZERO; 4], [Vec3A::ZERO; 4]);
        let (mut child, mut kind) = ([0u32; 4], [0u8; 4]);
        let mut whole = EMPTY;
        let (mut f, mut count) = (first_leaf, 0);
        for (c, m) in children_of(leaves).enumerate() {
            let b = if m > 1 {
                let (i, b) = self.node(f, m);
                (child[c], kind[c]) = (i, CHILD_INTERNAL);
                b
            } else {
                let start = (f * LEAF) as usize;
                let r = &self.boxes[start..(start + LEAF as usize).min(self.boxes.len())];
                (child[c], kind[c]) = (start as u32, r.len() as u8);
                let b = r.iter().fold(EMPTY, |a, b| a.union(*b));
                // An empty leaf (only NaN triangles) gets the origin: traversal quantises it.
                if b.lo.x > b.hi.x {
                    Bx { lo: Vec3A::ZERO, hi: Vec3A::ZERO }
                } else {
                    b
                }
            };
            (clo[c], chi[c]) = (b.lo, b.hi);
            whole = whole.union(b);
            f += m;
            count = c + 1;
        }
        for c in count..4 {
            (clo[c], chi[c]) = (whole.lo, whole.lo);
        }
        let w = quantize_node(&whole.aabb(), &clo, &chi, count, &child, &kind);
        self.nodes[me as usize * NODE_BYTES..][..NODE_BYTES].copy_from_slice(bytemuck::bytes_of(&w));
        (me, whole)
    }
}

const NODE_BYTES: usize = std::mem::size_of::<WideNode>();
/// Slots a CLAS tree has room for (slots are bytes).
const MAX_SLOTS: usize = 256;

/// Spreads the low 10 bits of `x` to every third bit.
const fn spread_bits(x: u32) -> u32 {
    let mut v = x & 0x3ff;
    v = (v | v << 16) & 0x0300_00ff;
    v = (v | v << 8) & 0x0300_f00f;
    v = (v | v << 4) & 0x030c_30c3;
    (v | v << 2) & 0x0924_9249
}

/// `spread_bits` of every 8-bit value: three lookups per Morton key.
const SPREAD: [u32; 256] = {
    let mut t = [0u32; 256];
    let mut i = 0;
    while i < 256 {
        t[i] = spread_bits(i as u32);
        i += 1;
    }
    t
};

fn spread(x: u32) -> u32 {
    SPREAD[(x & 0xff) as usize]
}

/// The tree of a CLAS over `tris` (at most 256: slots are bytes), as `write_local` makes it.
#[cfg(test)]
pub fn build_local(tris: &[[f32; 9]]) -> LocalTree {
    let mut order = vec![0u8; tris.len()];
    let mut bytes = vec![0u8; local_node_count(tris.len() as u64) as usize * NODE_BYTES];
    let bounds = write_local(tris, &mut order, &mut bytes);
    LocalTree { order, nodes: bytes.chunks_exact(NODE_BYTES).map(bytemuck::pod_read_unaligned).collect(), bounds }
}

/// Writes the tree of a CLAS over `tris` (at most 256) into `order` (one byte per triangle)
/// and `nodes` (`local_node_count` nodes); returns its bounds. Slots follow the Morton order of
/// the centroids in the cluster's centroid box (ties by triangle index), cut into the fixed
/// shape: one sort per cluster, the cost instantiation pays for a BLAS that need not sort.
pub fn write_local(tris: &[[f32; 9]], order: &mut [u8], nodes: &mut [u8]) -> [f32; 6] {
    with_scratch(&SCRATCH, |s| write_local_with(tris, order, nodes, s))
}

fn write_local_with(tris: &[[f32; 9]], order: &mut [u8], nodes: &mut [u8], s: &mut Scratch) -> [f32; 6] {
    let tris = &tris[..tris.len().min(MAX_SLOTS)];
    if tris.is_empty() {
        return [0.0; 6];
    }
    s.boxes.clear();
    s.centroids.clear();
    let (mut lo, mut hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    for t in tris {
        let (b, c) = tri_bx(t);
        (lo, hi) = (lo.min(c), hi.max(c));
        s.boxes.push(b);
        s.centroids.push(c);
    }
    // 8 bits an axis: 256 cells a side for at most 256 triangles.
    let ext = hi - lo;
    let scale = Vec3A::select(hi.cmpgt(lo), Vec3A::splat(255.0) / ext, Vec3A::ZERO);
    s.keys.clear();
    s.keys.extend(s.centroids.iter().enumerate().map(|(i, &c)| {
        let q = ((c - lo) * scale).max(Vec3A::ZERO).min(Vec3A::splat(255.0));
        (spread(q.x as u32) | spread(q.y as u32) << 1 | spread(q.z as u32) << 2) << 8 | i as u32
    }));
    // Keys are distinct (the index is in the low byte), so any sort gives the same order.
    s.keys.sort_unstable();
    s.slot_boxes.clear();
    for (o, &k) in order.iter_mut().zip(&s.keys) {
        *o = k as u8;
        s.slot_boxes.push(s.boxes[k as u8 as usize]);
    }
    let mut l = Local { boxes: &s.slot_boxes, nodes, emitted: 0 };
    let (_, b) = l.node(0, (tris.len() as u32).div_ceil(LEAF));
    [b.lo.x, b.lo.y, b.lo.z, b.hi.x, b.hi.y, b.hi.z]
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

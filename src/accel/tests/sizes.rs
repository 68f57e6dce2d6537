//! The size query's bounds (docs/ACCEL_API.md, "Sizes"): the node-count bound against a brute
//! force over every binary tree shape the builder could make, the collapse of adversarial
//! trees above and below the emission cut, and real builds of hostile inputs in every tier and
//! flag combination into exactly the queried destination and scratch.
use super::*;
use crate::accel::layout::{max_nodes, max_nodes_for, max_nodes_with_leaves, parse, pairs_leaves, CHILD_INTERNAL};
use crate::accel::tree::{wide_children, BinNode};

/// A binary tree shape: a leaf (of `lay_out`'s primitives per leaf), or a node over two subtrees.
#[derive(Clone)]
enum Shape {
    Leaf,
    Node(Box<Shape>, Box<Shape>),
}
impl Shape {
    fn leaves(&self) -> u32 {
        match self {
            Shape::Leaf => 1,
            Shape::Node(l, r) => l.leaves() + r.leaves(),
        }
    }
}

/// Every shape with `n` leaves (Catalan many).
fn shapes(n: u32) -> Vec<Shape> {
    if n == 1 {
        return vec![Shape::Leaf];
    }
    let mut out = Vec::new();
    for k in 1..n {
        for l in shapes(k) {
            for r in shapes(n - k) {
                out.push(Shape::Node(Box::new(l.clone()), Box::new(r.clone())));
            }
        }
    }
    out
}

/// Lays `shape` out in the builder's slot scheme (a subtree over k primitives at slot r owns
/// r..r+2k-1, left child at r+1, right at r+2·left) with a box of random size per node: the
/// collapse opens the child of largest area, so random areas reach the opening orders.
/// With `per_leaf` primitives per leaf the counts (which decide the emission cut) are those of
/// trees whose leaves hold that many.
fn lay_out(shape: &Shape, nodes: &mut [BinNode], slot: usize, start: u32, area: &mut impl FnMut() -> f32, per_leaf: u32) {
    let s = area();
    let count = shape.leaves() * per_leaf;
    let left_count = match shape {
        Shape::Leaf => 0,
        Shape::Node(l, _) => l.leaves() * per_leaf,
    };
    nodes[slot] = BinNode { lo: [0.0; 3], start, hi: [s, s, s], count, left_count, wide_nodes: 0 };
    if let Shape::Node(l, r) = shape {
        lay_out(l, nodes, slot + 1, start, area, per_leaf);
        lay_out(r, nodes, slot + 2 * left_count as usize, start + left_count, area, per_leaf);
    }
}

/// Wide nodes the encoder emits for the binary tree at `nodes[i]`: one per wide node, the
/// internal children made by `wide_children` each heading its own (a root leaf takes one).
fn wide_count(nodes: &[BinNode], i: usize) -> u64 {
    let (ch, n, _) = wide_children(nodes, i);
    1 + ch[..n].iter().filter(|&&c| c != i && nodes[c].left_count != 0).map(|&c| wide_count(nodes, c)).sum::<u64>()
}

fn tree_of(shape: &Shape, seed: u64) -> Vec<BinNode> {
    tree_with_leaves_of(shape, seed, 1)
}

fn tree_with_leaves_of(shape: &Shape, seed: u64, per_leaf: u32) -> Vec<BinNode> {
    let n = (shape.leaves() * per_leaf) as usize;
    let mut nodes = vec![BinNode { lo: [0.0; 3], start: 0, hi: [0.0; 3], count: 0, left_count: 0, wide_nodes: 0 }; 2 * n - 1];
    let mut f = crate::accel::testing::unit_floats(seed);
    lay_out(shape, &mut nodes, 0, 0, &mut || 0.01 + f(), per_leaf);
    nodes
}

/// Brute force: over every shape of up to 9 leaves and several area orders, the most wide
/// nodes the collapse makes never exceeds `max_nodes`, and reaches it where the worst shape
/// exists (8 leaves: four pairs under one full node, 5 wide nodes).
#[test]
fn node_bound_holds_for_every_tree_shape_and_is_reached() {
    for n in 1..=9u32 {
        let mut worst = 0;
        for (k, shape) in shapes(n).iter().enumerate() {
            for trial in 0..6 {
                let nodes = tree_of(shape, 1 + k as u64 * 7 + trial);
                worst = worst.max(wide_count(&nodes, 0));
            }
        }
        assert!(worst <= max_nodes(n as u64), "{n} leaves: {worst} wide nodes > bound {}", max_nodes(n as u64));
        if n == 8 || n <= 2 {
            assert_eq!(worst, max_nodes(n as u64), "{n} leaves: the bound is reached");
        }
        // Trees that pair their leaves: L leaves hold 2L or 2L + 1 primitives.
        for p in [2 * n as u64, 2 * n as u64 + 1] {
            assert!(worst <= max_nodes_with_leaves(p, p / 2), "{n} leaves of pairs: {worst} > {}", max_nodes_with_leaves(p, p / 2));
        }
    }
}

/// The worst family at any size: full wide nodes over pairs of single-primitive leaves, and
/// above the emission cut (EMIT_CUT) nodes split into two cut roots, which the collapse may
/// not open; also random shapes. None exceeds `max_nodes`.
#[test]
fn node_bound_holds_for_adversarial_trees_across_the_emission_cut() {
    // Pairs under full nodes: ((p, p), (p, p)) recursively, halves of the count above the cut.
    fn adversarial(n: u32) -> Shape {
        match n {
            1 => Shape::Leaf,
            2 => Shape::Node(Box::new(Shape::Leaf), Box::new(Shape::Leaf)),
            _ if n > crate::accel::params::EMIT_CUT || !n.is_multiple_of(8) => Shape::Node(Box::new(adversarial(n / 2)), Box::new(adversarial(n - n / 2))),
            _ => {
                let q = n / 4;
                let half = |a: u32, b: u32| Shape::Node(Box::new(adversarial(a)), Box::new(adversarial(b)));
                Shape::Node(Box::new(half(q, q)), Box::new(half(q, n - 3 * q)))
            }
        }
    }
    fn random_shape(n: u32, next: &mut impl FnMut() -> u64) -> Shape {
        if n == 1 {
            return Shape::Leaf;
        }
        let k = 1 + (next() % (n as u64 - 1)) as u32;
        Shape::Node(Box::new(random_shape(k, next)), Box::new(random_shape(n - k, next)))
    }
    let mut next = crate::accel::testing::xorshift(5);
    for &n in &[8u32, 64, 4096, 4104, 8192, 8200, 3 * 4097, 20_000] {
        for (what, shape) in [("adversarial", adversarial(n)), ("random", random_shape(n, &mut next))] {
            let w = wide_count(&tree_of(&shape, n as u64), 0);
            assert!(w <= max_nodes(n as u64), "{what} tree of {n} leaves: {w} wide nodes > bound {}", max_nodes(n as u64));
            // The same shapes with two primitives per leaf: the cut falls at half the leaves.
            let p = 2 * n as u64;
            let w = wide_count(&tree_with_leaves_of(&shape, n as u64, 2), 0);
            assert!(w <= max_nodes_with_leaves(p, p / 2), "{what} tree of {n} leaves of two: {w} wide nodes > bound {}", max_nodes_with_leaves(p, p / 2));
        }
    }
}

/// Tiny triangles at the points of a coarse lattice, far apart (each its own SAH leaf: the
/// most nodes per primitive a tier makes), in random order.
fn spread_triangles(n: usize, seed: u64) -> Vec<Vec3> {
    let mut f = crate::accel::testing::unit_floats(seed);
    let side = (n as f32).cbrt().ceil() as usize + 1;
    let mut cells: Vec<usize> = (0..side * side * side).collect();
    for i in (1..cells.len()).rev() {
        cells.swap(i, (f() * (i + 1) as f32) as usize % (i + 1));
    }
    let mut v = Vec::with_capacity(3 * n);
    for &c in &cells[..n] {
        let p = Vec3::new((c % side) as f32, (c / side % side) as f32, (c / side / side) as f32) * 1000.0;
        v.extend([p, p + Vec3::new(0.01, 0.0, 0.0), p + Vec3::new(0.0, 0.01, 0.0)]);
    }
    v
}

const FLAG_SETS: [u32; 8] = [
    0,
    BuildFlags::PREFER_FAST_TRACE,
    BuildFlags::PREFER_FAST_BUILD,
    BuildFlags::PREFER_FAST_TRACE | BuildFlags::PREFER_FAST_BUILD,
    BuildFlags::ALLOW_UPDATE,
    BuildFlags::ALLOW_UPDATE | BuildFlags::ALLOW_COMPACTION | BuildFlags::PREFER_FAST_TRACE,
    BuildFlags::ALLOW_DATA_ACCESS | BuildFlags::PREFER_FAST_BUILD | BuildFlags::LOW_MEMORY,
    BuildFlags::ALLOW_UPDATE | BuildFlags::ALLOW_DATA_ACCESS | BuildFlags::ALLOW_COMPACTION,
];

/// Builds `geoms` with every flag set into exactly the queried sizes (`try_build`: dst and
/// scratch of the query, scratch misaligned); each must succeed, fit, and stay within the
/// node bound for the primitives it stored.
fn fits_in_every_tier(what: &str, ty: AsType, geoms: &[Geometry], view: &dyn DeviceView) {
    for flags in FLAG_SETS {
        let (r, dst) = try_build(ty, flags, geoms, view);
        let r = r.unwrap_or_else(|e| panic!("{what}, flags {flags:#x}: {e:?}"));
        assert!(r.used_size <= dst.len() as u64);
        assert!(dst[r.used_size as usize..].iter().all(|&b| b == 0xAA), "{what}, flags {flags:#x}: written beyond the used size");
        let bound = max_nodes_for(ty, BuildFlags(flags), r.primitive_count as u64);
        assert!(r.node_count as u64 <= bound, "{what}, flags {flags:#x}: {} nodes for {} primitives (bound {bound})", r.node_count, r.primitive_count);
        validate(&dst).unwrap_or_else(|e| panic!("{what}, flags {flags:#x}: {e}"));
        if pairs_leaves(ty, BuildFlags(flags)) && r.primitive_count >= 2 {
            assert!(smallest_leaf(&dst) >= 2, "{what}, flags {flags:#x}: a leaf of one primitive");
            assert!(r.leaf_count as u64 <= r.primitive_count as u64 / 2, "{what}, flags {flags:#x}: {r:?}");
        }
    }
}

/// Primitives of the smallest leaf of a structure (read from its wide nodes).
fn smallest_leaf(bytes: &[u8]) -> u32 {
    let p = parse(bytes).expect("a structure");
    let mut least = u32::MAX;
    for i in 0..p.raw.node_count {
        let nd = p.node(i).expect("node");
        for &k in &nd.kind[..nd.child_count as usize] {
            if k != 0 && k != CHILD_INTERNAL {
                least = least.min(k as u32);
            }
        }
    }
    least
}

/// Groups of three tiny triangles far apart, in each one far from the other two (without
/// the pairing rule the fast-build tier splits such a group into one and two), in random
/// group order.
fn outlier_triples(groups: usize, seed: u64) -> Vec<Vec3> {
    let base = spread_triangles(groups, seed);
    base.chunks_exact(3).flat_map(|t| {
        let far = Vec3::new(0.0, 0.0, 300.0);
        let near = Vec3::new(0.02, 0.0, 0.0);
        [t[0], t[1], t[2], t[0] + near, t[1] + near, t[2] + near, t[0] + far, t[1] + far, t[2] + far]
    }).collect()
}

#[test]
fn hostile_triangle_inputs_fit_the_queried_size_in_every_tier() {
    let one_point = vec![Vec3::splat(3.0); 3 * 3000];
    let spread = spread_triangles(5000, 1);
    let mut rng = Rng::new(9);
    let soup = random_soup(&mut rng, 4000, 100.0, 20.0);
    // Degenerate triangles (lines and points) among good ones: dropped without ALLOW_UPDATE.
    let mut degenerate = spread_triangles(2000, 2);
    for t in degenerate.chunks_exact_mut(3).step_by(2) {
        t[1] = t[0];
        t[2] = t[0] + Vec3::X;
    }
    // One triangle repeated: identical boxes everywhere (no split can separate them).
    let tri = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let identical: Vec<Vec3> = (0..20_000).flat_map(|_| tri).collect();
    // Clustered tiers: at least CLUSTER_MIN primitives of neighbours that pair tightly.
    let strip: Vec<Vec3> = spread_triangles(10_000, 3).chunks_exact(3).flat_map(|t| [t[0], t[1], t[2], t[0], t[2], t[1]]).collect();
    let triples = outlier_triples(3000, 8);
    // Clustered: neighbours that pair tightly, among lone triangles far from them.
    let mixed: Vec<Vec3> = spread_triangles(12_000, 10).chunks_exact(3).enumerate().flat_map(|(i, t)| if i % 3 == 0 { vec![t[0], t[1], t[2]] } else { vec![t[0], t[1], t[2], t[0], t[2], t[1]] }).collect();
    for (what, v) in [("one point", &one_point), ("spread", &spread), ("soup", &soup), ("degenerate", &degenerate), ("identical", &identical), ("strip", &strip), ("outlier triples", &triples), ("mixed clusters", &mixed)] {
        let vb = f32_bytes(v);
        let n = (v.len() / 3) as u32;
        fits_in_every_tier(what, AsType::BottomLevel, &[tri_geom(&vb, 3 * n, &[], n, 1)], &NoDevice);
    }
    let vb = f32_bytes(&tri);
    fits_in_every_tier("one primitive", AsType::BottomLevel, &[tri_geom(&vb, 3, &[], 1, 0)], &NoDevice);
}

#[test]
fn many_geometries_aabbs_and_mixed_opaque_flags_fit_the_queried_size() {
    // 300 geometries of one to three spread triangles, opaque and not in turn.
    let spread = spread_triangles(900, 4);
    let vbs: Vec<Vec<u8>> = spread.chunks(9).map(f32_bytes).collect();
    let geoms: Vec<Geometry> = vbs.iter().enumerate().map(|(i, b)| tri_geom(b, (b.len() / 12) as u32, &[], 1 + (i % 3) as u32, (i % 2) as u32)).collect();
    fits_in_every_tier("300 geometries", AsType::BottomLevel, &geoms, &NoDevice);
    // AABBs: spread points as boxes, with some min > max (inactive) and all in one point.
    let boxes: Vec<u8> = spread.chunks_exact(3).enumerate().flat_map(|(i, t)| {
        let (lo, hi) = if i % 7 == 0 { (t[0] + Vec3::ONE, t[0]) } else { (t[0], t[0] + Vec3::splat(0.5)) };
        [lo.to_array(), hi.to_array()].concat()
    }).flat_map(f32::to_le_bytes).collect();
    let n = (boxes.len() / 24) as u32;
    let aabbs = [Geometry { flags: GeometryFlags(0), primitive_count: n, data: GeometryData::Aabbs { data: &boxes, stride: 24 } }];
    fits_in_every_tier("aabbs", AsType::BottomLevel, &aabbs, &NoDevice);
    let same: Vec<u8> = (0..2000).flat_map(|_| [1.0f32, 1.0, 1.0, 1.0, 1.0, 1.0]).flat_map(f32::to_le_bytes).collect();
    let aabbs = [Geometry { flags: GeometryFlags(1), primitive_count: 2000, data: GeometryData::Aabbs { data: &same, stride: 24 } }];
    fits_in_every_tier("aabbs in one point", AsType::BottomLevel, &aabbs, &NoDevice);
}

#[test]
fn instance_trees_fit_the_queried_size() {
    let vb = f32_bytes(&[Vec3::ZERO, Vec3::X, Vec3::Y]);
    let blas = build_ok(AsType::BottomLevel, 0, &[tri_geom(&vb, 3, &[], 1, 0)], &NoDevice);
    let mut view = MapView::new();
    view.insert(0x1000, blas);
    let spread = spread_triangles(3000, 5);
    // Instances far apart, some inactive (reference 0), some in one point.
    let inst: Vec<u8> = spread.chunks_exact(3).enumerate().flat_map(|(i, t)| {
        let p = if i % 5 == 0 { Vec3::ZERO } else { t[0] };
        instance_bytes(translate(p.x, p.y, p.z), i as u32, 0xff, 0, (i % 4) as u8, if i % 11 == 0 { 0 } else { 0x1000 })
    }).collect();
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: 3000, data: GeometryData::Instances { array_of_pointers: false, data: &inst } }];
    fits_in_every_tier("instances", AsType::TopLevel, &g, &view);
}

/// Large counts: at most 92 B per triangle for every flag set (NVIDIA's query answers 92 for
/// PREFER_FAST_TRACE on the dragon) and at most 68 B (NVIDIA's PREFER_FAST_BUILD answer) for
/// the fast-build tier, linear in the count, and no wrap for the largest counts.
#[test]
fn the_bound_per_triangle_for_large_counts() {
    let shape = GeometryShape::Triangles { format: VertexFormat::R32G32B32Sfloat, index_type: IndexType::U32, max_vertex: 437_644, has_transform: false };
    for flags in FLAG_SETS {
        let dragon = 871_414u64;
        let s = build_sizes(AsType::BottomLevel, BuildFlags(flags), &[shape], &[dragon as u32]);
        let per = s.acceleration_structure_size as f64 / dragon as f64;
        assert!(per <= 92.0, "flags {flags:#x}: {per:.1} B/tri");
        if pairs_leaves(AsType::BottomLevel, BuildFlags(flags)) {
            assert!(per <= 68.0, "flags {flags:#x}: {per:.1} B/tri");
        }
        // At least what any build stores per triangle (data and record) and a third of a
        // node per pair of triangles.
        assert!(per >= 36.0 + 8.0 + 64.0 / 6.0, "flags {flags:#x}: {per:.1} B/tri");
        let big = build_sizes(AsType::BottomLevel, BuildFlags(flags), &[shape; 4], &[u32::MAX; 4]);
        assert!(big.acceleration_structure_size > 4 * u32::MAX as u64 * 54 && big.acceleration_structure_size < u64::MAX / 2);
    }
    let t = build_sizes(AsType::TopLevel, BuildFlags(0), &[GeometryShape::Instances], &[10_000]);
    assert!(t.acceleration_structure_size as f64 / 10_000.0 <= 180.0, "{t:?}");
}

/// Measured against the query: the bound is what a real build of the worst input needs, not
/// far above it (the spread lattice makes single-primitive leaves in the C_T = 1 tiers).
#[test]
fn the_bound_is_near_what_the_worst_inputs_use() {
    let spread = spread_triangles(20_000, 6);
    let vb = f32_bytes(&spread);
    let g = [tri_geom(&vb, 60_000, &[], 20_000, 1)];
    let (r, dst) = try_build(AsType::BottomLevel, BuildFlags::PREFER_FAST_TRACE, &g, &NoDevice);
    let r = r.expect("build");
    // A third of a node per primitive or more: leaves of one primitive, as the bound assumes.
    assert!(r.node_count as u64 * 3 >= r.primitive_count as u64, "{r:?}");
    assert!(r.used_size as f64 >= 0.8 * dst.len() as f64, "{} of {}", r.used_size, dst.len());
    // The fast-build tier pairs the same triangles: about a sixth of a node per primitive.
    let (r, dst) = try_build(AsType::BottomLevel, BuildFlags::PREFER_FAST_BUILD, &g, &NoDevice);
    let r = r.expect("build");
    assert!(r.node_count as u64 * 6 >= r.primitive_count as u64, "{r:?}");
    assert!(r.used_size as f64 >= 0.85 * dst.len() as f64, "{} of {}", r.used_size, dst.len());
}

#[test]
fn update_scratch_of_a_blas_is_what_refit_uses() {
    let spread = spread_triangles(3000, 7);
    let vb = f32_bytes(&spread);
    let g = [tri_geom(&vb, 9000, &[], 3000, 1)];
    let flags = BuildFlags(BuildFlags::ALLOW_UPDATE);
    let sz = build_sizes(AsType::BottomLevel, flags, &[shape_of(&g[0])], &[3000]);
    assert!(sz.update_scratch_size < 1024, "{sz:?}");
    let mut dst = build_ok(AsType::BottomLevel, flags.0, &g, &NoDevice);
    let before = dst.clone();
    let mut scratch = vec![0x5Au8; sz.update_scratch_size as usize];
    let r = update(&BuildDesc { ty: AsType::BottomLevel, flags, geometries: &g }, &NoDevice, None, &mut dst, &mut scratch).expect("update");
    assert_eq!(r.primitive_count, 3000);
    // Same input: the refit gives the same structure back.
    assert_eq!(dst[..r.used_size as usize], before[..r.used_size as usize]);
    let mut short = vec![0u8; sz.update_scratch_size as usize - 1];
    assert!(matches!(update(&BuildDesc { ty: AsType::BottomLevel, flags, geometries: &g }, &NoDevice, None, &mut dst, &mut short), Err(BuildError::ScratchTooSmall { .. })));
}

//! Metrics (SAH, counts, sizes) and structural validation of a built structure.
use super::geometry::{sanitize, triangle_bounds, Aabb};
use super::layout::{self, Parsed, CHILD_INTERNAL};
use glam::Vec3;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Metrics {
    /// Binary SAH (PEERS.md formula, C_T = C_I = 1) of the tree before collapse, from the header.
    pub sah_cost: f32,
    /// Same formula over the BVH4 with decoded (quantised) boxes.
    pub wide_sah_cost: f32,
    pub node_count: u32,
    pub leaf_count: u32,
    pub bytes_per_primitive: f32,
    pub max_depth: u32,
}

fn to_aabb(b: [f32; 6]) -> Aabb {
    Aabb { lo: [b[0], b[1], b[2]], hi: [b[3], b[4], b[5]] }
}

fn node_union(n: &layout::WideNode) -> Aabb {
    let mut b = Aabb::EMPTY;
    for c in 0..(n.child_count as usize).min(4) {
        if n.kind[c] != 0 {
            b = b.union(&to_aabb(n.child_box(c)));
        }
    }
    b
}

pub fn metrics(structure: &[u8]) -> Option<Metrics> {
    let p = layout::parse(structure)?;
    let r = p.raw;
    let root_area = to_aabb(r.bounds).half_area() as f64;
    let mut sum = 0f64;
    let mut max_depth = 0u32;
    let mut stack: Vec<(u32, u32)> = Vec::new();
    if r.node_count > 0 {
        stack.push((0, 1));
    }
    let mut visited = 0u64;
    while let Some((i, d)) = stack.pop() {
        visited += 1;
        if visited > r.node_count as u64 {
            return None; // a cycle: not a tree
        }
        let n = p.node(i)?;
        max_depth = max_depth.max(d);
        sum += node_union(&n).half_area() as f64;
        for c in 0..(n.child_count as usize).min(4) {
            match n.kind[c] {
                0 => {}
                CHILD_INTERNAL => stack.push((n.child[c], d + 1)),
                k => sum += to_aabb(n.child_box(c)).half_area() as f64 * k as f64,
            }
        }
    }
    let wide = if root_area > 0.0 && root_area.is_finite() { (sum / root_area) as f32 } else { 0.0 };
    let prims = r.primitive_count.max(1) as f32;
    Some(Metrics {
        sah_cost: r.sah_cost,
        wide_sah_cost: wide,
        node_count: r.node_count,
        leaf_count: r.leaf_count,
        bytes_per_primitive: r.used_size as f32 / prims,
        max_depth,
    })
}

fn contains(outer: &Aabb, inner: &Aabb) -> bool {
    (0..3).all(|a| outer.lo[a] <= inner.lo[a] && inner.hi[a] <= outer.hi[a])
}

fn prim_box(p: &Parsed, s: u32) -> Option<Aabb> {
    if p.is_tlas() {
        return None; // instance boxes depend on the BLASes (no view here); traversal tests cover them
    }
    let d = p.prim(s)?;
    let g = p.record(s).and_then(|r| p.geometry(r.geometry))?;
    let (lo, hi) = if g.kind == layout::KIND_AABBS {
        sanitize([d[0], d[1], d[2]], [d[3], d[4], d[5]])
    } else {
        triangle_bounds(&[Vec3::new(d[0], d[1], d[2]), Vec3::new(d[3], d[4], d[5]), Vec3::new(d[6], d[7], d[8])])
    };
    Some(Aabb { lo, hi })
}

/// Invariants: everything `check::check` verifies (checksum, counts, records, the preorder
/// tree), then valid header and sections, a tree (each node reached once, children after
/// parents), every stored primitive in exactly one leaf, child boxes inside parents, primitive
/// boxes inside their leaf boxes, records and instance BLAS indices in range.
pub fn validate(structure: &[u8]) -> Result<(), String> {
    super::check::check(structure).map_err(|reason| format!("check: {reason}"))?;
    let p = layout::parse(structure).ok_or("header invalid")?;
    let r = p.raw;
    let n = r.primitive_count as usize;
    let mut seen = vec![false; n];
    let mut node_seen = vec![false; r.node_count as usize];
    // Each entry carries the intersection of the decoded boxes on its path: every primitive
    // must lie inside it (decoded boxes of a child need not lie inside the decoded parent box,
    // since each level rounds outward in its own frame; what traversal needs is containment of
    // the primitives in every box on the path).
    let everything = Aabb { lo: [f32::NEG_INFINITY; 3], hi: [f32::INFINITY; 3] };
    let mut stack: Vec<(u32, Aabb)> = Vec::new();
    if r.node_count > 0 {
        stack.push((0, everything));
    } else if n > 0 {
        return Err("primitives but no nodes".into());
    }
    let root = to_aabb(r.bounds);
    let clip = |a: &Aabb, b: &Aabb| {
        let mut c = *a;
        for k in 0..3 {
            c.lo[k] = c.lo[k].max(b.lo[k]);
            c.hi[k] = c.hi[k].min(b.hi[k]);
        }
        c
    };
    while let Some((i, path)) = stack.pop() {
        let node = p.node(i).ok_or(format!("node {i} out of range"))?;
        let slot = node_seen.get_mut(i as usize).ok_or("node index")?;
        if *slot {
            return Err(format!("node {i} reached twice"));
        }
        *slot = true;
        if node.child_count == 0 || node.child_count > 4 {
            return Err(format!("node {i}: child count {}", node.child_count));
        }
        for c in 0..node.child_count as usize {
            let cb = to_aabb(node.child_box(c));
            match node.kind[c] {
                0 => return Err(format!("node {i}: empty slot {c} below child_count")),
                CHILD_INTERNAL => {
                    if node.child[c] <= i {
                        return Err(format!("node {i}: child {} not after parent", node.child[c]));
                    }
                    stack.push((node.child[c], clip(&path, &cb)));
                }
                k => {
                    let leaf_box = clip(&path, &cb);
                    for s in node.child[c]..node.child[c].saturating_add(k as u32) {
                        check_leaf_slot(&p, s, &mut seen, (&leaf_box, &root), i)?;
                    }
                }
            }
        }
    }
    if let Some(s) = seen.iter().position(|x| !x) {
        return Err(format!("primitive slot {s} in no leaf"));
    }
    if let Some(s) = node_seen.iter().position(|x| !x) {
        return Err(format!("node {s} unreachable"));
    }
    Ok(())
}

/// Checks primitive slot `s` of a leaf of node `i`: in no other leaf, its box inside the leaf's
/// path box and the header bounds (`boxes`), its record and (TLAS) instance in range.
fn check_leaf_slot(p: &Parsed, s: u32, seen: &mut [bool], (leaf_box, root): (&Aabb, &Aabb), i: u32) -> Result<(), String> {
    let r = p.raw;
    let e = seen.get_mut(s as usize).ok_or(format!("node {i}: leaf slot {s} out of range"))?;
    if *e {
        return Err(format!("primitive slot {s} in two leaves"));
    }
    *e = true;
    if let Some(pb) = prim_box(p, s) {
        if !contains(leaf_box, &pb) {
            return Err(format!("node {i}: primitive {s} box {pb:?} outside its leaf/ancestor boxes {leaf_box:?}"));
        }
        if !contains(root, &pb) {
            return Err(format!("primitive {s} outside the header bounds"));
        }
    }
    let rec = p.record(s).ok_or("record")?;
    let g = p.geometry(rec.geometry).ok_or(format!("record {s}: geometry {} out of range", rec.geometry))?;
    if rec.primitive >= g.primitive_count {
        return Err(format!("record {s}: primitive {} out of range", rec.primitive));
    }
    if p.is_tlas() {
        let inst = p.instance(s).ok_or("instance")?;
        if inst.blas_index >= r.blas_reference_count {
            return Err(format!("instance {s}: BLAS index {} out of range", inst.blas_index));
        }
    }
    Ok(())
}

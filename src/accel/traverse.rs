//! Traversal per the Vulkan ray traversal rules: BVH4 with conservative boxes, watertight
//! ray/triangle test, instance masks and flags, opacity and culling rules, and a resumable
//! candidate iterator (`RayQuery`) with commit semantics.
//!
//! Facing convention (VK_KHR_acceleration_structure, VkGeometryInstanceFlagBitsKHR and the
//! ray traversal chapter): facing is decided in object space. A triangle is front-facing when
//! its vertices v0, v1, v2 appear clockwise as seen from the ray origin in a left-handed frame,
//! which is, numerically, `dot((v1 - v0) x (v2 - v0), direction) < 0`; the instance flag
//! TRIANGLE_FLIP_FACING (2, formerly FRONT_COUNTERCLOCKWISE) inverts it. Instance transforms do
//! not change facing; geometry transforms (applied at build time) do.
use super::clas::{self, Side};
use super::layout::{self, InstanceRecord, Parsed, CHILD_INTERNAL};
use super::{DeviceView, GeometryFlags};
use glam::{DVec3, Vec3, Vec4};
use setup::{level_of, open_top, opened, resolve_instance_in, BlasMemo, Opened};

mod closest;
mod setup;
#[cfg(test)]
mod tests;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub direction: Vec3,
    pub tmin: f32,
    pub tmax: f32,
}

/// SPIR-V RayFlags values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct RayFlags(pub u32);
impl RayFlags {
    pub const OPAQUE: u32 = 1;
    pub const NO_OPAQUE: u32 = 2;
    pub const TERMINATE_ON_FIRST_HIT: u32 = 4;
    pub const SKIP_CLOSEST_HIT_SHADER: u32 = 8;
    pub const CULL_BACK_FACING_TRIANGLES: u32 = 0x10;
    pub const CULL_FRONT_FACING_TRIANGLES: u32 = 0x20;
    pub const CULL_OPAQUE: u32 = 0x40;
    pub const CULL_NO_OPAQUE: u32 = 0x80;
    pub const SKIP_TRIANGLES: u32 = 0x100;
    pub const SKIP_AABBS: u32 = 0x200;
}

/// VkGeometryInstanceFlagBitsKHR.
pub const INSTANCE_FACING_CULL_DISABLE: u32 = 1;
pub const INSTANCE_FLIP_FACING: u32 = 2;
pub const INSTANCE_FORCE_OPAQUE: u32 = 4;
pub const INSTANCE_FORCE_NO_OPAQUE: u32 = 8;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HitKind {
    Triangle,
    Aabb,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f32,
    pub kind: HitKind,
    /// Weights of v1 and v2 (triangles); zero for AABBs.
    pub barycentrics: [f32; 2],
    /// Triangles: facing after TRIANGLE_FLIP_FACING. AABBs: false.
    pub front_face: bool,
    pub opaque: bool,
    /// InstanceId (index in the TLAS build's instance array).
    pub instance_index: u32,
    pub instance_custom_index: u32,
    pub sbt_record_offset: u32,
    pub geometry_index: u32,
    pub primitive_index: u32,
    pub object_ray_origin: Vec3,
    pub object_ray_direction: Vec3,
    pub object_to_world: [f32; 12],
    pub world_to_object: [f32; 12],
    /// Triangles: the stored vertices v0, v1, v2 (object space, geometry transform applied,
    /// application order), for VK_KHR_ray_tracing_position_fetch. AABBs: zero.
    pub vertices: [Vec3; 3],
    /// The CLAS's cluster ID for a triangle of a cluster BLAS; -1 for any other hit.
    pub cluster_id: i32,
}

/// Pending traversal items at most (a valid BVH4 needs 3 per level of depth).
const MAX_STACK: usize = 1 << 16;

const IDENTITY: [f32; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

fn max_dim(d: Vec3) -> usize {
    let a = d.abs();
    if a.x >= a.y && a.x >= a.z {
        0
    } else if a.y >= a.z {
        1
    } else {
        2
    }
}

/// Per-ray constants of the watertight test (axis permutation and shear), computed once per
/// ray (per level) instead of once per triangle. Same arithmetic as the per-triangle setup.
#[derive(Clone, Copy, Debug)]
struct Shear {
    kx: usize,
    ky: usize,
    kz: usize,
    sx: f32,
    sy: f32,
    sz: f32,
}

fn shear(d: Vec3) -> Shear {
    let kz = max_dim(d);
    let mut kx = (kz + 1) % 3;
    let mut ky = (kx + 1) % 3;
    if d[kz] < 0.0 {
        std::mem::swap(&mut kx, &mut ky);
    }
    let sx = d[kx] / d[kz];
    let sy = d[ky] / d[kz];
    let sz = 1.0 / d[kz];
    Shear { kx, ky, kz, sx, sy, sz }
}

/// Watertight ray/triangle test (Woop, Benthin, Wald 2013) with the double-precision fallback
/// for edge hits. Returns (t, u, v, front) with u, v the weights of v1 and v2, and t within
/// [tmin, tmax] inclusive. `front` is the unflipped Vulkan facing (see the module doc).
pub fn intersect_triangle(ray: &Ray, v0: Vec3, v1: Vec3, v2: Vec3) -> Option<(f32, f32, f32, bool)> {
    let sh = shear(ray.direction);
    intersect_sheared(&sh, ray.origin.to_array(), ray.tmin, ray.tmax, v0.to_array(), v1.to_array(), v2.to_array())
}

#[inline(always)]
fn intersect_sheared(sh: &Shear, o: [f32; 3], tmin: f32, tmax: f32, v0: [f32; 3], v1: [f32; 3], v2: [f32; 3]) -> Option<(f32, f32, f32, bool)> {
    let Shear { kx, ky, kz, sx, sy, sz } = *sh;
    let a = [v0[0] - o[0], v0[1] - o[1], v0[2] - o[2]];
    let b = [v1[0] - o[0], v1[1] - o[1], v1[2] - o[2]];
    let c = [v2[0] - o[0], v2[1] - o[1], v2[2] - o[2]];
    let ax = a[kx] - sx * a[kz];
    let ay = a[ky] - sy * a[kz];
    let bx = b[kx] - sx * b[kz];
    let by = b[ky] - sy * b[kz];
    let cx = c[kx] - sx * c[kz];
    let cy = c[ky] - sy * c[kz];
    let mut u = cx * by - cy * bx;
    let mut v = ax * cy - ay * cx;
    let mut w = bx * ay - by * ax;
    if u == 0.0 || v == 0.0 || w == 0.0 {
        u = (cx as f64 * by as f64 - cy as f64 * bx as f64) as f32;
        v = (ax as f64 * cy as f64 - ay as f64 * cx as f64) as f32;
        w = (bx as f64 * ay as f64 - by as f64 * ax as f64) as f32;
    }
    // NaN in any of u, v, w fails both sign tests below only partially, so reject explicitly.
    if u.is_nan() || v.is_nan() || w.is_nan() {
        return None;
    }
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    // The final combination runs in f64: T / det is then correctly rounded for the common
    // cases (an axis ray hitting the plane z = 5 gives t = 5, not 4.9999995). The sign tests
    // above stay in f32/f64-fallback exactly as the watertight algorithm prescribes.
    let (ud, vd, wd) = (u as f64, v as f64, w as f64);
    let det = ud + vd + wd;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let az = (sz * a[kz]) as f64;
    let bz = (sz * b[kz]) as f64;
    let cz = (sz * c[kz]) as f64;
    let t = ((ud * az + vd * bz + wd * cz) / det) as f32;
    if !(t >= tmin && t <= tmax) {
        return None;
    }
    Some((t, (vd / det) as f32, (wd / det) as f32, det > 0.0))
}

/// Slab test of all four child boxes of a node at once (one `Vec4` lane each): entry distances
/// clamped to tmin, and a hit mask. The far distance is widened by a few ulps (Ize 2013) so
/// rounding never loses a box the ray touches. A NaN slab distance (0 * inf: a zero direction
/// component with the origin exactly on a slab plane) means the origin lies in the closed slab
/// and this axis constrains nothing. (f32::min alone would drop the NaN and return the
/// infinite other bound: a false miss.)
#[inline(always)]
fn ray_box4(n: &layout::WideNode, org: [f32; 3], inv: [f32; 3], tmin: f32, tmax: f32) -> ([f32; 4], u32) {
    // The four children in the lanes of one vector, with the per-lane arithmetic of the
    // scalar form; `f32::min`/`max` ignore a NaN operand, so the selects below do too
    // (maxps/minps would return it).
    let q = |b: [u8; 4]| Vec4::new(b[0] as f32, b[1] as f32, b[2] as f32, b[3] as f32);
    let mut tn = Vec4::splat(tmin);
    let mut tf = Vec4::splat(tmax);
    for a in 0..3 {
        let s = Vec4::splat(n.scale(a));
        let base = Vec4::splat(n.origin[a]);
        let (o, i) = (Vec4::splat(org[a]), Vec4::splat(inv[a]));
        let lo = base + q(n.qlo[a]) * s;
        let hi = base + q(n.qhi[a]) * s;
        let t0 = (lo - o) * i;
        let t1 = (hi - o) * i;
        let skip = t0.is_nan_mask() | t1.is_nan_mask();
        let l = t0.min(t1);
        let h = t0.max(t1);
        let ntn = tn.max(l);
        let far = h + h.abs() * 4.8e-7;
        let ntf = Vec4::select(far.is_nan_mask(), tf, tf.min(far));
        tn = Vec4::select(skip, tn, ntn);
        tf = Vec4::select(skip, tf, ntf);
    }
    (tn.to_array(), tn.cmple(tf).bitmask())
}

/// `ray_box4` for a ray with finite origin and inverse direction: the same operations, without
/// the NaN selects, which change nothing while every slab distance is finite. None when one is
/// not (or a sum of two overflows): the general form then decides.
#[inline(always)]
fn ray_box4_finite(n: &layout::WideNode, org: &[Vec4; 3], inv: &[Vec4; 3], tmin: f32, tmax: f32) -> Option<(Vec4, u32)> {
    // All 24 quantised planes converted at once (exact: bytes are small integers).
    let qb: [u8; 24] = bytemuck::cast([n.qlo, n.qhi]);
    let qf = qb.map(f32::from);
    let q = |at: usize| Vec4::new(qf[at], qf[at + 1], qf[at + 2], qf[at + 3]);
    let mut tn = Vec4::splat(tmin);
    let mut tf = Vec4::splat(tmax);
    // NaN exactly when some t0 or t1 is NaN or infinite (infinity times zero).
    let mut check = Vec4::ZERO;
    for a in 0..3 {
        let s = Vec4::splat(n.scale(a));
        let base = Vec4::splat(n.origin[a]);
        let t0 = (base + q(4 * a) * s - org[a]) * inv[a];
        let t1 = (base + q(12 + 4 * a) * s - org[a]) * inv[a];
        check += (t0 + t1) * Vec4::ZERO;
        let h = t0.max(t1);
        tn = tn.max(t0.min(t1));
        tf = tf.min(h + h.abs() * 4.8e-7);
    }
    if check.is_nan_mask().any() {
        return None;
    }
    Some((tn, tn.cmple(tf).bitmask()))
}

/// A child the ray enters: its entry distance, index (node or first primitive slot) and
/// kind (CHILD_INTERNAL or the leaf's primitive count).
#[derive(Clone, Copy, Debug)]
struct Child {
    tnear: f32,
    index: u32,
    kind: u8,
}

/// The children of node `node` the ray enters within [tmin, tmax], in push order: farthest
/// first, children with equal entry distance in slot order, so the nearest (and of those the
/// last slot) is processed first.
#[inline(always)]
fn enter_children(l: &Level<'_>, node: u32, tmin: f32, tmax: f32, out: &mut [Child; 4]) -> usize {
    let Some(n) = l.node(node) else { return 0 };
    let (tn, hit) = match l.finite.then(|| ray_box4_finite(&n, &l.org4, &l.inv4, tmin, tmax)).flatten() {
        Some((tn, m)) => (tn.to_array(), m),
        None => ray_box4(&n, l.org.to_array(), l.inv.to_array(), tmin, tmax),
    };
    let mut live = hit & ((1u32 << (n.child_count as u32).min(4)) - 1);
    let mut nh = 0;
    while live != 0 {
        let c = live.trailing_zeros() as usize;
        live &= live - 1;
        let kind = n.kind[c];
        // Children always follow their parent in the layout; refusing anything else makes a
        // corrupted blob unable to loop.
        if kind == 0 || (kind == CHILD_INTERNAL && n.child[c] <= node) {
            continue;
        }
        // Insertion by descending entry distance, after equal ones (a stable sort).
        let x = Child { tnear: tn[c], index: n.child[c], kind };
        let mut j = nh;
        while j > 0 && out[j - 1].tnear.total_cmp(&x.tnear) == std::cmp::Ordering::Less {
            out[j] = out[j - 1];
            j -= 1;
        }
        out[j] = x;
        nh += 1;
    }
    nh
}

#[derive(Clone, Copy, Debug)]
enum Item {
    Node { node: u32, inner: bool, tnear: f32 },
    Prims { first: u32, count: u32, inner: bool },
    ExitInstance,
}

#[derive(Clone, Copy)]
struct Level<'a> {
    s: Parsed<'a>,
    org: Vec3,
    dir: Vec3,
    inv: Vec3,
    sh: Shear,
    /// See `Opened::uni_tri`.
    uni_tri: Option<u32>,
    /// A cluster BLAS: per-triangle cluster ID, geometry index, flags and index in cluster.
    cluster: Option<Side<'a>>,
    /// Origin and inverse direction, one axis splatted per vector, and whether all are finite.
    org4: [Vec4; 3],
    inv4: [Vec4; 3],
    finite: bool,
}

impl Level<'_> {
    /// Node `i` of this level's tree (a cluster BLAS's reach into its CLASes' trees).
    #[inline(always)]
    fn node(&self, i: u32) -> Option<layout::WideNode> {
        match &self.cluster {
            Some(c) => c.node(&self.s, i),
            None => self.s.node(i),
        }
    }
}

#[derive(Clone, Copy)]
struct InstCtx<'a> {
    level: Level<'a>,
    rec: InstanceRecord,
}

/// The candidate iterator a ray query needs. Opaque triangle hits are committed internally;
/// non-opaque triangles and all AABBs are returned by `proceed` as candidates.
pub struct RayQuery<'a> {
    top: Option<Level<'a>>,
    view: &'a dyn DeviceView,
    ray: Ray,
    flags: u32,
    cull_mask: u8,
    tmax: f32,
    stack: Vec<Item>,
    inst: Option<InstCtx<'a>>,
    candidate: Option<Hit>,
    committed: Option<Hit>,
    done: bool,
    /// all_hits mode: opaque hits are reported as candidates too, and nothing shrinks tmax.
    collect_all: bool,
    /// Remaining node visits + primitive tests for the top structure and the current instance.
    /// In a valid tree a ray meets every node and primitive at most once, so running out means
    /// the blob is corrupt (e.g. a DAG that would make traversal exponential): stop that level.
    budget_top: u64,
    budget_inner: u64,
    /// The first instance reference met that names no built bottom-level structure (its
    /// instance was treated as absent), for the caller to report once.
    unresolved: Option<u64>,
    /// The structure slice the query was started on, the walkable top level found in it, and
    /// the last BLAS entered: kept by `restart` while the structure and view stay the same.
    source: &'a [u8],
    top_opened: Option<Opened<'a>>,
    blas: BlasMemo<'a>,
}

fn ray_ok(r: &Ray) -> bool {
    !(r.origin.is_nan() || r.direction.is_nan() || r.tmin.is_nan() || r.tmax.is_nan() || r.tmin > r.tmax || r.direction == Vec3::ZERO)
}

/// Checked once per level (a handful of geometries at most; else the general path).
fn uniform_triangles(s: &Parsed<'_>) -> Option<u32> {
    let n = s.raw.geometry_count;
    if n == 0 || n > 8 || s.is_tlas() {
        return None;
    }
    let g0 = s.geometry(0)?;
    if g0.kind != layout::KIND_TRIANGLES {
        return None;
    }
    for i in 1..n {
        let g = s.geometry(i)?;
        if g.kind != layout::KIND_TRIANGLES || g.flags != g0.flags {
            return None;
        }
    }
    Some(g0.flags)
}

#[inline(always)]
fn make_level<'a>(s: (Parsed<'a>, Option<Side<'a>>), view: &'a dyn DeviceView, org: Vec3, dir: Vec3) -> Level<'a> {
    level_of(&opened(s, view), org, dir)
}

impl<'a> RayQuery<'a> {
    pub fn new(structure: &'a [u8], view: &'a dyn DeviceView, ray: Ray, flags: RayFlags, cull_mask: u8) -> Self {
        let mut q = RayQuery {
            top: None,
            view,
            ray,
            flags: flags.0,
            cull_mask,
            tmax: ray.tmax,
            stack: Vec::with_capacity(64),
            inst: None,
            candidate: None,
            committed: None,
            done: false,
            collect_all: false,
            budget_top: 0,
            budget_inner: 0,
            unresolved: None,
            source: structure,
            top_opened: open_top(structure, view),
            blas: None,
        };
        q.start();
        q
    }


    #[inline(always)]
    fn level_ref(&self, inner: bool) -> Option<&Level<'a>> {
        if inner {
            self.inst.as_ref().map(|i| &i.level)
        } else {
            self.top.as_ref()
        }
    }

    /// Next candidate; None when traversal is done.
    pub fn proceed(&mut self) -> Option<Hit> {
        self.candidate = None;
        while !self.done {
            let Some(item) = self.stack.pop() else {
                self.done = true;
                break;
            };
            let inner = match item {
                Item::Node { inner, .. } | Item::Prims { inner, .. } => Some(inner),
                Item::ExitInstance => None,
            };
            match inner {
                Some(true) if self.budget_inner == 0 => continue,
                Some(true) => self.budget_inner -= 1,
                Some(false) if self.budget_top == 0 => {
                    self.terminate();
                    break;
                }
                Some(false) => self.budget_top -= 1,
                None => {}
            }
            match item {
                Item::ExitInstance => self.inst = None,
                Item::Node { node, inner, tnear } => {
                    if tnear > self.tmax {
                        continue;
                    }
                    let (tmin, tmax) = (self.ray.tmin, self.tmax);
                    let Some(l) = self.level_ref(inner) else { continue };
                    let mut hits = [Child { tnear: 0.0, index: 0, kind: 0 }; 4];
                    let nh = enter_children(l, node, tmin, tmax, &mut hits);
                    // A cluster BLAS node whose CLAS is gone: skipped, and reported once.
                    if nh == 0 {
                        if let Some(addr) = l.cluster.and_then(|c| c.fault(node)) {
                            self.unresolved.get_or_insert(addr);
                        }
                    }
                    // A valid tree never holds more than three pending siblings per level; a
                    // stack this deep means a corrupt blob, whose rest is dropped.
                    if self.stack.len() + nh > MAX_STACK {
                        continue;
                    }
                    for h in &hits[..nh] {
                        self.stack.push(match h.kind {
                            CHILD_INTERNAL => Item::Node { node: h.index, inner, tnear: h.tnear },
                            k => Item::Prims { first: h.index, count: k as u32, inner },
                        });
                    }
                }
                Item::Prims { first, count, inner } => {
                    if count > 1 {
                        self.stack.push(Item::Prims { first: first.wrapping_add(1), count: count - 1, inner });
                    }
                    let Some(l) = self.level_ref(inner) else { continue };
                    if l.s.is_tlas() {
                        let l = *l;
                        self.enter_instance(l, first);
                    } else if let Some(hit) = self.test_prim(l, first) {
                        if let Some(h) = self.handle_hit(hit) {
                            return Some(h);
                        }
                    }
                }
            }
        }
        None
    }

    fn enter_instance(&mut self, l: Level<'a>, slot: u32) {
        // Instances only live in a top-level structure that is itself the query root.
        if self.inst.is_some() {
            return;
        }
        match resolve_instance_in(&l, slot, self.view, &self.ray, self.cull_mask, &mut self.blas) {
            Entered::Absent => {}
            Entered::Unresolved(addr) => {
                self.unresolved.get_or_insert(addr);
            }
            Entered::Blas(rec, level) => {
                self.budget_inner = level.s.raw.node_count as u64 + level.s.raw.primitive_count as u64;
                self.inst = Some(InstCtx { level, rec });
                self.stack.push(Item::ExitInstance);
                self.stack.push(Item::Node { node: 0, inner: true, tnear: self.ray.tmin });
            }
        }
    }

    fn test_prim(&self, l: &Level<'a>, slot: u32) -> Option<Hit> {
        let cx = PrimCtx { flags: self.flags, tmin: self.ray.tmin, tmax: self.tmax, inst: self.inst.as_ref().map(|i| &i.rec) };
        test_prim(&cx, l, slot)
    }

    fn handle_hit(&mut self, hit: Hit) -> Option<Hit> {
        if hit.kind == HitKind::Triangle && hit.opaque && !self.collect_all {
            self.commit(hit);
            return None;
        }
        self.candidate = Some(hit);
        Some(hit)
    }

    fn commit(&mut self, hit: Hit) {
        self.committed = Some(hit);
        if !self.collect_all {
            self.tmax = hit.t;
        }
        if self.flags & RayFlags::TERMINATE_ON_FIRST_HIT != 0 {
            self.terminate();
        }
    }

    /// Commit the current triangle candidate.
    pub fn confirm(&mut self) {
        if let Some(c) = self.candidate.take() {
            if c.kind == HitKind::Triangle && c.t <= self.tmax {
                self.commit(c);
            }
        }
    }

    /// Commit the current AABB candidate at t (ignored outside [tmin, current tmax]).
    pub fn generate_intersection(&mut self, t: f32) {
        if let Some(c) = self.candidate {
            if c.kind == HitKind::Aabb && t >= self.ray.tmin && t <= self.tmax {
                self.candidate = None;
                self.commit(Hit { t, ..c });
            }
        }
    }

    pub fn terminate(&mut self) {
        self.done = true;
        self.stack.clear();
        self.inst = None;
    }

    pub fn committed(&self) -> Option<Hit> {
        self.committed
    }

    /// The first instance reference this traversal met that names no built bottom-level
    /// structure (the instance was skipped as absent); None when every reference resolved.
    pub fn unresolved_reference(&self) -> Option<u64> {
        self.unresolved
    }
}

/// What the primitive test needs of the traversal state.
#[derive(Clone, Copy)]
struct PrimCtx<'r> {
    flags: u32,
    tmin: f32,
    /// The current (shrinking) end of the interval.
    tmax: f32,
    /// The instance being traversed, None at the root level.
    inst: Option<&'r InstanceRecord>,
}

/// What a TLAS leaf slot leads to.
// Returned by value and taken apart at once: boxing the large variant would allocate per
// instance entered.
#[allow(clippy::large_enum_variant)]
enum Entered<'a> {
    /// Masked out, no such instance, an empty BLAS or a degenerate transformed ray.
    Absent,
    /// The reference names no built BLAS: the instance is absent, reported once.
    Unresolved(u64),
    Blas(InstanceRecord, Level<'a>),
}

fn resolve_instance<'a>(l: &Level<'a>, slot: u32, view: &'a dyn DeviceView, ray: &Ray, cull_mask: u8) -> Entered<'a> {
    resolve_instance_in(l, slot, view, ray, cull_mask, &mut None)
}

/// Opacity after instance and ray flags; None when the ray culls it.
#[inline(always)]
fn opacity(f: u32, geom_flags: u32, inst_flags: u32) -> Option<bool> {
    let mut opaque = geom_flags & GeometryFlags::OPAQUE != 0;
    if inst_flags & INSTANCE_FORCE_OPAQUE != 0 {
        opaque = true;
    } else if inst_flags & INSTANCE_FORCE_NO_OPAQUE != 0 {
        opaque = false;
    }
    if f & RayFlags::OPAQUE != 0 {
        opaque = true;
    } else if f & RayFlags::NO_OPAQUE != 0 {
        opaque = false;
    }
    if (opaque && f & RayFlags::CULL_OPAQUE != 0) || (!opaque && f & RayFlags::CULL_NO_OPAQUE != 0) {
        return None;
    }
    Some(opaque)
}

/// Geometric test + flag rules for stored primitive `slot` of a BLAS level.
#[inline(always)]
fn test_prim(cx: &PrimCtx<'_>, l: &Level<'_>, slot: u32) -> Option<Hit> {
    if let Some(c) = &l.cluster {
        return test_cluster_triangle(cx, l, c, slot);
    }
    let inst_flags = cx.inst.map_or(0, |i| i.flags);
    let f = cx.flags;
    // Every condition below is a pure conjunct, so with uniform triangle geometries the
    // record/geometry lookups (another cache line per primitive) move after the hit test.
    let (rec, gkind, opaque) = match l.uni_tri {
        Some(gflags) => (None, layout::KIND_TRIANGLES, opacity(f, gflags, inst_flags)?),
        None => {
            let rec = l.s.record(slot)?;
            let geom = l.s.geometry(rec.geometry)?;
            (Some(rec), geom.kind, opacity(f, geom.flags, inst_flags)?)
        }
    };
    let data = l.s.prim(slot)?;
    let (t, kind, bary, front, vertices) = match gkind {
        layout::KIND_TRIANGLES => {
            if f & RayFlags::SKIP_TRIANGLES != 0 {
                return None;
            }
            let (t, uv, front, vertices) = triangle_test(cx, l, &data, inst_flags, false)?;
            (t, HitKind::Triangle, uv, front, vertices)
        }
        layout::KIND_AABBS => {
            if f & RayFlags::SKIP_AABBS != 0 {
                return None;
            }
            let b = [data[0], data[1], data[2], data[3], data[4], data[5]];
            let t = ray_box_exact(l.org, l.dir, &b, cx.tmin, cx.tmax)?;
            (t, HitKind::Aabb, [0.0, 0.0], false, [Vec3::ZERO; 3])
        }
        _ => return None,
    };
    let rec = match rec {
        Some(r) => r,
        None => {
            let r = l.s.record(slot)?;
            l.s.geometry(r.geometry)?;
            r
        }
    };
    Some(hit_of(cx, l, (t, kind, bary, front, opaque), (rec.geometry, rec.primitive, -1), vertices))
}

/// The hit record of a primitive test that passed: (t, kind, barycentrics, front, opaque) and
/// (geometry index, primitive index, cluster ID).
#[inline(always)]
fn hit_of(cx: &PrimCtx<'_>, l: &Level<'_>, (t, kind, bary, front, opaque): (f32, HitKind, [f32; 2], bool, bool), (geometry_index, primitive_index, cluster_id): (u32, u32, i32), vertices: [Vec3; 3]) -> Hit {
    let (ii, ci, sbt, o2w, w2o) = match cx.inst {
        Some(i) => (i.instance_index, i.custom_index, i.sbt_offset, i.object_to_world, i.world_to_object),
        None => (0, 0, 0, IDENTITY, IDENTITY),
    };
    Hit {
        t,
        kind,
        barycentrics: bary,
        front_face: front,
        opaque,
        instance_index: ii,
        instance_custom_index: ci,
        sbt_record_offset: sbt,
        geometry_index,
        primitive_index,
        object_ray_origin: l.org,
        object_ray_direction: l.dir,
        object_to_world: o2w,
        world_to_object: w2o,
        vertices,
        cluster_id,
    }
}

/// `test_prim` for a cluster BLAS: the triangle is read from its CLAS (resolved through the
/// view; a CLAS that is gone yields nothing), its flags and facts from the CLAS's words.
#[inline(always)]
fn test_cluster_triangle(cx: &PrimCtx<'_>, l: &Level<'_>, c: &Side<'_>, slot: u32) -> Option<Hit> {
    let inst_flags = cx.inst.map_or(0, |i| i.flags);
    let f = cx.flags;
    let (data, e) = c.triangle(slot)?;
    let opaque = opacity(f, e.flags, inst_flags)?;
    if f & RayFlags::SKIP_TRIANGLES != 0 {
        return None;
    }
    let (t, uv, front, vertices) = triangle_test(cx, l, &data, inst_flags, e.flags & clas::FLAG_CULL_DISABLE != 0)?;
    Some(hit_of(cx, l, (t, HitKind::Triangle, uv, front, opaque), (e.geometry_index, e.primitive_index, e.cluster_id as i32), vertices))
}

/// The sheared ray/triangle test and the facing cull, shared by ordinary and cluster triangles:
/// (t, barycentrics, front facing, vertices), or None for a miss or a culled face.
#[inline(always)]
fn triangle_test(cx: &PrimCtx<'_>, l: &Level<'_>, data: &[f32], inst_flags: u32, cull_disable: bool) -> Option<(f32, [f32; 2], bool, [Vec3; 3])> {
    let f = cx.flags;
    let v0 = [data[0], data[1], data[2]];
    let v1 = [data[3], data[4], data[5]];
    let v2 = [data[6], data[7], data[8]];
    let (t, u, v, front_raw) = intersect_sheared(&l.sh, l.org.to_array(), cx.tmin, cx.tmax, v0, v1, v2)?;
    let front = front_raw ^ (inst_flags & INSTANCE_FLIP_FACING != 0);
    let culled = (f & RayFlags::CULL_BACK_FACING_TRIANGLES != 0 && !front) || (f & RayFlags::CULL_FRONT_FACING_TRIANGLES != 0 && front);
    if !cull_disable && inst_flags & INSTANCE_FACING_CULL_DISABLE == 0 && culled {
        return None;
    }
    Some((t, [u, v], front, [v0, v1, v2].map(Vec3::from_array)))
}

/// Exact (unwidened) entry distance of a ray into an AABB primitive within [tmin, tmax].
fn ray_box_exact(org: Vec3, dir: Vec3, b: &[f32; 6], tmin: f32, tmax: f32) -> Option<f32> {
    let o = DVec3::new(org.x as f64, org.y as f64, org.z as f64);
    let d = DVec3::new(dir.x as f64, dir.y as f64, dir.z as f64);
    let mut tn = tmin as f64;
    let mut tf = tmax as f64;
    for a in 0..3 {
        let (lo, hi) = (b[a] as f64, b[a + 3] as f64);
        if d[a] == 0.0 {
            if o[a] < lo || o[a] > hi {
                return None;
            }
            continue;
        }
        let t0 = (lo - o[a]) / d[a];
        let t1 = (hi - o[a]) / d[a];
        tn = tn.max(t0.min(t1));
        tf = tf.min(t0.max(t1));
    }
    if tn <= tf && !tn.is_nan() {
        Some((tn as f32).clamp(tmin, tmax))
    } else {
        None
    }
}

/// closest_hit through the resumable query, every candidate confirmed: the definition the
/// plain loop in `closest` must match.
#[cfg(test)]
fn run(mut q: RayQuery<'_>) -> Option<Hit> {
    while let Some(c) = q.proceed() {
        match c.kind {
            HitKind::Triangle => q.confirm(),
            HitKind::Aabb => q.generate_intersection(c.t),
        }
    }
    q.committed()
}

/// Every candidate confirmed (AABB candidates: hit at max(tmin, box entry t)).
pub fn closest_hit(structure: &[u8], view: &dyn DeviceView, ray: Ray, flags: RayFlags, cull_mask: u8) -> Option<Hit> {
    closest::trace(structure, view, ray, flags.0, cull_mask)
}

/// closest_hit with TERMINATE_ON_FIRST_HIT.
pub fn any_hit(structure: &[u8], view: &dyn DeviceView, ray: Ray, flags: RayFlags, cull_mask: u8) -> Option<Hit> {
    closest::trace(structure, view, ray, flags.0 | RayFlags::TERMINATE_ON_FIRST_HIT, cull_mask)
}

/// Every candidate/hit the traversal meets within [tmin, tmax] (flags and culling applied), in
/// no particular order.
pub fn all_hits(structure: &[u8], view: &dyn DeviceView, ray: Ray, flags: RayFlags, cull_mask: u8) -> Vec<Hit> {
    let mut q = RayQuery::new(structure, view, ray, RayFlags(flags.0 & !RayFlags::TERMINATE_ON_FIRST_HIT), cull_mask);
    q.collect_all = true;
    let mut out = Vec::new();
    while let Some(h) = q.proceed() {
        out.push(h);
    }
    out
}

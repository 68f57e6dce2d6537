//! A ray query's per-ray setup: what a level needs of its structure that does not depend on
//! the ray ([`Opened`]: the parsed header, the cluster side table, the uniform-triangle flags),
//! kept by the query from one ray to the next ([`RayQuery::restart`]) together with the last
//! bottom-level structure it entered, so a shader tracing many rays through one structure
//! parses the headers and asks the device view once per lane, not once per ray.
//!
//! Owns: the opened forms and their reuse. Must not touch: traversal order and the box and
//! primitive arithmetic (the parent module's), which see the same `Level` either way.
use glam::{Vec3, Vec4};

use super::super::clas::{self, Side};
use super::super::input::{transform_dir, transform_point};
use super::super::layout::Parsed;
use super::super::DeviceView;
use super::{ray_ok, shear, uniform_triangles, Entered, Item, Level, Ray, RayFlags, RayQuery};

/// What a level needs of its structure that does not depend on the ray.
#[derive(Clone, Copy)]
pub(super) struct Opened<'a> {
    pub s: Parsed<'a>,
    pub cluster: Option<Side<'a>>,
    /// Some(flags) when every geometry of this BLAS is triangles with these same flags.
    pub uni_tri: Option<u32>,
}

/// A cluster BLAS resolves its CLASes through `view`.
pub(super) fn opened<'a>((s, cluster): (Parsed<'a>, Option<Side<'a>>), view: &'a dyn DeviceView) -> Opened<'a> {
    let cluster = cluster.map(|c| c.with_view(view));
    let uni_tri = if cluster.is_some() { None } else { uniform_triangles(&s) };
    Opened { s, cluster, uni_tri }
}

/// The last bottom-level structure a ray query entered: (reference, its walkable form, or None
/// when the reference names no built BLAS).
pub(super) type BlasMemo<'a> = Option<(u64, Option<Opened<'a>>)>;

/// The level of an opened structure for a ray (object-space origin and direction).
#[inline(always)]
pub(super) fn level_of<'a>(o: &Opened<'a>, org: Vec3, dir: Vec3) -> Level<'a> {
    let inv = Vec3::ONE / dir;
    let (org4, inv4) = ([0, 1, 2].map(|a| Vec4::splat(org[a])), [0, 1, 2].map(|a| Vec4::splat(inv[a])));
    let Opened { s, cluster, uni_tri } = *o;
    Level { s, org, dir, inv, sh: shear(dir), uni_tri, cluster, org4, inv4, finite: org.is_finite() && inv.is_finite() }
}

/// The walkable top level of a query's structure (a PTLAS is walked through the top-level
/// structure it embeds).
pub(super) fn open_top<'a>(structure: &'a [u8], view: &'a dyn DeviceView) -> Option<Opened<'a>> {
    let structure = super::super::ptlas::traversable(structure).unwrap_or(structure);
    clas::open_walkable(structure).map(|w| opened(w, view))
}

/// `resolve_instance`, looking the BLAS up in `memo` (the last one resolved through the same
/// view) before asking the view.
pub(super) fn resolve_instance_in<'a>(l: &Level<'a>, slot: u32, view: &'a dyn DeviceView, ray: &Ray, cull_mask: u8, memo: &mut BlasMemo<'a>) -> Entered<'a> {
    let Some(rec) = l.s.instance(slot) else { return Entered::Absent };
    if rec.mask & cull_mask as u32 == 0 {
        return Entered::Absent;
    }
    let Some(addr) = l.s.blas_address(rec.blas_index) else { return Entered::Absent };
    let found = match *memo {
        Some((a, o)) if a == addr => o,
        _ => {
            let o = view.acceleration_structure(addr).and_then(clas::open_walkable).filter(|b| !b.0.is_tlas()).map(|w| opened(w, view));
            *memo = Some((addr, o));
            o
        }
    };
    // A reference that resolves to no built BLAS is never followed: the instance is absent.
    let Some(blas) = found else {
        return Entered::Unresolved(addr);
    };
    if blas.s.raw.node_count == 0 {
        return Entered::Absent;
    }
    let org = transform_point(&rec.world_to_object, ray.origin);
    let dir = transform_dir(&rec.world_to_object, ray.direction);
    if org.is_nan() || dir.is_nan() || dir == Vec3::ZERO {
        return Entered::Absent;
    }
    Entered::Blas(rec, level_of(&blas, org, dir))
}

impl<'a> RayQuery<'a> {
    /// This query started afresh on a new ray, exactly as `RayQuery::new` would start it, but
    /// keeping its stack's allocation and, while `structure` and `view` are the ones it had,
    /// the opened top level and the last BLAS entered. Field by field, in place: the query is
    /// a few kilobytes, which a move per ray would copy.
    pub fn restart(&mut self, structure: &'a [u8], view: &'a dyn DeviceView, ray: Ray, flags: RayFlags, cull_mask: u8) {
        let same_view = std::ptr::addr_eq(view, self.view);
        if !same_view {
            self.blas = None;
        }
        // A cluster BLAS at the top resolves its CLASes through the view it was opened with.
        if !std::ptr::eq(structure, self.source) || !same_view {
            self.top_opened = open_top(structure, view);
        }
        self.source = structure;
        self.view = view;
        self.ray = ray;
        self.flags = flags.0;
        self.cull_mask = cull_mask;
        self.tmax = ray.tmax;
        self.stack.clear();
        self.inst = None;
        self.candidate = None;
        self.committed = None;
        self.done = false;
        self.collect_all = false;
        self.budget_inner = 0;
        self.unresolved = None;
        self.start();
    }

    /// The top level for this ray, and the root on the stack (or done, when there is nothing
    /// to traverse). The rest of the state is that of a fresh query.
    pub(super) fn start(&mut self) {
        let ray = self.ray;
        self.top = self.top_opened.as_ref().map(|o| level_of(o, ray.origin, ray.direction));
        let (budget, walk) = match &self.top {
            Some(l) => (l.s.raw.node_count as u64 + l.s.raw.primitive_count as u64, ray_ok(&ray) && l.s.raw.node_count > 0),
            None => (0, false),
        };
        self.budget_top = budget;
        if walk {
            self.stack.push(Item::Node { node: 0, inner: false, tnear: ray.tmin });
        } else {
            self.done = true;
        }
    }
}

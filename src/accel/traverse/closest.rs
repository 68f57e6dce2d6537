//! `closest_hit` and `any_hit` as one plain loop: every candidate is confirmed, so nothing
//! needs to be resumable. Node order, culling, budgets and stack limit are those of
//! `RayQuery::proceed` followed by confirming each candidate (the `reference` function keeps
//! that path), so both give the same hit, bit for bit.
//!
//! Owns: the non-resumable loop. Must not touch: the arithmetic of box and primitive tests
//! (shared with the ray query through the parent module).
use super::{enter_children, make_level, opacity, ray_ok, resolve_instance, test_prim, Child, Entered, Hit, Level, PrimCtx, Ray, RayFlags, MAX_STACK};
use crate::accel::layout::{self, InstanceRecord, CHILD_INTERNAL};
use crate::accel::DeviceView;

/// The stack entry marking an instance's end (never a child: kind 0 is an empty slot), so
/// stack depths, and with them the corrupt-blob limit, match the ray query's.
const EXIT: Child = Child { tnear: 0.0, index: 0, kind: 0 };

/// Entries kept in place before the rest goes to the heap (a valid tree's traversal rarely
/// holds more: at most three pending siblings per level of depth).
const INLINE: usize = 32;

/// The traversal stack: the first `INLINE` entries in place, the rest in `spill`
/// (`spill.len() == len.saturating_sub(INLINE)`), so a ray allocates nothing.
struct Stack {
    len: usize,
    inline: [Child; INLINE],
    spill: Vec<Child>,
}

impl Stack {
    fn len(&self) -> usize {
        self.len
    }

    #[inline(always)]
    fn push(&mut self, c: Child) {
        match self.inline.get_mut(self.len) {
            Some(slot) => *slot = c,
            None => self.spill.push(c),
        }
        self.len += 1;
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<Child> {
        self.len = self.len.checked_sub(1)?;
        match self.inline.get(self.len) {
            Some(&c) => Some(c),
            None => self.spill.pop(),
        }
    }

    fn truncate(&mut self, len: usize) {
        if len < self.len {
            self.len = len;
            self.spill.truncate(len.saturating_sub(INLINE));
        }
    }
}

/// Starts loading a pending child's node or primitives, which random rays mostly miss in cache.
#[inline(always)]
fn prefetch(l: &Level<'_>, c: Child) {
    if l.cluster.is_some() {
        return;
    }
    let r = &l.s.raw;
    let at = match c.kind {
        CHILD_INTERNAL => r.nodes_offset.wrapping_add(c.index as u64 * layout::NODE_SIZE as u64),
        _ => r.prims_offset.wrapping_add(c.index as u64 * layout::PRIM_SIZE as u64),
    };
    arbor_prefetch::read(l.s.bytes, at as usize);
}

struct Tracer<'a> {
    view: &'a dyn DeviceView,
    ray: Ray,
    flags: u32,
    cull_mask: u8,
    tmax: f32,
    best: Option<Hit>,
    done: bool,
    stack: Stack,
}

/// Closest hit (any hit with TERMINATE_ON_FIRST_HIT in `flags`), every candidate confirmed.
pub(super) fn trace<'a>(structure: &'a [u8], view: &'a dyn DeviceView, ray: Ray, flags: u32, cull_mask: u8) -> Option<Hit> {
    // A PTLAS is walked through the top-level structure it embeds.
    let structure = super::super::ptlas::traversable(structure).unwrap_or(structure);
    let s = super::super::clas::open_walkable(structure)?;
    if !ray_ok(&ray) || s.0.raw.node_count == 0 {
        return None;
    }
    let top = make_level(s, view, ray.origin, ray.direction);
    let mut t = Tracer { view, ray, flags, cull_mask, tmax: ray.tmax, best: None, done: false, stack: Stack { len: 0, inline: [EXIT; INLINE], spill: Vec::new() } };
    t.stack.push(Child { tnear: ray.tmin, index: 0, kind: CHILD_INTERNAL });
    t.level(&top, None, 0);
    t.best
}

impl<'a> Tracer<'a> {
    /// Traverses one level until the stack is back at `base`. The top level's visit budget
    /// running out ends the traversal; an instance's ends that instance.
    fn level(&mut self, l: &Level<'a>, inst: Option<&InstanceRecord>, base: usize) {
        let mut budget = l.s.raw.node_count as u64 + l.s.raw.primitive_count as u64;
        let tlas = l.s.is_tlas();
        if let Some(g) = l.uni_tri {
            // Triangles the ray flags cull or skip as a whole: nothing here can hit.
            if opacity(self.flags, g, inst.map_or(0, |i| i.flags)).is_none() || self.flags & RayFlags::SKIP_TRIANGLES != 0 {
                self.stack.truncate(base);
                return;
            }
        }
        // The nearest child of the last node goes on directly: pushing and popping it would
        // leave everything (stack depth included) as it is now.
        let mut next = None;
        loop {
            let e = match next.take() {
                Some(e) => e,
                None if self.stack.len() > base => match self.stack.pop() {
                    Some(e) => e,
                    None => break,
                },
                None => break,
            };
            if budget == 0 {
                self.stop(inst.is_none(), base);
                return;
            }
            budget -= 1;
            if e.kind == CHILD_INTERNAL {
                if e.tnear > self.tmax {
                    continue;
                }
                let mut hits = [EXIT; 4];
                let nh = enter_children(l, e.index, self.ray.tmin, self.tmax, &mut hits);
                if nh > 0 && self.stack.len() + nh <= MAX_STACK {
                    for &h in &hits[..nh - 1] {
                        prefetch(l, h);
                        self.stack.push(h);
                    }
                    next = Some(hits[nh - 1]);
                }
            } else if tlas {
                // One instance at a time, the rest of the leaf pending on the stack.
                if e.kind > 1 {
                    self.stack.push(Child { tnear: e.tnear, index: e.index.wrapping_add(1), kind: e.kind - 1 });
                }
                self.instance(l, e.index);
                if self.done {
                    return;
                }
            } else {
                for i in 0..e.kind as u32 {
                    if i > 0 {
                        if budget == 0 {
                            self.stop(inst.is_none(), base);
                            return;
                        }
                        budget -= 1;
                    }
                    let cx = PrimCtx { flags: self.flags, tmin: self.ray.tmin, tmax: self.tmax, inst };
                    if let Some(hit) = test_prim(&cx, l, e.index.wrapping_add(i)) {
                        self.tmax = hit.t;
                        self.best = Some(hit);
                        if self.flags & RayFlags::TERMINATE_ON_FIRST_HIT != 0 {
                            self.stop(true, base);
                            return;
                        }
                    }
                }
            }
        }
    }

    /// Ends the whole traversal (`all`) or the current level's part of the stack.
    fn stop(&mut self, all: bool, base: usize) {
        if all {
            self.done = true;
            self.stack.truncate(0);
        } else {
            self.stack.truncate(base);
        }
    }

    fn instance(&mut self, l: &Level<'a>, slot: u32) {
        let Entered::Blas(rec, level) = resolve_instance(l, slot, self.view, &self.ray, self.cull_mask) else { return };
        self.stack.push(EXIT);
        self.stack.push(Child { tnear: self.ray.tmin, index: 0, kind: CHILD_INTERNAL });
        let base = self.stack.len() - 1;
        self.level(&level, Some(&rec), base);
        if !self.done {
            self.stack.pop();
        }
    }
}

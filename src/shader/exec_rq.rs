//! Ray-query instructions of the lane executor: each lane's queries are slots of native
//! traversal state ([`accel::RayQuery`]) in its lane group, keyed by the query variable's
//! lane-frame address, and every op runs the traversal for the lanes in the mask.
//!
//! Owns the Vulkan-visible semantics on top of `accel`'s traversal (which owns intersection,
//! flags, culling, masks and the commit rules): what each getter returns for the candidate and
//! the committed intersection, the intersection-type encodings, and the faults. A query on an
//! address that is no structure, on bytes that fail the header check, or any use of a query
//! never initialised is a [`Fault`]; such a query finds nothing and execution goes on.
//! Committed getters with nothing committed are not faults (shaders legitimately read the
//! committed t as the current tmax): t is tmax, everything else zero.
use glam::Vec3;

use super::alu;
use super::exec::{Ctx, Group, Wg};
use super::ir::{RayQueryOp, RqKind, RqValue, Sc};
use super::memory::{Fault, FaultKind, FaultSpace};
use super::LANES;
use crate::accel::{self, DeviceView, Hit, HitKind, NoDevice, Ray, RayFlags, RayQuery};

/// One lane's initialised ray query.
pub(super) struct Slot<'a> {
    q: RayQuery<'a>,
    ray: Ray,
    flags: u32,
    /// The intersection the last Proceed stopped at (kept after Confirm/Generate, for getters).
    candidate: Option<Hit>,
}

/// The ray queries of one lane group: per lane, (query address, state). Shaders use one or
/// two queries, so a short list beats a map. The first `live[lane]` slots are the current
/// workgroup's; the rest are kept from earlier workgroups, whose queries a new Initialize
/// restarts instead of allocating a new one (each keeps its stack and the structures it
/// opened: nothing is allocated or looked up in shared state per ray).
///
/// Also the last structure an Initialize resolved and found valid, (address, bytes): every ray
/// of a dispatch usually names the same one. Its bytes stay valid for the whole dispatch
/// (`'a`), across workgroups.
pub(super) struct Queries<'a> {
    lanes: [Vec<(u64, Slot<'a>)>; LANES],
    live: [usize; LANES],
    last: Option<(u64, &'a [u8])>,
}

/// What an Initialize starts a query on.
struct Start<'a> {
    bytes: &'a [u8],
    view: &'a dyn DeviceView,
    ray: Ray,
    flags: u32,
    cull: u8,
}

impl<'a> Queries<'a> {
    pub fn new() -> Self {
        Queries { lanes: std::array::from_fn(|_| Vec::new()), live: [0; LANES], last: None }
    }

    /// Forgets every query (a new workgroup starts with none initialised).
    pub fn clear(&mut self) {
        self.live = [0; LANES];
    }

    fn get(&mut self, lane: usize, at: u64) -> Option<&mut Slot<'a>> {
        self.lanes[lane][..self.live[lane]].iter_mut().find(|(a, _)| *a == at).map(|(_, s)| s)
    }

    /// Lane `lane`'s query at `at` started: the live slot of that address restarted, else a
    /// kept slot taken over, else a new one.
    fn start(&mut self, lane: usize, at: u64, s: Start<'a>) {
        let (slots, live) = (&mut self.lanes[lane], &mut self.live[lane]);
        let i = match slots[..*live].iter().position(|(a, _)| *a == at) {
            Some(i) => i,
            None if *live < slots.len() => {
                slots[*live].0 = at;
                *live += 1;
                *live - 1
            }
            None => {
                let q = RayQuery::new(s.bytes, s.view, s.ray, RayFlags(s.flags), s.cull);
                slots.push((at, Slot { q, ray: s.ray, flags: s.flags, candidate: None }));
                *live += 1;
                return;
            }
        };
        let slot = &mut slots[i].1;
        slot.q.restart(s.bytes, s.view, s.ray, RayFlags(s.flags), s.cull);
        (slot.ray, slot.flags, slot.candidate) = (s.ray, s.flags, None);
    }
}

fn fault(wg: &mut Wg, group_index: u32, lane: usize, kind: FaultKind, at: u64) {
    wg.fault_count += 1;
    if wg.faults.len() < 16 {
        let invocation = group_index * LANES as u32 + lane as u32;
        wg.faults.push(Fault { kind, space: FaultSpace::RayQuery, at, len: 0, write: false, workgroup: wg.id, invocation });
    }
}

pub(super) fn exec_ray_query<'a>(ctx: &Ctx<'a>, group: &mut Group<'a>, wg: &mut Wg, op: &RayQueryOp, mask: u32) {
    for l in (0..LANES).filter(|&l| (mask >> l) & 1 != 0) {
        let at = group.regs[op.query as usize][l];
        if op.kind == RqKind::Initialize {
            let start = initialize(ctx, &mut *group, wg, op, l);
            group.queries.start(l, at, start);
            continue;
        }
        let Some(slot) = group.queries.get(l, at) else {
            fault(wg, group.index, l, FaultKind::Uninitialized, at);
            for &d in &op.dst {
                group.regs[d as usize][l] = 0;
            }
            continue;
        };
        match op.kind {
            RqKind::Initialize => {}
            RqKind::Proceed => {
                slot.candidate = slot.q.proceed();
                group.regs[op.dst[0] as usize][l] = slot.candidate.is_some() as u64;
                if let (None, Some(address)) = (wg.unresolved, slot.q.unresolved_reference()) {
                    let invocation = group.index * LANES as u32 + l as u32;
                    let kind = FaultKind::UnresolvedInstance;
                    wg.unresolved = Some(Fault { kind, space: FaultSpace::RayQuery, at: address, len: 0, write: false, workgroup: wg.id, invocation });
                }
            }
            RqKind::Terminate => slot.q.terminate(),
            RqKind::Confirm => slot.q.confirm(),
            RqKind::Generate => {
                let t = f32::from_bits(group.regs[op.args[0] as usize][l] as u32);
                slot.q.generate_intersection(t);
            }
            RqKind::Get { value, committed } => {
                let mut out = [0u64; 12];
                get(slot, value, committed, &mut out);
                for (k, &d) in op.dst.iter().enumerate() {
                    group.regs[d as usize][l] = out[k];
                }
            }
        }
    }
}

/// OpRayQueryInitializeKHR for lane `l`: resolves the structure (faulting when it cannot) for
/// a traversal, which finds nothing when the structure is missing.
fn initialize<'a>(ctx: &Ctx<'a>, group: &mut Group<'a>, wg: &mut Wg, op: &RayQueryOp, l: usize) -> Start<'a> {
    let a = |k: usize| group.regs[op.args[k] as usize][l];
    let f = |k: usize| f32::from_bits(a(k) as u32);
    let address = a(0);
    let flags = a(1) as u32;
    // Only the 8 low bits of the cull mask take part (SPIR-V).
    let cull = a(2) as u8;
    let ray = Ray { origin: Vec3::new(f(3), f(4), f(5)), tmin: f(6), direction: Vec3::new(f(7), f(8), f(9)), tmax: f(10) };
    let view: &'a dyn DeviceView = ctx.mem.acceleration_structures().unwrap_or(&NoDevice);
    if let Some((_, bytes)) = group.queries.last.filter(|(at, _)| *at == address) {
        return Start { bytes, view, ray, flags, cull };
    }
    let bytes: &'a [u8] = match view.acceleration_structure(address) {
        None => {
            fault(wg, group.index, l, FaultKind::Unmapped, address);
            &[]
        }
        Some(b) if accel::header(b).is_none() => {
            fault(wg, group.index, l, FaultKind::InvalidStructure, address);
            &[]
        }
        Some(b) => {
            group.queries.last = Some((address, b));
            b
        }
    };
    Start { bytes, view, ray, flags, cull }
}

fn f32s(out: &mut [u64], v: &[f32]) {
    for (o, x) in out.iter_mut().zip(v) {
        *o = alu::norm(Sc::F32, x.to_bits() as u64);
    }
}

/// Column-major mat4x3 from a row-major 3x4 (VkTransformMatrixKHR order).
fn columns(m: &[f32; 12]) -> [f32; 12] {
    std::array::from_fn(|k| m[(k % 3) * 4 + k / 3])
}

fn get(slot: &Slot<'_>, value: RqValue, committed: bool, out: &mut [u64; 12]) {
    let hit = if committed { slot.q.committed() } else { slot.candidate };
    match value {
        RqValue::TMin => f32s(out, &[slot.ray.tmin]),
        RqValue::RayFlags => out[0] = slot.flags as u64,
        RqValue::WorldRayOrigin => f32s(out, &slot.ray.origin.to_array()),
        RqValue::WorldRayDirection => f32s(out, &slot.ray.direction.to_array()),
        // Committed: 0 none, 1 triangle, 2 generated. Candidate: 0 triangle, 1 AABB.
        RqValue::Type => {
            out[0] = match (committed, hit.map(|h| h.kind)) {
                (true, None) => 0,
                (true, Some(HitKind::Triangle)) => 1,
                (true, Some(HitKind::Aabb)) => 2,
                (false, Some(HitKind::Aabb)) => 1,
                (false, _) => 0,
            }
        }
        // Nothing committed: the committed t is the ray's tmax (what traversal still accepts).
        RqValue::T if committed && hit.is_none() => f32s(out, &[slot.ray.tmax]),
        // No intersection is no cluster: -1, as for ordinary geometry.
        RqValue::ClusterId if hit.is_none() => out[0] = alu::norm(Sc::I32, u64::MAX),
        _ => {
            if let Some(h) = hit {
                hit_value(&h, value, out);
            }
        }
    }
}

/// The getters that read an intersection.
fn hit_value(h: &Hit, value: RqValue, out: &mut [u64; 12]) {
    match value {
        RqValue::T => f32s(out, &[h.t]),
        RqValue::InstanceCustomIndex => out[0] = h.instance_custom_index as u64,
        RqValue::InstanceId => out[0] = h.instance_index as u64,
        RqValue::SbtRecordOffset => out[0] = h.sbt_record_offset as u64,
        RqValue::GeometryIndex => out[0] = h.geometry_index as u64,
        RqValue::PrimitiveIndex => out[0] = h.primitive_index as u64,
        RqValue::Barycentrics => f32s(out, &h.barycentrics),
        RqValue::FrontFace => out[0] = h.front_face as u64,
        RqValue::CandidateAabbOpaque => out[0] = (h.kind == HitKind::Aabb && h.opaque) as u64,
        RqValue::ObjectRayOrigin => f32s(out, &h.object_ray_origin.to_array()),
        RqValue::ObjectRayDirection => f32s(out, &h.object_ray_direction.to_array()),
        RqValue::ObjectToWorld => f32s(out, &columns(&h.object_to_world)),
        RqValue::WorldToObject => f32s(out, &columns(&h.world_to_object)),
        RqValue::ClusterId => out[0] = alu::norm(Sc::I32, h.cluster_id as i64 as u64),
        RqValue::TriangleVertexPositions => {
            let v = h.vertices;
            f32s(out, &[v[0].x, v[0].y, v[0].z, v[1].x, v[1].y, v[1].z, v[2].x, v[2].y, v[2].z]);
        }
        RqValue::TMin | RqValue::RayFlags | RqValue::WorldRayOrigin | RqValue::WorldRayDirection | RqValue::Type => {}
    }
}

//! Running the checked builds of one command: where they run (one rule, [`Placement`]), the
//! writable regions each build gets, the geometry the library reads, and the library's
//! verdict turned into diagnostics.
//!
//! This module must not check valid usage itself (that is `validate`'s, before anything runs)
//! nor make views of memory (`crate::memory::region` hands out the writable ones).
use std::sync::Arc;

use ash::vk;
use rayon::prelude::*;

use super::inputs::InputMemory;
use super::validate::{self, triangle_ranges, update_vuid, violation, Prepared, INPUT_USAGE};
use super::{to_as_type, BuildInfo, DeviceLost, GeometryDesc, RangeInfo};
use crate::accel::{self, BuildFlags, GeometryFlags, IndexType, VertexFormat};
use crate::diag;
use crate::memory::region::{Claim, Region, WriteSet};

/// Where the builds of one command run: the one place that decides it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Placement {
    /// On the calling thread (a queue worker, or an application thread calling a host command,
    /// which `threads::run_here` made the one worker of a private pool): too little work to
    /// share among the pool's threads, so no hand-off to the pool and back.
    Here,
    /// On the pool the calling thread works for: a deferred operation's joiners, else Arbor's
    /// worker pool.
    Pool,
}

impl Placement {
    /// Small builds (`threads::runs_inline`: primitives × pool threads) run here. Updates
    /// always go to the pool: a refit splits even small trees across threads.
    pub(super) fn of_builds(builds: &[Prepared]) -> Placement {
        let prims: u64 = builds.iter().flat_map(|p| p.ranges.iter()).map(|r| r.primitive_count as u64).sum();
        let builds_only = builds.iter().all(|p| p.info.mode != vk::BuildAccelerationStructureModeKHR::UPDATE);
        if builds_only && crate::threads::runs_inline(prims) {
            Placement::Here
        } else {
            Placement::Pool
        }
    }

    fn run<R: Send>(self, f: impl FnOnce() -> R + Send) -> R {
        crate::threads::run_parallel(self == Placement::Here, f)
    }
}

/// Execute the builds of one command (`vkCmdBuildAccelerationStructures(Indirect)KHR` at queue
/// execution time, or `vkBuildAccelerationStructuresKHR` on the host). Invalid builds are
/// reported, skipped and their destination marked invalid; valid ones run in parallel on the
/// worker pool. Returns Err(DeviceLost) in strict mode when anything was invalid.
pub fn execute_builds(mem: &dyn InputMemory, infos: &[BuildInfo]) -> Result<(), DeviceLost> {
    let (runnable, mut invalid) = validate::check_builds(mem, infos);
    let placement = Placement::of_builds(&runnable);
    // Each build's destination and scratch, claimed for it alone before any build runs.
    let mut writes = WriteSet::new();
    let jobs: Vec<(Prepared, Option<Claim<'_, 2>>)> = runnable
        .into_iter()
        .map(|p| {
            let claim = claim_regions(mem, &mut writes, &p);
            (p, claim)
        })
        .collect();
    let results: Vec<bool> = placement.run(|| jobs.into_par_iter().map(|(p, claim)| claim.is_some_and(|c| run(mem, &p, c))).collect());
    invalid |= results.iter().any(|ok| !ok);
    if invalid && diag::strict() {
        return Err(DeviceLost);
    }
    Ok(())
}

/// The destination and scratch of a checked build (None when either no longer resolves, or,
/// against a check `validate` made, overlaps a region claimed before).
/// Each miss is reported: memory freed while the command was pending (reported by
/// vkFreeMemory too) is the way a checked region stops resolving.
fn claim_regions<'m>(mem: &'m dyn InputMemory, writes: &mut WriteSet, p: &Prepared) -> Option<Claim<'m, 2>> {
    let skipped = |what: &str| diag::report(diag::Level::Error, mem.command(), &format!("pInfos[{}]: {what}; build skipped", p.index));
    let dst = match Region::of_buffer(&p.dst.buffer, p.dst.offset, p.dst.size) {
        Ok(r) => r,
        Err(e) => {
            skipped(&format!("the destination no longer resolves ({e})"));
            return None;
        }
    };
    let scratch = if p.scratch_len == 0 {
        Region::empty()
    } else {
        match mem.writable(p.info.scratch, p.scratch_len) {
            Ok(r) => r,
            Err(e) => {
                skipped(&format!("the scratch no longer resolves ({e:?})"));
                return None;
            }
        }
    };
    match writes.claim([dst, scratch]) {
        Ok(c) => Some(c),
        Err(_) => {
            skipped("destination or scratch overlaps a region another element of the command writes");
            None
        }
    }
}

/// Run one checked build. Returns false when the library rejected it (reported, dst invalid).
fn run(mem: &dyn InputMemory, p: &Prepared, mut claim: Claim<'_, 2>) -> bool {
    let info = p.info;
    let Some(geometries) = geometry_data(mem, info, &p.ranges) else { return false };
    let Some(ty) = to_as_type(info.ty) else { return false };
    let desc = accel::BuildDesc { ty, flags: BuildFlags(info.flags.as_raw()), geometries: &geometries };
    let [dst, scratch] = claim.slices();
    let result = if info.mode == vk::BuildAccelerationStructureModeKHR::UPDATE {
        let src = info.src.as_ref().filter(|s| !Arc::ptr_eq(s, &p.dst));
        match src {
            None => accel::update(&desc, mem, None, dst, scratch),
            Some(s) => match s.bytes() {
                Ok(sb) => accel::update(&desc, mem, Some(sb), dst, scratch),
                Err(_) => return false,
            },
        }
    } else {
        accel::build(&desc, mem, dst, scratch)
    };
    match result {
        Ok(_) => true,
        Err(e) => {
            let (vuid, msg) = match &e {
                accel::BuildError::IndexOutOfRange { geometry, primitive, index } => (
                    "pInfos-03651",
                    format!("geometry {geometry} primitive {primitive}: index {index} exceeds maxVertex"),
                ),
                accel::BuildError::UpdateMismatch(what) => (update_vuid(what), format!("update does not match the last build: {what}")),
                accel::BuildError::InvalidAddress { geometry, primitive } => {
                    ("pInfos-03813", format!("geometry {geometry} instance {primitive}: pointer does not address a valid instance"))
                }
                other => ("pInfos-03651", format!("build rejected: {other:?}")),
            };
            violation(mem.command(), vuid, p.index, &msg);
            accel::mark_invalid(dst);
            false
        }
    }
}

/// The library's view of a checked build's geometries: input bytes resolved now, read in
/// place. None when an input no longer resolves (checked in `validate`: formats known, ranges
/// inside buffers).
fn geometry_data<'m>(mem: &'m dyn InputMemory, info: &BuildInfo, ranges: &[RangeInfo]) -> Option<Vec<accel::Geometry<'m>>> {
    let mut geometries = Vec::with_capacity(info.geometries.len());
    for (g, r) in info.geometries.iter().zip(ranges) {
        let count = r.primitive_count as u64;
        let flags = GeometryFlags(g.flags.as_raw());
        let data = match &g.desc {
            GeometryDesc::Triangles { .. } => triangle_data(mem, &g.desc, r)?,
            GeometryDesc::Aabbs { data, stride } => {
                let bytes = if count == 0 { &[][..] } else {
                    match mem.input(data + r.primitive_offset as u64, (count - 1) * stride + 24, INPUT_USAGE) {
                        Ok(b) => b,
                        Err(_) => return None,
                    }
                };
                accel::GeometryData::Aabbs { data: bytes, stride: *stride }
            }
            GeometryDesc::Instances { array_of_pointers, data } => {
                let bytes = if count == 0 { &[][..] } else {
                    match mem.input(data + r.primitive_offset as u64, count * if *array_of_pointers { 8 } else { 64 }, INPUT_USAGE) {
                        Ok(b) => b,
                        Err(_) => return None,
                    }
                };
                accel::GeometryData::Instances { array_of_pointers: *array_of_pointers, data: bytes }
            }
            GeometryDesc::Unsupported(_) => return None,
        };
        geometries.push(accel::Geometry { flags, primitive_count: r.primitive_count, data });
    }
    Some(geometries)
}

/// The library's view of one triangle geometry (formats and ranges checked in `validate`).
fn triangle_data<'m>(mem: &'m dyn InputMemory, desc: &GeometryDesc, r: &RangeInfo) -> Option<accel::GeometryData<'m>> {
    let GeometryDesc::Triangles { vertex_format, vertex_data, vertex_stride, max_vertex, index_type, index_data, transform_data } = desc else {
        return None;
    };
    let count = r.primitive_count as u64;
    let (Some(fmt), Some(it)) = (VertexFormat::from_vk(vertex_format.as_raw()), IndexType::from_vk(index_type.as_raw())) else {
        return None;
    };
    let (vertices, max_v, indices, transform) = if count == 0 {
        (&[][..], 0, &[][..], None)
    } else {
        let (vstart, vlen, max_v, istart) = triangle_ranges(fmt, *vertex_data, *vertex_stride, *max_vertex, it, r)?;
        let v = mem.input(vstart, vlen, INPUT_USAGE).ok();
        let i = if it == IndexType::None { Some(&[][..]) } else { mem.input(index_data + istart, count * 3 * it.size() as u64, INPUT_USAGE).ok() };
        let t = if *transform_data == 0 {
            Some(None)
        } else {
            mem.input(transform_data + r.transform_offset as u64, 48, INPUT_USAGE).ok().map(|b| {
                let mut m = [0f32; 12];
                for (k, v) in m.iter_mut().enumerate() {
                    *v = f32::from_le_bytes(b[k * 4..k * 4 + 4].try_into().unwrap());
                }
                Some(m)
            })
        };
        let (Some(v), Some(i), Some(t)) = (v, i, t) else { return None };
        (v, max_v, i, t)
    };
    Some(accel::GeometryData::Triangles {
        format: fmt,
        vertices,
        stride: *vertex_stride,
        max_vertex: max_v,
        index_type: it,
        indices,
        transform,
    })
}

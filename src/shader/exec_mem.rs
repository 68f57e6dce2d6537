//! Loads, stores and atomics of the lane executor: every access is bounds-checked against its
//! space (lane frame, shared memory, push constants, a descriptor's region, a resolved device
//! address); a failed check records a [`Fault`] and the access reads zero or is dropped.
use super::alu;
use super::exec::{Ctx, Group, Wg};
use super::ir::{AtomicOp, Op, Program, Sc, Space, ELEMENT_SHIFT};
use super::memory::{Fault, FaultKind, FaultSpace, ImageFormat, Memory, Region};
use super::LANES;

/// What one lane does at an address.
#[derive(Clone, Copy)]
pub(super) enum Access {
    Read,
    Write(u64),
    Rmw(AtomicOp, u64, u64),
}

pub(super) fn exec_mem(ctx: &Ctx, group: &mut Group, wg: &mut Wg, op: &Op, mask: u32) {
    let (ty, space, addr, dst, access) = match *op {
        Op::Load { ty, space, dst, addr } => (ty, space, addr, Some(dst), None),
        Op::Store { ty, space, addr, src } => (ty, space, addr, None, Some((Access::Write(0), src, 0))),
        Op::Atomic { op, ty, space, dst, addr, a, b } => (ty, space, addr, Some(dst), Some((Access::Rmw(op, 0, 0), a, b))),
        _ => return,
    };
    let fs = ctx.prog.lane_frame.len();
    if space == Space::Lane {
        let fast = match (op, dst) {
            (Op::Load { .. }, Some(dst)) => lane_loads(group, fs, ty, addr, dst, mask),
            (&Op::Store { src, .. }, _) => lane_stores(group, fs, ty, addr, src, mask),
            _ => false,
        };
        if fast {
            return;
        }
    }
    if let (Space::Push, Some(dst), None) = (space, dst, access) {
        if push_loads(ctx, group, ty, addr, dst, mask) {
            return;
        }
    }
    for l in (0..LANES).filter(|&l| (mask >> l) & 1 != 0) {
        let at = group.regs[addr as usize][l];
        let acc = match access {
            None => Access::Read,
            Some((Access::Write(_), src, _)) => Access::Write(group.regs[src as usize][l]),
            Some((Access::Rmw(op, ..), a, b)) => Access::Rmw(op, group.regs[a as usize][l], group.regs[b as usize][l]),
            Some((Access::Read, ..)) => Access::Read,
        };
        let frame = &mut group.frame[l * fs..(l + 1) * fs];
        let invocation = group.index * LANES as u32 + l as u32;
        let v = access_one(ctx, frame, wg, space, at, ty, acc).unwrap_or_else(|(kind, fspace)| {
            wg.fault_count += 1;
            if wg.faults.len() < 16 {
                let write = !matches!(acc, Access::Read);
                // An array element's fault names the element; `at` is the offset inside it.
                let at = if matches!(fspace, FaultSpace::ArrayElement { .. }) { at & ((1 << ELEMENT_SHIFT) - 1) } else { at };
                wg.faults.push(Fault { kind, space: fspace, at, len: ty.size(), write, workgroup: wg.id, invocation });
            }
            0
        });
        if let Some(d) = dst {
            group.regs[d as usize][l] = alu::norm(ty, v);
        }
    }
}

type AccessResult = Result<u64, (FaultKind, FaultSpace)>;

pub(super) fn access_one(ctx: &Ctx, frame: &mut [u8], wg: &mut Wg, space: Space, at: u64, ty: Sc, acc: Access) -> AccessResult {
    let size = ty.size() as usize;
    match space {
        Space::Lane => local(frame, at, size, ty, acc).ok_or((FaultKind::OutOfBounds, FaultSpace::Invocation)),
        Space::Workgroup => local(&mut wg.shared, at, size, ty, acc).ok_or((FaultKind::OutOfBounds, FaultSpace::Workgroup)),
        Space::Push => match acc {
            Access::Read => read_le(ctx.push, at, size).ok_or((FaultKind::OutOfBounds, FaultSpace::PushConstant)),
            _ => Err((FaultKind::Refused, FaultSpace::PushConstant)),
        },
        Space::Buffer(slot) => {
            let (region, fspace, at) = buffer_region(ctx, slot, at)?;
            if at.checked_add(size as u64).is_none_or(|end| end > region.len) {
                return Err((FaultKind::OutOfBounds, fspace));
            }
            let offset = region.offset.checked_add(at).ok_or((FaultKind::Refused, fspace))?;
            device(ctx, region.buffer, offset, ty, acc).ok_or((FaultKind::Refused, fspace))
        }
        Space::Image(slot) => {
            // The element is above ELEMENT_SHIFT; the offset below it is TEXEL_OUTSIDE for a
            // coordinate outside the view.
            let element = (at >> ELEMENT_SHIFT) as u32;
            let image = super::exec_image::view(ctx, slot, element)?;
            let fspace = super::exec_image::view_space(ctx, slot, element);
            let at = at & ((1 << ELEMENT_SHIFT) - 1);
            // Texel pointers reach single-component 32-bit integer texels only (the formats
            // image atomics are defined on); anything else is refused.
            if !matches!(image.format, ImageFormat::R32Uint | ImageFormat::R32Sint) || size != 4 {
                return Err((FaultKind::Refused, fspace));
            }
            let offset = image.offset.checked_add(at).filter(|_| at != super::exec_image::TEXEL_OUTSIDE).ok_or((FaultKind::OutOfBounds, fspace))?;
            device(ctx, image.buffer, offset, ty, acc).ok_or((FaultKind::Refused, fspace))
        }
        Space::Accel(slot) => {
            let ((set, binding), _) = ctx.prog.accel_arrays[slot as usize];
            let element = u32::try_from(at / 8).unwrap_or(u32::MAX);
            let fspace = FaultSpace::ArrayElement { set, binding, element };
            let elements = &ctx.accel_arrays[slot as usize];
            match acc {
                Access::Read if at.is_multiple_of(8) && size == 8 => elements.get(element as usize).copied().ok_or((FaultKind::ArrayIndex, fspace)),
                _ => Err((FaultKind::Refused, fspace)),
            }
        }
        Space::Physical => {
            let region = ctx.mem.address(at, size as u64).ok_or((FaultKind::Unmapped, FaultSpace::DeviceAddress))?;
            device(ctx, region.buffer, region.offset, ty, acc).ok_or((FaultKind::Refused, FaultSpace::DeviceAddress))
        }
    }
}

/// The region a `Space::Buffer` address falls in, the fault space naming it, and the offset
/// inside it. A single descriptor takes the address whole; an array's address carries the
/// element above `ELEMENT_SHIFT` (an index past the end is an `ArrayIndex` fault).
fn buffer_region(ctx: &Ctx, slot: u16, at: u64) -> Result<(Region, FaultSpace, u64), (FaultKind, FaultSpace)> {
    let (set, binding) = ctx.prog.bindings[slot as usize];
    let elements = &ctx.regions[slot as usize];
    if ctx.prog.binding_counts[slot as usize] == 1 {
        let fspace = FaultSpace::Binding { set, binding };
        return Ok((elements[0].ok_or((FaultKind::Unbound, fspace))?, fspace, at));
    }
    let element = u32::try_from(at >> ELEMENT_SHIFT).unwrap_or(u32::MAX);
    let fspace = FaultSpace::ArrayElement { set, binding, element };
    let region = elements.get(element as usize).ok_or((FaultKind::ArrayIndex, fspace))?;
    Ok((region.ok_or((FaultKind::Unbound, fspace))?, fspace, at & ((1 << ELEMENT_SHIFT) - 1)))
}

/// Every element region of every buffer slot, resolved once per dispatch. A runtime array has
/// as many elements as the bound set gives it (bounded: the executor holds them all).
pub(super) fn binding_regions(prog: &Program, memory: &dyn Memory) -> Vec<Vec<Option<Region>>> {
    const MAX_RESOLVED: u32 = 1 << 20;
    prog.bindings
        .iter()
        .zip(&prog.binding_counts)
        .map(|(&(s, b), &n)| {
            let n = if n == 0 { memory.binding_count(s, b).min(MAX_RESOLVED) } else { n };
            (0..n).map(|e| memory.binding_element(s, b, e)).collect()
        })
        .collect()
}

/// Per binding slot, the host address and length of a single descriptor's region when the
/// memory lets native code reach it directly (`Memory::host_span`), else [0, 0]: an array's
/// elements, and everything else, take the checked path.
pub(super) fn host_spans(prog: &Program, memory: &dyn Memory, regions: &[Vec<Option<Region>>]) -> Vec<[u64; 2]> {
    prog.binding_counts
        .iter()
        .zip(regions)
        .map(|(&n, r)| match (n, r.first().copied().flatten()) {
            (1, Some(reg)) => memory.host_span(reg.buffer, reg.offset, reg.len).map_or([0, 0], |at| [at as u64, reg.len]),
            _ => [0, 0],
        })
        .collect()
}

/// The structure address of every element of every acceleration-structure array, resolved
/// once per dispatch (0 for an element with nothing bound: a query on it faults).
pub(super) fn accel_arrays(prog: &Program, memory: &dyn Memory) -> Vec<Vec<u64>> {
    const MAX_RESOLVED: u32 = 1 << 16;
    prog.accel_arrays
        .iter()
        .map(|&((s, b), n)| {
            let n = if n == 0 { memory.binding_count(s, b).min(MAX_RESOLVED) } else { n };
            (0..n).map(|e| memory.acceleration_structure_element(s, b, e).unwrap_or(0)).collect()
        })
        .collect()
}

fn read_le(bytes: &[u8], at: u64, size: usize) -> Option<u64> {
    let at = usize::try_from(at).ok()?;
    bytes.get(at..at.checked_add(size)?)?;
    Some(get_le(bytes, at, size))
}

/// Lane-frame and shared memory: plain bytes owned by this workgroup's thread.
fn local(bytes: &mut [u8], at: u64, size: usize, ty: Sc, acc: Access) -> Option<u64> {
    let old = read_le(bytes, at, size)?;
    let new = match acc {
        Access::Read => return Some(old),
        Access::Write(v) => v,
        Access::Rmw(op, v, cmp) => alu::atomic(op, ty, old, v, cmp),
    };
    put_le(bytes, at as usize, size, new);
    Some(if matches!(acc, Access::Write(_)) { new } else { old })
}

fn device(ctx: &Ctx, buffer: u64, offset: u64, ty: Sc, acc: Access) -> Option<u64> {
    let size = ty.size() as usize;
    match acc {
        Access::Read => {
            let mut w = [0u8; 8];
            ctx.mem.read(buffer, offset, &mut w[..size]).then(|| u64::from_le_bytes(w))
        }
        Access::Write(v) => ctx.mem.write(buffer, offset, &v.to_le_bytes()[..size]).then_some(v),
        Access::Rmw(op, v, cmp) => ctx.mem.atomic(buffer, offset, size, &|old| alu::atomic(op, ty, old, v, cmp)),
    }
}

/// Whether every lane in `mask` accesses `size` bytes inside its lane frame of `fs` bytes.
fn in_frame(at: &[u64; LANES], mask: u32, size: usize, fs: usize) -> bool {
    (0..LANES).all(|l| (mask >> l) & 1 == 0 || at[l].saturating_add(size as u64) <= fs as u64)
}

/// `size` (1, 2, 4 or 8) bytes at `p` as a little-endian value; fixed-size copies, so no
/// library call per lane.
#[inline(always)]
fn get_le(bytes: &[u8], p: usize, size: usize) -> u64 {
    fn get<const N: usize>(bytes: &[u8], p: usize) -> u64 {
        let mut w = [0u8; 8];
        w[..N].copy_from_slice(&bytes[p..p + N]);
        u64::from_le_bytes(w)
    }
    match size {
        4 => get::<4>(bytes, p),
        8 => get::<8>(bytes, p),
        2 => get::<2>(bytes, p),
        _ => get::<1>(bytes, p),
    }
}

/// The low `size` (1, 2, 4 or 8) bytes of `v` at `p`, little-endian.
#[inline(always)]
fn put_le(bytes: &mut [u8], p: usize, size: usize, v: u64) {
    fn put<const N: usize>(bytes: &mut [u8], p: usize, v: u64) {
        bytes[p..p + N].copy_from_slice(&v.to_le_bytes()[..N]);
    }
    match size {
        4 => put::<4>(bytes, p, v),
        8 => put::<8>(bytes, p, v),
        2 => put::<2>(bytes, p, v),
        _ => put::<1>(bytes, p, v),
    }
}

/// Loads from lane frames with every active lane's address in bounds (the common case: local
/// variables of unoptimised SPIR-V) skip the general path. Returns false, having done
/// nothing, otherwise.
fn lane_loads(group: &mut Group, fs: usize, ty: Sc, addr: u32, dst: u32, mask: u32) -> bool {
    let size = ty.size() as usize;
    let at = group.regs[addr as usize];
    if !in_frame(&at, mask, size, fs) {
        return false;
    }
    let mut out = group.regs[dst as usize];
    for (l, o) in out.iter_mut().enumerate() {
        if (mask >> l) & 1 != 0 {
            *o = alu::norm(ty, get_le(&group.frame, l * fs + at[l] as usize, size));
        }
    }
    group.regs[dst as usize] = out;
    true
}

/// Push-constant loads at one address in every active lane (a constant offset, the common
/// case): one read for the group. Anything else takes the per-lane path.
fn push_loads(ctx: &Ctx, group: &mut Group, ty: Sc, addr: u32, dst: u32, mask: u32) -> bool {
    let at = group.regs[addr as usize];
    let first = at[(mask.trailing_zeros() as usize).min(LANES - 1)];
    if (0..LANES).any(|l| (mask >> l) & 1 != 0 && at[l] != first) {
        return false;
    }
    let Some(v) = read_le(ctx.push, first, ty.size() as usize) else {
        return false;
    };
    let v = alu::norm(ty, v);
    let out = &mut group.regs[dst as usize];
    for (l, o) in out.iter_mut().enumerate() {
        *o = if (mask >> l) & 1 != 0 { v } else { *o };
    }
    true
}

/// Stores to lane frames, as `lane_loads` for loads.
fn lane_stores(group: &mut Group, fs: usize, ty: Sc, addr: u32, src: u32, mask: u32) -> bool {
    let size = ty.size() as usize;
    let (at, v) = (group.regs[addr as usize], group.regs[src as usize]);
    if !in_frame(&at, mask, size, fs) {
        return false;
    }
    for l in (0..LANES).filter(|&l| (mask >> l) & 1 != 0) {
        put_le(&mut group.frame, l * fs + at[l] as usize, size, v[l]);
    }
    true
}

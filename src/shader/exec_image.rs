//! Storage-image ops of the lane executor: coordinates checked against the bound view
//! (robustness: a read outside gives zero, a write outside is dropped, both are faults), texels
//! converted between the view's format and the shader's 32-bit components.
use super::exec::{Ctx, Group, Wg};
use super::ir::{Op, Program, Reg, Sc, ELEMENT_SHIFT};
use super::memory::{Fault, FaultKind, FaultSpace, ImageBinding, ImageFormat, Memory};
use super::LANES;

pub(super) fn exec_image(ctx: &Ctx, group: &mut Group, wg: &mut Wg, op: &Op, mask: u32) {
    match *op {
        Op::ImageRead { image, index, ty, n, dst, coord } => {
            for l in (0..LANES).filter(|&l| (mask >> l) & 1 != 0) {
                let e = element(group, index, l);
                let texel = access(ctx, group, wg, (image, e), coord, l, None).unwrap_or([0; 4]);
                let v = decode(view(ctx, image, e).ok().map(|b| b.format), ty, texel);
                for (k, &d) in dst.iter().enumerate().take(n as usize) {
                    group.regs[d as usize][l] = v[k];
                }
            }
        }
        Op::ImageWrite { image, index, ty, coord, src } => {
            for l in (0..LANES).filter(|&l| (mask >> l) & 1 != 0) {
                let v = src.map(|r| group.regs[r as usize][l]);
                let _ = access(ctx, group, wg, (image, element(group, index, l)), coord, l, Some((ty, v)));
            }
        }
        Op::ImageSize { image, index, n, dims, dst } => {
            for l in (0..LANES).filter(|&l| (mask >> l) & 1 != 0) {
                // Querying an unbound image is a fault like any access to it; the size reads zero.
                let e = element(group, index, l);
                let size = match view(ctx, image, e) {
                    Ok(b) => [b.extent[0], b.extent[1], b.extent[2], b.layers],
                    Err((kind, space)) => {
                        fault(wg, group, space, kind, 0, 0, false, l);
                        [0; 4]
                    }
                };
                for k in 0..n as usize {
                    group.regs[dst[k] as usize][l] = size[dims[k] as usize] as u64;
                }
            }
        }
        Op::ImageTexel { image, index, dst, coord } => {
            // Only the address: the atomic that uses it checks the binding and reports faults.
            for l in (0..LANES).filter(|&l| (mask >> l) & 1 != 0) {
                let e = element(group, index, l);
                let c = coord.map(|r| group.regs[r as usize][l] as u32 as i32 as i64);
                let at = view(ctx, image, e).ok().and_then(|b| b.texel_offset(c[0], c[1], c[2], c[3]));
                // Elements past 2^23 are past every array: clamped, they stay past the end.
                let element = (e.min(1 << 23) as u64) << ELEMENT_SHIFT;
                group.regs[dst as usize][l] = element | at.unwrap_or(TEXEL_OUTSIDE);
            }
        }
        _ => {}
    }
}

/// The offset part of a texel pointer whose coordinate is outside the view (or whose element
/// does not resolve): never a texel, so the atomic using it faults.
pub(super) const TEXEL_OUTSIDE: u64 = (1 << ELEMENT_SHIFT) - 1;

/// Lane `l`'s array element (the low 32 bits of the index register, as unsigned: a negative
/// index is past the end).
fn element(group: &Group, index: Reg, l: usize) -> u32 {
    group.regs[index as usize][l] as u32
}

/// The view of element `e` of image slot `image`, or the fault of reaching it (an index past
/// the array, nothing bound). Single images fault in their binding, array elements in theirs.
pub(super) fn view(ctx: &Ctx, image: u16, e: u32) -> Result<ImageBinding, (FaultKind, FaultSpace)> {
    let space = view_space(ctx, image, e);
    let b = ctx.images[image as usize].get(e as usize).ok_or((FaultKind::ArrayIndex, space))?;
    b.ok_or((FaultKind::Unbound, space))
}

/// Every element view of every image slot, resolved once per dispatch (a runtime array has
/// as many as the bound set gives it, bounded).
pub(super) fn image_bindings(prog: &Program, memory: &dyn Memory) -> Vec<Vec<Option<ImageBinding>>> {
    const MAX_RESOLVED: u32 = 1 << 16;
    prog.images
        .iter()
        .zip(&prog.image_counts)
        .map(|(&(s, b), &n)| {
            let n = if n == 0 { memory.binding_count(s, b).min(MAX_RESOLVED) } else { n };
            (0..n).map(|e| memory.image_element(s, b, e)).collect()
        })
        .collect()
}

/// Reads (write = None) or writes one lane's texel of (slot, element): the raw texel as four
/// 32-bit words, or None after recording a fault.
fn access(ctx: &Ctx, group: &Group, wg: &mut Wg, (image, e): (u16, u32), coord: [Reg; 4], l: usize, write: Option<(Sc, [u64; 4])>) -> Option<[u32; 4]> {
    let c = coord.map(|r| group.regs[r as usize][l] as u32 as i32 as i64);
    let b = match view(ctx, image, e) {
        Ok(b) => b,
        Err((kind, space)) => {
            fault(wg, group, space, kind, 0, 0, write.is_some(), l);
            return None;
        }
    };
    let space = view_space(ctx, image, e);
    let len = b.format.texel_size();
    let Some(at) = b.texel_offset(c[0], c[1], c[2], c[3]) else {
        // Where the texel would be, for the report (coordinates may be negative).
        let pitches = [b.format.texel_size() as u64, b.row_pitch, b.slice_pitch, b.layer_pitch];
        let would = c.iter().zip(pitches).fold(0u64, |acc, (&v, p)| acc.wrapping_add((v as u64).wrapping_mul(p)));
        fault(wg, group, space, FaultKind::OutOfBounds, would, len, write.is_some(), l);
        return None;
    };
    let size = len as usize;
    let mut bytes = [0u8; 16];
    let ok = match write {
        None => ctx.mem.read(b.buffer, b.offset.wrapping_add(at), &mut bytes[..size]),
        Some((ty, v)) => {
            encode(b.format, ty, v, &mut bytes);
            ctx.mem.write(b.buffer, b.offset.wrapping_add(at), &bytes[..size])
        }
    };
    if !ok {
        fault(wg, group, space, FaultKind::Refused, at, len, write.is_some(), l);
        return None;
    }
    Some(std::array::from_fn(|k| u32::from_le_bytes([bytes[4 * k], bytes[4 * k + 1], bytes[4 * k + 2], bytes[4 * k + 3]])))
}

/// The fault space naming element `e` of slot `image` (its binding for a single image).
pub(super) fn view_space(ctx: &Ctx, image: u16, e: u32) -> FaultSpace {
    let (set, binding) = ctx.prog.images[image as usize];
    if ctx.prog.image_counts[image as usize] == 1 {
        FaultSpace::Binding { set, binding }
    } else {
        FaultSpace::ArrayElement { set, binding, element: e }
    }
}

#[allow(clippy::too_many_arguments)] // one fault record: every field is needed
fn fault(wg: &mut Wg, group: &Group, space: FaultSpace, kind: FaultKind, at: u64, len: u32, write: bool, l: usize) {
    wg.fault_count += 1;
    if wg.faults.len() < 16 {
        let invocation = group.index * LANES as u32 + l as u32;
        wg.faults.push(Fault { kind, space, at, len, write, workgroup: wg.id, invocation });
    }
}

/// The raw texel (as stored) → four register values of type `ty`. Single-channel formats
/// give (r, 0, 0, 1), as the spec's texel-input conversion says. A read of an unbound or
/// faulting texel decodes zero bytes, i.e. reads zero.
pub(super) fn decode(format: Option<ImageFormat>, ty: Sc, raw: [u32; 4]) -> [u64; 4] {
    let one = if ty == Sc::F32 { 1f32.to_bits() } else { 1 } as u64;
    match format {
        None => [0; 4],
        Some(ImageFormat::R32Uint | ImageFormat::R32Sint | ImageFormat::R32Sfloat) => [raw[0] as u64, 0, 0, one],
        Some(ImageFormat::Rgba8Unorm) => {
            let b = raw[0].to_le_bytes();
            b.map(|c| (c as f32 / 255.0).to_bits() as u64)
        }
        Some(_) => raw.map(|w| w as u64),
    }
}

/// Four register values of type `ty` → the texel's bytes in `format` (first 4 or 16 bytes).
pub(super) fn encode(format: ImageFormat, _ty: Sc, v: [u64; 4], out: &mut [u8; 16]) {
    match format {
        ImageFormat::R32Uint | ImageFormat::R32Sint | ImageFormat::R32Sfloat => out[..4].copy_from_slice(&(v[0] as u32).to_le_bytes()),
        ImageFormat::Rgba8Unorm => {
            for k in 0..4 {
                // NaN becomes 0 (clamp of NaN is undefined; zero is the common choice).
                let f = f32::from_bits(v[k] as u32);
                let f = if f.is_nan() { 0.0 } else { f.clamp(0.0, 1.0) };
                out[k] = (f * 255.0).round() as u8;
            }
        }
        _ => {
            for k in 0..4 {
                out[4 * k..4 * k + 4].copy_from_slice(&(v[k] as u32).to_le_bytes());
            }
        }
    }
}

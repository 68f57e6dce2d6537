//! The executor's 32-bit float arms: one call per instruction over the whole lane group, the
//! lanes read into an `[f32; LANES]`, computed together (lanes outside the mask too: cheaper
//! than branching, and their results are discarded) and written back under the mask.
//!
//! Results are the bits `alu` gives for the same op, lane by lane: the arithmetic ops round
//! the same way in f32 as through f64 (innocuous double rounding), and the GLSL.std.450
//! functions are `vmath`'s in both places.
use super::exec::{store_lanes, Regs};
use super::ir::{BinOp, TriOp, UnOp};
use super::{vmath, LANES};

#[inline(always)]
fn f32s(r: &Regs) -> [f32; LANES] {
    // Loops, not `array::from_fn`, whose closure was not always inlined.
    let mut v = [0.0; LANES];
    for (o, &w) in v.iter_mut().zip(r) {
        *o = f32::from_bits(w as u32);
    }
    v
}

#[inline(always)]
fn store(regs: &mut [Regs], dst: u32, mask: u32, v: [f32; LANES]) {
    let mut w = [0; LANES];
    for (o, x) in w.iter_mut().zip(v) {
        *o = x.to_bits() as u64;
    }
    store_lanes(regs, dst, mask, w);
}

#[inline(always)]
fn each(a: &Regs, b: &Regs, f: impl Fn(f32, f32) -> f32) -> [f32; LANES] {
    let mut v = [0.0; LANES];
    for ((o, &x), &y) in v.iter_mut().zip(a).zip(b) {
        *o = f(f32::from_bits(x as u32), f32::from_bits(y as u32));
    }
    v
}

/// One-operand F32 ops; false when `op` is not one of them. Operands are read from the
/// register file in place.
pub(super) fn un(regs: &mut [Regs], op: UnOp, dst: u32, mask: u32, a: u32) -> bool {
    let f: fn(&[f32; LANES]) -> [f32; LANES] = match op {
        UnOp::Sin => vmath::sin,
        UnOp::Cos => vmath::cos,
        UnOp::Tan => vmath::tan,
        UnOp::Exp => vmath::exp,
        UnOp::Exp2 => vmath::exp2,
        UnOp::Log => vmath::log,
        UnOp::Log2 => vmath::log2,
        UnOp::Sqrt => vmath::sqrt,
        UnOp::InverseSqrt => vmath::inverse_sqrt,
        UnOp::Atan => vmath::atan,
        _ => return false,
    };
    let v = f(&f32s(&regs[a as usize]));
    store(regs, dst, mask, v);
    true
}

/// Two-operand F32 ops with a float result; false for the others (decided before any lane is
/// read).
pub(super) fn bin(regs: &mut [Regs], op: BinOp, dst: u32, mask: u32, a: u32, b: u32) -> bool {
    let (x, y) = (&regs[a as usize], &regs[b as usize]);
    let v = match op {
        BinOp::FAdd => each(x, y, |x, y| x + y),
        BinOp::FSub => each(x, y, |x, y| x - y),
        BinOp::FMul => each(x, y, |x, y| x * y),
        BinOp::FDiv => each(x, y, |x, y| x / y),
        BinOp::Pow => vmath::pow(&f32s(x), &f32s(y)),
        BinOp::Atan2 => vmath::atan2(&f32s(x), &f32s(y)),
        _ => return false,
    };
    store(regs, dst, mask, v);
    true
}

/// Three-operand F32 ops: the fused multiply-add.
// The op's operands, as `bin`'s; one call site.
#[allow(clippy::too_many_arguments)]
pub(super) fn tri(regs: &mut [Regs], op: TriOp, dst: u32, mask: u32, a: u32, b: u32, c: u32) -> bool {
    if op != TriOp::Fma {
        return false;
    }
    let v = vmath::fma(&f32s(&regs[a as usize]), &f32s(&regs[b as usize]), &f32s(&regs[c as usize]));
    store(regs, dst, mask, v);
    true
}

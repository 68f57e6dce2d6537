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
fn each(a: &[f32; LANES], b: &[f32; LANES], f: impl Fn(f32, f32) -> f32) -> [f32; LANES] {
    let mut v = [0.0; LANES];
    for ((o, &x), &y) in v.iter_mut().zip(a).zip(b) {
        *o = f(x, y);
    }
    v
}

/// One-operand F32 ops; false when `op` is not one of them.
pub(super) fn un(regs: &mut [Regs], op: UnOp, dst: u32, mask: u32, a: &Regs) -> bool {
    let x = f32s(a);
    let v = match op {
        UnOp::Sin => vmath::sin(&x),
        UnOp::Cos => vmath::cos(&x),
        UnOp::Tan => vmath::tan(&x),
        UnOp::Exp => vmath::exp(&x),
        UnOp::Exp2 => vmath::exp2(&x),
        UnOp::Log => vmath::log(&x),
        UnOp::Log2 => vmath::log2(&x),
        UnOp::Sqrt => vmath::sqrt(&x),
        UnOp::InverseSqrt => vmath::inverse_sqrt(&x),
        UnOp::Atan => vmath::atan(&x),
        _ => return false,
    };
    store(regs, dst, mask, v);
    true
}

/// Two-operand F32 ops with a float result; false for the others.
pub(super) fn bin(regs: &mut [Regs], op: BinOp, dst: u32, mask: u32, a: &Regs, b: &Regs) -> bool {
    let (x, y) = (f32s(a), f32s(b));
    let v = match op {
        BinOp::FAdd => each(&x, &y, |x, y| x + y),
        BinOp::FSub => each(&x, &y, |x, y| x - y),
        BinOp::FMul => each(&x, &y, |x, y| x * y),
        BinOp::FDiv => each(&x, &y, |x, y| x / y),
        BinOp::Pow => vmath::pow(&x, &y),
        BinOp::Atan2 => vmath::atan2(&x, &y),
        _ => return false,
    };
    store(regs, dst, mask, v);
    true
}

/// Three-operand F32 ops: the fused multiply-add.
// The op's operands, as `bin`'s; one call site.
#[allow(clippy::too_many_arguments)]
pub(super) fn tri(regs: &mut [Regs], op: TriOp, dst: u32, mask: u32, a: &Regs, b: &Regs, c: &Regs) -> bool {
    if op != TriOp::Fma {
        return false;
    }
    store(regs, dst, mask, vmath::fma(&f32s(a), &f32s(b), &f32s(c)));
    true
}

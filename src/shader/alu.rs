//! Scalar semantics of the IR's ALU ops on register words, shared by the lane executor and by
//! the specialization-constant folder (OpSpecConstantOp), so the two cannot disagree.
//!
//! Integer ops wrap; division by zero gives 0 and shifts by at least the width give 0 (the
//! results SPIR-V leaves undefined, made deterministic). Float ops follow IEEE-754 through
//! Rust's `f32`/`f64`. GLSL.std.450's imprecise functions are `vmath`'s for 32-bit floats (the
//! executor's lane-array forms give the same bits) and the host's libm for 64-bit ones.
use super::ir::{AtomicOp, BinOp, Sc, TriOp, UnOp};
use super::vmath;

/// Keeps only the bits of `ty` (upper bits of 32-bit values are zero by invariant).
#[inline(always)]
pub fn norm(ty: Sc, v: u64) -> u64 {
    match ty {
        Sc::Bool => (v != 0) as u64,
        Sc::I32 | Sc::F32 => v & 0xFFFF_FFFF,
        Sc::I64 | Sc::F64 => v,
    }
}

#[inline(always)]
fn sext(ty: Sc, v: u64) -> i64 {
    match ty {
        Sc::I32 | Sc::F32 => v as u32 as i32 as i64,
        Sc::Bool => v as i64,
        _ => v as i64,
    }
}

#[inline(always)]
pub fn f(ty: Sc, v: u64) -> f64 {
    match ty {
        Sc::F32 => f32::from_bits(v as u32) as f64,
        _ => f64::from_bits(v),
    }
}

#[inline(always)]
pub fn from_f(ty: Sc, x: f64) -> u64 {
    match ty {
        Sc::F32 => (x as f32).to_bits() as u64,
        _ => x.to_bits(),
    }
}

/// f32 arithmetic must round to f32 after every op; computing in f64 then rounding is exact
/// for +, -, *, / and sqrt (double rounding is innocuous for these at 53 ≥ 2·24+2 bits).
#[inline(always)]
fn fbin(ty: Sc, a: u64, b: u64, op: impl Fn(f64, f64) -> f64) -> u64 {
    from_f(ty, op(f(ty, a), f(ty, b)))
}

#[inline(always)]
fn fun(ty: Sc, a: u64, op: impl Fn(f64) -> f64) -> u64 {
    from_f(ty, op(f(ty, a)))
}

/// A GLSL.std.450 function: `narrow` (vmath) for F32, `wide` (libm) for F64.
#[inline(always)]
fn glsl(ty: Sc, a: u64, wide: impl Fn(f64) -> f64, narrow: impl Fn(f32) -> f32) -> u64 {
    match ty {
        Sc::F32 => narrow(f32::from_bits(a as u32)).to_bits() as u64,
        _ => from_f(ty, wide(f(ty, a))),
    }
}

/// Two-operand GLSL.std.450 functions, as [`glsl`].
#[inline(always)]
fn glsl2(ty: Sc, a: u64, b: u64, wide: impl Fn(f64, f64) -> f64, narrow: impl Fn(f32, f32) -> f32) -> u64 {
    match ty {
        Sc::F32 => narrow(f32::from_bits(a as u32), f32::from_bits(b as u32)).to_bits() as u64,
        _ => fbin(ty, a, b, wide),
    }
}

#[inline(always)]
fn shift_amount(ty: Sc, b: u64) -> Option<u32> {
    let s = b as u32;
    (s < ty.bits()).then_some(s)
}

#[inline(always)]
pub fn bin(op: BinOp, ty: Sc, a: u64, b: u64) -> u64 {
    use BinOp::*;
    let bits = ty.bits();
    let r = match op {
        IAdd => a.wrapping_add(b),
        ISub => a.wrapping_sub(b),
        IMul => a.wrapping_mul(b),
        UDiv => norm(ty, a).checked_div(norm(ty, b)).unwrap_or(0),
        UMod => norm(ty, a).checked_rem(norm(ty, b)).unwrap_or(0),
        SDiv => sext(ty, a).checked_div(sext(ty, b)).unwrap_or(0) as u64,
        SRem => sext(ty, a).checked_rem(sext(ty, b)).unwrap_or(0) as u64,
        SMod => {
            let (x, y) = (sext(ty, a), sext(ty, b));
            match x.checked_rem(y) {
                Some(r) if r != 0 && ((r < 0) != (y < 0)) => (r + y) as u64,
                Some(r) => r as u64,
                None => 0,
            }
        }
        Shl => shift_amount(ty, b).map_or(0, |s| a << s),
        ShrL => shift_amount(ty, b).map_or(0, |s| norm(ty, a) >> s),
        ShrA => {
            let s = shift_amount(ty, b).unwrap_or(bits - 1);
            (sext(ty, a) >> s) as u64
        }
        And => a & b,
        Or => a | b,
        Xor => a ^ b,
        IEq | LEq => (norm(ty, a) == norm(ty, b)) as u64,
        INe | LNe => (norm(ty, a) != norm(ty, b)) as u64,
        ULt => (norm(ty, a) < norm(ty, b)) as u64,
        ULe => (norm(ty, a) <= norm(ty, b)) as u64,
        UGt => (norm(ty, a) > norm(ty, b)) as u64,
        UGe => (norm(ty, a) >= norm(ty, b)) as u64,
        SLt => (sext(ty, a) < sext(ty, b)) as u64,
        SLe => (sext(ty, a) <= sext(ty, b)) as u64,
        SGt => (sext(ty, a) > sext(ty, b)) as u64,
        SGe => (sext(ty, a) >= sext(ty, b)) as u64,
        LAnd => ((a != 0) && (b != 0)) as u64,
        LOr => ((a != 0) || (b != 0)) as u64,
        UMin => norm(ty, a).min(norm(ty, b)),
        UMax => norm(ty, a).max(norm(ty, b)),
        SMin => sext(ty, a).min(sext(ty, b)) as u64,
        SMax => sext(ty, a).max(sext(ty, b)) as u64,
        UMulHi => {
            let p = (norm(ty, a) as u128) * (norm(ty, b) as u128);
            (p >> bits) as u64
        }
        SMulHi => {
            let p = (sext(ty, a) as i128) * (sext(ty, b) as i128);
            (p >> bits) as u64
        }
        AddCarry => {
            let s = (norm(ty, a) as u128) + (norm(ty, b) as u128);
            (s >> bits) as u64 & 1
        }
        SubBorrow => (norm(ty, a) < norm(ty, b)) as u64,
        _ => return fbin_op(op, ty, a, b),
    };
    norm(if op_is_compare(op) { Sc::Bool } else { ty }, r)
}

/// True for ops whose result is a Bool whatever the operand type.
#[inline(always)]
pub fn op_is_compare(op: BinOp) -> bool {
    use BinOp::*;
    matches!(
        op,
        IEq | INe | ULt | ULe | UGt | UGe | SLt | SLe | SGt | SGe | FOrdEq | FOrdNe | FOrdLt
            | FOrdLe | FOrdGt | FOrdGe | FUnordEq | FUnordNe | FUnordLt | FUnordLe | FUnordGt
            | FUnordGe | LEq | LNe | LAnd | LOr
    )
}

#[inline(always)]
fn fbin_op(op: BinOp, ty: Sc, a: u64, b: u64) -> u64 {
    use BinOp::*;
    let (x, y) = (f(ty, a), f(ty, b));
    let unord = x.is_nan() || y.is_nan();
    let cmp = |c: bool, u: bool| (if unord { u } else { c }) as u64;
    match op {
        FAdd => fbin(ty, a, b, |x, y| x + y),
        FSub => fbin(ty, a, b, |x, y| x - y),
        FMul => fbin(ty, a, b, |x, y| x * y),
        FDiv => fbin(ty, a, b, |x, y| x / y),
        // OpFRem: sign of the dividend (C fmod); OpFMod: sign of the divisor (GLSL mod).
        FRem => fbin(ty, a, b, |x, y| x % y),
        FMod => fbin(ty, a, b, |x, y| x - y * (x / y).floor()),
        FOrdEq => cmp(x == y, false),
        FOrdNe => cmp(x != y, false),
        FOrdLt => cmp(x < y, false),
        FOrdLe => cmp(x <= y, false),
        FOrdGt => cmp(x > y, false),
        FOrdGe => cmp(x >= y, false),
        FUnordEq => cmp(x == y, true),
        FUnordNe => cmp(x != y, true),
        FUnordLt => cmp(x < y, true),
        FUnordLe => cmp(x <= y, true),
        FUnordGt => cmp(x > y, true),
        FUnordGe => cmp(x >= y, true),
        FMin | NMin => fbin(ty, a, b, |x, y| x.min(y)),
        FMax | NMax => fbin(ty, a, b, |x, y| x.max(y)),
        Pow => glsl2(ty, a, b, f64::powf, vmath::pow1),
        Atan2 => glsl2(ty, a, b, f64::atan2, vmath::atan2_1),
        Step => fbin(ty, a, b, |edge, x| if x < edge { 0.0 } else { 1.0 }),
        Ldexp => from_f(ty, x * 2f64.powi(sext(Sc::I32, b) as i32)),
        _ => 0,
    }
}

#[inline(always)]
pub fn un(op: UnOp, ty: Sc, from: Sc, a: u64) -> u64 {
    use UnOp::*;
    let r = match op {
        SNeg => 0u64.wrapping_sub(a),
        FNeg => fun(ty, a, |x| -x),
        Not => !a,
        LNot => (a == 0) as u64,
        Bitcast | UConvert => norm(from, a),
        SConvert => sext(from, a) as u64,
        FConvert => from_f(ty, f(from, a)),
        ConvertFToU => from_f_to_int(ty, f(from, a), false),
        ConvertFToS => from_f_to_int(ty, f(from, a), true),
        ConvertUToF => u_to_f(ty, from, a),
        ConvertSToF => s_to_f(ty, sext(from, a)),
        IsNan => f(from, a).is_nan() as u64,
        IsInf => f(from, a).is_infinite() as u64,
        FAbs => fun(ty, a, f64::abs),
        SAbs => sext(ty, a).wrapping_abs() as u64,
        FSign => fun(ty, a, |x| if x > 0.0 { 1.0 } else if x < 0.0 { -1.0 } else { x }),
        SSign => sext(ty, a).signum() as u64,
        Floor => fun(ty, a, f64::floor),
        Ceil => fun(ty, a, f64::ceil),
        Trunc => fun(ty, a, f64::trunc),
        Round => fun(ty, a, f64::round),
        RoundEven => fun(ty, a, f64::round_ties_even),
        Fract => fun(ty, a, |x| x - x.floor()),
        Sqrt => fun(ty, a, f64::sqrt),
        InverseSqrt => glsl(ty, a, |x| 1.0 / x.sqrt(), vmath::inverse_sqrt1),
        Exp => glsl(ty, a, f64::exp, vmath::exp1),
        Log => glsl(ty, a, f64::ln, vmath::log1),
        Exp2 => glsl(ty, a, f64::exp2, vmath::exp2_1),
        Log2 => glsl(ty, a, f64::log2, vmath::log2_1),
        Sin => glsl(ty, a, f64::sin, vmath::sin1),
        Cos => glsl(ty, a, f64::cos, vmath::cos1),
        Tan => glsl(ty, a, f64::tan, vmath::tan1),
        Asin => fun(ty, a, f64::asin),
        Acos => fun(ty, a, f64::acos),
        Atan => glsl(ty, a, f64::atan, vmath::atan1),
        Sinh => fun(ty, a, f64::sinh),
        Cosh => fun(ty, a, f64::cosh),
        Tanh => fun(ty, a, f64::tanh),
        Asinh => fun(ty, a, f64::asinh),
        Acosh => fun(ty, a, f64::acosh),
        Atanh => fun(ty, a, f64::atanh),
        Radians => fun(ty, a, f64::to_radians),
        Degrees => fun(ty, a, f64::to_degrees),
        FindILsb => {
            let v = norm(from, a);
            if v == 0 { u64::MAX } else { v.trailing_zeros() as u64 }
        }
        FindUMsb => {
            let v = norm(from, a);
            if v == 0 { u64::MAX } else { 63 - v.leading_zeros() as u64 }
        }
        FindSMsb => {
            let v = sext(from, a);
            let v = if v < 0 { !v } else { v } as u64;
            if v == 0 { u64::MAX } else { 63 - v.leading_zeros() as u64 }
        }
        BitCount => norm(from, a).count_ones() as u64,
        BitReverse => norm(ty, a).reverse_bits() >> (64 - ty.bits()),
    };
    norm(ty, r)
}

fn u_to_f(ty: Sc, from: Sc, a: u64) -> u64 {
    // u64 → f32 must round once, not through f64.
    match ty {
        Sc::F32 => (norm(from, a) as f32).to_bits() as u64,
        _ => (norm(from, a) as f64).to_bits(),
    }
}

fn s_to_f(ty: Sc, v: i64) -> u64 {
    match ty {
        Sc::F32 => (v as f32).to_bits() as u64,
        _ => (v as f64).to_bits(),
    }
}

/// Float → integer: truncation, saturating (Rust's `as`), NaN → 0; the out-of-range results
/// SPIR-V leaves undefined.
fn from_f_to_int(ty: Sc, x: f64, signed: bool) -> u64 {
    match (ty, signed) {
        (Sc::I32, false) => x as u32 as u64,
        (Sc::I32, true) => x as i32 as u32 as u64,
        (_, false) => x as u64,
        (_, true) => x as i64 as u64,
    }
}

pub fn tri(op: TriOp, ty: Sc, a: u64, b: u64, c: u64) -> u64 {
    use TriOp::*;
    let r = match op {
        Fma => from_f(ty, fma(ty, f(ty, a), f(ty, b), f(ty, c))),
        FClamp | NClamp => from_f(ty, f(ty, a).max(f(ty, b)).min(f(ty, c))),
        UClamp => norm(ty, a).max(norm(ty, b)).min(norm(ty, c)),
        SClamp => sext(ty, a).max(sext(ty, b)).min(sext(ty, c)) as u64,
        FMix => {
            let (x, y, t) = (f(ty, a), f(ty, b), f(ty, c));
            from_f(ty, x * (1.0 - t) + y * t)
        }
        SmoothStep => {
            let (e0, e1, x) = (f(ty, a), f(ty, b), f(ty, c));
            let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
            from_f(ty, t * t * (3.0 - 2.0 * t))
        }
        BitFieldUExtract | BitFieldSExtract => {
            let (off, count) = (b as u32, c as u32);
            if count == 0 || off >= ty.bits() || off + count > ty.bits() {
                0
            } else {
                let v = norm(ty, a) >> off;
                let v = if count >= 64 { v } else { v & ((1u64 << count) - 1) };
                if op == BitFieldSExtract && count < 64 && (v >> (count - 1)) & 1 == 1 {
                    v | (!0u64 << count)
                } else {
                    v
                }
            }
        }
    };
    norm(ty, r)
}

fn fma(ty: Sc, a: f64, b: f64, c: f64) -> f64 {
    match ty {
        Sc::F32 => vmath::fma1(a as f32, b as f32, c as f32) as f64,
        _ => a.mul_add(b, c),
    }
}

pub fn bit_insert(ty: Sc, base: u64, insert: u64, offset: u64, count: u64) -> u64 {
    let (off, count) = (offset as u32, count as u32);
    if count == 0 || off >= ty.bits() || off + count > ty.bits() {
        return norm(ty, base);
    }
    let field = if count >= 64 { !0u64 } else { (1u64 << count) - 1 } << off;
    norm(ty, (base & !field) | ((insert << off) & field))
}

/// The new value an atomic RMW stores, given the old one.
pub fn atomic(op: AtomicOp, ty: Sc, old: u64, value: u64, comparator: u64) -> u64 {
    use AtomicOp::*;
    let r = match op {
        Exchange => value,
        CompareExchange => {
            if norm(ty, old) == norm(ty, comparator) { value } else { old }
        }
        IAdd => old.wrapping_add(value),
        ISub => old.wrapping_sub(value),
        SMin => bin(BinOp::SMin, ty, old, value),
        SMax => bin(BinOp::SMax, ty, old, value),
        UMin => bin(BinOp::UMin, ty, old, value),
        UMax => bin(BinOp::UMax, ty, old, value),
        And => old & value,
        Or => old | value,
        Xor => old ^ value,
    };
    norm(ty, r)
}

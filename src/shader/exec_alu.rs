//! The executor's ALU arms: one call per instruction over the whole lane group.
//!
//! Operands are read in place from the register file (no copies into temporaries), every lane
//! is computed (lanes outside the mask too: cheaper than branching, their results are
//! discarded) into one lane array, and that array is stored to the destination — whole when
//! every lane is active, else blended under the mask. The op (and type) is matched once per
//! instruction, outside the lane loop, so each arm's loop is straight-line code over
//! fixed-size arrays that LLVM unrolls and vectorises without bounds checks.
//!
//! Results are the bits `alu`'s scalar functions give for the same op, lane by lane: the
//! 32-bit integer arms below are those functions with the type fixed, and the generic arms
//! call them with constant op and type.
use super::alu;
use super::exec::{store_lanes, Regs};
use super::ir::{BinOp, Sc, TriOp, UnOp};
use super::LANES;

/// dst = f(a) lane by lane.
#[inline(always)]
pub(super) fn map1(regs: &mut [Regs], dst: u32, mask: u32, a: u32, f: impl Fn(u64) -> u64) {
    let x = &regs[a as usize];
    let mut v = [0; LANES];
    for (o, &x) in v.iter_mut().zip(x) {
        *o = f(x);
    }
    store_lanes(regs, dst, mask, v);
}

/// dst = f(a, b) lane by lane.
#[inline(always)]
pub(super) fn map2(regs: &mut [Regs], dst: u32, mask: u32, a: u32, b: u32, f: impl Fn(u64, u64) -> u64) {
    let (x, y) = (&regs[a as usize], &regs[b as usize]);
    let mut v = [0; LANES];
    for ((o, &x), &y) in v.iter_mut().zip(x).zip(y) {
        *o = f(x, y);
    }
    store_lanes(regs, dst, mask, v);
}

/// dst = f(a, b, c) lane by lane.
// The op's operands; the closure is the op.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn map3(regs: &mut [Regs], dst: u32, mask: u32, a: u32, b: u32, c: u32, f: impl Fn(u64, u64, u64) -> u64) {
    let (x, y, z) = (&regs[a as usize], &regs[b as usize], &regs[c as usize]);
    let mut v = [0; LANES];
    for (((o, &x), &y), &z) in v.iter_mut().zip(x).zip(y).zip(z) {
        *o = f(x, y, z);
    }
    store_lanes(regs, dst, mask, v);
}

/// Expands to a match whose arms call `alu` with constant op and type, so each arm's lane
/// loop is specialised (and can vectorise) instead of dispatching per lane.
macro_rules! specialised {
    (($op:ident, $ty:ident): $Op:ident, [$(($o:ident, $t:ident)),* $(,)?], $body:expr) => {
        match ($op, $ty) {
            $( ($Op::$o, Sc::$t) => {
                let ($op, $ty) = ($Op::$o, Sc::$t);
                $body
            } )*
            _ => $body,
        }
    };
}

/// Two-operand ops: 32-bit integers and 32-bit floats first, then the other common (op, type)
/// pairs with their own loops, the rest through `alu::bin` per lane.
pub(super) fn exec_bin(regs: &mut [Regs], op: BinOp, ty: Sc, dst: u32, mask: u32, a: u32, b: u32) {
    match ty {
        Sc::I32 => bin_i32(regs, op, dst, mask, a, b),
        Sc::F32 if super::exec_float::bin(regs, op, dst, mask, a, b) => {}
        _ => bin_other(regs, op, ty, dst, mask, a, b),
    }
}

/// The binary ops without a written-out loop of their own.
#[inline(never)]
fn bin_other(regs: &mut [Regs], op: BinOp, ty: Sc, dst: u32, mask: u32, a: u32, b: u32) {
    specialised!((op, ty): BinOp, [
        (UDiv, I32), (UMod, I32),
        (IAdd, I64), (ISub, I64), (IMul, I64), (Shl, I64), (ShrL, I64), (And, I64), (Or, I64),
        (Xor, I64), (FOrdLt, F32), (FOrdLe, F32), (FOrdGt, F32), (FOrdGe, F32), (FOrdEq, F32),
        (FMin, F32), (FMax, F32), (FAdd, F64), (FSub, F64), (FMul, F64), (FDiv, F64),
        (LAnd, Bool), (LOr, Bool), (LEq, Bool), (LNe, Bool),
    ], map2(regs, dst, mask, a, b, |x, y| alu::bin(op, ty, x, y)))
}

/// The low 32 bits of a register word.
const LO: u64 = 0xFFFF_FFFF;

/// A 32-bit value's word read unsigned / signed.
#[inline(always)]
fn u(v: u64) -> u32 {
    v as u32
}
#[inline(always)]
fn s(v: u64) -> i32 {
    v as u32 as i32
}

/// 32-bit integer ops written out: `alu::bin` with the type fixed to `Sc::I32` (values read
/// through their low 32 bits, results with the upper bits zero); the others go to `bin_other`.
fn bin_i32(regs: &mut [Regs], op: BinOp, dst: u32, mask: u32, a: u32, b: u32) {
    use BinOp::*;
    match op {
        IAdd => map2(regs, dst, mask, a, b, |x, y| x.wrapping_add(y) & LO),
        ISub => map2(regs, dst, mask, a, b, |x, y| x.wrapping_sub(y) & LO),
        IMul => map2(regs, dst, mask, a, b, |x, y| u(x).wrapping_mul(u(y)) as u64),
        Shl => map2(regs, dst, mask, a, b, |x, y| if u(y) < 32 { (x << u(y)) & LO } else { 0 }),
        ShrL => map2(regs, dst, mask, a, b, |x, y| if u(y) < 32 { (x & LO) >> u(y) } else { 0 }),
        ShrA => map2(regs, dst, mask, a, b, |x, y| (s(x) >> u(y).min(31)) as u32 as u64),
        And => map2(regs, dst, mask, a, b, |x, y| x & y & LO),
        Or => map2(regs, dst, mask, a, b, |x, y| (x | y) & LO),
        Xor => map2(regs, dst, mask, a, b, |x, y| (x ^ y) & LO),
        IEq => map2(regs, dst, mask, a, b, |x, y| (u(x) == u(y)) as u64),
        INe => map2(regs, dst, mask, a, b, |x, y| (u(x) != u(y)) as u64),
        ULt => map2(regs, dst, mask, a, b, |x, y| (u(x) < u(y)) as u64),
        ULe => map2(regs, dst, mask, a, b, |x, y| (u(x) <= u(y)) as u64),
        UGt => map2(regs, dst, mask, a, b, |x, y| (u(x) > u(y)) as u64),
        UGe => map2(regs, dst, mask, a, b, |x, y| (u(x) >= u(y)) as u64),
        SLt => map2(regs, dst, mask, a, b, |x, y| (s(x) < s(y)) as u64),
        SLe => map2(regs, dst, mask, a, b, |x, y| (s(x) <= s(y)) as u64),
        SGt => map2(regs, dst, mask, a, b, |x, y| (s(x) > s(y)) as u64),
        SGe => map2(regs, dst, mask, a, b, |x, y| (s(x) >= s(y)) as u64),
        UMin => map2(regs, dst, mask, a, b, |x, y| u(x).min(u(y)) as u64),
        UMax => map2(regs, dst, mask, a, b, |x, y| u(x).max(u(y)) as u64),
        SMin => map2(regs, dst, mask, a, b, |x, y| s(x).min(s(y)) as u32 as u64),
        SMax => map2(regs, dst, mask, a, b, |x, y| s(x).max(s(y)) as u32 as u64),
        _ => bin_other(regs, op, Sc::I32, dst, mask, a, b),
    }
}

/// Three-operand ops: fused multiply-add and clamps get their own loops.
// The op's operands, as exec_bin's; one call site.
#[allow(clippy::too_many_arguments)]
pub(super) fn exec_tri(regs: &mut [Regs], op: TriOp, ty: Sc, dst: u32, mask: u32, a: u32, b: u32, c: u32) {
    if ty == Sc::F32 && super::exec_float::tri(regs, op, dst, mask, a, b, c) {
        return;
    }
    specialised!((op, ty): TriOp, [
        (FClamp, F32), (NClamp, F32), (UClamp, I32), (SClamp, I32), (FMix, F32), (Fma, F64),
    ], map3(regs, dst, mask, a, b, c, |x, y, z| alu::tri(op, ty, x, y, z)))
}

/// Unary ops: the F32 float functions go to `exec_float`; conversions and other common ops get
/// their own loops.
// The op's operands, as exec_bin's; one call site.
#[allow(clippy::too_many_arguments)]
pub(super) fn exec_un(regs: &mut [Regs], op: UnOp, ty: Sc, from: Sc, dst: u32, mask: u32, a: u32) {
    if ty == Sc::F32 && super::exec_float::un(regs, op, dst, mask, a) {
        return;
    }
    if let Some(()) = un_i32(regs, op, ty, from, dst, mask, a) {
        return;
    }
    specialised!((op, ty): UnOp, [
        (ConvertUToF, F32), (ConvertSToF, F32), (ConvertFToU, I32), (ConvertFToS, I32),
        (Bitcast, F32), (UConvert, I64), (SConvert, I64),
        (FNeg, F32), (FAbs, F32), (Floor, F32), (Fract, F32),
    ], map1(regs, dst, mask, a, |x| alu::un(op, ty, from, x)))
}

/// The common one-operand ops on 32-bit integers and Bools, written out as `bin_i32`.
// The op's operands, as exec_bin's; one call site.
#[allow(clippy::too_many_arguments)]
fn un_i32(regs: &mut [Regs], op: UnOp, ty: Sc, from: Sc, dst: u32, mask: u32, a: u32) -> Option<()> {
    match (op, ty, from) {
        // Same-width bitcasts and 64 → 32-bit truncations keep the low 32 bits.
        (UnOp::Bitcast | UnOp::UConvert, Sc::I32, Sc::I32 | Sc::F32 | Sc::I64) => map1(regs, dst, mask, a, |x| x & LO),
        (UnOp::SConvert, Sc::I32, Sc::I32 | Sc::I64) => map1(regs, dst, mask, a, |x| x & LO),
        (UnOp::SNeg, Sc::I32, _) => map1(regs, dst, mask, a, |x| 0u64.wrapping_sub(x) & LO),
        (UnOp::Not, Sc::I32, _) => map1(regs, dst, mask, a, |x| !x & LO),
        (UnOp::LNot, Sc::Bool, _) => map1(regs, dst, mask, a, |x| (x == 0) as u64),
        _ => return None,
    }
    Some(())
}

#[cfg(test)]
mod tests {
    //! Each lane-array arm against `alu`'s scalar function applied lane by lane with the mask
    //! blend written out, over values that include the edges (0, ±1, the sign bit, 32-bit
    //! and 64-bit extremes, large shift counts) and words with upper bits set.
    use super::*;

    const EDGES: [u64; 12] = [0, 1, 2, 31, 32, 33, 0x7FFF_FFFF, 0x8000_0000, 0xFFFF_FFFF, 0x1_0000_0001, u64::MAX, 0x8000_0000_0000_0000];

    /// A small deterministic generator (xorshift), so failures reproduce.
    fn words(seed: u64, n: usize) -> Vec<u64> {
        let mut x = seed | 1;
        (0..n)
            .map(|i| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                if i % 3 == 0 { EDGES[(x % EDGES.len() as u64) as usize] } else if i % 3 == 1 { x & LO } else { x }
            })
            .collect()
    }

    /// A value of `ty` as the executor keeps it (32-bit values with zero upper bits; Bool 0/1),
    /// or the raw word to check that the arms read only what `alu` reads.
    fn typed(ty: Sc, w: u64, raw: bool) -> u64 {
        if raw { w } else { alu::norm(ty, w) }
    }

    fn regs_for(vals: &[u64], ty: Sc, raw: bool, k: usize) -> Vec<Regs> {
        (0..4).map(|r| std::array::from_fn(|l| typed(ty, vals[(k * 32 + r * LANES + l) % vals.len()], raw))).collect()
    }

    fn expect(before: &Regs, mask: u32, f: impl Fn(usize) -> u64) -> Regs {
        std::array::from_fn(|l| if (mask >> l) & 1 != 0 { f(l) } else { before[l] })
    }

    const TYPES: [Sc; 5] = [Sc::Bool, Sc::I32, Sc::I64, Sc::F32, Sc::F64];
    const MASKS: [u32; 3] = [0xFF, 0x5A, 0x01];

    #[test]
    fn bin_arms_match_alu() {
        use BinOp::*;
        let ops = [
            IAdd, ISub, IMul, UDiv, SDiv, UMod, SRem, SMod, Shl, ShrL, ShrA, And, Or, Xor, IEq, INe, ULt, ULe, UGt, UGe,
            SLt, SLe, SGt, SGe, FAdd, FSub, FMul, FDiv, FOrdEq, FOrdLt, FUnordNe, LEq, LNe, LAnd, LOr, FMin, FMax,
            UMin, UMax, SMin, SMax, UMulHi, SMulHi, AddCarry, SubBorrow,
        ];
        let vals = words(0x2545_F491_4F6C_DD1D, 4096);
        for (k, (&op, &ty)) in ops.iter().flat_map(|o| TYPES.iter().map(move |t| (o, t))).enumerate() {
            for raw in [false, true] {
                // Raw words only where `alu` defines the reading of upper bits (integers).
                if raw && !matches!(ty, Sc::I32 | Sc::I64) {
                    continue;
                }
                for mask in MASKS {
                    let mut regs = regs_for(&vals, ty, raw, k);
                    let (a, b, d) = (regs[0], regs[1], regs[2]);
                    exec_bin(&mut regs, op, ty, 2, mask, 0, 1);
                    let want = expect(&d, mask, |l| alu::bin(op, ty, a[l], b[l]));
                    assert_eq!(regs[2], want, "{op:?} {ty:?} raw {raw} mask {mask:#x} a {a:x?} b {b:x?}");
                }
            }
        }
    }

    #[test]
    fn un_arms_match_alu() {
        use UnOp::*;
        let ops = [SNeg, Not, LNot, Bitcast, UConvert, SConvert, ConvertUToF, ConvertSToF, ConvertFToU, ConvertFToS, FNeg, FAbs, Floor, Fract];
        let vals = words(0x9E37_79B9_7F4A_7C15, 4096);
        for (k, &op) in ops.iter().enumerate() {
            for (ty, from) in TYPES.iter().flat_map(|&t| TYPES.iter().map(move |&f| (t, f))) {
                for mask in MASKS {
                    let mut regs = regs_for(&vals, from, false, k);
                    let (a, d) = (regs[0], regs[2]);
                    exec_un(&mut regs, op, ty, from, 2, mask, 0);
                    let want = expect(&d, mask, |l| alu::un(op, ty, from, a[l]));
                    assert_eq!(regs[2], want, "{op:?} {ty:?} from {from:?} mask {mask:#x} a {a:x?}");
                }
            }
        }
    }

    #[test]
    fn tri_arms_match_alu() {
        use TriOp::*;
        let vals = words(0xD1B5_4A32_D192_ED03, 4096);
        for (k, &op) in [Fma, FClamp, NClamp, UClamp, SClamp, FMix].iter().enumerate() {
            for ty in [Sc::I32, Sc::F32, Sc::F64] {
                for mask in MASKS {
                    let mut regs = regs_for(&vals, ty, false, k);
                    let (a, b, c, d) = (regs[0], regs[1], regs[3], regs[2]);
                    exec_tri(&mut regs, op, ty, 2, mask, 0, 1, 3);
                    let want = expect(&d, mask, |l| alu::tri(op, ty, a[l], b[l], c[l]));
                    assert_eq!(regs[2], want, "{op:?} {ty:?} mask {mask:#x}");
                }
            }
        }
    }
}

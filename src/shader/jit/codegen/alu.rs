//! ALU ops: the common 32-bit and 64-bit integer, Bool and float ops inline (each the bits
//! `alu` gives: wrapping arithmetic, division by zero 0, shifts past the width 0, saturating
//! float → int), the others through `helpers`.
use cranelift_codegen::ir::condcodes::{FloatCC, IntCC};
use cranelift_codegen::ir::{InstBuilder, Value};

use super::super::helpers;
use super::vmath::Fn1;
use super::{Gen, F32, I32, I64};
use crate::shader::ir::{BinOp, Sc, UnOp};

/// The integer comparison of `op` (shared with the four-lane backend).
pub(in crate::shader::jit) fn int_cc(op: BinOp) -> Option<IntCC> {
    use BinOp::*;
    Some(match op {
        IEq => IntCC::Equal,
        INe => IntCC::NotEqual,
        ULt => IntCC::UnsignedLessThan,
        ULe => IntCC::UnsignedLessThanOrEqual,
        UGt => IntCC::UnsignedGreaterThan,
        UGe => IntCC::UnsignedGreaterThanOrEqual,
        SLt => IntCC::SignedLessThan,
        SLe => IntCC::SignedLessThanOrEqual,
        SGt => IntCC::SignedGreaterThan,
        SGe => IntCC::SignedGreaterThanOrEqual,
        _ => return None,
    })
}

fn float_cc(op: BinOp) -> Option<FloatCC> {
    use BinOp::*;
    Some(match op {
        FOrdEq => FloatCC::Equal,
        FOrdNe => FloatCC::OrderedNotEqual,
        FOrdLt => FloatCC::LessThan,
        FOrdLe => FloatCC::LessThanOrEqual,
        FOrdGt => FloatCC::GreaterThan,
        FOrdGe => FloatCC::GreaterThanOrEqual,
        FUnordEq => FloatCC::UnorderedOrEqual,
        FUnordNe => FloatCC::NotEqual,
        FUnordLt => FloatCC::UnorderedOrLessThan,
        FUnordLe => FloatCC::UnorderedOrLessThanOrEqual,
        FUnordGt => FloatCC::UnorderedOrGreaterThan,
        FUnordGe => FloatCC::UnorderedOrGreaterThanOrEqual,
        _ => return None,
    })
}

impl Gen<'_, '_, '_> {
    /// A two-operand op on register words `x`, `y`.
    pub(super) fn bin(&mut self, op: BinOp, ty: Sc, x: Value, y: Value) -> Option<Value> {
        if let Some(v) = self.bin_inline(op, ty, x, y) {
            return Some(v);
        }
        if ty == Sc::F32 {
            if let Some(f) = helpers::f32_binary(op) {
                return Some(self.call_f32(f as usize, &[x, y]));
            }
        }
        let code = self.b.ins().iconst(I64, helpers::bin_code(op, ty)? as i64);
        Some(self.call_int(helpers::bin as *const () as usize, &[code, x, y]))
    }

    // One function: one match over the type, then the op, each arm a few builder calls.
    fn bin_inline(&mut self, op: BinOp, ty: Sc, x: Value, y: Value) -> Option<Value> {
        use BinOp::*;
        match ty {
            Sc::I32 => {
                let (a, b) = (self.lo(x), self.lo(y));
                if let Some(cc) = int_cc(op) {
                    let c = self.b.ins().icmp(cc, a, b);
                    return Some(self.word_bool(c));
                }
                let r = match op {
                    IAdd => self.b.ins().iadd(a, b),
                    ISub => self.b.ins().isub(a, b),
                    IMul => self.b.ins().imul(a, b),
                    And => self.b.ins().band(a, b),
                    Or => self.b.ins().bor(a, b),
                    Xor => self.b.ins().bxor(a, b),
                    UMin => self.b.ins().umin(a, b),
                    UMax => self.b.ins().umax(a, b),
                    SMin => self.b.ins().smin(a, b),
                    SMax => self.b.ins().smax(a, b),
                    Shl | ShrL | ShrA => self.shift(op, a, b, 32),
                    UDiv | UMod => {
                        let zero = self.b.ins().icmp_imm_s(IntCC::Equal, b, 0);
                        let one = self.b.ins().iconst(I32, 1);
                        let d = self.b.ins().select(zero, one, b);
                        let q = if op == UDiv { self.b.ins().udiv(a, d) } else { self.b.ins().urem(a, d) };
                        let z = self.b.ins().iconst(I32, 0);
                        self.b.ins().select(zero, z, q)
                    }
                    SDiv | SRem => {
                        // In 64 bits, as `alu` does: INT_MIN / -1 cannot overflow there.
                        let (a, b) = (self.b.ins().sextend(I64, a), self.b.ins().sextend(I64, b));
                        let zero = self.b.ins().icmp_imm_s(IntCC::Equal, b, 0);
                        let one = self.b.ins().iconst(I64, 1);
                        let d = self.b.ins().select(zero, one, b);
                        let q = if op == SDiv { self.b.ins().sdiv(a, d) } else { self.b.ins().srem(a, d) };
                        let z = self.b.ins().iconst(I64, 0);
                        let q = self.b.ins().select(zero, z, q);
                        self.lo(q)
                    }
                    _ => return None,
                };
                Some(self.zx(r))
            }
            Sc::I64 => {
                if let Some(cc) = int_cc(op) {
                    let c = self.b.ins().icmp(cc, x, y);
                    return Some(self.word_bool(c));
                }
                Some(match op {
                    IAdd => self.b.ins().iadd(x, y),
                    ISub => self.b.ins().isub(x, y),
                    IMul => self.b.ins().imul(x, y),
                    And => self.b.ins().band(x, y),
                    Or => self.b.ins().bor(x, y),
                    Xor => self.b.ins().bxor(x, y),
                    UMin => self.b.ins().umin(x, y),
                    UMax => self.b.ins().umax(x, y),
                    SMin => self.b.ins().smin(x, y),
                    SMax => self.b.ins().smax(x, y),
                    Shl | ShrL | ShrA => {
                        let s = self.lo(y);
                        self.shift(op, x, s, 64)
                    }
                    _ => return None,
                })
            }
            Sc::Bool => {
                let (a, b) = (self.b.ins().icmp_imm_s(IntCC::NotEqual, x, 0), self.b.ins().icmp_imm_s(IntCC::NotEqual, y, 0));
                let c = match op {
                    LAnd => self.b.ins().band(a, b),
                    LOr => self.b.ins().bor(a, b),
                    LEq | IEq => self.b.ins().icmp(IntCC::Equal, a, b),
                    LNe | INe => self.b.ins().icmp(IntCC::NotEqual, a, b),
                    _ => return None,
                };
                Some(self.word_bool(c))
            }
            Sc::F32 | Sc::F64 => {
                let (a, b) = if ty == Sc::F32 { (self.f32_of(x), self.f32_of(y)) } else { (self.f64_of(x), self.f64_of(y)) };
                if let Some(cc) = float_cc(op) {
                    let c = self.b.ins().fcmp(cc, a, b);
                    return Some(self.word_bool(c));
                }
                let r = match op {
                    FAdd => self.b.ins().fadd(a, b),
                    FSub => self.b.ins().fsub(a, b),
                    FMul => self.b.ins().fmul(a, b),
                    FDiv => self.b.ins().fdiv(a, b),
                    _ => return None,
                };
                let code = helpers::bin_code(op, ty)? as i64;
                Some(self.nan_guard(r, |g| {
                    let code = g.b.ins().iconst(I64, code);
                    g.call_int(helpers::bin as *const () as usize, &[code, x, y])
                }))
            }
        }
    }

    /// `x * k` for the integer types when `k` is a power of two or one more than 2, 4 or 8:
    /// shifts and adds (one `lea` on x86-64) instead of a multiply, which is the longest link
    /// of loops like `x = 3x + 1`. None for other constants and types.
    pub(super) fn mul_const(&mut self, ty: Sc, x: Value, k: u64) -> Option<Value> {
        let (x, k) = match ty {
            Sc::I32 => (self.lo(x), k as u32 as u64),
            Sc::I64 => (x, k),
            _ => return None,
        };
        let r = if k.is_power_of_two() {
            self.b.ins().ishl_imm_u(x, k.trailing_zeros() as i64)
        } else if matches!(k, 3 | 5 | 9) {
            let s = self.b.ins().ishl_imm_u(x, (k - 1).trailing_zeros() as i64);
            self.b.ins().iadd(s, x)
        } else {
            return None;
        };
        Some(if ty == Sc::I32 { self.zx(r) } else { r })
    }

    /// Shifts of a `bits`-wide value `a` by the 32-bit amount `s`: past the width, 0 (left and
    /// logical right) or the sign (arithmetic right).
    fn shift(&mut self, op: BinOp, a: Value, s: Value, bits: i64) -> Value {
        if op == BinOp::ShrA {
            let max = self.b.ins().iconst(I32, bits - 1);
            let s = self.b.ins().umin(s, max);
            return self.b.ins().sshr(a, s);
        }
        let r = if op == BinOp::Shl { self.b.ins().ishl(a, s) } else { self.b.ins().ushr(a, s) };
        let ty = self.b.func.dfg.value_type(a);
        let within = self.b.ins().icmp_imm_s(IntCC::UnsignedLessThan, s, bits);
        let z = self.b.ins().iconst(ty, 0);
        self.b.ins().select(within, r, z)
    }

    /// A one-operand op (conversions included) on the register word `x`.
    pub(super) fn un(&mut self, op: UnOp, ty: Sc, from: Sc, x: Value) -> Option<Value> {
        use UnOp::*;
        let r = match (op, ty, from) {
            (Bitcast | UConvert, _, Sc::I32 | Sc::I64 | Sc::F32 | Sc::F64) => {
                let v = self.norm(from, x);
                self.norm(ty, v)
            }
            (SConvert, _, Sc::I32 | Sc::I64) => {
                let v = if from == Sc::I32 {
                    let l = self.lo(x);
                    self.b.ins().sextend(I64, l)
                } else {
                    x
                };
                self.norm(ty, v)
            }
            (SNeg, Sc::I32 | Sc::I64, _) => {
                let v = self.b.ins().ineg(x);
                self.norm(ty, v)
            }
            (Not, Sc::I32 | Sc::I64, _) => {
                let v = self.b.ins().bnot(x);
                self.norm(ty, v)
            }
            (LNot, Sc::Bool, _) => {
                let c = self.b.ins().icmp_imm_s(IntCC::Equal, x, 0);
                self.word_bool(c)
            }
            (ConvertSToF | ConvertUToF, Sc::F32, Sc::I32) => {
                let l = self.lo(x);
                let f = if op == ConvertSToF { self.b.ins().fcvt_from_sint(F32, l) } else { self.b.ins().fcvt_from_uint(F32, l) };
                self.word_f32(f)
            }
            (ConvertFToS | ConvertFToU, Sc::I32, Sc::F32) => {
                let f = self.f32_of(x);
                let i = if op == ConvertFToS { self.b.ins().fcvt_to_sint_sat(I32, f) } else { self.b.ins().fcvt_to_uint_sat(I32, f) };
                self.zx(i)
            }
            (Sqrt | FNeg | FAbs | Sin | Cos | Exp, Sc::F32, Sc::F32) => {
                let f = self.f32_of(x);
                let r = match op {
                    Sqrt => self.b.ins().sqrt(f),
                    FNeg => self.b.ins().fneg(f),
                    FAbs => self.b.ins().fabs(f),
                    Sin => self.vmath1(Fn1::Sin, f),
                    Cos => self.vmath1(Fn1::Cos, f),
                    _ => self.vmath1(Fn1::Exp, f),
                };
                let code = helpers::un_code(op, ty, from)? as i64;
                self.nan_guard(r, |g| {
                    let code = g.b.ins().iconst(I64, code);
                    g.call_int(helpers::un as *const () as usize, &[code, x])
                })
            }
            (_, Sc::F32, _) if helpers::f32_unary(op).is_some() => {
                let f = helpers::f32_unary(op)?;
                self.call_f32(f as usize, &[x])
            }
            _ => {
                let code = self.b.ins().iconst(I64, helpers::un_code(op, ty, from)? as i64);
                self.call_int(helpers::un as *const () as usize, &[code, x])
            }
        };
        Some(r)
    }
}

//! ALU ops on a call's lanes: the common I32, F32 and Bool ops as vector instructions (each the
//! bits `alu` gives), sin/cos/exp through the vectorised `vmath`, everything else lane by lane
//! through the helpers that run the interpreter's own arms. A float result that is a NaN in a
//! running lane is recomputed by the helpers (the interpreter's NaN bits).
use cranelift_codegen::ir::condcodes::{FloatCC, IntCC};
use cranelift_codegen::ir::{InstBuilder, MemFlagsData, Value};
use cranelift_frontend::FunctionBuilder;

use super::super::codegen::alu::int_cc;
use super::super::codegen::vmath::{splat_const, vmath, Fn1};
use super::super::helpers;
use super::gen::{Gen, F32X4, I32, I32X4, I64, PARTS, V, W};
use super::types::Cls;
use crate::shader::ir::{BinOp, Reg, Sc, TriOp, UnOp};

/// Float comparisons as the x64 backend's vector compares have them; FOrdNe and FUnordEq are
/// composed of two.
fn float_cc(op: BinOp) -> Option<FloatCC> {
    use BinOp::*;
    Some(match op {
        FOrdEq => FloatCC::Equal,
        FOrdLt => FloatCC::LessThan,
        FOrdLe => FloatCC::LessThanOrEqual,
        FOrdGt => FloatCC::GreaterThan,
        FOrdGe => FloatCC::GreaterThanOrEqual,
        FUnordNe => FloatCC::NotEqual,
        FUnordLt => FloatCC::UnorderedOrLessThan,
        FUnordLe => FloatCC::UnorderedOrLessThanOrEqual,
        FUnordGt => FloatCC::UnorderedOrGreaterThan,
        FUnordGe => FloatCC::UnorderedOrGreaterThanOrEqual,
        _ => return None,
    })
}

/// A two-operand instruction, emitted once per part.
type Op2 = fn(&mut FunctionBuilder, Value, Value) -> Value;

impl Gen<'_, '_, '_> {
    fn fv(&mut self, v: V) -> V {
        self.map(v, |b, x| b.ins().bitcast(F32X4, MemFlagsData::new(), x))
    }
    fn iv(&mut self, v: V) -> V {
        self.map(v, |b, x| b.ins().bitcast(I32X4, MemFlagsData::new(), x))
    }

    /// Per lane, helper `f` of the lanes' words after the op code (`code` first).
    fn per_lane(&mut self, f: usize, code: i64, args: &[Reg]) -> [Value; W] {
        std::array::from_fn(|l| {
            let mut xs = vec![self.b.ins().iconst(I64, code)];
            xs.extend(args.iter().map(|&r| self.word(r, l)));
            self.call_int(f, &xs)
        })
    }

    /// Helper `f` of W32 operands for every lane, through a trampoline that clobbers no
    /// register (`tramp`).
    fn per_lane_w32(&mut self, f: usize, code: i64, args: &[Reg]) -> V {
        for (k, &r) in args.iter().enumerate() {
            let v = self.vget(r, Cls::W32);
            for (p, &x) in v.iter().enumerate() {
                self.b.ins().stack_store(I64, x, self.buf, super::tramp::operand(k, 4 * p));
            }
        }
        let fv = self.b.ins().iconst(I64, f as i64);
        let c = self.b.ins().iconst(I64, code);
        let p = self.b.ins().stack_addr(I64, self.buf, 0);
        self.b.ins().call(self.tramps[args.len() - 1], &[fv, c, p]);
        std::array::from_fn(|p| self.b.ins().stack_load(I64, I32X4, self.buf, super::tramp::OUT + 16 * p as i32))
    }

    /// The W32 bits of F32 result `r` (f32x4 parts). A NaN in a running lane is noted, and the
    /// run of pure ops it is in is then redone through the helpers (`Gen::flush`); while
    /// redoing, the helpers' words for every lane.
    fn nan_guard(&mut self, r: V, f: usize, code: i64, args: &[Reg]) -> V {
        if self.redo {
            return self.per_lane_w32(f, code, args);
        }
        if self.skip_nan {
            return self.iv(r);
        }
        // One unordered compare tests two results: they are paired up.
        match self.nan_pending.take() {
            None => self.nan_pending = Some(r),
            Some(q) => {
                let nan = self.map2(q, r, |b, x, y| b.ins().fcmp(FloatCC::Unordered, x, y));
                self.note_nan(nan);
            }
        }
        self.iv(r)
    }

    fn note_nan(&mut self, nan: V) {
        self.nan_acc = Some(match self.nan_acc {
            Some(acc) => self.map2(acc, nan, |b, a, n| b.ins().bor(a, n)),
            None => nan,
        });
    }

    /// Lanes in which a float result of the run was a NaN (None: no float result).
    pub(super) fn nan_lanes(&mut self) -> Option<V> {
        if let Some(q) = self.nan_pending.take() {
            let nan = self.map(q, |b, x| b.ins().fcmp(FloatCC::Unordered, x, x));
            self.note_nan(nan);
        }
        self.nan_acc.take()
    }

    pub(super) fn bin(&mut self, op: BinOp, ty: Sc, dst: Reg, a: Reg, b: Reg) -> Option<()> {
        let code = helpers::bin_code(op, ty)? as i64;
        if let Some(v) = self.bin_vec(op, ty, code, a, b) {
            self.vset(dst, v);
        } else {
            let w = self.per_lane(helpers::bin as *const () as usize, code, &[a, b]);
            self.set_words(dst, w);
        }
        Some(())
    }

    fn bin_vec(&mut self, op: BinOp, ty: Sc, code: i64, a: Reg, b: Reg) -> Option<V> {
        use BinOp::*;
        match ty {
            Sc::I32 => {
                if let Some(v) = self.strict_unsigned(op, a, b) {
                    return Some(v);
                }
                if let Some(cc) = int_cc(op) {
                    let (x, y) = (self.vget(a, Cls::W32), self.vget(b, Cls::W32));
                    return Some(self.map2(x, y, |b, x, y| b.ins().icmp(cc, x, y)));
                }
                if let Some(v) = self.mul_by_constant(op, a, b) {
                    return Some(v);
                }
                if matches!(op, Shl | ShrL | ShrA) {
                    // Vector shifts take one amount for all lanes: a constant one.
                    let s = self.types.konst(b)? as u32;
                    let x = self.vget(a, Cls::W32);
                    if op != ShrA && s >= 32 {
                        return Some(self.splat32(0));
                    }
                    let k = self.b.ins().iconst(I32, s.min(31) as i64);
                    return Some(match op {
                        Shl => self.map(x, |b, x| b.ins().ishl(x, k)),
                        ShrL => self.map(x, |b, x| b.ins().ushr(x, k)),
                        _ => self.map(x, |b, x| b.ins().sshr(x, k)),
                    });
                }
                let f: Op2 = match op {
                    IAdd => |b, x, y| b.ins().iadd(x, y),
                    ISub => |b, x, y| b.ins().isub(x, y),
                    IMul => |b, x, y| b.ins().imul(x, y),
                    And => |b, x, y| b.ins().band(x, y),
                    Or => |b, x, y| b.ins().bor(x, y),
                    Xor => |b, x, y| b.ins().bxor(x, y),
                    UMin => |b, x, y| b.ins().umin(x, y),
                    UMax => |b, x, y| b.ins().umax(x, y),
                    SMin => |b, x, y| b.ins().smin(x, y),
                    SMax => |b, x, y| b.ins().smax(x, y),
                    _ => return None,
                };
                let (x, y) = (self.vget(a, Cls::W32), self.vget(b, Cls::W32));
                Some(self.map2(x, y, f))
            }
            Sc::F32 => self.bin_f32(op, code, a, b),
            Sc::Bool => {
                let f: Op2 = match op {
                    LAnd => |b, x, y| b.ins().band(x, y),
                    LOr => |b, x, y| b.ins().bor(x, y),
                    LNe | INe => |b, x, y| b.ins().bxor(x, y),
                    LEq | IEq => |b, x, y| {
                        let d = b.ins().bxor(x, y);
                        b.ins().bnot(d)
                    },
                    _ => return None,
                };
                let (x, y) = (self.vget(a, Cls::B), self.vget(b, Cls::B));
                Some(self.map2(x, y, f))
            }
            _ => None,
        }
    }

    /// `a <u b` and `a >u b` as one signed compare of sign-flipped operands (SSE has no unsigned
    /// compare: Cranelift's max, equal and not take three), a constant flipped at compile time.
    fn strict_unsigned(&mut self, op: BinOp, a: Reg, b: Reg) -> Option<V> {
        let (lo, hi) = match op {
            BinOp::ULt => (a, b),
            BinOp::UGt => (b, a),
            _ => return None,
        };
        let flip = |g: &mut Self, r: Reg| match g.types.konst(r) {
            Some(k) => [splat_const(g.b, I32X4, k as u32 ^ 0x8000_0000); PARTS],
            None => {
                let x = g.vget(r, Cls::W32);
                let sign = splat_const(g.b, I32X4, 0x8000_0000);
                g.map(x, |b, x| b.ins().bxor(x, sign))
            }
        };
        let (x, y) = (flip(self, hi), flip(self, lo));
        Some(self.map2(x, y, |b, x, y| b.ins().icmp(IntCC::SignedGreaterThan, x, y)))
    }

    /// `a * k` for a constant `k` of the form 2^s, 2^s + 1 or 2^s - 1 as a shift and an add or
    /// subtract (`pmulld` takes ten cycles on some cores; wrapping arithmetic gives the same bits).
    fn mul_by_constant(&mut self, op: BinOp, a: Reg, b: Reg) -> Option<V> {
        if op != BinOp::IMul {
            return None;
        }
        let (x, k) = match (self.types.konst(a), self.types.konst(b)) {
            (_, Some(k)) => (a, k as u32),
            (Some(k), None) => (b, k as u32),
            _ => return None,
        };
        let x = self.vget(x, Cls::W32);
        let (s, tail) = if k.is_power_of_two() {
            (k.trailing_zeros(), 0)
        } else if k > 1 && (k - 1).is_power_of_two() {
            ((k - 1).trailing_zeros(), 1)
        } else if k.checked_add(1).is_some_and(u32::is_power_of_two) && k > 1 {
            ((k + 1).trailing_zeros(), -1)
        } else {
            return None;
        };
        let sh = self.b.ins().iconst(I32, s as i64);
        Some(self.map(x, |b, x| {
            let y = b.ins().ishl(x, sh);
            match tail {
                1 => b.ins().iadd(y, x),
                -1 => b.ins().isub(y, x),
                _ => y,
            }
        }))
    }

    fn bin_f32(&mut self, op: BinOp, code: i64, a: Reg, b: Reg) -> Option<V> {
        use BinOp::*;
        let (x, y) = (self.vget(a, Cls::W32), self.vget(b, Cls::W32));
        let (x, y) = (self.fv(x), self.fv(y));
        if let Some(cc) = float_cc(op) {
            return Some(self.map2(x, y, |b, x, y| b.ins().fcmp(cc, x, y)));
        }
        let f: Op2 = match op {
            FOrdNe => |b, x, y| {
                let (c1, c2) = (b.ins().fcmp(FloatCC::Ordered, x, y), b.ins().fcmp(FloatCC::NotEqual, x, y));
                b.ins().band(c1, c2)
            },
            FUnordEq => |b, x, y| {
                let (c1, c2) = (b.ins().fcmp(FloatCC::Unordered, x, y), b.ins().fcmp(FloatCC::Equal, x, y));
                b.ins().bor(c1, c2)
            },
            FAdd => |b, x, y| b.ins().fadd(x, y),
            FSub => |b, x, y| b.ins().fsub(x, y),
            FMul => |b, x, y| b.ins().fmul(x, y),
            FDiv => |b, x, y| b.ins().fdiv(x, y),
            _ => return None,
        };
        let r = self.map2(x, y, f);
        if matches!(op, FOrdNe | FUnordEq) {
            return Some(r);
        }
        Some(self.nan_guard(r, helpers::bin as *const () as usize, code, &[a, b]))
    }

    pub(super) fn un(&mut self, op: UnOp, ty: Sc, from: Sc, dst: Reg, a: Reg) -> Option<()> {
        let code = helpers::un_code(op, ty, from)? as i64;
        if let Some(v) = self.un_vec(op, ty, from, code, a) {
            self.vset(dst, v);
            return Some(());
        }
        let w = match (op, ty, from) {
            (UnOp::UConvert | UnOp::Bitcast, Sc::I64 | Sc::F64, Sc::I32 | Sc::F32) => self.words(a),
            (UnOp::SConvert, Sc::I64, Sc::I32) => std::array::from_fn(|l| {
                let w = self.word(a, l);
                let x = self.b.ins().ireduce(I32, w);
                self.b.ins().sextend(I64, x)
            }),
            _ => self.per_lane(helpers::un as *const () as usize, code, &[a]),
        };
        self.set_words(dst, w);
        Some(())
    }

    fn un_vec(&mut self, op: UnOp, ty: Sc, from: Sc, code: i64, a: Reg) -> Option<V> {
        use UnOp::*;
        let w32 = |t: Sc| matches!(t, Sc::I32 | Sc::F32);
        Some(match (op, ty, from) {
            (Bitcast | UConvert | SConvert, _, _) if w32(ty) && w32(from) && (op == Bitcast || ty == Sc::I32) => self.vget(a, Cls::W32),
            (SNeg, Sc::I32, _) => {
                let x = self.vget(a, Cls::W32);
                self.map(x, |b, x| b.ins().ineg(x))
            }
            (Not, Sc::I32, _) => {
                let x = self.vget(a, Cls::W32);
                self.map(x, |b, x| b.ins().bnot(x))
            }
            (LNot, Sc::Bool, Sc::Bool) => {
                let x = self.vget(a, Cls::B);
                self.map(x, |b, x| b.ins().bnot(x))
            }
            (ConvertSToF, Sc::F32, Sc::I32) => {
                let x = self.vget(a, Cls::W32);
                let f = self.map(x, |b, x| b.ins().fcvt_from_sint(F32X4, x));
                self.iv(f)
            }
            // The x64 backend converts the halves exactly and rounds once in their sum (or
            // uses AVX-512's conversion): the correctly rounded value, as `alu`'s.
            (ConvertUToF, Sc::F32, Sc::I32) => {
                let x = self.vget(a, Cls::W32);
                let f = self.map(x, |b, x| b.ins().fcvt_from_uint(F32X4, x));
                self.iv(f)
            }
            (ConvertFToS, Sc::I32, Sc::F32) => {
                let x = self.vget(a, Cls::W32);
                let f = self.fv(x);
                self.map(f, |b, x| b.ins().fcvt_to_sint_sat(I32X4, x))
            }
            (Sqrt | FNeg | FAbs | Sin | Cos | Exp, Sc::F32, Sc::F32) => {
                let x = self.vget(a, Cls::W32);
                let f = self.fv(x);
                let r = match op {
                    Sqrt => self.map(f, |b, x| b.ins().sqrt(x)),
                    FNeg => self.map(f, |b, x| b.ins().fneg(x)),
                    FAbs => self.map(f, |b, x| b.ins().fabs(x)),
                    Sin => vmath(self.b, Fn1::Sin, &f).try_into().ok()?,
                    Cos => vmath(self.b, Fn1::Cos, &f).try_into().ok()?,
                    _ => vmath(self.b, Fn1::Exp, &f).try_into().ok()?,
                };
                self.nan_guard(r, helpers::un as *const () as usize, code, &[a])
            }
            _ => return None,
        })
    }

    pub(super) fn tri(&mut self, op: TriOp, ty: Sc, dst: Reg, a: Reg, b: Reg, c: Reg) -> Option<()> {
        let code = helpers::tri_code(op, ty)? as i64;
        if (op, ty) == (TriOp::Fma, Sc::F32) {
            // Hardware and `vmath::fma1` both round the exact a·b + c once.
            let (x, y, z) = (self.vget(a, Cls::W32), self.vget(b, Cls::W32), self.vget(c, Cls::W32));
            let (x, y, z) = (self.fv(x), self.fv(y), self.fv(z));
            let r = self.map3(x, y, z, |b, x, y, z| b.ins().fma(x, y, z));
            let v = self.nan_guard(r, helpers::tri as *const () as usize, code, &[a, b, c]);
            self.vset(dst, v);
        } else {
            let w = self.per_lane(helpers::tri as *const () as usize, code, &[a, b, c]);
            self.set_words(dst, w);
        }
        Some(())
    }
}

const _: () = assert!(W == 4 * PARTS);

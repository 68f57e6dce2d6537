//! ALU ops on four lanes: the common I32, F32 and Bool ops as vector instructions (each the
//! bits `alu` gives), sin/cos/exp through the vectorised `vmath`, everything else lane by lane
//! through the helpers that run the interpreter's own arms. A float result that is a NaN in a
//! running lane is recomputed by the helpers (the interpreter's NaN bits).
use cranelift_codegen::ir::condcodes::FloatCC;
use cranelift_codegen::ir::{InstBuilder, MemFlagsData, Value};

use super::super::codegen::alu::int_cc;
use super::super::codegen::vmath::{vmath, Fn1};
use super::super::helpers;
use super::gen::{Gen, F32X4, I32, I32X4, I64, W};
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

impl Gen<'_, '_, '_> {
    fn fv(&mut self, v: Value) -> Value {
        self.b.ins().bitcast(F32X4, MemFlagsData::new(), v)
    }
    fn iv(&mut self, v: Value) -> Value {
        self.b.ins().bitcast(I32X4, MemFlagsData::new(), v)
    }

    /// Per lane, helper `f` of the lanes' words after the op code (`code` first).
    fn per_lane(&mut self, f: usize, code: i64, args: &[Reg]) -> [Value; W] {
        std::array::from_fn(|l| {
            let mut xs = vec![self.b.ins().iconst(I64, code)];
            xs.extend(args.iter().map(|&r| self.word(r, l)));
            self.call_int(f, &xs)
        })
    }

    /// Helper `f` of W32 operands for the four lanes, through a trampoline that clobbers no
    /// register (`tramp`).
    fn per_lane_w32(&mut self, f: usize, code: i64, args: &[Reg]) -> Value {
        for (k, &r) in args.iter().enumerate() {
            let v = self.vget(r, Cls::W32);
            self.b.ins().stack_store(I64, v, self.buf, k as i32 * 16);
        }
        let fv = self.b.ins().iconst(I64, f as i64);
        let c = self.b.ins().iconst(I64, code);
        let p = self.b.ins().stack_addr(I64, self.buf, 0);
        self.b.ins().call(self.tramps[args.len() - 1], &[fv, c, p]);
        self.b.ins().stack_load(I64, I32X4, self.buf, super::tramp::OUT)
    }

    /// The W32 bits of F32 result `r` (f32x4). A NaN in a running lane is noted, and the run of
    /// pure ops it is in is then redone through the helpers (`Gen::flush`); while redoing,
    /// the helpers' words for every lane.
    fn nan_guard(&mut self, r: Value, f: usize, code: i64, args: &[Reg]) -> Value {
        if self.redo {
            return self.per_lane_w32(f, code, args);
        }
        let nan = self.b.ins().fcmp(FloatCC::Unordered, r, r);
        self.nan_acc = Some(match self.nan_acc {
            Some(acc) => self.b.ins().bor(acc, nan),
            None => nan,
        });
        self.iv(r)
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

    fn bin_vec(&mut self, op: BinOp, ty: Sc, code: i64, a: Reg, b: Reg) -> Option<Value> {
        use BinOp::*;
        match ty {
            Sc::I32 => {
                if let Some(cc) = int_cc(op) {
                    let (x, y) = (self.vget(a, Cls::W32), self.vget(b, Cls::W32));
                    return Some(self.b.ins().icmp(cc, x, y));
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
                        Shl => self.b.ins().ishl(x, k),
                        ShrL => self.b.ins().ushr(x, k),
                        _ => self.b.ins().sshr(x, k),
                    });
                }
                let (x, y) = (self.vget(a, Cls::W32), self.vget(b, Cls::W32));
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
                    _ => return None,
                })
            }
            Sc::F32 => {
                let (x, y) = (self.vget(a, Cls::W32), self.vget(b, Cls::W32));
                let (x, y) = (self.fv(x), self.fv(y));
                if let Some(cc) = float_cc(op) {
                    return Some(self.b.ins().fcmp(cc, x, y));
                }
                let r = match op {
                    FOrdNe | FUnordEq => {
                        let (k1, k2) = if op == FOrdNe { (FloatCC::Ordered, FloatCC::NotEqual) } else { (FloatCC::Unordered, FloatCC::Equal) };
                        let (c1, c2) = (self.b.ins().fcmp(k1, x, y), self.b.ins().fcmp(k2, x, y));
                        return Some(if op == FOrdNe { self.b.ins().band(c1, c2) } else { self.b.ins().bor(c1, c2) });
                    }
                    FAdd => self.b.ins().fadd(x, y),
                    FSub => self.b.ins().fsub(x, y),
                    FMul => self.b.ins().fmul(x, y),
                    FDiv => self.b.ins().fdiv(x, y),
                    _ => return None,
                };
                Some(self.nan_guard(r, helpers::bin as *const () as usize, code, &[a, b]))
            }
            Sc::Bool => {
                let (x, y) = (self.vget(a, Cls::B), self.vget(b, Cls::B));
                Some(match op {
                    LAnd => self.b.ins().band(x, y),
                    LOr => self.b.ins().bor(x, y),
                    LNe | INe => self.b.ins().bxor(x, y),
                    LEq | IEq => {
                        let d = self.b.ins().bxor(x, y);
                        self.b.ins().bnot(d)
                    }
                    _ => return None,
                })
            }
            _ => None,
        }
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

    fn un_vec(&mut self, op: UnOp, ty: Sc, from: Sc, code: i64, a: Reg) -> Option<Value> {
        use UnOp::*;
        let w32 = |t: Sc| matches!(t, Sc::I32 | Sc::F32);
        Some(match (op, ty, from) {
            (Bitcast | UConvert | SConvert, _, _) if w32(ty) && w32(from) && (op == Bitcast || ty == Sc::I32) => self.vget(a, Cls::W32),
            (SNeg, Sc::I32, _) => {
                let x = self.vget(a, Cls::W32);
                self.b.ins().ineg(x)
            }
            (Not, Sc::I32, _) => {
                let x = self.vget(a, Cls::W32);
                self.b.ins().bnot(x)
            }
            (LNot, Sc::Bool, Sc::Bool) => {
                let x = self.vget(a, Cls::B);
                self.b.ins().bnot(x)
            }
            (ConvertSToF, Sc::F32, Sc::I32) => {
                let x = self.vget(a, Cls::W32);
                let f = self.b.ins().fcvt_from_sint(F32X4, x);
                self.iv(f)
            }
            (ConvertFToS, Sc::I32, Sc::F32) => {
                let x = self.vget(a, Cls::W32);
                let f = self.fv(x);
                self.b.ins().fcvt_to_sint_sat(I32X4, f)
            }
            (Sqrt | FNeg | FAbs | Sin | Cos | Exp, Sc::F32, Sc::F32) => {
                let x = self.vget(a, Cls::W32);
                let f = self.fv(x);
                let r = match op {
                    Sqrt => self.b.ins().sqrt(f),
                    FNeg => self.b.ins().fneg(f),
                    FAbs => self.b.ins().fabs(f),
                    Sin => vmath(self.b, Fn1::Sin, f),
                    Cos => vmath(self.b, Fn1::Cos, f),
                    _ => vmath(self.b, Fn1::Exp, f),
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
            let r = self.b.ins().fma(x, y, z);
            let v = self.nan_guard(r, helpers::tri as *const () as usize, code, &[a, b, c]);
            self.vset(dst, v);
        } else {
            let w = self.per_lane(helpers::tri as *const () as usize, code, &[a, b, c]);
            self.set_words(dst, w);
        }
        Some(())
    }
}

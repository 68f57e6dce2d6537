//! `vmath`'s sin, cos and exp written out in Cranelift IR: the same f32 operations in the same
//! order (Rust neither contracts nor reassociates float arithmetic), so every non-NaN result
//! has `vmath`'s bits; a NaN result takes the helper (the interpreter's bits for NaNs). Inline,
//! they cost no call, which would spill every live float register.
use cranelift_codegen::ir::condcodes::FloatCC;
use cranelift_codegen::ir::{InstBuilder, MemFlagsData, Value};

use super::{Gen, F32, I32};

const ROUND: f32 = 12_582_912.0;
const ROUND_BITS: i64 = 0x4B40_0000;
const PIO2_1: f32 = 1.570_312_5;
const PIO2_2: f32 = 4.837_513e-4;
const PIO2_3: f32 = 7.549_79e-8;
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;

/// Which function.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum Fn1 {
    Sin,
    Cos,
    Exp,
}

impl Gen<'_, '_, '_> {
    fn k(&mut self, v: f32) -> Value {
        self.b.ins().f32const(v)
    }
    fn mul(&mut self, a: Value, b: Value) -> Value {
        self.b.ins().fmul(a, b)
    }
    fn mulk(&mut self, a: Value, k: f32) -> Value {
        let k = self.k(k);
        self.b.ins().fmul(a, k)
    }
    fn addk(&mut self, a: Value, k: f32) -> Value {
        let k = self.k(k);
        self.b.ins().fadd(a, k)
    }
    fn bits(&mut self, x: Value) -> Value {
        self.b.ins().bitcast(I32, MemFlagsData::new(), x)
    }
    fn float(&mut self, x: Value) -> Value {
        self.b.ins().bitcast(F32, MemFlagsData::new(), x)
    }

    /// `vmath::round_int`: (t rounded to an integer, that integer as i32).
    fn round_int(&mut self, t: Value) -> (Value, Value) {
        let s = self.addk(t, ROUND);
        let n = self.addk(s, -ROUND);
        let sb = self.bits(s);
        let ni = self.b.ins().iadd_imm_s(sb, -ROUND_BITS);
        (n, ni)
    }

    /// `vmath::horner`.
    fn horner(&mut self, x: Value, c: &[f32]) -> Value {
        let mut acc = self.k(c[0]);
        for &k in &c[1..] {
            let m = self.mul(acc, x);
            acc = self.addk(m, k);
        }
        acc
    }

    /// The f32 function `f` of `x` (an F32 value), as an F32 value.
    pub(super) fn vmath1(&mut self, f: Fn1, x: Value) -> Value {
        match f {
            Fn1::Sin | Fn1::Cos => self.sin_cos(f == Fn1::Cos, x),
            Fn1::Exp => self.exp(x),
        }
    }

    fn sin_cos(&mut self, cos: bool, x: Value) -> Value {
        // reduce_half_pi
        let t = self.mulk(x, std::f32::consts::FRAC_2_PI);
        let (j, ji) = self.round_int(t);
        let a = self.mulk(j, PIO2_1);
        let r = self.b.ins().fsub(x, a);
        let a = self.mulk(j, PIO2_2);
        let r = self.b.ins().fsub(r, a);
        let a = self.mulk(j, PIO2_3);
        let r = self.b.ins().fsub(r, a);
        let abs = self.b.ins().fabs(r);
        let one = self.k(1.0);
        let big = self.b.ins().fcmp(FloatCC::GreaterThan, abs, one);
        let zero = self.k(0.0);
        let r = self.b.ins().select(big, zero, r);
        let q = self.b.ins().band_imm_u(ji, 3);
        let q = if cos { self.b.ins().iadd_imm_s(q, 1) } else { q };
        // sin_cos_poly
        let z = self.mul(r, r);
        let p = self.mulk(z, -1.951_529_6e-4);
        let p = self.addk(p, 8.332_161e-3);
        let p = self.mul(p, z);
        let p = self.addk(p, -1.666_665_5e-1);
        let p = self.mul(p, z);
        let p = self.mul(p, r);
        let s = self.b.ins().fadd(p, r);
        let (sb, rb) = (self.bits(s), self.bits(r));
        let sign = self.b.ins().band_imm_u(rb, 0x8000_0000u32 as i64);
        let s = self.b.ins().bor(sb, sign);
        let p = self.mulk(z, 2.443_315_7e-5);
        let p = self.addk(p, -1.388_731_6e-3);
        let p = self.mul(p, z);
        let p = self.addk(p, 4.166_664_6e-2);
        let p = self.mul(p, z);
        let p = self.mul(p, z);
        let h = self.mulk(z, 0.5);
        let c = self.b.ins().fsub(p, h);
        let c = self.addk(c, 1.0);
        let c = self.bits(c);
        // sin_quadrant
        let odd = self.b.ins().band_imm_u(q, 1);
        let odd = self.b.ins().ineg(odd);
        let from_c = self.b.ins().band(c, odd);
        let not_odd = self.b.ins().bnot(odd);
        let from_s = self.b.ins().band(s, not_odd);
        let v = self.b.ins().bor(from_c, from_s);
        let flip = self.b.ins().band_imm_u(q, 2);
        let flip = self.b.ins().ishl_imm_u(flip, 30);
        let v = self.b.ins().bxor(v, flip);
        self.float(v)
    }

    fn exp(&mut self, x: Value) -> Value {
        // f32::clamp(-104, 89): NaN passes.
        let lo = self.k(-104.0);
        let below = self.b.ins().fcmp(FloatCC::LessThan, x, lo);
        let x = self.b.ins().select(below, lo, x);
        let hi = self.k(89.0);
        let above = self.b.ins().fcmp(FloatCC::GreaterThan, x, hi);
        let xc = self.b.ins().select(above, hi, x);
        let t = self.mulk(xc, std::f32::consts::LOG2_E);
        let (n, ni) = self.round_int(t);
        let a = self.mulk(n, LN2_HI);
        let r = self.b.ins().fsub(xc, a);
        let a = self.mulk(n, LN2_LO);
        let r = self.b.ins().fsub(r, a);
        let z = self.mul(r, r);
        let p = self.horner(r, &[1.987_569_1e-4, 1.398_2e-3, 8.333_452e-3, 4.166_579_6e-2, 1.666_666_5e-1, 0.5]);
        let p = self.mul(p, z);
        let p = self.b.ins().fadd(p, r);
        let p = self.addk(p, 1.0);
        // scale(p, ni): p · 2^(n>>1) · 2^(n - (n>>1)).
        let a = self.b.ins().sshr_imm_u(ni, 1);
        let b = self.b.ins().isub(ni, a);
        let pa = self.pow2i(a);
        let pb = self.pow2i(b);
        let p = self.mul(p, pa);
        self.mul(p, pb)
    }

    /// `vmath::pow2i`.
    fn pow2i(&mut self, n: Value) -> Value {
        let e = self.b.ins().iadd_imm_s(n, 127);
        let e = self.b.ins().ishl_imm_u(e, 23);
        self.float(e)
    }
}

//! `vmath`'s sin, cos and exp written out in Cranelift IR: the same f32 operations in the same
//! order (Rust neither contracts nor reassociates float arithmetic), so every non-NaN result
//! has `vmath`'s bits; a NaN result takes the helper (the interpreter's bits for NaNs). Inline,
//! they cost no call, which would spill every live float register. Written once over the value's
//! type: `f32` for the scalar JIT, `f32x4` (four invocations) for the SIMD one.
use cranelift_codegen::ir::condcodes::FloatCC;
use cranelift_codegen::ir::{types, InstBuilder, MemFlagsData, Type, Value};
use cranelift_frontend::FunctionBuilder;

use super::Gen;

const ROUND: f32 = 12_582_912.0;
const ROUND_BITS: i64 = 0x4B40_0000;
const PIO2_1: f32 = 1.570_312_5;
const PIO2_2: f32 = 4.837_513e-4;
const PIO2_3: f32 = 7.549_79e-8;
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;

/// Which function.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(in crate::shader::jit) enum Fn1 {
    Sin,
    Cos,
    Exp,
}

impl Gen<'_, '_, '_> {
    /// The f32 function `f` of `x` (an F32 value), as an F32 value.
    pub(super) fn vmath1(&mut self, f: Fn1, x: Value) -> Value {
        vmath(self.b, f, x)
    }
}

/// The function `f` of `x`, an `f32` or `f32x4` value, as a value of the same type.
pub(in crate::shader::jit) fn vmath(b: &mut FunctionBuilder, f: Fn1, x: Value) -> Value {
    let ty = b.func.dfg.value_type(x);
    let mut e = Emit { b, ty, ity: if ty.is_vector() { types::I32X4 } else { types::I32 } };
    match f {
        Fn1::Sin | Fn1::Cos => e.sin_cos(f == Fn1::Cos, x),
        Fn1::Exp => e.exp(x),
    }
}

struct Emit<'e, 'f> {
    b: &'e mut FunctionBuilder<'f>,
    /// The float type and the integer type of the same shape.
    ty: Type,
    ity: Type,
}

impl Emit<'_, '_> {
    fn k(&mut self, v: f32) -> Value {
        let s = self.b.ins().f32const(v);
        if self.ty.is_vector() { self.b.ins().splat(self.ty, s) } else { s }
    }
    fn ik(&mut self, v: i64) -> Value {
        let s = self.b.ins().iconst(types::I32, v as i32 as u32 as i64);
        if self.ty.is_vector() { self.b.ins().splat(self.ity, s) } else { s }
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
        self.b.ins().bitcast(self.ity, MemFlagsData::new(), x)
    }
    fn float(&mut self, x: Value) -> Value {
        self.b.ins().bitcast(self.ty, MemFlagsData::new(), x)
    }
    fn iaddk(&mut self, x: Value, k: i64) -> Value {
        let k = self.ik(k);
        self.b.ins().iadd(x, k)
    }
    fn bandk(&mut self, x: Value, k: i64) -> Value {
        let k = self.ik(k);
        self.b.ins().band(x, k)
    }
    fn shl(&mut self, x: Value, s: i64) -> Value {
        let s = self.b.ins().iconst(types::I32, s);
        self.b.ins().ishl(x, s)
    }
    /// `c ? x : y` for a comparison result `c` of this shape (a lane mask for vectors).
    fn select(&mut self, c: Value, x: Value, y: Value) -> Value {
        if self.ty.is_vector() {
            let c = self.b.ins().bitcast(self.ty, MemFlagsData::new(), c);
            self.b.ins().bitselect(c, x, y)
        } else {
            self.b.ins().select(c, x, y)
        }
    }
    /// `vmath::round_int`: (t rounded to an integer, that integer as i32).
    fn round_int(&mut self, t: Value) -> (Value, Value) {
        let s = self.addk(t, ROUND);
        let n = self.addk(s, -ROUND);
        let sb = self.bits(s);
        let ni = self.iaddk(sb, -ROUND_BITS);
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
        let r = self.select(big, zero, r);
        let q = self.bandk(ji, 3);
        let q = if cos { self.iaddk(q, 1) } else { q };
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
        let sign = self.bandk(rb, 0x8000_0000u32 as i64);
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
        let odd = self.bandk(q, 1);
        let odd = self.b.ins().ineg(odd);
        let from_c = self.b.ins().band(c, odd);
        let not_odd = self.b.ins().bnot(odd);
        let from_s = self.b.ins().band(s, not_odd);
        let v = self.b.ins().bor(from_c, from_s);
        let flip = self.bandk(q, 2);
        let flip = self.shl(flip, 30);
        let v = self.b.ins().bxor(v, flip);
        self.float(v)
    }

    fn exp(&mut self, x: Value) -> Value {
        // f32::clamp(-104, 89): NaN passes.
        let lo = self.k(-104.0);
        let below = self.b.ins().fcmp(FloatCC::LessThan, x, lo);
        let x = self.select(below, lo, x);
        let hi = self.k(89.0);
        let above = self.b.ins().fcmp(FloatCC::GreaterThan, x, hi);
        let xc = self.select(above, hi, x);
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
        let one = self.b.ins().iconst(types::I32, 1);
        let a = self.b.ins().sshr(ni, one);
        let b = self.b.ins().isub(ni, a);
        let pa = self.pow2i(a);
        let pb = self.pow2i(b);
        let p = self.mul(p, pa);
        self.mul(p, pb)
    }

    /// `vmath::pow2i`.
    fn pow2i(&mut self, n: Value) -> Value {
        let e = self.iaddk(n, 127);
        let e = self.shl(e, 23);
        self.float(e)
    }
}

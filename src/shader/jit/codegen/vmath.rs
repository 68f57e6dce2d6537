//! `vmath`'s sin, cos and exp written out in Cranelift IR: the same f32 operations in the same
//! order (Rust neither contracts nor reassociates float arithmetic), so every non-NaN result
//! has `vmath`'s bits; a NaN result takes the helper (the interpreter's bits for NaNs). Inline,
//! they cost no call, which would spill every live float register. Written once over the value's
//! type: `f32` for the scalar JIT, `f32x4` parts for the SIMD one, whose parts are emitted
//! step by step side by side (independent chains the core overlaps).
use cranelift_codegen::ir::condcodes::FloatCC;
use cranelift_codegen::ir::{types, ConstantData, InstBuilder, MemFlagsData, Type, Value};
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
        vmath(self.b, f, &[x])[0]
    }
}

/// The function `f` of each of `xs`, `f32` or `f32x4` values of one type, as values of that type.
pub(in crate::shader::jit) fn vmath(b: &mut FunctionBuilder, f: Fn1, xs: &[Value]) -> Vec<Value> {
    let ty = b.func.dfg.value_type(xs[0]);
    let mut e = Emit { b, ty, ity: if ty.is_vector() { types::I32X4 } else { types::I32 }, n: xs.len() };
    let x = xs.to_vec();
    match f {
        Fn1::Sin | Fn1::Cos => e.sin_cos(f == Fn1::Cos, &x),
        Fn1::Exp => e.exp(&x),
    }
}

/// A 128-bit vector of type `ty` with `bits` in every 32-bit lane: a constant-pool entry, which
/// instructions read as a memory operand (no register held across the code, nothing built).
pub(in crate::shader::jit) fn splat_const(b: &mut FunctionBuilder, ty: Type, bits: u32) -> Value {
    let bytes: Vec<u8> = (0..4).flat_map(|_| bits.to_le_bytes()).collect();
    let c = b.func.dfg.constants.insert(ConstantData::from(bytes));
    b.ins().vconst(ty, c)
}

/// Values of one step, one per part.
type Xs = Vec<Value>;

struct Emit<'e, 'f> {
    b: &'e mut FunctionBuilder<'f>,
    /// The float type and the integer type of the same shape.
    ty: Type,
    ity: Type,
    /// Parts.
    n: usize,
}

impl<'f> Emit<'_, 'f> {
    fn each(&mut self, a: &Xs, f: impl Fn(&mut FunctionBuilder<'f>, Value) -> Value) -> Xs {
        a.iter().map(|&x| f(self.b, x)).collect()
    }
    fn zip(&mut self, a: &Xs, b: &Xs, f: impl Fn(&mut FunctionBuilder<'f>, Value, Value) -> Value) -> Xs {
        a.iter().zip(b).map(|(&x, &y)| f(self.b, x, y)).collect()
    }
    fn k(&mut self, v: f32) -> Xs {
        let s = if self.ty.is_vector() { splat_const(self.b, self.ty, v.to_bits()) } else { self.b.ins().f32const(v) };
        vec![s; self.n]
    }
    fn ik(&mut self, v: i64) -> Xs {
        let s = if self.ty.is_vector() { splat_const(self.b, self.ity, v as u32) } else { self.b.ins().iconst(types::I32, v as i32 as u32 as i64) };
        vec![s; self.n]
    }
    fn mul(&mut self, a: &Xs, b: &Xs) -> Xs {
        self.zip(a, b, |b, x, y| b.ins().fmul(x, y))
    }
    fn sub(&mut self, a: &Xs, b: &Xs) -> Xs {
        self.zip(a, b, |b, x, y| b.ins().fsub(x, y))
    }
    fn add(&mut self, a: &Xs, b: &Xs) -> Xs {
        self.zip(a, b, |b, x, y| b.ins().fadd(x, y))
    }
    fn mulk(&mut self, a: &Xs, k: f32) -> Xs {
        let k = self.k(k);
        self.mul(a, &k)
    }
    fn addk(&mut self, a: &Xs, k: f32) -> Xs {
        let k = self.k(k);
        self.add(a, &k)
    }
    fn fcmp(&mut self, cc: FloatCC, a: &Xs, b: &Xs) -> Xs {
        self.zip(a, b, |b, x, y| b.ins().fcmp(cc, x, y))
    }
    fn bits(&mut self, x: &Xs) -> Xs {
        let ity = self.ity;
        self.each(x, |b, x| b.ins().bitcast(ity, MemFlagsData::new(), x))
    }
    fn float(&mut self, x: &Xs) -> Xs {
        let ty = self.ty;
        self.each(x, |b, x| b.ins().bitcast(ty, MemFlagsData::new(), x))
    }
    fn iaddk(&mut self, x: &Xs, k: i64) -> Xs {
        let k = self.ik(k);
        self.zip(x, &k, |b, x, y| b.ins().iadd(x, y))
    }
    fn bandk(&mut self, x: &Xs, k: i64) -> Xs {
        let k = self.ik(k);
        self.zip(x, &k, |b, x, y| b.ins().band(x, y))
    }
    fn shl(&mut self, x: &Xs, s: i64) -> Xs {
        let s = self.b.ins().iconst(types::I32, s);
        self.each(x, |b, x| b.ins().ishl(x, s))
    }
    /// `c ? x : y` for a comparison result `c` of this shape (a lane mask for vectors).
    fn select(&mut self, c: &Xs, x: &Xs, y: &Xs) -> Xs {
        let (vector, ty) = (self.ty.is_vector(), self.ty);
        (0..self.n)
            .map(|p| {
                if vector {
                    let c = self.b.ins().bitcast(ty, MemFlagsData::new(), c[p]);
                    self.b.ins().bitselect(c, x[p], y[p])
                } else {
                    self.b.ins().select(c[p], x[p], y[p])
                }
            })
            .collect()
    }
    /// `vmath::round_int`: (t rounded to an integer, that integer as i32).
    fn round_int(&mut self, t: &Xs) -> (Xs, Xs) {
        let s = self.addk(t, ROUND);
        let n = self.addk(&s, -ROUND);
        let sb = self.bits(&s);
        let ni = self.iaddk(&sb, -ROUND_BITS);
        (n, ni)
    }

    /// `vmath::horner`.
    fn horner(&mut self, x: &Xs, c: &[f32]) -> Xs {
        let mut acc = self.k(c[0]);
        for &k in &c[1..] {
            let m = self.mul(&acc, x);
            acc = self.addk(&m, k);
        }
        acc
    }

    fn sin_cos(&mut self, cos: bool, x: &Xs) -> Xs {
        // reduce_half_pi
        let t = self.mulk(x, std::f32::consts::FRAC_2_PI);
        let (j, ji) = self.round_int(&t);
        let a = self.mulk(&j, PIO2_1);
        let r = self.sub(x, &a);
        let a = self.mulk(&j, PIO2_2);
        let r = self.sub(&r, &a);
        let a = self.mulk(&j, PIO2_3);
        let r = self.sub(&r, &a);
        let abs = self.each(&r, |b, x| b.ins().fabs(x));
        let one = self.k(1.0);
        let big = self.fcmp(FloatCC::GreaterThan, &abs, &one);
        let zero = self.k(0.0);
        let r = self.select(&big, &zero, &r);
        let q = self.bandk(&ji, 3);
        let q = if cos { self.iaddk(&q, 1) } else { q };
        // sin_cos_poly
        let z = self.mul(&r, &r);
        let p = self.mulk(&z, -1.951_529_6e-4);
        let p = self.addk(&p, 8.332_161e-3);
        let p = self.mul(&p, &z);
        let p = self.addk(&p, -1.666_665_5e-1);
        let p = self.mul(&p, &z);
        let p = self.mul(&p, &r);
        let s = self.add(&p, &r);
        let (sb, rb) = (self.bits(&s), self.bits(&r));
        let sign = self.bandk(&rb, 0x8000_0000u32 as i64);
        let s = self.zip(&sb, &sign, |b, x, y| b.ins().bor(x, y));
        let p = self.mulk(&z, 2.443_315_7e-5);
        let p = self.addk(&p, -1.388_731_6e-3);
        let p = self.mul(&p, &z);
        let p = self.addk(&p, 4.166_664_6e-2);
        let p = self.mul(&p, &z);
        let p = self.mul(&p, &z);
        let h = self.mulk(&z, 0.5);
        let c = self.sub(&p, &h);
        let c = self.addk(&c, 1.0);
        let c = self.bits(&c);
        // sin_quadrant
        let odd = self.bandk(&q, 1);
        let odd = self.each(&odd, |b, x| b.ins().ineg(x));
        let from_c = self.zip(&c, &odd, |b, x, y| b.ins().band(x, y));
        let not_odd = self.each(&odd, |b, x| b.ins().bnot(x));
        let from_s = self.zip(&s, &not_odd, |b, x, y| b.ins().band(x, y));
        let v = self.zip(&from_c, &from_s, |b, x, y| b.ins().bor(x, y));
        let flip = self.bandk(&q, 2);
        let flip = self.shl(&flip, 30);
        let v = self.zip(&v, &flip, |b, x, y| b.ins().bxor(x, y));
        self.float(&v)
    }

    fn exp(&mut self, x: &Xs) -> Xs {
        // f32::clamp(-104, 89): NaN passes.
        let lo = self.k(-104.0);
        let below = self.fcmp(FloatCC::LessThan, x, &lo);
        let x = self.select(&below, &lo, x);
        let hi = self.k(89.0);
        let above = self.fcmp(FloatCC::GreaterThan, &x, &hi);
        let xc = self.select(&above, &hi, &x);
        let t = self.mulk(&xc, std::f32::consts::LOG2_E);
        let (n, ni) = self.round_int(&t);
        let a = self.mulk(&n, LN2_HI);
        let r = self.sub(&xc, &a);
        let a = self.mulk(&n, LN2_LO);
        let r = self.sub(&r, &a);
        let z = self.mul(&r, &r);
        let p = self.horner(&r, &[1.987_569_1e-4, 1.398_2e-3, 8.333_452e-3, 4.166_579_6e-2, 1.666_666_5e-1, 0.5]);
        let p = self.mul(&p, &z);
        let p = self.add(&p, &r);
        let p = self.addk(&p, 1.0);
        // scale(p, ni): p · 2^(n>>1) · 2^(n - (n>>1)).
        let one = self.b.ins().iconst(types::I32, 1);
        let a = self.each(&ni, |b, x| b.ins().sshr(x, one));
        let b = self.zip(&ni, &a, |b, x, y| b.ins().isub(x, y));
        let pa = self.pow2i(&a);
        let pb = self.pow2i(&b);
        let p = self.mul(&p, &pa);
        self.mul(&p, &pb)
    }

    /// `vmath::pow2i`.
    fn pow2i(&mut self, n: &Xs) -> Xs {
        let e = self.iaddk(n, 127);
        let e = self.shl(&e, 23);
        self.float(&e)
    }
}

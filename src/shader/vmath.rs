//! Branch-free `f32` versions of GLSL.std.450's float functions, for the lane executor.
//!
//! Each function exists twice: `sin1` etc. for one value, and `sin` etc. over a lane array,
//! which is the one-value function mapped over the array. The one-value bodies have no
//! branches and no calls (special cases are selects, rounding is the 1.5·2^23 trick, powers of
//! two are built from bits), so LLVM vectorises the array loops with the baseline x86-64
//! instruction set; both forms give the same bits, and `alu` (the constant folder and the
//! executor's generic path) uses the one-value form, so no path can disagree with another.
//!
//! Precision is what Vulkan requires of 32-bit floats ("Precision and Operation of SPIR-V
//! Instructions"): sin/cos absolute error ≤ 2^-11 in [-π, π], exp/exp2 ≤ 3 + 2·|x| ULP,
//! log/log2 ≤ 3 ULP outside [0.5, 2] and absolute ≤ 2^-21 inside, inversesqrt ≤ 2 ULP; tan,
//! pow and atan2 inherit from their formulas, atan ≤ 4096 ULP. The polynomials (minimax fits of
//! the classic single-precision math libraries) do better, as the tests hold them to: sin and cos
//! within 2^-22 on [-π, π], exp and exp2 within 2 ULP on [-2, 2], log and log2 on [0.5, 2] within
//! 2 ULP of the result or 2^-25, atan within 3 ULP; pow as its formula gives. `fma` is exact, as
//! the host's `mul_add`, without the host's FMA instruction. Denormal inputs and results are
//! kept, not flushed. Beyond |x| = 2^22·π/2 the argument reduction of sin, cos and tan no
//! longer finds the quadrant; the spec sets no bound there, and sin and cos stay in [-1, 1].
use std::f32::consts::{FRAC_2_PI, FRAC_PI_2, FRAC_PI_4, PI};

/// Adding then subtracting 1.5·2^23 rounds an `f32` of magnitude below 2^22 to an integer
/// (ties to even), and the sum's low mantissa bits hold that integer in two's complement.
const ROUND: f32 = 12_582_912.0;
const ROUND_BITS: u32 = 0x4B40_0000;

/// π/2 in three parts: the first two have few enough bits that `j · part` is exact for the
/// quadrant counts j that matter, so `x - j·π/2` loses nothing to cancellation.
const PIO2_1: f32 = 1.570_312_5;
const PIO2_2: f32 = 4.837_513e-4;
const PIO2_3: f32 = 7.549_79e-8;

const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
const LOG2E_M1: f32 = 0.442_695_04;

/// The integer `t` rounds to and its bits (`t` finite, |t| < 2^22).
#[inline(always)]
fn round_int(t: f32) -> (f32, i32) {
    let s = t + ROUND;
    (s - ROUND, s.to_bits().wrapping_sub(ROUND_BITS) as i32)
}

/// `a` where `c` holds, else `b`, by bit masks (a compiler may turn an `if` into a branch).
#[inline(always)]
fn pick(c: bool, a: f32, b: f32) -> f32 {
    let m = (c as u32).wrapping_neg();
    f32::from_bits((a.to_bits() & m) | (b.to_bits() & !m))
}

/// The polynomial with coefficients `c` (highest degree first) at x, by Horner's rule.
#[inline(always)]
fn horner<const K: usize>(x: f32, c: [f32; K]) -> f32 {
    c[1..].iter().fold(c[0], |acc, &k| acc * x + k)
}

/// 2^n for n in [-126, 127], from bits.
#[inline(always)]
fn pow2i(n: i32) -> f32 {
    f32::from_bits((n.wrapping_add(127) as u32) << 23)
}

/// x = j·π/2 + r, |r| ≤ π/4 (a little more where x·2/π rounds across a half): (r, j mod 4).
#[inline(always)]
fn reduce_half_pi(x: f32) -> (f32, u32) {
    let (j, ji) = round_int(x * FRAC_2_PI);
    let r = ((x - j * PIO2_1) - j * PIO2_2) - j * PIO2_3;
    // Huge |x| (no quadrant) leaves r large: bound it so results stay in [-1, 1]; NaN passes.
    let r = if r.abs() > 1.0 { 0.0 } else { r };
    (r, ji as u32 & 3)
}

/// sin r and cos r for |r| ≤ π/4 (slightly beyond is fine).
#[inline(always)]
fn sin_cos_poly(r: f32) -> (f32, f32) {
    let z = r * r;
    let s = ((-1.951_529_6e-4 * z + 8.332_161e-3) * z - 1.666_665_5e-1) * z * r + r;
    // sin r has the sign of r, also for r = -0 (where the sum above gives +0).
    let s = f32::from_bits(s.to_bits() | (r.to_bits() & 0x8000_0000));
    let c = ((2.443_315_7e-5 * z - 1.388_731_6e-3) * z + 4.166_664_6e-2) * z * z - 0.5 * z + 1.0;
    (s, c)
}

/// sin of j·π/2 + r from the quadrant q = j mod 4.
#[inline(always)]
fn sin_quadrant(r: f32, q: u32) -> f32 {
    let (s, c) = sin_cos_poly(r);
    // Selects by bit masks: a plain `if` here was turned into a branch per lane.
    let odd = (q & 1).wrapping_neg();
    let v = (c.to_bits() & odd) | (s.to_bits() & !odd);
    f32::from_bits(v ^ ((q & 2) << 30))
}

#[inline(always)]
pub fn sin1(x: f32) -> f32 {
    let (r, q) = reduce_half_pi(x);
    sin_quadrant(r, q)
}

#[inline(always)]
pub fn cos1(x: f32) -> f32 {
    let (r, q) = reduce_half_pi(x);
    sin_quadrant(r, q.wrapping_add(1))
}

#[inline(always)]
pub fn tan1(x: f32) -> f32 {
    let (r, q) = reduce_half_pi(x);
    let (s, c) = sin_cos_poly(r);
    // tan(r + π/2) = -cos r / sin r.
    if q & 1 != 0 {
        -c / s
    } else {
        s / c
    }
}

/// e^x: x = n·ln 2 + r, |r| ≤ ln2/2; e^r by polynomial; 2^n applied in two halves so that
/// results in the denormal range round once and overflow gives infinity.
#[inline(always)]
pub fn exp1(x: f32) -> f32 {
    let xc = x.clamp(-104.0, 89.0);
    let (n, ni) = round_int(xc * std::f32::consts::LOG2_E);
    let r = (xc - n * LN2_HI) - n * LN2_LO;
    let z = r * r;
    let p = horner(r, [1.987_569_1e-4, 1.398_2e-3, 8.333_452e-3, 4.166_579_6e-2, 1.666_666_5e-1, 0.5]);
    let p = p * z + r + 1.0;
    scale(p, ni)
}

/// p · 2^n for n in [-252, 254], rounding once.
#[inline(always)]
fn scale(p: f32, n: i32) -> f32 {
    let a = n >> 1;
    p * pow2i(a) * pow2i(n.wrapping_sub(a))
}

/// 2^x: x = n + r, |r| ≤ 1/2.
#[inline(always)]
pub fn exp2_1(x: f32) -> f32 {
    let xc = x.clamp(-152.0, 129.0);
    let (n, ni) = round_int(xc);
    let r = xc - n;
    let p = horner(r, [1.535_336_2e-4, 1.339_887_4e-3, 9.618_437e-3, 5.550_332_5e-2, 2.402_264_8e-1, 6.931_472e-1]);
    let p = p * r + 1.0;
    scale(p, ni)
}

/// x = 2^e · (1 + m), m in [√½ - 1, √2 - 1): (m, e) for finite x > 0, denormals included.
#[inline(always)]
fn split_log(x: f32) -> (f32, f32) {
    let tiny = x < f32::MIN_POSITIVE;
    let xs = if tiny { x * 8_388_608.0 } else { x };
    let bits = xs.to_bits();
    let e = ((bits >> 23) & 0xFF) as i32 - 126 - if tiny { 23 } else { 0 };
    // The mantissa in [0.5, 1); below √½ it is doubled so 1 + m straddles 1.
    let f = f32::from_bits((bits & 0x007F_FFFF) | 0x3F00_0000);
    let low = f < std::f32::consts::FRAC_1_SQRT_2;
    let m = if low { f + f - 1.0 } else { f - 1.0 };
    (m, (e - low as i32) as f32)
}

/// log(1 + m) - m + m²/2, the polynomial part shared by log and log2.
#[inline(always)]
fn log_poly(m: f32) -> f32 {
    let z = m * m;
    let p = horner(m, [
        7.037_683_6e-2, -1.151_461e-1, 1.167_699_9e-1, -1.242_014_1e-1, 1.424_932_3e-1, -1.666_805_8e-1,
        2.000_071_4e-1, -2.499_999_4e-1, 3.333_333e-1,
    ]);
    p * m * z
}

/// The special cases of log and log2: log 0 = -∞, log of a negative is NaN, log ∞ = ∞, and NaN
/// stays itself.
#[inline(always)]
fn log_special(x: f32, v: f32) -> f32 {
    let v = if x == 0.0 { f32::NEG_INFINITY } else { v };
    let v = if x == f32::INFINITY { x } else { v };
    let v = if x < 0.0 { f32::NAN } else { v };
    if x.is_nan() {
        x
    } else {
        v
    }
}

#[inline(always)]
pub fn log1(x: f32) -> f32 {
    let (m, e) = split_log(x);
    let y = log_poly(m) + e * LN2_LO - 0.5 * (m * m);
    log_special(x, (m + y) + e * LN2_HI)
}

#[inline(always)]
pub fn log2_1(x: f32) -> f32 {
    let (m, e) = split_log(x);
    let y = log_poly(m) - 0.5 * (m * m);
    // log2(1 + m) = (m + y)·log2(e), with log2(e) = 1 + LOG2E_M1 so the large part stays exact.
    let v = y * LOG2E_M1 + m * LOG2E_M1 + y + m + e;
    log_special(x, v)
}

/// x^y as exp2(y·log2 x), the formula Vulkan's precision is inherited from. Results SPIR-V
/// leaves undefined (x < 0, or x = 0 with y ≤ 0) are those of the formula.
#[inline(always)]
pub fn pow1(x: f32, y: f32) -> f32 {
    exp2_1(y * log2_1(x))
}

#[inline(always)]
pub fn sqrt1(x: f32) -> f32 {
    x.sqrt()
}

/// 1/√x: two correctly rounded operations, within 2 ULP.
#[inline(always)]
pub fn inverse_sqrt1(x: f32) -> f32 {
    1.0 / x.sqrt()
}

/// atan x: reduced to |t| ≤ tan(π/8) through atan x = π/2 + atan(-1/x) and
/// atan x = π/4 + atan((x - 1)/(x + 1)).
#[inline(always)]
pub fn atan1(x: f32) -> f32 {
    let a = x.abs();
    let big = a > 2.414_213_6;
    let mid = a > 0.414_213_57;
    // Both quotients for every lane, chosen by masks: `if` chains became branches per lane.
    let t = pick(big, -1.0 / a, pick(mid, (a - 1.0) / (a + 1.0), a));
    let base = pick(big, FRAC_PI_2, pick(mid, FRAC_PI_4, 0.0));
    let z = t * t;
    let v = base + (((8.053_744_5e-2 * z - 1.387_768_6e-1) * z + 1.997_771_1e-1) * z - 3.333_295e-1) * z * t + t;
    f32::from_bits(v.to_bits() | (x.to_bits() & 0x8000_0000))
}

/// atan2(y, x): atan(y/x) moved by ±π into the half plane of x < 0.
#[inline(always)]
pub fn atan2_1(y: f32, x: f32) -> f32 {
    let v = atan1(y / x);
    let turn = f32::from_bits(PI.to_bits() | (y.to_bits() & 0x8000_0000));
    if x < 0.0 || (x == 0.0 && x.is_sign_negative()) {
        v + turn
    } else {
        v
    }
}

/// Fused multiply-add, rounded once. a·b is exact in f64 (24 + 24 bits); the sum is rounded to
/// odd in f64 (53 bits ≥ 24 + 2), after which rounding to f32 is correct.
#[inline(always)]
pub fn fma1(a: f32, b: f32, c: f32) -> f32 {
    let p = a as f64 * b as f64;
    let c = c as f64;
    let s = p + c;
    // The exact error of the sum (TwoSum).
    let pp = s - c;
    let err = (p - pp) + (c - (s - pp));
    let bits = s.to_bits();
    // Round to odd: an inexact sum whose error points towards zero steps down one ulp in
    // magnitude, then the last bit is set. Infinities and NaN have a NaN error: kept as they are.
    let towards_zero = (err < 0.0) != (s < 0.0);
    let stepped = if towards_zero { bits - 1 } else { bits };
    let odd = if err != 0.0 && s.is_finite() { stepped | 1 } else { bits };
    f64::from_bits(odd) as f32
}

/// Applies a one-value function to every lane.
#[inline(always)]
fn map<const N: usize>(x: &[f32; N], f: impl Fn(f32) -> f32) -> [f32; N] {
    let mut out = [0.0; N];
    for (o, &v) in out.iter_mut().zip(x) {
        *o = f(v);
    }
    out
}

macro_rules! lane_fns {
    ($($(#[$doc:meta])* $name:ident = $one:ident;)*) => {
        $(
            $(#[$doc])*
            #[inline(never)]
            pub fn $name<const N: usize>(x: &[f32; N]) -> [f32; N] {
                map(x, $one)
            }
        )*
    };
}

lane_fns! {
    sin = sin1;
    cos = cos1;
    tan = tan1;
    exp = exp1;
    exp2 = exp2_1;
    log = log1;
    log2 = log2_1;
    sqrt = sqrt1;
    inverse_sqrt = inverse_sqrt1;
    atan = atan1;
}

#[inline(never)]
pub fn pow<const N: usize>(x: &[f32; N], y: &[f32; N]) -> [f32; N] {
    let mut out = [0.0; N];
    for (l, o) in out.iter_mut().enumerate() {
        *o = pow1(x[l], y[l]);
    }
    out
}

#[inline(never)]
pub fn atan2<const N: usize>(y: &[f32; N], x: &[f32; N]) -> [f32; N] {
    let mut out = [0.0; N];
    for (l, o) in out.iter_mut().enumerate() {
        *o = atan2_1(y[l], x[l]);
    }
    out
}

/// Fused multiply-add over lanes, [`fma1`] in each.
#[inline(never)]
pub fn fma<const N: usize>(a: &[f32; N], b: &[f32; N], c: &[f32; N]) -> [f32; N] {
    let mut out = [0.0; N];
    for (l, o) in out.iter_mut().enumerate() {
        *o = fma1(a[l], b[l], c[l]);
    }
    out
}

#[cfg(test)]
#[path = "vmath_tests.rs"]
mod tests;

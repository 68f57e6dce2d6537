//! vmath against the host's f64 functions (an independent reference), over dense sweeps and
//! edge values, with Vulkan's precision bounds for 32-bit floats; and the lane-array forms
//! against the one-value forms, bit for bit.
use super::*;

/// The spacing of f32 values at the magnitude of `r` (denormal spacing below the normals).
fn ulp(r: f64) -> f64 {
    let a = (r as f32).abs();
    if a < f32::MIN_POSITIVE {
        2f64.powi(-149)
    } else if a.is_infinite() {
        2f64.powi(104)
    } else {
        let e = ((a.to_bits() >> 23) & 0xFF) as i32 - 127;
        2f64.powi(e - 23)
    }
}

/// `n` evenly spaced values over [lo, hi], both ends included.
fn sweep(lo: f32, hi: f32, n: usize) -> impl Iterator<Item = f32> {
    (0..=n).map(move |i| (lo as f64 + (hi as f64 - lo as f64) * i as f64 / n as f64) as f32)
}

/// Every `stride`-th positive finite f32 bit pattern, denormals included.
fn positive_bits(stride: u32) -> impl Iterator<Item = f32> {
    (1..0x7F80_0000u32).step_by(stride as usize).map(f32::from_bits)
}

/// The largest error of `f` against `reference` in the units `unit` gives; panics naming the
/// first input whose error exceeds `bound(x, reference)` in those units.
fn check(name: &str, xs: impl Iterator<Item = f32>, f: fn(f32) -> f32, reference: fn(f64) -> f64, unit: fn(f64) -> f64, bound: impl Fn(f32, f64) -> f64) -> f64 {
    let mut worst = 0f64;
    for x in xs {
        let (got, want) = (f(x) as f64, reference(x as f64));
        let err = if got == want { 0.0 } else { (got - want).abs() / unit(want) };
        assert!(err <= bound(x, want), "{name}({x:e}) = {got:e}, reference {want:e}: error {err:e} over {:e}", bound(x, want));
        worst = worst.max(err);
    }
    worst
}

fn absolute(_: f64) -> f64 {
    1.0
}

#[test]
fn sin_cos_within_2_pow_minus_11_on_minus_pi_to_pi() {
    let pi = std::f32::consts::PI;
    let spec = |_: f32, _: f64| 2f64.powi(-11);
    // What the implementation reaches: a few f32 ulps of 1.
    let own = |_: f32, _: f64| 2f64.powi(-22);
    for (name, f, r) in [("sin", sin1 as fn(f32) -> f32, f64::sin as fn(f64) -> f64), ("cos", cos1, f64::cos)] {
        check(name, sweep(-pi, pi, 1 << 20), f, r, absolute, spec);
        check(name, sweep(-pi, pi, 1 << 20), f, r, absolute, own);
        // Beyond [-π, π] the spec sets no bound; the reduction keeps results close for the
        // arguments shaders use (time, angles in degrees).
        check(name, sweep(-1e4, 1e4, 1 << 20), f, r, absolute, |_, _| 2f64.powi(-18));
    }
}

#[test]
fn sin_cos_small_arguments_keep_relative_precision() {
    // sin x ≈ x near zero: the result stays within a couple of ulps, denormals included.
    let xs = || positive_bits(9973).take_while(|&x| x < 0.01);
    check("sin", xs(), sin1, f64::sin, ulp, |_, _| 2.0);
    check("sin", xs().map(|x| -x), sin1, f64::sin, ulp, |_, _| 2.0);
}

#[test]
fn tan_inherits_from_sin_over_cos() {
    // tan = sin / cos with each within 2^-11 of the truth (and the divide's rounding).
    let e = 2f64.powi(-11);
    let bound = |x: f32, want: f64| {
        let (s, c) = ((x as f64).sin().abs(), (x as f64).cos().abs());
        ((s + e) / (c - e).max(1e-30) - s / c).abs().max(want.abs() - (s - e).max(0.0) / (c + e)) + 2.0 * ulp(want)
    };
    let h = std::f32::consts::FRAC_PI_2;
    check("tan", sweep(-h + 0.01, h - 0.01, 1 << 20), tan1, f64::tan, absolute, bound);
    check("tan", sweep(-3.0, 3.0, 1 << 18).filter(|x| (x.abs() - h).abs() > 0.01), tan1, f64::tan, ulp, |_, _| 4.0);
}

#[test]
fn exp_and_exp2_within_3_plus_2x_ulp() {
    let spec = |x: f32, _: f64| 3.0 + 2.0 * x.abs() as f64;
    check("exp", sweep(-103.0, 88.7, 1 << 21), exp1, f64::exp, ulp, spec);
    check("exp", sweep(-2.0, 2.0, 1 << 20), exp1, f64::exp, ulp, |_, _| 2.0);
    check("exp2", sweep(-150.0, 127.99, 1 << 21), exp2_1, f64::exp2, ulp, spec);
    check("exp2", sweep(-2.0, 2.0, 1 << 20), exp2_1, f64::exp2, ulp, |_, _| 2.0);
}

#[test]
fn log_and_log2_within_3_ulp_outside_and_2_pow_minus_21_inside_half_to_two() {
    let inside = |x: f32| (0.5..=2.0).contains(&x);
    let spec = |x: f32, want: f64| if inside(x) { 2f64.powi(-21) / ulp(want) } else { 3.0 };
    for (name, f, r) in [("log", log1 as fn(f32) -> f32, f64::ln as fn(f64) -> f64), ("log2", log2_1, f64::log2)] {
        check(name, positive_bits(997), f, r, ulp, spec);
        check(name, sweep(0.5, 2.0, 1 << 21), f, r, absolute, |_, _| 2f64.powi(-21));
        // Own precision inside: a few ulps of the result's magnitude near 1 as well.
        check(name, sweep(0.5, 2.0, 1 << 20), f, r, absolute, |_, want| 2.0 * ulp(want).max(2f64.powi(-26)));
    }
}

#[test]
fn pow_inherits_from_exp2_of_y_log2_x() {
    let mut worst = 0f64;
    for x in sweep(1e-3, 1e3, 2000).chain([0.5, 1.0, 2.0, 10.0]) {
        for y in sweep(-8.0, 8.0, 400) {
            let (got, want) = (pow1(x, y) as f64, (x as f64).powf(y as f64));
            let t = y as f64 * (x as f64).log2();
            // log2's allowed error, carried through the product and exp2's own bound.
            let log_err = if (0.5..=2.0).contains(&x) { 2f64.powi(-21) } else { 3.0 * ulp((x as f64).log2()) };
            let arg_err = (y as f64).abs() * log_err + ulp(t);
            let bound = want * std::f64::consts::LN_2 * arg_err * 1.01 + (3.0 + 2.0 * t.abs()) * ulp(want);
            assert!((got - want).abs() <= bound, "pow({x:e}, {y:e}) = {got:e}, reference {want:e}, bound {bound:e}");
            worst = worst.max((got - want).abs() / ulp(want));
        }
    }
    // What the formula gives where |y·log2 x| reaches 80: log2's few ulps, multiplied by y.
    assert!(worst < 128.0, "pow is {worst} ulp off");
}

#[test]
fn sqrt_correctly_rounded_and_inverse_sqrt_within_2_ulp() {
    check("sqrt", positive_bits(101), sqrt1, f64::sqrt, ulp, |_, _| 0.5);
    check("inversesqrt", positive_bits(101), inverse_sqrt1, |x| 1.0 / x.sqrt(), ulp, |_, _| 2.0);
}

#[test]
fn atan_within_4096_ulp_and_atan2_by_quadrant() {
    check("atan", sweep(-100.0, 100.0, 1 << 20), atan1, f64::atan, ulp, |_, _| 4096.0);
    check("atan", sweep(-100.0, 100.0, 1 << 20), atan1, f64::atan, ulp, |_, _| 3.0);
    check("atan", positive_bits(4099), atan1, f64::atan, ulp, |_, _| 3.0);
    let mut worst = 0f64;
    for y in sweep(-5.0, 5.0, 301) {
        for x in sweep(-5.0, 5.0, 301).chain([0.0, -0.0]) {
            let (got, want) = (atan2_1(y, x) as f64, (y as f64).atan2(x as f64));
            if y == 0.0 && x == 0.0 {
                continue; // undefined in GLSL
            }
            let err = (got - want).abs() / ulp(want);
            assert!(err <= 4096.0, "atan2({y}, {x}) = {got}, reference {want}");
            worst = worst.max(err);
        }
    }
    assert!(worst <= 8.0, "atan2 is {worst} ulp off");
}

/// A small deterministic generator for the random sweeps.
fn next(state: &mut u64) -> u64 {
    *state ^= *state << 13;
    *state ^= *state >> 7;
    *state ^= *state << 17;
    *state
}

#[test]
fn fma_is_the_correctly_rounded_fused_result() {
    // The host's fused multiply-add (libm fmaf) is the reference; the inputs mix exponents so
    // that the exact sum often lies just beside an f32 rounding boundary.
    let mut s = 0x9E37_79B9_7F4A_7C15u64;
    for i in 0..2_000_000u32 {
        let r = next(&mut s);
        let a = f32::from_bits((r as u32 & 0x807F_FFFF) | ((100 + (r >> 32) as u32 % 56) << 23));
        let b = f32::from_bits(((r >> 20) as u32 & 0x807F_FFFF) | ((100 + (r >> 40) as u32 % 56) << 23));
        let p = a * b;
        // c near -a·b (cancellation), near a·b·2^-k (rounding boundaries), or anywhere.
        let c = match i % 4 {
            0 => -p,
            1 => p * f32::from_bits(((127 - (r >> 50) as u32 % 30) << 23) | (r as u32 >> 9 & 1)),
            2 => f32::from_bits(next(&mut s) as u32 & 0xFF7F_FFFF),
            _ => f32::from_bits((p.to_bits() & 0xFF80_0000).wrapping_sub(24 << 23) | 0x0040_0000),
        };
        let (got, want) = (fma1(a, b, c), a.mul_add(b, c));
        assert!(got.to_bits() == want.to_bits() || (got.is_nan() && want.is_nan()), "fma({a:e}, {b:e}, {c:e}) = {got:e}, want {want:e}");
        // The lane form gives the same bits.
        let lanes = fma(&[a; 8], &[b; 8], &[c; 8]);
        assert!(lanes.iter().all(|v| v.to_bits() == got.to_bits() || (v.is_nan() && got.is_nan())), "lane fma({a:e}, {b:e}, {c:e})");
    }
}

fn edges() -> Vec<f32> {
    let mut v = vec![0.0, -0.0, 1.0, -1.0, 0.5, 2.0, f32::MIN_POSITIVE, 1e-45, 1e-40, f32::MAX, f32::INFINITY, f32::NEG_INFINITY, f32::NAN];
    v.extend(v.clone().iter().map(|x| -x));
    v
}

#[test]
fn edge_values_follow_ieee_where_the_result_is_defined() {
    let inf = f32::INFINITY;
    for (x, want) in [(0.0, 1.0), (-0.0, 1.0), (inf, inf), (-inf, 0.0), (89.0, inf), (-104.0, 0.0), (-103.0, 1e-45)] {
        assert_eq!(exp1(x), want, "exp({x})");
    }
    for (x, want) in [(0.0, 1.0), (128.0, inf), (-inf, 0.0), (-149.0, 1e-45), (-126.0, f32::MIN_POSITIVE), (10.0, 1024.0)] {
        assert_eq!(exp2_1(x), want, "exp2({x})");
    }
    for (x, want) in [(1.0, 0.0), (0.0, -inf), (-0.0, -inf), (inf, inf), (1e-45, -149.0), (8.0, 3.0), (0.25, -2.0)] {
        assert_eq!(log2_1(x), want, "log2({x})");
    }
    assert_eq!(log1(1.0), 0.0);
    assert_eq!(log1(0.0), -inf);
    assert!(log1(-1.0).is_nan() && log2_1(-1e-45).is_nan() && log1(-inf).is_nan());
    for f in [sin1, cos1, tan1] {
        assert!(f(inf).is_nan() && f(-inf).is_nan() && f(f32::NAN).is_nan());
    }
    assert_eq!((sin1(0.0).to_bits(), sin1(-0.0).to_bits(), cos1(0.0)), (0.0f32.to_bits(), (-0.0f32).to_bits(), 1.0));
    assert_eq!((atan1(inf), atan1(-inf), atan1(-0.0).to_bits()), (std::f32::consts::FRAC_PI_2, -std::f32::consts::FRAC_PI_2, (-0.0f32).to_bits()));
    assert_eq!((pow1(2.0, 10.0), pow1(0.0, 2.0), pow1(1.0, 7.5), pow1(4.0, 0.5)), (1024.0, 0.0, 1.0, 2.0));
    assert_eq!((inverse_sqrt1(0.0), inverse_sqrt1(4.0)), (inf, 0.5));
    // Huge arguments: no quadrant, but sin and cos stay in [-1, 1].
    for x in [1e10f32, -3e20, f32::MAX, 1.2e7] {
        assert!(sin1(x).abs() <= 1.0 && cos1(x).abs() <= 1.0, "sin/cos({x})");
    }
    // NaN in, NaN out, for every one-value function.
    for f in [sin1, cos1, tan1, exp1, exp2_1, log1, log2_1, sqrt1, inverse_sqrt1, atan1] {
        assert!(f(f32::NAN).is_nan());
    }
}

#[test]
fn lane_arrays_give_the_bits_of_the_one_value_forms() {
    let mut s = 0x1234_5678_9ABC_DEF1u64;
    let mut xs: Vec<f32> = edges();
    xs.extend((0..4000).map(|_| f32::from_bits(next(&mut s) as u32)));
    xs.extend((0..4000).map(|_| (next(&mut s) % 20_000) as f32 * 0.01 - 100.0));
    type Lanes = fn(&[f32; 8]) -> [f32; 8];
    type One = fn(f32) -> f32;
    let ones: [(Lanes, One); 10] = [
        (sin, sin1), (cos, cos1), (tan, tan1), (exp, exp1), (exp2, exp2_1), (log, log1), (log2, log2_1),
        (sqrt, sqrt1), (inverse_sqrt, inverse_sqrt1), (atan, atan1),
    ];
    let same = |a: f32, b: f32| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
    for chunk in xs.chunks_exact(8) {
        let x: [f32; 8] = chunk.try_into().unwrap();
        let y: [f32; 8] = std::array::from_fn(|l| x[(l + 3) % 8]);
        for (lanes, one) in ones {
            let out = lanes(&x);
            assert!((0..8).all(|l| same(out[l], one(x[l]))));
        }
        let (p, a, f) = (pow(&x, &y), atan2(&x, &y), fma(&x, &y, &x));
        assert!((0..8).all(|l| same(p[l], pow1(x[l], y[l])) && same(a[l], atan2_1(x[l], y[l])) && same(f[l], fma1(x[l], y[l], x[l]))));
    }
}

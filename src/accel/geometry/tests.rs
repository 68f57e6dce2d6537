use super::*;
use crate::accel::testing::xorshift;

/// The mantissa truncation equals `as i32` and `floor_lanes` equals `floor` on [0, 2^22):
/// every integer boundary of the bin and quantisation ranges and its float neighbours,
/// halves (round-to-even ties), and a sweep.
#[test]
fn vector_truncation_is_exact() {
    let mut xs = vec![0.0f32, 1e-30, 0.49999997, 0.5, 0.50000006, 1.5, 2.5, 31.999998, 4_194_303.5];
    for i in 0..=300u32 {
        let f = i as f32;
        xs.extend([f, f32::from_bits(f.to_bits().saturating_sub(1)), f32::from_bits(f.to_bits() + 1), f + 0.5]);
    }
    xs.extend((0..100_000).map(|i| i as f32 * 0.000_37));
    for q in xs.chunks(4) {
        let mut v = [0f32; 4];
        v[..q.len()].copy_from_slice(q);
        let got = trunc_lanes(Vec4::from_array(v));
        let got3 = trunc_lanes3(Vec3A::new(v[0], v[1], v[2]));
        let fl = floor_lanes(Vec4::from_array(v)).to_array();
        for k in 0..4 {
            assert_eq!(got[k], v[k] as i32, "{}", v[k]);
            assert_eq!(fl[k].to_bits(), v[k].floor().to_bits(), "{}", v[k]);
        }
        assert_eq!(&got3[..3], &got[..3]);
    }
}

/// The two-sum instance box equals the eight-corner one bit for bit on finite terms
/// (monotonic rounding), including signed zeros, overflow to infinity and mirrored axes.
#[test]
fn instance_box_from_two_sums_matches_eight_corners() {
    let mut next = xorshift(0x2545_f491_4f6c_dd1d);
    let specials = [0.0f32, -0.0, 1.0, -1.0, 3.0e38, -3.0e38, 1e-38, -1e-45, 0.5, 2.0];
    let mut pick = move || {
        let r = next();
        if r.is_multiple_of(3) {
            specials[(r >> 8) as usize % specials.len()]
        } else {
            ((r >> 11) as f64 / (1u64 << 53) as f64 * 200.0 - 100.0) as f32
        }
    };
    let bits = |b: ([f32; 3], [f32; 3])| (b.0.map(f32::to_bits), b.1.map(f32::to_bits));
    for _ in 0..200_000 {
        let m: [f32; 12] = std::array::from_fn(|_| pick());
        let (a, b, c) = (pick(), pick(), pick());
        let (d, e, f) = (pick(), pick(), pick());
        let bb = [a.min(d), b.min(e), c.min(f), a.max(d), b.max(e), c.max(f)];
        let want = instance_box_corners(&m, &bb);
        let got = instance_bounds_of(&m, Some(&bb));
        assert_eq!(bits(got), bits(want), "transform {m:?} box {bb:?}");
    }
}

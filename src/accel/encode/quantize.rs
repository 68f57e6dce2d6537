//! One wide node's bytes: child boxes quantised conservatively into the node's frame. Used by
//! the emission and by refit.
//!
//! Owns: the quantisation arithmetic. Must not touch: which children a node has.
use crate::accel::geometry::{floor_lanes, Aabb};
use crate::accel::layout::WideNode;
use bytemuck::Zeroable;
use glam::{Vec3A, Vec4};

/// Quantise child boxes into the frame of `node_box`, rounding outward and verifying with the
/// exact decode arithmetic of `WideNode::child_box`, so decoded boxes always contain the input.
/// The child boxes come as vectors (slots past `cnt` hold the node's lo corner): each axis'
/// four values come from one transpose in registers, where gathering them through a stack
/// array stalled on store-to-load forwarding.
#[inline]
pub fn quantize_node(node_box: &Aabb, clo: &[Vec3A; 4], chi: &[Vec3A; 4], cnt: usize, child: &[u32], kind: &[u8]) -> WideNode {
    let cnt = cnt.min(4);
    let col = |v: Vec3A| Vec4::from((v, 0.0));
    let tlo = glam::Mat4::from_cols(col(clo[0]), col(clo[1]), col(clo[2]), col(clo[3])).transpose();
    let thi = glam::Mat4::from_cols(col(chi[0]), col(chi[1]), col(chi[2]), col(chi[3])).transpose();
    let mut n = WideNode::zeroed();
    n.origin = node_box.lo;
    for a in 0..3 {
        let lo = node_box.lo[a];
        let hi = node_box.hi[a];
        let e = frame_exponent(lo, hi);
        n.exp[a] = e as u8;
        let s = f32::from_bits(e << 23);
        let inv_s = 1.0 / s; // exact: s is a power of two
        // Four children at once: truncated guesses (clamped in float first: the same values as
        // the scalar `(x as u32).min(255)` for x > 0, else 0), checked with the decode
        // arithmetic lane-wise (the same IEEE operations as `quantize_scalar`); lanes that
        // need a step (rare) take the scalar path below.
        let (blo, bhi) = (tlo.col(a), thi.col(a));
        let (lov, sv, top) = (Vec4::splat(lo), Vec4::splat(s), Vec4::splat(255.0));
        // floor of values clamped to [0, 255] is the truncation `as u32` would give, already
        // as a float (no conversions until the final byte extraction).
        let qlf = floor_lanes(((blo - lov) * inv_s).max(Vec4::ZERO).min(top));
        let q0 = floor_lanes(((bhi - lov) * inv_s).max(Vec4::ZERO).min(top));
        let bad_l = (lov + qlf * sv).cmpgt(blo) & qlf.cmpgt(Vec4::ZERO);
        // The scalar search steps qh up from the truncated guess to the first value whose
        // decode reaches b.hi: usually the guess itself or the next one.
        let q1 = (q0 + Vec4::ONE).min(top);
        let ok0 = (lov + q0 * sv).cmpge(bhi) | q0.cmpge(top);
        let ok1 = (lov + q1 * sv).cmpge(bhi) | q1.cmpge(top);
        let qh = Vec4::select(ok0, q0, q1);
        let bad_h = !(ok0 | ok1);
        if !bad_l.any() && !bad_h.any() {
            // Integers below 2^23 read from the mantissa after adding 2^23 (exact).
            let magic = Vec4::splat(8_388_608.0);
            let (ql, qh) = ((qlf + magic).to_array(), (qh + magic).to_array());
            for c in 0..cnt {
                n.qlo[a][c] = ql[c].to_bits() as u8;
                n.qhi[a][c] = qh[c].to_bits() as u8;
            }
            continue;
        }
        for c in 0..cnt {
            (n.qlo[a][c], n.qhi[a][c]) = quantize_scalar(lo, s, inv_s, clo[c][a], chi[c][a]);
        }
    }
    n.child_count = cnt as u8;
    for c in 0..cnt {
        n.child[c] = child.get(c).copied().unwrap_or(0);
        n.kind[c] = kind.get(c).copied().unwrap_or(0);
    }
    n
}

/// The frame exponent of one axis: the smallest power of two s = 2^(e-127) with
/// lo + 255·s >= hi, found from the extent, then verified.
#[inline(always)]
fn frame_exponent(lo: f32, hi: f32) -> u32 {
    let ext = (hi - lo).max(0.0);
    let mut e: u32 = if ext > 0.0 && ext.is_finite() {
        ((ext * (1.0 / 255.0)).to_bits() >> 23 & 0xff).max(1)
    } else if ext > 0.0 {
        254
    } else {
        1
    };
    // Usually `e` already fits or the next one does: two explicit steps before the general
    // loop, which the compiler otherwise turned into a 16-wide search with a serial
    // byte-by-byte reduction (a third of the node's encoding time).
    let short = |e: u32| e < 254 && lo + 255.0 * f32::from_bits(e << 23) < hi;
    if short(e) {
        e += 1;
        if short(e) {
            e += 1;
            while short(e) {
                e += 1;
            }
        }
    }
    e
}

/// One child's bounds on one axis quantised outward in the frame (lo, s): guesses by
/// truncation, then made exact with the decode arithmetic (usually zero or one step).
#[inline(always)]
fn quantize_scalar(lo: f32, s: f32, inv_s: f32, bl: f32, bh: f32) -> (u8, u8) {
    let dec = |q: u32| lo + q as f32 * s;
    let x = (bl - lo) * inv_s;
    let mut ql = if x > 0.0 { (x as u32).min(255) } else { 0 };
    while ql > 0 && dec(ql) > bl {
        ql -= 1;
    }
    let y = (bh - lo) * inv_s;
    let mut qh = if y > 0.0 { (y as u32).min(255) } else { 0 };
    while qh < 255 && dec(qh) < bh {
        qh += 1;
    }
    (ql as u8, qh as u8)
}

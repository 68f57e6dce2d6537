use super::*;
use crate::accel::geometry::centroid;
use crate::accel::params::{self, PLAN_GRID};
use crate::accel::testing::unit_floats as floats;

fn next_up(f: f32) -> f32 {
    if f >= 0.0 { f32::from_bits(f.to_bits() + 1) } else { f32::from_bits(f.to_bits() - 1) }
}
fn next_down(f: f32) -> f32 {
    if f > 0.0 { f32::from_bits(f.to_bits() - 1) } else if f == 0.0 { -f32::from_bits(1) } else { f32::from_bits(f.to_bits() + 1) }
}

/// Values around `at` on scales from `span` down to single floats.
fn probes_sorted(f: &mut impl FnMut() -> f32, at: f32, span: f32) -> Vec<f32> {
    let mut v = vec![-f32::MAX, f32::MAX, 0.0, at];
    for _ in 0..40 {
        let x = at + (f() - 0.5) * 2.0 * span;
        v.extend([x, next_up(x), next_down(x)]);
    }
    v
}

/// The threshold of a split test is exact: c < t gives the test's own answer for values
/// at, next to and far from t, for offsets and scales of every sign and size; and a grid
/// cell's first value is exact the same way.
#[test]
fn thresholds_are_the_split_tests() {
    let mut f = floats(0x9e37_79b9_7f4a_7c15);
    for case in 0..2000 {
        let cmin = (f() - 0.5) * [1e-3, 1.0, 1e4, 3e7][case % 4];
        let scale = [1e-6, 0.37, 32.0, 1e6][(case / 4) % 4] * (0.5 + f());
        let limit = 1.0 + (f() * 31.0).floor();
        let sp = Splitter { a: case % 3, cmin, scale, limit };
        let t = threshold(&sp);
        let left = |c: f32| (c - sp.cmin) * sp.scale < sp.limit;
        let mut probes = vec![-f32::MAX, f32::MAX, 0.0, -0.0, cmin, cmin + limit / scale];
        if t.is_finite() {
            probes.extend([t, next_up(t), next_down(t), next_down(next_down(t))]);
        }
        probes.extend((0..20).map(|_| cmin + (f() - 0.2) * 2.0 * limit / scale));
        for c in probes {
            assert_eq!(c < t, left(c), "case {case}: c {c} threshold {t} ({sp_a} {cmin} {scale} {limit})", sp_a = sp.a);
        }
        // An axis' grid cell is monotonic in the value (what the ranks rely on).
        let (gmin, ginv) = (cmin, scale * PLAN_GRID as f32 / 32.0);
        let mut vals: Vec<f32> = probes_sorted(&mut f, cmin, limit / scale);
        vals.sort_by(f32::total_cmp);
        for w in vals.windows(2) {
            assert!(line_coord(w[0], gmin, ginv) <= line_coord(w[1], gmin, ginv), "case {case}: {} {}", w[0], w[1]);
        }
    }
}

/// The classification (previous bucket's box, grid, walk) gives every reference the bucket
/// the split tests of the planned tree give it, and each bucket's exact count and box:
/// clustered references in input order, references with their centroid on a threshold and
/// next to it, and references outside the sample's box.
#[test]
fn classification_is_the_walk_down_the_split_tests() {
    let mut f = floats(0x2545_f491_4f6c_dd1d);
    for (case, flags) in [BuildFlags::PREFER_FAST_BUILD, 0, BuildFlags::PREFER_FAST_TRACE].into_iter().enumerate() {
        let p = params::BuildParams::from_flags(BuildFlags(flags));
        // Points along a random walk (input order is coherent), boxes around them.
        let mut at = Vec3A::ZERO;
        let mut refs: Vec<PrimRef> = (0..200_000u32)
            .map(|i| {
                at += Vec3A::new(f() - 0.5, f() - 0.5, (f() - 0.5) * 0.3) * 0.05;
                if i % 5000 == 0 {
                    at = Vec3A::new(f(), f(), f()) * 20.0;
                }
                let e = Vec3A::new(f(), f(), f()) * 0.02;
                PrimRef { lo: (at - e).to_array(), geom: 0, hi: (at + e).to_array(), prim: i }
            })
            .collect();
        let mut cb = Aabb::EMPTY;
        for r in &refs {
            cb.grow_point(&centroid(r));
        }
        let step = 8;
        let mut sample: Vec<PrimRef> = refs.iter().step_by(step).copied().collect();
        let mut scratch = vec![PrimRef::zeroed(); sample.len()];
        let (tree, buckets) = grow_plan(&p, &mut sample, &mut scratch, cb, 0, Sampling { step, min_sample: p.sample_target / PLAN_MIN_SAMPLE_DIV, parallel: true });
        assert!(buckets >= 8, "case {case}: {buckets} buckets");
        let plan = TopPlan::new(tree, buckets as usize, &cb);
        // References on every threshold, just below it, and outside the root box.
        for nd in &plan.tree {
            if let Some(sp) = nd.split {
                let t = threshold(&sp);
                for c in [t, next_down(t), next_up(t)] {
                    let mut x = [f() * 20.0, f() * 20.0, f() * 20.0];
                    x[sp.a] = c;
                    refs.push(PrimRef { lo: x, geom: 0, hi: x, prim: 0 });
                }
            }
        }
        refs.push(PrimRef { lo: [-1e6; 3], geom: 0, hi: [-1e6; 3], prim: 0 });
        refs.push(PrimRef { lo: [1e6; 3], geom: 0, hi: [1e6; 3], prim: 0 });
        check_against_walk(&plan, &refs, &format!("case {case}"));
    }
}

/// `plan.classify` gives every reference of `refs` the bucket of the walk down the split
/// tests, and every bucket its exact count and box.
fn check_against_walk(plan: &TopPlan, refs: &[PrimRef], what: &str) {
    let walk = |r: &PrimRef| {
        let mut i = 0usize;
        loop {
            let nd = plan.tree[i];
            match nd.split {
                Some(sp) => i = nd.kids[!sp.left(r) as usize] as usize,
                None => return nd.bucket as usize,
            }
        }
    };
    let mut ids = vec![0u8; refs.len()];
    let mut cells = vec![BucketCell::zeroed(); plan.buckets];
    plan.classify(refs, &mut ids, &mut cells);
    let mut want = vec![(0u32, Aabb::EMPTY); plan.buckets];
    for (r, &id) in refs.iter().zip(&ids) {
        let b = walk(r);
        assert_eq!(id as usize, b, "{what}: reference {r:?}");
        want[b].0 += 1;
        want[b].1.grow(&r.lo, &r.hi);
    }
    for (c, (k, bx)) in cells.iter().zip(&want) {
        assert_eq!(c.count, *k, "{what}");
        if *k > 0 {
            assert_eq!((c.lo, c.hi), (bx.lo, bx.hi), "{what}");
        }
    }
}

/// Thresholds closer than one cell of an axis' grid (three in one cell, the slow count)
/// still classify exactly, at, next to and between them.
#[test]
fn thresholds_sharing_a_grid_cell_classify_exactly() {
    let x = |a: usize, t: f32| Some(Splitter { a, cmin: 0.0, scale: 1.0, limit: t });
    let node = |split, kids: [u32; 2], bucket| TopNode { split, kids, bucket };
    let tree = vec![
        node(x(0, 0.5005), [1, 6], 0),
        node(x(0, 0.5), [2, 3], 0),
        node(None, [0; 2], 0),
        node(x(0, 0.5003), [4, 5], 0),
        node(None, [0; 2], 1),
        node(None, [0; 2], 2),
        node(x(1, 0.3), [7, 8], 0),
        node(None, [0; 2], 3),
        node(None, [0; 2], 4),
    ];
    let cb = Aabb { lo: [0.0; 3], hi: [1.0; 3] };
    let plan = TopPlan::new(tree, 5, &cb);
    let cell = |t: f32| line_coord(t, plan.gmin[0], plan.ginv[0]);
    assert!(cell(0.5) == cell(0.5005) && plan.line[0][cell(0.5)].base == MANY, "the three thresholds share a cell");
    let mut f = floats(0x1234_5678_9abc_def1);
    let mut refs = Vec::new();
    for t in [0.5f32, 0.5003, 0.5005, 0.3] {
        for c in [t, next_up(t), next_down(t), t + 1e-4, t - 1e-4] {
            for axis in 0..2 {
                let mut p = [f(), f(), f()];
                p[axis] = c;
                refs.push(PrimRef { lo: p, geom: 0, hi: p, prim: 0 });
            }
        }
    }
    refs.extend((0..2000).map(|_| {
        let p = [0.499 + f() * 0.002, f(), f()];
        PrimRef { lo: p, geom: 0, hi: p, prim: 0 }
    }));
    check_against_walk(&plan, &refs, "close thresholds");
}

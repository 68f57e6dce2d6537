//! Unit tests of the build stages' internals: exact splits, the compaction's copies, and the
//! equivalence of the partitions.
use super::ingest::copy_prefixes;
use super::partition::{par_partition_from_nodes, par_partition_to_nodes};
use super::small_split::{ordered_bits, small_split, sort_network, NET8};
use crate::accel::geometry::{PrimRef, DROPPED};
use crate::accel::params::MAX_SMALL;
use crate::accel::tree::{node_refs, node_refs_mut, BinNode};
use crate::accel::testing::xorshift;
use bytemuck::Zeroable;


/// 0-1 principle: a comparator network sorts every input iff it sorts every 0/1 input.
#[test]
fn sorting_networks_sort() {
    for bits in 0u32..(1 << MAX_SMALL) {
        let mut v = [u64::MAX; MAX_SMALL];
        for (i, x) in v.iter_mut().enumerate() {
            *x = (bits >> i & 1) as u64;
        }
        sort_network(&mut v, &NET8);
        assert!(v.windows(2).all(|w| w[0] <= w[1]), "input {bits:#b}: {v:?}");
    }
    let keys = [-1.5f32, -0.0, 0.0, 2.0, f32::MIN, f32::MAX, 1e-30, -1e-30];
    let mut sorted = keys;
    sorted.sort_by(|a, b| a.total_cmp(b));
    let mut by_bits = keys;
    by_bits.sort_by_key(|&k| ordered_bits(k));
    assert_eq!(sorted.map(f32::to_bits), by_bits.map(f32::to_bits));
}

/// Nodes of three to five references split at the cheapest of all their bipartitions: the
/// cost `small_split` returns is that of a brute-force enumeration in f64 (sides' boxes and
/// weights from the references), the reordered references describe a split of that cost,
/// and nothing is lost; weighted (cluster) references count their primitives. The sweeps'
/// splits are among the bipartitions, so no tier's small nodes got worse.
#[test]
fn small_nodes_take_the_cheapest_bipartition() {
    let mut next = xorshift(0x9e37_79b9_7f4a_7c15);
    let mut f = move || (next() >> 40) as f32 / (1u64 << 24) as f32;
    let cost64 = |set: &[PrimRef], weighted: bool| -> f64 {
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        let mut w = 0f64;
        for r in set {
            for a in 0..3 {
                lo[a] = lo[a].min(r.lo[a] as f64);
                hi[a] = hi[a].max(r.hi[a] as f64);
            }
            w += if weighted { r.geom as f64 } else { 1.0 };
        }
        let d = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
        (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]) * w
    };
    for case in 0..3000 {
        let n = 3 + case % 3;
        let weighted = case % 2 == 1;
        // Clustered boxes, some flat or shared, so that ties and degenerate sides occur.
        let refs: Vec<PrimRef> = (0..n)
            .map(|k| {
                let c = [f() * 4.0, if case % 7 == 0 { 1.0 } else { f() * 4.0 }, f() * 4.0];
                let e = [f(), f() * 0.3, if case % 5 == 0 { 0.0 } else { f() }];
                PrimRef { lo: c, geom: 1 + (k as u32 * 7 + case as u32) % 4, hi: [c[0] + e[0], c[1] + e[1], c[2] + e[2]], prim: k as u32 }
            })
            .collect();
        let mut brute = f64::INFINITY;
        for m in 1u32..(1 << n) - 1 {
            let (mut l, mut r) = (Vec::new(), Vec::new());
            for (i, x) in refs.iter().enumerate() {
                if m >> i & 1 != 0 { l.push(*x) } else { r.push(*x) }
            }
            brute = brute.min(cost64(&l, weighted) + cost64(&r, weighted));
        }
        for axes in [(0, 3), (1, 2)] {
            if axes == (1, 2) && n == 5 {
                continue; // one axis sorts from five references on
            }
            let mut got = refs.clone();
            let (mid, cost) = small_split(&mut got, axes, weighted).expect("a split");
            assert!((cost as f64 - brute).abs() <= 1e-4 * brute.max(1e-3), "case {case} n {n}: cost {cost} against brute force {brute}");
            let again = cost64(&got[..mid], weighted) + cost64(&got[mid..], weighted);
            assert!((again - brute).abs() <= 1e-4 * brute.max(1e-3), "case {case}: the reordered split costs {again}, not {brute}");
            let mut ids: Vec<u32> = got.iter().map(|r| r.prim).collect();
            ids.sort_unstable();
            assert_eq!(ids, (0..n as u32).collect::<Vec<_>>());
        }
    }
    // Huge sanitised boxes (areas overflow to infinity) still split, as the sweeps did.
    for n in 3..=5 {
        let huge: Vec<PrimRef> = (0..n).map(|k| PrimRef { lo: [-f32::MAX; 3], geom: 1, hi: [f32::MAX; 3], prim: k }).collect();
        for axes in [(0, 3), (1, 2)] {
            let mut got = huge.clone();
            let (mid, cost) = small_split(&mut got, axes, true).expect("huge boxes split");
            assert!((1..n as usize).contains(&mid) && cost == f32::INFINITY, "n {n}: {mid} {cost}");
        }
    }
}

/// The compaction's parallel copy of chunk prefixes gives what copying them one after the
/// other gives: chunks of every fill from empty to full, more of them than one task takes
/// (the halves in parallel), on a pool of three.
#[test]
fn chunk_prefixes_are_copied_in_order() {
    let mut bits = xorshift(0x2545_f491_4f6c_dd1d);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
    for (chunks, chunk_len) in [(1usize, 7usize), (5, 16), (40, 9), (133, 32)] {
        let src: Vec<PrimRef> = (0..chunks * chunk_len).map(|i| PrimRef { lo: [i as f32; 3], geom: 0, hi: [i as f32 + 1.0; 3], prim: i as u32 }).collect();
        let kept: Vec<usize> = (0..chunks).map(|c| if c % 7 == 3 { 0 } else if c % 5 == 1 { chunk_len } else { (bits() % (chunk_len as u64 + 1)) as usize }).collect();
        let expect: Vec<u32> = (0..chunks).flat_map(|c| (0..kept[c]).map(move |k| (c * chunk_len + k) as u32)).collect();
        let mut offs: Vec<u32> = Vec::new();
        let mut acc = 0usize;
        for &k in &kept {
            offs.push(acc as u32);
            acc += k;
        }
        let mut dst = vec![PrimRef { lo: [0.0; 3], geom: DROPPED, hi: [0.0; 3], prim: u32::MAX }; acc];
        pool.install(|| copy_prefixes(&src, chunk_len, &offs, 0, acc, &mut dst));
        assert_eq!(dst.iter().map(|r| r.prim).collect::<Vec<_>>(), expect, "{chunks} chunks of {chunk_len}");
    }
}

/// The one-pass partition (one-thread pools, small nodes) and the parallel one (statistics,
/// then scatter) give the same count, boxes and bytes, both into node slots and back into
/// `refs`, including everything on one side; the bytes of a build may not depend on which
/// one ran.
#[test]
fn one_pass_partition_matches_the_parallel_one() {
    let mut bits = xorshift(0x9e37_79b9_7f4a_7c15);
    let mut next = move || (bits() >> 40) as f32 / (1u64 << 24) as f32;
    let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
    for n in [2usize, 3, 5, 64, 1000, 4097] {
        let refs: Vec<PrimRef> = (0..n)
            .map(|i| {
                let lo = [next() * 10.0, next() * 10.0, next() * 10.0];
                PrimRef { lo, geom: i as u32 % 3, hi: [lo[0] + next(), lo[1] + next(), lo[2] + next()], prim: i as u32 }
            })
            .collect();
        for limit in [-1.0f32, 2.5, 5.0, 9.0, 11.0] {
            let is_left = |r: &PrimRef| r.lo[0] * 0.5 + r.hi[0] * 0.5 < limit;
            let empty = BinNode::zeroed();
            // Into node slots.
            let (mut a, mut b) = (vec![empty; 2 * n - 1], vec![empty; 2 * n - 1]);
            let x = pool.install(|| par_partition_to_nodes(&refs, &mut a, false, is_left));
            let y = pool.install(|| par_partition_to_nodes(&refs, &mut b, true, is_left));
            assert_eq!(x, y, "n {n} limit {limit}");
            let nl = x.unwrap().0;
            if nl > 0 && nl < n {
                assert_eq!(node_refs(&a[1..], nl), node_refs(&b[1..], nl), "n {n} limit {limit}: lefts");
                assert_eq!(node_refs(&a[2 * nl..], n - nl), node_refs(&b[2 * nl..], n - nl), "n {n} limit {limit}: rights");
                // Stable: the lefts are the left references in input order.
                let want: Vec<PrimRef> = refs.iter().filter(|r| is_left(r)).copied().collect();
                assert_eq!(node_refs(&b[1..], nl), Some(&want[..]));
            }
            // From node slots back into refs.
            let mut slots = vec![empty; 2 * n - 1];
            node_refs_mut(&mut slots, n).unwrap().copy_from_slice(&refs);
            let (mut ra, mut rb) = (vec![refs[0]; n], vec![refs[0]; n]);
            let x = pool.install(|| par_partition_from_nodes(&mut ra, &slots, false, is_left));
            let y = pool.install(|| par_partition_from_nodes(&mut rb, &slots, true, is_left));
            assert_eq!(x, y, "n {n} limit {limit}: from nodes");
            assert_eq!(ra, rb, "n {n} limit {limit}: from nodes");
        }
    }
}

//! The PREFER_FAST_BUILD instance tree: a linear BVH. The instances are sorted once by the
//! Morton code of their centroid; each node then splits its (contiguous, sorted) range where
//! the highest bit of the code that differs within it changes, and the boxes come bottom-up,
//! one union per node. No node bins or partitions its references: one pass over them for the
//! codes, three radix passes over the keys, one gather, then work per node instead of per
//! reference and level. Leaves come from the SAH on the way back up (a subtree of at most
//! `max_leaf` references becomes a leaf where that is cheaper than its nodes), so the tree
//! keeps the tier's leaf/split balance.
//!
//! Owns: the node decisions and node slots of these trees (the same slot scheme and wide
//! sizes as `subtree`, so encoding does not know which builder ran). Must not touch: other
//! tiers and BLAS builds, which keep the binned SAH of `subtree`.
use super::subtree::BuildContext;
use crate::accel::encode::nodes::wide_count;
use crate::accel::geometry::{half_area_vec, ref_hi, ref_lo, Aabb, PrimRef};
use crate::accel::params::EMIT_CUT;
use crate::accel::tree::{is_cut, node_refs_mut, wide_size_above_cut, BinNode};
use crate::accel::{AsType, BuildDesc, BuildFlags};
use glam::Vec3A;
use rayon::prelude::*;

/// Bits of the Morton code per axis (the code sits above the reference's index in a key).
const BITS: u32 = 10;
/// Bits per radix pass (three passes sort the 30-bit codes).
const RADIX: u32 = 10;
/// References per parallel task of the code and gather passes: small enough that a
/// 10,000-instance TLAS spreads evenly over a few threads (the keys hold global indices, so
/// the chunking never shows in the bytes).
const CHUNK: usize = 1024;

/// Whether `desc` builds its tree here: instance trees of the fast-build tier.
pub fn applies(desc: &BuildDesc) -> bool {
    desc.ty == AsType::TopLevel && desc.flags.contains(BuildFlags::PREFER_FAST_BUILD) && !desc.flags.contains(BuildFlags::PREFER_FAST_TRACE)
}

/// Builds the tree over `refs` (or over the first `refs.len()` references' worth of the node
/// slots, `in_nodes`) into `nodes`, with `keys` (16 bytes per reference, 8-aligned) as the
/// sort's scratch: the references end in `refs` in leaf order. `centroids` is the box of
/// their centroids. Returns the tree's unnormalised SAH sum and depth, as `build_tree` does;
/// None (nothing written) when `keys` is too small.
pub fn build_tree(ctx: &BuildContext, refs: &mut [PrimRef], nodes: &mut [BinNode], keys: &mut [u8], centroids: Aabb, in_nodes: bool) -> Option<(f64, u32)> {
    let n = refs.len();
    let keys: &mut [u64] = bytemuck::try_cast_slice_mut(keys.get_mut(..n * 16)?).ok()?;
    let (keys, tmp) = keys.split_at_mut(n);
    let slots = node_refs_mut(nodes, n)?;
    // The keys, and the references to the node slots on the way (the gather's source).
    if in_nodes {
        encode_keys(slots, None, centroids, keys);
    } else {
        encode_keys(refs, Some(slots), centroids, keys);
    }
    let src = node_refs_mut(nodes, n)?;
    let sorted = radix_sort(keys, tmp);
    // The references in code order (ties in input order): a gather from the node slots.
    refs.par_chunks_mut(CHUNK).zip(sorted.par_chunks(CHUNK)).for_each(|(d, k)| {
        for (r, &key) in d.iter_mut().zip(k) {
            *r = src[key as u32 as usize];
        }
    });
    let top = Span { start: 0, parent_count: u32::MAX };
    let out = node(ctx, refs, sorted, nodes, top);
    Some((out.sah, out.depth))
}

/// Key of each reference: its centroid's Morton code (the centroid box cut into 2^BITS cells
/// per axis along its longest side) above its index; `copy` receives the references.
fn encode_keys(src: &[PrimRef], copy: Option<&mut [PrimRef]>, cb: Aabb, keys: &mut [u64]) {
    let lo = Vec3A::from(cb.lo);
    let ext = (Vec3A::from(cb.hi) - lo).max_element();
    let cells = (1u32 << BITS) as f32;
    let scale = if ext > 0.0 && ext.is_finite() { cells / ext } else { 0.0 };
    let top = Vec3A::splat(cells - 1.0);
    let code_of = |c: usize, ks: &mut [u64]| {
        for (k, (key, r)) in ks.iter_mut().zip(&src[c * CHUNK..]).enumerate() {
            // The centroid as ingest computes it; NaN and out-of-box values clamp to a cell.
            let centroid = ref_lo(r) * 0.5 + ref_hi(r) * 0.5;
            let q = ((centroid - lo) * scale).max(Vec3A::ZERO).min(top);
            let code = SPREAD[q.x as usize & 0x3FF] | SPREAD[q.y as usize & 0x3FF] << 1 | SPREAD[q.z as usize & 0x3FF] << 2;
            *key = (code as u64) << 32 | (c * CHUNK + k) as u64;
        }
    };
    match copy {
        Some(copy) => keys.par_chunks_mut(CHUNK).zip(copy.par_chunks_mut(CHUNK)).enumerate().for_each(|(c, (ks, cp))| {
            code_of(c, ks);
            cp.copy_from_slice(&src[c * CHUNK..c * CHUNK + cp.len()]);
        }),
        None => keys.par_chunks_mut(CHUNK).enumerate().for_each(|(c, ks)| code_of(c, ks)),
    }
}

/// `spread` of every BITS-bit value: three loads per key instead of three bit-twiddling
/// sequences (a tenth of the tree's instructions).
static SPREAD: [u32; 1 << BITS] = {
    let mut t = [0u32; 1 << BITS];
    let mut v = 0;
    while v < t.len() {
        t[v] = spread(v as u32);
        v += 1;
    }
    t
};

/// The low BITS bits of `v` spread to every third bit.
const fn spread(v: u32) -> u32 {
    let mut x = v & 0x3FF;
    x = (x | x << 16) & 0x0300_00FF;
    x = (x | x << 8) & 0x0300_F00F;
    x = (x | x << 4) & 0x030C_30C3;
    (x | x << 2) & 0x0924_9249
}

/// Keys from which the sort's last two digits go bucket by bucket on the pool.
const PAR_SORT_FROM: usize = 4096;
/// Threads from which the bucketed sort runs: on one or two the three plain passes were as
/// fast or faster (docs/BENCHMARKS.md); the split is for many-core pools.
const PAR_SORT_THREADS: usize = 4;
/// Keys per parallel task of the bucket sorts.
const BUCKET_TASK: usize = 2048;
/// Buckets of this many keys or more sort by radix passes (smaller: a comparison sort).
const BUCKET_RADIX_FROM: usize = 64;

/// Sorts `keys` by their codes, stably (the indices below them make every key distinct, so
/// the order is the one any sort would give); returns the sorted keys, in `tmp`. Large inputs
/// are scattered by the top digit first, then the buckets (disjoint ranges) are sorted in
/// parallel, `keys` serving as their scratch: the same order, whatever the thread count.
fn radix_sort<'k>(keys: &'k mut [u64], tmp: &'k mut [u64]) -> &'k [u64] {
    if keys.len() < PAR_SORT_FROM || rayon::current_num_threads() < PAR_SORT_THREADS {
        radix_pass(keys, tmp, 0);
        radix_pass(tmp, keys, 1);
        radix_pass(keys, tmp, 2);
        return tmp;
    }
    let starts = radix_pass(keys, tmp, 2);
    sort_buckets(tmp, keys, &starts, 0);
    tmp
}

/// One stable counting pass of `from` into `to` on digit `pass`; returns where each digit's
/// keys start in `to`, and their end.
fn radix_pass(from: &[u64], to: &mut [u64], pass: u32) -> [u32; (1 << RADIX) + 1] {
    let shift = 32 + pass * RADIX;
    let digit = |k: u64| (k >> shift) as usize & ((1 << RADIX) - 1);
    let mut starts = [0u32; (1 << RADIX) + 1];
    for &k in from {
        starts[digit(k) + 1] += 1;
    }
    for d in 1..starts.len() {
        starts[d] += starts[d - 1];
    }
    let mut next = starts;
    for &k in from {
        let d = digit(k);
        if let Some(slot) = to.get_mut(next[d] as usize) {
            *slot = k;
        }
        next[d] += 1;
    }
    starts
}

/// Sorts each bucket of `s` (bucket b at `bounds[b]..bounds[b + 1]`, less `base`) on the two
/// lower digits, `scratch` (as long as `s`) beside it: halves of the buckets in parallel.
fn sort_buckets(s: &mut [u64], scratch: &mut [u64], bounds: &[u32], base: usize) {
    if s.len() > BUCKET_TASK && bounds.len() > 2 {
        let mid = bounds.len() / 2;
        let cut = (bounds[mid] as usize).saturating_sub(base).min(s.len());
        let (sa, sb) = s.split_at_mut(cut);
        let (ka, kb) = scratch.split_at_mut(cut.min(scratch.len()));
        rayon::join(|| sort_buckets(sa, ka, &bounds[..=mid], base), || sort_buckets(sb, kb, &bounds[mid..], base + cut));
        return;
    }
    for w in bounds.windows(2) {
        let (lo, hi) = ((w[0] as usize).saturating_sub(base), (w[1] as usize).saturating_sub(base));
        let (Some(b), Some(k)) = (s.get_mut(lo..hi), scratch.get_mut(lo..hi)) else { continue };
        if b.len() >= BUCKET_RADIX_FROM {
            // Two passes: the keys come back to `b`.
            radix_pass(b, k, 0);
            radix_pass(k, b, 1);
        } else {
            b.sort_unstable();
        }
    }
}

/// Where a node sits: its first reference in the build and its parent's reference count
/// (u32::MAX at the root), which decides whether it is a cut root.
#[derive(Clone, Copy)]
struct Span {
    start: u32,
    parent_count: u32,
}

/// What a subtree gives its parent: its box, its cost for the leaf decision (C_T per node),
/// its reported SAH sum (C_T = 1) and its depth.
struct Built {
    lo: Vec3A,
    hi: Vec3A,
    cost: f32,
    sah: f64,
    depth: u32,
}

/// Builds the subtree over `refs` (sorted, `keys` theirs) into `nodes[..2n-1]`.
fn node(ctx: &BuildContext, refs: &[PrimRef], keys: &[u64], nodes: &mut [BinNode], at: Span) -> Built {
    let (n, p) = (refs.len(), &ctx.params);
    if n <= 1 || (n as u32 <= p.max_leaf && n as f32 <= p.traversal_cost) {
        // No split can cost less than C_T·A (`subtree::decide` makes the same leaf).
        let (lo, hi) = refs.iter().fold((Vec3A::INFINITY, Vec3A::NEG_INFINITY), |(lo, hi), r| (lo.min(ref_lo(r)), hi.max(ref_hi(r))));
        let area = half_area_vec(lo, hi);
        if let Some(slot) = nodes.first_mut() {
            *slot = leaf(lo, hi, at.start, n);
        }
        return Built { lo, hi, cost: area * n as f32, sah: area as f64 * n as f64, depth: 1 };
    }
    let mid = split(keys);
    let Some((me, rest)) = nodes.split_first_mut() else { return Built { lo: Vec3A::ZERO, hi: Vec3A::ZERO, cost: 0.0, sah: 0.0, depth: 0 } };
    let (ln, rn) = rest.split_at_mut((2 * mid - 1).min(rest.len()));
    let (lr, rr) = refs.split_at(mid);
    let (lk, rk) = keys.split_at(mid);
    let (ls, rs) = (Span { start: at.start, parent_count: n as u32 }, Span { start: at.start + mid as u32, parent_count: n as u32 });
    let (l, r) = if n >= ctx.params.parallel_cutoff as usize {
        rayon::join(|| node(ctx, lr, lk, ln, ls), || node(ctx, rr, rk, rn, rs))
    } else {
        (node(ctx, lr, lk, ln, ls), node(ctx, rr, rk, rn, rs))
    };
    let (lo, hi) = (l.lo.min(r.lo), l.hi.max(r.hi));
    let area = half_area_vec(lo, hi);
    let split_cost = area * p.traversal_cost + l.cost + r.cost;
    if n as u32 <= p.max_leaf && area * n as f32 <= split_cost {
        *me = leaf(lo, hi, at.start, n);
        return Built { lo, hi, cost: area * n as f32, sah: area as f64 * n as f64, depth: 1 };
    }
    *me = leaf(lo, hi, at.start, n);
    me.left_count = mid as u32;
    // Wide sizes as `subtree::finish_split` keeps them: above the cut, and at cut roots
    // (instance trees pre-emit nothing, so a cut root counts its wide subtree).
    let me_count = n as u32;
    let w = if me_count > EMIT_CUT {
        wide_size_above_cut(nodes)
    } else if is_cut(at.parent_count, me_count) {
        wide_count(nodes, 0)
    } else {
        0
    };
    nodes[0].wide_nodes = w;
    Built { lo, hi, cost: split_cost, sah: area as f64 + l.sah + r.sah, depth: 1 + l.depth.max(r.depth) }
}

/// A leaf node (or an internal one before its left count and wide size are set).
fn leaf(lo: Vec3A, hi: Vec3A, start: u32, n: usize) -> BinNode {
    BinNode { lo: lo.to_array(), start, hi: hi.to_array(), count: n as u32, left_count: 0, wide_nodes: 0 }
}

/// The left count of a node over sorted `keys` (at least two): where the highest code bit
/// that differs within them turns to 1, or half of them when their codes are all equal.
fn split(keys: &[u64]) -> usize {
    let (first, last) = (keys[0] >> 32, keys[keys.len() - 1] >> 32);
    if first == last {
        return keys.len() / 2;
    }
    let bit = 63 - (first ^ last).leading_zeros();
    keys.partition_point(|&k| (k >> 32) >> bit & 1 == 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The radix passes (and the bucketed sort) against the standard library's sort, on codes
    /// with many repeats.
    #[test]
    fn radix_sort_matches_a_comparison_sort() {
        let mut next = crate::accel::testing::xorshift(5);
        // Below and above the bucketed sort's cutoff; few codes (large buckets) and many.
        for (n, codes) in [(3000u64, 700u64), (5000, 700), (20_000, 50), (20_000, 1 << 20)] {
            let keys: Vec<u64> = (0..n).map(|i| ((next() % codes * 0x0013_5791) & 0x3FFF_FFFF) << 32 | i).collect();
            let mut want = keys.clone();
            want.sort_unstable();
            for threads in [1, PAR_SORT_THREADS + 1] {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
                let (mut keys, mut tmp) = (keys.clone(), vec![0u64; keys.len()]);
                assert_eq!(pool.install(|| radix_sort(&mut keys, &mut tmp).to_vec()), want, "{n} keys, {codes} codes, {threads} threads");
            }
        }
    }

    /// The split point against a scan for the first code whose highest differing bit is set,
    /// and `spread` against a bit-by-bit interleave.
    #[test]
    fn split_and_spread_match_their_definitions() {
        let mut next = crate::accel::testing::xorshift(9);
        for len in 2..200usize {
            let mut keys: Vec<u64> = (0..len as u64).map(|i| (next() % (1 + len as u64 / 3)) << 32 | i).collect();
            keys.sort_unstable();
            let codes: Vec<u64> = keys.iter().map(|k| k >> 32).collect();
            let want = if codes[0] == codes[len - 1] {
                len / 2
            } else {
                let top = (0..64).rev().find(|&b| (codes[0] ^ codes[len - 1]) >> b & 1 == 1).unwrap_or(0);
                codes.iter().position(|c| c >> top & 1 == 1).unwrap_or(len)
            };
            assert_eq!(split(&keys), want, "{codes:?}");
        }
        for v in 0..1u32 << BITS {
            let want = (0..BITS).fold(0u32, |acc, b| acc | (v >> b & 1) << (3 * b));
            assert_eq!((spread(v), SPREAD[v as usize]), (want, want), "{v:#x}");
        }
        assert_eq!(spread(0x7FF), spread(0x3FF), "bits above BITS are ignored");
    }
}

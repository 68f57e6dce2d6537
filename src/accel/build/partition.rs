//! Stable partitions of a node's references by a split test: in place (`partition_seq`), out
//! of place into the children's node slots (`partition_out`), and for large nodes in parallel
//! fixed chunks or in one equivalent pass (`par_partition_to_nodes`, `_from_nodes`). Every
//! form gives the same order and boxes, so the choice never changes the bytes.
//!
//! Owns: moving references. Must not touch: the split choice, node contents.
use super::bins::Splitter;
use crate::accel::geometry::{ref_hi, ref_lo, to_aabb, Aabb, PrimRef};
use crate::accel::params::{PARTITION_CHUNKS, PAR_PARTITION_FROM};
use crate::accel::tree::{node_refs, node_refs_mut, BinNode};
use glam::Vec3A;
use rayon::prelude::*;

pub const PRIMREF_BYTES: usize = std::mem::size_of::<PrimRef>();

/// Out-of-place stable partition by `sp`: the lefts of `src` in order from `dst[0]`, the
/// rights in order from `dst[rbase]` (bytes). Returns the left count, or None when it is not
/// `nl` (what was written is then garbage; nothing is written outside `dst`). The sides'
/// boxes come from the bins, and no centroid bounds are needed (see `build_rec`).
#[inline(never)]
pub fn partition_out(src: &[PrimRef], dst: &mut [u8], nl: usize, rbase: usize, sp: &Splitter) -> Option<usize> {
    let n = src.len();
    if nl > n || nl * PRIMREF_BYTES > rbase || dst.len() < rbase + (n - nl) * PRIMREF_BYTES || dst.len() < PRIMREF_BYTES {
        return None;
    }
    // Write offsets are clamped to the last whole reference of `dst`, so the compiler drops
    // the per-store bounds checks; a clamp only matters when the count is not `nl`, and
    // then the result is discarded anyway.
    let cap = dst.len() - PRIMREF_BYTES;
    let (mut li, mut ri) = (0usize, rbase);
    for r in src {
        let left = sp.left(r) as usize;
        let at = if left != 0 { li } else { ri }.min(cap);
        if let Some(d) = dst.get_mut(at..).and_then(|x| x.first_chunk_mut::<PRIMREF_BYTES>()) {
            *d = bytemuck::cast(*r);
        }
        li += PRIMREF_BYTES * left;
        ri += PRIMREF_BYTES * (left ^ 1);
    }
    (li == nl * PRIMREF_BYTES).then_some(nl)
}

/// In-place partition by `sp`; returns the left count.
#[inline(never)]
pub fn partition_seq(refs: &mut [PrimRef], sp: &Splitter) -> usize {
    let n = refs.len();
    // Partition in place (deterministic: sequential, same bin function as binning).
    // Branchless Lomuto: every reference is swapped with the first right one and
    // the boundary advances by the comparison, so no branch depends on the data.
    let mut i = 0usize;
    for j in 0..n {
        let r = refs[j];
        let left = sp.left(&r);
        // i <= j always (i counts the lefts before j).
        refs[j] = refs[i];
        refs[i] = r;
        i += left as usize;
    }
    i
}


#[derive(Clone, Copy)]
pub struct PartStat {
    left: usize,
    l_lo: Vec3A,
    l_hi: Vec3A,
    r_lo: Vec3A,
    r_hi: Vec3A,
}

/// Moves a node's references from the start of its node slots into `refs` (parallel copy in
/// the partition's fixed chunks).
pub fn restore(refs: &mut [PrimRef], nodes: &[BinNode]) {
    let n = refs.len();
    if n < PAR_PARTITION_FROM {
        if let Some(src) = node_refs(nodes, n) {
            refs.copy_from_slice(src);
        }
        return;
    }
    if let Some(src) = node_refs(nodes, n) {
        let chunk = n.div_ceil(PARTITION_CHUNKS).max(1);
        refs.par_chunks_mut(chunk).zip(src.par_chunks(chunk)).for_each(|(d, s)| d.copy_from_slice(s));
    }
}

/// Per-chunk left counts and boxes of a stable partition of `src` (64 fixed chunks); the
/// totals are returned as (left count, left box, right box).
// One tuple read at one call site; a named struct would only be destructured there.
#[allow(clippy::type_complexity)]
pub fn part_stats(src: &[PrimRef], is_left: &(impl Fn(&PrimRef) -> bool + Sync)) -> (usize, usize, [PartStat; PARTITION_CHUNKS], usize, Aabb, Aabb) {
    let n = src.len();
    let chunk = n.div_ceil(PARTITION_CHUNKS).max(1);
    let (inf, ninf) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let empty = PartStat { left: 0, l_lo: inf, l_hi: ninf, r_lo: inf, r_hi: ninf };
    let mut stats = [empty; PARTITION_CHUNKS];
    src.par_chunks(chunk).zip(stats.par_iter_mut()).for_each(|(c, st)| {
        let mut s = empty;
        for r in c {
            let (lo, hi) = (ref_lo(r), ref_hi(r));
            if is_left(r) {
                s.left += 1;
                s.l_lo = s.l_lo.min(lo);
                s.l_hi = s.l_hi.max(hi);
            } else {
                s.r_lo = s.r_lo.min(lo);
                s.r_hi = s.r_hi.max(hi);
            }
        }
        *st = s;
    });
    let nchunks = n.div_ceil(chunk);
    let nl: usize = stats[..nchunks].iter().map(|s| s.left).sum();
    let mut t = empty;
    for s in &stats[..nchunks] {
        t.l_lo = t.l_lo.min(s.l_lo);
        t.l_hi = t.l_hi.max(s.l_hi);
        t.r_lo = t.r_lo.min(s.r_lo);
        t.r_hi = t.r_hi.max(s.r_hi);
    }
    (chunk, nchunks, stats, nl, to_aabb(t.l_lo, t.l_hi), to_aabb(t.r_lo, t.r_hi))
}

/// Scatter of a stable partition: the lefts of `src` in order into `lout` (nl long), the rights
/// into `rout`, each chunk into its own disjoint range.
pub fn part_scatter(src: &[PrimRef], chunk: usize, nchunks: usize, stats: &[PartStat; PARTITION_CHUNKS], lout: &mut [PrimRef], rout: &mut [PrimRef], is_left: &(impl Fn(&PrimRef) -> bool + Sync)) {
    let n = src.len();
    let (mut lrest, mut rrest) = (lout, rout);
    let mut outs: [(&mut [PrimRef], &mut [PrimRef]); PARTITION_CHUNKS] = std::array::from_fn(|_| (&mut [][..], &mut [][..]));
    for (k, o) in outs.iter_mut().enumerate().take(nchunks) {
        let len = chunk_len_at(n, chunk, k);
        let l = stats[k].left;
        let (lcut, rcut) = (l.min(lrest.len()), (len - l).min(rrest.len()));
        let (lo_part, lr) = std::mem::take(&mut lrest).split_at_mut(lcut);
        let (ro_part, rr) = std::mem::take(&mut rrest).split_at_mut(rcut);
        lrest = lr;
        rrest = rr;
        *o = (lo_part, ro_part);
    }
    src.par_chunks(chunk).zip(outs.par_iter_mut()).for_each(|(c, (lo, ro))| {
        let (mut i, mut j) = (0usize, 0usize);
        for r in c {
            if is_left(r) {
                if let Some(d) = lo.get_mut(i) {
                    *d = *r;
                }
                i += 1;
            } else {
                if let Some(d) = ro.get_mut(j) {
                    *d = *r;
                }
                j += 1;
            }
        }
    });
}

/// Stable partition of `refs` by `is_left` (left ones first, both sides in input order) into
/// the subtree's (still unwritten) node slots: the lefts at the start of the left child's slots
/// (1..2·nl), the rights at the start of the right child's (2·nl..2n-1); each child then finds
/// its references at the start of its own slots (`in_nodes`), and `refs` is left as it was.
/// Returns the left count and the boxes of both sides; with everything on one side
/// the caller must ignore the slots. None (nothing usable moved) when the slots cannot be
/// viewed as references. `one_pass`: sequentially, in one pass (`partition_one_pass`).
pub fn par_partition_to_nodes(refs: &[PrimRef], nodes: &mut [BinNode], one_pass: bool, is_left: impl Fn(&PrimRef) -> bool + Sync) -> Option<(usize, Aabb, Aabb)> {
    let n = refs.len();
    if one_pass {
        let rest = nodes.get_mut(1..)?;
        if rest.len() < 2 * n - 2 {
            return None;
        }
        let slot = std::mem::size_of::<BinNode>();
        return partition_one_pass(refs, bytemuck::cast_slice_mut(&mut rest[..2 * n - 2]), |nl| (2 * nl).saturating_sub(1) * slot, &is_left);
    }
    let (chunk, nchunks, stats, nl, l, r) = part_stats(refs, &is_left);
    if nl == 0 || nl == n {
        return Some((nl, l, r));
    }
    let rest = nodes.get_mut(1..)?;
    if rest.len() < 2 * n - 2 {
        return None;
    }
    let (lslots, rslots) = rest.split_at_mut(2 * nl - 1);
    let lout = node_refs_mut(lslots, nl)?;
    let rout = node_refs_mut(rslots, n - nl)?;
    part_scatter(refs, chunk, nchunks, &stats, lout, rout, &is_left);
    Some((nl, l, r))
}

/// The same stable partition for a node whose references are at the start of its node slots:
/// scattered straight into `refs`, which then holds all of them (partitioned) in every case.
pub fn par_partition_from_nodes(refs: &mut [PrimRef], nodes: &[BinNode], one_pass: bool, is_left: impl Fn(&PrimRef) -> bool + Sync) -> Option<(usize, Aabb, Aabb)> {
    let n = refs.len();
    let src = node_refs(nodes, n)?;
    if one_pass {
        return partition_one_pass(src, bytemuck::cast_slice_mut(refs), |nl| nl * PRIMREF_BYTES, &is_left);
    }
    let (chunk, nchunks, stats, nl, l, r) = part_stats(src, &is_left);
    let (lout, rout) = refs.split_at_mut(nl);
    part_scatter(src, chunk, nchunks, &stats, lout, rout, &is_left);
    Some((nl, l, r))
}

/// The stable partition of `par_partition_to_nodes` / `_from_nodes` in one sequential pass
/// (for nodes that have the thread to themselves, `BuildContext::one_pass`), where the left count is
/// not known in advance (sampled nodes): lefts ascending from the
/// start of `dst`, rights descending from its last whole reference, then the rights reversed
/// into place from byte `rbase(left count)`. The same order, count and boxes as `part_stats`
/// followed by `part_scatter` (same arithmetic, same branches), so the same bytes for any
/// thread count. Everything on one side still writes `dst`. None when `dst` is too small
/// (what was written is then garbage; `src` is never written).
pub fn partition_one_pass(src: &[PrimRef], dst: &mut [u8], rbase: impl Fn(usize) -> usize, is_left: &impl Fn(&PrimRef) -> bool) -> Option<(usize, Aabb, Aabb)> {
    let n = src.len();
    let top = dst.len() / PRIMREF_BYTES * PRIMREF_BYTES;
    if top < n * PRIMREF_BYTES {
        return None;
    }
    let (inf, ninf) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    let (mut l_lo, mut l_hi, mut r_lo, mut r_hi) = (inf, ninf, inf, ninf);
    let (mut li, mut ri) = (0usize, top);
    for r in src {
        let (lo, hi) = (ref_lo(r), ref_hi(r));
        // Branches, as in `part_stats`: high in the tree the sides come in long runs.
        if is_left(r) {
            if let Some(d) = dst.get_mut(li..).and_then(|x| x.first_chunk_mut::<PRIMREF_BYTES>()) {
                *d = bytemuck::cast(*r);
            }
            li += PRIMREF_BYTES;
            l_lo = l_lo.min(lo);
            l_hi = l_hi.max(hi);
        } else {
            ri -= PRIMREF_BYTES;
            if let Some(d) = dst.get_mut(ri..).and_then(|x| x.first_chunk_mut::<PRIMREF_BYTES>()) {
                *d = bytemuck::cast(*r);
            }
            r_lo = r_lo.min(lo);
            r_hi = r_hi.max(hi);
        }
    }
    let nl = li / PRIMREF_BYTES;
    let nr = n - nl;
    let out = (nl, to_aabb(l_lo, l_hi), to_aabb(r_lo, r_hi));
    if nr == 0 {
        return Some(out);
    }
    let rb = rbase(nl);
    let rend = rb.checked_add(nr * PRIMREF_BYTES).filter(|&e| e <= dst.len())?;
    if rend <= ri {
        // Disjoint (the usual case in node slots): one reversed copy.
        for j in 0..nr {
            let from = top - (j + 1) * PRIMREF_BYTES;
            dst.copy_within(from..from + PRIMREF_BYTES, rb + j * PRIMREF_BYTES);
        }
    } else {
        // Overlapping (always in place when partitioning back into `refs`): reverse where they
        // are, then move.
        let seg: &mut [PrimRef] = bytemuck::try_cast_slice_mut(dst.get_mut(ri..top)?).ok()?;
        seg.reverse();
        if rb != ri {
            dst.copy_within(ri..top, rb);
        }
    }
    Some(out)
}

#[inline]
pub fn chunk_len_at(n: usize, chunk: usize, k: usize) -> usize {
    n.saturating_sub(k * chunk).min(chunk)
}


//! The top of large BLAS trees, decided on one sample of the references (`plan`).
//!
//! Without it the first levels of a large tree each move every reference: a counting pass and
//! a scatter per level (dragon: four to five levels above the subtrees that threads build on
//! their own, 2.3–2.8 ms of a 16-thread FAST_BUILD build). Here ingest leaves its chunks
//! uncompacted; the splits of those levels are chosen on an evenly strided sample of the
//! references (`grow`, the binned SAH of `build_rec` on the sample); one pass gives every
//! reference its bucket (a leaf of that small tree) with exact per-chunk counts and boxes
//! (`classify_chunks`: each split test is a threshold on one centroid coordinate, a bucket a
//! box of centroids, looked up through the previous reference's bucket and a grid before any
//! walk down the tree); one scatter moves the references from their chunks into their
//! buckets' node slots (`scatter`), the copy compaction would otherwise have made. The top
//! nodes are written from the exact counts and boxes and each bucket becomes a task (`tasks`).
//!
//! Deterministic: the sample depends on the input alone, the classification on the sample,
//! and counts, boxes and the stable scatter order on neither chunking nor threads; whether a
//! build plans depends on its type and size alone. Host memory: the sample lives in the
//! unused node slots, the per-chunk cells and bucket bytes in scratch; the heap holds only
//! tables of a fixed size (the grid, the tree, the scatter's ranges).
use super::*;

/// BLAS builds with at least this many primitives plan their top (scratch permitting).
pub(super) const TOP_MIN: usize = 4 * PAR_BIN_CUTOFF;
/// Levels of the planned top at most: at most 64 buckets, one byte per reference names one.
const LEVELS: usize = 6;
const BUCKETS: usize = 1 << LEVELS;
/// Chunk groups of the scatter (fixed, whatever the thread count).
const GROUPS: usize = 64;
/// The root's sample is this many times the tier's `sample_target`; a top node is split while
/// its share of the sample holds at least `sample_target / MIN_SAMPLE_DIV` references (a
/// 32nd of the root's) and it is estimated to hold at least SPLIT_MIN. Dragon, one thread:
/// FAST_BUILD 16,384 samples, SAH 54.77 (54.70 with a sample per top node); the default tier
/// 32,768, 49.15 (49.14); FAST_TRACE 32,768, 48.96 (48.87; that per-node sampling gave 48.82
/// to 48.99 for sample sizes from 6,000 to 10,000: the top's SAH is the draw of a sample).
/// Smaller buckets fit a core's cache better: 16 threads on the 16-core machine, three
/// interleaved rounds, FAST_BUILD medians 12.6 / 12.0 / 10.8 ms with 24 buckets (nodes split
/// down to 32,768 references and 512 samples), 11.0 / 11.0 / 11.4 with 60; the default tier
/// 20.4 / 21.7 / 21.5 against 20.3 / 20.5 / 21.3. FAST_TRACE, four rounds, the old top against
/// this: 27.2 / 28.2 / 27.5 / 28.7 against 24.8 / 25.9 / 24.7 / 24.6. A sample twice as large
/// cost as much planning (0.5 ms) as it saved.
const ROOT_SAMPLE: usize = 4;
const MIN_SAMPLE_DIV: usize = 8;
const SPLIT_MIN: usize = PAR_BIN_CUTOFF / 2;
/// Samples from which a top node's sample partitions in parallel.
const PAR_SAMPLE_PARTITION: usize = 8192;
/// Samples per parallel binning task of a top node.
const SAMPLE_BIN_CHUNK: usize = 2048;

/// A node of the planned top: an inner node's split test and children, or a bucket.
#[derive(Clone, Copy)]
struct TopNode {
    split: Option<Splitter>,
    kids: [u32; 2],
    bucket: u32,
}

/// Per chunk and bucket: the count and box of the chunk's references in the bucket (scratch).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct BucketCell {
    lo: [f32; 3],
    count: u32,
    hi: [f32; 3],
    pad: u32,
}
/// Scratch words per bucket cell.
pub(super) const CELL_WORDS: usize = std::mem::size_of::<BucketCell>() / 4;

/// The planned top. Each split test `Splitter::left` (c < limit after (c - cmin)·scale, on
/// the centroid c = lo·0.5 + hi·0.5 of one axis) is monotonic in c, so it is the comparison
/// c < t with the threshold t of `threshold`, and a bucket is exactly the box of centroids
/// [lo, hi) its path's thresholds cut out. Neighbouring references mostly share a bucket, so
/// a reference is first tested against the previous reference's bucket box (one vector test);
/// only when it is outside does it look up the grid, then the bucket before that one, then
/// walk the tree: complete, `depth` levels in heap order (children of i at 2i + 1 and
/// 2i + 2; a bucket above the last level is padded with tests that send everything left).
pub(super) struct TopPlan {
    tree: Vec<TopNode>,
    pub(super) buckets: usize,
    depth: usize,
    /// Per test: its threshold in the split axis' lane, +inf in the others (left: c < t in
    /// every lane).
    t: [Vec3A; BUCKETS - 1],
    /// Per heap leaf: its bucket.
    bucket: [u8; BUCKETS],
    /// Per bucket: its box of centroids [lo, hi).
    lo: [Vec3A; BUCKETS],
    hi: [Vec3A; BUCKETS],
    /// A GRID³ grid over the root's centroid box: the bucket of every centroid in a cell that
    /// lies inside one bucket's box, NO_BUCKET for a cell that straddles a threshold.
    gmin: Vec3A,
    ginv: Vec3A,
    grid: Vec<u8>,
}

/// Cells of the classification grid per axis (a power of two) and the mark of a cell that
/// straddles a threshold.
const GRID: usize = 32;
const NO_BUCKET: u8 = u8::MAX;

/// The grid cell of centroid coordinate `c` on one axis, as the vector lanes of
/// `TopPlan::cell` compute it: truncation of the clamped scaled offset.
#[inline(always)]
fn grid_coord(c: f32, gmin: f32, ginv: f32) -> usize {
    ((c - gmin) * ginv).max(0.0).min((GRID - 1) as f32) as usize
}

/// The smallest finite c in cell `j` or above on one axis (-inf for cell 0, +inf when no
/// finite c reaches it): cells are intervals [first(j), first(j + 1)), since `grid_coord`
/// rounds monotonically. Binary search over the floats in order.
fn grid_first(j: usize, gmin: f32, ginv: f32) -> f32 {
    first_where(|c| grid_coord(c, gmin, ginv) >= j, j == 0)
}

/// The smallest finite c for which the monotonic `holds` is true (-inf when `below`, or when
/// it holds for every finite c; +inf when it holds for none).
fn first_where(holds: impl Fn(f32) -> bool, below: bool) -> f32 {
    // Float bits mapped to an order-preserving integer and back (finite values only here).
    let key = |f: f32| {
        let b = f.to_bits();
        if b >> 31 != 0 { !b } else { b | 1 << 31 }
    };
    let float = |k: u32| f32::from_bits(if k >> 31 != 0 { k & !(1 << 31) } else { !k });
    if below || holds(-f32::MAX) {
        return f32::NEG_INFINITY;
    }
    if !holds(f32::MAX) {
        return f32::INFINITY;
    }
    let (mut lo, mut hi) = (key(-f32::MAX), key(f32::MAX));
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if holds(float(mid)) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    float(hi)
}

/// The smallest finite c whose centroid test `sp.left` fails (-inf when it fails for every
/// finite c, +inf when it holds for every one): the test is c < t for every finite c, since
/// (c - cmin)·scale rounds monotonically for scale > 0.
fn threshold(sp: &Splitter) -> f32 {
    first_where(|c| !((c - sp.cmin) * sp.scale < sp.limit), false)
}

impl TopPlan {
    fn new(tree: Vec<TopNode>, buckets: usize, cb: &Aabb) -> TopPlan {
        fn levels(tree: &[TopNode], i: usize) -> usize {
            match tree.get(i) {
                Some(TopNode { split: Some(_), kids, .. }) => 1 + levels(tree, kids[0] as usize).max(levels(tree, kids[1] as usize)),
                _ => 0,
            }
        }
        let depth = levels(&tree, 0).min(LEVELS);
        let ext = Vec3A::from(cb.hi) - Vec3A::from(cb.lo);
        let ginv = Vec3A::select(ext.cmpgt(Vec3A::ZERO), Vec3A::splat(GRID as f32) / ext, Vec3A::ZERO);
        let ginv = Vec3A::select(ginv.is_finite_mask(), ginv, Vec3A::ZERO);
        let gmin = Vec3A::from(cb.lo);
        let mut t = TopPlan { tree, buckets, depth, t: [Vec3A::INFINITY; BUCKETS - 1], bucket: [0; BUCKETS], lo: [Vec3A::NEG_INFINITY; BUCKETS], hi: [Vec3A::INFINITY; BUCKETS], gmin, ginv, grid: vec![NO_BUCKET; GRID * GRID * GRID] };
        t.flatten(0, 0, 0, Vec3A::NEG_INFINITY, Vec3A::INFINITY);
        // Cell boundaries per axis, then every bucket marks the cells inside its box.
        let first: [[f32; GRID + 1]; 3] = std::array::from_fn(|a| std::array::from_fn(|j| if j == GRID { f32::INFINITY } else { grid_first(j, gmin[a], ginv[a]) }));
        for b in 0..t.buckets.min(BUCKETS) {
            let range = |a: usize| {
                let f = &first[a];
                // Cells j with first(j) >= lo and first(j + 1) <= hi.
                let j0 = (0..GRID).find(|&j| f[j] >= t.lo[b][a]).unwrap_or(GRID);
                let j1 = (0..GRID).rev().find(|&j| f[j + 1] <= t.hi[b][a]).map_or(0, |j| j + 1);
                j0..j1.max(j0)
            };
            let (rx, ry, rz) = (range(0), range(1), range(2));
            for z in rz.clone() {
                for y in ry.clone() {
                    for x in rx.clone() {
                        t.grid[x + GRID * (y + GRID * z)] = b as u8;
                    }
                }
            }
        }
        t
    }

    /// The grid cell of centroid `c` (`grid_coord` lane-wise).
    #[inline(always)]
    fn cell(&self, c: Vec3A) -> usize {
        let q = trunc_i32x4(((c - self.gmin) * self.ginv).max(Vec3A::ZERO).min(Vec3A::splat((GRID - 1) as f32)));
        (q[0] as usize + GRID * (q[1] as usize + GRID * q[2] as usize)) & (GRID * GRID * GRID - 1)
    }

    fn flatten(&mut self, i: usize, at: usize, level: usize, lo: Vec3A, hi: Vec3A) {
        let Some(&nd) = self.tree.get(i) else { return };
        match nd.split {
            Some(sp) if level < self.depth && at < BUCKETS - 1 => {
                let (a, th) = (sp.a.min(2), threshold(&sp));
                self.t[at][a] = th;
                let (mut lhi, mut rlo) = (hi, lo);
                lhi[a] = lhi[a].min(th);
                rlo[a] = rlo[a].max(th);
                self.flatten(nd.kids[0] as usize, 2 * at + 1, level + 1, lo, lhi);
                self.flatten(nd.kids[1] as usize, 2 * at + 2, level + 1, rlo, hi);
            }
            // A bucket above the last level: the padding test (+inf) sends it left.
            _ if level < self.depth => self.flatten(i, 2 * at + 1, level + 1, lo, hi),
            _ => {
                let b = nd.bucket as usize & (BUCKETS - 1);
                if let Some(x) = self.bucket.get_mut((at + 1).saturating_sub(1 << self.depth)) {
                    *x = b as u8;
                }
                (self.lo[b], self.hi[b]) = (lo, hi);
            }
        }
    }

    /// The bucket of centroid `c`: the walk down the thresholds.
    #[inline(always)]
    fn walk(&self, c: Vec3A) -> usize {
        let mut i = 0usize;
        for _ in 0..self.depth {
            let k = i.min(BUCKETS - 2);
            i = 2 * k + 1 + !c.cmplt(self.t[k]).all() as usize;
        }
        self.bucket[(i + 1).saturating_sub(1 << self.depth) & (BUCKETS - 1)] as usize & (BUCKETS - 1)
    }

    /// The buckets of `refs` into `out`, and each bucket's count and box into `cells`.
    fn classify(&self, refs: &[PrimRef], out: &mut [u8], cells: &mut [BucketCell]) {
        let mut lo = [Vec3A::INFINITY; BUCKETS];
        let mut hi = [Vec3A::NEG_INFINITY; BUCKETS];
        let mut count = [0u32; BUCKETS];
        // A run of references in one bucket keeps its box and count in registers.
        let (mut cur, mut rlo, mut rhi, mut rk) = (0usize, Vec3A::INFINITY, Vec3A::NEG_INFINITY, 0u32);
        let (mut blo, mut bhi) = (self.lo[0], self.hi[0]);
        // The bucket before the current one: boundaries are crossed back and forth.
        let (mut prev, mut plo, mut phi) = (0usize, self.lo[0], self.hi[0]);
        for (r, d) in refs.iter().zip(out.iter_mut()) {
            let (l, h) = (ref_lo(r), ref_hi(r));
            let c = l * 0.5 + h * 0.5;
            if !(c.cmpge(blo) & c.cmplt(bhi)).all() {
                count[cur] += rk;
                lo[cur] = lo[cur].min(rlo);
                hi[cur] = hi[cur].max(rhi);
                let g = self.grid[self.cell(c)];
                let next = if g != NO_BUCKET {
                    g as usize & (BUCKETS - 1)
                } else if (c.cmpge(plo) & c.cmplt(phi)).all() {
                    prev
                } else {
                    self.walk(c)
                };
                (prev, plo, phi) = (cur, blo, bhi);
                cur = next;
                (rlo, rhi, rk) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY, 0);
                (blo, bhi) = (self.lo[cur], self.hi[cur]);
            }
            *d = cur as u8;
            rlo = rlo.min(l);
            rhi = rhi.max(h);
            rk += 1;
        }
        count[cur] += rk;
        lo[cur] = lo[cur].min(rlo);
        hi[cur] = hi[cur].max(rhi);
        for (b, c) in cells.iter_mut().enumerate() {
            *c = BucketCell { lo: lo[b].to_array(), count: count[b], hi: hi[b].to_array(), pad: 0 };
        }
    }
}

/// The planned top below a node whose sample is `sample` (`step` references per sample):
/// splits as `build_rec` chooses them over the sample's bins, while the sample keeps at least
/// `min_sample` references and the node about SPLIT_MIN references. Returns the nodes
/// (this one first, indices relative to it) and the bucket count, buckets numbered left to
/// right. Depends on the sample alone.
fn grow(p: &BuildParams, sample: &mut [PrimRef], scratch: &mut [PrimRef], cb: Aabb, step: usize, level: usize, min_sample: usize) -> (Vec<TopNode>, u32) {
    let s = sample.len();
    let est = s.saturating_mul(step);
    let bucket = || (vec![TopNode { split: None, kids: [0; 2], bucket: 0 }], 1);
    if level >= LEVELS || s < min_sample.max(2) || est < SPLIT_MIN {
        return bucket();
    }
    let k = p.bins.clamp(2, MAX_BINS).min((est / REFS_PER_BIN).max(p.min_bins.max(2)));
    let Some((bn, scale)) = node_binning(p, &cb, k) else { return bucket() };
    let bins = if s >= 2 * SAMPLE_BIN_CHUNK {
        bin_in_chunks(sample, SAMPLE_BIN_CHUNK, k, bn.axes, |c, b| bin_refs(c, &bn, b))
    } else {
        let mut b = Bins::new();
        bin_refs(sample, &bn, &mut b);
        b
    };
    let Some((a, b, lbox, rbox, _)) = sweep_bins(&bins, k, &scale) else { return bucket() };
    let sp = bn.splitter(a, (b + 1) as f32);
    // Large samples partition in parallel into `scratch` (stable, in fixed chunks), which then
    // holds the children's samples and lends them `sample` as their scratch; small ones in
    // place. The tree never depends on a sample's order (bins are sums, minima and maxima).
    let is_left = |r: &PrimRef| sp.left(r);
    let (i, (ls, lt), (rs, rt)) = if s >= PAR_SAMPLE_PARTITION && scratch.len() >= s {
        let (chunk, nchunks, stats, nl, _, _) = part_stats(sample, &is_left);
        let (lout, rout) = scratch[..s].split_at_mut(nl);
        part_scatter(sample, chunk, nchunks, &stats, lout, rout, &is_left);
        let (lt, rt) = sample.split_at_mut(nl);
        (nl, (lout, lt), (rout, rt))
    } else {
        let i = partition_seq(sample, &sp);
        let (lt, rt) = scratch.split_at_mut(i.min(scratch.len()));
        let (ls, rs) = sample.split_at_mut(i);
        (i, (ls, lt), (rs, rt))
    };
    if i == 0 || i == s {
        return bucket();
    }
    let ((mut l, lb), (r, rb)) = if s >= 1024 {
        rayon::join(|| grow(p, ls, lt, lbox, step, level + 1, min_sample), || grow(p, rs, rt, rbox, step, level + 1, min_sample))
    } else {
        (grow(p, ls, lt, lbox, step, level + 1, min_sample), grow(p, rs, rt, rbox, step, level + 1, min_sample))
    };
    let off = 1 + l.len() as u32;
    let mut tree = Vec::with_capacity(1 + l.len() + r.len());
    tree.push(TopNode { split: Some(sp), kids: [1, off], bucket: 0 });
    for nd in &mut l {
        nd.kids = nd.kids.map(|x| x + 1);
    }
    tree.append(&mut l);
    tree.extend(r.into_iter().map(|nd| TopNode { split: nd.split, kids: nd.kids.map(|x| x + off), bucket: nd.bucket + lb }));
    (tree, lb + rb)
}

/// Plans the top of the tree over the `built` references that ingest left in its chunks of
/// `refs` (chunk c keeps the prefix `kept[c]` of its slots) from an evenly strided sample of
/// them in chunk order (what the compacted references would be), with the root's bins over
/// `cb` (the references' centroid box). The sample is gathered into `room` (scratch that is
/// free until the scatter), whose rest is the partitions' second buffer. None when the sample
/// does not split or `room` is too small.
pub(super) fn plan(desc: &BuildDesc, p: &BuildParams, refs: &[PrimRef], kept: &[u32], built: usize, cb: Aabb, room: &mut [PrimRef]) -> Option<TopPlan> {
    let target = p.sample_target.max(1) * ROOT_SAMPLE;
    let step = (built / target).max(1);
    if kept.iter().map(|&k| k as usize).sum::<usize>() != built {
        return None;
    }
    // In blocks of sample positions, each walking the chunks from the start (no per-chunk
    // table on the heap).
    const BLOCK: usize = 1024;
    let count = built.div_ceil(step);
    let (sample, scratch) = room.split_at_mut_checked(count)?;
    sample.par_chunks_mut(BLOCK).enumerate().for_each(|(blk, out)| {
        let mut chunks = chunk_layout(desc).zip(kept).map(|((first, len), &k)| (first, (k as usize).min(len)));
        let (mut cur, mut before) = (chunks.next(), 0usize);
        for (j, d) in out.iter_mut().enumerate() {
            let pos = (blk * BLOCK + j) * step;
            while let Some((_, k)) = cur {
                if pos < before + k {
                    break;
                }
                before += k;
                cur = chunks.next();
            }
            if let Some(r) = cur.and_then(|(first, _)| refs.get(first + pos - before)) {
                *d = *r;
            }
        }
    });
    let (tree, buckets) = grow(p, sample, scratch, cb, step, 0, p.sample_target / MIN_SAMPLE_DIV);
    let buckets = buckets as usize;
    (2..=BUCKETS).contains(&buckets).then(|| TopPlan::new(tree, buckets, &cb))
}

/// Whether a build of `total` primitives in `chunks` ingest chunks plans its top: a BLAS
/// build of at least TOP_MIN primitives whose `prefix` scratch (`words` u32) holds the
/// per-chunk kept counts, the bucket cells of any plan and one byte per reference slot.
pub(super) fn wanted(desc: &BuildDesc, total: usize, chunks: usize, words: usize) -> bool {
    let need = chunks.saturating_mul(1 + BUCKETS * CELL_WORDS).saturating_add(total.div_ceil(4));
    desc.ty != AsType::TopLevel && total >= TOP_MIN && need <= words
}

/// Ingest chunks of `desc` in order: (first reference slot, slots).
fn chunk_layout<'d>(desc: &'d BuildDesc<'d>) -> impl Iterator<Item = (usize, usize)> + 'd {
    let mut base = 0usize;
    desc.geometries.iter().flat_map(move |g| {
        let count = g.primitive_count as usize;
        let len = ingest_chunk(g);
        let b = base;
        base += count;
        (0..count.div_ceil(len)).map(move |ci| (b + ci * len, (count - ci * len).min(len)))
    })
}

/// Gives every kept reference (the prefix `kept[c]` of each ingest chunk c) its bucket in
/// `ids` (at its slot) and fills each chunk's bucket cells, in parallel over chunks.
pub(super) fn classify_chunks(plan: &TopPlan, desc: &BuildDesc, refs: &[PrimRef], kept: &[u32], cells: &mut [BucketCell], ids: &mut [u8]) {
    let nb = plan.buckets;
    // Geometry by geometry (chunks of one length), each chunk a task.
    let (mut base, mut first_chunk) = (0usize, 0usize);
    for g in desc.geometries {
        let count = g.primitive_count as usize;
        let len = ingest_chunk(g);
        let nch = count.div_ceil(len);
        let (Some(src), Some(k), Some(id), Some(cell)) = (refs.get(base..base + count), kept.get(first_chunk..first_chunk + nch), ids.get_mut(base..base + count), cells.get_mut(first_chunk * nb..(first_chunk + nch) * nb)) else { return };
        src.par_chunks(len).zip(k.par_iter()).zip(id.par_chunks_mut(len)).zip(cell.par_chunks_mut(nb)).for_each(|(((src, &k), id), cell)| {
            let k = (k as usize).min(src.len());
            plan.classify(&src[..k], &mut id[..k], cell);
        });
        base += count;
        first_chunk += nch;
    }
}

/// Exact reference counts and boxes of every planned top node (sums over its buckets' cells).
pub(super) struct TopSums {
    count: Vec<usize>,
    boxes: Vec<Aabb>,
}

pub(super) fn sums(plan: &TopPlan, cells: &[BucketCell]) -> Option<TopSums> {
    let nb = plan.buckets;
    let (mut bcount, mut blo, mut bhi) = ([0usize; BUCKETS], [Vec3A::INFINITY; BUCKETS], [Vec3A::NEG_INFINITY; BUCKETS]);
    for chunk in cells.chunks_exact(nb) {
        for (b, c) in chunk.iter().enumerate() {
            if c.count > 0 {
                bcount[b] += c.count as usize;
                blo[b] = blo[b].min(Vec3A::from(c.lo));
                bhi[b] = bhi[b].max(Vec3A::from(c.hi));
            }
        }
    }
    // Children follow their parent in `tree`: one backward pass sums them.
    let n = plan.tree.len();
    let (mut count, mut lo, mut hi) = (vec![0usize; n], vec![Vec3A::INFINITY; n], vec![Vec3A::NEG_INFINITY; n]);
    for i in (0..n).rev() {
        let nd = plan.tree[i];
        if nd.split.is_some() {
            let [l, r] = nd.kids.map(|x| x as usize);
            if l <= i || r <= i || l >= n || r >= n {
                return None;
            }
            (count[i], lo[i], hi[i]) = (count[l] + count[r], lo[l].min(lo[r]), hi[l].max(hi[r]));
        } else {
            let b = nd.bucket as usize & (BUCKETS - 1);
            (count[i], lo[i], hi[i]) = (bcount[b], blo[b], bhi[b]);
        }
    }
    let boxes = lo.iter().zip(&hi).map(|(&l, &h)| to_aabb(l, h)).collect();
    Some(TopSums { count, boxes })
}

impl TopSums {
    pub(super) fn total(&self) -> usize {
        self.count.first().copied().unwrap_or(0)
    }
}

/// Each bucket's (node slot, first reference): the buckets' subtrees laid out as
/// `finish_split` lays out children (left child at r + 1, right child at r + 2·left count);
/// an inner node with an empty side is replaced by its other child.
fn places(plan: &TopPlan, s: &TopSums, i: usize, slot: usize, first: usize, out: &mut [(usize, usize); BUCKETS]) {
    let Some(nd) = plan.tree.get(i) else { return };
    match nd.split {
        None => out[nd.bucket as usize & (BUCKETS - 1)] = (slot, first),
        Some(_) => {
            let [l, r] = nd.kids.map(|x| x as usize);
            let (nl, nr) = (s.count[l], s.count[r]);
            if nl == 0 {
                places(plan, s, r, slot, first, out);
            } else if nr == 0 {
                places(plan, s, l, slot, first, out);
            } else {
                places(plan, s, l, slot + 1, first, out);
                places(plan, s, r, slot + 2 * nl, first + nl, out);
            }
        }
    }
}

/// Moves every kept reference from its ingest chunk into its bucket: bucket b's references in
/// chunk order from the start of its node slots (`places`), so each bucket's subtree finds
/// them there (`build_rec`'s `in_nodes`). Chunk groups work in parallel, each on its own
/// disjoint ranges. None, with nothing written, when a range does not fit `nodes`.
pub(super) fn scatter(plan: &TopPlan, s: &TopSums, desc: &BuildDesc, refs: &[PrimRef], kept: &[u32], cells: &[BucketCell], ids: &[u8], nodes: &mut [BinNode]) -> Option<()> {
    let nb = plan.buckets;
    let mut at = [(0usize, 0usize); BUCKETS];
    places(plan, s, 0, 0, 0, &mut at);
    let nch = kept.len();
    let groups = nch.min(GROUPS).max(1);
    let bounds_of = |g: usize| (g * nch / groups, (g + 1) * nch / groups);
    // References per (group, bucket).
    let mut gcount = vec![0usize; groups * nb];
    for g in 0..groups {
        let (a, b) = bounds_of(g);
        for c in cells.chunks_exact(nb).take(b).skip(a) {
            for (k, cell) in c.iter().enumerate() {
                gcount[g * nb + k] += cell.count as usize;
            }
        }
    }
    let mut parts: Vec<&mut [PrimRef]> = Vec::with_capacity(groups * nb);
    parts.resize_with(groups * nb, || &mut [][..]);
    let mut order: Vec<usize> = (0..nb).filter(|&b| (0..groups).any(|g| gcount[g * nb + b] > 0)).collect();
    order.sort_by_key(|&b| at[b].0);
    let slot = std::mem::size_of::<BinNode>();
    let (mut rest, mut pos): (&mut [u8], usize) = (bytemuck::cast_slice_mut(nodes), 0);
    for &b in &order {
        let k: usize = (0..groups).map(|g| gcount[g * nb + b]).sum();
        let from = at[b].0 * slot;
        let t = std::mem::take(&mut rest).get_mut(from.checked_sub(pos)?..)?;
        if t.len() < k * PRIMREF_BYTES {
            return None;
        }
        let (area, t) = t.split_at_mut(k * PRIMREF_BYTES);
        rest = t;
        pos = from + k * PRIMREF_BYTES;
        let mut area: &mut [PrimRef] = bytemuck::try_cast_slice_mut(area).ok()?;
        for g in 0..groups {
            let (x, y) = std::mem::take(&mut area).split_at_mut(gcount[g * nb + b]);
            parts[g * nb + b] = x;
            area = y;
        }
    }
    parts.par_chunks_mut(nb).enumerate().for_each(|(g, outs)| {
        let (a, b) = bounds_of(g);
        let mut fill = [0usize; BUCKETS];
        for ((first, len), &k) in chunk_layout(desc).zip(kept).skip(a).take(b - a) {
            let k = (k as usize).min(len);
            let (Some(src), Some(id)) = (refs.get(first..first + k), ids.get(first..first + k)) else { continue };
            for (r, &b) in src.iter().zip(id) {
                let b = b as usize & (BUCKETS - 1);
                if let Some(d) = outs.get_mut(b).and_then(|o| o.get_mut(fill[b])) {
                    *d = *r;
                }
                fill[b] += 1;
            }
        }
    });
    Some(())
}

/// Writes the planned top's nodes and returns one task per non-empty bucket (its subtree,
/// references at the start of its node slots).
#[allow(clippy::too_many_arguments)]
pub(super) fn tasks<'a>(plan: &TopPlan, s: &TopSums, i: usize, refs: &'a mut [PrimRef], nodes: &'a mut [BinNode], pre: &'a mut [u8], start: u32, idx: usize, depth: u32, parent_count: u32, out: &mut Vec<Task<'a>>) {
    let (Some(nd), Some(&n), Some(&bx)) = (plan.tree.get(i), s.count.get(i), s.boxes.get(i)) else { return };
    if n == 0 {
        return;
    }
    let Some(_) = nd.split else {
        out.push(Task { refs, nodes, start, bounds: bx, cb: bx, depth, in_nodes: true, pre, parent_count, idx });
        return;
    };
    let [l, r] = nd.kids.map(|x| x as usize);
    let mid = s.count.get(l).copied().unwrap_or(0);
    if mid == 0 || mid >= n {
        return tasks(plan, s, if mid == 0 { r } else { l }, refs, nodes, pre, start, idx, depth, parent_count, out);
    }
    if let Some(slot) = nodes.get_mut(0) {
        *slot = BinNode { lo: bx.lo, start, hi: bx.hi, count: n as u32, left_count: mid as u32, reserved: 0 };
    }
    let (lrefs, rrefs) = refs.split_at_mut(mid.min(refs.len()));
    let rest = nodes.get_mut(1..).unwrap_or(&mut []);
    let (lnodes, rnodes) = rest.split_at_mut((2 * mid - 1).min(rest.len()));
    let (lpre, rpre) = pre.split_at_mut((PRE_BYTES_PER_PRIM * mid).min(pre.len()));
    tasks(plan, s, l, lrefs, lnodes, lpre, start, idx + 1, depth + 1, n as u32, out);
    tasks(plan, s, r, rrefs, rnodes, rpre, start + mid as u32, idx + 2 * mid, depth + 1, n as u32, out);
}

/// Ingest chunks of `desc` (one `kept` count each).
pub(super) fn chunk_count(desc: &BuildDesc) -> usize {
    chunk_layout(desc).count()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::builder::pass_timing::unit_floats as floats;

    fn next_up(f: f32) -> f32 {
        if f >= 0.0 { f32::from_bits(f.to_bits() + 1) } else { f32::from_bits(f.to_bits() - 1) }
    }
    fn next_down(f: f32) -> f32 {
        if f > 0.0 { f32::from_bits(f.to_bits() - 1) } else if f == 0.0 { -f32::from_bits(1) } else { f32::from_bits(f.to_bits() + 1) }
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
            let (gmin, ginv) = (cmin, scale);
            for j in 0..=GRID {
                let first = if j == GRID { f32::INFINITY } else { grid_first(j, gmin, ginv) };
                if first.is_finite() {
                    assert!(grid_coord(first, gmin, ginv) >= j && (j == 0 || grid_coord(next_down(first), gmin, ginv) < j), "case {case}: cell {j} starts at {first}");
                }
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
            let p = BuildParams::from_flags(BuildFlags(flags));
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
            let (tree, buckets) = grow(&p, &mut sample, &mut scratch, cb, step, 0, p.sample_target / MIN_SAMPLE_DIV);
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
            let mut cells = vec![BucketCell::zeroed(); buckets as usize];
            plan.classify(&refs, &mut ids, &mut cells);
            let mut want = vec![(0u32, Aabb::EMPTY); buckets as usize];
            for (r, &id) in refs.iter().zip(&ids) {
                let b = walk(r);
                assert_eq!(id as usize, b, "case {case}: reference {r:?}");
                want[b].0 += 1;
                want[b].1.grow(&r.lo, &r.hi);
            }
            for (c, (k, bx)) in cells.iter().zip(&want) {
                assert_eq!(c.count, *k, "case {case}");
                if *k > 0 {
                    assert_eq!((c.lo, c.hi), (bx.lo, bx.hi), "case {case}");
                }
            }
        }
    }
}

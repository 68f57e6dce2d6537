//! The planned top of large BLAS trees, decided on one sample (`plan_from_input`, `plan`).
//!
//! Without it the first levels of a large tree each move every reference: a counting pass and
//! a scatter per level (docs/TUNING.md). Here ingest leaves its chunks
//! uncompacted; the splits of those levels are chosen on an evenly strided sample (`grow_plan`, the
//! binned SAH of `build_rec` on the sample): of the input triangles, on one thread beside
//! ingest, when every geometry holds plain f32 triangles, else of the references after
//! ingest; one pass gives every
//! reference its bucket (a leaf of that small tree) with exact per-chunk counts and boxes
//! (`classify_chunks`: each split test is a threshold on one centroid coordinate, so a
//! centroid's ranks among each axis' thresholds name its bucket through one table); one
//! scatter moves the references from their chunks into their buckets' node slots
//! (`scatter`), the copy compaction would otherwise have made. The top
//! nodes are written from the exact counts and boxes and each bucket becomes a task (`tasks`).
//!
//! Deterministic: the sample depends on the input alone, the classification on the sample,
//! and counts, boxes and the stable scatter order on neither chunking nor threads; whether a
//! build plans depends on its type and size alone. Host memory: the sample lives in the
//! unused node slots, the per-chunk cells and bucket bytes in scratch; the heap holds only
//! tables of a fixed size (the axes' grids, the rank table, the tree, the scatter's ranges).
//!
//! Owns: the plan, the bucket classification and the scatter into buckets. Must not touch:
//! the subtrees below the buckets.
use super::bins::{bin_count, bin_in_chunks, bin_refs, node_binning, sweep_bins, Bins, Splitter};
use super::ingest::ingest_chunk;
use super::partition::{part_scatter, part_stats, partition_seq, PRIMREF_BYTES};
use super::subtree::Subtree;
use crate::accel::geometry::{ref_hi, ref_lo, to_aabb, trunc_lanes3, Aabb, PrimRef};
use crate::accel::params::{BuildParams, PLAN_BIN_CHUNK, PLAN_GRID, PLAN_INPUT_SAMPLE, PLAN_LEVELS, PLAN_MIN, PLAN_MIN_SAMPLE_DIV, PLAN_INPUT_PREFETCH, PLAN_PAR_PARTITION, PLAN_PAR_SPLIT, PLAN_ROOT_SAMPLE, PLAN_SAMPLE_BLOCK, PLAN_SCATTER_GROUPS, PLAN_SPLIT_MIN, PRE_BYTES_PER_PRIM};
use crate::accel::primitive::FastTris;
use crate::accel::tree::BinNode;
use crate::accel::{AsType, BuildDesc, BuildFlags};
use bytemuck::{Pod, Zeroable};
use glam::Vec3A;
use rayon::prelude::*;

/// Buckets of a plan at most: one byte per reference names one.
const BUCKETS: usize = 1 << PLAN_LEVELS;

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
pub struct BucketCell {
    lo: [f32; 3],
    count: u32,
    hi: [f32; 3],
    pad: u32,
}
/// Scratch words per bucket cell.
pub const CELL_WORDS: usize = std::mem::size_of::<BucketCell>() / 4;

/// The planned top. Each split test `Splitter::left` (c < limit after (c - cmin)·scale, on
/// the centroid c = lo·0.5 + hi·0.5 of one axis) is monotonic in c, so it is the comparison
/// c < t with the threshold t of `threshold`. On each axis the distinct thresholds T_0 < T_1
/// < … cut the line into intervals; a centroid's rank on the axis, the number of thresholds
/// it is not below, decides every test on that axis (c < T_i exactly when the rank is at
/// most i), so the three ranks name the bucket through one table. A rank comes from a fine
/// grid of the axis (`PLAN_GRID` cells): every threshold in a lower cell counts, the one in the
/// centroid's own cell is compared, and none in a higher cell does (the cell of a value is
/// monotonic in it); a cell with two or more thresholds counts them one by one.
pub struct TopPlan {
    tree: Vec<TopNode>,
    pub buckets: usize,
    /// Per axis: the distinct thresholds of its tests, in order.
    th: [Vec<f32>; 3],
    /// The axes' grids over the root's centroid box: PLAN_GRID cells per axis, axis by axis.
    gmin: Vec3A,
    ginv: Vec3A,
    line: Box<[[LineCell; PLAN_GRID]; 3]>,
    /// Bucket per rank triple, at rx + stride[1]·ry + stride[2]·rz.
    stride: [usize; 3],
    table: Box<[u8; TABLE]>,
}

/// One cell of an axis' grid: the thresholds in lower cells, and the one in this cell (`one`
/// = 1; 0 for none). `base` = MANY: two or more thresholds in the cell.
#[derive(Clone, Copy)]
struct LineCell {
    t: f32,
    base: u16,
    one: u16,
}
const MANY: u16 = u16::MAX;

/// Rank triples at most: the product of (thresholds + 1) over the axes, for at most
/// BUCKETS - 1 thresholds in all, is at most 22³.
const TABLE: usize = 1 << 14;
const _: () = assert!(22 * 22 * 22 <= TABLE && BUCKETS - 1 <= 63);

/// The grid cell of centroid coordinate `c` on one axis, as the vector lanes of
/// `TopPlan::ranks` compute it: truncation of the clamped scaled offset (monotonic in `c`).
#[inline(always)]
fn line_coord(c: f32, gmin: f32, ginv: f32) -> usize {
    ((c - gmin) * ginv).max(0.0).min((PLAN_GRID - 1) as f32) as usize
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
#[allow(clippy::neg_cmp_op_on_partial_ord)] // the negation of the split test itself, NaN included.
fn threshold(sp: &Splitter) -> f32 {
    first_where(|c| !((c - sp.cmin) * sp.scale < sp.limit), false)
}

impl TopPlan {
    fn new(tree: Vec<TopNode>, buckets: usize, cb: &Aabb) -> TopPlan {
        let mut th: [Vec<f32>; 3] = Default::default();
        for sp in tree.iter().filter_map(|nd| nd.split) {
            th[sp.a.min(2)].push(threshold(&sp));
        }
        for t in &mut th {
            t.sort_by(f32::total_cmp);
            t.dedup_by(|x, y| x.total_cmp(y).is_eq());
        }
        let ext = Vec3A::from(cb.hi) - Vec3A::from(cb.lo);
        let ginv = Vec3A::select(ext.cmpgt(Vec3A::ZERO), Vec3A::splat(PLAN_GRID as f32) / ext, Vec3A::ZERO);
        let ginv = Vec3A::select(ginv.is_finite_mask(), ginv, Vec3A::ZERO);
        let gmin = Vec3A::from(cb.lo);
        let mut line = Box::new([[LineCell { t: 0.0, base: 0, one: 0 }; PLAN_GRID]; 3]);
        for (a, cells) in line.iter_mut().enumerate() {
            let mut here = [0u16; PLAN_GRID];
            for &t in &th[a] {
                here[line_coord(t, gmin[a], ginv[a])] += 1;
            }
            let mut below = 0u16;
            for (j, cell) in cells.iter_mut().enumerate() {
                let t = th[a].get(below as usize).copied().unwrap_or(0.0);
                *cell = match here[j] {
                    0 => LineCell { t, base: below, one: 0 },
                    1 => LineCell { t, base: below, one: 1 },
                    _ => LineCell { t, base: MANY, one: 0 },
                };
                below += here[j];
            }
        }
        let dims = th.each_ref().map(|t| t.len() + 1);
        let stride = [1, dims[0], dims[0] * dims[1]];
        let mut plan = TopPlan { tree, buckets, th, gmin, ginv, line, stride, table: Box::new([0; TABLE]) };
        plan.fill(0, [0..dims[0], 0..dims[1], 0..dims[2]]);
        plan
    }

    /// Writes the bucket of every rank triple in `ranks` (ranges per axis), all of which reach
    /// node `i` of the tree: its children's sides of its test, or its bucket.
    fn fill(&mut self, i: usize, ranks: [std::ops::Range<usize>; 3]) {
        if ranks.iter().any(|r| r.is_empty()) {
            return;
        }
        let Some(&nd) = self.tree.get(i) else { return };
        match nd.split {
            Some(sp) => {
                // c < T_k exactly for ranks up to k.
                let (a, t) = (sp.a.min(2), threshold(&sp));
                let k = self.th[a].partition_point(|x| x.total_cmp(&t).is_lt());
                let (mut l, mut r) = (ranks.clone(), ranks);
                l[a].end = l[a].end.min(k + 1);
                r[a].start = r[a].start.max(k + 1);
                self.fill(nd.kids[0] as usize, l);
                self.fill(nd.kids[1] as usize, r);
            }
            None if ranks[2].end * self.stride[2] <= TABLE => {
                for z in ranks[2].clone() {
                    for y in ranks[1].clone() {
                        for x in ranks[0].clone() {
                            if let Some(b) = self.table.get_mut(x * self.stride[0] + y * self.stride[1] + z * self.stride[2]) {
                                *b = nd.bucket as u8;
                            }
                        }
                    }
                }
            }
            None => {}
        }
    }

    /// The bucket of centroid `c`: its ranks from the axes' grids, then the table. (A rank
    /// counts the thresholds `c` is not below, `!(c < t)`: the negation of the split test.)
    #[inline(always)]
    #[allow(clippy::neg_cmp_op_on_partial_ord)] // the negation of the split test, NaN included.
    fn bucket_of(&self, c: Vec3A) -> usize {
        let q = trunc_lanes3(((c - self.gmin) * self.ginv).max(Vec3A::ZERO).min(Vec3A::splat((PLAN_GRID - 1) as f32)));
        let mut idx = 0usize;
        for a in 0..3 {
            let cell = self.line[a][q[a] as usize & (PLAN_GRID - 1)];
            let rank = if cell.base != MANY { cell.base as usize + (!(c[a] < cell.t) as usize & cell.one as usize) } else { self.rank(a, c[a]) };
            idx += rank * self.stride[a];
        }
        self.table[idx & (TABLE - 1)] as usize & (BUCKETS - 1)
    }

    /// The rank of `c` on axis `a`, threshold by threshold (a grid cell with several).
    #[cold]
    #[inline(never)]
    #[allow(clippy::neg_cmp_op_on_partial_ord)] // the negation of the split test, NaN included.
    fn rank(&self, a: usize, c: f32) -> usize {
        self.th[a].iter().filter(|&&t| !(c < t)).count()
    }

    /// The buckets of `refs` into `out`, and each bucket's count and box into `cells`.
    fn classify(&self, refs: &[PrimRef], out: &mut [u8], cells: &mut [BucketCell]) {
        // Four sets of sums, one per reference of a group of four: neighbours mostly share a
        // bucket, and one set would chain each sum through memory from one to the next.
        const SETS: usize = 4;
        // Each bucket's box as one pair (split arrays 4 KiB apart alias in the store buffer).
        let mut acc = [[[Vec3A::INFINITY, Vec3A::NEG_INFINITY]; BUCKETS]; SETS];
        let mut count = [[0u32; BUCKETS]; SETS];
        let n = refs.len().min(out.len());
        let (refs, out) = (&refs[..n], &mut out[..n]);
        let mut add = |k: usize, r: &PrimRef, d: &mut u8| {
            let (l, h) = (ref_lo(r), ref_hi(r));
            let b = self.bucket_of(l * 0.5 + h * 0.5);
            *d = b as u8;
            let [bl, bh] = &mut acc[k][b];
            (*bl, *bh) = (bl.min(l), bh.max(h));
            count[k][b] += 1;
        };
        let mut groups = refs.chunks_exact(SETS).zip(out.chunks_exact_mut(SETS));
        for (rs, ds) in &mut groups {
            for (k, (r, d)) in rs.iter().zip(ds.iter_mut()).enumerate() {
                add(k, r, d);
            }
        }
        let tail = n / SETS * SETS;
        for (r, d) in refs[tail..].iter().zip(&mut out[tail..]) {
            add(0, r, d);
        }
        for (b, c) in cells.iter_mut().enumerate().take(BUCKETS) {
            let ([mut l, mut h], mut k) = (acc[0][b], count[0][b]);
            for s in 1..SETS {
                (l, h, k) = (l.min(acc[s][b][0]), h.max(acc[s][b][1]), k + count[s][b]);
            }
            *c = BucketCell { lo: l.to_array(), count: k, hi: h.to_array(), pad: 0 };
        }
    }
}

/// How a plan's sample stands for the references: each sample is `step` references; a top
/// node splits while its sample holds at least `min_sample`; `parallel`: whether large samples
/// bin, partition and split their children in parallel, or everything runs on the calling
/// thread (the plan is the same either way).
#[derive(Clone, Copy)]
struct Sampling {
    step: usize,
    min_sample: usize,
    parallel: bool,
}

/// The planned top below a node at `level` whose sample is `sample`: splits as `build_rec`
/// chooses them over the sample's bins, while the sample keeps at least `min_sample`
/// references and the node about PLAN_SPLIT_MIN references. Returns the nodes (this one
/// first, indices relative to it) and the bucket count, buckets numbered left to right.
/// Depends on the sample alone.
fn grow_plan(p: &BuildParams, sample: &mut [PrimRef], scratch: &mut [PrimRef], cb: Aabb, level: usize, sampling: Sampling) -> (Vec<TopNode>, u32) {
    let Sampling { step, min_sample, parallel: par } = sampling;
    let s = sample.len();
    let est = s.saturating_mul(step);
    let bucket = || (vec![TopNode { split: None, kids: [0; 2], bucket: 0 }], 1);
    if level >= PLAN_LEVELS || s < min_sample.max(2) || est < PLAN_SPLIT_MIN {
        return bucket();
    }
    let k = bin_count(p, est);
    let Some((bn, scale)) = node_binning(p, &cb, k, est) else { return bucket() };
    let bins = if par && s >= 2 * PLAN_BIN_CHUNK {
        bin_in_chunks(sample, PLAN_BIN_CHUNK, k, bn.axes, |c, b| bin_refs(c, &bn, b))
    } else {
        let mut b = Bins::new();
        bin_refs(sample, &bn, &mut b);
        b
    };
    let Some((a, b, lbox, rbox, _)) = sweep_bins(&bins, k, &scale, 1) else { return bucket() };
    let sp = bn.splitter(a, (b + 1) as f32);
    // Large samples partition in parallel into `scratch` (stable, in fixed chunks), which then
    // holds the children's samples and lends them `sample` as their scratch; small ones in
    // place. The tree never depends on a sample's order (bins are sums, minima and maxima).
    let is_left = |r: &PrimRef| sp.left(r);
    let (i, (ls, lt), (rs, rt)) = if par && s >= PLAN_PAR_PARTITION && scratch.len() >= s {
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
    let ((mut l, lb), (r, rb)) = if par && s >= PLAN_PAR_SPLIT {
        rayon::join(|| grow_plan(p, ls, lt, lbox, level + 1, sampling), || grow_plan(p, rs, rt, rbox, level + 1, sampling))
    } else {
        (grow_plan(p, ls, lt, lbox, level + 1, sampling), grow_plan(p, rs, rt, rbox, level + 1, sampling))
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
pub fn plan(desc: &BuildDesc, p: &BuildParams, refs: &[PrimRef], kept: &[u32], built: usize, cb: Aabb, room: &mut [PrimRef]) -> Option<TopPlan> {
    let target = p.sample_target.max(1) * PLAN_ROOT_SAMPLE;
    let step = (built / target).max(1);
    if kept.iter().map(|&k| k as usize).sum::<usize>() != built {
        return None;
    }
    // In blocks of sample positions, each walking the chunks from the start (no per-chunk
    // table on the heap).
    let count = built.div_ceil(step);
    let (sample, scratch) = room.split_at_mut_checked(count)?;
    sample.par_chunks_mut(PLAN_SAMPLE_BLOCK).enumerate().for_each(|(blk, out)| {
        let mut chunks = chunk_layout(desc).zip(kept).map(|((first, len), &k)| (first, (k as usize).min(len)));
        let (mut cur, mut before) = (chunks.next(), 0usize);
        for (j, d) in out.iter_mut().enumerate() {
            let pos = (blk * PLAN_SAMPLE_BLOCK + j) * step;
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
    plan_on(p, sample, scratch, cb, Sampling { step, min_sample: p.sample_target / PLAN_MIN_SAMPLE_DIV, parallel: true })
}

/// Plans the top, as `plan` does, from an evenly strided sample of PLAN_INPUT_SAMPLE input
/// primitives instead of the references, on the calling thread alone, so that it runs beside
/// ingest (`build` joins the two): every geometry holds plain f32 triangles (`FastTris`, read
/// directly, the sample's index bytes and vertices prefetched ahead). Not in parallel blocks: a
/// thread of the plan waiting for its blocks took ingest chunks meanwhile, and the plan ended
/// after ingest (docs/TUNING.md). The root's bins span the
/// sample's centroid box. FAST_BUILD's clusters are made by ingest later, so its sample is of
/// triangles: the plan only chooses the buckets, and any choice gives a valid top (their counts
/// and boxes come from the references themselves). The sample goes to `room`, whose rest is
/// the partitions' second buffer. None when a geometry is not plain, the sample does not
/// split or `room` is too small.
pub fn plan_from_input(desc: &BuildDesc, p: &BuildParams, total: usize, room: &mut [PrimRef]) -> Option<TopPlan> {
    if !desc.geometries.iter().all(|g| FastTris::of(g).is_some()) {
        return None;
    }
    let allow_update = desc.flags.contains(BuildFlags::ALLOW_UPDATE);
    let step = (total / PLAN_INPUT_SAMPLE).max(1);
    let (sample, scratch) = room.split_at_mut_checked(total.div_ceil(step))?;
    // The index bytes of the sample this many ahead are prefetched, and the vertices of the
    // sample half as far ahead (their indices are in cache by then).
    // Kept triangles (not the dropped ones) in order from the front, and their centroid box.
    let (mut n, mut clo, mut chi) = (0usize, Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    // The geometry of the current sample: its index, first global ID and reader.
    let (mut gi, mut gbase) = (0usize, 0usize);
    let mut fast = desc.geometries.first().and_then(FastTris::of);
    for j in 0..sample.len() {
        let id = j * step;
        while let Some(g) = desc.geometries.get(gi).filter(|g| id >= gbase + g.primitive_count as usize) {
            gbase += g.primitive_count as usize;
            gi += 1;
            fast = desc.geometries.get(gi).and_then(FastTris::of);
        }
        let Some(ft) = fast.as_ref() else { break };
        let end = gbase + desc.geometries.get(gi).map_or(0, |g| g.primitive_count as usize);
        let ahead = |k: usize| Some(id + k * step).filter(|&x| x < end).map(|x| (x - gbase) as u32);
        if let Some(q) = ahead(PLAN_INPUT_PREFETCH) {
            ft.prefetch_indices(q);
        }
        if let Some(q) = ahead(PLAN_INPUT_PREFETCH / 2) {
            ft.prefetch(q);
        }
        if let Some(Some((lo, hi, _))) = ft.bounds((id - gbase) as u32, allow_update) {
            if let Some(d) = sample.get_mut(n) {
                *d = PrimRef { lo: lo.to_array(), geom: gi as u32, hi: hi.to_array(), prim: id as u32 };
                n += 1;
                let c = lo * 0.5 + hi * 0.5;
                (clo, chi) = (clo.min(c), chi.max(c));
            }
        }
    }
    plan_on(p, &mut sample[..n], scratch, to_aabb(clo, chi), Sampling { step, min_sample: PLAN_INPUT_SAMPLE / (PLAN_ROOT_SAMPLE * PLAN_MIN_SAMPLE_DIV), parallel: false })
}

/// The planned top grown from `sample` (`grow_plan`, root bins over `cb`), when it has 2 to
/// BUCKETS buckets.
fn plan_on(p: &BuildParams, sample: &mut [PrimRef], scratch: &mut [PrimRef], cb: Aabb, sampling: Sampling) -> Option<TopPlan> {
    let (tree, buckets) = grow_plan(p, sample, scratch, cb, 0, sampling);
    let buckets = buckets as usize;
    (2..=BUCKETS).contains(&buckets).then(|| TopPlan::new(tree, buckets, &cb))
}

/// Whether a build of `total` primitives in `chunks` ingest chunks plans its top: a BLAS
/// build of at least PLAN_MIN primitives whose `prefix` scratch (`words` u32) holds the
/// per-chunk kept counts, the bucket cells of any plan and one byte per reference slot.
pub fn should_plan(desc: &BuildDesc, total: usize, chunks: usize, words: usize) -> bool {
    let need = chunks.saturating_mul(1 + BUCKETS * CELL_WORDS).saturating_add(total.div_ceil(4));
    desc.ty != AsType::TopLevel && total >= PLAN_MIN && need <= words
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
pub fn classify_chunks(plan: &TopPlan, desc: &BuildDesc, refs: &[PrimRef], kept: &[u32], cells: &mut [BucketCell], ids: &mut [u8]) {
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
pub struct PlanSums {
    count: Vec<usize>,
    boxes: Vec<Aabb>,
}

pub fn bucket_sums(plan: &TopPlan, cells: &[BucketCell]) -> Option<PlanSums> {
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
    Some(PlanSums { count, boxes })
}

impl PlanSums {
    /// References in the smallest non-empty bucket of `plan` (0 when all are empty).
    pub fn smallest_bucket(&self, plan: &TopPlan) -> usize {
        plan.tree.iter().zip(&self.count).filter(|(nd, &c)| nd.split.is_none() && c > 0).map(|(_, &c)| c).min().unwrap_or(0)
    }
    pub fn total(&self) -> usize {
        self.count.first().copied().unwrap_or(0)
    }
}

/// Each bucket's (node slot, first reference): the buckets' subtrees laid out as
/// `finish_split` lays out children (left child at r + 1, right child at r + 2·left count);
/// an inner node with an empty side is replaced by its other child.
fn bucket_slots(plan: &TopPlan, s: &PlanSums, i: usize, slot: usize, first: usize, out: &mut [(usize, usize); BUCKETS]) {
    let Some(nd) = plan.tree.get(i) else { return };
    match nd.split {
        None => out[nd.bucket as usize & (BUCKETS - 1)] = (slot, first),
        Some(_) => {
            let [l, r] = nd.kids.map(|x| x as usize);
            let (nl, nr) = (s.count[l], s.count[r]);
            if nl == 0 {
                bucket_slots(plan, s, r, slot, first, out);
            } else if nr == 0 {
                bucket_slots(plan, s, l, slot, first, out);
            } else {
                bucket_slots(plan, s, l, slot + 1, first, out);
                bucket_slots(plan, s, r, slot + 2 * nl, first + nl, out);
            }
        }
    }
}

/// What `classify_chunks` found: each ingest chunk's kept count and bucket cells, and each
/// reference's bucket (at its slot).
#[derive(Clone, Copy)]
pub struct Classified<'a> {
    pub kept: &'a [u32],
    pub cells: &'a [BucketCell],
    pub ids: &'a [u8],
}

/// Moves every kept reference from its ingest chunk into its bucket: bucket b's references in
/// chunk order from the start of its node slots (`bucket_slots`), so each bucket's subtree finds
/// them there (`build_rec`'s `in_nodes`). Chunk groups work in parallel, each on its own
/// disjoint ranges. None, with nothing written, when a range does not fit `nodes`.
pub fn scatter(plan: &TopPlan, s: &PlanSums, desc: &BuildDesc, refs: &[PrimRef], classified: Classified<'_>, nodes: &mut [BinNode]) -> Option<()> {
    let Classified { kept, cells, ids } = classified;
    let nb = plan.buckets;
    let mut at = [(0usize, 0usize); BUCKETS];
    bucket_slots(plan, s, 0, 0, 0, &mut at);
    let nch = kept.len();
    let groups = nch.clamp(1, PLAN_SCATTER_GROUPS);
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

/// Writes the planned top's nodes below plan node `i` and returns one task per non-empty
/// bucket (its subtree, references at the start of its node slots). `at` is the position of
/// node `i` in the tree (its references, node slots, pre-emission range, first reference,
/// slot, depth and parent's size); its boxes and `in_nodes` are set here.
pub fn tasks<'a>(plan: &TopPlan, s: &PlanSums, i: usize, at: Subtree<'a>, out: &mut Vec<Subtree<'a>>) {
    let (Some(nd), Some(&n), Some(&bx)) = (plan.tree.get(i), s.count.get(i), s.boxes.get(i)) else { return };
    if n == 0 {
        return;
    }
    let Some(_) = nd.split else {
        out.push(Subtree { bounds: bx, bin_box: bx, in_nodes: true, ..at });
        return;
    };
    let [l, r] = nd.kids.map(|x| x as usize);
    let mid = s.count.get(l).copied().unwrap_or(0);
    if mid == 0 || mid >= n {
        return tasks(plan, s, if mid == 0 { r } else { l }, at, out);
    }
    let Subtree { refs, nodes, pre_area, start, slot, depth, .. } = at;
    if let Some(node) = nodes.get_mut(0) {
        *node = BinNode { lo: bx.lo, start, hi: bx.hi, count: n as u32, left_count: mid as u32, wide_nodes: 0 };
    }
    let (lrefs, rrefs) = refs.split_at_mut(mid.min(refs.len()));
    let rest = nodes.get_mut(1..).unwrap_or(&mut []);
    let (lnodes, rnodes) = rest.split_at_mut((2 * mid - 1).min(rest.len()));
    let (lpre, rpre) = pre_area.split_at_mut((PRE_BYTES_PER_PRIM * mid).min(pre_area.len()));
    let child = |refs, nodes, pre_area, start, slot| Subtree { refs, nodes, start, bounds: bx, bin_box: bx, depth: depth + 1, in_nodes: true, pre_area, parent_count: n as u32, slot };
    tasks(plan, s, l, child(lrefs, lnodes, lpre, start, slot + 1), out);
    tasks(plan, s, r, child(rrefs, rnodes, rpre, start + mid as u32, slot + 2 * mid), out);
}

/// Ingest chunks of `desc` (one `kept` count each).
pub fn chunk_count(desc: &BuildDesc) -> usize {
    chunk_layout(desc).count()
}

#[cfg(test)]
mod tests;

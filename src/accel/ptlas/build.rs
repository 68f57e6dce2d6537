//! One PTLAS build: pick the layout (the source's, or a new one when the capacities grew),
//! apply the op records to the stored state (writes, then updates, then translations), rebuild
//! the partitions they touched, then the top level, then the headers.
//!
//! Owns: the state transitions of instance slots, membership and translations. Must not touch:
//! tree shape (`tree`), section placement (`layout`).
use bytemuck::Zeroable;
use rayon::prelude::*;

use super::layout::{self, Capacities, PartitionRecord, PtlasHeader, Sections, StoredInstance, NO_ROOT, PARTITION_RECORD_SIZE, STORED_INSTANCE_SIZE};
use super::tree::{self, Changed, Entry};
use super::{BuildReport, Ops, PtlasError, Source, UpdateInstance, WriteInstance, WriteTranslation};
use super::{INSTANCE_FLAGS_SHARED_WITH_KHR, INSTANCE_FLAG_EXPLICIT_BOUNDING_BOX, OP_UPDATE_INSTANCE, OP_WRITE_INSTANCE, OP_WRITE_PARTITION_TRANSLATION, PARTITION_INDEX_GLOBAL};
use crate::accel::geometry::{instance_bounds_of, sanitize, Aabb, BlasBoundsMemo};
use crate::accel::input::invert_transform;
use crate::accel::layout::{self as base, InstanceRecord, PrimRecord, RawHeader, WideNode, CHILD_INTERNAL, INSTANCE_RECORD_SIZE, NODE_SIZE, RECORD_SIZE};
use super::Input;
use crate::accel::DeviceView;

/// Scratch is not needed by the build (its working arrays are per partition and small); a
/// non-zero size is still reported, since real clients allocate scratch only when non-zero and
/// portable tests require it.
const SCRATCH_SIZE: u64 = 64;

pub fn scratch_size(_c: &Capacities) -> u64 {
    SCRATCH_SIZE
}

fn rd<T: bytemuck::Pod>(b: &[u8], off: u64) -> T {
    let o = off as usize;
    bytemuck::pod_read_unaligned(&b[o..o + std::mem::size_of::<T>()])
}

fn wr<T: bytemuck::Pod>(b: &mut [u8], off: u64, v: &T) {
    let o = off as usize;
    b[o..o + std::mem::size_of::<T>()].copy_from_slice(bytemuck::bytes_of(v));
}

/// The blob being built: its header, sections and bytes.
struct Blob<'a> {
    h: PtlasHeader,
    s: Sections,
    c: Capacities,
    bytes: &'a mut [u8],
}

impl Blob<'_> {
    fn stored(&self, slot: u32) -> StoredInstance {
        rd(self.bytes, self.s.instances + slot as u64 * STORED_INSTANCE_SIZE as u64)
    }
    fn set_stored(&mut self, slot: u32, v: &StoredInstance) {
        wr(self.bytes, self.s.instances + slot as u64 * STORED_INSTANCE_SIZE as u64, v)
    }
    fn partition(&self, p: u32) -> PartitionRecord {
        rd(self.bytes, self.s.partitions + p as u64 * PARTITION_RECORD_SIZE as u64)
    }
    fn set_partition(&mut self, p: u32, v: &PartitionRecord) {
        wr(self.bytes, self.s.partitions + p as u64 * PARTITION_RECORD_SIZE as u64, v)
    }
    /// Byte offset and capacity of partition p's member list (p = partitions: the global one).
    fn members_at(&self, p: u32) -> (u64, u32) {
        let start = self.s.members + p as u64 * self.c.per_partition as u64 * 4;
        (start, if p == self.c.partitions { self.c.global } else { self.c.per_partition })
    }
    fn members(&self, p: u32) -> Vec<u32> {
        let (at, _) = self.members_at(p);
        let n = self.partition(p).member_count;
        (0..n).map(|k| rd::<u32>(self.bytes, at + k as u64 * 4)).collect()
    }
    /// Position of `slot` in the sorted list p (Ok: present).
    fn find(&self, p: u32, slot: u32) -> Result<u32, u32> {
        let (at, _) = self.members_at(p);
        let (mut lo, mut hi) = (0u32, self.partition(p).member_count);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            match rd::<u32>(self.bytes, at + mid as u64 * 4).cmp(&slot) {
                std::cmp::Ordering::Less => lo = mid + 1,
                std::cmp::Ordering::Greater => hi = mid,
                std::cmp::Ordering::Equal => return Ok(mid),
            }
        }
        Err(lo)
    }
    fn insert(&mut self, p: u32, slot: u32, record: u32) -> Result<(), PtlasError> {
        let (at, cap) = self.members_at(p);
        let mut rec = self.partition(p);
        let Err(pos) = self.find(p, slot) else { return Ok(()) };
        if rec.member_count >= cap {
            return Err(PtlasError::PartitionFull { record, partition: p });
        }
        let (from, to) = ((at + pos as u64 * 4) as usize, (at + rec.member_count as u64 * 4) as usize);
        self.bytes.copy_within(from..to, from + 4);
        wr(self.bytes, at + pos as u64 * 4, &slot);
        rec.member_count += 1;
        self.set_partition(p, &rec);
        Ok(())
    }
    fn remove(&mut self, p: u32, slot: u32) {
        let (at, _) = self.members_at(p);
        let mut rec = self.partition(p);
        let Ok(pos) = self.find(p, slot) else { return };
        let (from, end) = ((at + (pos as u64 + 1) * 4) as usize, (at + rec.member_count as u64 * 4) as usize);
        self.bytes.copy_within(from..end, from - 4);
        // The freed tail word goes back to zero: the bytes depend on the member set only.
        wr(self.bytes, at + (rec.member_count as u64 - 1) * 4, &0u32);
        rec.member_count -= 1;
        self.set_partition(p, &rec);
    }
}

/// Clear the blob and lay out empty state for `c`.
fn init(bytes: &mut [u8], c: Capacities, build_flags: u32) -> Blob<'_> {
    let s = layout::sections(&c);
    bytes[..s.end as usize].fill(0);
    let h = layout::header_for(&c, &s, build_flags);
    let mut blob = Blob { h, s, c, bytes };
    let empty = PartitionRecord { root: NO_ROOT, ..PartitionRecord::zeroed() };
    for p in 0..=c.partitions {
        blob.set_partition(p, &empty);
    }
    blob
}

/// The state of a blob, taken out so it can be laid out again.
struct Saved {
    instances: Vec<(u32, StoredInstance)>,
    translations: Vec<(u32, [f32; 3])>,
}

fn save(bytes: &[u8], h: &PtlasHeader) -> Saved {
    let c = Capacities::of_header(h);
    let s = layout::sections(&c);
    let instances = (0..c.instances)
        .map(|k| (k, rd::<StoredInstance>(bytes, s.instances + k as u64 * STORED_INSTANCE_SIZE as u64)))
        .filter(|(_, st)| st.written != 0)
        .collect();
    let translations = (0..=c.partitions)
        .map(|p| {
            let r: PartitionRecord = rd(bytes, s.partitions + p as u64 * PARTITION_RECORD_SIZE as u64);
            // The global partition keeps its translation across a new layout.
            (if p == c.partitions { PARTITION_INDEX_GLOBAL } else { p }, r.translation)
        })
        .filter(|(_, t)| *t != [0.0; 3])
        .collect();
    Saved { instances, translations }
}

/// The partition slot of a partition index (the global partition is the last slot).
fn slot_of(c: &Capacities, partition_index: u32) -> u32 {
    if partition_index == PARTITION_INDEX_GLOBAL {
        c.partitions
    } else {
        partition_index
    }
}

fn restore(blob: &mut Blob, saved: &Saved, dirty: &mut [bool]) {
    for (slot, st) in &saved.instances {
        let p = slot_of(&blob.c, st.partition_index);
        if *slot >= blob.c.instances || p > blob.c.partitions || blob.insert(p, *slot, 0).is_err() {
            continue;
        }
        blob.set_stored(*slot, st);
    }
    for (index, t) in &saved.translations {
        let p = slot_of(&blob.c, *index);
        if p <= blob.c.partitions {
            let mut r = blob.partition(p);
            r.translation = *t;
            blob.set_partition(p, &r);
        }
    }
    dirty.fill(true);
}

/// The blob the build continues from, laid out for the capacities it will have.
fn open<'a>(input: &Input, source: Source, dst: &'a mut [u8]) -> Result<(Blob<'a>, Vec<bool>, bool), PtlasError> {
    let want = Capacities::of(input);
    let prior = match source {
        Source::Empty => None,
        Source::InPlace => Some(layout::parse(dst).ok_or(PtlasError::InvalidSource)?),
        Source::Other(src) => Some(layout::parse(src).ok_or(PtlasError::InvalidSource)?),
    };
    // A grown source keeps its larger capacities when dst holds them (clients vary
    // instanceCount between builds); otherwise the layout is this build's.
    let caps = match prior {
        Some(h) => {
            let grown = Capacities::of_header(&h).max(want);
            if layout::sections(&grown).end <= dst.len() as u64 { grown } else { want }
        }
        None => want,
    };
    let s = layout::sections(&caps);
    if s.end > dst.len() as u64 {
        return Err(PtlasError::DestinationTooSmall { needed: s.end, got: dst.len() as u64 });
    }
    if s.top_nodes.saturating_add(caps.partitions as u64 * s.partition_nodes) > u32::MAX as u64 {
        return Err(PtlasError::DestinationTooSmall { needed: u64::MAX, got: dst.len() as u64 });
    }
    let mut dirty = vec![false; caps.partitions as usize + 1];
    let same = prior.is_some_and(|h| Capacities::of_header(&h) == caps);
    let blob = match (source, prior) {
        (Source::InPlace, Some(_)) if same => Blob { h: layout::header_for(&caps, &s, input.flags), s, c: caps, bytes: dst },
        (Source::Other(src), Some(_)) if same => {
            dst[..s.end as usize].copy_from_slice(&src[..s.end as usize]);
            Blob { h: layout::header_for(&caps, &s, input.flags), s, c: caps, bytes: dst }
        }
        (Source::Other(src), Some(h)) => {
            let saved = save(src, &h);
            let mut b = init(dst, caps, input.flags);
            restore(&mut b, &saved, &mut dirty);
            b
        }
        (_, Some(h)) => {
            let saved = save(dst, &h);
            let mut b = init(dst, caps, input.flags);
            restore(&mut b, &saved, &mut dirty);
            b
        }
        (_, None) => init(dst, caps, input.flags),
    };
    let relaid = prior.is_some() && !same;
    Ok((blob, dirty, relaid))
}

/// What the ops of one build did to each partition (index `partitions`: the global one).
struct Dirty {
    /// Its records, tree or bounds must be redone.
    touched: Vec<bool>,
    /// Its member set, its set of active members or its translation changed: the tree is rebuilt.
    reshaped: Vec<bool>,
    /// (partition, slot and its box in the tree) of records that changed while the partition's
    /// leaf set stayed.
    changed: Vec<(u32, Changed)>,
    /// BLAS bounds for the boxes of `changed`.
    memo: BlasBoundsMemo,
}

impl Dirty {
    fn reshape(&mut self, p: u32) {
        self.touched[p as usize] = true;
        self.reshaped[p as usize] = true;
    }
    /// `slot` of partition p changed from `old` to `new`; its leaf set changed too when the
    /// slot's activity flipped. The box `old` had in the tree is kept to find its leaf.
    fn change(&mut self, blob: &Blob, p: u32, slot: u32, old: &StoredInstance, new: &StoredInstance, view: &dyn DeviceView) {
        self.touched[p as usize] = true;
        if active(old) != active(new) {
            self.reshaped[p as usize] = true;
        } else if !self.reshaped[p as usize] {
            let previous = active(old).then(|| {
                let t = blob.partition(p).translation;
                let (lo, hi) = leaf_bounds(old, &translated(old, t), t, &mut self.memo, view);
                Aabb { lo, hi }
            });
            self.changed.push((p, Changed { slot, previous }));
        }
    }
}

fn apply_writes(blob: &mut Blob, input: &Input, ops: &Ops, dirty: &mut Dirty, view: &dyn DeviceView) -> Result<(), PtlasError> {
    let op = OP_WRITE_INSTANCE;
    for k in 0..ops.writes.count {
        let w: WriteInstance = ops.writes.get(k).ok_or(PtlasError::RecordUnreadable { op, record: k })?;
        if w.instance_index >= input.instance_count {
            return Err(PtlasError::InstanceIndex { op, record: k, index: w.instance_index });
        }
        if w.partition_index != PARTITION_INDEX_GLOBAL && w.partition_index >= input.partition_count {
            return Err(PtlasError::PartitionIndex { op, record: k, index: w.partition_index });
        }
        let slot = w.instance_index;
        let np = slot_of(&blob.c, w.partition_index);
        let old = blob.stored(slot);
        let moved = old.written == 0 || slot_of(&blob.c, old.partition_index) != np;
        if old.written != 0 && moved {
            let op_ = slot_of(&blob.c, old.partition_index);
            blob.remove(op_, slot);
            dirty.reshape(op_);
        }
        blob.insert(np, slot, k)?;
        let st = StoredInstance {
            transform: w.transform,
            explicit_aabb: w.explicit_aabb,
            instance_id: w.instance_id,
            mask: w.instance_mask,
            sbt_offset: w.instance_contribution_to_hit_group_index,
            flags: w.instance_flags,
            instance_index: w.instance_index,
            partition_index: w.partition_index,
            blas: w.acceleration_structure,
            written: 1,
            reserved: 0,
        };
        if moved {
            dirty.reshape(np);
        } else {
            dirty.change(blob, np, slot, &old, &st, view);
        }
        blob.set_stored(slot, &st);
    }
    Ok(())
}

fn apply_updates(blob: &mut Blob, input: &Input, ops: &Ops, dirty: &mut Dirty, ignored: &mut u32, view: &dyn DeviceView) -> Result<(), PtlasError> {
    let op = OP_UPDATE_INSTANCE;
    for k in 0..ops.updates.count {
        let u: UpdateInstance = ops.updates.get(k).ok_or(PtlasError::RecordUnreadable { op, record: k })?;
        if u.instance_index >= input.instance_count {
            return Err(PtlasError::InstanceIndex { op, record: k, index: u.instance_index });
        }
        let mut st = blob.stored(u.instance_index);
        if st.written == 0 {
            *ignored += 1;
            continue;
        }
        let old = st;
        st.sbt_offset = u.instance_contribution_to_hit_group_index;
        st.blas = u.acceleration_structure;
        blob.set_stored(u.instance_index, &st);
        dirty.change(blob, slot_of(&blob.c, st.partition_index), u.instance_index, &old, &st, view);
    }
    Ok(())
}

fn apply_translations(blob: &mut Blob, input: &Input, ops: &Ops, dirty: &mut Dirty) -> Result<(), PtlasError> {
    let op = OP_WRITE_PARTITION_TRANSLATION;
    for k in 0..ops.translations.count {
        let t: WriteTranslation = ops.translations.get(k).ok_or(PtlasError::RecordUnreadable { op, record: k })?;
        if !blob.c.translation {
            return Err(PtlasError::TranslationNotEnabled { record: k });
        }
        if t.partition_index != PARTITION_INDEX_GLOBAL && t.partition_index >= input.partition_count {
            return Err(PtlasError::PartitionIndex { op, record: k, index: t.partition_index });
        }
        let p = slot_of(&blob.c, t.partition_index);
        let mut r = blob.partition(p);
        r.translation = t.partition_translation;
        blob.set_partition(p, &r);
        dirty.reshape(p);
    }
    Ok(())
}

/// Active: written, with a BLAS, and not degenerate (an all-zero or NaN transform adds nothing).
fn active(st: &StoredInstance) -> bool {
    st.written != 0 && st.blas != 0 && st.transform.iter().any(|&x| x != 0.0) && !st.transform.iter().any(|x| x.is_nan())
}

/// One rebuilt partition: its nodes, its members' traversal records, its bounds.
struct Rebuilt {
    p: u32,
    nodes: Vec<WideNode>,
    records: Vec<(u32, InstanceRecord, u64)>,
    bounds: Option<Aabb>,
    entries: Vec<Entry>,
}

/// The traversal record of one slot of a partition translated by `t`, its BLAS table entry,
/// and its leaf box when active.
fn traversal_record(slot: u32, st: &StoredInstance, t: [f32; 3], memo: &mut BlasBoundsMemo, view: &dyn DeviceView) -> (InstanceRecord, u64, Option<Aabb>) {
    let mut rec = InstanceRecord { instance_index: slot, ..InstanceRecord::zeroed() };
    if !active(st) {
        return (rec, 0, None);
    }
    let world = translated(st, t);
    rec.object_to_world = world;
    rec.world_to_object = invert_transform(&world);
    rec.custom_index = st.instance_id & 0x00ff_ffff;
    rec.mask = st.mask & 0xff;
    rec.sbt_offset = st.sbt_offset & 0x00ff_ffff;
    rec.flags = st.flags & INSTANCE_FLAGS_SHARED_WITH_KHR;
    rec.blas_index = slot;
    let (lo, hi) = leaf_bounds(st, &world, t, memo, view);
    (rec, st.blas, Some(Aabb { lo, hi }))
}

/// The stored transform with the partition translation added.
fn translated(st: &StoredInstance, t: [f32; 3]) -> [f32; 12] {
    let mut world = st.transform;
    world[3] += t[0];
    world[7] += t[1];
    world[11] += t[2];
    world
}

/// The box of an active instance: its explicit AABB (translated) or its BLAS through `world`.
fn leaf_bounds(st: &StoredInstance, world: &[f32; 12], t: [f32; 3], memo: &mut BlasBoundsMemo, view: &dyn DeviceView) -> ([f32; 3], [f32; 3]) {
    if st.flags & INSTANCE_FLAG_EXPLICIT_BOUNDING_BOX != 0 {
        let b = st.explicit_aabb;
        sanitize([b[0] + t[0], b[1] + t[1], b[2] + t[2]], [b[3] + t[0], b[4] + t[1], b[5] + t[2]])
    } else {
        instance_bounds_of(world, memo.get(st.blas, view))
    }
}

fn rebuild(blob: &Blob, p: u32, view: &dyn DeviceView) -> Rebuilt {
    let members = blob.members(p);
    let t = blob.partition(p).translation;
    let mut records = Vec::with_capacity(members.len());
    let mut entries = Vec::with_capacity(members.len());
    let mut memo = BlasBoundsMemo::new();
    for &slot in &members {
        let (rec, blas, b) = traversal_record(slot, &blob.stored(slot), t, &mut memo, view);
        records.push((slot, rec, blas));
        if let Some(b) = b {
            entries.push(Entry { lo: b.lo, hi: b.hi, child: slot, kind: 1 });
        }
    }
    let mut nodes = Vec::new();
    let bounds = if p < blob.c.partitions {
        let base = (blob.s.top_nodes + p as u64 * blob.s.partition_nodes) as u32;
        tree::build(&mut entries, base, &mut nodes)
    } else {
        // Global instances are top-level entries of their own.
        None
    };
    Rebuilt { p, nodes, records, bounds, entries }
}

fn write_rebuilt(blob: &mut Blob, r: &Rebuilt) {
    let ts = blob.s.tlas;
    for (slot, rec, blas) in &r.records {
        wr(blob.bytes, ts + blob.s.tlas_instances + *slot as u64 * INSTANCE_RECORD_SIZE as u64, rec);
        wr(blob.bytes, ts + blob.s.tlas_blas_table + *slot as u64 * 8, blas);
        let pr = if *blas == 0 { PrimRecord::zeroed() } else { PrimRecord { geometry: 0, primitive: *slot } };
        wr(blob.bytes, ts + blob.s.tlas_records + *slot as u64 * RECORD_SIZE as u64, &pr);
    }
    let mut rec = blob.partition(r.p);
    rec.active_count = r.entries.len() as u32;
    if r.p < blob.c.partitions {
        let base = blob.s.top_nodes + r.p as u64 * blob.s.partition_nodes;
        write_nodes(blob, base, blob.s.partition_nodes, &r.nodes);
        rec.node_count = r.nodes.len() as u32;
        rec.root = if r.nodes.is_empty() { NO_ROOT } else { base as u32 };
        rec.bounds = r.bounds.map_or([0.0; 6], |b| [b.lo[0], b.lo[1], b.lo[2], b.hi[0], b.hi[1], b.hi[2]]);
        rec.rebuilt_area = r.bounds.map_or(0.0, |b| b.half_area());
    }
    blob.set_partition(r.p, &rec);
}

/// A refit may grow a partition's box to this many times its half-area at the last rebuild;
/// past it the partition is rebuilt (a deterministic rule: it reads only stored state).
const REFIT_AREA_LIMIT: f32 = 1.5;

/// One refitted partition: the records of its changed slots, its rewritten nodes, its bounds.
struct Refitted {
    p: u32,
    records: Vec<(u32, InstanceRecord, u64)>,
    nodes: Vec<(u32, WideNode)>,
    bounds: Aabb,
}

/// Refits partition p, whose leaf set is unchanged, after the records of `changed` (sorted by
/// slot, each once) changed. None: the tree must be rebuilt instead (malformed nodes, or
/// the partition's box grew past REFIT_AREA_LIMIT).
fn refit(blob: &Blob, p: u32, changed: &[Changed], view: &dyn DeviceView) -> Option<Refitted> {
    let rec = blob.partition(p);
    if rec.root == NO_ROOT || p >= blob.c.partitions {
        return None;
    }
    let t = rec.translation;
    let mut memo = BlasBoundsMemo::new();
    let records: Vec<(u32, InstanceRecord, u64)> = changed
        .iter()
        .map(|&Changed { slot, .. }| {
            let (r, blas, _) = traversal_record(slot, &blob.stored(slot), t, &mut memo, view);
            (slot, r, blas)
        })
        .collect();
    let first = blob.s.top_nodes + p as u64 * blob.s.partition_nodes;
    let count = (rec.node_count as u64).min(blob.s.partition_nodes);
    let at = (blob.s.tlas + blob.s.tlas_nodes + first * NODE_SIZE as u64) as usize;
    let raw = &blob.bytes[at..at + count as usize * NODE_SIZE];
    let copied: Vec<WideNode>;
    let region: &[WideNode] = match bytemuck::try_cast_slice(raw) {
        Ok(r) => r,
        Err(_) => {
            copied = raw.chunks_exact(NODE_SIZE).map(bytemuck::pod_read_unaligned).collect();
            &copied
        }
    };
    let mut leaf_box = |slot: u32| {
        let st = blob.stored(slot);
        let (lo, hi) = leaf_bounds(&st, &translated(&st, t), t, &mut memo, view);
        Aabb { lo, hi }
    };
    let r = tree::refit(region, first as u32, changed, &mut leaf_box).ok()?;
    (r.bounds.half_area() <= REFIT_AREA_LIMIT * rec.rebuilt_area).then_some(Refitted { p, records, nodes: r.nodes, bounds: r.bounds })
}

fn write_refitted(blob: &mut Blob, r: &Refitted) {
    let ts = blob.s.tlas;
    for (slot, rec, blas) in &r.records {
        wr(blob.bytes, ts + blob.s.tlas_instances + *slot as u64 * INSTANCE_RECORD_SIZE as u64, rec);
        wr(blob.bytes, ts + blob.s.tlas_blas_table + *slot as u64 * 8, blas);
    }
    for (k, node) in &r.nodes {
        wr(blob.bytes, ts + blob.s.tlas_nodes + *k as u64 * NODE_SIZE as u64, node);
    }
    let mut rec = blob.partition(r.p);
    let b = r.bounds;
    rec.bounds = [b.lo[0], b.lo[1], b.lo[2], b.hi[0], b.hi[1], b.hi[2]];
    blob.set_partition(r.p, &rec);
}

/// A partition redone by this build.
enum Redone {
    Rebuilt(Rebuilt),
    Refitted(Refitted),
}

/// Redoes partition p: a refit when only records of its leaves changed and refits are allowed,
/// else a rebuild.
fn redo(blob: &Blob, p: u32, dirty: &Dirty, changed: &[Changed], may_refit: bool, view: &dyn DeviceView) -> Redone {
    if may_refit && !dirty.reshaped[p as usize] {
        if let Some(r) = refit(blob, p, changed, view) {
            return Redone::Refitted(r);
        }
    }
    Redone::Rebuilt(rebuild(blob, p, view))
}

/// Nodes at node index `first` of a region of `capacity`, the rest of the region zeroed.
fn write_nodes(blob: &mut Blob, first: u64, capacity: u64, nodes: &[WideNode]) {
    let at = (blob.s.tlas + blob.s.tlas_nodes + first * NODE_SIZE as u64) as usize;
    let bytes: &[u8] = bytemuck::cast_slice(nodes);
    blob.bytes[at..at + bytes.len()].copy_from_slice(bytes);
    let end = at + (capacity as usize) * NODE_SIZE;
    blob.bytes[at + bytes.len()..end].fill(0);
}

/// The top level over partition roots and global instances; returns its bounds.
fn build_top(blob: &mut Blob, global: &[Entry]) -> Option<Aabb> {
    let mut entries: Vec<Entry> = Vec::with_capacity(blob.c.partitions as usize + global.len());
    for p in 0..blob.c.partitions {
        let r = blob.partition(p);
        if r.root != NO_ROOT {
            let b = r.bounds;
            entries.push(Entry { lo: [b[0], b[1], b[2]], hi: [b[3], b[4], b[5]], child: r.root, kind: CHILD_INTERNAL });
        }
    }
    entries.extend_from_slice(global);
    let mut nodes = Vec::new();
    let bounds = tree::build(&mut entries, 0, &mut nodes);
    write_nodes(blob, 0, blob.s.top_nodes, &nodes);
    bounds
}

fn finish(blob: &mut Blob, bounds: Option<Aabb>, active: u32) {
    let s = blob.s;
    let n = blob.c.instances;
    let raw = RawHeader {
        magic: base::MAGIC,
        version: base::FORMAT_VERSION,
        ty: 0,
        flags: blob.h.build_flags,
        valid: base::valid_word(),
        geometry_count: 0,
        primitive_count: n,
        instance_count: n,
        node_count: (s.top_nodes + blob.c.partitions as u64 * s.partition_nodes) as u32,
        leaf_count: active,
        blas_reference_count: n,
        sah_cost: 0.0,
        bounds: bounds.map_or([0.0; 6], |b| [b.lo[0], b.lo[1], b.lo[2], b.hi[0], b.hi[1], b.hi[2]]),
        total_primitives: n,
        blas_table_capacity: n,
        used_size: s.tlas_size,
        nodes_offset: s.tlas_nodes,
        prims_offset: s.tlas_records,
        records_offset: s.tlas_records,
        geometries_offset: s.tlas_records,
        instances_offset: s.tlas_instances,
        blas_table_offset: s.tlas_blas_table,
        max_leaf_size: 1,
        reserved: 0,
        checksum: 0,
        spare: 0,
    };
    wr(blob.bytes, s.tlas, &raw);
    let h = blob.h;
    wr(blob.bytes, 0, &h);
}

pub fn build(input: &Input, ops: &Ops, view: &dyn DeviceView, source: Source, dst: &mut [u8], scratch: &mut [u8]) -> Result<BuildReport, PtlasError> {
    let c = Capacities::of(input);
    if (scratch.len() as u64) < scratch_size(&c) {
        return Err(PtlasError::ScratchTooSmall { needed: scratch_size(&c), got: scratch.len() as u64 });
    }
    let (mut blob, touched, relaid) = open(input, source, dst)?;
    let mut dirty = Dirty { reshaped: touched.clone(), touched, changed: Vec::new(), memo: BlasBoundsMemo::new() };
    let mut report = BuildReport { relaid, ..BuildReport::default() };
    apply_writes(&mut blob, input, ops, &mut dirty, view)?;
    apply_updates(&mut blob, input, ops, &mut dirty, &mut report.ignored_updates, view)?;
    apply_translations(&mut blob, input, ops, &mut dirty)?;
    // The global partition's instances are top-level entries: their boxes are needed every build.
    let global = blob.c.partitions;
    dirty.reshape(global);
    // A slot changed twice (written, then updated) keeps its first entry: the box in the tree.
    dirty.changed.sort_by_key(|&(p, c)| (p, c.slot));
    dirty.changed.dedup_by_key(|&mut (p, c)| (p, c.slot));
    // Slots changed per partition: a run of `changed` each (it is sorted by partition).
    let mut runs = vec![(0usize, 0usize); global as usize + 1];
    for (k, &(p, _)) in dirty.changed.iter().enumerate() {
        let r = &mut runs[p as usize];
        *r = if r.1 == 0 { (k, k + 1) } else { (r.0, k + 1) };
    }
    let slots: Vec<Changed> = dirty.changed.iter().map(|&(_, c)| c).collect();
    // PREFER_FAST_TRACE rebuilds every touched partition: bytes then depend on the state alone.
    let may_refit = input.flags & crate::accel::BuildFlags::PREFER_FAST_TRACE == 0;
    let list: Vec<u32> = (0..=global).filter(|&p| dirty.touched[p as usize]).collect();
    let redone: Vec<Redone> = {
        let (b, d) = (&blob, &dirty);
        list.par_iter().map(|&p| redo(b, p, d, &slots[runs[p as usize].0..runs[p as usize].1], may_refit, view)).collect()
    };
    let mut global_entries = Vec::new();
    for r in &redone {
        match r {
            Redone::Rebuilt(r) => {
                write_rebuilt(&mut blob, r);
                report.rebuilt_partitions += 1;
                if r.p == global {
                    global_entries = r.entries.clone();
                }
            }
            Redone::Refitted(r) => {
                write_refitted(&mut blob, r);
                report.refitted_partitions += 1;
            }
        }
    }
    let bounds = build_top(&mut blob, &global_entries);
    let active: u32 = (0..=global).map(|p| blob.partition(p).active_count).sum();
    finish(&mut blob, bounds, active);
    report.used_size = blob.s.end;
    report.active_instances = active;
    Ok(report)
}

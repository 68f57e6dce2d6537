//! PTLAS builds against a KHR TLAS of the equivalent instance list (translations applied,
//! disabled instances inactive), and incremental builds against from-scratch builds of the
//! final state, in traversal and in bytes.
use glam::Vec3;

use super::*;
use crate::accel::tests::{build_ok, tri_geom, Rng};
use crate::accel::{all_hits, closest_hit, AsType, Geometry, GeometryData, GeometryFlags, MapView, Ray, RayFlags};

const BLAS_A: u64 = 0x10_0000;
const BLAS_B: u64 = 0x20_0000;

/// Two BLASes: a few random triangles, and AABBs; both inserted in a view.
fn blases(rng: &mut Rng) -> MapView {
    let verts: Vec<Vec3> = (0..24).map(|_| rng.v3(1.0)).collect();
    let vb: Vec<u8> = verts.iter().flat_map(|v| v.to_array()).flat_map(|x| x.to_le_bytes()).collect();
    let a = build_ok(AsType::BottomLevel, 0, &[tri_geom(&vb, 24, &[], 8, 1)], &crate::accel::NoDevice);
    let boxes: Vec<u8> = (0..4)
        .flat_map(|_| {
            let c = rng.v3(1.0);
            [c.x - 0.2, c.y - 0.2, c.z - 0.2, c.x + 0.2, c.y + 0.2, c.z + 0.2]
        })
        .flat_map(|x| x.to_le_bytes())
        .collect();
    let g = Geometry { flags: GeometryFlags(0), primitive_count: 4, data: GeometryData::Aabbs { data: &boxes, stride: 24 } };
    let b = build_ok(AsType::BottomLevel, 0, &[g], &crate::accel::NoDevice);
    let mut view = MapView::new();
    view.insert(BLAS_A, a);
    view.insert(BLAS_B, b);
    view
}

fn random_write(rng: &mut Rng, index: u32, partitions: u32) -> WriteInstance {
    let t = rng.v3(6.0);
    let s = rng.range(0.5, 1.5);
    let blas = match rng.next_u32() % 8 {
        0 => 0,
        1..=2 => BLAS_B,
        _ => BLAS_A,
    };
    let partition = if rng.next_u32().is_multiple_of(6) { PARTITION_INDEX_GLOBAL } else { rng.next_u32() % partitions };
    let mut flags = rng.next_u32() % 16;
    let mut aabb = [0.0; 6];
    if rng.next_u32().is_multiple_of(3) {
        // A generous explicit box around the instance (every BLAS lies within [-1.5, 1.5]^3 scaled).
        flags |= INSTANCE_FLAG_EXPLICIT_BOUNDING_BOX;
        aabb = [t.x - 3.0 * s, t.y - 3.0 * s, t.z - 3.0 * s, t.x + 3.0 * s, t.y + 3.0 * s, t.z + 3.0 * s];
    }
    WriteInstance {
        transform: [s, 0.0, 0.0, t.x, 0.0, s, 0.0, t.y, 0.0, 0.0, s, t.z],
        explicit_aabb: aabb,
        instance_id: rng.next_u32() & 0xff_ffff,
        instance_mask: 1 << (rng.next_u32() % 8),
        instance_contribution_to_hit_group_index: rng.next_u32() & 0xffff,
        instance_flags: flags,
        instance_index: index,
        partition_index: partition,
        acceleration_structure: blas,
    }
}

/// The model: per slot, the last write (with updates applied), and translations by partition.
#[derive(Clone, Default)]
struct Model {
    slots: Vec<Option<WriteInstance>>,
    translations: std::collections::BTreeMap<u32, [f32; 3]>,
}

impl Model {
    /// The KHR TLAS built from the equivalent instance list.
    fn khr_tlas(&self, view: &MapView) -> Vec<u8> {
        let mut bytes = Vec::new();
        for s in &self.slots {
            let (mut m, custom, mask, sbt, flags, r) = match s {
                Some(w) => (w.transform, w.instance_id, w.instance_mask, w.instance_contribution_to_hit_group_index, w.instance_flags & 0xf, w.acceleration_structure),
                None => ([0.0; 12], 0, 0, 0, 0, 0),
            };
            if let Some(w) = s {
                let t = self.translations.get(&w.partition_index).copied().unwrap_or([0.0; 3]);
                m[3] += t[0];
                m[7] += t[1];
                m[11] += t[2];
            }
            m.iter().for_each(|x| bytes.extend(x.to_le_bytes()));
            bytes.extend((custom & 0xff_ffff | mask << 24).to_le_bytes());
            bytes.extend((sbt & 0xff_ffff | flags << 24).to_le_bytes());
            bytes.extend(r.to_le_bytes());
        }
        let n = self.slots.len() as u32;
        let g = Geometry { flags: GeometryFlags(0), primitive_count: n, data: GeometryData::Instances { array_of_pointers: false, data: &bytes } };
        build_ok(AsType::TopLevel, 0, &[g], view)
    }
    /// Writes of every slot ever written, with its final record, and every translation.
    fn final_ops(&self) -> (Vec<WriteInstance>, Vec<WriteTranslation>) {
        let writes = self.slots.iter().flatten().copied().collect();
        let translations = self.translations.iter().map(|(&p, &t)| WriteTranslation { partition_index: p, partition_translation: t }).collect();
        (writes, translations)
    }
}

fn ops<'a>(w: &'a [WriteInstance], u: &'a [UpdateInstance], t: &'a [WriteTranslation]) -> Ops<'a> {
    Ops {
        writes: Strided { data: bytemuck::cast_slice(w), count: w.len() as u32, stride: WRITE_INSTANCE_SIZE as u64 },
        updates: Strided { data: bytemuck::cast_slice(u), count: u.len() as u32, stride: 0 },
        translations: Strided { data: bytemuck::cast_slice(t), count: t.len() as u32, stride: 16 },
    }
}

/// PREFER_FAST_TRACE: every touched partition rebuilt, never refitted.
const FAST_TRACE: u32 = crate::accel::BuildFlags::PREFER_FAST_TRACE;

fn input(n: u32, per: u32, partitions: u32, global: u32) -> Input {
    Input { flags: FAST_TRACE, instance_count: n, max_instance_per_partition_count: per, partition_count: partitions, max_instance_in_global_partition_count: global, translation: true }
}

fn build_from(inp: &Input, o: &Ops, view: &MapView, source: Source, dst: &mut [u8]) -> BuildReport {
    let sizes = build_sizes(inp);
    let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
    build(inp, o, view, source, dst, &mut scratch).unwrap()
}

/// Every hit of both structures along random rays, as sorted sets, and the closest hit distance.
fn assert_same_traversal(ptlas: &[u8], khr: &[u8], view: &MapView, rng: &mut Rng, rays: u32) {
    for _ in 0..rays {
        let origin = rng.v3(10.0);
        let target = rng.v3(6.0);
        let ray = Ray { origin, direction: (target - origin).normalize(), tmin: 0.0, tmax: 100.0 };
        let flags = RayFlags([0, RayFlags::CULL_BACK_FACING_TRIANGLES, RayFlags::OPAQUE, RayFlags::CULL_OPAQUE][rng.next_u32() as usize % 4]);
        let mask = (rng.next_u32() & 0xff) as u8 | 1;
        let key = |h: &crate::accel::Hit| (h.instance_index, h.geometry_index, h.primitive_index, h.t.to_bits(), h.sbt_record_offset, h.instance_custom_index, h.front_face);
        let mut a: Vec<_> = all_hits(ptlas, view, ray, flags, mask).iter().map(key).collect();
        let mut b: Vec<_> = all_hits(khr, view, ray, flags, mask).iter().map(key).collect();
        a.sort_unstable();
        b.sort_unstable();
        assert_eq!(a, b, "ray {ray:?}");
        let ta = closest_hit(ptlas, view, ray, flags, mask).map(|h| h.t);
        let tb = closest_hit(khr, view, ray, flags, mask).map(|h| h.t);
        assert_eq!(ta, tb);
    }
}

#[test]
fn from_scratch_traverses_like_the_khr_tlas() {
    for seed in 1..=4u64 {
        let mut rng = Rng::new(seed);
        let view = blases(&mut rng);
        let (n, partitions) = (60 + seed as u32 * 20, 1 + seed as u32 * 3);
        let inp = input(n, n, partitions, n);
        let mut model = Model { slots: vec![None; n as usize], ..Model::default() };
        let mut writes = Vec::new();
        for i in 0..n {
            // Some slots are never written: disabled instances.
            if !rng.next_u32().is_multiple_of(5) {
                let w = random_write(&mut rng, i, partitions);
                model.slots[i as usize] = Some(w);
                writes.push(w);
            }
        }
        let translations: Vec<WriteTranslation> = [0, PARTITION_INDEX_GLOBAL].iter().map(|&p| WriteTranslation { partition_index: p, partition_translation: rng.v3(2.0).to_array() }).collect();
        for t in &translations {
            model.translations.insert(t.partition_index, t.partition_translation);
        }
        let mut dst = vec![0u8; build_sizes(&inp).acceleration_structure_size as usize];
        let report = build_from(&inp, &ops(&writes, &[], &translations), &view, Source::Empty, &mut dst);
        assert_eq!(report.used_size, dst.len() as u64);
        assert!(crate::accel::header(&dst).is_some());
        assert_same_traversal(&dst, &model.khr_tlas(&view), &view, &mut rng, 300);
    }
}

/// One random round of ops, applied to the model too.
fn random_round(rng: &mut Rng, model: &mut Model, partitions: u32) -> (Vec<WriteInstance>, Vec<UpdateInstance>, Vec<WriteTranslation>) {
    let n = model.slots.len() as u32;
    let mut touched = std::collections::BTreeSet::new();
    let mut writes = Vec::new();
    for _ in 0..(rng.next_u32() % 12) {
        let i = rng.next_u32() % n;
        if touched.insert(i) {
            let w = random_write(rng, i, partitions);
            model.slots[i as usize] = Some(w);
            writes.push(w);
        }
    }
    let mut updates = Vec::new();
    for _ in 0..(rng.next_u32() % 6) {
        let i = rng.next_u32() % n;
        if !touched.insert(i) {
            continue;
        }
        // Disable, reactivate or swap the BLAS; the SBT offset changes too.
        let blas = [0, BLAS_A, BLAS_B][rng.next_u32() as usize % 3];
        let u = UpdateInstance { instance_index: i, instance_contribution_to_hit_group_index: rng.next_u32() & 0xfff, acceleration_structure: blas };
        if let Some(w) = model.slots[i as usize].as_mut() {
            w.acceleration_structure = blas;
            w.instance_contribution_to_hit_group_index = u.instance_contribution_to_hit_group_index;
        }
        updates.push(u);
    }
    let mut translations = Vec::new();
    if rng.next_u32().is_multiple_of(3) {
        let p = if rng.next_u32().is_multiple_of(4) { PARTITION_INDEX_GLOBAL } else { rng.next_u32() % partitions };
        let t = WriteTranslation { partition_index: p, partition_translation: rng.v3(2.0).to_array() };
        model.translations.insert(p, t.partition_translation);
        translations.push(t);
    }
    (writes, updates, translations)
}

#[test]
fn incremental_builds_equal_a_from_scratch_build_of_the_final_state() {
    for seed in 10..14u64 {
        let mut rng = Rng::new(seed);
        let view = blases(&mut rng);
        let (n, partitions) = (80u32, 5u32);
        let inp = input(n, n, partitions, n);
        let size = build_sizes(&inp).acceleration_structure_size as usize;
        let mut model = Model { slots: vec![None; n as usize], ..Model::default() };
        let (mut in_place, mut ping, mut pong) = (vec![0u8; size], vec![0u8; size], vec![0u8; size]);
        let first = random_round(&mut rng, &mut model, partitions);
        let o = ops(&first.0, &first.1, &first.2);
        build_from(&inp, &o, &view, Source::Empty, &mut in_place);
        build_from(&inp, &o, &view, Source::Empty, &mut ping);
        for round in 0..30u32 {
            let (w, u, t) = random_round(&mut rng, &mut model, partitions);
            let o = ops(&w, &u, &t);
            build_from(&inp, &o, &view, Source::InPlace, &mut in_place);
            // Ping-pong: src → dst, then the roles swap.
            if round.is_multiple_of(2) {
                build_from(&inp, &o, &view, Source::Other(&ping), &mut pong);
            } else {
                build_from(&inp, &o, &view, Source::Other(&pong), &mut ping);
            }
        }
        let last = &ping; // round 29 (odd) wrote ping
        let (w, t) = model.final_ops();
        let mut scratch_built = vec![0u8; size];
        build_from(&inp, &ops(&w, &[], &t), &view, Source::Empty, &mut scratch_built);
        assert!(in_place == scratch_built, "in-place sequence differs in bytes from the from-scratch build");
        assert!(*last == scratch_built, "ping-pong sequence differs in bytes from the from-scratch build");
        assert_same_traversal(&in_place, &model.khr_tlas(&view), &view, &mut rng, 200);
    }
}

#[test]
fn only_dirty_partitions_are_rebuilt() {
    let mut rng = Rng::new(99);
    let view = blases(&mut rng);
    let inp = input(64, 64, 8, 0);
    let writes: Vec<WriteInstance> = (0..64).map(|i| WriteInstance { partition_index: i % 8, ..random_write(&mut rng, i, 8) }).collect();
    let mut dst = vec![0u8; build_sizes(&inp).acceleration_structure_size as usize];
    build_from(&inp, &ops(&writes, &[], &[]), &view, Source::Empty, &mut dst);
    let one = [WriteInstance { partition_index: 3, ..random_write(&mut rng, 11, 8) }];
    // Slot 11 rewritten in its own partition (3): that partition plus the (empty) global one.
    let r = build_from(&inp, &ops(&one, &[], &[]), &view, Source::InPlace, &mut dst);
    assert_eq!(r.rebuilt_partitions, 2);
    assert_eq!(r.refitted_partitions, 0, "PREFER_FAST_TRACE never refits");
    let moved = [WriteInstance { partition_index: 5, ..random_write(&mut rng, 11, 8) }];
    let r = build_from(&inp, &ops(&moved, &[], &[]), &view, Source::InPlace, &mut dst);
    assert_eq!(r.rebuilt_partitions, 3);
}

#[test]
fn sizes_errors_and_growth() {
    let inp = input(10, 4, 3, 2);
    let s = build_sizes(&inp);
    assert!(s.build_scratch_size > 0 && s.update_scratch_size > 0);
    let empty = build_sizes(&input(0, 0, 0, 0));
    assert!(empty.acceleration_structure_size > 0 && empty.build_scratch_size > 0);
    // Larger counts never need less memory.
    assert!(build_sizes(&input(11, 4, 3, 2)).acceleration_structure_size > s.acceleration_structure_size);
    assert!(build_sizes(&Input { translation: false, ..inp }).acceleration_structure_size <= s.acceleration_structure_size);
    let view = MapView::new();
    let mut scratch = vec![0u8; s.build_scratch_size as usize];
    let mut small = vec![0u8; s.acceleration_structure_size as usize - 1];
    assert!(matches!(build(&inp, &Ops::default(), &view, Source::Empty, &mut small, &mut scratch), Err(PtlasError::DestinationTooSmall { .. })));
    let mut dst = vec![0u8; s.acceleration_structure_size as usize];
    let w = |i: u32, p: u32| WriteInstance { instance_index: i, partition_index: p, acceleration_structure: 0, ..bytemuck::Zeroable::zeroed() };
    let bad = [w(10, 0)];
    assert!(matches!(build(&inp, &ops(&bad, &[], &[]), &view, Source::Empty, &mut dst, &mut scratch), Err(PtlasError::InstanceIndex { index: 10, .. })));
    assert!(traversable(&dst).is_none(), "a failed build leaves dst invalid");
    let full = [w(0, 1), w(1, 1), w(2, 1), w(3, 1), w(4, 1)];
    assert!(matches!(build(&inp, &ops(&full, &[], &[]), &view, Source::Empty, &mut dst, &mut scratch), Err(PtlasError::PartitionFull { partition: 1, .. })));
    let no_t = Input { translation: false, ..inp };
    let t = [WriteTranslation { partition_index: 0, partition_translation: [1.0; 3] }];
    let mut dst2 = vec![0u8; build_sizes(&no_t).acceleration_structure_size as usize];
    assert!(matches!(build(&no_t, &ops(&[], &[], &t), &view, Source::Empty, &mut dst2, &mut scratch), Err(PtlasError::TranslationNotEnabled { .. })));
    assert!(matches!(build(&inp, &Ops::default(), &view, Source::InPlace, &mut dst, &mut scratch), Err(PtlasError::InvalidSource)));
    // A source laid out for fewer instances grows into a larger destination, keeping its state.
    let ok = [WriteInstance { transform: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0], acceleration_structure: BLAS_A, ..w(3, 0) }];
    build(&inp, &ops(&ok, &[], &[]), &view, Source::Empty, &mut dst, &mut scratch).unwrap();
    let big = input(20, 8, 3, 2);
    let mut grown = vec![0u8; build_sizes(&big).acceleration_structure_size as usize];
    let r = build(&big, &Ops::default(), &view, Source::Other(&dst), &mut grown, &mut scratch).unwrap();
    assert!(r.relaid);
    assert_eq!(header(&grown).unwrap().instance_capacity, 20);
    assert_eq!(r.active_instances, 1);
}

/// A refit round: `count` distinct slots rewritten in their own partition with a moved
/// transform (some with the other BLAS, some through UPDATE_INSTANCE); with `reshape`, one slot
/// also moves partition or is disabled, so that partition is rebuilt while others refit.
fn refit_round(rng: &mut Rng, model: &mut Model, count: u32, reshape: bool, partitions: u32) -> (Vec<WriteInstance>, Vec<UpdateInstance>) {
    let n = model.slots.len() as u32;
    let mut touched = std::collections::BTreeSet::new();
    let (mut writes, mut updates) = (Vec::new(), Vec::new());
    for _ in 0..count {
        let i = rng.next_u32() % n;
        let Some(old) = model.slots[i as usize] else { continue };
        if !touched.insert(i) {
            continue;
        }
        if rng.next_u32().is_multiple_of(4) {
            let blas = if old.acceleration_structure == BLAS_A { BLAS_B } else { BLAS_A };
            let u = UpdateInstance { instance_index: i, instance_contribution_to_hit_group_index: rng.next_u32() & 0xfff, acceleration_structure: if old.acceleration_structure == 0 { 0 } else { blas } };
            let w = model.slots[i as usize].as_mut().unwrap();
            w.acceleration_structure = u.acceleration_structure;
            w.instance_contribution_to_hit_group_index = u.instance_contribution_to_hit_group_index;
            updates.push(u);
            continue;
        }
        let mut w = old;
        let d = rng.v3(0.4);
        w.transform[3] += d.x;
        w.transform[7] += d.y;
        w.transform[11] += d.z;
        for k in 0..3 {
            w.explicit_aabb[k] += d[k];
            w.explicit_aabb[k + 3] += d[k];
        }
        model.slots[i as usize] = Some(w);
        writes.push(w);
    }
    if reshape {
        let i = rng.next_u32() % n;
        if touched.insert(i) {
            let w = random_write(rng, i, partitions);
            model.slots[i as usize] = Some(w);
            writes.push(w);
        }
    }
    (writes, updates)
}

/// Initial state for the refit tests: every slot written, most in partitions.
fn refit_start(rng: &mut Rng, n: u32, partitions: u32) -> (Model, Vec<WriteInstance>) {
    let mut model = Model { slots: vec![None; n as usize], ..Model::default() };
    let writes: Vec<WriteInstance> = (0..n).map(|i| random_write(rng, i, partitions)).collect();
    for w in &writes {
        model.slots[w.instance_index as usize] = Some(*w);
    }
    (model, writes)
}

/// Runs the refit sequence of `seed` in place and ping-ponged (flags 0: refits allowed) and
/// returns both final blobs, the model, the view and the refit and rebuild counts.
fn refit_sequence(seed: u64, rounds: u32) -> (Vec<u8>, Vec<u8>, Model, MapView, u32, u32) {
    let mut rng = Rng::new(seed);
    let view = blases(&mut rng);
    let (n, partitions) = (200u32, 6u32);
    let inp = Input { flags: 0, ..input(n, n, partitions, n) };
    let size = build_sizes(&inp).acceleration_structure_size as usize;
    let (mut model, first) = refit_start(&mut rng, n, partitions);
    let (mut in_place, mut ping, mut pong) = (vec![0u8; size], vec![0u8; size], vec![0u8; size]);
    build_from(&inp, &ops(&first, &[], &[]), &view, Source::Empty, &mut in_place);
    build_from(&inp, &ops(&first, &[], &[]), &view, Source::Empty, &mut ping);
    let (mut refitted, mut rebuilt) = (0, 0);
    for round in 0..rounds {
        let (w, u) = refit_round(&mut rng, &mut model, 30, round % 5 == 4, partitions);
        let o = ops(&w, &u, &[]);
        let r = build_from(&inp, &o, &view, Source::InPlace, &mut in_place);
        refitted += r.refitted_partitions;
        rebuilt += r.rebuilt_partitions;
        let r2 = if round.is_multiple_of(2) { build_from(&inp, &o, &view, Source::Other(&ping), &mut pong) } else { build_from(&inp, &o, &view, Source::Other(&pong), &mut ping) };
        assert_eq!(r, r2);
    }
    let last = if rounds % 2 == 1 { pong } else { ping };
    (in_place, last, model, view, refitted, rebuilt)
}

#[test]
fn refit_sequences_trace_like_from_scratch_builds_and_a_khr_tlas() {
    for seed in 30..33u64 {
        let (in_place, ping_pong, model, view, refitted, rebuilt) = refit_sequence(seed, 20);
        assert!(refitted > 20, "the sequence refits partitions ({refitted} refitted, {rebuilt} rebuilt)");
        // The same algorithm on the same state: in place and ping-pong agree byte for byte.
        assert!(in_place == ping_pong, "in-place and ping-pong refit sequences differ in bytes");
        let inp = input(200, 200, 6, 200);
        let (w, t) = model.final_ops();
        let mut scratch_built = vec![0u8; in_place.len()];
        build_from(&Input { flags: 0, ..inp }, &ops(&w, &[], &t), &view, Source::Empty, &mut scratch_built);
        // Refit trees differ from rebuilt ones byte-wise; traversal is the same.
        assert!(in_place != scratch_built, "a refit tree is expected to differ from a rebuilt one in bytes");
        let mut rng = Rng::new(seed + 100);
        assert_same_traversal(&in_place, &scratch_built, &view, &mut rng, 300);
        assert_same_traversal(&in_place, &model.khr_tlas(&view), &view, &mut rng, 300);
    }
}

#[test]
fn refit_sequences_are_the_same_bytes_at_every_thread_count() {
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| refit_sequence(40, 12).0)
    };
    let one = run(1);
    assert!(run(2) == one, "2 threads differ from 1");
    assert!(run(4) == one, "4 threads differ from 1");
}

#[test]
fn a_partition_whose_box_grows_past_the_bound_is_rebuilt() {
    let mut rng = Rng::new(50);
    let view = blases(&mut rng);
    let inp = Input { flags: 0, ..input(64, 64, 2, 0) };
    let mut writes: Vec<WriteInstance> = (0..64).map(|i| WriteInstance { partition_index: i % 2, ..random_write(&mut rng, i, 2) }).collect();
    for w in &mut writes {
        w.acceleration_structure = BLAS_A;
    }
    let mut dst = vec![0u8; build_sizes(&inp).acceleration_structure_size as usize];
    build_from(&inp, &ops(&writes, &[], &[]), &view, Source::Empty, &mut dst);
    let mut small = writes[2];
    small.transform[3] += 0.01;
    let r = build_from(&inp, &ops(&[small], &[], &[]), &view, Source::InPlace, &mut dst);
    assert_eq!((r.refitted_partitions, r.rebuilt_partitions), (1, 1), "a small move refits (the global partition is rebuilt)");
    let mut far = writes[4];
    far.transform[3] += 100.0;
    let r = build_from(&inp, &ops(&[far], &[], &[]), &view, Source::InPlace, &mut dst);
    assert_eq!((r.refitted_partitions, r.rebuilt_partitions), (0, 2), "a move that grows the partition box past the bound rebuilds");
    let mut model = Model { slots: writes.iter().map(|w| Some(*w)).collect(), ..Model::default() };
    model.slots[2] = Some(small);
    model.slots[4] = Some(far);
    let mut rng = Rng::new(51);
    assert_same_traversal(&dst, &model.khr_tlas(&view), &view, &mut rng, 300);
}

/// Every leaf box lies inside the decoded child boxes of all its ancestors (`path`: those above
/// node k), walked from `base`: what conservative traversal needs.
fn assert_leaves_contained(nodes: &[crate::accel::layout::WideNode], base: u32, k: usize, path: &mut Vec<[f32; 6]>, boxes: &std::collections::HashMap<u32, crate::accel::geometry::Aabb>) {
    let n = nodes[k];
    for c in 0..n.child_count as usize {
        path.push(n.child_box(c));
        if n.kind[c] == crate::accel::layout::CHILD_INTERNAL {
            assert_leaves_contained(nodes, base, (n.child[c] - base) as usize, path, boxes);
        } else {
            let l = boxes[&n.child[c]];
            for b in path.iter() {
                assert!((0..3).all(|a| b[a] <= l.lo[a] && l.hi[a] <= b[a + 3]), "leaf {} outside an ancestor's box", n.child[c]);
            }
        }
        path.pop();
    }
}

#[test]
fn tree_refit_finds_leaves_by_their_previous_box_or_by_scanning_alike() {
    use super::tree::{self, Changed, Entry};
    use crate::accel::geometry::Aabb;
    let mut rng = Rng::new(60);
    let base = 7u32;
    let mut boxes = std::collections::HashMap::new();
    let mut entries: Vec<Entry> = (0..300u32)
        .map(|slot| {
            let c = rng.v3(20.0);
            let e = rng.range(0.1, 2.0);
            let (lo, hi) = ((c - e).to_array(), (c + e).to_array());
            boxes.insert(slot, Aabb { lo, hi });
            Entry { lo, hi, child: slot, kind: 1 }
        })
        .collect();
    let mut nodes = Vec::new();
    tree::build(&mut entries, base, &mut nodes);
    for round in 0..20 {
        let mut slots: Vec<u32> = (0..12).map(|_| rng.next_u32() % 300).collect();
        slots.sort_unstable();
        slots.dedup();
        let previous: Vec<Changed> = slots.iter().map(|&slot| Changed { slot, previous: Some(boxes[&slot]) }).collect();
        // A previous box no node contains: the search misses and the refit scans.
        let wrong: Vec<Changed> = slots.iter().map(|&slot| Changed { slot, previous: Some(Aabb { lo: [1e6; 3], hi: [1e6 + 1.0; 3] }) }).collect();
        for &slot in &slots {
            let d = rng.v3(1.5);
            let b = boxes.get_mut(&slot).unwrap();
            b.lo = (glam::Vec3::from(b.lo) + d).to_array();
            b.hi = (glam::Vec3::from(b.hi) + d).to_array();
        }
        let mut leaf = |slot: u32| boxes[&slot];
        let by_search = tree::refit(&nodes, base, &previous, &mut leaf).unwrap();
        let by_scan = tree::refit(&nodes, base, &wrong, &mut leaf).unwrap();
        assert_eq!(by_search.nodes, by_scan.nodes, "round {round}");
        assert_eq!(by_search.bounds, by_scan.bounds);
        assert!(!by_search.nodes.is_empty() && by_search.nodes[0].0 == base, "the root is on every path");
        for (k, node) in by_search.nodes {
            nodes[(k - base) as usize] = node;
        }
        let b = by_search.bounds;
        assert_leaves_contained(&nodes, base, 0, &mut vec![[b.lo[0], b.lo[1], b.lo[2], b.hi[0], b.hi[1], b.hi[2]]], &boxes);
    }
}

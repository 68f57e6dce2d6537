//! The plain closest/any-hit loop against the resumable query with every candidate confirmed
//! (its definition): the same hit, bit for bit, over triangles (uniform and mixed geometry
//! flags), AABBs, instances with every flag, masks, ray flags, and corrupted structures; and a
//! query restarted from ray to ray against a fresh one.
use super::*;
use crate::accel::tests::{build_ok, f32_bytes, tri_geom, Rng};
use crate::accel::{AsType, BuildFlags, Geometry, GeometryData, GeometryFlags, MapView, NoDevice};

/// Every field, floats by their bits.
fn key(h: &Option<Hit>) -> Option<Vec<u32>> {
    h.as_ref().map(|h| {
        let mut w = vec![h.t.to_bits(), h.barycentrics[0].to_bits(), h.barycentrics[1].to_bits(), h.front_face as u32, h.opaque as u32, h.kind as u32];
        w.extend([h.instance_index, h.instance_custom_index, h.sbt_record_offset, h.geometry_index, h.primitive_index]);
        w.extend(h.object_ray_origin.to_array().iter().chain(&h.object_ray_direction.to_array()).map(|x| x.to_bits()));
        w.extend(h.object_to_world.iter().chain(&h.world_to_object).map(|x| x.to_bits()));
        w.extend(h.vertices.iter().flat_map(|v| v.to_array()).map(f32::to_bits));
        w
    })
}

fn soup(rng: &mut Rng, n: usize, scale: f32, size: f32) -> Vec<Vec3> {
    (0..n)
        .flat_map(|_| {
            let c = rng.v3(scale);
            [c + rng.v3(size), c + rng.v3(size), c + rng.v3(size)]
        })
        .collect()
}

fn instance(transform: [f32; 12], custom: u32, mask: u8, sbt: u32, flags: u8, reference: u64) -> Vec<u8> {
    let mut b: Vec<u8> = transform.iter().flat_map(|x| x.to_le_bytes()).collect();
    b.extend((custom | (mask as u32) << 24).to_le_bytes());
    b.extend((sbt | (flags as u32) << 24).to_le_bytes());
    b.extend(reference.to_le_bytes());
    b
}

/// Structures of every kind: uniform opaque triangles, two triangle geometries with different
/// flags, non-opaque AABBs, and a TLAS over them (plus an unresolved reference).
fn scene() -> (Vec<Vec<u8>>, MapView) {
    let mut rng = Rng::new(27);
    let v1 = f32_bytes(&soup(&mut rng, 600, 4.0, 0.8));
    let v2 = f32_bytes(&soup(&mut rng, 300, 4.0, 0.8));
    let v3 = f32_bytes(&soup(&mut rng, 300, 4.0, 0.8));
    let uniform = build_ok(AsType::BottomLevel, BuildFlags::PREFER_FAST_TRACE, &[tri_geom(&v1, 1800, &[], 600, 1)], &NoDevice);
    let mixed = build_ok(AsType::BottomLevel, 0, &[tri_geom(&v2, 900, &[], 300, 1), tri_geom(&v3, 900, &[], 300, 0)], &NoDevice);
    let boxes: Vec<u8> = (0..200)
        .flat_map(|_| {
            let (c, e) = (rng.v3(4.0), rng.v3(0.5).abs());
            [c - e, c + e]
        })
        .flat_map(|v| v.to_array())
        .flat_map(|x| x.to_le_bytes())
        .collect();
    let aabbs = build_ok(AsType::BottomLevel, 0, &[Geometry { flags: GeometryFlags(0), primitive_count: 200, data: GeometryData::Aabbs { data: &boxes, stride: 24 } }], &NoDevice);
    let mut view = MapView::new();
    view.insert(0x1000_0000, uniform.clone());
    view.insert(0x2000_0000, mixed.clone());
    view.insert(0x3000_0000, aabbs.clone());
    let rot = [0.0, -1.0, 0.0, 1.0, 1.0, 0.0, 0.0, -2.0, 0.0, 0.0, 2.0, 0.5];
    let mut inst = Vec::new();
    for (k, (reference, flags)) in [(0x1000_0000u64, 0u8), (0x2000_0000, 2), (0x3000_0000, 0), (0x1000_0000, 1 | 8), (0x2000_0000, 4), (0x0bad_0000, 0)].into_iter().enumerate() {
        let mut t = if k % 2 == 1 { rot } else { [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0] };
        t[3] += k as f32 * 1.5;
        inst.extend(instance(t, 10 + k as u32, 1 << k, k as u32, flags, reference));
    }
    let g = Geometry { flags: GeometryFlags(0), primitive_count: 6, data: GeometryData::Instances { array_of_pointers: false, data: &inst } };
    let tlas = build_ok(AsType::TopLevel, 0, &[g], &view);
    (vec![uniform, mixed, aabbs, tlas], view)
}

const FLAGS: [u32; 12] = [0, 1, 2, 0x10, 0x20, 0x40, 0x80, 0x100, 0x200, 0x2 | 0x10, 0x1 | 0x20, 0x100 | 0x80];

fn rays(rng: &mut Rng, n: usize) -> Vec<Ray> {
    (0..n)
        .map(|i| {
            let o = rng.v3(7.0);
            let d = rng.v3(4.0) - o;
            let (tmin, tmax) = match i % 5 {
                0 => (0.0, rng.range(0.1, 1.0)),
                1 => (rng.range(0.0, 0.5), f32::INFINITY),
                _ => (0.0, f32::INFINITY),
            };
            Ray { origin: o, direction: d, tmin, tmax }
        })
        .collect()
}

/// Compares both paths for every ray, ray flag (with and without TERMINATE_ON_FIRST_HIT)
/// and cull mask; returns how many rays hit.
fn compare(s: &[u8], view: &dyn DeviceView, rays: &[Ray]) -> usize {
    let mut hits = 0;
    for &f in &FLAGS {
        for mask in [0xff, 0x05, 0x3a] {
            for r in rays {
                let fast = closest_hit(s, view, *r, RayFlags(f), mask);
                let slow = run(RayQuery::new(s, view, *r, RayFlags(f), mask));
                assert_eq!(key(&fast), key(&slow), "closest, flags {f:#x}, mask {mask:#x}, {r:?}");
                hits += fast.is_some() as usize;
                let fast = any_hit(s, view, *r, RayFlags(f), mask);
                let slow = run(RayQuery::new(s, view, *r, RayFlags(f | RayFlags::TERMINATE_ON_FIRST_HIT), mask));
                assert_eq!(key(&fast), key(&slow), "any, flags {f:#x}, mask {mask:#x}, {r:?}");
            }
        }
    }
    hits
}

#[test]
fn plain_loop_matches_ray_query() {
    let (structures, view) = scene();
    let rays = rays(&mut Rng::new(5), 300);
    for (i, s) in structures.iter().enumerate() {
        let hits = compare(s, &view, &rays);
        assert!(hits > rays.len(), "structure {i}: {hits} hits");
    }
}

#[test]
fn plain_loop_matches_ray_query_on_corrupt_structures() {
    let (structures, view) = scene();
    let rays = rays(&mut Rng::new(9), 40);
    let mut rng = Rng::new(11);
    for s in &structures {
        let used = crate::accel::header(s).unwrap().used_size as usize;
        for _ in 0..25 {
            let mut c = s.clone();
            // Flip bytes past the header (nodes, primitives, records, instances).
            for _ in 0..8 {
                let at = 160 + rng.next_u32() as usize % (used - 160);
                c[at] ^= 1 << (rng.next_u32() % 8);
            }
            compare(&c, &view, &rays);
        }
    }
}

/// Every candidate (each confirmed) and the committed hit and unresolved reference of a query.
fn trail(q: &mut RayQuery<'_>) -> Vec<Option<Vec<u32>>> {
    let mut out = Vec::new();
    while let Some(c) = q.proceed() {
        out.push(key(&Some(c)));
        match c.kind {
            HitKind::Triangle => q.confirm(),
            HitKind::Aabb => q.generate_intersection(c.t),
        }
    }
    out.push(key(&q.committed()));
    out.push(q.unresolved_reference().map(|a| vec![a as u32, (a >> 32) as u32]));
    out
}

#[test]
fn restarted_query_matches_a_fresh_one() {
    let (structures, view) = scene();
    let rays = rays(&mut Rng::new(13), 60);
    let empty = MapView::new();
    let mut rng = Rng::new(17);
    let mut q = RayQuery::new(&structures[3], &view, rays[0], RayFlags(0), 0xff);
    let mut hits = 0;
    // One query restarted on every ray, switching structure, view, flags and mask at random
    // (also in the middle of a traversal), against a fresh query for each.
    for k in 0..2000 {
        let s = &structures[if rng.next_u32().is_multiple_of(4) { rng.next_u32() as usize % 4 } else { 3 }];
        let v: &dyn DeviceView = if rng.next_u32().is_multiple_of(8) { &empty } else { &view };
        let (f, mask) = (FLAGS[rng.next_u32() as usize % FLAGS.len()], [0xff, 0x05, 0x3a][rng.next_u32() as usize % 3]);
        let r = rays[k % rays.len()];
        q.restart(s, v, r, RayFlags(f), mask);
        if k % 7 == 3 {
            // Abandoned after its first candidate: the next restart must not see its state.
            q.proceed();
            continue;
        }
        let restarted = trail(&mut q);
        let fresh = trail(&mut RayQuery::new(s, v, r, RayFlags(f), mask));
        assert_eq!(restarted, fresh, "ray {k}: flags {f:#x}, mask {mask:#x}, {r:?}");
        hits += (fresh[fresh.len() - 2].is_some()) as usize;
    }
    assert!(hits > 300, "{hits} rays hit");
}

//! Checks of the pieces the brute-force reference borrows from the library:
//! `intersect_triangle` against an independent double-precision test, and `fetch_triangle` /
//! `fetch_aabb` against our own vertex-format decoders and the inactive-primitive rules.

mod reference;

use arbor::accel::{self, Geometry, GeometryData, GeometryFlags, IndexType, Ray, VertexFormat};
use arbor_scene::Rng;
use reference::brute_force::*;
use reference::*;
use glam::Vec3;

fn rv(rng: &mut Rng, s: f32) -> Vec3 {
    Vec3::new(rng.range(-s, s), rng.range(-s, s), rng.range(-s, s))
}

#[test]
fn intersect_triangle_agrees_with_f64_away_from_edges() {
    let mut rng = Rng::new(11);
    let (mut hits, mut misses, mut checked_front) = (0, 0, 0);
    for i in 0..200_000 {
        // Mix of scales: unit, tiny and large triangles.
        let s = [1.0f32, 1e-3, 1e3][i % 3];
        let (a, b, c) = (rv(&mut rng, s), rv(&mut rng, s), rv(&mut rng, s));
        let o = rv(&mut rng, 3.0 * s);
        // Aim at the triangle most of the time so that hits are frequent.
        let target = if i % 4 == 0 { rv(&mut rng, s) } else {
            let (u, v) = (rng.range(-0.2, 1.2), rng.range(-0.2, 1.2));
            a + (b - a) * u + (c - a) * v
        };
        let d = (target - o) * rng.range(0.1, 10.0);
        let tmin = if i % 5 == 0 { rng.range(0.0, 0.5) } else { 0.0 };
        let tmax = if i % 7 == 0 { rng.range(0.3, 2.0) } else { f32::INFINITY };
        let ray = Ray { origin: o, direction: d, tmin, tmax };
        let f = |v: Vec3| [v.x as f64, v.y as f64, v.z as f64];
        let reference = intersect_f64(f(o), f(d), f(a), f(b), f(c));
        let lib = accel::intersect_triangle(&ray, a, b, c);
        let Some((t, u, v)) = reference else {
            continue;
        };
        let bary = u.min(v).min(1.0 - u - v);
        // Conditioning: a ray grazing the plane makes f32 barycentrics legitimately imprecise.
        let n = (b - a).cross(c - a);
        let cos = (n.normalize().dot(d.normalize())).abs() as f64;
        let tm = (t - tmin as f64).min(tmax as f64 - t) / t.abs().max(1.0);
        // Relative margins: decisions closer than this to flipping are not judged.
        if cos < 1e-3 || bary.abs() < 1e-4 / cos || tm.abs() < 1e-4 / cos {
            continue;
        }
        let inside = bary > 0.0 && tm > 0.0;
        match lib {
            Some((lt, lu, lv, front)) => {
                assert!(inside, "case {i}: library hits at t {lt}, f64 says miss (t {t}, bary {bary})");
                assert!(((lt as f64) - t).abs() <= 1e-4 / cos * t.abs().max(1e-6 * s as f64), "case {i}: t {lt} vs {t}, cos {cos}");
                assert!(((lu as f64) - u).abs() < 1e-4 / cos && ((lv as f64) - v).abs() < 1e-4 / cos, "case {i}: uv ({lu},{lv}) vs ({u},{v}), cos {cos}");
                assert_eq!(front, front_facing_f64(f(d), f(a), f(b), f(c)), "case {i}: facing");
                checked_front += 1;
                hits += 1;
            }
            None => {
                assert!(!inside, "case {i}: library misses, f64 hits at t {t} (u {u}, v {v})");
                misses += 1;
            }
        }
    }
    assert!(hits > 20_000 && misses > 20_000 && checked_front == hits, "hits {hits} misses {misses}");
}

#[test]
fn intersect_triangle_is_watertight_on_shared_edges() {
    // Rays through the shared edge of two triangles (a quad split along its diagonal) hit at
    // least one of them (Woop et al.: watertight), and never report a point outside both.
    let mut rng = Rng::new(5);
    for i in 0..50_000 {
        let p = [rv(&mut rng, 1.0), rv(&mut rng, 1.0), rv(&mut rng, 1.0), rv(&mut rng, 1.0)];
        let s = rng.next_f32();
        let on_edge = p[0] + (p[2] - p[0]) * s;
        let o = rv(&mut rng, 4.0);
        let ray = Ray { origin: o, direction: on_edge - o, tmin: 0.0, tmax: f32::INFINITY };
        let h1 = accel::intersect_triangle(&ray, p[0], p[1], p[2]);
        let h2 = accel::intersect_triangle(&ray, p[0], p[2], p[3]);
        // Skip rays nearly parallel to either triangle.
        let n1 = (p[1] - p[0]).cross(p[2] - p[0]).normalize();
        let n2 = (p[2] - p[0]).cross(p[3] - p[0]).normalize();
        let dn = ray.direction.normalize();
        if n1.dot(dn).abs() < 1e-2 || n2.dot(dn).abs() < 1e-2 || !(1e-3..=1.0 - 1e-3).contains(&s) {
            continue;
        }
        // Only when the edge is a silhouette-free crossing (both triangles on opposite sides as
        // seen from the ray) must one of them be hit; check that case.
        let side = |q: Vec3| (on_edge - o).cross(p[2] - p[0]).dot(q - p[0]);
        if side(p[1]) * side(p[3]) < 0.0 {
            assert!(h1.is_some() || h2.is_some(), "case {i}: ray through shared edge hits neither triangle");
        }
    }
}

#[test]
fn fetch_triangle_decodes_formats_index_types_and_transforms() {
    let mut rng = Rng::new(3);
    let positions: Vec<[f32; 3]> = (0..300).map(|_| [rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)]).collect();
    let tris: Vec<[u32; 3]> = (0..100).map(|_| [rng.below(300), rng.below(300), rng.below(300)]).collect();
    let transform = [0.0f32, -2.0, 0.0, 1.5, 1.0, 0.0, 0.0, -0.25, 0.0, 0.0, 0.5, 3.0];
    let formats = [
        VertexFormat::R32G32B32Sfloat,
        VertexFormat::R32G32Sfloat,
        VertexFormat::R32G32B32A32Sfloat,
        VertexFormat::R16G16Sfloat,
        VertexFormat::R16G16B16A16Sfloat,
        VertexFormat::R16G16Snorm,
        VertexFormat::R16G16B16A16Snorm,
    ];
    for format in formats {
        for stride in [format.size() as usize, format.size() as usize + 4, 32] {
            let (vbytes, decoded) = encode_vertices(&positions, format, stride);
            for index_type in [IndexType::U32, IndexType::U16, IndexType::None] {
                for xf in [None, Some(transform)] {
                    let (vb, ib, count) = match index_type {
                        IndexType::U32 => (vbytes.clone(), tris.iter().flatten().flat_map(|i| i.to_le_bytes()).collect::<Vec<u8>>(), tris.len()),
                        IndexType::U16 => (vbytes.clone(), tris.iter().flatten().flat_map(|&i| (i as u16).to_le_bytes()).collect(), tris.len()),
                        IndexType::None => {
                            // Three consecutive vertices per triangle.
                            let mut vb = Vec::new();
                            for t in &tris {
                                for &i in t {
                                    vb.extend_from_slice(&vbytes[i as usize * stride..(i as usize + 1) * stride]);
                                }
                            }
                            (vb, Vec::new(), tris.len())
                        }
                    };
                    let max_vertex = if index_type == IndexType::None { 3 * count as u32 - 1 } else { 299 };
                    let g = Geometry {
                        flags: GeometryFlags(0),
                        primitive_count: count as u32,
                        data: GeometryData::Triangles { format, vertices: &vb, stride: stride as u64, max_vertex, index_type, indices: &ib, transform: xf },
                    };
                    for (p, t) in tris.iter().enumerate() {
                        let got = accel::fetch_triangle(&g, p as u32).unwrap_or_else(|| panic!("{format:?} {index_type:?}: triangle {p} inactive"));
                        for k in 0..3 {
                            let d = decoded[t[k] as usize];
                            let want = match xf {
                                None => d,
                                Some(m) => {
                                    let m64: [f64; 12] = m.map(|x| x as f64);
                                    xform_point(&m64, [d[0] as f64, d[1] as f64, d[2] as f64]).map(|x| x as f32)
                                }
                            };
                            let g = got[k].to_array();
                            for c in 0..3 {
                                assert!(
                                    (g[c] - want[c]).abs() <= 2e-7 * want[c].abs().max(1.0),
                                    "{format:?} stride {stride} {index_type:?} xf {} tri {p} corner {k}: {:?} vs {:?}",
                                    xf.is_some(),
                                    g,
                                    want
                                );
                            }
                        }
                    }
                    assert!(accel::fetch_triangle(&g, count as u32).is_none(), "out-of-range primitive must be None");
                }
            }
        }
    }
}

#[test]
fn inactive_triangles_and_aabbs() {
    // A NaN in the x of any vertex makes a triangle inactive; NaN elsewhere is undefined (not
    // tested); an AABB is inactive when minX is NaN.
    let nan = f32::NAN;
    let positions = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [nan, 0.0, 0.0], [f32::INFINITY, 0.0, 0.0]];
    let tris: [[u32; 3]; 4] = [[0, 1, 2], [0, 3, 2], [3, 1, 2], [0, 1, 4]];
    let vb: Vec<u8> = positions.iter().flatten().flat_map(|c: &f32| c.to_le_bytes()).collect();
    let ib: Vec<u8> = tris.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
    let g = Geometry {
        flags: GeometryFlags(0),
        primitive_count: 4,
        data: GeometryData::Triangles {
            format: VertexFormat::R32G32B32Sfloat,
            vertices: &vb,
            stride: 12,
            max_vertex: 4,
            index_type: IndexType::U32,
            indices: &ib,
            transform: None,
        },
    };
    assert!(accel::fetch_triangle(&g, 0).is_some());
    assert!(accel::fetch_triangle(&g, 1).is_none());
    assert!(accel::fetch_triangle(&g, 2).is_none());
    // Infinity is not NaN: active (and then degenerate for traversal).
    assert!(accel::fetch_triangle(&g, 3).is_some());
    let boxes = AabbData::new(&[[0.0, 0.0, 0.0, 1.0, 1.0, 1.0], [nan, 0.0, 0.0, 1.0, 1.0, 1.0], [-1.0, -2.0, -3.0, 4.0, 5.0, 6.0]], 32, 0);
    let ga = boxes.geometry();
    assert_eq!(accel::fetch_aabb(&ga, 0), Some([0.0, 0.0, 0.0, 1.0, 1.0, 1.0]));
    assert!(accel::fetch_aabb(&ga, 1).is_none());
    assert_eq!(accel::fetch_aabb(&ga, 2), Some([-1.0, -2.0, -3.0, 4.0, 5.0, 6.0]));
}

#[test]
fn half_float_and_snorm_encoders_round_trip() {
    // Our own encoders, used to feed the library, are checked against known values.
    assert_eq!(f32_to_f16(1.0), 0x3C00);
    assert_eq!(f32_to_f16(-2.0), 0xC000);
    assert_eq!(f32_to_f16(65504.0), 0x7BFF);
    assert_eq!(f32_to_f16(5.960_464_5e-8), 0x0001);
    assert_eq!(f16_to_f32(0x3555), 0.333_251_95);
    assert_eq!(f32_to_snorm16(1.0), 32767);
    assert_eq!(f32_to_snorm16(-1.0), -32767);
    assert_eq!(snorm16_to_f32(-32768), -1.0);
    let mut rng = Rng::new(9);
    for _ in 0..10_000 {
        let x = rng.range(-100.0, 100.0);
        let h = f16_to_f32(f32_to_f16(x));
        assert!((h - x).abs() <= x.abs() / 1024.0, "{x} -> {h}");
        let y = rng.range(-1.0, 1.0);
        assert!((snorm16_to_f32(f32_to_snorm16(y)) - y).abs() <= 0.5 / 32767.0 + 1e-7);
    }
}

use super::*;
use crate::accel::encode::leaves::cluster_prefix;
use crate::accel::params::FAST_BUILD_TAU;

#[test]
fn pairs_prefix_and_geometries_account_for_every_primitive() {
    const DROP: u32 = u32::MAX;
    let r = |x: f32, id: u32| PrimRef { lo: [x, 0.0, 0.0], geom: 0, hi: [x + 1.0, 1.0, 1.0], prim: id };
    // Touching unit boxes pair (union 1x2 against two 1x1); far ones stay single; 15 and
    // 17 touch but their IDs do not follow; a dropped reference (18) breaks the 17-19 run.
    let mut c = vec![r(0.0, 10), r(1.0, 11), r(50.0, 12), r(51.0, 13), r(200.0, 14), r(90.0, 15), r(91.0, 17), PrimRef { geom: DROP, ..r(92.0, 18) }, r(93.0, 19)];
    let (m, clo, chi) = cluster_in_place(&mut c, FAST_BUILD_TAU, 2, DROP);
    let out = c[..m].to_vec();
    let ids: Vec<(u32, u32)> = out.iter().map(|p| (p.prim, p.geom)).collect();
    assert_eq!(ids, vec![(10, 2), (12, 2), (14, 1), (15, 1), (17, 1), (19, 1)]);
    assert!(c[m..].iter().all(|r| r.geom == DROP));
    assert_eq!((out[0].lo, out[0].hi), ([0.0; 3], [2.0, 1.0, 1.0]));
    assert_eq!((clo.to_array(), chi.to_array()), ([1.0, 0.5, 0.5], [200.5, 0.5, 0.5]));
    // The sampled test: every neighbour of a touching row is tight, none of a spread one.
    let row = |gap: f32| move |_g: u32, p: u32| Some(r(p as f32 * gap, p));
    assert!(worth_clustering(&[0, 5000, 9000], FAST_BUILD_TAU, row(1.0)));
    assert!(!worth_clustering(&[0, 9000], FAST_BUILD_TAU, row(3.0)));
    assert!(!worth_clustering(&[0, 9000], FAST_BUILD_TAU, |_, _| None));
    let mut p = vec![0u32; m + 1];
    cluster_prefix(&out, &mut p);
    assert_eq!(p, vec![0, 2, 4, 5, 6, 7, 8]);
    assert_eq!(geometry_of(7, &[0, 5, 9, 20]), 1);
    assert_eq!(geometry_of(9, &[0, 5, 9, 20]), 2);
    assert_eq!(geometry_of(0, &[0, 5, 9, 20]), 0);
    assert_eq!(geometry_of(19, &[0, 20]), 0);
    // An empty geometry (1) owns no ID: 5 is geometry 2's first.
    assert_eq!(geometry_of(5, &[0, 5, 5, 9]), 2);
    assert_eq!(geometry_of(4, &[0, 5, 5, 9]), 0);
    // Clusters of up to four: a row of touching unit boxes groups by fours while the union
    // stays within tau times the members' sum (half areas 2x1x1: 5 against 2 x 3; 3x1x1: 7
    // against 3 x 3; 4x1x1: 9 against 4 x 3).
    let mut row: Vec<PrimRef> = (0..10).map(|i| r(i as f32, 100 + i)).collect();
    let (m, ..) = cluster_in_place(&mut row, FAST_BUILD_TAU, 4, DROP);
    let ids: Vec<(u32, u32)> = row[..m].iter().map(|p| (p.prim, p.geom)).collect();
    assert_eq!(ids, vec![(100, 4), (104, 4), (108, 2)]);
}

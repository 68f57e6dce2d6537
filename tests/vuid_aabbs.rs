//! AABBs in device memory that break VkAabbPositionsKHR's rules: min > max on an axis is
//! reported by VUID (once per geometry, naming the first such primitive) and the build is
//! skipped; a NaN minX makes the AABB inactive, as the spec says, and is not reported.
mod harness;

use harness::vuid::*;

fn boxes(bad: Option<(usize, usize)>, nan_at: Option<usize>) -> Vec<u8> {
    let mut out = Vec::new();
    for k in 0..8usize {
        let mut b = [k as f32, 0.0, 0.0, k as f32 + 0.5, 1.0, 1.0];
        if let Some((p, axis)) = bad {
            if p == k || p + 2 == k {
                b.swap(axis, axis + 3);
            }
        }
        if nan_at == Some(k) {
            b[0] = f32::NAN;
        }
        out.extend(b.iter().flat_map(|x| x.to_le_bytes()));
    }
    out
}

#[test]
fn aabbs_with_min_above_max_03546_03547_03548() {
    scenario(|a, _m| {
        for (axis, vuid) in ["-minX-03546", "-minY-03547", "-minZ-03548"].iter().enumerate() {
            let data = guarded_data(a, &boxes(Some((3, axis)), None));
            let geoms = [aabbs_geom(data.address(a), 24)];
            let inf = info(BLAS, NO_FLAGS, &geoms);
            let sizes = a.sizes(DEVICE, &inf, &[8]);
            let dst = guarded_structure(a, BLAS, sizes.acceleration_structure_size);
            let scratch = guarded(a, sizes.build_scratch_size);
            let inf = inf.dst_acceleration_structure(dst.s).scratch_data(madr(scratch.address(a)));
            expect_invalid(
                a,
                Expect { command: CMD, vuid: format!("VUID-VkAabbPositionsKHR{vuid}"), needles: &["geometry 0: primitive 3:"], writable: &[dst.r, scratch], invalidated: &[] },
                || cmd_build(a, &[inf], &[&[range(8)]]),
            );
            assert!(header_of(a, &dst).is_none());
            let text = harness::diagnostics();
            assert_eq!(text.matches(&format!("VUID-VkAabbPositionsKHR{vuid}")).count(), 1, "reported once per geometry");
        }
    });
}

#[test]
fn an_aabb_with_a_nan_min_x_is_inactive() {
    scenario(|a, _m| {
        let data = guarded_data(a, &boxes(None, Some(2)));
        let geoms = [aabbs_geom(data.address(a), 24)];
        let inf = info(BLAS, NO_FLAGS, &geoms);
        let sizes = a.sizes(DEVICE, &inf, &[8]);
        let dst = guarded_structure(a, BLAS, sizes.acceleration_structure_size);
        let scratch = guarded(a, sizes.build_scratch_size);
        let mark = harness::diagnostics().len();
        cmd_build(a, &[inf.dst_acceleration_structure(dst.s).scratch_data(madr(scratch.address(a)))], &[&[range(8)]]);
        assert!(!harness::diagnostics()[mark..].contains("arbor: error"), "{}", &harness::diagnostics()[mark..]);
        let h = header_of(a, &dst).expect("built");
        assert_eq!(h.primitive_count, 7, "the NaN box is inactive");
        accel_validate(&dst.r.read(a));
    });
}

fn accel_validate(bytes: &[u8]) {
    arbor::accel::validate(bytes).expect("valid structure");
}

//! Self-checking structures: every copy verifies its source (checksum and structure), so bit
//! flips, truncations and spliced fields of serialized data are rejected with a named check,
//! and traversal of whatever is accepted stays total.
use super::*;

/// A BLAS of a random soup, a BLAS of AABBs and a TLAS over both.
fn structures() -> (Vec<u8>, Vec<u8>, Vec<u8>, MapView) {
    let mut rng = Rng::new(5);
    let v = random_soup(&mut rng, 300, 4.0, 0.5);
    let idx: Vec<u32> = (0..900).collect();
    let (vb, ib) = (f32_bytes(&v), u32_bytes(&idx));
    let tri = build_ok(AsType::BottomLevel, BuildFlags::ALLOW_UPDATE, &[tri_geom(&vb, 900, &ib, 300, 0)], &NoDevice);
    let boxes: Vec<u8> = (0..50).flat_map(|k| [k as f32, 0.0, 0.0, k as f32 + 0.5, 1.0, 1.0]).flat_map(|x| x.to_le_bytes()).collect();
    let ga = Geometry { flags: GeometryFlags(1), primitive_count: 50, data: GeometryData::Aabbs { data: &boxes, stride: 24 } };
    let aabbs = build_ok(AsType::BottomLevel, 0, &[ga], &NoDevice);
    let mut view = MapView::new();
    view.insert(0x1000, tri.clone());
    view.insert(0x100000, aabbs.clone());
    let inst: Vec<u8> = (0..20).flat_map(|k| instance_bytes(translate(3.0 * k as f32, 0.0, 0.0), k, 0xff, 0, 0, if k % 2 == 0 { 0x1000 } else { 0x100000 })).collect();
    let g = Geometry { flags: GeometryFlags(0), primitive_count: 20, data: GeometryData::Instances { array_of_pointers: false, data: &inst } };
    let tlas = build_ok(AsType::TopLevel, 0, &[g], &view);
    (tri, aabbs, tlas, view)
}

fn serialized(s: &[u8]) -> Vec<u8> {
    let mut out = vec![0u8; serialized_size(s).unwrap() as usize];
    serialize(s, [9u8; 16], &mut out).unwrap();
    out
}

#[test]
fn built_updated_and_copied_structures_pass_their_checks() {
    let (tri, aabbs, tlas, _) = structures();
    for s in [&tri, &aabbs, &tlas] {
        crate::accel::check::check(s).expect("a fresh build passes");
        let mut c = vec![0u8; s.len()];
        clone_into(s, &mut c).unwrap();
        let mut d = vec![0u8; s.len()];
        deserialize(&serialized(s), [9u8; 16], &mut d).unwrap();
    }
}

/// Random bit flips in the payload of serialized data (outside the Vulkan header, which has
/// checks of its own, and the BLAS table, which the handle list overwrites) are all rejected,
/// by the checksum or an earlier check; nothing is written.
#[test]
fn every_bit_flip_in_a_payload_is_rejected() {
    let (tri, aabbs, tlas, _) = structures();
    for s in [&tri, &aabbs, &tlas] {
        let ser = serialized(s);
        let n = u64::from_le_bytes(ser[48..56].try_into().unwrap()) as usize;
        let payload = 56 + 8 * n;
        let raw = crate::accel::layout::parse(s).unwrap().raw;
        let table = payload + raw.blas_table_offset as usize..payload + raw.blas_table_offset as usize + 8 * raw.blas_table_capacity as usize;
        let mut rng = Rng::new(11);
        for _ in 0..400 {
            let at = payload + rng.next_u32() as usize % (ser.len() - payload);
            if table.contains(&at) {
                continue;
            }
            let mut bad = ser.clone();
            bad[at] ^= 1 << (rng.next_u32() % 8);
            let mut dst = vec![0x5Au8; s.len()];
            let r = deserialize(&bad, [9u8; 16], &mut dst);
            assert!(matches!(r, Err(CopyError::Corrupt(_))), "flip at {at}: {r:?}");
            assert!(dst.iter().all(|&b| b == 0x5A), "a rejected blob wrote its destination");
        }
        // A structure written over in memory: copies refuse it.
        let mut bad = s.clone();
        let at = header(s).unwrap().used_size as usize - 3;
        bad[at] ^= 0x10;
        assert!(matches!(clone_into(&bad, &mut vec![0u8; s.len()]), Err(CopyError::Corrupt("checksum"))));
        assert!(matches!(serialize(&bad, [9u8; 16], &mut vec![0u8; ser.len()]), Err(CopyError::Corrupt("checksum"))));
    }
}

/// A rewritten handle list is not covered by the checksum (applications relocate it); the
/// handles themselves are checked by the driver against live structures.
#[test]
fn the_handle_list_is_relocatable() {
    let (_, _, tlas, _) = structures();
    let mut ser = serialized(&tlas);
    ser[56..64].copy_from_slice(&0xDEAD_0000u64.to_le_bytes());
    let mut d = vec![0u8; tlas.len()];
    deserialize(&ser, [9u8; 16], &mut d).unwrap();
    assert_eq!(blas_references(&d)[0], 0xDEAD_0000);
}

/// Truncated data and a spliced count are rejected by name.
#[test]
fn truncations_and_spliced_counts_are_rejected() {
    let (tri, _, tlas, _) = structures();
    for s in [&tri, &tlas] {
        let ser = serialized(s);
        for cut in [0, 31, 55, 60, 56 + 160, ser.len() / 2, ser.len() - 1] {
            let r = deserialize(&ser[..cut], [9u8; 16], &mut vec![0u8; s.len()]);
            assert!(matches!(r, Err(CopyError::Corrupt(_))), "cut at {cut}: {r:?}");
        }
        let mut spliced = ser.clone();
        let n = u64::from_le_bytes(ser[48..56].try_into().unwrap());
        spliced[48..56].copy_from_slice(&(n + 1).to_le_bytes());
        assert!(deserialize(&spliced, [9u8; 16], &mut vec![0u8; s.len()]).is_err());
    }
}

//! A TLAS's bytes after its tree is built, on two branches at once: the instance sections
//! (records, instance records, BLAS table) on one, the wide nodes on the other. Nodes come
//! last in the layout, so neither branch's offsets depend on the other's output; each branch
//! then hashes the checksum part it completed while its bytes are in cache, and the header
//! combines the two hashes (`checksum::combine`): the same checksum as `checksum::seal`.
//! The bytes are those of the sequential path, whatever the thread count.
//!
//! Owns: the order of the TLAS's final writes. Must not touch: the header (`finish_tlas`).
use super::instances::write_instances;
use super::{wide_nodes, zero_gaps};
use crate::accel::checksum;
use crate::accel::geometry::PrimRef;
use crate::accel::layout::{self, NODE_SIZE, RECORD_SIZE};
use crate::accel::tree::BinNode;
use crate::accel::{AsType, BuildDesc, BuildError, DeviceView};

/// What the two branches wrote.
pub struct Written {
    pub node_count: u32,
    pub leaf_count: u32,
    /// BLAS-table entries (stored instances).
    pub blas_refs: u32,
    /// `checksum::part_hash` of both parts.
    pub parts: [u64; 2],
}

/// Writes the instance sections of the `refs.len()` stored instances (leaf order) and the
/// wide nodes of `tree` (non-empty) into dst, zeroes the gaps up to the used size and hashes
/// both checksum parts. `keys` (8 bytes per stored instance, 8-aligned) is scratch for the
/// BLAS table's order.
pub fn write(desc: &BuildDesc, view: &dyn DeviceView, dst: &mut [u8], tree: &[BinNode], refs: &[PrimRef], keys: &mut [u8]) -> Result<Written, BuildError> {
    let (active, ngeo) = (refs.len(), desc.geometries.len() as u64);
    let s = layout::sections(AsType::TopLevel, 0, active as u64, ngeo);
    let table_end = s.blas_table as usize + active * 8;
    let too_small = |needed: u64| BuildError::DestinationTooSmall { needed, got: dst.len() as u64 };
    if s.nodes as usize > dst.len() {
        return Err(too_small(s.nodes));
    }
    let keys: &mut [u64] = keys.get_mut(..active * 8).and_then(|k| bytemuck::try_cast_slice_mut(k).ok()).ok_or(BuildError::ScratchTooSmall { needed: layout::build_scratch_size(AsType::TopLevel, active as u64), got: 0 })?;
    // The gap between the table and the nodes starts part 1: zero before the split.
    dst[table_end..s.nodes as usize].fill(0);
    let (head, tail) = dst.split_at_mut(table_end);
    let nodes_at = s.nodes as usize - table_end;
    let (instances, nodes) = rayon::join(
        || {
            let blas_refs = instance_sections(desc, view, head, &s, refs, keys);
            (blas_refs, checksum::part_hash(&head[layout::HEADER_SIZE..s.blas_table as usize], 0))
        },
        || -> Result<_, BuildError> {
            let (node_count, leaf_count) = wide_nodes(tree, tail, nodes_at, &[], None)?;
            let used = layout::sections(AsType::TopLevel, node_count as u64, active as u64, ngeo).end as usize - table_end;
            let nodes_end = nodes_at + node_count as usize * NODE_SIZE;
            let got = (tail.len() + table_end) as u64;
            tail.get_mut(nodes_end..used).ok_or(BuildError::DestinationTooSmall { needed: (used + table_end) as u64, got })?.fill(0);
            Ok((node_count, leaf_count, checksum::part_hash(&tail[..used], 1)))
        },
    );
    let (blas_refs, h0) = instances;
    let (node_count, leaf_count, h1) = nodes?;
    Ok(Written { node_count, leaf_count, blas_refs, parts: [h0, h1] })
}

/// The records, instance records and BLAS table in `head` (dst up to the table's end), and the
/// gaps between them zeroed. Returns the table's entry count.
fn instance_sections(desc: &BuildDesc, view: &dyn DeviceView, head: &mut [u8], s: &layout::Sections, refs: &[PrimRef], keys: &mut [u64]) -> u32 {
    let active = refs.len();
    let (records_end, inst_end) = (s.records as usize + active * RECORD_SIZE, s.instances as usize + active * layout::INSTANCE_RECORD_SIZE);
    let (front, table) = head.split_at_mut(s.blas_table as usize);
    let (front, inst) = front.split_at_mut(s.instances as usize);
    let blas_refs = write_instances(desc, view, refs, keys, &mut inst[..active * layout::INSTANCE_RECORD_SIZE], &mut front[s.records as usize..records_end], table);
    let filled = [
        (s.records, records_end as u64),
        (s.geometries, s.geometries + desc.geometries.len() as u64 * layout::GEOMETRY_SIZE as u64),
        (s.instances, inst_end as u64),
        (s.blas_table, head.len() as u64),
    ];
    zero_gaps(head, &filled, head.len() as u64);
    blas_refs
}

#[cfg(test)]
mod tests {
    use crate::accel::tests::{build_ok, f32_bytes, tri_geom};
    use crate::accel::{checksum, layout, AsType, BuildFlags, Geometry, GeometryData, GeometryFlags, MapView, NoDevice};
    use glam::Vec3;

    /// The checksum sealed from the two branches' part hashes equals the one hashed from the
    /// finished bytes (`checksum::structure_checksum`, the sequential path) for TLASes whose
    /// first part spans more than one hash chunk, all active (the table in input order) and
    /// with inactive instances (the ranked table); and the bytes are the same on 1, 2, 5 and
    /// 16 threads.
    #[test]
    fn parts_sealed_beside_each_other_match_the_whole_bytes_hash() {
        let vb = f32_bytes(&[Vec3::ZERO, Vec3::X, Vec3::Y]);
        let mut view = MapView::new();
        view.insert(0x8000, build_ok(AsType::BottomLevel, 0, &[tri_geom(&vb, 3, &[], 1, GeometryFlags::OPAQUE)], &NoDevice));
        let mut next = crate::accel::testing::unit_floats(41);
        let n = 12_000u32;
        for inactive_every in [0u32, 13] {
            let records: Vec<u8> = (0..n)
                .flat_map(|i| {
                    let t = [1.0, 0.0, 0.0, next() * 100.0, 0.0, 1.0, 0.0, next() * 100.0, 0.0, 0.0, 1.0, next() * 100.0];
                    let reference = if inactive_every != 0 && i % inactive_every == 3 { 0u64 } else { 0x8000 };
                    let mut r: Vec<u8> = t.iter().flat_map(|f: &f32| f.to_le_bytes()).collect();
                    r.extend((i | 0xff << 24).to_le_bytes());
                    r.extend(0u32.to_le_bytes());
                    r.extend(reference.to_le_bytes());
                    r
                })
                .collect();
            let g = Geometry { flags: GeometryFlags(0), primitive_count: n, data: GeometryData::Instances { array_of_pointers: false, data: &records } };
            let builds: Vec<Vec<u8>> = [1, 2, 5, 16]
                .iter()
                .map(|&t| rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap().install(|| build_ok(AsType::TopLevel, BuildFlags::PREFER_FAST_BUILD, &[g], &view)))
                .collect();
            assert!(builds.windows(2).all(|w| w[0] == w[1]), "bytes differ between thread counts ({inactive_every})");
            let p = layout::parse(&builds[0]).expect("a valid header");
            assert!(p.raw.blas_table_offset as usize - layout::HEADER_SIZE > 1 << 20, "part 0 within one hash chunk");
            assert_eq!(p.raw.checksum, checksum::structure_checksum(&p.raw, p.bytes), "inactive every {inactive_every}");
        }
    }
}

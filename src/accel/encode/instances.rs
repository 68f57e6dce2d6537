//! The TLAS sections: instance records (both transforms, the BLAS-table index) and the BLAS
//! table: one reference per stored instance, in the instance order of the input.
//!
//! Owns: the instances and BLAS-table sections. Must not touch: nodes, BLAS bytes.
use crate::accel::geometry::PrimRef;
use crate::accel::input::{self, read_instance};
use crate::accel::layout::{self, InstanceRecord, PrimRecord, RECORD_SIZE};
use crate::accel::params::{INSTANCE_CHUNK, PREFETCH_AHEAD};
use crate::accel::{BuildDesc, DeviceView, GeometryData};
use bytemuck::Zeroable;
use rayon::prelude::*;

/// The key that orders instances as the build's input does: geometry, then instance index.
pub fn input_order_key(geometry: u32, primitive: u32) -> u64 {
    (geometry as u64) << 32 | primitive as u64
}

/// Sorts `keys` (the `input_order_key`s of the stored instances) and writes the BLAS table
/// from them: entry k is the (translated) reference of the k-th stored instance in input order.
/// Slots past the stored instances are zeroed so the bytes stay deterministic.
pub fn write_table(desc: &BuildDesc, view: &dyn DeviceView, keys: &mut [u64], table: &mut [u8]) {
    keys.par_sort_unstable();
    let reference = |k: u64| desc.geometries.get((k >> 32) as usize).and_then(|g| input::read_instance_reference(g, k as u32, view));
    let n = keys.len().min(table.len() / 8);
    let (used, rest) = table.split_at_mut(n * 8);
    used.par_chunks_mut(8).zip(keys.par_iter()).for_each(|(d, &k)| d.copy_from_slice(&reference(k).unwrap_or(0).to_le_bytes()));
    rest.fill(0);
}

/// Instance records + BLAS table for stored instances (TLAS). The table holds one reference
/// per stored (active) instance, duplicates included, in the instance order of the input (the
/// serialized header lists it, and applications rewrite it entry by entry; inactive instances
/// store nothing and contribute no entry). `keys` is scratch for ordering the instances.
/// Returns the number of table entries (= stored instances).
pub fn write_instances(desc: &BuildDesc, view: &dyn DeviceView, refs: &[PrimRef], keys: &mut [u64], instances: &mut [u8], records: &mut [u8], table: &mut [u8]) -> u32 {
    let n = refs.len();
    let read = |r: &PrimRef| {
        let g = desc.geometries.get(r.geom as usize)?;
        match g.data {
            // Packed records are decoded in place: the records need no translated reference
            // (the table has it), only whether there is one.
            GeometryData::Instances { array_of_pointers: false, data } => input::decode_instance(data.get(r.prim as usize * input::INSTANCE_SIZE..)?).filter(|i| i.reference != 0),
            _ => read_instance(r.geom, g, r.prim, view).ok().flatten(),
        }
    };
    // One geometry with every instance active (the usual TLAS): an instance's place in input
    // order is its index, so the table and the records' BLAS-table indices need no sort and
    // no search. The same bytes as the general path, which ranks the stored instances.
    let all_active = matches!(desc.geometries, [g] if g.primitive_count as usize == n);
    let keys = &mut keys[..if all_active { 0 } else { n }];
    if let (true, [g]) = (all_active, desc.geometries) {
        let n_table = n.min(table.len() / 8);
        let (used, rest) = table.split_at_mut(n_table * 8);
        used.par_chunks_mut(8 * INSTANCE_CHUNK).enumerate().for_each(|(c, d)| {
            for (k, e) in d.chunks_exact_mut(8).enumerate() {
                e.copy_from_slice(&input::read_instance_reference(g, (c * INSTANCE_CHUNK + k) as u32, view).unwrap_or(0).to_le_bytes());
            }
        });
        rest.fill(0);
    } else {
        keys.par_iter_mut().zip(refs.par_iter()).for_each(|(k, r)| *k = input_order_key(r.geom, r.prim));
        write_table(desc, view, keys, table);
    }
    let keys = &keys[..];
    let packed = match desc.geometries {
        [g] => match g.data {
            GeometryData::Instances { array_of_pointers: false, data } => Some(data),
            _ => None,
        },
        _ => None,
    };
    let blas_index = |r: &PrimRef| if all_active { r.prim } else { keys.binary_search(&input_order_key(r.geom, r.prim)).map_or(u32::MAX, |x| x as u32) };
    instances
        .par_chunks_mut(INSTANCE_CHUNK * layout::INSTANCE_RECORD_SIZE)
        .zip(records.par_chunks_mut(INSTANCE_CHUNK * RECORD_SIZE))
        .zip(refs.par_chunks(INSTANCE_CHUNK))
        .for_each(|((id, rd), rs)| {
            for (k, r) in rs.iter().enumerate() {
                // Leaf order visits the input's records at random: a large TLAS waits on
                // memory here unless the record a few instances ahead is on its way.
                if let (Some(data), Some(a)) = (packed, rs.get(k + PREFETCH_AHEAD)) {
                    let o = a.prim as usize * input::INSTANCE_SIZE;
                    arbor_prefetch::read(data, o);
                    arbor_prefetch::read(data, o + input::INSTANCE_SIZE - 1);
                }
                let mut rec = InstanceRecord::zeroed();
                if let Some(inst) = read(r) {
                    rec.object_to_world = inst.transform;
                    rec.world_to_object = input::invert_transform(&inst.transform);
                    rec.custom_index = inst.custom_index;
                    rec.mask = inst.mask;
                    rec.sbt_offset = inst.sbt_offset;
                    rec.flags = inst.flags;
                    rec.blas_index = blas_index(r);
                }
                rec.instance_index = r.prim;
                let o = k * layout::INSTANCE_RECORD_SIZE;
                if let Some(d) = id.get_mut(o..o + layout::INSTANCE_RECORD_SIZE) {
                    d.copy_from_slice(bytemuck::bytes_of(&rec));
                }
                let prec = PrimRecord { geometry: r.geom, primitive: r.prim };
                if let Some(d) = rd.get_mut(k * RECORD_SIZE..(k + 1) * RECORD_SIZE) {
                    d.copy_from_slice(bytemuck::bytes_of(&prec));
                }
            }
        });
    n as u32
}

//! The TLAS sections: instance records (both transforms, the BLAS index) and the table of
//! distinct BLAS addresses, in leaf order.
//!
//! Owns: the instances and BLAS-table sections. Must not touch: nodes, BLAS bytes.
use crate::accel::geometry::PrimRef;
use crate::accel::input::{self, read_instance};
use crate::accel::layout::{self, InstanceRecord, PrimRecord, RECORD_SIZE};
use crate::accel::params::INSTANCE_CHUNK;
use crate::accel::{BuildDesc, DeviceView};
use bytemuck::Zeroable;
use rayon::prelude::*;

/// Sort `keys` and move the distinct values to the front; returns how many there are.
pub fn sort_distinct(keys: &mut [u64]) -> usize {
    keys.sort_unstable();
    let mut distinct = 0usize;
    for i in 0..keys.len() {
        if i == 0 || keys[i] != keys[distinct - 1] {
            keys[distinct] = keys[i];
            distinct += 1;
        }
    }
    distinct
}

/// Instance records + BLAS table for stored instances (TLAS). `keys` is scratch for the sort.
/// Returns the number of distinct BLAS addresses.
pub fn write_instances(desc: &BuildDesc, view: &dyn DeviceView, refs: &[PrimRef], keys: &mut [u64], instances: &mut [u8], records: &mut [u8], table: &mut [u8]) -> u32 {
    let n = refs.len();
    let read = |r: &PrimRef| desc.geometries.get(r.geom as usize).and_then(|g| read_instance(r.geom, g, r.prim, view).ok().flatten());
    // Distinct references, sorted (deterministic, no hashing, no heap).
    let keys = &mut keys[..n];
    let reference = |r: &PrimRef| desc.geometries.get(r.geom as usize).and_then(|g| input::read_instance_reference(g, r.prim, view));
    keys.par_iter_mut().zip(refs.par_iter()).for_each(|(k, r)| *k = reference(r).unwrap_or(0));
    let distinct = sort_distinct(keys);
    let keys = &keys[..distinct];
    for (i, k) in keys.iter().enumerate() {
        if let Some(d) = table.get_mut(i * 8..i * 8 + 8) {
            d.copy_from_slice(&k.to_le_bytes());
        }
    }
    // Unused table slots (capacity > distinct) are zero so the bytes stay deterministic.
    if let Some(rest) = table.get_mut(distinct * 8..) {
        rest.fill(0);
    }
    instances
        .par_chunks_mut(INSTANCE_CHUNK * layout::INSTANCE_RECORD_SIZE)
        .zip(records.par_chunks_mut(INSTANCE_CHUNK * RECORD_SIZE))
        .zip(refs.par_chunks(INSTANCE_CHUNK))
        .for_each(|((id, rd), rs)| {
            for (k, r) in rs.iter().enumerate() {
                let mut rec = InstanceRecord::zeroed();
                if let Some(inst) = read(r) {
                    rec.object_to_world = inst.transform;
                    rec.world_to_object = input::invert_transform(&inst.transform);
                    rec.custom_index = inst.custom_index;
                    rec.mask = inst.mask;
                    rec.sbt_offset = inst.sbt_offset;
                    rec.flags = inst.flags;
                    rec.blas_index = keys.binary_search(&inst.reference).map_or(u32::MAX, |x| x as u32);
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
    distinct as u32
}

//! Update (refit): same topology, new vertex/AABB positions or instance definitions. Checks the
//! update rules visible here, rewrites primitive data, then recomputes node boxes bottom-up
//! (preorder layout: every child has a larger index than its parent).
use super::builder::{self, carve, encode_node, geometry_record, make_ref, triangle_bounds, Aabb};
use super::input::read_instance;
use super::layout::{self, InstanceRecord, Parsed, CHILD_INTERNAL, NODE_SIZE, PRIM_SIZE};
use super::{AsType, BuildDesc, BuildError, BuildFlags, BuildReport, DeviceView, GeometryData};
use bytemuck::Zeroable;
use glam::Vec3;
use rayon::prelude::*;

fn mismatch(s: &'static str) -> BuildError {
    BuildError::UpdateMismatch(s)
}

fn check(desc: &BuildDesc, p: &Parsed, view: &dyn DeviceView) -> Result<(), BuildError> {
    let r = p.raw;
    if r.flags & BuildFlags::ALLOW_UPDATE == 0 {
        return Err(mismatch("source was not built with ALLOW_UPDATE"));
    }
    if r.ty != desc.ty as u32 {
        return Err(mismatch("acceleration structure type differs"));
    }
    if r.flags != desc.flags.0 {
        return Err(mismatch("build flags differ"));
    }
    if r.geometry_count as usize != desc.geometries.len() {
        return Err(mismatch("geometry count differs"));
    }
    let mut total = 0u64;
    for (gi, g) in desc.geometries.iter().enumerate() {
        let old = p.geometry(gi as u32).ok_or(BuildError::InvalidSource("geometry table"))?;
        let new = geometry_record(g, old.active_count, true);
        if old.kind != new.kind {
            return Err(mismatch("geometry type differs"));
        }
        if old.flags != new.flags {
            return Err(mismatch("geometry flags differ"));
        }
        if old.primitive_count != new.primitive_count {
            return Err(mismatch("primitive count differs"));
        }
        if old.format != new.format || old.index_type != new.index_type || old.max_vertex != new.max_vertex {
            return Err(mismatch("vertex format, index type or maxVertex differs"));
        }
        if old.has_transform != new.has_transform {
            return Err(mismatch("transform presence differs"));
        }
        if old.index_hash != new.index_hash {
            return Err(mismatch("index values differ"));
        }
        total += g.primitive_count as u64;
    }
    // Inactive primitives exist only if fewer were stored than IDs consumed; then check that
    // exactly the same number per geometry is still storable (stored ones are checked one by one).
    if total != r.primitive_count as u64 {
        for (gi, g) in desc.geometries.iter().enumerate() {
            let old = p.geometry(gi as u32).ok_or(BuildError::InvalidSource("geometry table"))?;
            let n: Result<u32, BuildError> = (0..g.primitive_count)
                .into_par_iter()
                .map(|k| make_ref(gi as u32, g, k, view, true).map(|o| o.is_some() as u32))
                .reduce(|| Ok(0), |a, b| Ok(a? + b?));
            if n? != old.active_count {
                return Err(mismatch("active/inactive state of a primitive changed"));
            }
        }
    }
    Ok(())
}

fn prim_bounds(d: &[f32; 9], kind: u32) -> ([f32; 3], [f32; 3]) {
    if kind == layout::KIND_AABBS {
        builder::sanitize([d[0], d[1], d[2]], [d[3], d[4], d[5]])
    } else {
        triangle_bounds(&[Vec3::new(d[0], d[1], d[2]), Vec3::new(d[3], d[4], d[5]), Vec3::new(d[6], d[7], d[8])])
    }
}

pub fn update(desc: &BuildDesc, view: &dyn DeviceView, src: Option<&[u8]>, dst: &mut [u8], scratch: &mut [u8]) -> Result<BuildReport, BuildError> {
    if let Some(s) = src {
        let p = layout::parse(s).ok_or(BuildError::InvalidSource("source is not a valid structure"))?;
        let used = p.raw.used_size;
        let got = dst.len() as u64;
        let d = dst.get_mut(..used as usize).ok_or(BuildError::DestinationTooSmall { needed: used, got })?;
        d.copy_from_slice(&s[..used as usize]);
    }
    let raw = {
        let p = layout::parse(dst).ok_or(BuildError::InvalidSource("destination is not a valid structure"))?;
        check(desc, &p, view)?;
        p.raw
    };
    let total = builder::total_primitives(desc)?;
    let need = layout::update_scratch_size(total);
    if (scratch.len() as u64) < need {
        return Err(BuildError::ScratchTooSmall { needed: need, got: scratch.len() as u64 });
    }
    let n = raw.primitive_count as usize;
    let is_tlas = raw.ty == AsType::TopLevel as u32;
    let used = raw.used_size as usize;
    let dst = &mut dst[..used];

    // 1. New primitive data; every stored primitive must still be storable.
    let (boxes, rest) = carve::<[f32; 6]>(scratch, raw.node_count as usize).ok_or(BuildError::ScratchTooSmall { needed: need, got: 0 })?;
    if is_tlas {
        let (keys, _) = carve::<u64>(rest, n).ok_or(BuildError::ScratchTooSmall { needed: need, got: 0 })?;
        refit_instances(desc, view, &raw, dst, keys)?;
    } else {
        let (head, tail) = dst.split_at_mut(raw.records_offset as usize);
        let prims = &mut head[raw.prims_offset as usize..raw.prims_offset as usize + n * PRIM_SIZE];
        let records = &tail[..n * layout::RECORD_SIZE];
        prims
            .par_chunks_mut(1024 * PRIM_SIZE)
            .zip(records.par_chunks(1024 * layout::RECORD_SIZE))
            .map(|(pd, rd)| {
                for (k, rb) in rd.chunks_exact(layout::RECORD_SIZE).enumerate() {
                    let rec: layout::PrimRecord = bytemuck::pod_read_unaligned(rb);
                    let g = desc.geometries.get(rec.geometry as usize).ok_or(BuildError::InvalidSource("record"))?;
                    let mut data = [0f32; 9];
                    match g.data {
                        GeometryData::Triangles { .. } => {
                            let v = super::input::read_triangle(rec.geometry, g, rec.primitive)?.ok_or(mismatch("an active primitive became inactive"))?;
                            data = [v[0].x, v[0].y, v[0].z, v[1].x, v[1].y, v[1].z, v[2].x, v[2].y, v[2].z];
                        }
                        GeometryData::Aabbs { .. } => {
                            let b = super::input::read_aabb(rec.geometry, g, rec.primitive)?.ok_or(mismatch("an active primitive became inactive"))?;
                            data[..6].copy_from_slice(&b);
                        }
                        GeometryData::Instances { .. } => return Err(BuildError::WrongGeometryType { geometry: rec.geometry }),
                    }
                    if let Some(d) = pd.get_mut(k * PRIM_SIZE..(k + 1) * PRIM_SIZE) {
                        d.copy_from_slice(bytemuck::bytes_of(&data));
                    }
                }
                Ok(())
            })
            .reduce(|| Ok(()), |a, b| a.and(b))?;
    }

    let raw = layout::parse(dst).map(|p| p.raw).ok_or(BuildError::InvalidSource("structure"))?;
    // 2. Node boxes bottom-up; exact child boxes of internal nodes come from `boxes`.
    let nc = raw.node_count as usize;
    let mut root = Aabb::EMPTY;
    for i in (0..nc).rev() {
        let (wn, nb) = {
            let p = Parsed { raw, bytes: &*dst };
            let node = p.node(i as u32).ok_or(BuildError::InvalidSource("node"))?;
            let cnt = (node.child_count as usize).min(4);
            let mut cb = [Aabb::EMPTY; 4];
            let mut nb = Aabb::EMPTY;
            for c in 0..cnt {
                cb[c] = match node.kind[c] {
                    CHILD_INTERNAL => {
                        let ch = node.child[c] as usize;
                        if ch <= i || ch >= nc {
                            return Err(BuildError::InvalidSource("node order"));
                        }
                        let b = boxes[ch];
                        Aabb { lo: [b[0], b[1], b[2]], hi: [b[3], b[4], b[5]] }
                    }
                    0 => Aabb::EMPTY,
                    k => leaf_bounds(&p, node.child[c], k as u32, view)?,
                };
                nb = nb.union(&cb[c]);
            }
            (encode_node(&nb, &cb[..cnt], &node.child[..cnt], &node.kind[..cnt]), nb)
        };
        boxes[i] = [nb.lo[0], nb.lo[1], nb.lo[2], nb.hi[0], nb.hi[1], nb.hi[2]];
        let off = raw.nodes_offset as usize + i * NODE_SIZE;
        if let Some(d) = dst.get_mut(off..off + NODE_SIZE) {
            d.copy_from_slice(bytemuck::bytes_of(&wn));
        }
        if i == 0 {
            root = nb;
        }
    }
    let mut h = raw;
    if n > 0 {
        h.bounds = [root.lo[0], root.lo[1], root.lo[2], root.hi[0], root.hi[1], root.hi[2]];
    }
    layout::write_header(dst, &h);
    Ok(BuildReport { used_size: raw.used_size, node_count: raw.node_count, leaf_count: raw.leaf_count, primitive_count: raw.primitive_count })
}

fn leaf_bounds(p: &Parsed, first: u32, count: u32, view: &dyn DeviceView) -> Result<Aabb, BuildError> {
    let mut b = Aabb::EMPTY;
    for s in first..first.saturating_add(count) {
        let (lo, hi) = if p.is_tlas() {
            let rec = p.instance(s).ok_or(BuildError::InvalidSource("leaf range"))?;
            let addr = p.blas_address(rec.blas_index).unwrap_or(0);
            builder::instance_bounds(&rec.object_to_world, addr, view)
        } else {
            let d = p.prim(s).ok_or(BuildError::InvalidSource("leaf range"))?;
            let g = p.record(s).and_then(|r| p.geometry(r.geometry)).ok_or(BuildError::InvalidSource("record"))?;
            prim_bounds(&d, g.kind)
        };
        b.grow(&lo, &hi);
    }
    Ok(b)
}

/// TLAS: rewrite instance records and the BLAS table from the new instance definitions.
fn refit_instances(desc: &BuildDesc, view: &dyn DeviceView, raw: &layout::RawHeader, dst: &mut [u8], keys: &mut [u64]) -> Result<(), BuildError> {
    let n = raw.primitive_count as usize;
    let rec_off = raw.records_offset as usize;
    let read_rec = |dst: &[u8], i: usize| -> Option<layout::PrimRecord> {
        let o = rec_off + i * layout::RECORD_SIZE;
        dst.get(o..o + layout::RECORD_SIZE).map(bytemuck::pod_read_unaligned)
    };
    // Keys: the new references of stored instances, sorted and made distinct.
    for i in 0..n {
        let r = read_rec(dst, i).ok_or(BuildError::InvalidSource("record"))?;
        let g = desc.geometries.get(r.geometry as usize).ok_or(BuildError::InvalidSource("record"))?;
        let inst = read_instance(r.geometry, g, r.primitive, view)?.ok_or(mismatch("an active instance became inactive"))?;
        keys[i] = inst.reference;
    }
    let keys = &mut keys[..n];
    let distinct = super::builder::sort_distinct(keys);
    let keys = &keys[..distinct];
    let table = raw.blas_table_offset as usize;
    for i in 0..raw.blas_table_capacity as usize {
        let v = keys.get(i).copied().unwrap_or(0);
        if let Some(d) = dst.get_mut(table + 8 * i..table + 8 * i + 8) {
            d.copy_from_slice(&v.to_le_bytes());
        }
    }
    for i in 0..n {
        let r = read_rec(dst, i).ok_or(BuildError::InvalidSource("record"))?;
        let g = desc.geometries.get(r.geometry as usize).ok_or(BuildError::InvalidSource("record"))?;
        let inst = read_instance(r.geometry, g, r.primitive, view)?.ok_or(mismatch("an active instance became inactive"))?;
        let mut rec = InstanceRecord::zeroed();
        rec.object_to_world = inst.transform;
        rec.world_to_object = super::input::invert_transform(&inst.transform);
        rec.custom_index = inst.custom_index;
        rec.mask = inst.mask;
        rec.sbt_offset = inst.sbt_offset;
        rec.flags = inst.flags;
        rec.instance_index = r.primitive;
        rec.blas_index = keys.binary_search(&inst.reference).map_or(u32::MAX, |x| x as u32);
        let o = raw.instances_offset as usize + i * layout::INSTANCE_RECORD_SIZE;
        if let Some(d) = dst.get_mut(o..o + layout::INSTANCE_RECORD_SIZE) {
            d.copy_from_slice(bytemuck::bytes_of(&rec));
        }
    }
    let mut h = *raw;
    h.blas_reference_count = distinct as u32;
    layout::write_header(dst, &h);
    Ok(())
}

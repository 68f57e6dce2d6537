//! Update (refit): same topology, new vertex/AABB positions or instance definitions. Checks the
//! update rules visible here, rewrites primitive data, then recomputes node boxes bottom-up,
//! subtree by subtree in parallel (preorder layout: each subtree is a contiguous node range).
use super::encode::instances::{input_order_key, write_table};
use super::encode::quantize::quantize_node;
use super::geometry::{instance_bounds_of, sanitize, triangle_box, triangle_bounds, Aabb, BlasBoundsMemo};
use super::layout::carve;
use super::params::{PAR_REFIT_NODES, REFIT_BATCH, REFIT_CHUNK, REFIT_INSTANCE_CHUNK};
use super::primitive::{geometry_record, make_ref, total_primitives, FastTris};
use super::input::read_instance;
use super::layout::{self, InstanceRecord, Parsed, CHILD_INTERNAL, NODE_SIZE, PRIM_SIZE};
use super::{AsType, BuildDesc, BuildError, BuildFlags, BuildReport, DeviceView, GeometryData};
use bytemuck::Zeroable;
use glam::{Vec3, Vec3A};
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
        sanitize([d[0], d[1], d[2]], [d[3], d[4], d[5]])
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
    let total = total_primitives(desc)?;
    let is_tlas = raw.ty == AsType::TopLevel as u32;
    let need = layout::update_scratch_size(if is_tlas { AsType::TopLevel } else { AsType::BottomLevel }, total);
    if (scratch.len() as u64) < need {
        return Err(BuildError::ScratchTooSmall { needed: need, got: scratch.len() as u64 });
    }
    let n = raw.primitive_count as usize;
    let used = raw.used_size as usize;
    let dst = &mut dst[..used];

    // 1. New primitive data; every stored primitive must still be storable. A TLAS also keeps
    // each instance's new box for the node pass.
    let mut inst_boxes: &[[f32; 6]] = &[];
    if is_tlas {
        let (keys, rest) = carve::<u64>(scratch, n).ok_or(BuildError::ScratchTooSmall { needed: need, got: 0 })?;
        let (boxes, _) = carve::<[f32; 6]>(rest, n).ok_or(BuildError::ScratchTooSmall { needed: need, got: 0 })?;
        refit_instances(desc, view, &raw, dst, keys, boxes)?;
        inst_boxes = boxes;
    } else {
        refit_primitives(desc, &raw, dst)?;
    }

    let raw = layout::parse(dst).map(|p| p.raw).ok_or(BuildError::InvalidSource("structure"))?;
    // 2. Node boxes bottom-up, subtree by subtree: nodes are stored in preorder, so each
    // subtree is a contiguous range of nodes (checked on the way) and the children's ranges can
    // be refitted in parallel. The node section is the last one, so everything the leaves
    // read lies before it.
    let nc = raw.node_count as usize;
    let mut root = Aabb::EMPTY;
    if nc > 0 {
        let nodes_at = raw.nodes_offset as usize;
        let (head, tail) = dst.split_at_mut(nodes_at.min(used));
        let p = Parsed { raw, bytes: &*head };
        // The leaves' primitive kind, once, when every geometry of the BLAS has the same one
        // (Vulkan requires it; the library also accepts mixed ones, which take the per-primitive
        // lookup like a TLAS).
        let mut kinds = (0..raw.geometry_count).map(|g| p.geometry(g).map(|g| g.kind));
        let first = kinds.next().flatten();
        let kind = if is_tlas || first.is_none() || !kinds.all(|k| k == first) { None } else { first };
        let nodes = tail.get_mut(..nc * NODE_SIZE).ok_or(BuildError::InvalidSource("node"))?;
        let leaves = Leaves { kind, inst_boxes };
        root = refit_subtree(&p, &leaves, nodes, 0)?;
    }
    let mut h = raw;
    if n > 0 {
        h.bounds = [root.lo[0], root.lo[1], root.lo[2], root.hi[0], root.hi[1], root.hi[2]];
    }
    layout::write_header(dst, &h);
    super::checksum::seal(dst);
    Ok(BuildReport { used_size: raw.used_size, node_count: raw.node_count, leaf_count: raw.leaf_count, primitive_count: raw.primitive_count, clusters: None, top_planned: super::TopPlanned::No, forked_buckets: 0 })
}

/// BLAS: rewrites every stored primitive's data from the new input, in leaf order; every
/// stored primitive must still be storable.
fn refit_primitives(desc: &BuildDesc, raw: &layout::RawHeader, dst: &mut [u8]) -> Result<(), BuildError> {
    let n = raw.primitive_count as usize;
    let (head, tail) = dst.split_at_mut(raw.records_offset as usize);
    let prims = &mut head[raw.prims_offset as usize..raw.prims_offset as usize + n * PRIM_SIZE];
    let records = &tail[..n * layout::RECORD_SIZE];
    // Plain f32 triangles without a transform are read directly (`FastTris`); anything
    // else, and every error, through `read_triangle`.
    let fast: Vec<Option<FastTris>> = desc.geometries.iter().map(FastTris::of).collect();
    prims
        .par_chunks_mut(REFIT_CHUNK * PRIM_SIZE)
        .zip(records.par_chunks(REFIT_CHUNK * layout::RECORD_SIZE))
        .map(|(pd, rd)| {
            // In leaf order the reads jump around the input, and each triangle's index load
            // and then its vertex loads miss. A batch loads every record's indices first,
            // then the vertices, so a batch's misses overlap instead of each vertex load
            // waiting for its own index.
            for (rbatch, dbatch) in rd.chunks(REFIT_BATCH * layout::RECORD_SIZE).zip(pd.chunks_mut(REFIT_BATCH * PRIM_SIZE)) {
                let mut idx: [Option<[u32; 3]>; REFIT_BATCH] = [None; REFIT_BATCH];
                for (rb, ix) in rbatch.chunks_exact(layout::RECORD_SIZE).zip(idx.iter_mut()) {
                    let rec: layout::PrimRecord = bytemuck::pod_read_unaligned(rb);
                    *ix = fast.get(rec.geometry as usize).and_then(|f| f.as_ref()).and_then(|f| f.indices(rec.primitive));
                }
                for ((rb, ix), d) in rbatch.chunks_exact(layout::RECORD_SIZE).zip(idx).zip(dbatch.chunks_exact_mut(PRIM_SIZE)) {
                    let rec: layout::PrimRecord = bytemuck::pod_read_unaligned(rb);
                    let g = desc.geometries.get(rec.geometry as usize).ok_or(BuildError::InvalidSource("record"))?;
                    let mut data = [0f32; 9];
                    let fast_tri = ix.and_then(|ix| fast.get(rec.geometry as usize).and_then(|f| f.as_ref()).and_then(|f| f.positions(ix)));
                    if let Some([a, b, c]) = fast_tri {
                        if a.x.is_nan() || b.x.is_nan() || c.x.is_nan() {
                            return Err(mismatch("an active primitive became inactive"));
                        }
                        data = [a.x, a.y, a.z, b.x, b.y, b.z, c.x, c.y, c.z];
                    } else {
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
                    }
                    d.copy_from_slice(bytemuck::bytes_of(&data));
                }
            }
            Ok(())
        })
        .reduce(|| Ok(()), |a, b| a.and(b))
}


/// What the leaves of a refit read: the BLAS leaf kind when it is the same for all geometries,
/// and for a TLAS the instances' new boxes, in slot order (computed with the instance records).
struct Leaves<'a> {
    kind: Option<u32>,
    inst_boxes: &'a [[f32; 6]],
}

/// Refits the subtree whose nodes are `nodes` (node `base` first, its whole preorder range) and
/// returns its box. The internal children must be `base + 1` and then each the next node after
/// the previous child's range (what preorder storage gives); anything else is an invalid source.
fn refit_subtree(p: &Parsed, leaves: &Leaves, nodes: &mut [u8], base: usize) -> Result<Aabb, BuildError> {
    let order = BuildError::InvalidSource("node order");
    let total = nodes.len() / NODE_SIZE;
    let (me, rest) = nodes.split_at_mut(NODE_SIZE.min(nodes.len()));
    if me.len() < NODE_SIZE {
        return Err(BuildError::InvalidSource("node"));
    }
    let node: layout::WideNode = bytemuck::pod_read_unaligned(me);
    let cnt = (node.child_count as usize).min(4);
    // The children's node ranges, in child order.
    let mut starts = [usize::MAX; 4];
    let mut next = base + 1;
    for c in 0..cnt {
        if node.kind[c] == CHILD_INTERNAL {
            let ch = node.child[c] as usize;
            // The first internal child right after this node, each next one after the last.
            let first = starts[..c].iter().all(|&s| s == usize::MAX);
            if (first && ch != next) || ch < next || ch >= base + total {
                return Err(order);
            }
            starts[c] = ch;
            next = ch + 1;
        }
    }
    let mut parts: [Option<(&mut [u8], usize)>; 4] = [None, None, None, None];
    let mut rest = rest;
    let mut at = base + 1;
    for c in 0..cnt {
        if starts[c] == usize::MAX {
            continue;
        }
        // This child's range ends where the next internal child starts, or with the parent's.
        let end = starts[c + 1..cnt].iter().copied().find(|&s| s != usize::MAX).unwrap_or(base + total);
        let (mine, r) = std::mem::take(&mut rest).split_at_mut((end - at) * NODE_SIZE);
        rest = r;
        parts[c] = Some((mine, starts[c]));
        at = end;
    }
    let mut results: [Option<Result<Aabb, BuildError>>; 4] = [None, None, None, None];
    let big = total >= PAR_REFIT_NODES;
    if big {
        parts.par_iter_mut().zip(results.par_iter_mut()).for_each(|(part, res)| {
            if let Some((n, b)) = part.take() {
                *res = Some(refit_subtree(p, leaves, n, b));
            }
        });
    } else {
        for (part, res) in parts.iter_mut().zip(results.iter_mut()) {
            if let Some((n, b)) = part.take() {
                *res = Some(refit_subtree(p, leaves, n, b));
            }
        }
    }
    let mut clo = [Vec3A::ZERO; 4];
    let mut chi = [Vec3A::ZERO; 4];
    let (mut nlo, mut nhi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    for c in 0..cnt {
        let b = match node.kind[c] {
            CHILD_INTERNAL => results[c].take().unwrap_or(Err(BuildError::InvalidSource("node")))?,
            0 => Aabb::EMPTY,
            k => leaf_bounds_of(p, leaves, node.child[c], k as u32)?,
        };
        (clo[c], chi[c]) = (Vec3A::from(b.lo), Vec3A::from(b.hi));
        nlo = nlo.min(clo[c]);
        nhi = nhi.max(chi[c]);
    }
    let nb = Aabb { lo: nlo.to_array(), hi: nhi.to_array() };
    for c in cnt..4 {
        (clo[c], chi[c]) = (Vec3A::from(nb.lo), Vec3A::from(nb.lo));
    }
    let wn = quantize_node(&nb, &clo, &chi, cnt, &node.child[..cnt], &node.kind[..cnt]);
    me.copy_from_slice(bytemuck::bytes_of(&wn));
    Ok(nb)
}

/// `leaf_bounds` with the BLAS leaf kind known (`kind`), so no per-primitive record lookup;
/// None: `leaf_bounds`.
fn leaf_bounds_of(p: &Parsed, leaves: &Leaves, first: u32, count: u32) -> Result<Aabb, BuildError> {
    if p.is_tlas() {
        // TLAS: the boxes the instance pass computed, in slot order.
        let end = first.checked_add(count).ok_or(BuildError::InvalidSource("leaf range"))?;
        let bs = leaves.inst_boxes.get(first as usize..end as usize).ok_or(BuildError::InvalidSource("leaf range"))?;
        let mut b = Aabb::EMPTY;
        for x in bs {
            b.grow(&[x[0], x[1], x[2]], &[x[3], x[4], x[5]]);
        }
        return Ok(b);
    }
    let Some(kind) = leaves.kind else { return leaf_bounds(p, first, count) };
    if kind == layout::KIND_TRIANGLES {
        // One range check for the leaf, vertices straight into registers (`triangle_box`: the
        // same box `prim_bounds` gives).
        let o = (p.raw.prims_offset as usize).checked_add(first as usize * PRIM_SIZE).ok_or(BuildError::InvalidSource("leaf range"))?;
        if first.checked_add(count).is_none_or(|e| e > p.raw.primitive_count) {
            return Err(BuildError::InvalidSource("leaf range"));
        }
        let bytes = p.bytes.get(o..o + count as usize * PRIM_SIZE).ok_or(BuildError::InvalidSource("leaf range"))?;
        let (mut lo, mut hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
        for t in bytes.chunks_exact(PRIM_SIZE) {
            let Some((t, _)) = t.split_first_chunk::<36>() else { continue };
            let f = |i: usize| f32::from_le_bytes([t[4 * i], t[4 * i + 1], t[4 * i + 2], t[4 * i + 3]]);
            let (l, h) = triangle_box(Vec3A::new(f(0), f(1), f(2)), Vec3A::new(f(3), f(4), f(5)), Vec3A::new(f(6), f(7), f(8)));
            lo = lo.min(l);
            hi = hi.max(h);
        }
        return Ok(Aabb { lo: lo.to_array(), hi: hi.to_array() });
    }
    let mut b = Aabb::EMPTY;
    for s in first..first.saturating_add(count) {
        let d = p.prim(s).ok_or(BuildError::InvalidSource("leaf range"))?;
        let (lo, hi) = prim_bounds(&d, kind);
        b.grow(&lo, &hi);
    }
    Ok(b)
}

/// The lower-indexed of two errors (deterministic whatever the split of a parallel pass).
fn lowest_err(a: Result<(), (usize, BuildError)>, b: Result<(), (usize, BuildError)>) -> Result<(), (usize, BuildError)> {
    match (a, b) {
        (Err(x), Err(y)) => Err(if x.0 <= y.0 { x } else { y }),
        (Err(x), _) | (_, Err(x)) => Err(x),
        _ => Ok(()),
    }
}

/// BLAS leaf boxes with the kind looked up per primitive (geometries of mixed kinds).
fn leaf_bounds(p: &Parsed, first: u32, count: u32) -> Result<Aabb, BuildError> {
    let mut b = Aabb::EMPTY;
    for s in first..first.saturating_add(count) {
        let d = p.prim(s).ok_or(BuildError::InvalidSource("leaf range"))?;
        let g = p.record(s).and_then(|r| p.geometry(r.geometry)).ok_or(BuildError::InvalidSource("record"))?;
        let (lo, hi) = prim_bounds(&d, g.kind);
        b.grow(&lo, &hi);
    }
    Ok(b)
}

/// TLAS: rewrite instance records and the BLAS table from the new instance definitions.
fn refit_instances(desc: &BuildDesc, view: &dyn DeviceView, raw: &layout::RawHeader, dst: &mut [u8], keys: &mut [u64], boxes: &mut [[f32; 6]]) -> Result<(), BuildError> {
    let n = raw.primitive_count as usize;
    let rec_off = raw.records_offset as usize;
    let read_rec = |dst: &[u8], i: usize| -> Option<layout::PrimRecord> {
        let o = rec_off + i * layout::RECORD_SIZE;
        dst.get(o..o + layout::RECORD_SIZE).map(bytemuck::pod_read_unaligned)
    };
    let read = |dst: &[u8], i: usize| -> Result<super::input::InstanceDesc, BuildError> {
        let r = read_rec(dst, i).ok_or(BuildError::InvalidSource("record"))?;
        let g = desc.geometries.get(r.geometry as usize).ok_or(BuildError::InvalidSource("record"))?;
        read_instance(r.geometry, g, r.primitive, view)?.ok_or(mismatch("an active instance became inactive"))
    };
    // The BLAS table: one entry per stored instance in input order (as the build wrote it; the
    // active set cannot change), each from the instance's new reference. An unreadable
    // instance gets 0 here; the instance pass below reports it and a failed update leaves the
    // destination marked invalid.
    {
        let d: &[u8] = dst;
        let keys = keys.get_mut(..n).ok_or(BuildError::InvalidSource("record"))?;
        keys.par_iter_mut()
            .enumerate()
            .map(|(i, k)| {
                let r = read_rec(d, i).ok_or((i, BuildError::InvalidSource("record")))?;
                *k = input_order_key(r.geometry, r.primitive);
                Ok(())
            })
            .reduce(|| Ok(()), lowest_err)
            .map_err(|e| e.1)?;
        let table = raw.blas_table_offset as usize;
        let end = table + raw.blas_table_capacity as usize * 8;
        write_table(desc, view, keys, dst.get_mut(table..end).ok_or(BuildError::InvalidSource("BLAS table"))?);
    }
    let keys = &keys[..n];
    let (head, tail) = dst.split_at_mut(raw.instances_offset as usize);
    let head: &[u8] = head;
    tail.get_mut(..n * layout::INSTANCE_RECORD_SIZE)
        .ok_or(BuildError::InvalidSource("instances"))?
        .par_chunks_mut(REFIT_INSTANCE_CHUNK * layout::INSTANCE_RECORD_SIZE)
        .zip(boxes.get_mut(..n).ok_or(BuildError::InvalidSource("instances"))?.par_chunks_mut(REFIT_INSTANCE_CHUNK))
        .enumerate()
        .map(|(ci, (out, bx))| {
            let mut memo = BlasBoundsMemo::new();
            for (k, (o, bo)) in out.chunks_exact_mut(layout::INSTANCE_RECORD_SIZE).zip(bx.iter_mut()).enumerate() {
                let i = ci * REFIT_INSTANCE_CHUNK + k;
                let inst = read(head, i).map_err(|e| (i, e))?;
                let (lo, hi) = instance_bounds_of(&inst.transform, memo.get(inst.reference, view));
                *bo = [lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]];
                let r = read_rec(head, i).ok_or((i, BuildError::InvalidSource("record")))?;
                let mut rec = InstanceRecord::zeroed();
                rec.object_to_world = inst.transform;
                rec.world_to_object = super::input::invert_transform(&inst.transform);
                rec.custom_index = inst.custom_index;
                rec.mask = inst.mask;
                rec.sbt_offset = inst.sbt_offset;
                rec.flags = inst.flags;
                rec.instance_index = r.primitive;
                rec.blas_index = keys.binary_search(&input_order_key(r.geometry, r.primitive)).map_or(u32::MAX, |x| x as u32);
                o.copy_from_slice(bytemuck::bytes_of(&rec));
            }
            Ok(())
        })
        .reduce(|| Ok(()), lowest_err)
        .map_err(|e| e.1)?;
    Ok(())
}

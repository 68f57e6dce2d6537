//! Workloads through Vulkan on the device queue: builds (PREFER_FAST_TRACE, PREFER_FAST_BUILD),
//! refit updates, compaction copies and indirect builds, timed by queue timestamps where the
//! queue has them.
use ash::vk;

use super::inputs::{build_sizes, device_target, Inputs};
use super::{Options, RenderData, Row, Scene, SceneKind, Stats, Workload};
use crate::vkctx::{payload, Arena, Gpu, Place};

pub(super) fn fill_times(row: &mut Row, times: &[(Option<f64>, f64)]) {
    let wall: Vec<f64> = times.iter().map(|t| t.1).collect();
    let ts: Vec<f64> = times.iter().filter_map(|t| t.0).collect();
    row.wall = Stats::of(&wall);
    if ts.len() == times.len() && !ts.is_empty() && ts.iter().all(|&t| t > 0.0) {
        row.time = Stats::of(&ts);
        row.timing = "timestamp";
    } else {
        row.time = row.wall;
        row.timing = "fence";
    }
}

fn metrics_into(a: &Arena, s: vk::AccelerationStructureKHR, row: &mut Row) -> Result<Vec<u8>, String> {
    let ser = a.serialize(s)?;
    let p = payload(&ser).ok_or("serialization shorter than its header")?;
    match arbor::accel::metrics(p) {
        Some(m) => {
            row.sah = Some(m.sah_cost as f64);
            row.nodes = Some(m.node_count as u64);
            row.leaves = Some(m.leaf_count as u64);
        }
        None => row.note = "serialized payload is not an Arbor structure".into(),
    }
    Ok(p.to_vec())
}

fn flags_of(w: Workload) -> vk::BuildAccelerationStructureFlagsKHR {
    match w {
        Workload::FastBuild => vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD,
        _ => vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE,
    }
}

pub(super) fn device_build(
    gpu: &Gpu,
    inp: &Inputs,
    w: Workload,
    opts: &Options,
    row: &mut Row,
    render: Option<&mut Option<RenderData>>,
    scene: &Scene,
) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [inp.geom];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(flags_of(w) | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let (sizes, s, info) = device_target(&a, inp, info)?;
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(inp.count)];
    let times = gpu.timed(opts.warmup, opts.repeat, |cb| {
        // SAFETY: valid infos; buffers live until `timed` has waited.
        unsafe { gpu.ext.cmd_build_acceleration_structures(cb, &[info], &[&range]) };
    })?;
    fill_times(row, &times);
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.build_scratch_size;
    row.compacted_size = Some(a.query(s, vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR)?);
    if opts.metrics {
        let top = metrics_into(&a, s, row)?;
        if let Some(slot) = render {
            let meshes = match &scene.kind {
                SceneKind::Mesh(m) => vec![m.clone()],
                SceneKind::Instances { blases, .. } => blases.clone(),
            };
            // The BLASes built by `prepare`, serialized, keyed by the addresses the TLAS references.
            let mut blases = Vec::new();
            for (&h, &addr) in inp.blas_handles.iter().zip(&inp.blas_addresses) {
                let ser = a.serialize(h)?;
                blases.push((addr, payload(&ser).ok_or("short serialization")?.to_vec()));
            }
            *slot = Some(RenderData { top, blases, meshes, records: inp.records.clone() });
        }
    }
    Ok(())
}

pub(super) fn update(gpu: &Gpu, inp: &Inputs, opts: &Options, row: &mut Row) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [inp.geom];
    let flags = vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE | vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE;
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(flags)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let sizes = build_sizes(gpu, vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, inp.count);
    let (s, _) = a.structure(inp.ty, sizes.acceleration_structure_size, Place::Device)?;
    let scratch = a.buffer(sizes.build_scratch_size.max(sizes.update_scratch_size), Place::Device)?;
    let sd = vk::DeviceOrHostAddressKHR { device_address: scratch.address };
    let build = info.dst_acceleration_structure(s).scratch_data(sd);
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(inp.count)];
    gpu.submit(|cb| {
        // SAFETY: valid infos; buffers live until the wait.
        unsafe { gpu.ext.cmd_build_acceleration_structures(cb, &[build], &[&range]) };
    })?;
    let moved = [inp.moved];
    let upd = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(flags)
        .mode(vk::BuildAccelerationStructureModeKHR::UPDATE)
        .geometries(&moved)
        .src_acceleration_structure(s)
        .dst_acceleration_structure(s)
        .scratch_data(sd);
    let times = gpu.timed(opts.warmup, opts.repeat, |cb| {
        // SAFETY: valid infos (in-place update of a structure built with ALLOW_UPDATE).
        unsafe { gpu.ext.cmd_build_acceleration_structures(cb, &[upd], &[&range]) };
    })?;
    fill_times(row, &times);
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.update_scratch_size;
    row.note = "in place, moved input".into();
    Ok(())
}

pub(super) fn compact(gpu: &Gpu, inp: &Inputs, opts: &Options, row: &mut Row) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [inp.geom];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let (sizes, s, info) = device_target(&a, inp, info)?;
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(inp.count)];
    gpu.submit(|cb| {
        // SAFETY: valid infos; buffers live until the wait.
        unsafe { gpu.ext.cmd_build_acceleration_structures(cb, &[info], &[&range]) };
    })?;
    let compacted = a.query(s, vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR)?;
    let (c, _) = a.structure(inp.ty, compacted, Place::Device)?;
    let times = gpu.timed(opts.warmup, opts.repeat, |cb| {
        let ci = vk::CopyAccelerationStructureInfoKHR::default().src(s).dst(c).mode(vk::CopyAccelerationStructureModeKHR::COMPACT);
        // SAFETY: valid structures; dst has the compacted size.
        unsafe { gpu.ext.cmd_copy_acceleration_structure(cb, &ci) };
    })?;
    fill_times(row, &times);
    row.as_size = sizes.acceleration_structure_size;
    row.compacted_size = Some(compacted);
    row.scratch_size = 0;
    row.note = "copy COMPACT of the fast-trace structure".into();
    Ok(())
}

pub(super) fn indirect(gpu: &Gpu, inp: &Inputs, opts: &Options, row: &mut Row) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [inp.geom];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let (sizes, s, info) = device_target(&a, inp, info)?;
    let mut record = [0u8; 16];
    record[..4].copy_from_slice(&inp.count.to_le_bytes());
    let rec = a.upload(&record)?;
    let max = [inp.count];
    let times = gpu.timed(opts.warmup, opts.repeat, |cb| {
        // SAFETY: valid infos; the range record lives in `rec`.
        unsafe { gpu.ext.cmd_build_acceleration_structures_indirect(cb, &[info], &[rec.address], &[16], &[&max]) };
    })?;
    fill_times(row, &times);
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.build_scratch_size;
    row.compacted_size = Some(a.query(s, vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR)?);
    Ok(())
}

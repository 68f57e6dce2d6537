//! Host builds through Vulkan (vkBuildAccelerationStructuresKHR): plain, and deferred operations
//! joined by threads started once per workload.
use std::time::Instant;

use ash::vk;

use super::inputs::{build_sizes, host, instances, triangles, Inputs};
use super::{Options, Row, Stats};
use crate::vkctx::{Arena, Gpu, Place};

pub(super) fn host_build(gpu: &Gpu, inp: &Inputs, deferred: bool, opts: &Options, row: &mut Row) -> Result<(), String> {
    let a = Arena::new(gpu);
    let geoms = [if inp.ty == vk::AccelerationStructureTypeKHR::TOP_LEVEL {
        instances(host(&inp.host_instances))
    } else {
        triangles(host(&inp.host_vertices), host(&inp.host_indices), inp.max_vertex)
    }];
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(inp.ty)
        .flags(vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION)
        .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
        .geometries(&geoms);
    let sizes = build_sizes(gpu, vk::AccelerationStructureBuildTypeKHR::HOST, &info, inp.count);
    let (s, _) = a.structure(inp.ty, sizes.acceleration_structure_size, Place::Host)?;
    let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
    let info = info
        .dst_acceleration_structure(s)
        .scratch_data(vk::DeviceOrHostAddressKHR { host_address: scratch.as_mut_ptr().cast() });
    let range = [vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(inp.count)];
    let mut times = Vec::new();
    // Deferred builds are joined by `joiners` threads started once for the workload (as an
    // application's job system would be), not per build: the timing then covers the driver's
    // deferred operation and its shared work, not thread creation.
    std::thread::scope(|sc| -> Result<(), String> {
        let joiners = deferred.then(|| Joiners::start(sc, gpu, opts.joiners.max(1)));
        for k in 0..opts.warmup + opts.repeat {
            let t0 = Instant::now();
            if let Some(j) = &joiners {
                join_deferred(gpu, &info, &range, j)?;
            } else {
                // SAFETY: valid infos; host memory alive for the call.
                unsafe { gpu.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[info], &[&range]) }
                    .map_err(|e| format!("vkBuildAccelerationStructuresKHR: {e}"))?;
            }
            let ms = t0.elapsed().as_secs_f64() * 1e3;
            if k >= opts.warmup {
                times.push(ms);
            }
        }
        Ok(())
    })?;
    drop(scratch);
    row.time = Stats::of(&times);
    row.wall = row.time;
    row.timing = "host";
    row.as_size = sizes.acceleration_structure_size;
    row.scratch_size = sizes.build_scratch_size;
    let mut v = [0u8; 8];
    // SAFETY: valid structure built with ALLOW_COMPACTION; one u64.
    unsafe {
        gpu.ext
            .write_acceleration_structures_properties(&[s], vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR, &mut v, 8)
            .map_err(|e| format!("vkWriteAccelerationStructuresPropertiesKHR: {e}"))?;
    }
    row.compacted_size = Some(u64::from_le_bytes(v));
    if deferred {
        row.note = format!("deferred, joined by {} threads (started once)", opts.joiners.max(1));
    }
    Ok(())
}

/// Threads that join the deferred operations handed to them (`run`), started once.
struct Joiners {
    ops: Vec<std::sync::mpsc::Sender<u64>>,
    done: std::sync::mpsc::Receiver<()>,
}

impl Joiners {
    fn start<'s>(sc: &'s std::thread::Scope<'s, '_>, gpu: &Gpu, n: usize) -> Joiners {
        let dev = gpu.device.handle();
        let join = gpu.deferred.fp().deferred_operation_join_khr;
        let (done_tx, done) = std::sync::mpsc::channel();
        let ops = (0..n)
            .map(|_| {
                let (tx, rx) = std::sync::mpsc::channel::<u64>();
                let done_tx = done_tx.clone();
                sc.spawn(move || {
                    // Until `Joiners` is dropped: join each operation until it has no more work.
                    for raw in rx {
                        let op = <vk::DeferredOperationKHR as vk::Handle>::from_raw(raw);
                        // SAFETY: a live deferred operation of `dev` (destroyed only after every
                        // joiner reported back).
                        while unsafe { join(dev, op) } == vk::Result::THREAD_IDLE_KHR {}
                        let _ = done_tx.send(());
                    }
                });
                tx
            })
            .collect();
        Joiners { ops, done }
    }

    /// Every thread joins `op`; returns when all of them have come back.
    fn run(&self, op: vk::DeferredOperationKHR) {
        let raw = vk::Handle::as_raw(op);
        let sent = self.ops.iter().filter(|tx| tx.send(raw).is_ok()).count();
        for _ in 0..sent {
            let _ = self.done.recv();
        }
    }
}

/// vkBuildAccelerationStructuresKHR under a deferred operation joined by `joiners`.
fn join_deferred(
    gpu: &Gpu,
    info: &vk::AccelerationStructureBuildGeometryInfoKHR,
    range: &[vk::AccelerationStructureBuildRangeInfoKHR],
    joiners: &Joiners,
) -> Result<(), String> {
    // SAFETY: valid infos; host memory outlives the operation (joined before returning).
    unsafe {
        let op = gpu.deferred.create_deferred_operation(None).map_err(|e| format!("vkCreateDeferredOperationKHR: {e}"))?;
        let ranges = [range.as_ptr()];
        let r = (gpu.ext.fp().build_acceleration_structures_khr)(gpu.device.handle(), op, 1, info, ranges.as_ptr());
        let result = match r {
            vk::Result::OPERATION_DEFERRED_KHR => {
                joiners.run(op);
                gpu.deferred.get_deferred_operation_result(op).map_err(|e| format!("deferred build: {e}"))
            }
            vk::Result::OPERATION_NOT_DEFERRED_KHR | vk::Result::SUCCESS => Ok(()),
            e => Err(format!("vkBuildAccelerationStructuresKHR (deferred): {e}")),
        };
        gpu.deferred.destroy_deferred_operation(op, None);
        result
    }
}

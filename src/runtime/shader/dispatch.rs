//! vkCmdDispatch, vkCmdDispatchBase and vkCmdDispatchIndirect as executed: the [`Dispatch`]
//! command resolves the bound descriptors, reads an indirect record, runs the library's
//! `dispatch` on the worker pool under the watchdog, and turns what the library contained
//! (faults, a stop) into diagnostics and, for a stop, a lost device.
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use crate::diag;
use crate::memory::Buffer;
use crate::runtime::command::{Exec, ExecContext, ExecError};
use crate::shader::{self as lib, FaultKind, FaultSpace};

use super::memory::{DispatchMemory, Unresolved};
use super::{BoundSet, ComputePipeline};

/// Watchdog default: long enough for any honest test dispatch on a slow machine, short enough
/// that a hung CI job fails in seconds rather than at its own timeout.
const DEFAULT_WATCHDOG_SECONDS: f64 = 10.0;

/// `ARBOR_WATCHDOG_SECONDS`, read once: how long one dispatch may run before the device is
/// marked lost.
pub fn watchdog_seconds() -> f64 {
    static S: OnceLock<f64> = OnceLock::new();
    *S.get_or_init(|| {
        std::env::var("ARBOR_WATCHDOG_SECONDS")
            .ok()
            .and_then(|v| v.trim().parse::<f64>().ok())
            .filter(|s| s.is_finite() && *s > 0.0)
            .unwrap_or(DEFAULT_WATCHDOG_SECONDS)
    })
}

/// How many workgroups a dispatch runs.
pub enum DispatchSize {
    /// vkCmdDispatch (base 0) and vkCmdDispatchBase.
    Direct { groups: [u32; 3], base: [u32; 3] },
    /// vkCmdDispatchIndirect: a VkDispatchIndirectCommand read when the command executes.
    Indirect { buffer: Arc<Buffer>, offset: u64 },
}

/// A recorded dispatch: the compute state as it was bound, and its size.
pub struct Dispatch {
    pub name: &'static str,
    pub pipeline: Arc<ComputePipeline>,
    pub sets: Vec<Option<BoundSet>>,
    pub push_constants: Vec<u8>,
    pub size: DispatchSize,
    /// maxComputeWorkGroupCount (indirect records are checked against it when read).
    pub max_groups: [u32; 3],
}

impl Dispatch {
    fn groups(&self) -> Result<([u32; 3], [u32; 3]), ExecError> {
        match &self.size {
            DispatchSize::Direct { groups, base } => Ok((*groups, *base)),
            DispatchSize::Indirect { buffer, offset } => {
                let mut record = [0u8; 12];
                buffer.read(*offset, &mut record)?;
                let g = [0, 1, 2].map(|i| u32::from_le_bytes(record[4 * i..4 * i + 4].try_into().unwrap_or_default()));
                if let Some(i) = (0..3).find(|&i| g[i] > self.max_groups[i]) {
                    let axis = ["x", "y", "z"][i];
                    return Err(ExecError::Invalid {
                        vuid: ["VUID-VkDispatchIndirectCommand-x-00417", "VUID-VkDispatchIndirectCommand-y-00418", "VUID-VkDispatchIndirectCommand-z-00419"][i],
                        message: format!("the indirect record's {axis} = {} exceeds maxComputeWorkGroupCount {}; dispatch skipped", g[i], self.max_groups[i]),
                    });
                }
                Ok((g, [0; 3]))
            }
        }
    }

    fn report_unresolved(&self, missing: &[((u32, u32), Unresolved)]) {
        for ((set, binding), why) in missing {
            let (vuid, what) = match why {
                Unresolved::NotBound => ("VUID-vkCmdDispatch-None-08600", "no descriptor set bound there (or the set has no such binding)"),
                Unresolved::Empty => ("VUID-vkCmdDispatch-None-08114", "the descriptor was never written or its buffer was destroyed"),
                Unresolved::PastEnd { .. } => ("VUID-vkCmdBindDescriptorSets-pDynamicOffsets-01979", "the dynamic offset moves the range past the buffer's end"),
                Unresolved::Image => ("VUID-vkCmdDispatch-None-08114", "an image descriptor that is no usable storage image (a sampler or sampled image, a destroyed view or image, or no memory bound)"),
            };
            diag::vuid(vuid, self.name, &format!("set {set} binding {binding}: {what}; the shader's accesses to it are contained"));
        }
    }
}

/// The rule a contained fault broke, for its diagnostic.
fn fault_rule(kind: FaultKind, space: FaultSpace) -> &'static str {
    match (kind, space) {
        (_, FaultSpace::DeviceAddress) => {
            "VUID-RuntimeSpirv-PhysicalStorageBuffer64-04708 (a PhysicalStorageBuffer access must lie inside a live buffer)"
        }
        (FaultKind::Unbound, _) => "VUID-vkCmdDispatch-None-08114 (the binding has no valid descriptor)",
        (FaultKind::ArrayIndex, _) => {
            "VUID-vkCmdDispatch-None-10068 (a descriptor-array index must be less than the array's length; the access is discarded)"
        }
        (_, FaultSpace::Binding { .. } | FaultSpace::ArrayElement { .. }) => "robustBufferAccess (out of the descriptor's range: reads return zero, writes are discarded)",
        _ => "robustness (out of the block: reads return zero, writes are discarded)",
    }
}

impl Exec for Dispatch {
    fn name(&self) -> &'static str {
        self.name
    }

    fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        let (groups, base) = self.groups()?;
        if groups.contains(&0) {
            return Ok(());
        }
        let pipeline = &self.pipeline.pipeline;
        let used: Vec<(u32, u32)> = pipeline.bindings().iter().map(|b| (b.set, b.binding)).collect();
        let (memory, missing) = DispatchMemory::new(ctx.memory(), &self.sets, &used);
        self.report_unresolved(&missing);
        let mut push = self.push_constants.clone();
        if push.len() < pipeline.push_constant_size as usize {
            push.resize(pipeline.push_constant_size as usize, 0);
        }
        let seconds = watchdog_seconds();
        // vkDestroyDevice raises the queue's cancel flag; a lost device sets its flag: either
        // stops a running dispatch within a few thousand blocks, not at the deadline.
        let flags = [ctx.cancel, &ctx.device.lost];
        let watchdog = lib::Watchdog { deadline: Some(Instant::now() + Duration::from_secs_f64(seconds)), stop_flags: &flags, ..Default::default() };
        let invocations = groups.iter().chain(&pipeline.local_size).map(|&n| n as u64).product::<u64>();
        let small = invocations <= 4 * lib::LANES as u64;
        let report = crate::threads::run_parallel(small, || lib::dispatch(pipeline, &memory, &push, groups, base, &watchdog));
        if let Some(first) = report.faults.first() {
            diag::report(
                diag::Level::Error,
                self.name,
                &format!("[{}] {} contained memory fault(s); first: {first}", fault_rule(first.kind, first.space), report.fault_count),
            );
        }
        if let Some(f) = report.unresolved_instance {
            // One line per dispatch: every ray through that instance meets the same reference.
            diag::report(
                diag::Level::Error,
                self.name,
                &format!(
                    "[an instance's accelerationStructureReference must name a built bottom-level structure while the top-level one is traced \
                     (VUID-vkCmdBuildAccelerationStructuresKHR-pInfos-12281); the CLASes a cluster BLAS was built from must stay live and unmoved] a ray query \
                     met a reference to {:#x}, which is no built bottom-level structure or CLAS (destroyed, moved or rebuilt since the \
                     build that referenced it?); that instance or cluster was treated as absent \
                     (first met by workgroup {:?}, invocation {}; reported once per dispatch)",
                    f.at, f.workgroup, f.invocation
                ),
            );
        }
        match report.stopped {
            Some(lib::Stop::Cancelled) => diag::report(
                diag::Level::Warn,
                self.name,
                "dispatch stopped before it finished: the device is being destroyed or was lost",
            ),
            Some(_) => {
                diag::report(
                    diag::Level::Error,
                    self.name,
                    &format!("the shader did not finish within {seconds} s (ARBOR_WATCHDOG_SECONDS); stopped, device lost"),
                );
                ctx.device.mark_lost();
            }
            None => {}
        }
        Ok(())
    }
}

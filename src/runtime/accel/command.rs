//! The acceleration-structure commands as the runtime runs them: the recorded commands a
//! queue's worker executes ([`BuildCommand`], [`CopyCommand`], [`WritePropertiesCommand`], each
//! an [`Exec`]), and the host commands, run now on the calling thread or under a deferred
//! operation ([`build_on_host`], [`copy_on_host`]).
//!
//! This module owns when and on which thread a command runs; what it does is `build`'s,
//! `copy`'s and `query`'s. It sees no raw pointer: host commands arrive with the `HostMemory`
//! the dispatch layer vouched for.
use std::sync::Arc;

use ash::vk;

use super::inputs::{DeviceInputs, HostInputs, StructureLookup};
use super::{execute_builds, execute_copy, property, AccelerationStructure, BuildInfo, Copy, DeviceLost, GeometryDesc, Ranges};
use crate::diag;
use crate::memory::region::HostMemory;
use crate::runtime::command::{CommandBuffer, Exec, ExecContext, ExecError};
use crate::runtime::in_use::Collector;
use crate::runtime::deferred::DeferredOperation;
use crate::runtime::query::QueryPool;
use crate::runtime::Device;

/// Which build command was recorded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BuildKind {
    /// vkCmdBuildAccelerationStructuresKHR: range records given at record time.
    Direct,
    /// vkCmdBuildAccelerationStructuresIndirectKHR: range records read when it executes.
    Indirect,
}

impl BuildKind {
    pub fn command(self) -> &'static str {
        match self {
            BuildKind::Direct => "vkCmdBuildAccelerationStructuresKHR",
            BuildKind::Indirect => "vkCmdBuildAccelerationStructuresIndirectKHR",
        }
    }
}

/// A recorded build command: its builds run when the queue executes it.
pub struct BuildCommand {
    pub kind: BuildKind,
    pub infos: Vec<BuildInfo>,
}

impl Exec for BuildCommand {
    fn name(&self) -> &'static str {
        self.kind.command()
    }
    fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        if self.kind == BuildKind::Indirect && !ctx.device.features.acceleration_structure_indirect_build {
            diag::vuid(
                "VUID-vkCmdBuildAccelerationStructuresIndirectKHR-accelerationStructureIndirectBuild-03650",
                self.name(),
                "the accelerationStructureIndirectBuild feature is not enabled",
            );
        }
        let inputs = DeviceInputs::new(ctx.memory(), self.name());
        execute_builds(&inputs, &self.infos).map_err(|_| ExecError::Invalid {
            vuid: "strict",
            message: "an acceleration-structure build broke a valid-usage rule (ARBOR_STRICT)".into(),
        })
    }
    fn uses(&self, c: &mut Collector<'_>) {
        for info in &self.infos {
            for s in info.src.iter().chain(&info.dst) {
                c.structure(s);
            }
            c.address(info.scratch);
            for g in &info.geometries {
                match &g.desc {
                    GeometryDesc::Triangles { vertex_data, index_data, transform_data, .. } => {
                        for a in [vertex_data, index_data, transform_data] {
                            c.address(*a);
                        }
                    }
                    GeometryDesc::Aabbs { data, .. } | GeometryDesc::Instances { data, .. } => c.address(*data),
                    GeometryDesc::Unsupported(_) => {}
                }
            }
            if let Ranges::Indirect { address, .. } = &info.ranges {
                c.address(*address);
            }
        }
    }
}

impl Copy {
    /// The command that makes this copy: the recorded one, or the host one (`host`).
    pub fn command(&self, host: bool) -> &'static str {
        match (self, host) {
            (Copy::Structure { .. }, false) => "vkCmdCopyAccelerationStructureKHR",
            (Copy::Structure { .. }, true) => "vkCopyAccelerationStructureKHR",
            (Copy::ToMemory { .. }, false) => "vkCmdCopyAccelerationStructureToMemoryKHR",
            (Copy::ToMemory { .. }, true) => "vkCopyAccelerationStructureToMemoryKHR",
            (Copy::FromMemory { .. }, false) => "vkCmdCopyMemoryToAccelerationStructureKHR",
            (Copy::FromMemory { .. }, true) => "vkCopyMemoryToAccelerationStructureKHR",
        }
    }
}

/// A recorded copy (structure ↔ structure, to memory, from memory by device address).
pub struct CopyCommand {
    pub op: Copy,
}

impl Exec for CopyCommand {
    fn name(&self) -> &'static str {
        self.op.command(false)
    }
    fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        let inputs = DeviceInputs::new(ctx.memory(), self.name());
        execute_copy(&inputs, &self.op).map_err(|_| ExecError::Invalid {
            vuid: "strict",
            message: "an acceleration-structure copy broke a valid-usage rule (ARBOR_STRICT)".into(),
        })
    }
    fn uses(&self, c: &mut Collector<'_>) {
        match &self.op {
            Copy::Structure { src, dst, .. } => {
                for s in src.iter().chain(dst) {
                    c.structure(s);
                }
            }
            Copy::ToMemory { src, dst, .. } => {
                src.iter().for_each(|s| c.structure(s));
                c.address(*dst);
            }
            Copy::FromMemory { src, dst, .. } => {
                c.address(*src);
                dst.iter().for_each(|s| c.structure(s));
            }
        }
    }
}

/// Recorded vkCmdWriteAccelerationStructuresPropertiesKHR.
pub struct WritePropertiesCommand {
    pub structures: Vec<Option<Arc<AccelerationStructure>>>,
    pub query_type: vk::QueryType,
    pub pool: Arc<QueryPool>,
    pub first: u32,
}

impl WritePropertiesCommand {
    /// Records the command into `cb` once the query pool's rules are checked for the `count`
    /// queries from `first` (a violation is reported and nothing recorded).
    pub fn record(
        cb: &CommandBuffer,
        structures: Vec<Option<Arc<AccelerationStructure>>>,
        query_type: vk::QueryType,
        pool: Option<Arc<QueryPool>>,
        (first, count): (u32, u32),
    ) {
        const CMD: &str = "vkCmdWriteAccelerationStructuresPropertiesKHR";
        let Some(pool) = pool else {
            diag::vuid(&format!("VUID-{CMD}-queryPool-parameter"), CMD, "not a valid query pool");
            return;
        };
        if pool.query_type != query_type {
            diag::vuid(&format!("VUID-{CMD}-queryPool-02493"), CMD, "queryPool was created with another queryType");
            return;
        }
        if pool.check_range(first, count).is_err() {
            diag::vuid(&format!("VUID-{CMD}-query-04880"), CMD, "firstQuery + accelerationStructureCount exceeds the pool");
            return;
        }
        cb.record_custom(Box::new(WritePropertiesCommand { structures, query_type, pool, first }));
    }
}

impl Exec for WritePropertiesCommand {
    fn name(&self) -> &'static str {
        "vkCmdWriteAccelerationStructuresPropertiesKHR"
    }
    /// Every query of the command becomes available, whatever the structure held: an invalid
    /// one (reported by `property`) gets 0, so a host WAIT on it returns instead of hanging.
    fn execute(&self, _ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        let mut invalid = false;
        for (i, s) in self.structures.iter().enumerate() {
            let value = property(s.as_deref(), self.query_type, self.name(), i);
            invalid |= value.is_none();
            self.pool.write(self.first + i as u32, value.unwrap_or(0));
        }
        if invalid && diag::strict() {
            return Err(ExecError::Invalid { vuid: "strict", message: "invalid property query (ARBOR_STRICT)".into() });
        }
        Ok(())
    }
    fn uses(&self, c: &mut Collector<'_>) {
        self.structures.iter().flatten().for_each(|s| c.structure(s));
    }
}

/// When a host command runs: its `deferredOperation` argument.
pub enum Deferral {
    /// VK_NULL_HANDLE: now, on the calling thread.
    Now,
    /// Under this deferred operation: when threads join it.
    On(Arc<DeferredOperation>),
    /// A handle that names no deferred operation.
    Unknown,
}

/// `vkBuildAccelerationStructuresKHR`: the builds of `infos`, reading host memory through
/// `host` and instance handles through `lookup`.
pub fn build_on_host(device: &Arc<Device>, deferral: Deferral, host: HostMemory, lookup: StructureLookup, infos: Vec<BuildInfo>) -> vk::Result {
    const CMD: &str = "vkBuildAccelerationStructuresKHR";
    let work = host_work(device, host, lookup, CMD, move |inputs| execute_builds(inputs, &infos));
    // Run now, the calling thread first becomes the one worker of a private pool
    // (`threads::run_here`): builds that `build::Placement` keeps here then run on this thread
    // alone, and larger ones go to Arbor's pool from it, as from a queue worker.
    run_host(device, deferral, CMD, work, crate::threads::run_here)
}

/// The host copy commands (`vkCopyAccelerationStructureKHR`, `…ToMemoryKHR`, `…FromMemoryKHR`),
/// whose memory side is a host pointer read or written through `host`.
pub fn copy_on_host(device: &Arc<Device>, deferral: Deferral, host: HostMemory, lookup: StructureLookup, op: Copy) -> vk::Result {
    let name = op.command(true);
    let work = host_work(device, host, lookup, name, move |inputs| execute_copy(inputs, &op));
    // Run now, a copy goes to Arbor's pool from the calling thread (`execute_copy`).
    run_host(device, deferral, name, work, |work| work())
}

type HostWork = Box<dyn FnOnce() -> vk::Result + Send>;

/// A host command's work: `execute` over the command's host inputs, its result as the
/// command's (VK_ERROR_DEVICE_LOST in strict mode when something was invalid).
fn host_work(
    device: &Arc<Device>,
    host: HostMemory,
    lookup: StructureLookup,
    command: &'static str,
    execute: impl FnOnce(&HostInputs) -> Result<(), DeviceLost> + Send + 'static,
) -> HostWork {
    let device = device.clone();
    Box::new(move || {
        // Host work counts as activity: a thread waiting on a fence this thread submits next
        // must not take the build for a stall.
        let _executing = crate::runtime::stall::running();
        let inputs = HostInputs::new(host, &device.memory, lookup, command);
        match execute(&inputs) {
            Ok(()) => vk::Result::SUCCESS,
            Err(DeviceLost) => vk::Result::ERROR_DEVICE_LOST,
        }
    })
}

/// Run `work` under `deferral`: now through `now`, or on a deferred operation's joiners.
fn run_host(device: &Device, deferral: Deferral, command: &str, work: HostWork, now: impl FnOnce(HostWork) -> vk::Result) -> vk::Result {
    if !device.features.acceleration_structure_host_commands {
        diag::vuid(
            &format!("VUID-{command}-accelerationStructureHostCommands-03581"),
            command,
            "the accelerationStructureHostCommands feature is not enabled",
        );
    }
    match deferral {
        Deferral::Now => now(work),
        Deferral::Unknown => {
            diag::vuid(&format!("VUID-{command}-deferredOperation-parameter"), command, "not a valid deferred operation");
            vk::Result::ERROR_UNKNOWN
        }
        Deferral::On(op) if op.is_pending() => {
            diag::vuid(&format!("VUID-{command}-deferredOperation-03678"), command, "the previous deferred operation is not complete");
            vk::Result::ERROR_UNKNOWN
        }
        Deferral::On(op) => op.defer(crate::threads::configured_threads(), work),
    }
}

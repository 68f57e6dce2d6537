//! Command pools and command buffers: recording, with the checks recording can make. The
//! recorded [`Command`]s and the executor that runs them on a queue's worker thread are in
//! `execute` (re-exported here).
//!
//! Recording checks what it can see (VUIDs reported through `diag`, the offending command is
//! not recorded) and stores a [`Command`] that owns deep copies of its arguments and `Arc`s of
//! the objects it names, so nothing recorded points into application memory (DESIGN.md,
//! principle 3 and lavapipe's vk_cmd_enqueue lesson). Ending a recording freezes it into an
//! `Arc<Recording>`; a submission holds that `Arc`, so re-recording or freeing a buffer the
//! application still has pending is diagnosed but can never make the worker read freed state.
//!
//! Extension point: a command that does not fit the built-in variants (acceleration-structure
//! builds, copies, property writes) implements [`Exec`] and is recorded with
//! [`CommandBuffer::record_custom`]; the executor calls [`Exec::execute`] with an
//! [`ExecContext`] (device memory, timestamps, cancellable waits, the rayon pool via
//! `crate::threads`). Returning `Err` reports the failure, skips the command and goes on (or
//! loses the device in strict mode). Query results (compacted size, serialization size…) are
//! written with [`QueryPool::write`], which makes the query available.
//!
//! (Not a doc test: `cargo test --release --workspace` cannot link doc tests here; the same
//! pattern is compiled and run by `runtime::queue::tests`.)
//!
//! ```ignore
//! use arbor::runtime::command::{Exec, ExecContext, ExecError};
//!
//! /// Everything the command needs, owned (deep copies, `Arc`s): nothing points into the
//! /// application's memory once recording returns.
//! struct WriteMarker {
//!     address: u64,
//! }
//!
//! impl Exec for WriteMarker {
//!     fn name(&self) -> &'static str {
//!         "vkCmdExampleMarker"
//!     }
//!     fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError> {
//!         // Device memory is read and written when the queue runs the command, through the
//!         // checked address space; a refused access becomes a diagnostic, not a crash.
//!         ctx.memory().write(self.address, &ctx.timestamp().to_le_bytes())?;
//!         Ok(())
//!     }
//! }
//! // Recording (in the dispatch function of the command):
//! // command_buffer.record_custom(Box::new(WriteMarker { address }));
//! ```
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak};

use ash::vk;

use super::query::{QueryKind, QueryPool, RangeError, ReadFlags};
use super::sync::Event;
use crate::diag;
use crate::memory::Buffer;

mod execute;

pub use execute::{copy_results_len, execute_recording, Command, CopyRegion, Exec, ExecContext, ExecError, Flow, Secondary};

// ---------------------------------------------------------------------------------------------
// Pools and buffers

/// One `VkCommandPool`. It owns its command buffers' handles (freed with the pool).
pub struct CommandPool {
    pub flags: vk::CommandPoolCreateFlags,
    pub family: u32,
    /// (handle value, buffer) of every live buffer allocated from the pool.
    buffers: Mutex<Vec<(usize, Arc<CommandBuffer>)>>,
}

impl CommandPool {
    pub fn new(flags: vk::CommandPoolCreateFlags, family: u32) -> CommandPool {
        CommandPool { flags, family, buffers: Mutex::new(Vec::new()) }
    }

    fn list(&self) -> MutexGuard<'_, Vec<(usize, Arc<CommandBuffer>)>> {
        self.buffers.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub fn allocate(self: &Arc<Self>, level: vk::CommandBufferLevel) -> Arc<CommandBuffer> {
        Arc::new(CommandBuffer {
            level,
            pool: Arc::downgrade(self),
            pool_flags: self.flags,
            state: Mutex::new(CbState::default()),
            pending: AtomicU32::new(0),
        })
    }

    /// Remember a buffer's handle (after the dispatch layer made it).
    pub fn adopt(&self, handle: usize, buffer: Arc<CommandBuffer>) {
        self.list().push((handle, buffer));
    }

    /// Forget a handle (vkFreeCommandBuffers). Returns whether it belonged to this pool.
    pub fn release(&self, handle: usize, command: &str) -> bool {
        let mut l = self.list();
        let Some(i) = l.iter().position(|(h, _)| *h == handle) else { return false };
        let (_, b) = l.swap_remove(i);
        if b.is_pending() {
            diag::vuid("VUID-vkFreeCommandBuffers-pCommandBuffers-00047", command, "freeing a command buffer that is pending execution (the queue keeps its recording alive)");
        }
        true
    }

    /// Take every handle (vkDestroyCommandPool), diagnosing pending buffers.
    pub fn take_all(&self) -> Vec<usize> {
        let l = std::mem::take(&mut *self.list());
        if l.iter().any(|(_, b)| b.is_pending()) {
            diag::vuid("VUID-vkDestroyCommandPool-commandPool-00041", "vkDestroyCommandPool", "a command buffer of the pool is pending execution");
        }
        l.into_iter().map(|(h, _)| h).collect()
    }

    /// vkResetCommandPool: every buffer back to the initial state.
    pub fn reset(&self, release_resources: bool) {
        let l = self.list();
        if l.iter().any(|(_, b)| b.is_pending()) {
            diag::vuid("VUID-vkResetCommandPool-commandPool-00040", "vkResetCommandPool", "a command buffer of the pool is pending execution");
        }
        for (_, b) in l.iter() {
            b.state().reset(release_resources);
        }
    }

    /// vkTrimCommandPool: give back spare recording capacity.
    pub fn trim(&self) {
        for (_, b) in self.list().iter() {
            let mut s = b.state();
            s.building.shrink_to_fit();
        }
    }
}

#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub enum Lifecycle {
    #[default]
    Initial,
    Recording,
    Executable,
    Invalid,
}

/// A frozen recording (what a submission executes).
#[derive(Default)]
pub struct Recording {
    pub commands: Vec<Command>,
    /// Valid-usage violations seen while recording (strict mode loses the device on submit).
    pub violations: u32,
    pub usage: vk::CommandBufferUsageFlags,
    /// The buffer's generation when this recording was made.
    pub generation: u64,
}

#[derive(Default)]
struct CbState {
    lifecycle: Lifecycle,
    usage: vk::CommandBufferUsageFlags,
    building: Vec<Command>,
    violations: u32,
    recorded: Option<Arc<Recording>>,
    /// Bumped by every reset/begin: lets a primary detect that a secondary it recorded changed.
    generation: u64,
    /// Bound compute pipeline, descriptor sets and push constants.
    compute: crate::runtime::shader::BindState,
}

impl CbState {
    fn reset(&mut self, release_resources: bool) {
        self.lifecycle = Lifecycle::Initial;
        self.building.clear();
        if release_resources {
            self.building.shrink_to_fit();
        }
        self.violations = 0;
        self.recorded = None;
        self.generation += 1;
        self.compute = Default::default();
    }
}

/// One `VkCommandBuffer`.
pub struct CommandBuffer {
    pub level: vk::CommandBufferLevel,
    pub pool: Weak<CommandPool>,
    pool_flags: vk::CommandPoolCreateFlags,
    state: Mutex<CbState>,
    /// Submissions (or primaries in submissions) not yet completed that include this buffer.
    pending: AtomicU32,
}

/// A command buffer as a submission holds it.
pub struct SubmittedBuffer {
    pub buffer: Arc<CommandBuffer>,
    pub recording: Arc<Recording>,
    /// Secondaries it executes (recursively), with their recordings: pending with it.
    pub involved: Vec<(Arc<CommandBuffer>, Arc<Recording>)>,
}

impl CommandBuffer {
    fn state(&self) -> MutexGuard<'_, CbState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub fn is_pending(&self) -> bool {
        self.pending.load(Ordering::Acquire) > 0
    }

    pub fn lifecycle(&self) -> Lifecycle {
        self.state().lifecycle
    }

    fn is_primary(&self) -> bool {
        self.level == vk::CommandBufferLevel::PRIMARY
    }

    /// vkBeginCommandBuffer. `has_inheritance`: pInheritanceInfo was given.
    pub fn begin(&self, usage: vk::CommandBufferUsageFlags, has_inheritance: bool) {
        const CMD: &str = "vkBeginCommandBuffer";
        if self.is_pending() {
            diag::vuid("VUID-vkBeginCommandBuffer-commandBuffer-00049", CMD, "the command buffer is pending execution (the queue keeps the old recording)");
        }
        let mut s = self.state();
        match s.lifecycle {
            Lifecycle::Recording => {
                diag::vuid("VUID-vkBeginCommandBuffer-commandBuffer-00049", CMD, "the command buffer is already recording; the recording restarts");
            }
            Lifecycle::Executable | Lifecycle::Invalid
                if !self.pool_flags.contains(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER) =>
            {
                diag::vuid(
                    "VUID-vkBeginCommandBuffer-commandBuffer-00050",
                    CMD,
                    "the buffer is not in the initial state and its pool lacks RESET_COMMAND_BUFFER (reset the pool first)",
                );
            }
            _ => {}
        }
        s.reset(false);
        s.lifecycle = Lifecycle::Recording;
        s.usage = usage;
        if !self.is_primary() && !has_inheritance {
            diag::vuid("VUID-vkBeginCommandBuffer-commandBuffer-00051", CMD, "a secondary command buffer needs pInheritanceInfo");
            s.violations += 1;
        }
        if !self.is_primary() && usage.contains(vk::CommandBufferUsageFlags::RENDER_PASS_CONTINUE) {
            diag::report(diag::Level::Warn, CMD, "RENDER_PASS_CONTINUE: Arbor has no render passes; the flag has no effect");
        }
    }

    /// vkEndCommandBuffer.
    pub fn end(&self) -> vk::Result {
        let mut s = self.state();
        if s.lifecycle != Lifecycle::Recording {
            diag::vuid("VUID-vkEndCommandBuffer-commandBuffer-00059", "vkEndCommandBuffer", "the command buffer is not recording");
            return vk::Result::SUCCESS;
        }
        let recording = Recording {
            commands: std::mem::take(&mut s.building),
            violations: s.violations,
            usage: s.usage,
            generation: s.generation,
        };
        s.recorded = Some(Arc::new(recording));
        s.lifecycle = Lifecycle::Executable;
        vk::Result::SUCCESS
    }

    /// vkResetCommandBuffer.
    pub fn reset(&self, release_resources: bool) {
        const CMD: &str = "vkResetCommandBuffer";
        if !self.pool_flags.contains(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER) {
            diag::vuid("VUID-vkResetCommandBuffer-commandBuffer-00046", CMD, "the pool was not created with RESET_COMMAND_BUFFER");
        }
        if self.is_pending() {
            diag::vuid("VUID-vkResetCommandBuffer-commandBuffer-00045", CMD, "the command buffer is pending execution (the queue keeps the old recording)");
        }
        self.state().reset(release_resources);
    }

    /// Report a valid-usage violation found while recording; the command is not recorded.
    pub fn violation(&self, vuid: &str, command: &str, message: &str) {
        diag::vuid(vuid, command, message);
        self.state().violations += 1;
    }

    /// Append a command (only while recording).
    fn push(&self, command: &str, c: Command) {
        let mut s = self.state();
        if s.lifecycle != Lifecycle::Recording {
            drop(s);
            not_recording(command);
            return;
        }
        s.building.push(c);
    }

    /// Check the recording state before validating arguments (so a misuse is reported once).
    fn recording(&self, command: &str) -> bool {
        if self.state().lifecycle != Lifecycle::Recording {
            not_recording(command);
            return false;
        }
        true
    }

    /// Read or change the bound compute state (only while recording; None otherwise).
    pub fn compute_state<R>(&self, command: &str, f: impl FnOnce(&mut crate::runtime::shader::BindState) -> R) -> Option<R> {
        let mut s = self.state();
        if s.lifecycle != Lifecycle::Recording {
            drop(s);
            not_recording(command);
            return None;
        }
        Some(f(&mut s.compute))
    }

    /// Record a command implemented elsewhere (see the module docs).
    pub fn record_custom(&self, command: Box<dyn Exec>) {
        let name = command.name();
        self.push(name, Command::Custom(command));
    }

    /// Record a command built by the caller (for variants without their own entry point).
    pub fn record(&self, command: Command) {
        let name = command.name();
        self.push(name, command);
    }

    // --- transfer commands ------------------------------------------------------------------

    pub fn cmd_copy_buffer(&self, v: &CopyVuids, src: Arc<Buffer>, dst: Arc<Buffer>, regions: Vec<CopyRegion>) {
        let cmd = v.command;
        if !self.recording(cmd) {
            return;
        }
        if !src.usage.contains(vk::BufferUsageFlags::TRANSFER_SRC) {
            return self.violation(v.src_usage, cmd, "srcBuffer lacks TRANSFER_SRC usage");
        }
        if !dst.usage.contains(vk::BufferUsageFlags::TRANSFER_DST) {
            return self.violation(v.dst_usage, cmd, "dstBuffer lacks TRANSFER_DST usage");
        }
        for (i, r) in regions.iter().enumerate() {
            if r.size == 0 {
                return self.violation(v.size_zero, cmd, &format!("pRegions[{i}].size is 0"));
            }
            if r.src_offset >= src.size {
                return self.violation(v.src_offset, cmd, &format!("pRegions[{i}].srcOffset {} is not less than the source size {}", r.src_offset, src.size));
            }
            if r.dst_offset >= dst.size {
                return self.violation(v.dst_offset, cmd, &format!("pRegions[{i}].dstOffset {} is not less than the destination size {}", r.dst_offset, dst.size));
            }
            if r.size > src.size - r.src_offset {
                return self.violation(v.src_size, cmd, &format!("pRegions[{i}] reads past the end of the source ({} + {} > {})", r.src_offset, r.size, src.size));
            }
            if r.size > dst.size - r.dst_offset {
                return self.violation(v.dst_size, cmd, &format!("pRegions[{i}] writes past the end of the destination ({} + {} > {})", r.dst_offset, r.size, dst.size));
            }
        }
        if Arc::ptr_eq(&src, &dst) {
            let overlaps = |a: u64, b: u64, n: u64, m: u64| a < b + m && b < a + n;
            for (i, r) in regions.iter().enumerate() {
                for (j, q) in regions.iter().enumerate() {
                    if overlaps(r.src_offset, q.dst_offset, r.size, q.size) {
                        return self.violation(v.overlap, cmd, &format!("pRegions[{i}] source overlaps pRegions[{j}] destination in the same buffer"));
                    }
                }
            }
        }
        self.push(cmd, Command::CopyBuffer { src, dst, regions });
    }

    pub fn cmd_fill_buffer(&self, dst: Arc<Buffer>, offset: u64, size: u64, data: u32) {
        const CMD: &str = "vkCmdFillBuffer";
        if !self.recording(CMD) {
            return;
        }
        if !dst.usage.contains(vk::BufferUsageFlags::TRANSFER_DST) {
            return self.violation("VUID-vkCmdFillBuffer-dstBuffer-00029", CMD, "dstBuffer lacks TRANSFER_DST usage");
        }
        if offset >= dst.size {
            return self.violation("VUID-vkCmdFillBuffer-dstOffset-00024", CMD, &format!("dstOffset {offset} is not less than the buffer size {}", dst.size));
        }
        if !offset.is_multiple_of(4) {
            return self.violation("VUID-vkCmdFillBuffer-dstOffset-00025", CMD, &format!("dstOffset {offset} is not a multiple of 4"));
        }
        let size = if size == vk::WHOLE_SIZE {
            // VK_WHOLE_SIZE: to the end of the buffer, rounded down to a multiple of 4.
            (dst.size - offset) & !3
        } else {
            if size == 0 {
                return self.violation("VUID-vkCmdFillBuffer-size-00026", CMD, "size is 0");
            }
            if size > dst.size - offset {
                return self.violation("VUID-vkCmdFillBuffer-size-00027", CMD, &format!("dstOffset {offset} + size {size} exceeds the buffer size {}", dst.size));
            }
            if !size.is_multiple_of(4) {
                return self.violation("VUID-vkCmdFillBuffer-size-00028", CMD, &format!("size {size} is not a multiple of 4"));
            }
            size
        };
        if size > 0 {
            self.push(CMD, Command::FillBuffer { dst, offset, size, data });
        }
    }

    pub fn cmd_update_buffer(&self, dst: Arc<Buffer>, offset: u64, data: Vec<u8>) {
        const CMD: &str = "vkCmdUpdateBuffer";
        if !self.recording(CMD) {
            return;
        }
        let n = data.len() as u64;
        if !dst.usage.contains(vk::BufferUsageFlags::TRANSFER_DST) {
            return self.violation("VUID-vkCmdUpdateBuffer-dstBuffer-00034", CMD, "dstBuffer lacks TRANSFER_DST usage");
        }
        if offset >= dst.size {
            return self.violation("VUID-vkCmdUpdateBuffer-dstOffset-00032", CMD, &format!("dstOffset {offset} is not less than the buffer size {}", dst.size));
        }
        if !offset.is_multiple_of(4) {
            return self.violation("VUID-vkCmdUpdateBuffer-dstOffset-00036", CMD, &format!("dstOffset {offset} is not a multiple of 4"));
        }
        if n == 0 || n > 65536 {
            return self.violation("VUID-vkCmdUpdateBuffer-dataSize-00037", CMD, &format!("dataSize {n} must be in 1..=65536"));
        }
        if !n.is_multiple_of(4) {
            return self.violation("VUID-vkCmdUpdateBuffer-dataSize-00038", CMD, &format!("dataSize {n} is not a multiple of 4"));
        }
        if n > dst.size - offset {
            return self.violation("VUID-vkCmdUpdateBuffer-dataSize-00033", CMD, &format!("dstOffset {offset} + dataSize {n} exceeds the buffer size {}", dst.size));
        }
        self.push(CMD, Command::UpdateBuffer { dst, offset, data });
    }

    pub fn cmd_barrier(&self, command: &str) {
        if self.recording(command) {
            self.push(command, Command::Barrier);
        }
    }

    // --- events -----------------------------------------------------------------------------

    pub fn cmd_set_event(&self, command: &str, event: Arc<Event>, set: bool) {
        if self.recording(command) {
            self.push(command, if set { Command::SetEvent(event) } else { Command::ResetEvent(event) });
        }
    }

    pub fn cmd_wait_events(&self, command: &str, events: Vec<Arc<Event>>) {
        if self.recording(command) && !events.is_empty() {
            self.push(command, Command::WaitEvents(events));
        }
    }

    // --- queries ----------------------------------------------------------------------------

    pub fn cmd_write_timestamp(&self, command: &'static str, pool: Arc<QueryPool>, query: u32) {
        if !self.recording(command) {
            return;
        }
        let v2 = command == "vkCmdWriteTimestamp2";
        if pool.kind != QueryKind::Timestamp {
            let vuid = if v2 { "VUID-vkCmdWriteTimestamp2-queryPool-03861" } else { "VUID-vkCmdWriteTimestamp-queryPool-01416" };
            return self.violation(vuid, command, &format!("queryPool has query type {}, not TIMESTAMP", pool.query_type.as_raw()));
        }
        if query >= pool.count {
            let vuid = if v2 { "VUID-vkCmdWriteTimestamp2-query-04903" } else { "VUID-vkCmdWriteTimestamp-query-04904" };
            return self.violation(vuid, command, &format!("query {query} is not less than the pool's {} queries", pool.count));
        }
        self.push(command, Command::WriteTimestamp { pool, query, name: command });
    }

    pub fn cmd_reset_query_pool(&self, pool: Arc<QueryPool>, first: u32, count: u32) {
        const CMD: &str = "vkCmdResetQueryPool";
        if !self.recording(CMD) {
            return;
        }
        match pool.check_range(first, count) {
            Err(RangeError::First) => self.violation("VUID-vkCmdResetQueryPool-firstQuery-00796", CMD, &format!("firstQuery {first} is not less than the pool's {} queries", pool.count)),
            Err(RangeError::Count) => self.violation("VUID-vkCmdResetQueryPool-firstQuery-00797", CMD, &format!("firstQuery {first} + queryCount {count} exceeds the pool's {} queries", pool.count)),
            Ok(()) => self.push(CMD, Command::ResetQueries { pool, first, count }),
        }
    }

    /// vkCmdBeginQuery / vkCmdEndQuery: no supported query type is begun and ended (occlusion
    /// needs a graphics queue, pipeline statistics a feature Arbor does not offer).
    pub fn cmd_begin_end_query(&self, command: &str, pool: Arc<QueryPool>, query: u32) {
        if !self.recording(command) {
            return;
        }
        let (vuid, why) = match pool.kind {
            QueryKind::Timestamp => ("VUID-vkCmdBeginQuery-queryType-02804", "timestamp queries are written with vkCmdWriteTimestamp, not begun"),
            QueryKind::AccelerationStructure(_) => ("VUID-vkCmdBeginQuery-queryType-04728", "acceleration-structure queries are written by vkCmdWriteAccelerationStructuresPropertiesKHR"),
            QueryKind::Unsupported(t) if t == vk::QueryType::OCCLUSION => ("VUID-vkCmdBeginQuery-queryType-00803", "occlusion queries need a graphics queue; Arbor's queue family has none"),
            QueryKind::Unsupported(_) => ("VUID-vkCmdBeginQuery-queryType-00800", "this query type is not supported by Arbor"),
        };
        self.violation(vuid, command, &format!("query {query} of a pool of query type {}: {why}; not recorded", pool.query_type.as_raw()));
    }

    // The Vulkan command's own parameters, one for one.
    #[allow(clippy::too_many_arguments)]
    pub fn cmd_copy_query_pool_results(&self, pool: Arc<QueryPool>, first: u32, count: u32, dst: Arc<Buffer>, offset: u64, stride: u64, flags: vk::QueryResultFlags) {
        const CMD: &str = "vkCmdCopyQueryPoolResults";
        if !self.recording(CMD) {
            return;
        }
        match pool.check_range(first, count) {
            Err(RangeError::First) => return self.violation("VUID-vkCmdCopyQueryPoolResults-firstQuery-00820", CMD, &format!("firstQuery {first} is not less than the pool's {} queries", pool.count)),
            Err(RangeError::Count) => return self.violation("VUID-vkCmdCopyQueryPoolResults-firstQuery-00821", CMD, &format!("firstQuery {first} + queryCount {count} exceeds the pool's {} queries", pool.count)),
            Ok(()) => {}
        }
        let f = ReadFlags::from_vk(flags);
        if offset >= dst.size {
            return self.violation("VUID-vkCmdCopyQueryPoolResults-dstOffset-00819", CMD, &format!("dstOffset {offset} is not less than the buffer size {}", dst.size));
        }
        if !f.wide && (!offset.is_multiple_of(4) || !stride.is_multiple_of(4)) {
            return self.violation("VUID-vkCmdCopyQueryPoolResults-flags-00822", CMD, "without 64_BIT, dstOffset and stride must be multiples of 4");
        }
        if f.wide && (!offset.is_multiple_of(8) || !stride.is_multiple_of(8)) {
            return self.violation("VUID-vkCmdCopyQueryPoolResults-flags-00823", CMD, "with 64_BIT, dstOffset and stride must be multiples of 8");
        }
        let len = copy_results_len(count, stride, &f);
        if len > dst.size - offset {
            return self.violation("VUID-vkCmdCopyQueryPoolResults-dstBuffer-00824", CMD, &format!("the results need {len} bytes from dstOffset {offset}; the buffer has {}", dst.size));
        }
        if !dst.usage.contains(vk::BufferUsageFlags::TRANSFER_DST) {
            return self.violation("VUID-vkCmdCopyQueryPoolResults-dstBuffer-00825", CMD, "dstBuffer lacks TRANSFER_DST usage");
        }
        if f.partial && !pool.kind.allows_partial() {
            return self.violation("VUID-vkCmdCopyQueryPoolResults-queryType-00827", CMD, "PARTIAL is not allowed for this query type");
        }
        if count > 0 {
            self.push(CMD, Command::CopyQueryResults { pool, first, count, dst, offset, stride, flags });
        }
    }

    // --- secondaries ------------------------------------------------------------------------

    pub fn cmd_execute_commands(&self, secondaries: Vec<Arc<CommandBuffer>>) {
        const CMD: &str = "vkCmdExecuteCommands";
        if !self.recording(CMD) {
            return;
        }
        if !self.is_primary() {
            return self.violation("VUID-vkCmdExecuteCommands-bufferlevel", CMD, "commandBuffer must be a primary command buffer");
        }
        let mut list = Vec::with_capacity(secondaries.len());
        for (i, s) in secondaries.into_iter().enumerate() {
            if s.is_primary() {
                return self.violation("VUID-vkCmdExecuteCommands-pCommandBuffers-00088", CMD, &format!("pCommandBuffers[{i}] is not a secondary command buffer"));
            }
            let (lifecycle, recorded) = {
                let st = s.state();
                (st.lifecycle, st.recorded.clone())
            };
            let Some(recording) = recorded.filter(|_| lifecycle == Lifecycle::Executable) else {
                return self.violation("VUID-vkCmdExecuteCommands-pCommandBuffers-00089", CMD, &format!("pCommandBuffers[{i}] is not in the executable state"));
            };
            if s.is_pending() && !recording.usage.contains(vk::CommandBufferUsageFlags::SIMULTANEOUS_USE) {
                return self.violation("VUID-vkCmdExecuteCommands-pCommandBuffers-00091", CMD, &format!("pCommandBuffers[{i}] is pending and was not recorded with SIMULTANEOUS_USE"));
            }
            list.push(Secondary { buffer: s, recording });
        }
        if !list.is_empty() {
            self.push(CMD, Command::ExecuteCommands(list));
        }
    }

    // --- submission -------------------------------------------------------------------------

    /// Checks for vkQueueSubmit and marks the buffer (and its secondaries) pending. On a
    /// violation the buffer is reported and left out of the submission.
    pub fn prepare_submit(self: &Arc<Self>, command: &str) -> Option<SubmittedBuffer> {
        if !self.is_primary() {
            diag::vuid("VUID-VkSubmitInfo-pCommandBuffers-00075", command, "a secondary command buffer cannot be submitted; left out");
            return None;
        }
        let recording = {
            let s = self.state();
            match (&s.recorded, s.lifecycle) {
                (Some(r), Lifecycle::Executable) => r.clone(),
                (_, l) => {
                    drop(s);
                    diag::vuid("VUID-vkQueueSubmit-pCommandBuffers-00070", command, &format!("the command buffer is in the {l:?} state, not executable; left out"));
                    return None;
                }
            }
        };
        if self.is_pending() && !recording.usage.contains(vk::CommandBufferUsageFlags::SIMULTANEOUS_USE) {
            diag::vuid("VUID-vkQueueSubmit-pCommandBuffers-00071", command, "the command buffer is already pending and was not recorded with SIMULTANEOUS_USE; left out");
            return None;
        }
        // Secondaries recorded into it must still hold the recording the primary captured.
        let mut involved = Vec::new();
        let mut stack: Vec<Arc<Recording>> = vec![recording.clone()];
        while let Some(r) = stack.pop() {
            for c in &r.commands {
                if let Command::ExecuteCommands(list) = c {
                    for s in list {
                        let (generation, lifecycle) = {
                            let st = s.buffer.state();
                            (st.generation, st.lifecycle)
                        };
                        if generation != s.recording.generation || lifecycle != Lifecycle::Executable {
                            diag::vuid(
                                "VUID-vkQueueSubmit-pCommandBuffers-00072",
                                command,
                                "a secondary command buffer it executes was reset, re-recorded or invalidated (ONE_TIME_SUBMIT), so the primary is invalid; left out",
                            );
                            return None;
                        }
                        let simultaneous = s.recording.usage.contains(vk::CommandBufferUsageFlags::SIMULTANEOUS_USE);
                        if !simultaneous && (s.buffer.is_pending() || involved.iter().any(|(b, _): &(Arc<CommandBuffer>, _)| Arc::ptr_eq(b, &s.buffer))) {
                            diag::vuid(
                                "VUID-vkQueueSubmit-pCommandBuffers-00073",
                                command,
                                "a secondary command buffer it executes is already pending and was not recorded with SIMULTANEOUS_USE; left out",
                            );
                            return None;
                        }
                        involved.push((s.buffer.clone(), s.recording.clone()));
                        stack.push(s.recording.clone());
                    }
                }
            }
        }
        self.pending.fetch_add(1, Ordering::AcqRel);
        for (b, _) in &involved {
            b.pending.fetch_add(1, Ordering::AcqRel);
        }
        Some(SubmittedBuffer { buffer: self.clone(), recording, involved })
    }

    /// After execution: no longer pending; a ONE_TIME_SUBMIT recording becomes invalid.
    fn complete(&self, recording: &Recording) {
        if recording.usage.contains(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT) {
            let mut s = self.state();
            if s.generation == recording.generation && s.lifecycle == Lifecycle::Executable {
                s.lifecycle = Lifecycle::Invalid;
            }
        }
        self.pending.fetch_sub(1, Ordering::AcqRel);
    }
}

fn not_recording(command: &str) {
    diag::vuid(&format!("VUID-{command}-commandBuffer-recording"), command, "the command buffer is not in the recording state; command ignored");
}

impl SubmittedBuffer {
    /// Mark the buffer and its secondaries complete (executed or abandoned).
    pub fn complete(&self) {
        for (b, r) in &self.involved {
            b.complete(r);
        }
        self.buffer.complete(&self.recording);
    }
}

/// The VUIDs of vkCmdCopyBuffer and vkCmdCopyBuffer2 (same rules, different names).
pub struct CopyVuids {
    pub command: &'static str,
    pub src_offset: &'static str,
    pub dst_offset: &'static str,
    pub src_size: &'static str,
    pub dst_size: &'static str,
    pub overlap: &'static str,
    pub src_usage: &'static str,
    pub dst_usage: &'static str,
    pub size_zero: &'static str,
}

pub const COPY_BUFFER_VUIDS: CopyVuids = CopyVuids {
    command: "vkCmdCopyBuffer",
    src_offset: "VUID-vkCmdCopyBuffer-srcOffset-00113",
    dst_offset: "VUID-vkCmdCopyBuffer-dstOffset-00114",
    src_size: "VUID-vkCmdCopyBuffer-size-00115",
    dst_size: "VUID-vkCmdCopyBuffer-size-00116",
    overlap: "VUID-vkCmdCopyBuffer-pRegions-00117",
    src_usage: "VUID-vkCmdCopyBuffer-srcBuffer-00118",
    dst_usage: "VUID-vkCmdCopyBuffer-dstBuffer-00120",
    size_zero: "VUID-VkBufferCopy-size-01988",
};

pub const COPY_BUFFER2_VUIDS: CopyVuids = CopyVuids {
    command: "vkCmdCopyBuffer2",
    src_offset: "VUID-VkCopyBufferInfo2-srcOffset-00113",
    dst_offset: "VUID-VkCopyBufferInfo2-dstOffset-00114",
    src_size: "VUID-VkCopyBufferInfo2-size-00115",
    dst_size: "VUID-VkCopyBufferInfo2-size-00116",
    overlap: "VUID-VkCopyBufferInfo2-pRegions-00117",
    src_usage: "VUID-VkCopyBufferInfo2-srcBuffer-00118",
    dst_usage: "VUID-VkCopyBufferInfo2-dstBuffer-00120",
    size_zero: "VUID-VkBufferCopy2-size-01988",
};

#[cfg(test)]
mod tests {
    use super::*;

    fn pool(flags: vk::CommandPoolCreateFlags) -> Arc<CommandPool> {
        Arc::new(CommandPool::new(flags, 0))
    }

    fn fill_target() -> Arc<Buffer> {
        Arc::new(Buffer::new(64, vk::BufferUsageFlags::TRANSFER_DST | vk::BufferUsageFlags::TRANSFER_SRC, vk::BufferCreateFlags::empty()))
    }

    fn count(r: &Recording) -> usize {
        r.commands.len()
    }

    #[test]
    fn lifecycle_and_one_time_submit() {
        let p = pool(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        let cb = p.allocate(vk::CommandBufferLevel::PRIMARY);
        assert_eq!(cb.lifecycle(), Lifecycle::Initial);
        cb.begin(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT, false);
        assert_eq!(cb.lifecycle(), Lifecycle::Recording);
        cb.cmd_fill_buffer(fill_target(), 0, vk::WHOLE_SIZE, 7);
        cb.cmd_barrier("vkCmdPipelineBarrier");
        assert_eq!(cb.end(), vk::Result::SUCCESS);
        assert_eq!(cb.lifecycle(), Lifecycle::Executable);
        let s = cb.prepare_submit("test").expect("executable");
        assert_eq!(count(&s.recording), 2);
        assert!(cb.is_pending());
        assert!(cb.prepare_submit("test").is_none(), "pending without SIMULTANEOUS_USE is refused");
        s.complete();
        assert!(!cb.is_pending());
        assert_eq!(cb.lifecycle(), Lifecycle::Invalid, "ONE_TIME_SUBMIT: invalid after execution");
        assert!(cb.prepare_submit("test").is_none());
        cb.begin(vk::CommandBufferUsageFlags::SIMULTANEOUS_USE, false);
        let _ = cb.end();
        let a = cb.prepare_submit("test").unwrap();
        let b = cb.prepare_submit("test").expect("SIMULTANEOUS_USE may be pending twice");
        a.complete();
        b.complete();
        assert_eq!(cb.lifecycle(), Lifecycle::Executable);
    }

    #[test]
    fn invalid_commands_are_not_recorded() {
        let p = pool(vk::CommandPoolCreateFlags::empty());
        let cb = p.allocate(vk::CommandBufferLevel::PRIMARY);
        let before = diag::reported_count();
        cb.cmd_fill_buffer(fill_target(), 0, 4, 1); // not recording
        cb.begin(vk::CommandBufferUsageFlags::empty(), false);
        let t = fill_target();
        cb.cmd_fill_buffer(t.clone(), 2, 4, 1); // unaligned offset
        cb.cmd_fill_buffer(t.clone(), 0, 68, 1); // past the end
        cb.cmd_update_buffer(t.clone(), 0, vec![0; 6]); // size not a multiple of 4
        let ro = Arc::new(Buffer::new(64, vk::BufferUsageFlags::TRANSFER_SRC, vk::BufferCreateFlags::empty()));
        cb.cmd_copy_buffer(&COPY_BUFFER_VUIDS, t.clone(), ro, vec![CopyRegion { src_offset: 0, dst_offset: 0, size: 4 }]); // no TRANSFER_DST
        cb.cmd_copy_buffer(&COPY_BUFFER_VUIDS, t.clone(), t.clone(), vec![CopyRegion { src_offset: 0, dst_offset: 8, size: 16 }]); // overlap
        cb.cmd_fill_buffer(t.clone(), 60, vk::WHOLE_SIZE, 1); // fine: 4 bytes
        let _ = cb.end();
        assert!(diag::reported_count() >= before + 6);
        let s = cb.prepare_submit("test").unwrap();
        assert_eq!(count(&s.recording), 1);
        assert_eq!(s.recording.violations, 5);
        s.complete();
        // Begin on an executable buffer of a pool without RESET_COMMAND_BUFFER is diagnosed.
        let before = diag::reported_count();
        cb.begin(vk::CommandBufferUsageFlags::empty(), false);
        assert!(diag::reported_count() > before);
    }

    #[test]
    fn secondaries_follow_their_primary() {
        let p = pool(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        let primary = p.allocate(vk::CommandBufferLevel::PRIMARY);
        let secondary = p.allocate(vk::CommandBufferLevel::SECONDARY);
        secondary.begin(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT, true);
        secondary.cmd_fill_buffer(fill_target(), 0, 4, 1);
        let _ = secondary.end();
        assert!(secondary.prepare_submit("test").is_none(), "secondaries cannot be submitted");
        primary.begin(vk::CommandBufferUsageFlags::SIMULTANEOUS_USE, false);
        primary.cmd_execute_commands(vec![secondary.clone()]);
        let _ = primary.end();
        let s = primary.prepare_submit("test").unwrap();
        assert!(secondary.is_pending(), "pending with its primary");
        assert!(primary.prepare_submit("test").is_none(), "the secondary is pending and not SIMULTANEOUS_USE");
        s.complete();
        assert!(!secondary.is_pending());
        assert_eq!(secondary.lifecycle(), Lifecycle::Invalid);
        assert!(primary.prepare_submit("test").is_none(), "its ONE_TIME_SUBMIT secondary ran: the primary is invalid");
        // Re-recording the secondary also invalidates the primary that captured the old one.
        secondary.begin(vk::CommandBufferUsageFlags::empty(), true);
        let _ = secondary.end();
        assert!(primary.prepare_submit("test").is_none());
        primary.begin(vk::CommandBufferUsageFlags::empty(), false);
        primary.cmd_execute_commands(vec![secondary.clone()]);
        let _ = primary.end();
        primary.prepare_submit("test").unwrap().complete();
    }

    #[test]
    fn pool_reset_and_free() {
        let p = pool(vk::CommandPoolCreateFlags::empty());
        let a = p.allocate(vk::CommandBufferLevel::PRIMARY);
        p.adopt(0x10, a.clone());
        a.begin(vk::CommandBufferUsageFlags::empty(), false);
        let _ = a.end();
        p.reset(true);
        assert_eq!(a.lifecycle(), Lifecycle::Initial);
        assert!(p.release(0x10, "test"));
        assert!(!p.release(0x10, "test"));
        assert!(p.take_all().is_empty());
    }
}

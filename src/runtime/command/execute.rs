//! The executor: the recorded [`Command`]s and how a queue's worker thread runs a recording
//! ([`execute_recording`]), with the [`Exec`] extension point and the [`ExecContext`] a command
//! sees while it runs (the parent module's docs show an example).
//!
//! This module runs what was recorded; it must not record or check recording-time rules (that
//! is the parent's `CommandBuffer`).
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use ash::vk;

use super::{CommandBuffer, Recording};
use crate::diag;
use crate::memory::{AccessError, AddressSpace, Buffer};
use crate::runtime::in_use::Collector;
use crate::runtime::query::{QueryPool, ReadFlags};
use crate::runtime::sync::{self, Deadline, Event, WaitOutcome};
use crate::runtime::Device;

/// Largest copy/fill chunk staged through host memory at once (keeps extra memory bounded).
const CHUNK: u64 = 4 << 20;

/// Why executing a command failed.
#[derive(Debug)]
pub enum ExecError {
    /// A valid-usage rule that only execution can check was broken.
    Invalid { vuid: &'static str, message: String },
    /// A device-memory access was refused (freed memory, destroyed buffer, bad range).
    Access(AccessError),
    /// The queue is being stopped (device destruction): stop executing.
    Cancelled,
}

impl From<AccessError> for ExecError {
    fn from(e: AccessError) -> Self {
        ExecError::Access(e)
    }
}

/// What a command sees while it executes.
pub struct ExecContext<'a> {
    pub device: &'a Arc<Device>,
    /// Raised when the queue is stopped; long waits and long work should check it.
    pub cancel: &'a AtomicBool,
}

impl ExecContext<'_> {
    /// The device's memory (resolve device addresses, read and write).
    pub fn memory(&self) -> &AddressSpace {
        &self.device.memory
    }

    /// Current device timestamp (ns).
    pub fn timestamp(&self) -> u64 {
        self.device.timestamp_now()
    }

    /// Block (cancellably) until `ready()` holds. `ready` runs under the sync hub's lock; it
    /// must only read state.
    pub fn wait(&self, ready: impl FnMut() -> bool) -> Result<(), ExecError> {
        // Blocked, not executing: what it waits for must come from elsewhere (`stall`).
        match crate::runtime::stall::blocked(|| sync::wait_until(Deadline::Never, Some(self.cancel), ready)) {
            WaitOutcome::Ready => Ok(()),
            _ => Err(ExecError::Cancelled),
        }
    }

    pub fn cancelled(&self) -> bool {
        self.cancel.load(Ordering::Acquire)
    }

    /// Report a valid-usage violation found while executing, for a command that handles it
    /// itself (skips part of its work, marks a destination invalid) instead of returning
    /// `Err`. In strict mode the device is lost and the submission stops after this command.
    pub fn violation(&self, vuid: &str, command: &str, message: &str) {
        diag::vuid(vuid, command, message);
        if diag::strict() {
            diag::report(diag::Level::Error, command, "strict mode: device lost");
            self.device.mark_lost();
        }
    }
}

/// A command implemented outside this module (the acceleration-structure commands).
pub trait Exec: Send + Sync {
    /// The Vulkan command it was recorded by, for diagnostics ("vkCmdBuildAccelerationStructuresKHR").
    fn name(&self) -> &'static str;
    /// Run it. Reads of device memory happen here, not at record time.
    fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError>;
    /// The structures, buffers and device addresses it names, collected when it is submitted
    /// (`in_use`: destroying them while it is pending is reported).
    fn uses(&self, _uses: &mut Collector<'_>) {}
}

/// A buffer copy region (validated at record time, checked again when executed).
#[derive(Clone, Copy, Debug)]
pub struct CopyRegion {
    pub src_offset: u64,
    pub dst_offset: u64,
    pub size: u64,
}

/// A secondary command buffer recorded into a primary: the buffer (for pending/lifecycle
/// tracking) and the recording it had at that moment.
pub struct Secondary {
    pub buffer: Arc<CommandBuffer>,
    pub recording: Arc<Recording>,
}

/// One recorded command, owning everything it needs.
pub enum Command {
    CopyBuffer { src: Arc<Buffer>, dst: Arc<Buffer>, regions: Vec<CopyRegion> },
    FillBuffer { dst: Arc<Buffer>, offset: u64, size: u64, data: u32 },
    UpdateBuffer { dst: Arc<Buffer>, offset: u64, data: Vec<u8> },
    /// Pipeline barriers: a CPU queue executes in order and writes memory directly, so there is
    /// nothing to do; recorded so the command stream mirrors what the application recorded.
    Barrier,
    SetEvent(Arc<Event>),
    ResetEvent(Arc<Event>),
    WaitEvents(Vec<Arc<Event>>),
    WriteTimestamp { pool: Arc<QueryPool>, query: u32, name: &'static str },
    ResetQueries { pool: Arc<QueryPool>, first: u32, count: u32 },
    CopyQueryResults { pool: Arc<QueryPool>, first: u32, count: u32, dst: Arc<Buffer>, offset: u64, stride: u64, flags: vk::QueryResultFlags },
    ExecuteCommands(Vec<Secondary>),
    Custom(Box<dyn Exec>),
}

impl Command {
    pub fn name(&self) -> &'static str {
        match self {
            Command::CopyBuffer { .. } => "vkCmdCopyBuffer",
            Command::FillBuffer { .. } => "vkCmdFillBuffer",
            Command::UpdateBuffer { .. } => "vkCmdUpdateBuffer",
            Command::Barrier => "vkCmdPipelineBarrier",
            Command::SetEvent(_) => "vkCmdSetEvent",
            Command::ResetEvent(_) => "vkCmdResetEvent",
            Command::WaitEvents(_) => "vkCmdWaitEvents",
            Command::WriteTimestamp { name, .. } => name,
            Command::ResetQueries { .. } => "vkCmdResetQueryPool",
            Command::CopyQueryResults { .. } => "vkCmdCopyQueryPoolResults",
            Command::ExecuteCommands(_) => "vkCmdExecuteCommands",
            Command::Custom(c) => c.name(),
        }
    }

    /// What the command names, for `in_use`.
    pub fn uses(&self, c: &mut Collector<'_>) {
        match self {
            Command::CopyBuffer { src, dst, .. } => {
                c.buffer(src);
                c.buffer(dst);
            }
            Command::FillBuffer { dst, .. } | Command::UpdateBuffer { dst, .. } | Command::CopyQueryResults { dst, .. } => c.buffer(dst),
            Command::ExecuteCommands(secondaries) => {
                for s in secondaries {
                    for cmd in &s.recording.commands {
                        cmd.uses(c);
                    }
                }
            }
            Command::Custom(x) => x.uses(c),
            Command::Barrier
            | Command::SetEvent(_)
            | Command::ResetEvent(_)
            | Command::WaitEvents(_)
            | Command::WriteTimestamp { .. }
            | Command::ResetQueries { .. } => {}
        }
    }

    fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        match self {
            Command::CopyBuffer { src, dst, regions } => {
                for r in regions {
                    copy_buffer(src, dst, r)?;
                }
                Ok(())
            }
            Command::FillBuffer { dst, offset, size, data } => fill_buffer(dst, *offset, *size, *data),
            Command::UpdateBuffer { dst, offset, data } => Ok(dst.write(*offset, data)?),
            Command::Barrier => Ok(()),
            Command::SetEvent(e) => {
                e.set();
                Ok(())
            }
            Command::ResetEvent(e) => {
                e.reset();
                Ok(())
            }
            Command::WaitEvents(events) => ctx.wait(|| events.iter().all(|e| e.is_set())),
            Command::WriteTimestamp { pool, query, name } => {
                let vuid = if *name == "vkCmdWriteTimestamp2" { "VUID-vkCmdWriteTimestamp2-None-03864" } else { "VUID-vkCmdWriteTimestamp-None-00830" };
                if !pool.write(*query, ctx.timestamp()) {
                    return Err(ExecError::Invalid { vuid, message: format!("query {query} was not unavailable (reset it before writing it again); the timestamp was written") });
                }
                Ok(())
            }
            Command::ResetQueries { pool, first, count } => {
                pool.reset(*first, *count);
                Ok(())
            }
            Command::CopyQueryResults { pool, first, count, dst, offset, stride, flags } => {
                let f = ReadFlags::from_vk(*flags);
                if f.wait {
                    let end = *first + *count;
                    ctx.wait(|| (*first..end).all(|q| pool.is_available(q)))?;
                }
                let len = copy_results_len(*count, *stride, &f);
                dst.with_slice_mut(*offset, len, |out| {
                    pool.read_into(*first, *count, *stride, &f, out);
                })?;
                Ok(())
            }
            Command::ExecuteCommands(secondaries) => {
                for s in secondaries {
                    if execute_recording(&s.recording, ctx) == Flow::Stop {
                        return Err(ExecError::Cancelled);
                    }
                }
                Ok(())
            }
            Command::Custom(c) => c.execute(ctx),
        }
    }
}

fn copy_buffer(src: &Buffer, dst: &Buffer, r: &CopyRegion) -> Result<(), ExecError> {
    let mut done = 0;
    let mut staging = vec![0u8; r.size.min(CHUNK) as usize];
    while done < r.size {
        let n = (r.size - done).min(CHUNK);
        let tmp = &mut staging[..n as usize];
        src.read(r.src_offset + done, tmp)?;
        dst.write(r.dst_offset + done, tmp)?;
        done += n;
    }
    Ok(())
}

fn fill_buffer(dst: &Buffer, offset: u64, size: u64, data: u32) -> Result<(), ExecError> {
    let mut done = 0;
    while done < size {
        let n = (size - done).min(CHUNK);
        dst.with_slice_mut(offset + done, n, |s| {
            for w in s.chunks_mut(4) {
                w.copy_from_slice(&data.to_le_bytes()[..w.len()]);
            }
        })?;
        done += n;
    }
    Ok(())
}

/// Bytes vkCmdCopyQueryPoolResults/vkGetQueryPoolResults write for `count` queries.
pub fn copy_results_len(count: u32, stride: u64, f: &ReadFlags) -> u64 {
    if count == 0 {
        0
    } else {
        (count as u64 - 1) * stride + f.element_size()
    }
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Flow {
    Continue,
    /// Stop the submission: cancelled, or the device was lost (strict mode).
    Stop,
}

/// Execute a recording in order. A failing command is reported and skipped; in strict mode it
/// loses the device and stops the submission.
pub fn execute_recording(recording: &Recording, ctx: &ExecContext<'_>) -> Flow {
    if recording.violations > 0 && diag::strict() {
        diag::report(diag::Level::Error, "vkQueueSubmit", "strict mode: the command buffer was recorded with valid-usage violations; device lost");
        ctx.device.mark_lost();
        return Flow::Stop;
    }
    for c in &recording.commands {
        if ctx.cancelled() {
            return Flow::Stop;
        }
        let msg = match c.execute(ctx) {
            Ok(()) if ctx.device.is_lost() => return Flow::Stop,
            Ok(()) => continue,
            Err(ExecError::Cancelled) => return Flow::Stop,
            Err(ExecError::Invalid { vuid, message }) => format!("[{vuid}] {message}"),
            Err(ExecError::Access(a)) => format!("device-memory access refused: {a}; command skipped"),
        };
        diag::report(diag::Level::Error, c.name(), &msg);
        if diag::strict() {
            diag::report(diag::Level::Error, c.name(), "strict mode: device lost");
            ctx.device.mark_lost();
            return Flow::Stop;
        }
    }
    Flow::Continue
}

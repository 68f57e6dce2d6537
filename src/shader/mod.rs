//! Compute shaders: SPIR-V → Arbor's IR → native code (Cranelift) or a SIMD-lane interpreter.
//! Pure library: no Vulkan
//! handles, no `unsafe`, no access to the rest of the driver; device memory is reached only
//! through the [`Memory`] trait the caller implements.
//!
//! Pipeline of modules:
//! - `parse`: words → [`Module`], rejecting unknown capabilities/extensions/opcodes with their
//!   word offset (so a bad module fails at pipeline creation, never at dispatch);
//! - `specialize`: constants and specialization constants (OpSpecConstantOp folded) → values;
//! - `lower`/`lower_ops`: one entry point → [`ir::Program`]: calls inlined, composites flattened
//!   into scalar registers, every memory access an explicit byte address in a [`ir::Space`];
//! - `exec`: runs lane groups of [`LANES`] invocations under an execution mask, per-lane block
//!   cursors, always the lowest block index first (blocks are in structured order, so lanes
//!   reconverge at merge blocks); `dispatch`: workgroups over rayon, barriers, faults, watchdog;
//! - `alu`: scalar semantics shared by the executor and the constant folder;
//! - `jit`: the native-code backend (below);
//! - `vmath`: branch-free f32 GLSL.std.450 functions (one value, and over lane arrays) and the
//!   exact `fma`; `exec_float`: the executor's F32 float ops over a whole lane group at once;
//! - `memory`: the [`Memory`] trait, [`Fault`]s, and [`HostMemory`] for tests;
//! - `lower_image`/`exec_image`: storage images (OpImageRead/Write/QuerySize on 1D/2D/3D,
//!   arrayed or not) and texel buffers (Dim Buffer, OpImageFetch for uniform ones), texels
//!   converted from the [`ImageFormat`] of the bound view; OpImageTexelPointer for image
//!   atomics (a `Space::Image` address);
//! - `lower_array`: arrays of buffer descriptors (and, in `lower_image`, of images): the
//!   element rides in the address (buffers, texel pointers) or in a register of the image op,
//!   and the executor resolves every element once per dispatch.
//!
//! Backends. [`Pipeline::compute`] compiles the program with Cranelift (`jit`) unless
//! `ARBOR_SHADER_JIT=0` (read once) or the host is neither x86-64 nor aarch64; the choice is
//! made there, never at dispatch. For loops of float math, and loops without buffer accesses,
//! on x86-64 the SIMD backend (`jit::simd`) comes first, for other programs second
//! (`jit::simd::pays`): eight lanes side by side in two 128-bit vectors per register (I32/F32
//! as i32x4 pairs, Bool as lane masks, 64-bit values as eight scalars), blocks run under an
//! execution mask in the interpreter's lowest-cursor-first schedule, sin/cos/exp vectorised with
//! `vmath`'s operations; a workgroup is one call, and a lane whose invocation has ended takes
//! the workgroup's next one (`jit::simd::refill`). It declines programs with
//! anything it does not cover (a register used as two types, images, subgroup ops, barriers,
//! workgroup memory, ...). The other native backend is the scalar JIT (`ARBOR_SHADER_JIT=scalar`
//! forces it): one invocation at a time (the IR's blocks as native blocks, registers as SSA variables), so
//! divergent branches and loops cost nothing extra; a workgroup is a loop over its invocations.
//! Loops heavy in `vmath` functions (sin, exp, …: at least 1/16 of their ops) that the SIMD
//! backend declines stay on the interpreter, whose lane arms compute them eight lanes at a time
//! (`ARBOR_SHADER_JIT=all` compiles them too). The scalar JIT covers ALU ops of every type (the
//! common integer, Bool and float ops inline; sin, cos, exp written out as `vmath` computes
//! them; the rest through helpers that run the interpreter's own lane arms), control flow,
//! phis, selects, push constants, lane memory and single buffer descriptors whose memory is
//! plain host memory (`Memory::host_span`) inline behind bounds checks, and every other buffer
//! access (arrays, device addresses, atomics, anything out of bounds) through the
//! interpreter's access function, so faults are the same records; the SIMD backend does the
//! same lane by lane and reaches the uncommon ops through the same helpers. Programs that need the invocations of a
//! lane group or workgroup together stay on the interpreter: workgroup barriers and shared
//! memory (whose unsynchronised order the lane schedule defines), subgroup and ballot ops,
//! images and ray queries, atomics on lane memory. The interpreter is the reference: same
//! register words, same memory, same faults (ordered by the key `jit` describes), NaN bits
//! included (a NaN result is recomputed by the interpreter's arm). Two things differ by design:
//! the watchdog's step count (the JITs count blocks per call) and, in a shader whose
//! invocations race on device memory without synchronisation, which write another invocation
//! of the same workgroup sees (Vulkan leaves that undefined; each backend is deterministic).
//!
//! Ray queries (SPV_KHR_ray_query, and position fetch): `lower_rq` turns each `OpRayQuery*`
//! into an IR op naming the query by its variable's lane-frame address; `exec_rq` keeps a
//! per-lane slot of native traversal state ([`crate::accel::RayQuery`]) in the lane group
//! (plain data, so barriers still work) and runs each op for the lanes in the mask — Proceed
//! is resumable, so it is an ordinary op returning a Bool register, and the shader's own loop
//! does the rest. Structures are reached by device address through [`Memory`].
//!
//! Where ray-tracing stages fit (not built yet): raygen/hit/miss/callable use the same
//! scheduler: a trace call ends a block; the lanes in the mask run the chosen shader's program
//! as a function-like call on a subset of lanes (their own cursors and registers, the caller's
//! state kept as data), and resume at the continuation block — no coroutines, as with barriers.
//!
//! For the Vulkan wiring:
//! - Create a [`Module`] at vkCreateShaderModule (or when a stage chains the create info) and a
//!   [`Pipeline`] at vkCreateComputePipelines; every [`ShaderError`] arises there, never at
//!   dispatch. [`Pipeline::bindings`], [`Pipeline::push_constant_size`] and
//!   [`Pipeline::local_size`] are what the pipeline layout checks need.
//! - Implement [`Memory`] over src/memory: `binding` returns the descriptor's buffer range with
//!   dynamic offsets applied (uniform and storage buffers alike); `address` resolves a device
//!   address to the one live buffer containing it; `image` returns a bound storage image's
//!   [`ImageBinding`] (format, extent, pitches, and the id `read`/`write` get). The executor
//!   bounds-checks every access against those regions itself, so `read`/`write` may assume
//!   in-range offsets. For ray queries, `acceleration_structure(set, binding)` returns the
//!   bound structure's device address and `acceleration_structures()` a
//!   [`crate::accel::DeviceView`] resolving a structure's device address to its bytes (and
//!   instance pointers to theirs); the pipeline's [`Pipeline::bindings`] list
//!   acceleration-structure descriptors too.
//! - Ray-query faults ([`FaultSpace::RayQuery`]): an address that is no live structure
//!   (`Unmapped`, null included, as for an unbound descriptor), bytes failing the header check
//!   (`InvalidStructure`: destroyed, failed build), a query used before Initialize
//!   (`Uninitialized`); the query finds nothing.
//! - [`dispatch`] returns a [`DispatchReport`]: each [`Fault`] (kind, binding or address, byte
//!   offset, workgroup, invocation) is one robustness diagnostic; `stopped` means the
//!   [`Watchdog`] fired (give it the submission's deadline and a device-lost flag) and the
//!   device should be marked lost.
//! - [`LANES`] is the subgroup size to report; supported subgroup stages/operations: compute,
//!   basic, vote, ballot, arithmetic, shuffle, shuffle-relative (not clustered, not quad).
pub mod alu;
mod exec;
mod exec_alu;
mod exec_float;
mod exec_image;
mod exec_mem;
mod exec_rq;
pub mod ir;
mod jit;
mod layout;
mod lower;
mod lower_array;
mod lower_copies;
mod lower_image;
mod lower_ops;
mod lower_rq;
mod lower_select;
mod lower_vars;
mod memory;
mod parse;
mod specialize;
pub mod vmath;
#[cfg(test)]
mod image_tests;
#[cfg(test)]
mod tests;

use std::sync::Arc;

pub use exec::{dispatch, DispatchReport, Stop, Watchdog};
pub use memory::{Fault, FaultKind, FaultSpace, HostMemory, ImageBinding, ImageFormat, Memory, Region};
pub use parse::Module;

/// Invocations a lane group runs together; also the subgroup size Arbor reports.
pub const LANES: usize = 8;

/// Why a module or pipeline cannot be created. Offsets are in 32-bit words from the start of
/// the module.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ShaderError {
    Malformed { offset: usize, reason: String },
    UnsupportedCapability { capability: String, offset: usize },
    UnsupportedExtension { name: String, offset: usize },
    UnsupportedOpcode { opcode: String, offset: usize },
    UnsupportedExtInst { set: String, number: u32, offset: usize },
    /// A supported opcode used in a way this library does not run (a storage class, a type).
    Unsupported { what: String, offset: usize },
    NoEntryPoint { name: String },
    Specialization { id: u32, reason: String },
}

impl std::fmt::Display for ShaderError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ShaderError::Malformed { offset, reason } => write!(f, "malformed SPIR-V at word {offset}: {reason}"),
            ShaderError::UnsupportedCapability { capability, offset } => {
                write!(f, "unsupported capability {capability} at word {offset}")
            }
            ShaderError::UnsupportedExtension { name, offset } => write!(f, "unsupported extension {name} at word {offset}"),
            ShaderError::UnsupportedOpcode { opcode, offset } => write!(f, "unsupported instruction {opcode} at word {offset}"),
            ShaderError::UnsupportedExtInst { set, number, offset } => {
                write!(f, "unsupported {set} instruction {number} at word {offset}")
            }
            ShaderError::Unsupported { what, offset } => write!(f, "unsupported: {what} at word {offset}"),
            ShaderError::NoEntryPoint { name } => write!(f, "no GLCompute entry point named {name:?}"),
            ShaderError::Specialization { id, reason } => write!(f, "specialization constant {id}: {reason}"),
        }
    }
}

impl std::error::Error for ShaderError {}

/// A descriptor binding the pipeline's entry point uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BindingUse {
    pub set: u32,
    pub binding: u32,
    /// The array length the shader declares: 1 for a single descriptor, 0 for a runtime
    /// array.
    pub count: u32,
}

/// A compute pipeline: one specialised, lowered entry point. Cheap to clone.
#[derive(Clone, Debug)]
pub struct Pipeline {
    pub(crate) program: Arc<ir::Program>,
    /// Workgroup size after specialization.
    pub local_size: [u32; 3],
    /// Bytes of push constants the entry point reads (highest member end).
    pub push_constant_size: u32,
    /// The program as native code, when it compiled (`jit`); None runs the interpreter.
    pub(crate) jit: Option<Arc<jit::Jit>>,
}

impl Pipeline {
    /// Lowers `entry_point` of `module` with the given specialization data: (SpecId, bytes of
    /// the value, little-endian, 4 or 8 bytes; booleans are 4-byte 0/1).
    pub fn compute(module: &Module, entry_point: &str, specialization: &[(u32, Vec<u8>)]) -> Result<Pipeline, ShaderError> {
        let entry = module
            .entry_points
            .iter()
            .find(|e| e.name == entry_point)
            .ok_or_else(|| ShaderError::NoEntryPoint { name: entry_point.into() })?;
        let consts = specialize::Constants::new(module, specialization)?;
        let local_size = consts.local_size(module, entry)?;
        // Backstop: lowering checks the shapes it relies on, but a module that passes the
        // parse checks yet is invalid SPIR-V in a way not anticipated must still fail here,
        // as an error, rather than take the caller down.
        let lowered = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| lower::lower(module, &consts, entry)))
            .map_err(|_| ShaderError::Malformed { offset: 0, reason: "invalid module (lowering failed)".into() })??;
        let jit = jit::for_pipeline(&lowered.program).map(Arc::new);
        Ok(Pipeline { program: Arc::new(lowered.program), local_size, push_constant_size: lowered.push_size, jit })
    }

    /// Whether dispatches run native code (else the interpreter).
    pub fn is_compiled(&self) -> bool {
        self.jit.is_some()
    }

    /// This pipeline on the interpreter (the reference backend).
    pub fn interpreted(&self) -> Pipeline {
        Pipeline { jit: None, ..self.clone() }
    }

    /// This pipeline compiled to native code whatever `ARBOR_SHADER_JIT` and the cost rule
    /// say; None when the program uses something the JIT does not compile.
    pub fn compiled(&self) -> Option<Pipeline> {
        let jit = jit::compile(&self.program)?;
        Some(Pipeline { jit: Some(Arc::new(jit)), ..self.clone() })
    }

    /// Descriptor bindings the entry point uses: buffers and acceleration structures in
    /// first-use order, then storage images in first-use order.
    pub fn bindings(&self) -> Vec<BindingUse> {
        let p = &self.program;
        let buffers = p.bindings.iter().zip(&p.binding_counts).map(|(&(set, binding), &count)| BindingUse { set, binding, count });
        let images = p.images.iter().zip(&p.image_counts).map(|(&(set, binding), &count)| BindingUse { set, binding, count });
        buffers.chain(images).collect()
    }

    /// Bytes of workgroup shared memory one workgroup needs.
    pub fn workgroup_memory_size(&self) -> u32 {
        self.program.workgroup_bytes
    }
}

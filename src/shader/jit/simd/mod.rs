//! The SIMD native-code backend: a workgroup per call on `W` lanes (one interpreter lane group
//! of eight), in Cranelift's 128-bit vector types; a lane whose invocation has ended takes the
//! workgroup's next one (`refill`).
//!
//! Registers take one form each (`types`): I32/F32 `PARTS` i32x4 vectors, Bool as many lane
//! masks, I64, F64 and addresses `W` scalar words. Blocks run under an execution mask in the
//! interpreter's schedule (`gen`), so a divergent branch costs both sides but no per-lane
//! dispatch; writes under a partial mask blend, except to registers that never outlive their
//! block. ALU ops are vector instructions where the bits are `alu`'s (`alu`), sin/cos/exp the
//! vectorised `vmath`; the rest, and every memory access, go lane by lane (in-bounds accesses
//! to the lane frame, push constants and host-span buffers inline, everything else through the
//! scalar JIT's helpers), so values and fault records are the interpreter's. A program with
//! anything else is declined and runs on the scalar JIT or the interpreter.
use cranelift_codegen::ir::{types as cl, AbiParam, Function, UserFuncName};
use cranelift_codegen::settings::{self, Configurable};
use cranelift_frontend::{FunctionBuilder, FunctionBuilderContext};
use cranelift_jit::{JITBuilder, JITModule};
use cranelift_module::{Linkage, Module};

use super::super::exec::{Ctx, Wg, CHECK_EVERY};
use super::super::ir::{Op, Program, Sc, Space};
use super::helpers::Run;
use super::{account, flush, Jit};

mod alu;
mod fuse;
mod gen;
mod mem;
mod nan;
mod refill;
mod tight;
#[cfg(test)]
mod tight_tests;
#[cfg(test)]
mod const_tests;
#[cfg(test)]
mod refill_tests;
#[cfg(test)]
mod tests;
mod tramp;
mod types;

pub(in crate::shader) use gen::W;

/// Whether the SIMD backend is the faster choice for `prog`: loops in which F32 arithmetic is
/// at least an eighth of the ops (W lanes of float math per instruction, sin/cos/exp
/// vectorised: compute-alu), or loops without memory ops (integer loops and branches whose
/// lanes end apart run with lane refill a little faster than on the scalar JIT:
/// compute-divergent). Buffer accesses go lane by lane on this backend, which gains nothing over
/// the scalar JIT there (compute-memory); docs/BENCHMARKS.md has the figures.
pub(super) fn pays(prog: &Program) -> bool {
    let in_loop = super::codegen::loop_blocks(prog);
    let (mut ops, mut float, mut memory) = (0usize, 0usize, 0usize);
    for blk in prog.blocks.iter().zip(&in_loop).filter(|b| *b.1).map(|b| b.0) {
        ops += blk.ops.len();
        float += blk.ops.iter().filter(|op| matches!(op, Op::Un { ty: Sc::F32, .. } | Op::Bin { ty: Sc::F32, .. } | Op::Tri { ty: Sc::F32, .. })).count();
        memory += blk.ops.iter().filter(|op| matches!(op, Op::Load { space, .. } | Op::Store { space, .. } | Op::Atomic { space, .. } if *space != Space::Lane)).count();
    }
    ops > 0 && ((float > 0 && float * 8 >= ops) || memory == 0)
}

/// Compiles `prog` for the SIMD backend (a workgroup per call on `W` lanes), or None when it
/// uses something this backend does not compile or code generation fails.
pub(super) fn compile(prog: &Program) -> Option<Jit> {
    let mut types = types::analyse(prog)?;
    refill::widen_blends(prog, &mut types);
    // A panic inside Cranelift must not take pipeline creation down.
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| build(prog, types))).ok().flatten()
}

fn build(prog: &Program, types: types::Types) -> Option<Jit> {
    let mut flags = settings::builder();
    // The code is emitted in the order it should run (parts side by side): the optimiser's
    // rescheduling would put each part's whole chain after the other's.
    flags.set("opt_level", "none").ok()?;
    flags.set("use_colocated_libcalls", "false").ok()?;
    flags.set("is_pic", "false").ok()?;
    // The host's SSE4.1/AVX/FMA flags come from cranelift_native's detection.
    let isa = cranelift_native::builder().ok()?.finish(settings::Flags::new(flags)).ok()?;
    let call_conv = isa.default_call_conv();
    let mut module = JITModule::new(JITBuilder::with_isa(isa, cranelift_module::default_libcall_names()));
    let mut sig = module.make_signature();
    sig.params.extend((0..5).map(|_| AbiParam::new(cl::I64)));
    sig.returns.push(AbiParam::new(cl::I64));
    let id = module.declare_function("invocations", Linkage::Export, &sig).ok()?;
    let tramps = tramp::define(&mut module, call_conv)?;
    let calls = tramp::define_calls(&mut module, call_conv)?;
    let mut ctx = module.make_context();
    ctx.func = Function::with_name_signature(UserFuncName::user(0, id.as_u32()), sig);
    let tramps = tramps.map(|t| module.declare_func_in_func(t, &mut ctx.func));
    let calls = calls.map(|t| module.declare_func_in_func(t, &mut ctx.func));
    let mut fctx = FunctionBuilderContext::new();
    let mut b = FunctionBuilder::new(&mut ctx.func, &mut fctx);
    let mut gen = gen::Gen::new(&mut b, prog, types, call_conv, tramps);
    gen.calls = Some(calls);
    gen.translate()?;
    let descs = std::mem::take(&mut gen.descs);
    b.finalize(module.isa().frontend_config());
    module.define_function(id, &mut ctx).ok()?;
    module.clear_context(&mut ctx);
    let code = arbor_jitcode::Code::new(module, id).ok()?;
    Some(Jit { code, descs, lanes: W })
}

/// Runs workgroup `wg` in one call, its lanes taking the next invocation as they finish;
/// `frames` holds `W` lane frames (the code's refills fill them).
pub(in crate::shader) fn run_workgroup(ctx: &Ctx, jit: &Jit, wg: &mut Wg, frames: &mut [u8]) {
    let mut run = Run::new(ctx, wg, &jit.descs);
    let mut next_check = run.wg.steps + CHECK_EVERY;
    let steps = jit.code.call(&mut run, frames, ctx.push);
    if account(&mut run, steps, &mut next_check) {
        flush(&mut run);
    }
}

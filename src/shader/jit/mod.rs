//! The native-code backend: each [`Program`] that `codegen::supported` accepts is compiled with
//! Cranelift at pipeline creation into one function that runs one invocation; a workgroup is a
//! loop over its invocations. The interpreter (`exec`) stays the reference: the JIT gives the
//! same register words op for op (`codegen`), reaches memory through the interpreter's own
//! access function (`helpers::mem`) except for in-bounds lane-frame and push-constant accesses,
//! and reports the same faults. The one unsafe step, calling the finalized code, is in the
//! `arbor-jitcode` crate.
//!
//! Fault order: the interpreter records a workgroup's faults lane group by lane group, op by
//! op, lane by lane; the JIT keys each fault by (lane group, progress, site, lane) and sorts by
//! that key, whatever order the invocations ran in. Progress is the invocation's block count on
//! the scalar backend and its taken back edges on the SIMD one (the interpreter's lanes run a
//! loop's rounds in step, a round's blocks in index order, which is also site order): the
//! interpreter's order wherever a group's lanes take the same back edges up to the faulting
//! access, acyclic divergence included (and the same records, ordered by that key, where
//! their loops run different round counts).
//!
//! Steps: the watchdog's step count is the sum of the blocks every invocation ran (the
//! interpreter counts lane-group block runs), polled at back edges every `CHECK_EVERY` blocks of
//! an invocation and between invocations.
use std::sync::OnceLock;

use cranelift_codegen::ir::{types, AbiParam, Function, UserFuncName};
use cranelift_codegen::settings::{self, Configurable};
use cranelift_frontend::{FunctionBuilder, FunctionBuilderContext};
use cranelift_jit::{JITBuilder, JITModule};
use cranelift_module::{Linkage, Module};

use super::exec::{check_watchdog, init_frame, Ctx, Wg, CHECK_EVERY};
use super::ir::Program;
use super::LANES;

mod codegen;
mod helpers;
mod simd;
#[cfg(test)]
mod tests;

use helpers::{MemDesc, Run, MAX_FAULTS, STOPPED};

/// A program compiled to native code.
pub(crate) struct Jit {
    code: arbor_jitcode::Code,
    descs: Vec<MemDesc>,
    /// Lanes per call: 1 (`codegen`, one invocation per call) or `simd::W` (`simd`, a
    /// workgroup per call); a call's frame holds that many lane frames.
    pub(super) lanes: usize,
}

impl std::fmt::Debug for Jit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Jit {{ {} lanes, {} memory sites }}", self.lanes, self.descs.len())
    }
}

/// Which pipelines are compiled, from `ARBOR_SHADER_JIT` (read once): `0` none, `scalar` every
/// program the scalar JIT can compile on the scalar JIT, `all` every program either backend
/// can compile (the SIMD one first), anything else (or unset) on the SIMD backend when
/// `simd::pays`, else on the scalar JIT (the SIMD one when the scalar one declines), and
/// programs neither takes, or that `codegen::prefers_interpreter` keeps there, on the
/// interpreter. Never on a host Cranelift does not support.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Mode {
    Off,
    Auto,
    Scalar,
    All,
}

fn mode() -> Mode {
    static MODE: OnceLock<Mode> = OnceLock::new();
    *MODE.get_or_init(|| match std::env::var("ARBOR_SHADER_JIT").as_deref() {
        _ if !cfg!(any(target_arch = "x86_64", target_arch = "aarch64")) => Mode::Off,
        Ok("0") => Mode::Off,
        Ok("all") => Mode::All,
        Ok("scalar") => Mode::Scalar,
        _ => Mode::Auto,
    })
}

/// The pipeline-creation choice: `prog` compiled, or None for the interpreter.
pub(crate) fn for_pipeline(prog: &Program) -> Option<Jit> {
    match mode() {
        Mode::Off => None,
        Mode::Scalar => compile(prog),
        Mode::Auto if !simd::pays(prog) => compile(prog).or_else(|| compile_simd(prog)),
        m => compile_simd(prog).or_else(|| if m == Mode::Auto && codegen::prefers_interpreter(prog) { None } else { compile(prog) }),
    }
}

/// Compiles `prog` for the SIMD backend (a workgroup per call on `simd::W` lanes), or None.
pub(crate) fn compile_simd(prog: &Program) -> Option<Jit> {
    if !cfg!(target_arch = "x86_64") {
        return None;
    }
    simd::compile(prog)
}

/// Compiles `prog`, or None when it uses something the JIT does not compile (it then runs on
/// the interpreter) or code generation fails.
pub(crate) fn compile(prog: &Program) -> Option<Jit> {
    if !codegen::supported(prog) {
        return None;
    }
    // Cranelift reports errors as values, but a panic inside it must not take pipeline
    // creation down: the interpreter can always run the program.
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| build(prog))).ok().flatten()
}

fn build(prog: &Program) -> Option<Jit> {
    let mut flags = settings::builder();
    flags.set("opt_level", "speed").ok()?;
    flags.set("use_colocated_libcalls", "false").ok()?;
    flags.set("is_pic", "false").ok()?;
    let isa = cranelift_native::builder().ok()?.finish(settings::Flags::new(flags)).ok()?;
    let call_conv = isa.default_call_conv();
    let mut module = JITModule::new(JITBuilder::with_isa(isa, cranelift_module::default_libcall_names()));
    let mut sig = module.make_signature();
    sig.params.extend((0..5).map(|_| AbiParam::new(types::I64)));
    sig.returns.push(AbiParam::new(types::I64));
    let id = module.declare_function("invocation", Linkage::Export, &sig).ok()?;
    let mut ctx = module.make_context();
    ctx.func = Function::with_name_signature(UserFuncName::user(0, id.as_u32()), sig);
    let mut fctx = FunctionBuilderContext::new();
    let mut b = FunctionBuilder::new(&mut ctx.func, &mut fctx);
    let mut gen = codegen::Gen::new(&mut b, prog, call_conv);
    gen.translate()?;
    let descs = std::mem::take(&mut gen.descs);
    b.finalize(module.isa().frontend_config());
    module.define_function(id, &mut ctx).ok()?;
    module.clear_context(&mut ctx);
    let code = arbor_jitcode::Code::new(module, id).ok()?;
    Some(Jit { code, descs, lanes: 1 })
}

/// Runs workgroup `wg` invocation by invocation (or in one call on the SIMD backend);
/// `frame` is this thread's buffer of `jit.lanes` lane frames.
pub(super) fn run_workgroup(ctx: &Ctx, jit: &Jit, wg: &mut Wg, frame: &mut [u8]) {
    if jit.lanes == simd::W {
        return simd::run_workgroup(ctx, jit, wg, frame);
    }
    let n = ctx.local.iter().product::<u32>();
    let id = wg.id;
    let mut run = Run::new(ctx, wg, &jit.descs);
    let mut next_check = run.wg.steps + CHECK_EVERY;
    for index in 0..n {
        init_frame(ctx, frame, id, index, n);
        run.invocation = index;
        run.kept = 0;
        run.accounted = 0;
        let steps = jit.code.call(&mut run, frame, ctx.push);
        if !account(&mut run, steps, &mut next_check) {
            return;
        }
        if (index + 1) % LANES as u32 == 0 {
            flush(&mut run);
        }
    }
    flush(&mut run);
}

/// After one call of the code: re-raises a helper's panic, adds the call's steps to the
/// workgroup's and polls the watchdog. False when the workgroup stops (its faults flushed).
fn account(run: &mut Run, steps: u64, next_check: &mut u64) -> bool {
    if let Some(p) = run.panic.take() {
        std::panic::resume_unwind(p);
    }
    if steps == STOPPED {
        flush(run);
        return false;
    }
    run.wg.steps += steps - run.accounted;
    if run.wg.steps >= *next_check {
        *next_check = run.wg.steps + CHECK_EVERY;
        if let Some(stop) = check_watchdog(run.ctx.watchdog, run.wg.steps) {
            run.wg.stopped = Some(stop);
            flush(run);
            return false;
        }
    }
    true
}

/// Moves a lane group's faults into the workgroup's report in the interpreter's order.
fn flush(run: &mut Run) {
    run.pending.sort_by_key(|p| p.0);
    for (_, f) in run.pending.drain(..) {
        if run.wg.faults.len() < MAX_FAULTS {
            run.wg.faults.push(f);
        }
    }
}

//! The one unsafe step of Arbor's shader JIT (src/shader/jit): turning the code pointer of a
//! finalized Cranelift module into a function and calling it. src/shader is safe Rust with no
//! access to the rest of the driver, so, as with `arbor-prefetch`, the step lives in a crate of
//! its own behind an interface that only accepts what the generated code expects.
//!
//! Soundness rests on the code generators (src/shader/jit/codegen.rs, one invocation per call,
//! and src/shader/jit/simd/, four): the code is generated from a checked `ir::Program`; every
//! memory access it makes either goes through a helper (safe Rust, reached with the context
//! reference it was given) or is an inline access to the lane frame(s) or push constants
//! guarded by a bounds check against the lengths passed here (the SIMD entry first checks that
//! the frame holds its lane frames). The helpers reach the running call's frame only through
//! `with_frame`, while the code is suspended in them.
use std::cell::Cell;

use cranelift_codegen::ir::{types, AbiParam, Signature};
use cranelift_jit::JITModule;
use cranelift_module::{FuncId, Module, ModuleError};

/// `extern "C" fn(context, frame, frame_len, push, push_len) -> u64`, the signature every
/// generated entry point has.
type Entry = extern "C" fn(*mut u8, *mut u8, u64, *const u8, u64) -> u64;

/// A finalized module and its entry point. The code is freed when this is dropped.
pub struct Code {
    module: Option<JITModule>,
    entry: Entry,
}

// SAFETY: after finalization the module's code and data are immutable; shared use only reads
// the entry pointer and calls it (the generated code keeps no state of its own), and the
// module itself is touched again only by `drop`, which has exclusive access.
unsafe impl Sync for Code {}
// SAFETY: as above; the module holds no thread-bound resources (memory mappings and a symbol
// table), so it may be freed from any thread.
unsafe impl Send for Code {}

impl Code {
    /// Finalizes `module` and takes `func`, a function defined in it. Its declared signature
    /// must be (i64 context, i64 frame, i64 frame length, i64 push, i64 push length) -> i64 in
    /// the host's default calling convention, what `Entry` spells; any other is refused.
    pub fn new(mut module: JITModule, func: FuncId) -> Result<Code, Box<ModuleError>> {
        let mut expected = Signature::new(module.isa().default_call_conv());
        expected.params = vec![AbiParam::new(types::I64); 5];
        expected.returns = vec![AbiParam::new(types::I64)];
        let decl = module.declarations().get_function_decl(func);
        if decl.signature != expected {
            let name = decl.linkage_name(func).into_owned();
            return Err(Box::new(ModuleError::IncompatibleSignature(name, expected, decl.signature.clone())));
        }
        module.finalize_definitions().map_err(Box::new)?;
        let ptr = module.get_finalized_function(func);
        // SAFETY: `ptr` is the finalized, executable code of `func`, whose declared signature
        // was checked above to be the one `Entry` spells (Cranelift compiles a definition only
        // against its declaration); it stays mapped while `module` lives, as long as `self`.
        let entry = unsafe { std::mem::transmute::<*const u8, Entry>(ptr) };
        Ok(Code { module: Some(module), entry })
    }

    /// Runs the entry point with `context` (which the code passes on, unread, to the helpers it
    /// calls) over one invocation's `frame` and the push constants.
    /// While the code runs, `with_frame` on this thread reaches `frame` (the helpers the code
    /// calls fill lane frames there).
    #[inline]
    pub fn call<T>(&self, context: &mut T, frame: &mut [u8], push: &[u8]) -> u64 {
        let ptr = frame.as_mut_ptr();
        let len = frame.len();
        let _lent = Lent::new(ptr, len);
        (self.entry)(context as *mut T as *mut u8, ptr, len as u64, push.as_ptr(), push.len() as u64)
    }
}

thread_local! {
    /// The frame of the call running on this thread (null when none, or while `with_frame`
    /// has it).
    static FRAME: Cell<(*mut u8, usize)> = const { Cell::new((std::ptr::null_mut(), 0)) };
}

/// Records a call's frame for its duration; restores the outer call's (a helper may run code
/// itself) when the call returns or unwinds.
struct Lent((*mut u8, usize));

impl Lent {
    fn new(ptr: *mut u8, len: usize) -> Lent {
        Lent(FRAME.with(|f| f.replace((ptr, len))))
    }
}

impl Drop for Lent {
    fn drop(&mut self) {
        FRAME.with(|f| f.set(self.0));
    }
}

/// Runs `f` over the frame of the code running on this thread: for the helpers that code calls
/// (safe Rust with no other way to the frame, which the call borrows). None outside a call, or
/// inside another `with_frame`.
pub fn with_frame<R>(f: impl FnOnce(&mut [u8]) -> R) -> Option<R> {
    let (ptr, len) = FRAME.with(|c| c.replace((std::ptr::null_mut(), 0)));
    if ptr.is_null() {
        return None;
    }
    // Gives the frame back when `f` returns or unwinds.
    let _back = Lent((ptr, len));
    // SAFETY: `ptr` and `len` are the slice `Code::call` borrowed exclusively for the call
    // still running on this thread (a finished call restores the slot it found, so a recorded
    // frame always belongs to a live call). The generated code is suspended inside the helper
    // that reached here and touches the frame again only after it returns, which is after `f`
    // has; the slot is empty while `f` runs, so no second slice of it exists at once.
    let frame = unsafe { std::slice::from_raw_parts_mut(ptr, len) };
    Some(f(frame))
}

impl Drop for Code {
    fn drop(&mut self) {
        if let Some(module) = self.module.take() {
            // SAFETY: `self` is being dropped, so no call through `entry` is running or can
            // start: every call borrows `self`.
            unsafe { module.free_memory() };
        }
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn no_frame_is_reached_outside_a_call() {
        assert!(super::with_frame(|f| f.len()).is_none());
    }
}

//! Out-of-line lane helpers that clobber no register. The SIMD code calls the interpreter's
//! helpers on rare paths (a NaN result); a System V call there clobbers every vector register,
//! and the register allocator then keeps the hot path's vectors in stack slots. These
//! trampolines use Cranelift's `preserve_all` convention (they save what they use, calls
//! included), take every lane's operands from a buffer and leave the results there, so the
//! calling code sees a call that clobbers nothing.
use cranelift_codegen::ir::{types, AbiParam, Function, InstBuilder, MemFlagsData, Signature, UserFuncName, Value};
use cranelift_codegen::isa::CallConv;
use cranelift_frontend::{FunctionBuilder, FunctionBuilderContext};
use cranelift_jit::JITModule;
use cranelift_module::{FuncId, Linkage, Module};

use super::gen::W;

/// Bytes of the buffer: up to three operands, then the results, each `W` i32 lanes.
pub(super) const BUF: u32 = 4 * W as u32 * 4;
/// Where the results start in the buffer.
pub(super) const OUT: i32 = 3 * W as i32 * 4;

/// Where lane `l` of operand `k` is in the buffer.
pub(super) const fn operand(k: usize, l: usize) -> i32 {
    ((k * W + l) * 4) as i32
}

/// Defines local function `name` of signature `sig`, its body written by `body` from the entry
/// block's parameters (the body ends with its return).
fn define_fn(module: &mut JITModule, name: &str, user: (u32, u32), sig: &Signature, body: impl FnOnce(&mut FunctionBuilder, &[Value])) -> Option<FuncId> {
    let id = module.declare_function(name, Linkage::Local, sig).ok()?;
    let mut ctx = module.make_context();
    ctx.func = Function::with_name_signature(UserFuncName::user(user.0, user.1), sig.clone());
    let mut fctx = FunctionBuilderContext::new();
    let mut b = FunctionBuilder::new(&mut ctx.func, &mut fctx);
    let entry = b.create_block();
    b.append_block_params_for_function_params(entry);
    b.switch_to_block(entry);
    let p = b.block_params(entry).to_vec();
    body(&mut b, &p);
    b.seal_all_blocks();
    b.finalize(module.isa().frontend_config());
    module.define_function(id, &mut ctx).ok()?;
    module.clear_context(&mut ctx);
    Some(id)
}

/// A System V signature of `n` i64 parameters and an i64 result.
fn helper_sig(call_conv: CallConv, n: usize) -> Signature {
    let mut helper = Signature::new(call_conv);
    helper.params.extend((0..n).map(|_| AbiParam::new(types::I64)));
    helper.returns.push(AbiParam::new(types::I64));
    helper
}

/// Defines `lanes1`..`lanes3`: (helper address, op code, buffer) in `preserve_all`; each calls
/// `helper(code, operand words…)` for every lane (32-bit operands zero-extended, results
/// truncated to 32 bits).
pub(super) fn define(module: &mut JITModule, call_conv: CallConv) -> Option<[FuncId; 3]> {
    let mut sig = Signature::new(CallConv::PreserveAll);
    sig.params.extend((0..3).map(|_| AbiParam::new(types::I64)));
    let ids: Option<Vec<FuncId>> = (1..=3usize)
        .map(|n| {
            define_fn(module, &format!("lanes{n}"), (1, n as u32), &sig, |b, p| {
                let helper = b.import_signature(helper_sig(call_conv, n + 1));
                let flags = MemFlagsData::trusted();
                for l in 0..W {
                    let mut args = vec![p[1]];
                    for k in 0..n {
                        let x = b.ins().load(types::I32, flags, p[2], operand(k, l));
                        args.push(b.ins().uextend(types::I64, x));
                    }
                    let call = b.ins().call_indirect(helper, p[0], &args);
                    let r = b.inst_results(call)[0];
                    let r = b.ins().ireduce(types::I32, r);
                    b.ins().store(flags, r, p[2], OUT + l as i32 * 4);
                }
                b.ins().return_(&[]);
            })
        })
        .collect();
    ids?.try_into().ok()
}

/// Most arguments a helper takes (`helpers::mem_lane`).
pub(super) const MAX_ARGS: usize = 7;

/// Defines `call1`..`call7`: (buffer) in `preserve_all`; each calls the System V function whose
/// address is the buffer's first word with the next `n` words and stores its result after them.
/// Every helper call of the SIMD code goes through one, so the vectors live across it stay in
/// registers (a System V call would clobber them all).
pub(super) fn define_calls(module: &mut JITModule, call_conv: CallConv) -> Option<[FuncId; MAX_ARGS]> {
    let mut sig = Signature::new(CallConv::PreserveAll);
    sig.params.push(AbiParam::new(types::I64));
    let ids: Option<Vec<FuncId>> = (1..=MAX_ARGS)
        .map(|n| {
            define_fn(module, &format!("call{n}"), (3, n as u32), &sig, |b, p| {
                let helper = b.import_signature(helper_sig(call_conv, n));
                let buf = p[0];
                let flags = MemFlagsData::trusted();
                let f = b.ins().load(types::I64, flags, buf, 0);
                let args: Vec<_> = (1..=n).map(|k| b.ins().load(types::I64, flags, buf, 8 * k as i32)).collect();
                let call = b.ins().call_indirect(helper, f, &args);
                let r = b.inst_results(call)[0];
                b.ins().store(flags, r, buf, 8 * (n as i32 + 1));
                b.ins().return_(&[]);
            })
        })
        .collect();
    ids?.try_into().ok()
}

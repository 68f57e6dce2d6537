//! What the generated code calls: `extern "C"` functions in safe Rust. The ALU helpers run
//! `alu`'s and `vmath`'s own functions (so the JIT cannot disagree with the interpreter on the
//! ops it does not emit inline); `mem` runs the interpreter's `access_one` for every access that
//! is not an in-bounds lane-frame, push-constant or host-span buffer access; `poll` is the
//! watchdog.
use super::super::alu;
use super::super::exec::{check_watchdog, init_frame, Ctx, Wg, CHECK_EVERY};
use super::super::exec_alu::{exec_bin, exec_tri, exec_un};
use super::super::exec_mem::{access_one, Access};
use super::super::ir::{AtomicOp, BinOp, Sc, Space, TriOp, UnOp, ELEMENT_SHIFT};
use super::super::memory::{Fault, FaultSpace};
use super::super::vmath;
use super::super::LANES;
use super::simd::W;

/// Faults kept per workgroup (the interpreter's limit).
pub(super) const MAX_FAULTS: usize = 16;

/// The entry point's return value when the watchdog stopped the invocation.
pub(super) const STOPPED: u64 = u64::MAX;

/// What a memory helper call does.
#[derive(Clone, Copy, Debug)]
pub(super) enum MemKind {
    Load,
    Store,
    Atomic(AtomicOp),
}

/// One memory-op site of the program: the helper's `desc` argument indexes these (in program
/// order, which is also the fault-order key within a block).
#[derive(Clone, Copy, Debug)]
pub(super) struct MemDesc {
    pub ty: Sc,
    pub space: Space,
    pub kind: MemKind,
}

/// Where a fault stands in the interpreter's order inside one workgroup: the invocation's lane
/// group, its progress (blocks run on the scalar backend, back edges taken on the SIMD one),
/// the site, its lane in the group.
pub(super) type FaultKey = (u32, u64, u32, u32);

/// The context every helper gets: the dispatch, this workgroup, and the running invocation.
pub(super) struct Run<'r, 'a> {
    pub ctx: &'r Ctx<'a>,
    pub wg: &'r mut Wg,
    pub descs: &'r [MemDesc],
    pub invocation: u32,
    /// This workgroup's faults, sorted into the interpreter's order when it is done.
    pub pending: Vec<(FaultKey, Fault)>,
    /// Faults of the running invocation kept in `pending` (the first `MAX_FAULTS` are all a
    /// workgroup's report can need).
    pub kept: usize,
    /// Steps of the running call already added to the workgroup's count.
    pub accounted: u64,
    /// A panic caught in a helper (a `Memory` implementation's): unwinding cannot cross the
    /// generated code, so the helper keeps it, later helpers do nothing, the next poll stops
    /// the invocation, and the caller resumes the unwind once the code has returned.
    pub panic: Option<Box<dyn std::any::Any + Send>>,
    /// SIMD calls (a whole workgroup each): every lane's invocation and `kept`, the next
    /// invocation to hand out and the workgroup's count.
    pub lane_inv: [u32; W],
    pub lane_kept: [usize; W],
    pub next: u32,
    pub count: u32,
    /// `Ctx::spans`, for the generated code's inline buffer accesses (`SPANS_AT`).
    pub spans: *const [u64; 2],
}

/// Where the generated code finds `Run::spans` in the context it is passed.
pub(super) const SPANS_AT: i32 = std::mem::offset_of!(Run<'static, 'static>, spans) as i32;

impl<'r, 'a> Run<'r, 'a> {
    pub fn new(ctx: &'r Ctx<'a>, wg: &'r mut Wg, descs: &'r [MemDesc]) -> Self {
        let count = ctx.local.iter().product::<u32>();
        Run { ctx, wg, descs, invocation: 0, pending: Vec::new(), kept: 0, accounted: 0, panic: None, lane_inv: [0; W], lane_kept: [0; W], next: 0, count, spans: ctx.spans.as_ptr() }
    }
}

/// SIMD calls: hands the next invocations to the lanes in `done` (a bit per lane) and fills
/// their frames. The lanes refilled (a bit each) in the low word, the invocations still to hand
/// out in the high word.
pub(super) extern "C" fn refill(run: &mut Run, done: u64) -> u64 {
    if run.panic.is_some() {
        return 0;
    }
    let fs = run.ctx.prog.lane_frame.len();
    let (ctx, id, count) = (run.ctx, run.wg.id, run.count);
    let mut got = 0u64;
    arbor_jitcode::with_frame(|frame| {
        for l in (0..W).filter(|&l| done >> l & 1 != 0) {
            let Some(f) = frame.get_mut(l * fs..(l + 1) * fs).filter(|_| run.next < count) else { break };
            init_frame(ctx, f, id, run.next, count);
            run.lane_inv[l] = run.next;
            run.lane_kept[l] = 0;
            run.next += 1;
            got |= 1 << l;
        }
    });
    got | ((count - run.next) as u64) << 32
}

/// SIMD calls: `mem` for lane `lane` of the call.
pub(super) extern "C" fn mem_lane(run: &mut Run, desc: u64, at: u64, a: u64, b: u64, steps: u64, lane: u64) -> u64 {
    let lane = lane as usize % W;
    run.invocation = run.lane_inv[lane];
    run.kept = run.lane_kept[lane];
    let v = mem(run, desc, at, a, b, steps);
    run.lane_kept[lane] = run.kept;
    v
}

/// Memory access `desc` at `at` (value `a`, comparator `b`), as the interpreter does it.
pub(super) extern "C" fn mem(run: &mut Run, desc: u64, at: u64, a: u64, b: u64, steps: u64) -> u64 {
    if run.panic.is_some() {
        return 0;
    }
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| access(run, desc, at, a, b, steps))) {
        Ok(v) => v,
        Err(p) => {
            run.panic = Some(p);
            0
        }
    }
}

fn access(run: &mut Run, desc: u64, at: u64, a: u64, b: u64, steps: u64) -> u64 {
    let d = run.descs[desc as usize];
    let acc = match d.kind {
        MemKind::Load => Access::Read,
        MemKind::Store => Access::Write(a),
        MemKind::Atomic(op) => Access::Rmw(op, a, b),
    };
    // The lane frame is reached inline; a lane access comes here only when out of bounds, and
    // an empty frame makes it the same fault.
    match access_one(run.ctx, &mut [], run.wg, d.space, at, d.ty, acc) {
        Ok(v) => alu::norm(d.ty, v),
        Err((kind, fspace)) => {
            run.wg.fault_count += 1;
            if run.kept < MAX_FAULTS {
                run.kept += 1;
                let at = if matches!(fspace, FaultSpace::ArrayElement { .. }) { at & ((1 << ELEMENT_SHIFT) - 1) } else { at };
                let write = !matches!(acc, Access::Read);
                let fault = Fault { kind, space: fspace, at, len: d.ty.size(), write, workgroup: run.wg.id, invocation: run.invocation };
                let inv = run.invocation;
                run.pending.push(((inv / LANES as u32, steps, desc as u32, inv % LANES as u32), fault));
            }
            0
        }
    }
}

/// Adds the invocation's steps to the workgroup's count and asks the watchdog: the step count
/// at which to poll again, or 0 to stop.
pub(super) extern "C" fn poll(run: &mut Run, steps: u64) -> u64 {
    if run.panic.is_some() {
        return 0;
    }
    run.wg.steps += steps - run.accounted;
    run.accounted = steps;
    match check_watchdog(run.ctx.watchdog, run.wg.steps) {
        Some(stop) => {
            run.wg.stopped = Some(stop);
            0
        }
        None => steps + CHECK_EVERY,
    }
}

const TYS: [Sc; 5] = [Sc::Bool, Sc::I32, Sc::I64, Sc::F32, Sc::F64];

#[rustfmt::skip]
const BINS: &[BinOp] = {
    use BinOp::*;
    &[IAdd, ISub, IMul, UDiv, SDiv, UMod, SRem, SMod, Shl, ShrL, ShrA, And, Or, Xor,
     IEq, INe, ULt, ULe, UGt, UGe, SLt, SLe, SGt, SGe, FAdd, FSub, FMul, FDiv, FRem, FMod,
     FOrdEq, FOrdNe, FOrdLt, FOrdLe, FOrdGt, FOrdGe, FUnordEq, FUnordNe, FUnordLt, FUnordLe, FUnordGt, FUnordGe,
     LEq, LNe, LAnd, LOr, FMin, FMax, NMin, NMax, UMin, UMax, SMin, SMax, Pow, Atan2, Step, Ldexp,
     UMulHi, SMulHi, AddCarry, SubBorrow]
};

#[rustfmt::skip]
const UNS: &[UnOp] = {
    use UnOp::*;
    &[SNeg, FNeg, Not, LNot, Bitcast, UConvert, SConvert, FConvert, ConvertFToU, ConvertFToS, ConvertUToF, ConvertSToF,
     IsNan, IsInf, FAbs, SAbs, FSign, SSign, Floor, Ceil, Trunc, Round, RoundEven, Fract,
     Sqrt, InverseSqrt, Exp, Log, Exp2, Log2, Sin, Cos, Tan, Asin, Acos, Atan, Sinh, Cosh, Tanh, Asinh, Acosh, Atanh,
     Radians, Degrees, FindILsb, FindSMsb, FindUMsb, BitCount, BitReverse]
};

#[rustfmt::skip]
const TRIS: &[TriOp] = {
    use TriOp::*;
    &[Fma, FClamp, NClamp, UClamp, SClamp, FMix, SmoothStep, BitFieldUExtract, BitFieldSExtract]
};

pub(super) fn ty_code(ty: Sc) -> u64 {
    TYS.iter().position(|&t| t == ty).unwrap_or(0) as u64
}

/// The helper code of a binary op: op index, type index; None for an op missing from the
/// table (the program then falls back to the interpreter).
pub(super) fn bin_code(op: BinOp, ty: Sc) -> Option<u64> {
    BINS.iter().position(|&o| o == op).map(|i| i as u64 | ty_code(ty) << 8)
}
pub(super) fn un_code(op: UnOp, ty: Sc, from: Sc) -> Option<u64> {
    UNS.iter().position(|&o| o == op).map(|i| i as u64 | ty_code(ty) << 8 | ty_code(from) << 16)
}
pub(super) fn tri_code(op: TriOp, ty: Sc) -> Option<u64> {
    TRIS.iter().position(|&o| o == op).map(|i| i as u64 | ty_code(ty) << 8)
}

fn ty_of(code: u64, shift: u32) -> Sc {
    TYS[((code >> shift) & 0xFF) as usize % TYS.len()]
}

// The generic helpers run the interpreter's own lane arms (on a group whose lanes all hold the
// operands) rather than `alu`'s scalar functions: where IEEE-754 leaves a choice (the payload
// and sign of a NaN from two NaN operands, the zero `min` returns for ±0), the JIT then makes
// the interpreter's choice.
pub(super) extern "C" fn bin(code: u64, a: u64, b: u64) -> u64 {
    let mut regs = [[a; LANES], [b; LANES], [0; LANES]];
    exec_bin(&mut regs, BINS[(code & 0xFF) as usize % BINS.len()], ty_of(code, 8), 2, FULL, 0, 1);
    regs[2][0]
}
pub(super) extern "C" fn un(code: u64, a: u64) -> u64 {
    let mut regs = [[a; LANES], [0; LANES]];
    exec_un(&mut regs, UNS[(code & 0xFF) as usize % UNS.len()], ty_of(code, 8), ty_of(code, 16), 1, FULL, 0);
    regs[1][0]
}
pub(super) extern "C" fn tri(code: u64, a: u64, b: u64, c: u64) -> u64 {
    let mut regs = [[a; LANES], [b; LANES], [c; LANES], [0; LANES]];
    exec_tri(&mut regs, TRIS[(code & 0xFF) as usize % TRIS.len()], ty_of(code, 8), 3, FULL, 0, 1, 2);
    regs[3][0]
}
pub(super) extern "C" fn bit_insert(ty: u64, base: u64, insert: u64, offset: u64, count: u64) -> u64 {
    alu::bit_insert(ty_of(ty, 0), base, insert, offset, count)
}

/// Every lane of a group.
const FULL: u32 = (1 << LANES) - 1;

/// The F32 functions the interpreter takes from `vmath`, called with floats in registers:
/// `vmath`'s one-value form, and the interpreter's lane form for a NaN result (whose bits the
/// two forms may choose differently).
pub(super) fn f32_unary(op: UnOp) -> Option<extern "C" fn(f32) -> f32> {
    macro_rules! one {
        ($one:path, $lanes:path) => {{
            extern "C" fn f(x: f32) -> f32 {
                let r = $one(x);
                if r.is_nan() { $lanes(&[x; LANES])[0] } else { r }
            }
            f
        }};
    }
    Some(match op {
        UnOp::Sin => one!(vmath::sin1, vmath::sin),
        UnOp::Cos => one!(vmath::cos1, vmath::cos),
        UnOp::Tan => one!(vmath::tan1, vmath::tan),
        UnOp::Exp => one!(vmath::exp1, vmath::exp),
        UnOp::Exp2 => one!(vmath::exp2_1, vmath::exp2),
        UnOp::Log => one!(vmath::log1, vmath::log),
        UnOp::Log2 => one!(vmath::log2_1, vmath::log2),
        UnOp::InverseSqrt => one!(vmath::inverse_sqrt1, vmath::inverse_sqrt),
        UnOp::Atan => one!(vmath::atan1, vmath::atan),
        _ => return None,
    })
}

pub(super) fn f32_binary(op: BinOp) -> Option<extern "C" fn(f32, f32) -> f32> {
    extern "C" fn pow(x: f32, y: f32) -> f32 {
        let r = vmath::pow1(x, y);
        if r.is_nan() { vmath::pow(&[x; LANES], &[y; LANES])[0] } else { r }
    }
    extern "C" fn atan2(y: f32, x: f32) -> f32 {
        let r = vmath::atan2_1(y, x);
        if r.is_nan() { vmath::atan2(&[y; LANES], &[x; LANES])[0] } else { r }
    }
    match op {
        BinOp::Pow => Some(pow),
        BinOp::Atan2 => Some(atan2),
        _ => None,
    }
}

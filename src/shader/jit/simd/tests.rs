//! The SIMD backend against the interpreter (the reference) and `alu`: every test shader it
//! accepts over the same memory on both (workgroup sizes that leave a partial last call
//! included), each ALU op family over edge values lane by lane, the vectorised sin/cos/exp
//! over many values, the watchdog, and thread-count independence.
use std::path::PathBuf;
use std::sync::Arc;

use super::super::tests::{operands, run_filled, shader_files, words};
use crate::shader::ir::{self, BinOp, Op, Program, Sc, Space, TriOp, UnOp};
use crate::shader::tests::compile_with;
use crate::shader::{alu, dispatch, HostMemory, Module, Pipeline, Stop, Watchdog};

fn simd(p: &Pipeline) -> Option<Pipeline> {
    let jit = super::super::compile_simd(&p.program)?;
    assert_eq!(jit.lanes, super::W);
    Some(Pipeline { jit: Some(Arc::new(jit)), ..p.clone() })
}

fn bench(name: &str) -> Pipeline {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("bench/shaders").join(name);
    let words: Vec<u32> = std::fs::read(path).unwrap().chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
    Pipeline::compute(&Module::parse(&words).unwrap(), "main", &[]).unwrap()
}

#[test]
fn the_bench_kernels_compile_for_w_lanes() {
    for name in ["compute_alu.spv", "compute_divergent.spv", "compute_memory.spv"] {
        assert!(simd(&bench(name)).is_some(), "{name}");
    }
}

#[test]
fn float_and_memory_free_loops_choose_the_simd_backend_and_buffer_work_the_scalar_one() {
    for name in ["compute_alu.spv", "compute_divergent.spv"] {
        assert!(super::pays(&bench(name).program), "{name}");
    }
    assert!(!super::pays(&bench("compute_memory.spv").program));
}

#[test]
fn every_test_shader_it_accepts_gives_the_interpreters_memory_and_faults() {
    let mut compiled = Vec::new();
    for name in shader_files() {
        let Ok(variants) = std::panic::catch_unwind(|| compile_with(&name, &[])) else { continue };
        for (what, words) in variants {
            let Ok(module) = Module::parse(&words) else { continue };
            let Ok(p) = Pipeline::compute(&module, "main", &[]) else { continue };
            let Some(fast) = simd(&p) else { continue };
            // The shader's own size, and sizes whose last call of W lanes is partial (the
            // built-ins follow the pipeline's size on both backends), for shaders that do not
            // build their indices from the workgroup size (whose invocations would then race).
            let sized = ["WorkGroupSize", "local_size_x_id", "NumWorkGroups", "shared"];
            let src = std::fs::read_to_string(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/shaders").join(&name)).unwrap_or_default();
            let locals = if sized.iter().any(|w| src.contains(w)) { &[p.local_size][..] } else { &[p.local_size, [1, 1, 1], [5, 1, 1], [3, 3, 1], [7, 2, 1], [17, 1, 1], [33, 1, 1], [100, 1, 1]] };
            for &local in locals {
                let (fast, interp) = (Pipeline { local_size: local, ..fast.clone() }, Pipeline { local_size: local, ..p.interpreted() });
                for style in 0..3 {
                    let (want, want_mem) = run_filled(&interp, style, [3, 2, 1]);
                    let (got, got_mem) = run_filled(&fast, style, [3, 2, 1]);
                    assert_eq!(got.stopped.is_some(), want.stopped.is_some(), "{what} {local:?} fill {style}: {got:?} vs {want:?}");
                    if want.stopped.is_none() {
                        assert_eq!(got, want, "{what} {local:?} fill {style}: reports");
                        for (k, (g, w)) in got_mem.iter().zip(&want_mem).enumerate() {
                            let first = g.iter().zip(w).position(|(a, b)| a != b);
                            assert!(first.is_none(), "{what} {local:?} fill {style}: buffer {k} differs first at byte {first:?}");
                        }
                    }
                }
            }
            compiled.push(what);
        }
    }
    for name in ["arith.comp", "control.comp", "oob.comp", "spin.comp", "alu_loop.comp"] {
        assert_eq!(compiled.iter().filter(|w| w.starts_with(&format!("{name} "))).count(), 2, "{name} compiled: {compiled:?}");
    }
}

/// One op per invocation over 64 invocations (16 calls): operands loaded as `from` from
/// binding 0, the result stored in its own type (a whole word: the buffer starts zeroed).
fn op_program(op: Op, from: Sc, arity: usize, result: Sc) -> Program {
    use ir::builtin_offset as bo;
    let (gid, eight, n8) = (0, 1, 2);
    let mut ops = vec![Op::Load { ty: Sc::I32, space: Space::Lane, dst: 3, addr: gid }];
    for k in 0..arity as u32 {
        ops.push(Op::Index { dst: 4, base: n8, index: 3, index_ty: Sc::I32, stride: 8 });
        ops.push(Op::Index { dst: 5, base: 4, index: eight, index_ty: Sc::I64, stride: k as u64 * 64 });
        ops.push(Op::Load { ty: from, space: Space::Buffer(0), dst: 10 + k, addr: 5 });
    }
    ops.push(op);
    ops.push(Op::Index { dst: 6, base: n8, index: 3, index_ty: Sc::I32, stride: 8 });
    ops.push(Op::Store { ty: result, space: Space::Buffer(1), addr: 6, src: 20 });
    crate::shader::tests::two_buffer_program(vec![ir::Block { ops, term: ir::Term::Exit, phi_in: vec![], edge_moves: vec![] }], 24, vec![(gid, bo::GLOBAL_INVOCATION_ID as u64), (eight, 8), (n8, 0)], bo::END as usize)
}

/// The op's results on the SIMD backend against `want` for each invocation; false when the
/// backend declines the program.
fn check_op(op: Op, from: Sc, arity: usize, result: Sc, want: impl Fn(&[u64; 3]) -> u64) -> bool {
    let prog = op_program(op.clone(), from, arity, result);
    let Some(jit) = super::super::compile_simd(&prog) else { return false };
    let p = Pipeline { program: Arc::new(prog), local_size: [64, 1, 1], push_constant_size: 0, jit: Some(Arc::new(jit)) };
    let vals = operands(arity);
    let mut input = vec![0u8; 64 * 8 * 3];
    for (i, v) in vals.iter().enumerate() {
        for (k, w) in v.iter().enumerate() {
            input[(k * 64 + i) * 8..][..8].copy_from_slice(&w.to_le_bytes());
        }
    }
    let mut mem = HostMemory::new();
    let (a, o) = (mem.add_buffer(&input), mem.add_buffer(&[0; 64 * 8]));
    mem.bind(0, 0, a);
    mem.bind(0, 1, o);
    assert!(dispatch(&p, &mem, &[], [1, 1, 1], [0; 3], &Watchdog::default()).is_clean());
    let out = mem.bytes(o);
    for (i, v) in vals.iter().enumerate() {
        let v = v.map(|w| alu::norm(from, if from.size() == 4 { w & 0xFFFF_FFFF } else { w }));
        let got = u64::from_le_bytes(out[i * 8..][..8].try_into().unwrap());
        let want = alu::norm(result, want(&v));
        assert_eq!(got, want, "{op:?} on {v:x?} (lane {})", i % super::W);
    }
    true
}

const TYPES: [Sc; 5] = [Sc::Bool, Sc::I32, Sc::I64, Sc::F32, Sc::F64];

#[test]
fn binary_ops_match_alu_on_edge_values() {
    use BinOp::*;
    let ops = [
        IAdd, ISub, IMul, UDiv, SDiv, UMod, SRem, SMod, Shl, ShrL, ShrA, And, Or, Xor, IEq, INe, ULt, ULe, UGt, UGe, SLt, SLe, SGt,
        SGe, FAdd, FSub, FMul, FDiv, FRem, FMod, FOrdEq, FOrdNe, FOrdLt, FOrdLe, FOrdGt, FOrdGe, FUnordEq, FUnordNe, FUnordLt,
        FUnordLe, FUnordGt, FUnordGe, LEq, LNe, LAnd, LOr, FMin, FMax, NMin, NMax, UMin, UMax, SMin, SMax, Pow, Atan2, Step,
        Ldexp, UMulHi, SMulHi, AddCarry, SubBorrow,
    ];
    let mut n = 0;
    for op in ops {
        for ty in TYPES {
            let result = if super::types::bool_result(op) { Sc::Bool } else { ty };
            n += check_op(Op::Bin { op, ty, dst: 20, a: 10, b: 11 }, ty, 2, result, |v| alu::bin(op, ty, v[0], v[1])) as usize;
        }
    }
    assert!(n >= ops.len() * 3, "{n} compiled");
}

#[test]
fn unary_ops_and_conversions_match_alu_on_edge_values() {
    use UnOp::*;
    let ops = [
        SNeg, FNeg, Not, LNot, Bitcast, UConvert, SConvert, FConvert, ConvertFToU, ConvertFToS, ConvertUToF, ConvertSToF, IsNan,
        IsInf, FAbs, SAbs, FSign, SSign, Floor, Ceil, Trunc, Round, RoundEven, Fract, Sqrt, InverseSqrt, Exp, Log, Exp2, Log2,
        Sin, Cos, Tan, Asin, Acos, Atan, Sinh, Cosh, Tanh, Asinh, Acosh, Atanh, Radians, Degrees, FindILsb, FindSMsb, FindUMsb,
        BitCount, BitReverse,
    ];
    let mut n = 0;
    for op in ops {
        for ty in TYPES {
            for from in TYPES {
                n += check_op(Op::Un { op, ty, from, dst: 20, a: 10 }, from, 1, ty, |v| alu::un(op, ty, from, v[0])) as usize;
            }
        }
    }
    assert!(n >= ops.len() * 5, "{n} compiled");
}

#[test]
fn ternary_ops_select_and_bit_insert_match_alu_on_edge_values() {
    use TriOp::*;
    for op in [Fma, FClamp, NClamp, UClamp, SClamp, FMix, SmoothStep, BitFieldUExtract, BitFieldSExtract] {
        for ty in [Sc::I32, Sc::F32, Sc::I64, Sc::F64] {
            let want = |v: &[u64; 3]| alu::tri(op, ty, v[0], v[1], v[2]);
            // Bit-field offsets and counts are I32 whatever the base's width.
            if !matches!(op, BitFieldUExtract | BitFieldSExtract) || ty.size() == 4 {
                assert!(check_op(Op::Tri { op, ty, dst: 20, a: 10, b: 11, c: 12 }, ty, 3, ty, want), "{op:?} {ty:?}");
            }
        }
    }
    assert!(check_op(Op::BitInsert { ty: Sc::I32, dst: 20, base: 10, insert: 11, offset: 12, count: 12 }, Sc::I32, 3, Sc::I32, |v| {
        alu::bit_insert(Sc::I32, v[0], v[1], v[2], v[2])
    }));
    // Operands loaded as Bool: a lane-mask condition choosing between lane masks.
    assert!(check_op(Op::Select { dst: 20, cond: 10, a: 11, b: 12 }, Sc::Bool, 3, Sc::Bool, |v| if v[0] != 0 { v[1] } else { v[2] }));
}

#[test]
fn vectorised_float_functions_match_vmath_over_many_values() {
    use UnOp::*;
    const N: usize = 1 << 14;
    let rnd = words(0x9E37_79B9_7F4A_7C15, N);
    let vals: Vec<u64> = rnd
        .iter()
        .enumerate()
        .map(|(i, &w)| if i % 2 == 0 { w & 0xFFFF_FFFF } else { ((w % 200_001) as f32 / 1000.0 - 100.0).to_bits() as u64 })
        .collect();
    for op in [Sin, Cos, Exp, Sqrt, FNeg, FAbs] {
        let prog = op_program(Op::Un { op, ty: Sc::F32, from: Sc::F32, dst: 20, a: 10 }, Sc::F32, 1, Sc::F32);
        let jit = super::super::compile_simd(&prog).expect("compiles");
        let p = Pipeline { program: Arc::new(prog), local_size: [64, 1, 1], push_constant_size: 0, jit: Some(Arc::new(jit)) };
        let input: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        let run = |p: &Pipeline| {
            let mut mem = HostMemory::new();
            let (a, o) = (mem.add_buffer(&input), mem.add_buffer(&vec![0; N * 8]));
            mem.bind(0, 0, a);
            mem.bind(0, 1, o);
            assert!(dispatch(p, &mem, &[], [(N / 64) as u32, 1, 1], [0; 3], &Watchdog::default()).is_clean());
            mem.bytes(o)
        };
        let (out, want) = (run(&p), run(&p.interpreted()));
        for (i, &v) in vals.iter().enumerate() {
            let got = u64::from_le_bytes(out[i * 8..][..8].try_into().unwrap());
            let interp = u64::from_le_bytes(want[i * 8..][..8].try_into().unwrap());
            assert_eq!(got, interp, "{op:?}({:e} = {v:#x}) against the interpreter", f32::from_bits(v as u32));
            let reference = alu::un(op, Sc::F32, Sc::F32, v);
            if !f32::from_bits(reference as u32).is_nan() {
                assert_eq!(got, reference, "{op:?}({:e} = {v:#x}) against alu", f32::from_bits(v as u32));
            }
        }
    }
}

fn compiled(name: &str) -> Vec<(String, Pipeline)> {
    compile_with(name, &[])
        .into_iter()
        .map(|(what, words)| {
            let p = Pipeline::compute(&Module::parse(&words).unwrap(), "main", &[]).unwrap();
            (what, simd(&p).expect("compiles for W lanes"))
        })
        .collect()
}

#[test]
fn the_watchdog_stops_simd_code_that_does_not_terminate() {
    use std::sync::atomic::AtomicBool;
    for (what, p) in compiled("spin.comp") {
        let mut mem = HostMemory::new();
        let b = mem.add_buffer(&[0; 8]);
        mem.bind(0, 0, b);
        let budget = Watchdog { step_budget: Some(100_000), ..Watchdog::default() };
        assert_eq!(dispatch(&p, &mem, &[], [4, 1, 1], [0; 3], &budget).stopped, Some(Stop::StepBudget), "{what}");
        let deadline = Watchdog { deadline: Some(std::time::Instant::now() + std::time::Duration::from_millis(50)), ..Watchdog::default() };
        assert_eq!(dispatch(&p, &mem, &[], [2, 1, 1], [0; 3], &deadline).stopped, Some(Stop::Deadline), "{what}");
        let cancel = Watchdog { cancel: Some(Arc::new(AtomicBool::new(true))), ..Watchdog::default() };
        assert_eq!(dispatch(&p, &mem, &[], [2, 1, 1], [0; 3], &cancel).stopped, Some(Stop::Cancelled), "{what}");
    }
}

#[test]
fn simd_results_do_not_depend_on_thread_count() {
    for (what, p) in compiled("control.comp") {
        let p = Pipeline { local_size: [7, 3, 1], ..p };
        let run_on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| run_filled(&p, 1, [5, 1, 1]))
        };
        let one = run_on(1);
        assert!(one.1.iter().flatten().any(|&b| b != 0), "{what}");
        assert_eq!(run_on(2), one, "{what}");
        assert_eq!(run_on(3), one, "{what}");
    }
}

/// compute_alu.spv (the float loop the backend exists for) at workgroup sizes that are and are
/// not multiples of W, with `n` cutting the last workgroup short (lanes that leave at once
/// beside lanes that loop): the interpreter's output bits on 1 and 3 threads.
#[test]
fn the_alu_kernel_gives_the_interpreters_bits_at_every_workgroup_size() {
    let base = bench("compute_alu.spv");
    let fast = simd(&base).expect("compiles");
    for local in [1u32, 3, 5, 8, 17, 33, 64, 100] {
        let groups = 3u32;
        let n = groups * local - local / 2 - 1;
        let mut push = Vec::new();
        push.extend_from_slice(&n.to_le_bytes());
        push.extend_from_slice(&5u32.to_le_bytes());
        let run = |p: &Pipeline, threads: usize| {
            let mut mem = HostMemory::new();
            let out = mem.add_buffer(&vec![0xA5; (groups * local) as usize * 4]);
            mem.bind(0, 0, out);
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let report = pool.install(|| dispatch(p, &mem, &push, [groups, 1, 1], [0; 3], &Watchdog::default()));
            assert!(report.is_clean(), "local {local}: {report:?}");
            mem.bytes(out)
        };
        let want = run(&Pipeline { local_size: [local, 1, 1], ..base.interpreted() }, 2);
        let p = Pipeline { local_size: [local, 1, 1], ..fast.clone() };
        for threads in [1, 3] {
            let got = run(&p, threads);
            let first = got.iter().zip(&want).position(|(a, b)| a != b);
            assert!(first.is_none(), "local {local}, {threads} threads: differs first at byte {first:?}");
        }
        // The invocations past `n` wrote nothing; the others wrote a number.
        let word = |i: usize| u32::from_le_bytes(want[i * 4..][..4].try_into().unwrap());
        assert_eq!(word(n as usize), 0xA5A5_A5A5, "local {local}");
        assert!(f32::from_bits(word(n as usize - 1)).is_finite(), "local {local}");
    }
}

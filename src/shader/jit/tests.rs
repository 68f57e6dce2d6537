//! The JIT against the interpreter (the reference) and against `alu`: every test shader over
//! the same memory on both backends, each ALU op family over edge values, and the watchdog,
//! fault containment and thread-count independence under the JIT.
use std::path::PathBuf;

use crate::shader::ir::{self, BinOp, Op, Program, Sc, Space, TriOp, UnOp};
use crate::shader::tests::compile_with;
use crate::shader::{alu, dispatch, DispatchReport, HostMemory, Module, Pipeline, Stop, Watchdog};

/// A small deterministic generator (xorshift), so failures reproduce.
pub(super) fn words(seed: u64, n: usize) -> Vec<u64> {
    let mut x = seed | 1;
    (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        })
        .collect()
}

/// Buffer contents of one fill style: raw random words, small integers, small floats.
fn fill(style: usize, seed: u64, bytes: usize) -> Vec<u8> {
    words(seed, bytes / 4)
        .into_iter()
        .flat_map(|w| {
            let v = match style {
                0 => w as u32,
                1 => (w % 37) as u32,
                _ => ((w % 2001) as f32 / 64.0 - 10.0).to_bits(),
            };
            v.to_le_bytes()
        })
        .collect()
}

/// Runs `p` over fresh memory of fill `style`: every binding bound (four elements for an
/// array), push constants filled the same way (device addresses of the buffers for style 1).
pub(super) fn run_filled(p: &Pipeline, style: usize, groups: [u32; 3]) -> (DispatchReport, Vec<Vec<u8>>) {
    let mut mem = HostMemory::new();
    let mut ids = Vec::new();
    for (k, b) in p.bindings().iter().enumerate() {
        for e in 0..if b.count == 1 { 1 } else { 4 } {
            let id = mem.add_buffer(&fill(style, 7 + 31 * k as u64 + e, 4096));
            if b.count == 1 {
                mem.bind(b.set, b.binding, id);
            } else {
                mem.bind_element(b.set, b.binding, e as u32, id);
            }
            ids.push(id);
        }
    }
    let mut push = fill(style, 99, (p.push_constant_size as usize).next_multiple_of(8));
    if style == 1 {
        // Addresses into a buffer of their own: one a descriptor also reaches would let one
        // invocation's store race with another's load, whose order the backends may choose
        // differently.
        let target = mem.add_buffer(&fill(style, 5, 4096));
        for (k, w) in push.chunks_mut(8).enumerate() {
            w.copy_from_slice(&(mem.device_address(target) + 16 * k as u64).to_le_bytes());
        }
        ids.push(target);
    }
    let budget = Watchdog { step_budget: Some(300_000), ..Watchdog::default() };
    let report = dispatch(p, &mem, &push, groups, [0; 3], &budget);
    (report, ids.iter().map(|&i| mem.bytes(i)).collect())
}

pub(super) fn shader_files() -> Vec<String> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/shaders");
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| n.ends_with(".comp") || n.ends_with(".spvasm"))
        .collect();
    names.sort();
    names
}

#[test]
fn every_test_shader_gives_the_interpreters_memory_and_faults() {
    let mut compiled = Vec::new();
    for name in shader_files() {
        // Shaders that need defines to build belong to other tests.
        let Ok(variants) = std::panic::catch_unwind(|| compile_with(&name, &[])) else { continue };
        for (what, words) in variants {
            // Modules Arbor rejects (sampled images) are other tests' business.
            let Ok(module) = Module::parse(&words) else { continue };
            let Ok(p) = Pipeline::compute(&module, "main", &[]) else { continue };
            let Some(jit) = p.compiled() else { continue };
            let interp = p.interpreted();
            for style in 0..3 {
                let (want, want_mem) = run_filled(&interp, style, [3, 2, 1]);
                let (got, got_mem) = run_filled(&jit, style, [3, 2, 1]);
                assert_eq!(got.stopped.is_some(), want.stopped.is_some(), "{what} fill {style}: {got:?} vs {want:?}");
                if want.stopped.is_none() {
                    assert_eq!(got, want, "{what} fill {style}: reports");
                    for (k, (g, w)) in got_mem.iter().zip(&want_mem).enumerate() {
                        let first = g.iter().zip(w).position(|(a, b)| a != b);
                        assert!(first.is_none(), "{what} fill {style}: buffer {k} differs first at byte {first:?}");
                    }
                }
            }
            compiled.push(what);
        }
    }
    // The shaders the JIT must compile (both the glslang and the spirv-opt variant).
    for name in ["arith.comp", "control.comp", "math.comp", "oob.comp", "bda.comp", "spin.comp", "push_ubo_spec.comp", "alu_loop.comp"] {
        assert_eq!(compiled.iter().filter(|w| w.starts_with(&format!("{name} "))).count(), 2, "{name} compiled: {compiled:?}");
    }
}

/// One op over `n` invocations: operand k of invocation i is the I64 word k*n + i of binding
/// 0, loaded as `from` (normalised as the interpreter loads it), the result word stored whole
/// to binding 1.
fn op_program(op: Op, from: Sc, arity: usize) -> Program {
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
    ops.push(Op::Store { ty: Sc::I64, space: Space::Buffer(1), addr: 6, src: 20 });
    crate::shader::tests::two_buffer_program(vec![ir::Block { ops, term: ir::Term::Exit, phi_in: vec![], edge_moves: vec![] }], 24, vec![(gid, bo::GLOBAL_INVOCATION_ID as u64), (eight, 8), (n8, 0)], bo::END as usize)
}

const EDGES: [u64; 24] = [
    0, 1, 2, 31, 32, 33, 63, 64, 0x7FFF_FFFF, 0x8000_0000, 0xFFFF_FFFF, 0x1_0000_0001, u64::MAX, 0x8000_0000_0000_0000,
    0x7F80_0000, 0xFF80_0000, 0x7FC0_0000, 0x7FA0_0001, 0x8000_0000, 0x3F80_0000, 0xBF80_0000, 0x7FF0_0000_0000_0000,
    0x7FF8_0000_0000_0001, 0x4F80_0000,
];

/// 64 invocations: every pair of the first 8 edges (and then more) for two operands; random
/// words fill the rest.
pub(super) fn operands(arity: usize) -> Vec<[u64; 3]> {
    let rnd = words(0x2545_F491_4F6C_DD1D, 3 * 64);
    (0..64)
        .map(|i| {
            let e = |k: usize| EDGES[(i / EDGES.len().pow(k as u32)) % EDGES.len()];
            if i < 48 { [e(0), e(1), EDGES[(i * 7) % EDGES.len()]] } else { [rnd[i], rnd[64 + i], rnd[128 + i]] }
        })
        .map(|mut v| {
            v[arity.min(3)..].iter_mut().for_each(|w| *w = 0);
            v
        })
        .collect()
}

/// The op's results on the JIT, and `want` from the reference for each invocation.
fn check_op(op: Op, from: Sc, arity: usize, want: impl Fn(&[u64; 3]) -> u64) {
    let prog = op_program(op.clone(), from, arity);
    let jit = super::compile(&prog).unwrap_or_else(|| panic!("{op:?} did not compile"));
    let p = Pipeline { program: std::sync::Arc::new(prog), local_size: [64, 1, 1], push_constant_size: 0, jit: Some(std::sync::Arc::new(jit)) };
    let vals = operands(arity);
    let mut input = vec![0u8; 64 * 8 * 3];
    for (i, v) in vals.iter().enumerate() {
        for (k, w) in v.iter().enumerate() {
            input[(k * 64 + i) * 8..][..8].copy_from_slice(&w.to_le_bytes());
        }
    }
    for p in [p.clone(), p.interpreted()] {
        let mut mem = HostMemory::new();
        let (a, o) = (mem.add_buffer(&input), mem.add_buffer(&[0; 64 * 8]));
        mem.bind(0, 0, a);
        mem.bind(0, 1, o);
        assert!(dispatch(&p, &mem, &[], [1, 1, 1], [0; 3], &Watchdog::default()).is_clean());
        let out = mem.bytes(o);
        for (i, v) in vals.iter().enumerate() {
            let v = v.map(|w| alu::norm(from, if from.size() == 4 { w & 0xFFFF_FFFF } else { w }));
            let got = u64::from_le_bytes(out[i * 8..][..8].try_into().unwrap());
            assert_eq!(got, want(&v), "{op:?} on {v:x?} (JIT {})", p.is_compiled());
        }
    }
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
    for op in ops {
        for ty in TYPES {
            check_op(Op::Bin { op, ty, dst: 20, a: 10, b: 11 }, ty, 2, |v| alu::bin(op, ty, v[0], v[1]));
        }
    }
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
    for op in ops {
        for ty in TYPES {
            for from in TYPES {
                check_op(Op::Un { op, ty, from, dst: 20, a: 10 }, from, 1, |v| alu::un(op, ty, from, v[0]));
            }
        }
    }
}

#[test]
fn ternary_ops_select_and_bit_insert_match_alu_on_edge_values() {
    use TriOp::*;
    for op in [Fma, FClamp, NClamp, UClamp, SClamp, FMix, SmoothStep, BitFieldUExtract, BitFieldSExtract] {
        for ty in TYPES {
            check_op(Op::Tri { op, ty, dst: 20, a: 10, b: 11, c: 12 }, ty, 3, |v| alu::tri(op, ty, v[0], v[1], v[2]));
        }
    }
    for ty in [Sc::I32, Sc::I64] {
        check_op(Op::BitInsert { ty, dst: 20, base: 10, insert: 11, offset: 12, count: 12 }, ty, 3, |v| alu::bit_insert(ty, v[0], v[1], v[2], v[2]));
    }
    check_op(Op::Select { dst: 20, cond: 10, a: 11, b: 12 }, Sc::I64, 3, |v| if v[0] != 0 { v[1] } else { v[2] });
}

fn compiled(name: &str) -> Vec<(String, Pipeline)> {
    compile_with(name, &[])
        .into_iter()
        .map(|(what, words)| {
            let p = Pipeline::compute(&Module::parse(&words).unwrap(), "main", &[]).unwrap();
            (what, p.compiled().expect("compiles"))
        })
        .collect()
}

#[test]
fn the_watchdog_stops_native_code_that_does_not_terminate() {
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;
    for (what, p) in compiled("spin.comp") {
        let mut mem = HostMemory::new();
        let b = mem.add_buffer(&[0; 8]);
        mem.bind(0, 0, b);
        let budget = Watchdog { step_budget: Some(100_000), ..Watchdog::default() };
        assert_eq!(dispatch(&p, &mem, &[], [4, 1, 1], [0; 3], &budget).stopped, Some(Stop::StepBudget), "{what}");
        let deadline = Watchdog { deadline: Some(std::time::Instant::now() + std::time::Duration::from_millis(50)), ..Watchdog::default() };
        assert_eq!(dispatch(&p, &mem, &[], [2, 1, 1], [0; 3], &deadline).stopped, Some(Stop::Deadline), "{what}");
        let flag = Arc::new(AtomicBool::new(true));
        let cancel = Watchdog { cancel: Some(flag), ..Watchdog::default() };
        assert_eq!(dispatch(&p, &mem, &[], [2, 1, 1], [0; 3], &cancel).stopped, Some(Stop::Cancelled), "{what}");
    }
}

#[test]
fn out_of_bounds_accesses_fault_and_are_contained_under_the_jit() {
    for (what, p) in compiled("oob.comp") {
        let mut mem = HostMemory::new();
        let input = mem.add_buffer(&(0..24u32).flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>());
        let out = mem.add_buffer(&[0; 24 * 4]);
        mem.bind(0, 0, input);
        mem.bind(0, 1, out);
        let report = dispatch(&p, &mem, &10u32.to_le_bytes(), [1, 1, 1], [0; 3], &Watchdog::default());
        // Invocations 14 and 15 read and write index 24 and 25, past both 24-word buffers;
        // the interpreter reports both loads, then both stores.
        assert_eq!(report.fault_count, 4, "{what}: {report:?}");
        let f: Vec<(bool, u32)> = report.faults.iter().map(|f| (f.write, f.invocation)).collect();
        assert_eq!(f, [(false, 14), (false, 15), (true, 14), (true, 15)], "{what}");
        let o: Vec<u32> = mem.bytes(out).chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
        for (i, &x) in o.iter().enumerate() {
            assert_eq!(x, if i >= 10 { i as u32 + 1 } else { 0 }, "{what}: o[{i}]");
        }
    }
}

#[test]
fn native_results_do_not_depend_on_thread_count() {
    for (what, p) in compiled("control.comp") {
        let run_on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| run_filled(&p, 1, [5, 1, 1]))
        };
        let one = run_on(1);
        assert!(one.1.iter().flatten().any(|&b| b != 0), "{what}");
        assert_eq!(run_on(2), one, "{what}");
    }
}

#[test]
fn inline_float_functions_match_vmath_over_many_values() {
    use UnOp::*;
    const N: usize = 1 << 14;
    let rnd = words(0x9E37_79B9_7F4A_7C15, N);
    // Random bits (NaNs, infinities, denormals, huge values) and values in the usual ranges.
    let vals: Vec<u64> = rnd
        .iter()
        .enumerate()
        .map(|(i, &w)| if i % 2 == 0 { w & 0xFFFF_FFFF } else { ((w % 200_001) as f32 / 1000.0 - 100.0).to_bits() as u64 })
        .collect();
    for op in [Sin, Cos, Exp, Sqrt, FNeg, FAbs] {
        let prog = op_program(Op::Un { op, ty: Sc::F32, from: Sc::F32, dst: 20, a: 10 }, Sc::F32, 1);
        let jit = super::compile(&prog).expect("compiles");
        let p = Pipeline { program: std::sync::Arc::new(prog), local_size: [64, 1, 1], push_constant_size: 0, jit: Some(std::sync::Arc::new(jit)) };
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

#[test]
fn loops_heavy_in_float_functions_stay_on_the_interpreter() {
    let load = |name: &str| -> Pipeline {
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("bench/shaders").join(name);
        let words: Vec<u32> = std::fs::read(path).unwrap().chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
        Pipeline::compute(&Module::parse(&words).unwrap(), "main", &[]).unwrap()
    };
    // sin, cos and exp among about forty ops a round; the Collatz and copy loops have none.
    assert!(super::codegen::prefers_interpreter(&load("compute_alu.spv").program));
    for name in ["compute_divergent.spv", "compute_memory.spv"] {
        let p = load(name);
        assert!(!super::codegen::prefers_interpreter(&p.program), "{name}");
        assert!(p.compiled().is_some(), "{name}");
    }
}

/// Host memory behind the `Memory` trait's checked calls only (no host spans: every buffer
/// access of native code takes the helper path); with `panic_reads`, reads panic, as a broken
/// implementation's would.
struct Checked<'m> {
    mem: &'m HostMemory,
    panic_reads: bool,
}

impl crate::shader::Memory for Checked<'_> {
    fn binding(&self, set: u32, binding: u32) -> Option<crate::shader::Region> {
        self.mem.binding(set, binding)
    }
    fn address(&self, address: u64, len: u64) -> Option<crate::shader::Region> {
        self.mem.address(address, len)
    }
    fn read(&self, buffer: u64, offset: u64, out: &mut [u8]) -> bool {
        if self.panic_reads {
            panic!("read refused");
        }
        self.mem.read(buffer, offset, out)
    }
    fn write(&self, buffer: u64, offset: u64, data: &[u8]) -> bool {
        self.mem.write(buffer, offset, data)
    }
    fn atomic(&self, buffer: u64, offset: u64, size: usize, update: &dyn Fn(u64) -> u64) -> Option<u64> {
        self.mem.atomic(buffer, offset, size, update)
    }
}

#[test]
fn a_panic_in_memory_unwinds_out_of_native_code() {
    let prog = op_program(Op::Mov { dst: 20, src: 10 }, Sc::I32, 1);
    let jit = super::compile(&prog).expect("compiles");
    let p = Pipeline { program: std::sync::Arc::new(prog), local_size: [64, 1, 1], push_constant_size: 0, jit: Some(std::sync::Arc::new(jit)) };
    let mut host = HostMemory::new();
    let (a, o) = (host.add_buffer(&[0; 512]), host.add_buffer(&[0; 512]));
    host.bind(0, 0, a);
    host.bind(0, 1, o);
    let mem = Checked { mem: &host, panic_reads: true };
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| dispatch(&p, &mem, &[], [1, 1, 1], [0; 3], &Watchdog::default())));
    let msg = r.expect_err("the panic reaches the caller");
    assert_eq!(msg.downcast_ref::<&str>(), Some(&"read refused"));
}

/// Buffer loads and stores inline in host memory (`Memory::host_span`) leave the same bytes
/// and faults as the checked path, on both native backends, in and out of bounds.
#[test]
fn inline_buffer_accesses_match_the_checked_path() {
    use crate::shader::Memory;
    let mut seen = 0;
    for name in ["arith.comp", "oob.comp", "control.comp"] {
        for (what, words) in compile_with(name, &[]) {
            let p = Pipeline::compute(&Module::parse(&words).unwrap(), "main", &[]).unwrap();
            let simd = super::compile_simd(&p.program).map(|j| Pipeline { jit: Some(std::sync::Arc::new(j)), ..p.clone() });
            for (backend, fast) in [("scalar", p.compiled()), ("simd", simd)] {
                let Some(fast) = fast else { continue };
                let go = |spans: bool| {
                    let mut mem = HostMemory::new();
                    let ids: Vec<usize> = fast.bindings().iter().enumerate().map(|(k, b)| {
                        let id = mem.add_buffer(&fill(2, 7 + 31 * k as u64, 4096));
                        mem.bind(b.set, b.binding, id);
                        id
                    }).collect();
                    let push = fill(2, 99, (fast.push_constant_size as usize).next_multiple_of(8));
                    let checked = Checked { mem: &mem, panic_reads: false };
                    let m: &dyn Memory = if spans { &mem } else { &checked };
                    assert_eq!(m.host_span(0, 0, 4).is_some(), spans);
                    let report = dispatch(&fast, m, &push, [3, 2, 1], [0; 3], &Watchdog::default());
                    (report, ids.iter().map(|&id| mem.bytes(id)).collect::<Vec<_>>())
                };
                let (inline, checked) = (go(true), go(false));
                assert_eq!(inline.0, checked.0, "{what} on {backend}: reports");
                assert!(inline.1 == checked.1, "{what} on {backend}: memory");
                seen += 1;
            }
        }
    }
    assert!(seen >= 6, "{seen} pipelines");
}

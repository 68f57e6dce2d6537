//! Multiplies by constant registers (shifts and adds instead of a multiply) and Bool selects
//! against the condition itself (and / or instead of a select): native code against the
//! interpreter and a CPU computation, over inputs with every bit pattern class.
use std::sync::Arc;

use crate::shader::ir::{BinOp, Block, Op, Program, Reg, Sc, Space, Term};
use crate::shader::{dispatch, HostMemory, Pipeline, Watchdog};

const N: usize = 16;
/// Constants: zero, one, powers of two (the top bit of each width too), 3, 5, 9 and ones
/// that take the multiply (7, all ones, and 3 above the low 32 bits).
const KS: [u64; 11] = [0, 1, 2, 3, 4, 5, 7, 9, 1 << 31, u32::MAX as u64, (3 << 32) | 3];

fn inputs() -> Vec<u64> {
    (0..N as u64).map(|i| i.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (i & 3) ^ (i << 61)).collect()
}

/// For each constant: x32 * k, k * x32 (I32), x64 * k (I64); then x&1 && x&2, x&1 || x&2
/// as selects. Register 0 is 0, 1 is 8, 2 is 1, 3 is 2; constants from 10; the input word
/// of invocation i at 8i of binding 0, results at 8 * (slots * i + slot) of binding 1.
fn program() -> (Program, usize) {
    let mut consts: Vec<(Reg, u64)> = vec![(0, 0), (1, 8), (2, 1), (3, 2)];
    let mut ops = vec![
        Op::Load { ty: Sc::I32, space: Space::Lane, dst: 4, addr: 0 },
        Op::Index { dst: 5, base: 0, index: 4, index_ty: Sc::I32, stride: 8 },
        Op::Load { ty: Sc::I64, space: Space::Buffer(0), dst: 6, addr: 5 },
        Op::Load { ty: Sc::I32, space: Space::Buffer(0), dst: 7, addr: 5 },
    ];
    let mut results = Vec::new();
    let mut next = 40;
    let mut fresh = || {
        next += 1;
        next
    };
    for (j, &k) in KS.iter().enumerate() {
        let kr = 10 + j as Reg;
        consts.push((kr, k));
        let k32 = 10 + (KS.len() + j) as Reg;
        consts.push((k32, k & 0xFFFF_FFFF));
        for (ty, a, b) in [(Sc::I32, 7, k32), (Sc::I32, k32, 7), (Sc::I64, 6, kr)] {
            let dst = fresh();
            ops.push(Op::Bin { op: BinOp::IMul, ty, dst, a, b });
            results.push(dst);
        }
    }
    let (m1, m2, c1, c2) = (fresh(), fresh(), fresh(), fresh());
    ops.push(Op::Bin { op: BinOp::And, ty: Sc::I32, dst: m1, a: 7, b: 2 });
    ops.push(Op::Bin { op: BinOp::And, ty: Sc::I32, dst: m2, a: 7, b: 3 });
    ops.push(Op::Bin { op: BinOp::INe, ty: Sc::I32, dst: c1, a: m1, b: 0 });
    ops.push(Op::Bin { op: BinOp::INe, ty: Sc::I32, dst: c2, a: m2, b: 0 });
    let (and, or) = (fresh(), fresh());
    ops.push(Op::Select { dst: and, cond: c1, a: c2, b: c1 });
    ops.push(Op::Select { dst: or, cond: c1, a: c1, b: c2 });
    results.extend([and, or]);
    let slots = results.len();
    let (base, at) = (fresh(), fresh());
    ops.push(Op::Index { dst: base, base: 0, index: 4, index_ty: Sc::I32, stride: 8 * slots as u64 });
    for (s, &r) in results.iter().enumerate() {
        ops.push(Op::Index { dst: at, base, index: 2, index_ty: Sc::I32, stride: 8 * s as u64 });
        ops.push(Op::Store { ty: Sc::I64, space: Space::Buffer(1), addr: at, src: r });
    }
    let program = crate::shader::tests::two_buffer_program(vec![Block { ops, term: Term::Exit, phi_in: vec![], edge_moves: vec![] }], next + 1, consts, 160);
    (program, slots)
}

fn run(p: &Pipeline, slots: usize) -> Vec<u64> {
    let mut mem = HostMemory::new();
    let i = mem.add_buffer(&inputs().iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>());
    let o = mem.add_buffer(&vec![0xA5; 8 * N * slots]);
    mem.bind(0, 0, i);
    mem.bind(0, 1, o);
    let report = dispatch(p, &mem, &[], [1, 1, 1], [0; 3], &Watchdog::default());
    assert!(report.is_clean(), "{report:?}");
    mem.bytes(o).chunks(8).map(|c| u64::from_le_bytes(c.try_into().unwrap())).collect()
}

#[test]
fn constant_multiplies_and_bool_selects_match_the_interpreter_and_the_cpu() {
    let (program, slots) = program();
    let p = Pipeline { program: Arc::new(program), local_size: [N as u32, 1, 1], push_constant_size: 0, jit: None };
    let jit = p.compiled().expect("the program compiles");
    let (native, interpreted) = (run(&jit, slots), run(&p.interpreted(), slots));
    let mut want = Vec::new();
    for x in inputs() {
        let x32 = x as u32;
        for k in KS {
            let m = x32.wrapping_mul(k as u32) as u64;
            want.extend([m, m, x.wrapping_mul(k)]);
        }
        let (a, b) = (x & 1 != 0, x & 2 != 0);
        want.extend([(a && b) as u64, (a || b) as u64]);
    }
    assert_eq!(interpreted, want);
    assert_eq!(native, want);
}

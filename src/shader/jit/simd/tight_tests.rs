//! Loops of one block (`tight`) in the forms glslang's output does not reach: the loop taken on
//! the branch's false side, loop-carried values in edge moves (phis) rather than registers, and
//! a memory op inside the loop whose faults need the back-edge counts. Results and fault
//! records against the interpreter (the reference) and the step counts against a CPU Collatz.
use std::sync::Arc;

use crate::shader::ir::{self, BinOp, Block, EdgeMove, Op, Sc, Space, Term};
use crate::shader::{dispatch, HostMemory, Pipeline, Watchdog};

/// Per invocation: x = ((gid * 2654435761) >> 22) + 1, the Collatz step count of x into
/// binding 1; with `store_inside`, each round also writes its count to binding 0 at word
/// gid + 4096 * (count / 8), which faults from the eighth round on (lanes at different rounds)
/// and for every round of invocations past the buffer.
fn collatz(store_inside: bool) -> ir::Program {
    use ir::builtin_offset as bo;
    let (gid, one, three, mul, shift, zero, two, far) = (0, 1, 2, 3, 4, 5, 6, 7);
    let bin = |op, dst, a, b| Op::Bin { op, ty: Sc::I32, dst, a, b };
    let entry = vec![Op::Load { ty: Sc::I32, space: Space::Lane, dst: 10, addr: gid }, bin(BinOp::IMul, 11, 10, mul), bin(BinOp::ShrL, 11, 11, shift), bin(BinOp::IAdd, 11, 11, one)];
    let mut body = vec![
        bin(BinOp::And, 12, 20, one),
        bin(BinOp::INe, 13, 12, zero),
        bin(BinOp::IMul, 14, 20, three),
        bin(BinOp::IAdd, 14, 14, one),
        bin(BinOp::ShrL, 15, 20, one),
        Op::Select { dst: 16, cond: 13, a: 14, b: 15 },
        bin(BinOp::IAdd, 17, 21, one),
        bin(BinOp::ULt, 18, 16, two),
    ];
    if store_inside {
        body.extend([bin(BinOp::ShrL, 26, 17, three), bin(BinOp::IMul, 26, 26, far), bin(BinOp::IAdd, 26, 26, 10)]);
        body.push(Op::Index { dst: 19, base: zero, index: 26, index_ty: Sc::I32, stride: 4 });
        body.push(Op::Store { ty: Sc::I32, space: Space::Buffer(0), addr: 19, src: 17 });
    }
    let edge = |target, dst, src| EdgeMove { target, dst, src };
    let blocks = vec![
        Block { ops: entry, term: Term::Jump(1), phi_in: vec![], edge_moves: vec![edge(1, 22, 11), edge(1, 23, zero)] },
        // Leaves when x' < 2: the loop is the false side.
        Block { ops: body, term: Term::Cond { cond: 18, t: 2, f: 1 }, phi_in: vec![(20, 22), (21, 23)], edge_moves: vec![edge(1, 22, 16), edge(1, 23, 17), edge(2, 24, 17)] },
        Block {
            ops: vec![Op::Index { dst: 25, base: zero, index: 10, index_ty: Sc::I32, stride: 4 }, Op::Store { ty: Sc::I32, space: Space::Buffer(1), addr: 25, src: 24 }],
            term: Term::Exit,
            phi_in: vec![],
            edge_moves: vec![],
        },
    ];
    let consts = vec![(gid, bo::GLOBAL_INVOCATION_ID as u64), (one, 1), (three, 3), (mul, 2_654_435_761), (shift, 22), (zero, 0), (two, 2), (far, 4096)];
    crate::shader::tests::two_buffer_program(blocks, 27, consts, bo::END as usize)
}

fn steps(mut x: u32) -> u32 {
    let mut s = 0;
    loop {
        x = if x & 1 != 0 { 3 * x + 1 } else { x >> 1 };
        s += 1;
        if x < 2 {
            return s;
        }
    }
}

#[test]
fn one_block_loops_with_phis_on_the_false_side_match_the_interpreter_and_the_cpu() {
    for store_inside in [false, true] {
        let prog = collatz(store_inside);
        assert!(super::tight::self_loop(1, &prog.blocks[1]).is_some());
        let jit = super::super::compile_simd(&prog).expect("compiles for the SIMD backend");
        let fast = Pipeline { program: Arc::new(prog), local_size: [64, 1, 1], push_constant_size: 0, jit: Some(Arc::new(jit)) };
        for local in [1, 5, 64, 100] {
            let go = |p: &Pipeline| {
                let p = Pipeline { local_size: [local, 1, 1], ..p.clone() };
                let mut mem = HostMemory::new();
                let (a, o) = (mem.add_buffer(&[0; 256 * 4]), mem.add_buffer(&[0xA5; 300 * 4]));
                mem.bind(0, 0, a);
                mem.bind(0, 1, o);
                (dispatch(&p, &mem, &[], [3, 1, 1], [0; 3], &Watchdog::default()), mem.bytes(a), mem.bytes(o))
            };
            let want = go(&fast.interpreted());
            let got = go(&fast);
            assert!(got.0 == want.0, "store {store_inside}, local {local}: {:?} vs {:?}", got.0, want.0);
            assert!(got.1 == want.1 && got.2 == want.2, "store {store_inside}, local {local}: memory");
            assert_eq!(want.0.faults.is_empty(), !store_inside, "local {local}");
            for i in 0..3 * local {
                let x = (i.wrapping_mul(2_654_435_761) >> 22) + 1;
                assert_eq!(u32::from_le_bytes(got.2[i as usize * 4..][..4].try_into().unwrap()), steps(x), "invocation {i}");
            }
        }
    }
}

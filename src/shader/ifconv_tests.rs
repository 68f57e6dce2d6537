//! If-conversion (`lower_select`) against the program without it, both on the interpreter:
//! every shader of tests/shaders (glslang's and `spirv-opt -O`'s) over several data sets must
//! leave the same memory and the same report, and hand-built diamonds, triangles and phi
//! swaps must compute what a CPU reference computes, converted or not, while an arm that
//! loads from a buffer keeps its branch.
use std::sync::Arc;

use crate::shader::ir::{BinOp, Block, EdgeMove, Op, Reg, Sc, Space, Term};
use crate::shader::lower_select::{simplify, Bounds};
use crate::shader::{dispatch, DispatchReport, HostMemory, ImageBinding, ImageFormat, Module, Pipeline, Watchdog};

/// Bytes of every buffer the shaders get: room for a few hundred invocations' words, small
/// enough that stray indices fault.
const BUFFER_BYTES: usize = 4096;
/// Elements bound to an array of descriptors.
const ARRAY_ELEMENTS: u32 = 3;

fn lowered(module: &Module, simplify: bool) -> Option<Pipeline> {
    let entry = module.entry_points.iter().find(|e| e.name == "main")?;
    let consts = crate::shader::specialize::Constants::new(module, &[]).ok()?;
    let local_size = consts.local_size(module, entry).ok()?;
    let lowered = super::lower_with(module, &consts, entry, simplify).ok()?;
    Some(Pipeline { program: Arc::new(lowered.program), local_size, push_constant_size: lowered.push_size, jit: None })
}

/// A data set: `seed` 0 is all zeros, 1 small words (loop counts, indices, flags), others
/// random bytes.
fn data(seed: u64, n: usize) -> Vec<u8> {
    let mut h = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut next = || {
        h ^= h << 13;
        h ^= h >> 7;
        h ^= h << 17;
        h
    };
    match seed {
        0 => vec![0; n],
        1 => (0..n / 4).flat_map(|_| ((next() % 40) as u32).to_le_bytes()).collect(),
        _ => (0..n).map(|_| next() as u8).collect(),
    }
}

/// Runs `p` on memory filled from `seed`: every buffer binding (each element of an array) and
/// every storage image gets its own buffer. Returns the report and every buffer's bytes.
fn run(p: &Pipeline, seed: u64) -> (DispatchReport, Vec<Vec<u8>>) {
    let mut mem = HostMemory::new();
    let mut buffers = Vec::new();
    let bindings = p.bindings();
    let image_slots = p.program.images.len();
    let buffer_slots = bindings.len() - image_slots;
    for (k, b) in bindings.iter().enumerate() {
        let elements = if b.count == 1 { 1 } else { ARRAY_ELEMENTS.min(b.count.max(1)) };
        for e in 0..elements {
            let i = mem.add_buffer(&data(seed + 7 * buffers.len() as u64, BUFFER_BYTES));
            buffers.push(i);
            if k < buffer_slots {
                mem.bind_element(b.set, b.binding, e, i);
            } else {
                let view = ImageBinding::packed(i as u64, 0, ImageFormat::R32Uint, [8, 8, 4], 2);
                mem.bind_image_element(b.set, b.binding, e, view);
            }
        }
    }
    let push = data(seed + 1000, p.push_constant_size as usize);
    let watchdog = Watchdog { step_budget: Some(2_000_000), ..Default::default() };
    let report = dispatch(p, &mem, &push, [2, 1, 1], [0; 3], &watchdog);
    (report, buffers.iter().map(|&i| mem.bytes(i)).collect())
}

#[test]
fn every_test_shader_runs_the_same_converted_or_not() {
    let dir = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/shaders");
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.ends_with(".comp") || n.ends_with(".spvasm"))
        .collect();
    names.sort();
    let (mut compared, mut converted) = (0, 0);
    for name in &names {
        // Shaders that need defines (or that spirv-opt refuses) belong to other tests.
        let Ok(variants) = std::panic::catch_unwind(|| crate::shader::tests::compile_with(name, &[])) else { continue };
        for (what, words) in variants {
            let Ok(module) = Module::parse(&words) else { continue };
            let (Some(on), Some(off)) = (lowered(&module, true), lowered(&module, false)) else {
                assert!(lowered(&module, true).is_none() && lowered(&module, false).is_none(), "{what}: lowers only one way");
                continue;
            };
            converted += (on.program.blocks != off.program.blocks) as usize;
            for seed in 0..4 {
                let (a, b) = (run(&on, seed), run(&off, seed));
                // A shader that loops until the watchdog stops it stops at a different point:
                // converted programs run fewer blocks for the same work.
                if a.0.stopped.is_some() || b.0.stopped.is_some() {
                    assert_eq!(a.0.stopped.is_some(), b.0.stopped.is_some(), "{what}, data set {seed}: only one stopped");
                    continue;
                }
                assert_eq!(a.0, b.0, "{what}, data set {seed}: reports differ");
                assert!(a.1 == b.1, "{what}, data set {seed}: memory differs");
                compared += 1;
            }
        }
    }
    assert!(compared >= 2 * names.len(), "only {compared} runs compared for {} shaders", names.len());
    eprintln!("{compared} runs compared, {converted} programs changed by lower_select");
    assert!(converted >= 40, "only {converted} programs changed by lower_select");
}

/// A hand-built program over 16 invocations: block 0 loads `x = input[gid]`, `tail` stores
/// `out` to output[gid]. Registers 0..=3 are constants 0, 1, 4, 3; 4 is gid, 5 the input
/// address, 6 `x`.
struct Hand {
    blocks: Vec<Block>,
    consts: Vec<(Reg, u64)>,
    regs: u32,
}

const N: usize = 16;

impl Hand {
    fn new() -> Hand {
        let entry = vec![
            Op::Load { ty: Sc::I32, space: Space::Lane, dst: 4, addr: 0 },
            Op::Index { dst: 5, base: 0, index: 4, index_ty: Sc::I32, stride: 4 },
            Op::Load { ty: Sc::I32, space: Space::Buffer(0), dst: 6, addr: 5 },
        ];
        let b0 = Block { ops: entry, term: Term::Exit, phi_in: vec![], edge_moves: vec![] };
        Hand { blocks: vec![b0], consts: vec![(0, 0), (1, 1), (2, 4), (3, 3)], regs: 40 }
    }

    fn block(&mut self, ops: Vec<Op>, term: Term, phi_in: Vec<(Reg, Reg)>, edge_moves: Vec<EdgeMove>) {
        self.blocks.push(Block { ops, term, phi_in, edge_moves });
    }

    /// The final block: stores register `out` and exits.
    fn tail(&mut self, ops: Vec<Op>, phi_in: Vec<(Reg, Reg)>, out: Reg) {
        let mut ops = ops;
        ops.push(Op::Index { dst: 39, base: 0, index: 4, index_ty: Sc::I32, stride: 4 });
        ops.push(Op::Store { ty: Sc::I32, space: Space::Buffer(1), addr: 39, src: out });
        self.block(ops, Term::Exit, phi_in, vec![]);
    }

    fn pipeline(&self, convert: bool) -> Pipeline {
        let (mut blocks, mut regs, mut consts) = (self.blocks.clone(), self.regs, self.consts.clone());
        if convert {
            simplify(&mut blocks, &mut regs, &mut consts, &Bounds { push: 0, frame: 160 });
        }
        let program = crate::shader::tests::two_buffer_program(blocks, regs, consts, 160);
        Pipeline { program: Arc::new(program), local_size: [N as u32, 1, 1], push_constant_size: 0, jit: None }
    }

    /// The outputs for `input` with and without conversion, and whether conversion left a
    /// two-way branch in a block that runs.
    fn run(&self, input: &[u32]) -> [Vec<u32>; 2] {
        [true, false].map(|convert| {
            let mut mem = HostMemory::new();
            let i = mem.add_buffer(&input.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>());
            let o = mem.add_buffer(&[0; 4 * N]);
            mem.bind(0, 0, i);
            mem.bind(0, 1, o);
            let report = dispatch(&self.pipeline(convert), &mem, &[], [1, 1, 1], [0; 3], &Watchdog::default());
            assert!(report.is_clean(), "{report:?}");
            mem.bytes(o).chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect()
        })
    }

    fn branches_left(&self) -> usize {
        self.pipeline(true).program.blocks.iter().filter(|b| matches!(b.term, Term::Cond { .. })).count()
    }
}

/// Inputs whose low bits split every lane group both ways, with values near the 32-bit edge.
fn inputs() -> Vec<u32> {
    (0..N as u32).map(|i| i.wrapping_mul(0x9E37_79B9) ^ (i & 3)).collect()
}

fn odd(hand: &mut Hand) -> Reg {
    let b = &mut hand.blocks[0];
    b.ops.push(Op::Bin { op: BinOp::And, ty: Sc::I32, dst: 7, a: 6, b: 1 });
    b.ops.push(Op::Bin { op: BinOp::INe, ty: Sc::I32, dst: 8, a: 7, b: 0 });
    8
}

#[test]
fn a_diamond_becomes_a_select() {
    // out = x odd ? 3x + 1 : x >> 1, through a phi.
    let mut h = Hand::new();
    let c = odd(&mut h);
    h.blocks[0].term = Term::Cond { cond: c, t: 1, f: 2 };
    let then = vec![Op::Bin { op: BinOp::IMul, ty: Sc::I32, dst: 10, a: 6, b: 3 }, Op::Bin { op: BinOp::IAdd, ty: Sc::I32, dst: 11, a: 10, b: 1 }];
    h.block(then, Term::Jump(3), vec![], vec![EdgeMove { target: 3, dst: 20, src: 11 }]);
    h.block(vec![Op::Bin { op: BinOp::ShrL, ty: Sc::I32, dst: 12, a: 6, b: 1 }], Term::Jump(3), vec![], vec![EdgeMove { target: 3, dst: 20, src: 12 }]);
    h.tail(vec![], vec![(21, 20)], 21);
    assert_eq!(h.branches_left(), 0);
    let want: Vec<u32> = inputs().iter().map(|&x| if x & 1 != 0 { x.wrapping_mul(3).wrapping_add(1) } else { x >> 1 }).collect();
    let [on, off] = h.run(&inputs());
    assert_eq!(on, want);
    assert_eq!(off, want);
}

#[test]
fn a_triangle_becomes_a_select() {
    // out = x odd ? x * 4 - 3 : x, the untaken side's value coming on the branch's own edge;
    // the arm also changes a register (13) that the merge block reads without a phi.
    let mut h = Hand::new();
    let c = odd(&mut h);
    h.blocks[0].ops.push(Op::Mov { dst: 13, src: 3 });
    h.blocks[0].term = Term::Cond { cond: c, t: 1, f: 2 };
    h.blocks[0].edge_moves.push(EdgeMove { target: 2, dst: 20, src: 6 });
    let then = vec![
        Op::Bin { op: BinOp::IMul, ty: Sc::I32, dst: 10, a: 6, b: 2 },
        Op::Bin { op: BinOp::ISub, ty: Sc::I32, dst: 11, a: 10, b: 3 },
        Op::Bin { op: BinOp::IAdd, ty: Sc::I32, dst: 13, a: 13, b: 1 },
    ];
    h.block(then, Term::Jump(2), vec![], vec![EdgeMove { target: 2, dst: 20, src: 11 }]);
    h.tail(vec![Op::Bin { op: BinOp::Xor, ty: Sc::I32, dst: 22, a: 21, b: 13 }], vec![(21, 20)], 22);
    assert_eq!(h.branches_left(), 0);
    let want: Vec<u32> = inputs().iter().map(|&x| if x & 1 != 0 { x.wrapping_mul(4).wrapping_sub(3) ^ 4 } else { x ^ 3 }).collect();
    let [on, off] = h.run(&inputs());
    assert_eq!(on, want);
    assert_eq!(off, want);
}

#[test]
fn an_arm_that_loads_from_a_buffer_keeps_its_branch() {
    // The then arm reads input[x & 15]: an even lane must not run it (an index past the
    // buffer would fault), so the branch stays.
    let mut h = Hand::new();
    let c = odd(&mut h);
    h.blocks[0].term = Term::Cond { cond: c, t: 1, f: 2 };
    let then = vec![
        Op::Bin { op: BinOp::And, ty: Sc::I32, dst: 10, a: 6, b: 2 },
        Op::Index { dst: 11, base: 0, index: 10, index_ty: Sc::I32, stride: 4 },
        Op::Load { ty: Sc::I32, space: Space::Buffer(0), dst: 12, addr: 11 },
    ];
    h.block(then, Term::Jump(3), vec![], vec![EdgeMove { target: 3, dst: 20, src: 12 }]);
    h.block(vec![], Term::Jump(3), vec![], vec![EdgeMove { target: 3, dst: 20, src: 6 }]);
    h.tail(vec![], vec![(21, 20)], 21);
    assert_eq!(h.branches_left(), 1);
    let input = inputs();
    let want: Vec<u32> = input.iter().map(|&x| if x & 1 != 0 { input[(x & 4) as usize] } else { x }).collect();
    let [on, off] = h.run(&input);
    assert_eq!(on, want);
    assert_eq!(off, want);
}

#[test]
fn phis_that_swap_keep_parallel_copy_semantics() {
    // a = x, b = 3x; odd lanes swap them through the merge block's phis (which write a and b
    // themselves), their arm first incrementing b in place; then out = 7a ^ b.
    let mut h = Hand::new();
    let c = odd(&mut h);
    h.blocks[0].ops.push(Op::Mov { dst: 14, src: 6 });
    h.blocks[0].ops.push(Op::Bin { op: BinOp::IMul, ty: Sc::I32, dst: 15, a: 6, b: 3 });
    h.blocks[0].term = Term::Cond { cond: c, t: 1, f: 2 };
    let swap = vec![EdgeMove { target: 3, dst: 20, src: 15 }, EdgeMove { target: 3, dst: 21, src: 14 }];
    h.block(vec![Op::Bin { op: BinOp::IAdd, ty: Sc::I32, dst: 15, a: 15, b: 1 }], Term::Jump(3), vec![], swap);
    let keep = vec![EdgeMove { target: 3, dst: 20, src: 14 }, EdgeMove { target: 3, dst: 21, src: 15 }];
    h.block(vec![], Term::Jump(3), vec![], keep);
    let seven = 16;
    h.consts.push((seven, 7));
    let tail = vec![Op::Bin { op: BinOp::IMul, ty: Sc::I32, dst: 17, a: 14, b: seven }, Op::Bin { op: BinOp::Xor, ty: Sc::I32, dst: 18, a: 17, b: 15 }];
    h.tail(tail, vec![(14, 20), (15, 21)], 18);
    assert_eq!(h.branches_left(), 0);
    let want: Vec<u32> = inputs()
        .iter()
        .map(|&x| {
            let (a, b) = (x, x.wrapping_mul(3));
            let (a, b) = if x & 1 != 0 { (b.wrapping_add(1), a) } else { (a, b) };
            a.wrapping_mul(7) ^ b
        })
        .collect();
    let [on, off] = h.run(&inputs());
    assert_eq!(on, want);
    assert_eq!(off, want);
}

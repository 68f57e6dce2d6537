//! `ir::Program` → one Cranelift function that runs one invocation.
//!
//! Every IR register is a Cranelift variable holding the interpreter's 64-bit register word
//! (32-bit values with the upper bits zero, Bool 0 or 1): each op reads the words it needs,
//! computes in the op's type and writes the normalised word back, so the JIT's words are the
//! interpreter's word for word. IR blocks map 1:1 to Cranelift blocks; an edge with phi moves
//! or a back edge gets a block of its own (moves, then the watchdog poll on back edges).
//! Ops whose exact bits are not emitted inline here call `helpers`, which call `alu`/`vmath`.
//! `translate` returns None for anything it does not compile: the program then runs on the
//! interpreter.
use cranelift_codegen::ir::condcodes::IntCC;
use cranelift_codegen::ir::{types, AbiParam, Block, InstBuilder, MemFlagsData, SigRef, Signature, Value};
use cranelift_frontend::{FunctionBuilder, Variable};

use super::super::ir::{self, BinOp, Op, Program, Sc, Space, Term, TriOp, UnOp};
use super::super::lower_copies::writes;
use super::helpers::{self, MemDesc, MemKind, STOPPED};

pub(super) mod alu;
#[cfg(test)]
mod const_tests;
pub(super) mod vmath;

pub(super) const I64: types::Type = types::I64;
pub(super) const I32: types::Type = types::I32;
pub(super) const F32: types::Type = types::F32;
pub(super) const F64: types::Type = types::F64;

/// Helper signatures, imported once per function.
struct Sigs {
    /// (i64 × n) -> i64 for n = 1..=6.
    ints: Vec<SigRef>,
    /// (f32 × n) -> f32 for n = 1..=3.
    floats: Vec<SigRef>,
}

pub(super) struct Gen<'p, 'b, 'f> {
    b: &'b mut FunctionBuilder<'f>,
    prog: &'p Program,
    regs: Vec<Variable>,
    steps: Variable,
    next_poll: Variable,
    run: Value,
    frame: Value,
    frame_len: Value,
    push: Value,
    push_len: Value,
    blocks: Vec<Block>,
    /// The value of each register that holds a program constant and is never written.
    known: Vec<Option<u64>>,
    sigs: Sigs,
    pub descs: Vec<MemDesc>,
}

fn sig(call_conv: cranelift_codegen::isa::CallConv, ty: types::Type, n: usize) -> Signature {
    let mut s = Signature::new(call_conv);
    s.params.extend((0..n).map(|_| AbiParam::new(ty)));
    s.returns.push(AbiParam::new(ty));
    s
}

/// Whether `translate` can compile `prog` at all (the checks that need no code generation).
/// The host address and length of binding slot `slot`'s region, from the run context's span
/// table (`helpers::SPANS_AT`); a length of 0 when its accesses take the helper's path.
pub(super) fn span(b: &mut FunctionBuilder, run: Value, slot: u16) -> (Value, Value) {
    let flags = MemFlagsData::trusted();
    let table = b.ins().load(I64, flags, run, helpers::SPANS_AT);
    let at = 16 * slot as i32;
    (b.ins().load(I64, flags, table, at), b.ins().load(I64, flags, table, at + 8))
}

pub(super) fn supported(prog: &Program) -> bool {
    if !prog.accel_bindings.is_empty() {
        return false;
    }
    prog.blocks.iter().all(|blk| {
        !matches!(blk.term, Term::Barrier(_))
            && blk.ops.iter().all(|op| match op {
                Op::Load { space, .. } | Op::Store { space, .. } => *space != Space::Workgroup,
                Op::Atomic { space, .. } => !matches!(space, Space::Workgroup | Space::Lane),
                Op::Mov { .. } | Op::Un { .. } | Op::Bin { .. } | Op::Tri { .. } | Op::BitInsert { .. } | Op::Select { .. } => true,
                Op::Index { .. } | Op::AddImm { .. } => true,
                _ => false,
            })
    })
}

/// Which blocks lie in a loop: those from a back edge's target (a header, which comes first
/// in structured order) to the block that branches back to it.
pub(super) fn loop_blocks(prog: &Program) -> Vec<bool> {
    let mut in_loop = vec![false; prog.blocks.len()];
    for (i, blk) in prog.blocks.iter().enumerate() {
        let targets: Vec<u32> = match &blk.term {
            Term::Jump(t) => vec![*t],
            Term::Cond { t, f, .. } => vec![*t, *f],
            Term::Switch { default, cases, .. } => cases.iter().map(|c| c.1).chain([*default]).collect(),
            _ => vec![],
        };
        for t in targets.into_iter().filter(|&t| t as usize <= i) {
            in_loop[t as usize..=i].iter_mut().for_each(|b| *b = true);
        }
    }
    in_loop
}

/// Whether the interpreter runs `prog` faster: its lane arms compute `vmath`'s functions for
/// eight lanes in one vectorised call, where native code computes them once per invocation.
/// Loops whose ops are at least 1/16 such functions (compute-alu's are 3 in 40: sin, cos, exp)
/// ran at about half the interpreter's rate (docs/BENCHMARKS.md), so they stay there.
pub(super) fn prefers_interpreter(prog: &Program) -> bool {
    let in_loop = loop_blocks(prog);
    let (mut ops, mut math) = (0usize, 0usize);
    for blk in prog.blocks.iter().zip(&in_loop).filter(|b| *b.1).map(|b| b.0) {
        ops += blk.ops.len();
        math += blk
            .ops
            .iter()
            .filter(|op| match op {
                Op::Un { op, ty: Sc::F32, .. } => helpers::f32_unary(*op).is_some() || matches!(op, UnOp::Sin | UnOp::Cos | UnOp::Exp),
                Op::Bin { op, ty: Sc::F32, .. } => helpers::f32_binary(*op).is_some(),
                _ => false,
            })
            .count();
    }
    math > 0 && math * 16 >= ops
}

/// Constant registers no op, phi or edge move writes: their value is the same everywhere.
fn known_constants(prog: &Program) -> Vec<Option<u64>> {
    let mut known = vec![None; prog.reg_count as usize];
    for &(r, v) in &prog.consts {
        known[r as usize] = Some(v);
    }
    for blk in &prog.blocks {
        blk.ops.iter().for_each(|op| writes(op, &mut |r| known[r as usize] = None));
        blk.phi_in.iter().for_each(|&(d, _)| known[d as usize] = None);
        blk.edge_moves.iter().for_each(|m| known[m.dst as usize] = None);
    }
    known
}

impl<'p, 'b, 'f> Gen<'p, 'b, 'f> {
    /// Sets up the entry block: parameters, constants, the step counter.
    pub(super) fn new(b: &'b mut FunctionBuilder<'f>, prog: &'p Program, call_conv: cranelift_codegen::isa::CallConv) -> Self {
        let entry = b.create_block();
        b.append_block_params_for_function_params(entry);
        b.switch_to_block(entry);
        let p = b.block_params(entry).to_vec();
        let regs: Vec<Variable> = (0..prog.reg_count).map(|_| b.declare_var(I64)).collect();
        let zero = b.ins().iconst(I64, 0);
        for &r in &regs {
            b.def_var(r, zero);
        }
        for &(r, v) in &prog.consts {
            let c = b.ins().iconst(I64, v as i64);
            b.def_var(regs[r as usize], c);
        }
        let steps = b.declare_var(I64);
        b.def_var(steps, zero);
        let next_poll = b.declare_var(I64);
        let first = b.ins().iconst(I64, super::super::exec::CHECK_EVERY as i64);
        b.def_var(next_poll, first);
        let ints = (1..=6).map(|n| b.import_signature(sig(call_conv, I64, n))).collect();
        let floats = (1..=3).map(|n| b.import_signature(sig(call_conv, F32, n))).collect();
        let blocks: Vec<Block> = prog.blocks.iter().map(|_| b.create_block()).collect();
        b.ins().jump(blocks[0], &[]);
        let known = known_constants(prog);
        Gen { b, prog, regs, steps, next_poll, run: p[0], frame: p[1], frame_len: p[2], push: p[3], push_len: p[4], blocks, known, sigs: Sigs { ints, floats }, descs: Vec::new() }
    }

    /// Emits every block; None when an op or terminator is not compiled.
    pub(super) fn translate(&mut self) -> Option<()> {
        let prog = self.prog;
        for (i, blk) in prog.blocks.iter().enumerate() {
            self.b.switch_to_block(self.blocks[i]);
            let s = self.b.use_var(self.steps);
            let s = self.b.ins().iadd_imm_s(s, 1);
            self.b.def_var(self.steps, s);
            for &(dst, tmp) in &blk.phi_in {
                let v = self.get(tmp);
                self.set(dst, v);
            }
            for op in &blk.ops {
                self.op(op)?;
            }
            self.term(i as u32, blk)?;
        }
        self.b.seal_all_blocks();
        Some(())
    }

    fn get(&mut self, r: ir::Reg) -> Value {
        self.b.use_var(self.regs[r as usize])
    }

    fn set(&mut self, r: ir::Reg, v: Value) {
        self.b.def_var(self.regs[r as usize], v);
    }

    /// The block an edge from `from` to `to` enters: `to` itself, or a block doing the edge's
    /// phi moves and (on a back edge) the watchdog poll first.
    fn edge(&mut self, from: u32, blk: &ir::Block, to: u32) -> Block {
        let moves: Vec<_> = blk.edge_moves.iter().filter(|m| m.target == to).copied().collect();
        let back = to <= from;
        if moves.is_empty() && !back {
            return self.blocks[to as usize];
        }
        let here = self.b.current_block();
        let e = self.b.create_block();
        self.b.switch_to_block(e);
        for m in moves {
            let v = self.get(m.src);
            self.set(m.dst, v);
        }
        if back {
            self.poll();
        }
        self.b.ins().jump(self.blocks[to as usize], &[]);
        if let Some(h) = here {
            self.b.switch_to_block(h);
        }
        e
    }

    /// At a back edge: once the step count reaches the next poll, ask the watchdog.
    fn poll(&mut self) {
        let s = self.b.use_var(self.steps);
        let np = self.b.use_var(self.next_poll);
        let due = self.b.ins().icmp(IntCC::UnsignedGreaterThanOrEqual, s, np);
        let (call, stop, cont) = (self.b.create_block(), self.b.create_block(), self.b.create_block());
        self.b.ins().brif(due, call, &[], cont, &[]);
        self.b.switch_to_block(call);
        let run = self.run;
        let r = self.call_int(helpers::poll as *const () as usize, &[run, s]);
        self.b.def_var(self.next_poll, r);
        self.b.ins().brif(r, cont, &[], stop, &[]);
        self.b.switch_to_block(stop);
        let v = self.b.ins().iconst(I64, STOPPED as i64);
        self.b.ins().return_(&[v]);
        self.b.switch_to_block(cont);
    }

    fn term(&mut self, i: u32, blk: &ir::Block) -> Option<()> {
        match &blk.term {
            Term::Jump(t) => {
                let e = self.edge(i, blk, *t);
                self.b.ins().jump(e, &[]);
            }
            Term::Cond { cond, t, f } => {
                let c = self.get(*cond);
                let (et, ef) = (self.edge(i, blk, *t), self.edge(i, blk, *f));
                self.b.ins().brif(c, et, &[], ef, &[]);
            }
            Term::Switch { sel, default, cases } => {
                let v = self.get(*sel);
                for &(k, target) in cases {
                    let e = self.edge(i, blk, target);
                    let hit = self.b.ins().icmp_imm_s(IntCC::Equal, v, k as i64);
                    let next = self.b.create_block();
                    self.b.ins().brif(hit, e, &[], next, &[]);
                    self.b.switch_to_block(next);
                }
                let e = self.edge(i, blk, *default);
                self.b.ins().jump(e, &[]);
            }
            Term::Exit => {
                let s = self.b.use_var(self.steps);
                self.b.ins().return_(&[s]);
            }
            Term::Barrier(_) => return None,
        }
        Some(())
    }

    fn call(&mut self, f: usize, sig: SigRef, args: &[Value]) -> Value {
        let callee = self.b.ins().iconst(I64, f as i64);
        let inst = self.b.ins().call_indirect(sig, callee, args);
        self.b.inst_results(inst)[0]
    }

    fn call_int(&mut self, f: usize, args: &[Value]) -> Value {
        let sig = self.sigs.ints[args.len() - 1];
        self.call(f, sig, args)
    }

    fn call_f32(&mut self, f: usize, args: &[Value]) -> Value {
        let args: Vec<Value> = args.iter().map(|&a| self.f32_of(a)).collect();
        let sig = self.sigs.floats[args.len() - 1];
        let r = self.call(f, sig, &args);
        self.word_f32(r)
    }

    fn lo(&mut self, v: Value) -> Value {
        self.b.ins().ireduce(I32, v)
    }
    fn zx(&mut self, v: Value) -> Value {
        self.b.ins().uextend(I64, v)
    }
    fn f32_of(&mut self, v: Value) -> Value {
        let l = self.lo(v);
        self.b.ins().bitcast(F32, MemFlagsData::new(), l)
    }
    fn f64_of(&mut self, v: Value) -> Value {
        self.b.ins().bitcast(F64, MemFlagsData::new(), v)
    }
    fn word_f32(&mut self, x: Value) -> Value {
        let i = self.b.ins().bitcast(I32, MemFlagsData::new(), x);
        self.zx(i)
    }
    fn word_f64(&mut self, x: Value) -> Value {
        self.b.ins().bitcast(I64, MemFlagsData::new(), x)
    }
    /// A comparison result (i8 0/1) as a Bool word.
    fn word_bool(&mut self, c: Value) -> Value {
        self.zx(c)
    }
    /// `alu::norm`.
    fn norm(&mut self, ty: Sc, v: Value) -> Value {
        match ty {
            Sc::Bool => {
                let c = self.b.ins().icmp_imm_s(IntCC::NotEqual, v, 0);
                self.word_bool(c)
            }
            Sc::I32 | Sc::F32 => {
                let l = self.lo(v);
                self.zx(l)
            }
            Sc::I64 | Sc::F64 => v,
        }
    }

    fn op(&mut self, op: &Op) -> Option<()> {
        match *op {
            Op::Mov { dst, src } => {
                let v = self.get(src);
                self.set(dst, v);
            }
            Op::Select { dst, cond, a, b } => {
                let (c, x, y) = (self.get(cond), self.get(a), self.get(b));
                // `c && a` and `c || b` as if-conversion leaves them: a select whose other
                // operand is the Bool condition itself has Bool operands, words 0 or 1, so it
                // is their and / or (no compare and conditional move).
                let v = if b == cond {
                    self.b.ins().band(c, x)
                } else if a == cond {
                    self.b.ins().bor(c, y)
                } else {
                    self.b.ins().select(c, x, y)
                };
                self.set(dst, v);
            }
            Op::Index { dst, base, index, index_ty, stride } => {
                let i = self.get(index);
                let i = if index_ty == Sc::I32 {
                    let l = self.lo(i);
                    self.b.ins().sextend(I64, l)
                } else {
                    i
                };
                let scaled = self.b.ins().imul_imm_s(i, stride as i64);
                let base = self.get(base);
                let v = self.b.ins().iadd(base, scaled);
                self.set(dst, v);
            }
            Op::AddImm { dst, a, imm } => {
                let x = self.get(a);
                let v = self.b.ins().iadd_imm_s(x, imm as i64);
                self.set(dst, v);
            }
            Op::Bin { op, ty, dst, a, b } => {
                let (x, y) = (self.get(a), self.get(b));
                let by = |r: ir::Reg| self.known[r as usize];
                let v = match (op, by(a), by(b)) {
                    (BinOp::IMul, _, Some(k)) => self.mul_const(ty, x, k),
                    (BinOp::IMul, Some(k), _) => self.mul_const(ty, y, k),
                    _ => None,
                };
                let v = match v {
                    Some(v) => v,
                    None => self.bin(op, ty, x, y)?,
                };
                self.set(dst, v);
            }
            Op::Un { op, ty, from, dst, a } => {
                let x = self.get(a);
                let v = self.un(op, ty, from, x)?;
                self.set(dst, v);
            }
            Op::Tri { op, ty, dst, a, b, c } => {
                let (x, y, z) = (self.get(a), self.get(b), self.get(c));
                let code = helpers::tri_code(op, ty)? as i64;
                let v = if (op, ty) == (TriOp::Fma, Sc::F32) {
                    // Hardware and `vmath::fma1` both round the exact a·b + c once; only a NaN's
                    // bits can differ, and a NaN takes the interpreter's path.
                    let (a, b, c) = (self.f32_of(x), self.f32_of(y), self.f32_of(z));
                    let r = self.b.ins().fma(a, b, c);
                    self.nan_guard(r, |g| g.helper_tri(code, x, y, z))
                } else {
                    self.helper_tri(code, x, y, z)
                };
                self.set(dst, v);
            }
            Op::BitInsert { ty, dst, base, insert, offset, count } => {
                let t = helpers::ty_code(ty) as i64;
                let t = self.b.ins().iconst(I64, t);
                let args = [t, self.get(base), self.get(insert), self.get(offset), self.get(count)];
                let v = self.call_int(helpers::bit_insert as *const () as usize, &args);
                self.set(dst, v);
            }
            Op::Load { ty, space, dst, addr } => {
                let v = self.load(ty, space, addr)?;
                self.set(dst, v);
            }
            Op::Store { ty, space, addr, src } => self.store(ty, space, addr, src)?,
            Op::Atomic { op, ty, space, dst, addr, a, b } => {
                if matches!(space, Space::Lane | Space::Workgroup) {
                    return None;
                }
                let (at, x, y) = (self.get(addr), self.get(a), self.get(b));
                let v = self.mem_call(MemDesc { ty, space, kind: MemKind::Atomic(op) }, at, x, y);
                self.set(dst, v);
            }
            _ => return None,
        }
        Some(())
    }

    fn helper_tri(&mut self, code: i64, x: Value, y: Value, z: Value) -> Value {
        let code = self.b.ins().iconst(I64, code);
        self.call_int(helpers::tri as *const () as usize, &[code, x, y, z])
    }

    /// The word of float result `r` (F32 or F64), or `slow`'s word when `r` is a NaN: the bits
    /// of a NaN are the interpreter's to choose.
    fn nan_guard(&mut self, r: Value, slow: impl FnOnce(&mut Self) -> Value) -> Value {
        let ok = self.b.ins().fcmp(cranelift_codegen::ir::condcodes::FloatCC::Ordered, r, r);
        let f32 = self.b.func.dfg.value_type(r) == F32;
        self.guarded(ok, slow, |g| if f32 { g.word_f32(r) } else { g.word_f64(r) })
    }

    /// The memory helper for one site.
    fn mem_call(&mut self, desc: MemDesc, at: Value, a: Value, b: Value) -> Value {
        let d = self.descs.len() as i64;
        self.descs.push(desc);
        let d = self.b.ins().iconst(I64, d);
        let s = self.b.use_var(self.steps);
        let run = self.run;
        self.call_int(helpers::mem as *const () as usize, &[run, d, at, a, b, s])
    }

    /// Whether `size` bytes at `at` lie inside `len` bytes (`at + size <= len`, no wrap).
    fn in_bounds(&mut self, at: Value, len: Value, size: u32) -> Value {
        let last = self.b.ins().iadd_imm_s(len, -(size as i64));
        let fits = self.b.ins().icmp(IntCC::UnsignedLessThanOrEqual, at, last);
        let room = self.b.ins().icmp_imm_s(IntCC::UnsignedGreaterThanOrEqual, len, size as i64);
        self.b.ins().band(fits, room)
    }

    /// `bytes + at` when in bounds, else the helper's path; `inline` emits the in-bounds
    /// access, returning the loaded word (or a dummy for a store).
    fn guarded(&mut self, ok: Value, slow: impl FnOnce(&mut Self) -> Value, inline: impl FnOnce(&mut Self) -> Value) -> Value {
        let (fast_b, slow_b, join) = (self.b.create_block(), self.b.create_block(), self.b.create_block());
        let out = self.b.append_block_param(join, I64);
        self.b.ins().brif(ok, fast_b, &[], slow_b, &[]);
        self.b.switch_to_block(fast_b);
        let v = inline(self);
        self.b.ins().jump(join, &[v.into()]);
        self.b.switch_to_block(slow_b);
        let v = slow(self);
        self.b.ins().jump(join, &[v.into()]);
        self.b.switch_to_block(join);
        out
    }

    fn load(&mut self, ty: Sc, space: Space, addr: ir::Reg) -> Option<Value> {
        let at = self.get(addr);
        let desc = MemDesc { ty, space, kind: MemKind::Load };
        let (base, len) = match space {
            Space::Lane => (self.frame, self.frame_len),
            Space::Push => (self.push, self.push_len),
            Space::Buffer(slot) => span(self.b, self.run, slot),
            Space::Workgroup => return None,
            _ => {
                let z = self.b.ins().iconst(I64, 0);
                return Some(self.mem_call(desc, at, z, z));
            }
        };
        let ok = self.in_bounds(at, len, ty.size());
        Some(self.guarded(
            ok,
            |g| {
                let z = g.b.ins().iconst(I64, 0);
                g.mem_call(desc, at, z, z)
            },
            |g| {
                let p = g.b.ins().iadd(base, at);
                if ty.size() == 8 {
                    g.b.ins().load(I64, MemFlagsData::new(), p, 0)
                } else {
                    let w = g.b.ins().load(I32, MemFlagsData::new(), p, 0);
                    let w = g.zx(w);
                    g.norm(ty, w)
                }
            },
        ))
    }

    fn store(&mut self, ty: Sc, space: Space, addr: ir::Reg, src: ir::Reg) -> Option<()> {
        let (at, v) = (self.get(addr), self.get(src));
        let desc = MemDesc { ty, space, kind: MemKind::Store };
        let (base, len) = match space {
            Space::Lane => (self.frame, self.frame_len),
            Space::Buffer(slot) => span(self.b, self.run, slot),
            Space::Workgroup => return None,
            _ => {
                self.mem_call(desc, at, v, v);
                return Some(());
            }
        };
        let ok = self.in_bounds(at, len, ty.size());
        self.guarded(
            ok,
            |g| g.mem_call(desc, at, v, v),
            |g| {
                let p = g.b.ins().iadd(base, at);
                let w = if ty.size() == 8 { v } else { g.lo(v) };
                g.b.ins().store(MemFlagsData::new(), w, p, 0);
                g.b.ins().iconst(I64, 0)
            },
        );
        Some(())
    }
}

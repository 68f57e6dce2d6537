//! Registers and control flow of the SIMD code (memory is `mem`'s).
//!
//! Control flow is the interpreter's schedule made static: IR block `i` is emitted behind a
//! guard ("does any lane have its cursor at `i`?"), blocks in index order, so the lanes a block
//! runs for are exactly those the interpreter's lowest-cursor-first rule would run. A block's
//! terminator moves its lanes' cursors; execution falls to the next guard, except that a taken
//! back edge jumps to its header's guard (every running cursor is then at or past it).
//!
//! A vector register is `PARTS` independent i32x4 values side by side: each vector op is
//! emitted once per part, so the core has that many dependency chains to overlap.
use cranelift_codegen::ir::condcodes::IntCC;
use cranelift_codegen::ir::{types, AbiParam, Block, FuncRef, InstBuilder, SigRef, Signature, StackSlot, StackSlotData, StackSlotKind, Value};
use cranelift_frontend::{FunctionBuilder, Variable};

use super::super::super::exec::CHECK_EVERY;
use super::super::super::ir::{self, Op, Program, Sc, Space, Term};
use super::super::codegen::vmath::splat_const;
use super::super::helpers::{self, MemDesc, STOPPED};
use super::types::{Cls, Types};

pub(super) const I64: types::Type = types::I64;
pub(super) const I32: types::Type = types::I32;
pub(super) const I32X4: types::Type = types::I32X4;
pub(super) const F32X4: types::Type = types::F32X4;
/// i32x4 parts of a vector register. Two chains already fill the core's float units between
/// latencies; with four, x64's sixteen vector registers spill and compile time doubles.
pub(in crate::shader) const PARTS: usize = 2;
/// Invocations per call.
pub(in crate::shader) const W: usize = 4 * PARTS;
/// A vector register's value: lane `l` is lane `l % 4` of part `l / 4`.
pub(super) type V = [Value; PARTS];
/// The cursor of a lane that is done (above every block index).
pub(super) const DONE: i64 = i32::MAX as i64;

/// The spaces the SIMD backend reaches (workgroup memory needs the lane schedule of a whole
/// workgroup, images and the rest are left to the other backends).
pub(super) fn space_ok(space: Space) -> Option<()> {
    (!matches!(space, Space::Workgroup | Space::Image(_) | Space::Accel(_))).then_some(())
}

/// A register's value before a run of pure ops.
#[derive(Clone, Copy)]
enum Saved {
    Vec(V),
    Wide([Value; W]),
}

/// A register's variables.
#[derive(Clone, Copy)]
pub(super) enum Var {
    Vec([Variable; PARTS]),
    Wide([Variable; W]),
    Const(u64),
}

pub(super) struct Gen<'p, 'b, 'f> {
    pub b: &'b mut FunctionBuilder<'f>,
    pub prog: &'p Program,
    pub types: Types,
    pub vars: Vec<Var>,
    pub cursor: [Variable; PARTS],
    /// Back edges each lane has taken (with the site, the fault-order key: the interpreter's
    /// lanes run a loop's rounds in step, the blocks of a round in index order), and blocks
    /// the call has run (the watchdog's steps). No back-edge counts when no memory op (no
    /// fault) is inside a loop.
    pub lane_steps: Option<[Variable; PARTS]>,
    pub steps: Variable,
    pub next_poll: Variable,
    /// Invocations still to hand out to lanes (`refill`).
    pub left: Variable,
    pub run: Value,
    pub frame: Value,
    pub push: Value,
    pub push_len: Value,
    pub guards: Vec<Block>,
    /// The running block's lanes: a mask, and per lane an i8 truth value (made only for
    /// blocks whose ops go lane by lane).
    pub mask: V,
    pub on: [Value; W],
    /// The block being emitted.
    pub block: usize,
    /// The run of pure ops since the last memory op or block start: the ops, the values the
    /// registers they read had before it, the registers it wrote, and whether a float result
    /// in it was a NaN in some lane (`redo`: the run is being emitted again through the
    /// helpers).
    pending: Vec<Op>,
    saved: Vec<(ir::Reg, Saved)>,
    written: Vec<bool>,
    pub nan_acc: Option<V>,
    /// A float result whose NaN test waits for a second one.
    pub nan_pending: Option<V>,
    pub redo: bool,
    sigs: Vec<SigRef>,
    /// `tramp`'s lane helpers (1 to 3 operands) and their buffer.
    pub tramps: [FuncRef; 3],
    pub buf: StackSlot,
    /// `refill`'s watchdog poll that clobbers no register (set after `new`).
    pub calls: Option<[FuncRef; super::tramp::MAX_ARGS]>,
    pub descs: Vec<MemDesc>,
    /// Bytes of one lane's frame; lane `l`'s frame starts at `l * fs`.
    pub fs: u32,
    /// Per block, the header of the outermost loop holding it (`refill::outermost_loops`).
    pub outer: Vec<Option<u32>>,
    /// Per block and op, whether its float result needs no NaN test (`nan::covered`), and
    /// that answer for the op being emitted.
    nan_covered: Vec<Vec<bool>>,
    pub skip_nan: bool,
    /// Not-equal-zero tests folded into their select (`fuse`).
    fused: super::fuse::Fused,
}

fn sig(call_conv: cranelift_codegen::isa::CallConv, n: usize) -> Signature {
    let mut s = Signature::new(call_conv);
    s.params.extend((0..n).map(|_| AbiParam::new(I64)));
    s.returns.push(AbiParam::new(I64));
    s
}

/// Every register's variables, zero in every lane (constants some op also writes: their value).
fn declare_regs(b: &mut FunctionBuilder, prog: &Program, types: &Types) -> Vec<Var> {
    let zero64 = b.ins().iconst(I64, 0);
    let zero32 = b.ins().iconst(I32, 0);
    let zv = b.ins().splat(I32X4, zero32);
    let vars: Vec<Var> = (0..prog.reg_count)
        .map(|r| {
            if let Some(k) = types.konst(r) {
                return Var::Const(k);
            }
            match types.cls(r) {
                Cls::W64 => Var::Wide(std::array::from_fn(|_| {
                    let v = b.declare_var(I64);
                    b.def_var(v, zero64);
                    v
                })),
                _ => Var::Vec(std::array::from_fn(|_| {
                    let v = b.declare_var(I32X4);
                    b.def_var(v, zv);
                    v
                })),
            }
        })
        .collect();
    // Constants some op also writes start as their value in every lane.
    for &(r, k) in &prog.consts {
        match vars[r as usize] {
            Var::Wide(vs) => {
                let c = b.ins().iconst(I64, k as i64);
                vs.iter().for_each(|&v| b.def_var(v, c));
            }
            Var::Vec(vs) => {
                let w = if types.cls(r) == Cls::B { -((k != 0) as i64) } else { k as u32 as i64 };
                let c = b.ins().iconst(I32, w as i32 as u32 as i64);
                let c = b.ins().splat(I32X4, c);
                vs.iter().for_each(|&v| b.def_var(v, c));
            }
            Var::Const(_) => {}
        }
    }
    vars
}

/// Whether block `blk` has ops that go lane by lane (memory, or writes of wide registers),
/// which need the per-lane truth values.
fn lane_ops(types: &Types, blk: &ir::Block, frame: usize) -> bool {
    let wide = |r: ir::Reg| types.konst(r).is_none() && types.cls(r) == Cls::W64;
    // Loads at constant offsets of the lane frame or push constants need no lane's truth
    // value (`mem`: every frame is there; a push constant is one load for all).
    let uniform = |op: &Op| match *op {
        Op::Load { space: Space::Push, addr, .. } => types.konst(addr).is_some(),
        Op::Load { ty, space: Space::Lane, addr, .. } => types.konst(addr).is_some_and(|k| k.checked_add(ty.size() as u64).is_some_and(|e| e <= frame as u64)),
        _ => false,
    };
    blk.phi_in.iter().any(|&(d, _)| wide(d))
        || blk.ops.iter().any(|op| (matches!(op, Op::Load { .. } | Op::Store { .. } | Op::Atomic { .. }) && !uniform(op)) || super::types::defs_uses(op).is_some_and(|d| d.0.iter().any(|&r| wide(r))))
}

impl<'p, 'b, 'f> Gen<'p, 'b, 'f> {
    pub(super) fn new(b: &'b mut FunctionBuilder<'f>, prog: &'p Program, types: Types, call_conv: cranelift_codegen::isa::CallConv, tramps: [FuncRef; 3]) -> Self {
        let entry = b.create_block();
        b.append_block_params_for_function_params(entry);
        b.switch_to_block(entry);
        let p = b.block_params(entry).to_vec();
        let sigs: Vec<SigRef> = (1..=7).map(|n| b.import_signature(sig(call_conv, n))).collect();
        let fs = prog.lane_frame.len() as u32;
        let zero64 = b.ins().iconst(I64, 0);
        let zero32 = b.ins().iconst(I32, 0);
        let zv = b.ins().splat(I32X4, zero32);
        let vars = declare_regs(b, prog, &types);
        let cursor = std::array::from_fn(|_| b.declare_var(I32X4));
        let outer = super::refill::outermost_loops(prog);
        let keyed = prog.blocks.iter().zip(&outer).any(|(blk, o)| o.is_some() && blk.ops.iter().any(|op| matches!(op, Op::Load { .. } | Op::Store { .. } | Op::Atomic { .. })));
        let lane_steps = keyed.then(|| {
            let vs: [Variable; PARTS] = std::array::from_fn(|_| b.declare_var(I32X4));
            vs.iter().for_each(|&v| b.def_var(v, zv));
            vs
        });
        let (steps, next_poll, left) = (b.declare_var(I64), b.declare_var(I64), b.declare_var(I64));
        b.def_var(steps, zero64);
        let first = b.ins().iconst(I64, CHECK_EVERY as i64);
        b.def_var(next_poll, first);
        let guards: Vec<Block> = (0..=prog.blocks.len()).map(|_| b.create_block()).collect();
        let buf = b.create_sized_stack_slot(StackSlotData::new(StackSlotKind::ExplicitSlot, super::tramp::BUF, 4));
        // Refuse a frame too small for every lane (the inline accesses rely on it).
        let (frame_len, ok_b, bad_b) = (p[2], b.create_block(), b.create_block());
        let small = b.ins().icmp_imm_s(IntCC::UnsignedLessThan, frame_len, (fs as usize * W) as i64);
        b.ins().brif(small, bad_b, &[], ok_b, &[]);
        b.switch_to_block(bad_b);
        b.ins().return_(&[zero64]);
        b.switch_to_block(ok_b);
        let fused = super::fuse::fuse(prog, &types);
        let mut g = Gen {
            b,
            prog,
            types,
            vars,
            cursor,
            lane_steps,
            steps,
            next_poll,
            left,
            run: p[0],
            frame: p[1],
            push: p[3],
            push_len: p[4],
            guards,
            mask: [zv; PARTS],
            on: [zero32; W],
            block: 0,
            pending: Vec::new(),
            saved: Vec::new(),
            written: vec![false; prog.reg_count as usize],
            nan_acc: None,
            nan_pending: None,
            redo: false,
            sigs,
            tramps,
            calls: None,
            buf,
            descs: Vec::new(),
            fs,
            outer,
            nan_covered: super::nan::covered(prog),
            skip_nan: false,
            fused,
        };
        // Every lane starts done, with invocations to hand out (the count is the first
        // refill's answer): the code starts at the refill past the last block.
        let done = g.splat32(DONE);
        for (&c, &d) in g.cursor.iter().zip(&done) {
            g.b.def_var(c, d);
        }
        let unknown = g.b.ins().iconst(I64, -1);
        g.b.def_var(g.left, unknown);
        let end = g.guards[prog.blocks.len()];
        g.b.ins().jump(end, &[]);
        g
    }

    pub(super) fn splat32(&mut self, k: i64) -> V {
        [splat_const(self.b, I32X4, k as u32); PARTS]
    }

    /// `f` of each part.
    pub(super) fn map(&mut self, x: V, f: impl Fn(&mut FunctionBuilder<'f>, Value) -> Value) -> V {
        std::array::from_fn(|p| f(self.b, x[p]))
    }
    pub(super) fn map2(&mut self, x: V, y: V, f: impl Fn(&mut FunctionBuilder<'f>, Value, Value) -> Value) -> V {
        std::array::from_fn(|p| f(self.b, x[p], y[p]))
    }
    pub(super) fn map3(&mut self, x: V, y: V, z: V, f: impl Fn(&mut FunctionBuilder<'f>, Value, Value, Value) -> Value) -> V {
        std::array::from_fn(|p| f(self.b, x[p], y[p], z[p]))
    }

    /// Whether any lane of mask `m` is set.
    pub(super) fn any(&mut self, m: V) -> Value {
        let all = m[1..].iter().fold(m[0], |acc, &x| self.b.ins().bor(acc, x));
        self.b.ins().vany_true(all)
    }

    /// Lane `l` of `v`.
    pub(super) fn lane(&mut self, v: V, l: usize) -> Value {
        self.b.ins().extractlane(v[l / 4], (l % 4) as u8)
    }

    /// Emits every block; None when something is not compiled.
    pub(super) fn translate(&mut self) -> Option<()> {
        let prog = self.prog;
        let reached = super::refill::reachable(prog);
        for (i, blk) in prog.blocks.iter().enumerate() {
            self.b.switch_to_block(self.guards[i]);
            if !reached[i] {
                // No cursor ever names it (glslang's merge blocks after a return).
                self.b.ins().jump(self.guards[i + 1], &[]);
                continue;
            }
            let c = self.cursors();
            let here = self.splat32(i as i64);
            let m = self.map2(c, here, |b, c, h| b.ins().icmp(IntCC::Equal, c, h));
            let any = self.any(m);
            let body = self.b.create_block();
            self.b.ins().brif(any, body, &[], self.guards[i + 1], &[]);
            self.b.switch_to_block(body);
            if let Some((stay_if, exit)) = super::tight::self_loop(i, blk) {
                self.tight_loop(i as u32, blk, m, stay_if, exit)?;
            } else {
                self.body(i, blk, m)?;
                self.term(i as u32, blk)?;
            }
        }
        self.refill_end();
        self.b.seal_all_blocks();
        Some(())
    }

    /// Block `i`'s phi moves and ops for the lanes of mask `m` (its terminator is the caller's).
    pub(super) fn body(&mut self, i: usize, blk: &ir::Block, m: V) -> Option<()> {
        self.mask = m;
        self.block = i;
        if lane_ops(&self.types, blk, self.prog.lane_frame.len()) {
            for l in 0..W {
                let x = self.lane(m, l);
                self.on[l] = self.b.ins().icmp_imm_s(IntCC::NotEqual, x, 0);
            }
        }
        let s = self.b.use_var(self.steps);
        let s = self.b.ins().iadd_imm_s(s, 1);
        self.b.def_var(self.steps, s);
        for &(dst, tmp) in &blk.phi_in {
            self.mov(dst, tmp);
        }
        for (k, op) in blk.ops.iter().enumerate() {
            if self.fused.skip[i][k] {
                continue;
            }
            self.skip_nan = self.nan_covered[i][k];
            if super::types::pure(op) {
                self.save_inputs(op);
                self.op(op)?;
                self.pending.push(op.clone());
            } else {
                self.flush()?;
                self.op(op)?;
            }
        }
        self.skip_nan = false;
        self.flush()
    }

    pub(super) fn cursors(&mut self) -> V {
        std::array::from_fn(|p| self.b.use_var(self.cursor[p]))
    }

    // ---- runs of pure ops ----

    /// Notes the pre-run values of the registers `op` reads that the run has not written.
    fn save_inputs(&mut self, op: &Op) {
        let (defs, uses) = super::types::defs_uses(op).unwrap_or_default();
        for r in uses {
            if self.written[r as usize] || self.saved.iter().any(|s| s.0 == r) {
                continue;
            }
            let v = match self.vars[r as usize] {
                Var::Vec(vs) => Saved::Vec(vs.map(|v| self.b.use_var(v))),
                Var::Wide(vs) => Saved::Wide(vs.map(|v| self.b.use_var(v))),
                Var::Const(_) => continue,
            };
            self.saved.push((r, v));
        }
        defs.into_iter().for_each(|d| self.written[d as usize] = true);
    }

    /// Ends the run: when a float result in it was a NaN in a running lane, the run again
    /// from its inputs with every float op through the helpers (the interpreter's NaN bits).
    fn flush(&mut self) -> Option<()> {
        let ops = std::mem::take(&mut self.pending);
        let saved = std::mem::take(&mut self.saved);
        ops.iter().filter_map(super::types::defs_uses).flat_map(|d| d.0).for_each(|d| self.written[d as usize] = false);
        let Some(acc) = self.nan_lanes() else { return Some(()) };
        let mask = self.mask;
        let nan = self.map2(acc, mask, |b, a, m| b.ins().band(a, m));
        let any = self.any(nan);
        let (slow, join) = (self.b.create_block(), self.b.create_block());
        self.b.set_cold_block(slow);
        self.b.ins().brif(any, slow, &[], join, &[]);
        self.b.switch_to_block(slow);
        for (r, v) in saved {
            match (self.vars[r as usize], v) {
                (Var::Vec(vs), Saved::Vec(xs)) => (0..PARTS).for_each(|p| self.b.def_var(vs[p], xs[p])),
                (Var::Wide(vs), Saved::Wide(xs)) => (0..W).for_each(|l| self.b.def_var(vs[l], xs[l])),
                _ => {}
            }
        }
        self.redo = true;
        for op in &ops {
            self.op(op)?;
        }
        self.redo = false;
        self.b.ins().jump(join, &[]);
        self.b.switch_to_block(join);
        Some(())
    }

    // ---- registers ----

    /// Register `r` as a vector in class `c` (W32 or B).
    /// (A register of another class is converted as the interpreter would read its word.)
    pub(super) fn vget(&mut self, r: ir::Reg, c: Cls) -> V {
        match self.vars[r as usize] {
            Var::Vec(vs) => {
                let x = vs.map(|v| self.b.use_var(v));
                match (self.types.cls(r), c) {
                    (Cls::B, Cls::W32) => {
                        let one = self.splat32(1);
                        self.map2(x, one, |b, x, o| b.ins().band(x, o))
                    }
                    (Cls::W32, Cls::B) => {
                        let z = self.splat32(0);
                        self.map2(x, z, |b, x, z| b.ins().icmp(IntCC::NotEqual, x, z))
                    }
                    _ => x,
                }
            }
            Var::Const(k) => self.splat32(if c == Cls::B { -((k != 0) as i64) } else { k as u32 as i64 }),
            Var::Wide(_) => {
                let w = self.words(r);
                let w = if c == Cls::B { w.map(|x| self.b.ins().icmp_imm_s(IntCC::NotEqual, x, 0)).map(|x| self.b.ins().uextend(I64, x)) } else { w };
                self.vec_of_words(w, c == Cls::B)
            }
        }
    }

    /// Register `r`'s word in lane `l`, as the interpreter holds it.
    pub(super) fn word(&mut self, r: ir::Reg, l: usize) -> Value {
        match self.vars[r as usize] {
            Var::Wide(vs) => self.b.use_var(vs[l]),
            Var::Const(k) => self.b.ins().iconst(I64, k as i64),
            Var::Vec(vs) => {
                let v = self.b.use_var(vs[l / 4]);
                let x = self.b.ins().extractlane(v, (l % 4) as u8);
                let x = if self.types.cls(r) == Cls::B { self.b.ins().band_imm_u(x, 1) } else { x };
                self.b.ins().uextend(I64, x)
            }
        }
    }

    pub(super) fn words(&mut self, r: ir::Reg) -> [Value; W] {
        std::array::from_fn(|l| self.word(r, l))
    }

    /// Writes vector `v` to `r` for the running lanes.
    pub(super) fn vset(&mut self, r: ir::Reg, v: V) {
        let Var::Vec(vars) = self.vars[r as usize] else { unreachable!("a vector written to a wide register") };
        let blend = self.types.blends(self.block, r);
        for p in 0..PARTS {
            let x = if !blend {
                v[p]
            } else {
                let old = self.b.use_var(vars[p]);
                self.b.ins().bitselect(self.mask[p], v[p], old)
            };
            self.b.def_var(vars[p], x);
        }
    }

    /// Writes interpreter words (one per lane) to `r` in its class.
    pub(super) fn set_words(&mut self, r: ir::Reg, w: [Value; W]) {
        match self.vars[r as usize] {
            Var::Wide(vs) => {
                for l in 0..W {
                    let v = if !self.types.blends(self.block, r) {
                        w[l]
                    } else {
                        let old = self.b.use_var(vs[l]);
                        self.b.ins().select(self.on[l], w[l], old)
                    };
                    self.b.def_var(vs[l], v);
                }
            }
            Var::Vec(_) => {
                let bool_ = self.types.cls(r) == Cls::B;
                let v = self.vec_of_words(w, bool_);
                self.vset(r, v);
            }
            Var::Const(_) => unreachable!("a constant written"),
        }
    }

    /// One word per lane as a W32 vector (low halves) or a B mask (word != 0).
    pub(super) fn vec_of_words(&mut self, w: [Value; W], bool_: bool) -> V {
        if w.iter().all(|&x| x == w[0]) {
            // One word for every lane (a uniform load): a splat.
            let x = if bool_ { self.b.ins().bmask(I32, w[0]) } else { self.b.ins().ireduce(I32, w[0]) };
            return [self.b.ins().splat(I32X4, x); PARTS];
        }
        let lanes: Vec<Value> = w.iter().map(|&x| if bool_ { self.b.ins().bmask(I32, x) } else { self.b.ins().ireduce(I32, x) }).collect();
        std::array::from_fn(|p| {
            let mut v = self.b.ins().splat(I32X4, lanes[4 * p]);
            for l in 1..4 {
                v = self.b.ins().insertlane(v, lanes[4 * p + l], l as u8);
            }
            v
        })
    }

    fn mov(&mut self, dst: ir::Reg, src: ir::Reg) {
        match self.types.cls(dst) {
            Cls::W64 => {
                let w = self.words(src);
                self.set_words(dst, w);
            }
            c => {
                let v = self.vget(src, c);
                self.vset(dst, v);
            }
        }
    }

    // ---- calls ----

    fn call(&mut self, f: usize, sig: SigRef, args: &[Value]) -> Value {
        let callee = self.b.ins().iconst(I64, f as i64);
        let inst = self.b.ins().call_indirect(sig, callee, args);
        self.b.inst_results(inst)[0]
    }

    /// Helper `f` of `args`, through the `preserve_all` trampoline of its arity (`tramp`).
    pub(super) fn call_int(&mut self, f: usize, args: &[Value]) -> Value {
        let Some(calls) = self.calls else {
            let sig = self.sigs[args.len() - 1];
            return self.call(f, sig, args);
        };
        let fv = self.b.ins().iconst(I64, f as i64);
        self.b.ins().stack_store(I64, fv, self.buf, 0);
        for (k, &a) in args.iter().enumerate() {
            self.b.ins().stack_store(I64, a, self.buf, 8 * (k as i32 + 1));
        }
        let p = self.b.ins().stack_addr(I64, self.buf, 0);
        self.b.ins().call(calls[args.len() - 1], &[p]);
        self.b.ins().stack_load(I64, I64, self.buf, 8 * (args.len() as i32 + 1))
    }

    // ---- control flow ----

    fn term(&mut self, i: u32, blk: &ir::Block) -> Option<()> {
        let m = self.mask;
        let cur = self.cursors();
        // Each lane's next cursor (lanes outside the mask keep theirs).
        let next = match &blk.term {
            Term::Jump(t) => self.splat32(*t as i64),
            Term::Cond { cond, t, f } => {
                let c = self.vget(*cond, Cls::B);
                let (t, f) = (self.splat32(*t as i64), self.splat32(*f as i64));
                self.map3(c, t, f, |b, c, t, f| b.ins().bitselect(c, t, f))
            }
            Term::Switch { sel, default, cases } => {
                let s = self.vget(*sel, Cls::W32);
                let mut v = self.splat32(*default as i64);
                // The first matching case wins: apply them last to first.
                for &(k, target) in cases.iter().rev() {
                    let k = self.splat32(k as u32 as i64);
                    let hit = self.map2(s, k, |b, s, k| b.ins().icmp(IntCC::Equal, s, k));
                    let t = self.splat32(target as i64);
                    v = self.map3(hit, t, v, |b, h, t, v| b.ins().bitselect(h, t, v));
                }
                if cases.iter().any(|c| c.0 > u32::MAX as u64) {
                    return None;
                }
                v
            }
            Term::Exit => self.splat32(DONE),
            Term::Barrier(_) => return None,
        };
        let moved = self.map3(m, next, cur, |b, m, n, c| b.ins().bitselect(m, n, c));
        for (&var, &v) in self.cursor.iter().zip(&moved) {
            self.b.def_var(var, v);
        }
        let back: Vec<u32> = match &blk.term {
            Term::Jump(t) => vec![*t],
            Term::Cond { t, f, .. } => vec![*t, *f],
            Term::Switch { default, cases, .. } => cases.iter().map(|c| c.1).chain([*default]).collect(),
            _ => vec![],
        };
        let mut targets: Vec<u32> = blk.edge_moves.iter().map(|e| e.target).chain(back.iter().copied().filter(|&t| (t as usize) < self.outer.len() && self.outer[t as usize] == Some(t))).collect();
        targets.sort_unstable();
        targets.dedup();
        for t in targets {
            let tv = self.splat32(t as i64);
            let to = self.map2(next, tv, |b, n, t| b.ins().icmp(IntCC::Equal, n, t));
            let lanes = self.map2(to, m, |b, t, m| b.ins().band(t, m));
            for e in blk.edge_moves.iter().filter(|e| e.target == t) {
                self.edge_move(lanes, e.dst, e.src);
            }
            self.enter_loop(i, t, lanes);
        }
        let header = back.into_iter().filter(|&t| t <= i).min();
        let fall = self.guards[i as usize + 1];
        if let Some(h) = header {
            let iv = self.splat32(i as i64);
            let took = match blk.term {
                // A two-way branch with one back edge: the condition picks the lanes.
                Term::Cond { cond, t, f } if (t <= i) != (f <= i) => {
                    let c = self.vget(cond, Cls::B);
                    if t <= i { self.map2(c, m, |b, c, m| b.ins().band(c, m)) } else { self.map2(m, c, |b, m, c| b.ins().band_not(m, c)) }
                }
                _ => {
                    let took = self.map2(next, iv, |b, n, i| b.ins().icmp(IntCC::UnsignedLessThanOrEqual, n, i));
                    self.map2(took, m, |b, t, m| b.ins().band(t, m))
                }
            };
            self.count_back_edges(took);
            let any = self.any(took);
            let back_b = self.b.create_block();
            self.b.ins().brif(any, back_b, &[], fall, &[]);
            self.b.switch_to_block(back_b);
            self.back_edge(i, h);
        } else {
            self.b.ins().jump(fall, &[]);
        }
        Some(())
    }

    /// A phi temporary filled for the lanes in `lanes` (a mask).
    pub(super) fn edge_move(&mut self, lanes: V, dst: ir::Reg, src: ir::Reg) {
        match self.vars[dst as usize] {
            Var::Vec(vars) => {
                let v = self.vget(src, self.types.cls(dst));
                for p in 0..PARTS {
                    let old = self.b.use_var(vars[p]);
                    let x = self.b.ins().bitselect(lanes[p], v[p], old);
                    self.b.def_var(vars[p], x);
                }
            }
            Var::Wide(vs) => {
                let w = self.words(src);
                for l in 0..W {
                    let x = self.lane(lanes, l);
                    let on = self.b.ins().icmp_imm_s(IntCC::NotEqual, x, 0);
                    let old = self.b.use_var(vs[l]);
                    let v = self.b.ins().select(on, w[l], old);
                    self.b.def_var(vs[l], v);
                }
            }
            Var::Const(_) => unreachable!("a constant written"),
        }
    }

    /// At a taken back edge: once the step count reaches the next poll, ask the watchdog.
    pub(super) fn poll(&mut self) {
        let s = self.b.use_var(self.steps);
        let np = self.b.use_var(self.next_poll);
        let due = self.b.ins().icmp(IntCC::UnsignedGreaterThanOrEqual, s, np);
        let (call, stop, cont) = (self.b.create_block(), self.b.create_block(), self.b.create_block());
        self.b.set_cold_block(call);
        self.b.set_cold_block(stop);
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

    // ---- ops ----

    fn select(&mut self, dst: ir::Reg, cond: ir::Reg, a: ir::Reg, b: ir::Reg) {
        if let Some(t) = self.fused.negated[cond as usize] {
            // `t != 0 ? a : b` is `t == 0 ? b : a`.
            let (x, y, z) = (self.vget(t, Cls::W32), self.vget(b, self.types.cls(dst)), self.vget(a, self.types.cls(dst)));
            let zero = self.splat32(0);
            let eq = self.map2(x, zero, |b, x, z| b.ins().icmp(IntCC::Equal, x, z));
            let v = self.map3(eq, y, z, |b, c, y, z| b.ins().bitselect(c, y, z));
            self.vset(dst, v);
            return;
        }
        let c = self.vget(cond, Cls::B);
        match self.types.cls(dst) {
            Cls::W64 => {
                let (x, y) = (self.words(a), self.words(b));
                let w = std::array::from_fn(|l| {
                    let cl = self.lane(c, l);
                    let cl = self.b.ins().icmp_imm_s(IntCC::NotEqual, cl, 0);
                    self.b.ins().select(cl, x[l], y[l])
                });
                self.set_words(dst, w);
            }
            // `c && a` and `c || b` (logical and/or as glslang writes them): one op, no blend.
            Cls::B if b == cond => {
                let x = self.vget(a, Cls::B);
                let v = self.map2(c, x, |b, c, x| b.ins().band(c, x));
                self.vset(dst, v);
            }
            Cls::B if a == cond => {
                let y = self.vget(b, Cls::B);
                let v = self.map2(c, y, |b, c, y| b.ins().bor(c, y));
                self.vset(dst, v);
            }
            cl => {
                let (x, y) = (self.vget(a, cl), self.vget(b, cl));
                let v = self.map3(c, x, y, |b, c, x, y| b.ins().bitselect(c, x, y));
                self.vset(dst, v);
            }
        }
    }

    fn op(&mut self, op: &Op) -> Option<()> {
        match *op {
            Op::Mov { dst, src } => self.mov(dst, src),
            Op::Select { dst, cond, a, b } => self.select(dst, cond, a, b),
            Op::Index { dst, base, index, index_ty, stride } => {
                let base = self.words(base);
                let w = std::array::from_fn(|l| {
                    let i = self.word(index, l);
                    let i = if index_ty == Sc::I32 {
                        let x = self.b.ins().ireduce(I32, i);
                        self.b.ins().sextend(I64, x)
                    } else {
                        i
                    };
                    let scaled = self.b.ins().imul_imm_s(i, stride as i64);
                    self.b.ins().iadd(base[l], scaled)
                });
                self.set_words(dst, w);
            }
            Op::AddImm { dst, a, imm } => {
                let x = self.words(a);
                let w = x.map(|x| self.b.ins().iadd_imm_s(x, imm as i64));
                self.set_words(dst, w);
            }
            Op::Bin { op, ty, dst, a, b } => self.bin(op, ty, dst, a, b)?,
            Op::Un { op, ty, from, dst, a } => self.un(op, ty, from, dst, a)?,
            Op::Tri { op, ty, dst, a, b, c } => self.tri(op, ty, dst, a, b, c)?,
            Op::BitInsert { ty, dst, base, insert, offset, count } => {
                let t = helpers::ty_code(ty) as i64;
                let w = std::array::from_fn(|l| {
                    let t = self.b.ins().iconst(I64, t);
                    let args = [t, self.word(base, l), self.word(insert, l), self.word(offset, l), self.word(count, l)];
                    self.call_int(helpers::bit_insert as *const () as usize, &args)
                });
                self.set_words(dst, w);
            }
            Op::Load { ty, space, dst, addr } => {
                let w = self.load(ty, space, addr)?;
                self.set_words(dst, w);
            }
            Op::Store { ty, space, addr, src } => self.store(ty, space, addr, src)?,
            Op::Atomic { op, ty, space, dst, addr, a, b } => self.atomic(op, ty, space, dst, addr, a, b)?,
            _ => return None,
        }
        Some(())
    }
}

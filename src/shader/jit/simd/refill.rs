//! Lane refill: one call runs a whole workgroup, and a lane whose invocation has ended takes
//! the workgroup's next one, so that a loop whose lanes end at very different times (Collatz
//! step counts) keeps every lane busy instead of idling until the longest lane of the call is
//! done.
//!
//! At a taken back edge, when enough lanes are parked past the loop and invocations remain,
//! execution falls through instead of jumping back: the blocks after the loop run for the
//! parked lanes while the looping ones wait at their header's guard. Past the last block the
//! done lanes are refilled (`helpers::refill` assigns invocations and fills their frames);
//! their cursors and block counts restart at 0 and every register read before it is written
//! on some path from block 0 takes its initial value again, then execution restarts at guard
//! 0. Lanes are independent (the backend declines workgroup memory, barriers and every op
//! that crosses lanes), so any schedule gives each lane the interpreter's results; faults are
//! keyed per lane (`helpers::FaultKey`).
//!
//! Lanes may now wait at a back edge's target below the running block, so a write must keep
//! (blend) the waiting lanes' values of the registers live there (`widen_blends`).
use cranelift_codegen::ir::condcodes::IntCC;
use cranelift_codegen::ir::{InstBuilder, Value};

use super::super::super::ir::{Program, Reg, Term};
use super::super::helpers;
use super::gen::{Gen, Var, DONE, I32, I32X4, I64, PARTS, V, W};
use super::types::{defs_uses, Cls, Types};

/// Parked lanes (past the loop, done ones included) for which a back edge falls through: three
/// in eight, fewer refill passes while most lanes are still busy (docs/BENCHMARKS.md).
pub(super) const THRESHOLD: u32 = if 3 * W / 8 > 1 { (3 * W / 8) as u32 } else { 1 };

/// A register set, a bit per register.
pub(super) type Set = Vec<u64>;

pub(super) fn has(s: &Set, r: Reg) -> bool {
    s[r as usize / 64] >> (r % 64) & 1 != 0
}

pub(super) fn successors(term: &Term) -> Vec<usize> {
    match term {
        Term::Jump(t) | Term::Barrier(t) => vec![*t as usize],
        Term::Cond { t, f, .. } => vec![*t as usize, *f as usize],
        Term::Switch { default, cases, .. } => cases.iter().map(|c| c.1 as usize).chain([*default as usize]).collect(),
        Term::Exit => vec![],
    }
}

/// Per block, whether some path from block 0 reaches it.
pub(super) fn reachable(prog: &Program) -> Vec<bool> {
    let mut seen = vec![false; prog.blocks.len()];
    let mut work = vec![0usize];
    while let Some(b) = work.pop() {
        if b < seen.len() && !seen[b] {
            seen[b] = true;
            work.extend(successors(&prog.blocks[b].term));
        }
    }
    seen
}

/// The registers live into each block: read before written on some path from its start.
pub(super) fn live_in(prog: &Program) -> Vec<Set> {
    let words = (prog.reg_count as usize).div_ceil(64);
    let nb = prog.blocks.len();
    let set = |v: &mut Set, r: Reg| v[r as usize / 64] |= 1 << (r % 64);
    let mut gen = vec![vec![0u64; words]; nb];
    let mut kill = vec![vec![0u64; words]; nb];
    for (b, blk) in prog.blocks.iter().enumerate() {
        let (g, k) = (&mut gen[b], &mut kill[b]);
        let use_ = |g: &mut Set, k: &Set, r: Reg| {
            if !has(k, r) {
                set(g, r);
            }
        };
        for &(d, t) in &blk.phi_in {
            use_(g, k, t);
            set(k, d);
        }
        for op in &blk.ops {
            let (d, u) = defs_uses(op).unwrap_or_default();
            u.into_iter().for_each(|r| use_(g, k, r));
            d.into_iter().for_each(|r| set(k, r));
        }
        let term = match blk.term {
            Term::Cond { cond, .. } => Some(cond),
            Term::Switch { sel, .. } => Some(sel),
            _ => None,
        };
        // Edge moves write on one edge only: uses, not kills.
        term.into_iter().chain(blk.edge_moves.iter().map(|m| m.src)).for_each(|r| use_(g, k, r));
    }
    let succ: Vec<Vec<usize>> = prog.blocks.iter().map(|b| successors(&b.term)).collect();
    let mut live = gen.clone();
    let mut changed = true;
    while changed {
        changed = false;
        for b in (0..nb).rev() {
            for w in 0..words {
                let out = succ[b].iter().filter(|&&s| s < nb).fold(0u64, |acc, &s| acc | live[s][w]);
                let v = gen[b][w] | (out & !kill[b][w]);
                if v != live[b][w] {
                    live[b][w] = v;
                    changed = true;
                }
            }
        }
    }
    live
}

/// Per block, the header of the outermost loop holding it (natural loops of the back edges),
/// if any. The interpreter runs such a loop's rounds for a lane group in step and every block
/// outside loops once for the whole group, so faults ordered by (outermost header or block,
/// the lane's back edges inside that loop, site, lane) come in its order (`Gen::fault_progress`).
pub(super) fn outermost_loops(prog: &Program) -> Vec<Option<u32>> {
    let nb = prog.blocks.len();
    let succ: Vec<Vec<usize>> = prog.blocks.iter().map(|b| successors(&b.term)).collect();
    let mut pred = vec![Vec::new(); nb];
    for (b, ss) in succ.iter().enumerate() {
        ss.iter().filter(|&&s| s < nb).for_each(|&s| pred[s].push(b));
    }
    let mut outer: Vec<Option<u32>> = vec![None; nb];
    for (j, ss) in succ.iter().enumerate() {
        for &h in ss.iter().filter(|&&h| h <= j) {
            // The natural loop of j -> h: h and every block reaching j without passing h.
            let mut body = vec![false; nb];
            body[h] = true;
            let mut work = vec![j];
            while let Some(b) = work.pop() {
                if !body[b] {
                    body[b] = true;
                    work.extend(pred[b].iter().copied());
                }
            }
            for (o, _) in outer.iter_mut().zip(&body).filter(|(_, &inside)| inside) {
                *o = Some(o.map_or(h as u32, |x| x.min(h as u32)));
            }
        }
    }
    outer
}

/// Makes every block's writes keep the registers live into any back edge's target below it,
/// where lanes may wait while the block runs for others.
pub(super) fn widen_blends(prog: &Program, types: &mut Types) {
    let live = live_in(prog);
    let mut waiting = vec![0u64; live.first().map_or(0, Vec::len)];
    let targets: Vec<usize> = prog.blocks.iter().enumerate().flat_map(|(j, b)| successors(&b.term).into_iter().filter(move |&t| t <= j)).collect();
    for j in 0..prog.blocks.len() {
        for (w, x) in types.blend[j].iter_mut().enumerate() {
            *x |= waiting[w];
        }
        for &t in targets.iter().filter(|&&t| t == j) {
            waiting.iter_mut().zip(&live[t]).for_each(|(a, b)| *a |= b);
        }
    }
}

impl Gen<'_, '_, '_> {
    /// Lane `l`'s place in the interpreter's order at a memory op of the running block (the
    /// fault key's progress): the outermost loop's header (or the block, outside loops) in the
    /// high word, the lane's back edges taken inside that loop in the low one.
    pub(super) fn fault_progress(&mut self, l: usize) -> Value {
        let Some(h) = self.outer[self.block] else {
            return self.b.ins().iconst(I64, (self.block as i64) << 32);
        };
        let Some(steps) = self.lane_steps else { unreachable!("a memory op in a loop keeps back-edge counts") };
        let ls = self.b.use_var(steps[l / 4]);
        let s = self.b.ins().extractlane(ls, (l % 4) as u8);
        let s = self.b.ins().uextend(I64, s);
        self.b.ins().iadd_imm_s(s, (h as i64) << 32)
    }

    /// The lanes of `lanes` enter outermost loop `t` from block `i`: their back-edge counts
    /// restart.
    pub(super) fn enter_loop(&mut self, i: u32, t: u32, lanes: V) {
        if self.outer[t as usize] != Some(t) || self.outer[i as usize] == Some(t) {
            return;
        }
        self.restart_back_edges(lanes);
    }

    /// The lanes of `lanes` took a back edge: their counts grow by one (a mask lane is -1).
    pub(super) fn count_back_edges(&mut self, lanes: V) {
        for (&v, &m) in self.lane_steps.iter().flat_map(|vs| vs.iter()).zip(&lanes) {
            let ls = self.b.use_var(v);
            let ls = self.b.ins().isub(ls, m);
            self.b.def_var(v, ls);
        }
    }

    /// The back-edge counts of the lanes of `lanes` restart at 0.
    fn restart_back_edges(&mut self, lanes: V) {
        for (&v, &m) in self.lane_steps.iter().flat_map(|vs| vs.iter()).zip(&lanes) {
            let ls = self.b.use_var(v);
            let ls = self.b.ins().band_not(ls, m);
            self.b.def_var(v, ls);
        }
    }

    /// A bit per lane: lane `l` of `m` (a lane mask) in bit `l`.
    pub(super) fn bits(&mut self, m: V) -> Value {
        let mut acc = self.b.ins().vhigh_bits(I64, m[0]);
        for (p, &x) in m.iter().enumerate().skip(1) {
            let hi = self.b.ins().vhigh_bits(I64, x);
            let hi = self.b.ins().ishl_imm_s(hi, 4 * p as i64);
            acc = self.b.ins().bor(acc, hi);
        }
        acc
    }

    /// The lane mask of the lanes whose bit is set in `bits`.
    fn mask_of_bits(&mut self, bits: Value) -> V {
        let x = self.b.ins().ireduce(I32, bits);
        let x = self.b.ins().splat(I32X4, x);
        let z = self.splat32(0);
        std::array::from_fn(|p| {
            let k = self.b.ins().iconst(I32, 1 << (4 * p));
            let mut one = self.b.ins().splat(I32X4, k);
            for l in 1..4 {
                let k = self.b.ins().iconst(I32, 1 << (4 * p + l));
                one = self.b.ins().insertlane(one, k, l as u8);
            }
            let sel = self.b.ins().band(x, one);
            self.b.ins().icmp(IntCC::NotEqual, sel, z[p])
        })
    }

    fn cursor_now(&mut self) -> V {
        std::array::from_fn(|p| self.b.use_var(self.cursor[p]))
    }

    /// A taken back edge from block `i` to header `h`: polls, then falls through to block
    /// `i + 1` when invocations remain and enough lanes are parked past the loop.
    pub(super) fn back_edge(&mut self, i: u32, h: u32) {
        self.poll();
        let (back, fall) = (self.guards[h as usize], self.guards[i as usize + 1]);
        let left = self.b.use_var(self.left);
        let count_b = self.b.create_block();
        self.b.ins().brif(left, count_b, &[], back, &[]);
        self.b.switch_to_block(count_b);
        let cur = self.cursor_now();
        let iv = self.splat32(i as i64);
        let past = self.map2(cur, iv, |b, c, i| b.ins().icmp(IntCC::UnsignedGreaterThan, c, i));
        let past = if THRESHOLD == 1 {
            self.any(past)
        } else {
            let bits = self.bits(past);
            let n = self.b.ins().popcnt(bits);
            self.b.ins().icmp_imm_s(IntCC::UnsignedGreaterThanOrEqual, n, THRESHOLD as i64)
        };
        self.b.ins().brif(past, fall, &[], back, &[]);
    }

    /// Past the last block: refills the done lanes, then restarts at guard 0 while any lane
    /// runs, else returns the call's steps. The entry jumps here with every lane done.
    pub(super) fn refill_end(&mut self) {
        let n = self.prog.blocks.len();
        self.b.switch_to_block(self.guards[n]);
        let cur = self.cursor_now();
        let dv = self.splat32(DONE);
        let done = self.map2(cur, dv, |b, c, d| b.ins().icmp(IntCC::Equal, c, d));
        let done_bits = self.bits(done);
        let left = self.b.use_var(self.left);
        let z = self.b.ins().iconst(I64, 0);
        let some_done = self.b.ins().icmp(IntCC::NotEqual, done_bits, z);
        let some_left = self.b.ins().icmp(IntCC::NotEqual, left, z);
        let go = self.b.ins().band(some_done, some_left);
        let (call_b, check_b) = (self.b.create_block(), self.b.create_block());
        self.b.ins().brif(go, call_b, &[], check_b, &[]);
        self.b.switch_to_block(call_b);
        let run = self.run;
        let r = self.call_int(helpers::refill as *const () as usize, &[run, done_bits]);
        let left = self.b.ins().ushr_imm_u(r, 32);
        self.b.def_var(self.left, left);
        let got = self.mask_of_bits(r);
        let z32 = self.splat32(0);
        for p in 0..PARTS {
            let c = self.b.ins().bitselect(got[p], z32[p], cur[p]);
            self.b.def_var(self.cursor[p], c);
        }
        self.restart_back_edges(got);
        self.reset_live(got);
        self.b.ins().jump(check_b, &[]);
        self.b.switch_to_block(check_b);
        let cur = self.cursor_now();
        let done = self.map2(cur, dv, |b, c, d| b.ins().icmp(IntCC::Equal, c, d));
        let all = done[1..].iter().fold(done[0], |acc, &x| self.b.ins().band(acc, x));
        let all = self.b.ins().vall_true(all);
        let (ret_b, again_b) = (self.b.create_block(), self.b.create_block());
        self.b.ins().brif(all, ret_b, &[], again_b, &[]);
        self.b.switch_to_block(ret_b);
        let s = self.b.use_var(self.steps);
        self.b.ins().return_(&[s]);
        self.b.switch_to_block(again_b);
        // A restart is a back edge for the watchdog.
        self.poll();
        let g0 = self.guards[0];
        self.b.ins().jump(g0, &[]);
    }

    /// Every register live into block 0 takes its initial value in the lanes of `got`.
    fn reset_live(&mut self, got: V) {
        let live = live_in(self.prog);
        let Some(live0) = live.first() else { return };
        let on: [Value; W] = std::array::from_fn(|l| {
            let x = self.lane(got, l);
            self.b.ins().icmp_imm_s(IntCC::NotEqual, x, 0)
        });
        for r in (0..self.prog.reg_count).filter(|&r| has(live0, r)) {
            let k = self.prog.consts.iter().find(|c| c.0 == r).map_or(0, |c| c.1);
            match self.vars[r as usize] {
                Var::Vec(vs) => {
                    let w = if self.types.cls(r) == Cls::B { -((k != 0) as i64) } else { k as u32 as i64 };
                    let init = self.splat32(w);
                    for p in 0..PARTS {
                        let old = self.b.use_var(vs[p]);
                        let v = self.b.ins().bitselect(got[p], init[p], old);
                        self.b.def_var(vs[p], v);
                    }
                }
                Var::Wide(vs) => {
                    let init = self.b.ins().iconst(I64, k as i64);
                    for l in 0..W {
                        let old = self.b.use_var(vs[l]);
                        let v = self.b.ins().select(on[l], init, old);
                        self.b.def_var(vs[l], v);
                    }
                }
                Var::Const(_) => {}
            }
        }
    }
}

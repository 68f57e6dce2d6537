//! Loops of one block: a block whose two-way branch goes back to itself on one side and
//! forward on the other (glslang's and spirv-opt's form of a loop whose body is
//! if-converted: compute-alu, compute-divergent) runs its rounds in a loop of its own that
//! keeps only the mask of the lanes still looping.
//!
//! The general schedule pays, every round, for the guard's cursor test, the cursor's update
//! and refill's count of parked lanes. Here the cursors are left alone while the loop runs
//! (no other block runs in between): the lanes that left get the exit's cursor once, when the
//! loop is left. The lanes parked past the loop are those neither looping nor waiting below
//! it, and the waiting ones are counted once, on entry, so refill's test is one popcount of
//! the looping lanes. Everything else (back-edge counts, the watchdog's poll, edge moves, the
//! NaN re-run) is the general schedule's, round by round, so results, faults and their order
//! are the same.
use cranelift_codegen::ir::condcodes::IntCC;
use cranelift_codegen::ir::InstBuilder;
use cranelift_frontend::Variable;

use super::super::super::ir::{self, Term};
use super::gen::{Gen, I32X4, I64, PARTS, V, W};
use super::refill::THRESHOLD;
use super::types::Cls;

/// For a loop of one block at `i`: whether the branch stays when its condition holds, and
/// the exit target (forward).
pub(super) fn self_loop(i: usize, blk: &ir::Block) -> Option<(bool, u32)> {
    match blk.term {
        Term::Cond { t, f, .. } if t as usize == i && f as usize > i => Some((true, f)),
        Term::Cond { t, f, .. } if f as usize == i && t as usize > i => Some((false, t)),
        _ => None,
    }
}

impl Gen<'_, '_, '_> {
    /// Block `i`, a loop of one block, for the lanes of `m0` (those whose cursor is `i`)
    /// until none loops or refill wants the parked lanes; then falls to block `i + 1`.
    pub(super) fn tight_loop(&mut self, i: u32, blk: &ir::Block, m0: V, stay_if: bool, exit: u32) -> Option<()> {
        let Term::Cond { cond, .. } = blk.term else { return None };
        let cur = self.cursors();
        // The loop is left when at most `limit` lanes still loop: none, or (while invocations
        // are left to hand out) few enough that refill's THRESHOLD lanes are parked past it.
        let iv = self.splat32(i as i64);
        let below = self.map2(cur, iv, |b, c, i| b.ins().icmp(IntCC::SignedLessThan, c, i));
        let below = self.bits(below);
        let below = self.b.ins().popcnt(below);
        let most = self.b.ins().iconst(I64, (W as u32 - THRESHOLD) as i64);
        let limit = self.b.ins().isub(most, below);
        let zero = self.b.ins().iconst(I64, 0);
        let limit = self.b.ins().smax(limit, zero);
        let left = self.b.use_var(self.left);
        let limit = self.b.ins().select(left, limit, zero);
        let looping: [Variable; PARTS] = std::array::from_fn(|_| self.b.declare_var(I32X4));
        for (&v, &x) in looping.iter().zip(&m0) {
            self.b.def_var(v, x);
        }
        let (head, cont, out) = (self.b.create_block(), self.b.create_block(), self.b.create_block());
        self.b.ins().jump(head, &[]);

        self.b.switch_to_block(head);
        let m: V = looping.map(|v| self.b.use_var(v));
        self.body(i as usize, blk, m)?;
        let c = self.vget(cond, Cls::B);
        let took = if stay_if { self.map2(c, m, |b, c, m| b.ins().band(c, m)) } else { self.map2(m, c, |b, m, c| b.ins().band_not(m, c)) };
        for e in &blk.edge_moves {
            let lanes = if e.target == i { took } else { self.map2(m, took, |b, m, t| b.ins().band_not(m, t)) };
            self.edge_move(lanes, e.dst, e.src);
        }
        self.count_back_edges(took);
        for (&v, &x) in looping.iter().zip(&took) {
            self.b.def_var(v, x);
        }
        let bits = self.bits(took);
        let n = self.b.ins().popcnt(bits);
        let again = self.b.ins().icmp(IntCC::SignedGreaterThan, n, limit);
        self.b.ins().brif(again, cont, &[], out, &[]);

        self.b.switch_to_block(cont);
        self.poll();
        self.b.ins().jump(head, &[]);

        // The lanes that left move to the exit; those still looping wait at `i`.
        self.b.switch_to_block(out);
        let now: V = looping.map(|v| self.b.use_var(v));
        let gone = self.map2(m0, now, |b, m, n| b.ins().band_not(m, n));
        let xv = self.splat32(exit as i64);
        for p in 0..PARTS {
            let c = self.b.ins().bitselect(gone[p], xv[p], cur[p]);
            self.b.def_var(self.cursor[p], c);
        }
        self.enter_loop(i, exit, gone);
        let fall = self.guards[i as usize + 1];
        self.b.ins().jump(fall, &[]);
        Some(())
    }
}

//! Which float results need their own NaN test. A run of pure ops is redone through the
//! helpers when a float result in it is a NaN in a running lane (`Gen::flush`), so a result
//! needs no test of its own when a NaN in it cannot vanish before a tested one: every read of
//! it is a later op of the same run that carries a NaN operand into its result (add, subtract,
//! multiply, divide, fma, sqrt, negate), and nothing else reads it (no later block, branch or
//! phi move). The chain ends at a result that is tested, so the run is still redone.
use super::super::super::ir::{BinOp, Block, Op, Program, Reg, Sc, TriOp, UnOp};
use super::refill::{has, live_in, successors, Set};
use super::types::{defs_uses, pure};

/// Whether `op` gives a NaN whenever its F32 operand `r` is one.
fn carries(op: &Op, r: Reg) -> bool {
    match *op {
        Op::Bin { op: BinOp::FAdd | BinOp::FSub | BinOp::FMul | BinOp::FDiv, ty: Sc::F32, a, b, .. } => a == r || b == r,
        Op::Tri { op: TriOp::Fma, ty: Sc::F32, .. } => true,
        Op::Un { op: UnOp::Sqrt | UnOp::FNeg, ty: Sc::F32, .. } => true,
        _ => false,
    }
}

/// Per block, per op: whether the op's result needs no NaN test of its own.
pub(super) fn covered(prog: &Program) -> Vec<Vec<bool>> {
    let live = live_in(prog);
    prog.blocks.iter().map(|blk| block_covered(prog, blk, &live)).collect()
}

fn block_covered(prog: &Program, blk: &Block, live: &[Set]) -> Vec<bool> {
    let nb = prog.blocks.len();
    let words = (prog.reg_count as usize).div_ceil(64);
    let mut out: Set = vec![0; words];
    for s in successors(&blk.term).into_iter().filter(|&s| s < nb) {
        out.iter_mut().zip(&live[s]).for_each(|(o, l)| *o |= l);
    }
    let escapes = |r: Reg| {
        has(&out, r)
            || blk.edge_moves.iter().any(|m| m.src == r)
            || match blk.term {
                super::super::super::ir::Term::Cond { cond, .. } => cond == r,
                super::super::super::ir::Term::Switch { sel, .. } => sel == r,
                _ => false,
            }
    };
    let ops = &blk.ops;
    (0..ops.len())
        .map(|k| {
            let Some((defs, _)) = defs_uses(&ops[k]) else { return false };
            let [d] = defs[..] else { return false };
            if escapes(d) {
                return false;
            }
            // Every later read is a carrying op of the same run, and `d` is not written again.
            for op in &ops[k + 1..] {
                if !pure(op) {
                    // The run ends: a read from here on is a read outside it.
                    return !ops[k + 1..].iter().skip_while(|o| pure(o)).any(|o| defs_uses(o).is_none_or(|(ds, us)| us.contains(&d) || ds.contains(&d)));
                }
                let Some((ds, us)) = defs_uses(op) else { return false };
                if ds.contains(&d) || (us.contains(&d) && !carries(op, d)) {
                    return false;
                }
            }
            true
        })
        .collect()
}

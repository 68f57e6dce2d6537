//! Removes the register copies that promoted variables (`lower_vars`) leave behind, inside one
//! block (where every op runs under the same execution mask):
//!
//! - a load's copy `t = v` whose every use is later in the block, with `v` not written before
//!   the last of them: the uses read `v` and the copy goes;
//! - a store's copy `v = t` right after the op that defines `t`, its only use: that op writes
//!   `v` and the copy goes (ops read all their operands before writing).
//!
//! A value a subgroup op reads stays copied: it may read inactive lanes, whose contents differ.
//! `thread_jumps` then sends branches past empty blocks that only jump forward.
use super::ir::{Block, Op, Reg, Term};

/// Use and definition counts of every register over the whole program.
struct Counts {
    uses: Vec<u32>,
    defs: Vec<u32>,
}

/// Branches to an empty block that only jumps forward go straight to its target. A lane there
/// would wait for every lane behind it before moving on, which it does at the target anyway, so
/// which lanes run each block together is unchanged; the step for the empty block goes.
pub(super) fn thread_jumps(blocks: &mut [Block]) {
    let skip = |blocks: &[Block], mut t: u32| {
        for _ in 0..blocks.len() {
            let Some(b) = blocks.get(t as usize) else { break };
            match b.term {
                Term::Jump(u) if u > t && b.ops.is_empty() && b.phi_in.is_empty() && b.edge_moves.is_empty() => t = u,
                _ => break,
            }
        }
        t
    };
    for i in 0..blocks.len() {
        let term = match &blocks[i].term {
            Term::Jump(t) => Term::Jump(skip(blocks, *t)),
            Term::Cond { cond, t, f } => Term::Cond { cond: *cond, t: skip(blocks, *t), f: skip(blocks, *f) },
            other => other.clone(),
        };
        blocks[i].term = term;
    }
}

pub(super) fn forward(blocks: &mut [Block], reg_count: u32, consts: &[(Reg, u64)]) {
    let mut c = Counts { uses: vec![0; reg_count as usize], defs: vec![0; reg_count as usize] };
    for &(r, _) in consts {
        c.defs[r as usize] += 1;
    }
    for b in blocks.iter() {
        for &(d, t) in &b.phi_in {
            c.defs[d as usize] += 1;
            c.uses[t as usize] += 1;
        }
        for op in &b.ops {
            reads(op, &mut |r| c.uses[r as usize] += 1);
            writes(op, &mut |r| c.defs[r as usize] += 1);
        }
        for m in &b.edge_moves {
            c.defs[m.dst as usize] += 1;
            c.uses[m.src as usize] += 1;
        }
        term_reads(&b.term, &mut |r| c.uses[r as usize] += 1);
    }
    for b in blocks.iter_mut() {
        forward_loads(b, &mut c);
        fold_stores(b, &c);
    }
}

/// Load copies: `Mov t = v` with `t` defined once and used only later in this block.
fn forward_loads(b: &mut Block, c: &mut Counts) {
    let mut i = 0;
    while i < b.ops.len() {
        let Op::Mov { dst: t, src: v } = b.ops[i] else {
            i += 1;
            continue;
        };
        if c.defs[t as usize] != 1 || t == v || !forwardable(b, i, t, v, c.uses[t as usize]) {
            i += 1;
            continue;
        }
        for op in &mut b.ops[i + 1..] {
            replace_reads(op, t, v);
        }
        for m in b.edge_moves.iter_mut().filter(|m| m.src == t) {
            m.src = v;
        }
        match &mut b.term {
            Term::Cond { cond, .. } if *cond == t => *cond = v,
            Term::Switch { sel, .. } if *sel == t => *sel = v,
            _ => {}
        }
        c.uses[v as usize] += c.uses[t as usize];
        c.uses[t as usize] = 0;
        c.defs[t as usize] = 0;
        b.ops.remove(i);
    }
}

/// Whether all `n` uses of `t` are after op `i` in `b`, none by a subgroup op, and `v` is not
/// written between op `i` and the last use (the last using op may write it).
fn forwardable(b: &Block, i: usize, t: Reg, v: Reg, n: u32) -> bool {
    let mut seen = 0;
    let mut v_written = false;
    for op in &b.ops[i + 1..] {
        let mut here = 0;
        reads(op, &mut |r| here += (r == t) as u32);
        if here > 0 {
            if v_written || matches!(op, Op::Subgroup { .. }) {
                return false;
            }
            seen += here;
            if seen == n {
                return true;
            }
        }
        writes(op, &mut |r| v_written |= r == v);
    }
    seen += b.edge_moves.iter().filter(|m| m.src == t).count() as u32;
    term_reads(&b.term, &mut |r| seen += (r == t) as u32);
    seen == n && !v_written
}

/// Store copies: `Mov v = t` right after the single-result op defining `t`, `t` used only here.
fn fold_stores(b: &mut Block, c: &Counts) {
    let mut i = 1;
    while i < b.ops.len() {
        let Op::Mov { dst: v, src: t } = b.ops[i] else {
            i += 1;
            continue;
        };
        let single = c.uses[t as usize] == 1 && c.defs[t as usize] == 1 && t != v;
        match result_mut(&mut b.ops[i - 1]) {
            Some(d) if single && *d == t => {
                *d = v;
                b.ops.remove(i);
            }
            _ => i += 1,
        }
    }
}

/// The result register of an op that writes exactly one register from lane-wise operands.
pub(super) fn result_mut(op: &mut Op) -> Option<&mut Reg> {
    match op {
        Op::Mov { dst, .. }
        | Op::Un { dst, .. }
        | Op::Bin { dst, .. }
        | Op::Tri { dst, .. }
        | Op::BitInsert { dst, .. }
        | Op::Select { dst, .. }
        | Op::Index { dst, .. }
        | Op::AddImm { dst, .. }
        | Op::Load { dst, .. } => Some(dst),
        _ => None,
    }
}

fn term_reads(t: &Term, f: &mut impl FnMut(Reg)) {
    match t {
        Term::Cond { cond, .. } => f(*cond),
        Term::Switch { sel, .. } => f(*sel),
        Term::Jump(_) | Term::Exit | Term::Barrier(_) => {}
    }
}

/// Every register `op` reads.
pub(super) fn reads(op: &Op, f: &mut impl FnMut(Reg)) {
    match op {
        Op::Mov { src, .. } => f(*src),
        Op::Un { a, .. } | Op::AddImm { a, .. } | Op::Ballot { a, .. } => f(*a),
        Op::Bin { a, b, .. } | Op::Subgroup { a, b, .. } => [*a, *b].into_iter().for_each(f),
        Op::Tri { a, b, c, .. } => [*a, *b, *c].into_iter().for_each(f),
        Op::BitInsert { base, insert, offset, count, .. } => [*base, *insert, *offset, *count].into_iter().for_each(f),
        Op::Select { cond, a, b, .. } => [*cond, *a, *b].into_iter().for_each(f),
        Op::Index { base, index, .. } => [*base, *index].into_iter().for_each(f),
        Op::Load { addr, .. } => f(*addr),
        Op::Store { addr, src, .. } => [*addr, *src].into_iter().for_each(f),
        Op::Atomic { addr, a, b, .. } => [*addr, *a, *b].into_iter().for_each(f),
        Op::BallotOp { ballot, b, .. } => ballot.iter().chain([b]).copied().for_each(f),
        Op::ImageRead { index, coord, .. } | Op::ImageTexel { index, coord, .. } => [index].into_iter().chain(coord).copied().for_each(f),
        Op::ImageSize { index, .. } => f(*index),
        Op::ImageWrite { index, coord, src, .. } => [index].into_iter().chain(coord).chain(src).copied().for_each(f),
        Op::RayQuery(rq) => [&rq.query].into_iter().chain(&rq.args).copied().for_each(f),
    }
}

/// Every register `op` writes.
pub(super) fn writes(op: &Op, f: &mut impl FnMut(Reg)) {
    match op {
        Op::Store { .. } | Op::ImageWrite { .. } => {}
        Op::Ballot { dst, .. } | Op::ImageRead { dst, .. } | Op::ImageSize { dst, .. } => dst.iter().copied().for_each(f),
        Op::RayQuery(rq) => rq.dst.iter().copied().for_each(f),
        Op::Mov { dst, .. }
        | Op::Un { dst, .. }
        | Op::Bin { dst, .. }
        | Op::Tri { dst, .. }
        | Op::BitInsert { dst, .. }
        | Op::Select { dst, .. }
        | Op::Index { dst, .. }
        | Op::AddImm { dst, .. }
        | Op::Load { dst, .. }
        | Op::Atomic { dst, .. }
        | Op::Subgroup { dst, .. }
        | Op::BallotOp { dst, .. }
        | Op::ImageTexel { dst, .. } => f(*dst),
    }
}

/// Rewrites reads of `from` in `op` to `to`; only reached for ops `forwardable` accepted.
pub(super) fn replace_reads(op: &mut Op, from: Reg, to: Reg) {
    let r = |x: &mut Reg| {
        if *x == from {
            *x = to;
        }
    };
    match op {
        Op::Mov { src, .. } => r(src),
        Op::Un { a, .. } | Op::AddImm { a, .. } | Op::Ballot { a, .. } => r(a),
        Op::Bin { a, b, .. } | Op::Subgroup { a, b, .. } => [a, b].into_iter().for_each(r),
        Op::Tri { a, b, c, .. } => [a, b, c].into_iter().for_each(r),
        Op::BitInsert { base, insert, offset, count, .. } => [base, insert, offset, count].into_iter().for_each(r),
        Op::Select { cond, a, b, .. } => [cond, a, b].into_iter().for_each(r),
        Op::Index { base, index, .. } => [base, index].into_iter().for_each(r),
        Op::Load { addr, .. } => r(addr),
        Op::Store { addr, src, .. } => [addr, src].into_iter().for_each(r),
        Op::Atomic { addr, a, b, .. } => [addr, a, b].into_iter().for_each(r),
        Op::BallotOp { ballot, b, .. } => ballot.iter_mut().chain([b]).for_each(r),
        Op::ImageRead { index, coord, .. } | Op::ImageTexel { index, coord, .. } => [index].into_iter().chain(coord).for_each(r),
        Op::ImageSize { index, .. } => r(index),
        Op::ImageWrite { index, coord, src, .. } => [index].into_iter().chain(coord).chain(src).for_each(r),
        Op::RayQuery(rq) => [&mut rq.query].into_iter().chain(&mut rq.args).for_each(r),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shader::ir::{BinOp, Sc};

    fn block(ops: Vec<Op>) -> Block {
        Block { ops, term: Term::Exit, phi_in: Vec::new(), edge_moves: Vec::new() }
    }

    fn add(dst: Reg, a: Reg, b: Reg) -> Op {
        Op::Bin { op: BinOp::IAdd, ty: Sc::I32, dst, a, b }
    }

    #[test]
    fn increments_read_and_write_the_variable_directly() {
        // t = v; u = t + k; v = u  →  v = v + k
        let mut b = [block(vec![Op::Mov { dst: 1, src: 0 }, add(3, 1, 2), Op::Mov { dst: 0, src: 3 }])];
        forward(&mut b, 4, &[(2, 5)]);
        assert_eq!(b[0].ops, vec![add(0, 0, 2)]);
    }

    #[test]
    fn a_value_loaded_before_a_store_keeps_its_copy() {
        // t = v; v = k; u = t + k: u must see the old v.
        let ops = vec![Op::Mov { dst: 1, src: 0 }, Op::Mov { dst: 0, src: 2 }, add(3, 1, 2), Op::Store { ty: Sc::I32, space: crate::shader::ir::Space::Lane, addr: 2, src: 3 }];
        let mut b = [block(ops.clone())];
        forward(&mut b, 4, &[(2, 5)]);
        assert_eq!(b[0].ops, ops);
    }

    #[test]
    fn only_forward_jumps_out_of_empty_blocks_are_threaded() {
        let jump = |t| Block { term: Term::Jump(t), ..block(Vec::new()) };
        // 0 → 1 (empty, → 2) → 2 (empty, back to 1); 3 (→ 2) ends at 2 since 2 jumps back.
        let mut b = [jump(1), jump(2), jump(1), jump(2), block(Vec::new())];
        thread_jumps(&mut b);
        let targets: Vec<Term> = b.iter().map(|b| b.term.clone()).collect();
        assert_eq!(targets, vec![Term::Jump(2), Term::Jump(2), Term::Jump(2), Term::Jump(2), Term::Exit]);
    }

    #[test]
    fn a_value_used_in_another_block_keeps_its_copy() {
        let mut b = [block(vec![Op::Mov { dst: 1, src: 0 }]), block(vec![add(3, 1, 2)])];
        forward(&mut b, 4, &[(2, 5)]);
        assert_eq!(b[0].ops, vec![Op::Mov { dst: 1, src: 0 }]);
    }
}

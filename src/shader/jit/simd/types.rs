//! Which vector form each register takes: one class per register, found by unifying the types
//! every op reads and writes it as. A register that is both (an I32 word read as I64, a Bool
//! read as an integer) has no single form, and the program is declined.
use super::super::super::ir::{BinOp, Op, Program, Reg, Sc, Space, Term};

/// A register's form in the SIMD code.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Cls {
    /// I32 or F32: i32x4 vectors of the low 32 bits (the upper half of the word is zero).
    W32,
    /// Bool: i32x4 lane masks (all ones for true).
    B,
    /// I64, F64 and addresses: one scalar i64 word per lane.
    W64,
}

pub(super) fn cls(ty: Sc) -> Cls {
    match ty {
        Sc::Bool => Cls::B,
        Sc::I32 | Sc::F32 => Cls::W32,
        Sc::I64 | Sc::F64 => Cls::W64,
    }
}

/// Whether the op's result is a Bool whatever type it compares.
pub(super) fn bool_result(op: BinOp) -> bool {
    use BinOp::*;
    matches!(
        op,
        IEq | INe | ULt | ULe | UGt | UGe | SLt | SLe | SGt | SGe | FOrdEq | FOrdNe | FOrdLt | FOrdLe | FOrdGt | FOrdGe | FUnordEq
            | FUnordNe | FUnordLt | FUnordLe | FUnordGt | FUnordGe | LEq | LNe | LAnd | LOr
    )
}

/// The analysis: per register a class, the constant registers (never written by an op: their
/// value is materialised in whatever form a use needs), and the registers that need no blend.
pub(super) struct Types {
    cls: Vec<Cls>,
    konst: Vec<Option<u64>>,
    /// Per block, the registers whose writes there blend (`blend_sets`, widened by
    /// `refill::widen_blends`).
    pub(super) blend: Vec<Vec<u64>>,
}

impl Types {
    pub(super) fn cls(&self, r: Reg) -> Cls {
        self.cls[r as usize]
    }
    pub(super) fn konst(&self, r: Reg) -> Option<u64> {
        self.konst[r as usize]
    }
    /// Whether a write of `r` in block `b` must keep the other lanes' values.
    pub(super) fn blends(&self, b: usize, r: Reg) -> bool {
        self.blend[b][r as usize / 64] >> (r % 64) & 1 != 0
    }
}

struct Uf {
    parent: Vec<usize>,
    cls: Vec<Option<Cls>>,
    /// Constant registers take any form: they are neither constrained nor joined.
    konst: Vec<bool>,
    ok: bool,
}

impl Uf {
    fn find(&mut self, mut r: usize) -> usize {
        while self.parent[r] != r {
            self.parent[r] = self.parent[self.parent[r]];
            r = self.parent[r];
        }
        r
    }
    fn need(&mut self, r: Reg, c: Cls) {
        if self.konst[r as usize] {
            return;
        }
        let root = self.find(r as usize);
        match self.cls[root] {
            None => self.cls[root] = Some(c),
            Some(have) if have != c => self.ok = false,
            _ => {}
        }
    }
    fn join(&mut self, a: Reg, b: Reg) {
        if self.konst[a as usize] || self.konst[b as usize] {
            return;
        }
        let (ra, rb) = (self.find(a as usize), self.find(b as usize));
        if ra == rb {
            return;
        }
        self.parent[rb] = ra;
        if let Some(c) = self.cls[rb] {
            self.need(ra as Reg, c);
        }
    }
}

/// Whether `op` only computes (no memory): a run of such ops can be emitted again.
pub(super) fn pure(op: &Op) -> bool {
    matches!(op, Op::Mov { .. } | Op::Un { .. } | Op::Bin { .. } | Op::Tri { .. } | Op::BitInsert { .. } | Op::Select { .. } | Op::Index { .. } | Op::AddImm { .. })
}

/// Registers an op writes and reads (None: an op the SIMD backend does not compile).
pub(super) fn defs_uses(op: &Op) -> Option<(Vec<Reg>, Vec<Reg>)> {
    Some(match *op {
        Op::Mov { dst, src } => (vec![dst], vec![src]),
        Op::Un { dst, a, .. } => (vec![dst], vec![a]),
        Op::Bin { dst, a, b, .. } => (vec![dst], vec![a, b]),
        Op::Tri { dst, a, b, c, .. } => (vec![dst], vec![a, b, c]),
        Op::BitInsert { dst, base, insert, offset, count, .. } => (vec![dst], vec![base, insert, offset, count]),
        Op::Select { dst, cond, a, b } => (vec![dst], vec![cond, a, b]),
        Op::Index { dst, base, index, .. } => (vec![dst], vec![base, index]),
        Op::AddImm { dst, a, .. } => (vec![dst], vec![a]),
        Op::Load { dst, addr, .. } => (vec![dst], vec![addr]),
        Op::Store { addr, src, .. } => (vec![], vec![addr, src]),
        Op::Atomic { dst, addr, a, b, .. } => (vec![dst], vec![addr, a, b]),
        _ => return None,
    })
}

/// The classes of `prog`'s registers, or None when some register has no single form or the
/// program uses an op, space or terminator the SIMD backend does not compile.
pub(super) fn analyse(prog: &Program) -> Option<Types> {
    let n = prog.reg_count as usize;
    let mut written = vec![false; n];
    for blk in &prog.blocks {
        for op in &blk.ops {
            defs_uses(op)?.0.iter().for_each(|&d| written[d as usize] = true);
        }
        blk.phi_in.iter().for_each(|&(d, _)| written[d as usize] = true);
        blk.edge_moves.iter().for_each(|m| written[m.dst as usize] = true);
        if matches!(blk.term, Term::Barrier(_)) {
            return None;
        }
    }
    let mut konst = vec![None; n];
    for &(r, v) in &prog.consts {
        if !written[r as usize] {
            konst[r as usize] = Some(v);
        }
    }
    let mut uf = Uf { parent: (0..n).collect(), cls: vec![None; n], konst: konst.iter().map(Option::is_some).collect(), ok: true };
    for blk in &prog.blocks {
        for &(d, t) in &blk.phi_in {
            uf.join(d, t);
        }
        for m in &blk.edge_moves {
            uf.join(m.dst, m.src);
        }
        match blk.term {
            Term::Cond { cond, .. } => uf.need(cond, Cls::B),
            Term::Switch { sel, .. } => uf.need(sel, Cls::W32),
            _ => {}
        }
        for op in &blk.ops {
            constrain(&mut uf, op)?;
        }

    }
    if !uf.ok {
        return None;
    }
    let cls = (0..n).map(|r| {
        let root = uf.find(r);
        uf.cls[root].unwrap_or(Cls::W32)
    });
    let cls: Vec<Cls> = cls.collect();
    let blend = blend_sets(prog, n);
    Some(Types { cls, konst, blend })
}

fn constrain(uf: &mut Uf, op: &Op) -> Option<()> {
    match *op {
        Op::Mov { dst, src } => uf.join(dst, src),
        Op::Un { ty, from, dst, a, .. } => {
            uf.need(a, cls(from));
            uf.need(dst, cls(ty));
        }
        Op::Bin { op, ty, dst, a, b } => {
            uf.need(a, cls(ty));
            // Ldexp's exponent is an integer of its own width.
            if op != BinOp::Ldexp {
                uf.need(b, cls(ty));
            } else if ty != Sc::F32 {
                return None;
            } else {
                uf.need(b, Cls::W32);
            }
            uf.need(dst, if bool_result(op) { Cls::B } else { cls(ty) });
        }
        Op::Tri { ty, dst, a, b, c, .. } => {
            for r in [dst, a, b, c] {
                uf.need(r, cls(ty));
            }
        }
        Op::BitInsert { ty, dst, base, insert, offset, count } => {
            for r in [dst, base, insert] {
                uf.need(r, cls(ty));
            }
            uf.need(offset, Cls::W32);
            uf.need(count, Cls::W32);
        }
        Op::Select { dst, cond, a, b } => {
            uf.need(cond, Cls::B);
            uf.join(dst, a);
            uf.join(dst, b);
        }
        Op::Index { dst, base, index, index_ty, .. } => {
            uf.need(dst, Cls::W64);
            uf.need(base, Cls::W64);
            uf.need(index, cls(index_ty));
        }
        Op::AddImm { dst, a, .. } => {
            uf.need(dst, Cls::W64);
            uf.need(a, Cls::W64);
        }
        Op::Load { ty, space, dst, addr } => {
            super::gen::space_ok(space)?;
            uf.need(dst, cls(ty));
            uf.need(addr, Cls::W64);
        }
        Op::Store { ty, space, addr, src } => {
            super::gen::space_ok(space)?;
            uf.need(src, cls(ty));
            uf.need(addr, Cls::W64);
        }
        Op::Atomic { ty, space, dst, addr, a, b, .. } => {
            super::gen::space_ok(space)?;
            if matches!(space, Space::Lane) {
                return None;
            }
            for r in [dst, a, b] {
                uf.need(r, cls(ty));
            }
            uf.need(addr, Cls::W64);
        }
        _ => return None,
    }
    Some(())
}

/// Per block, the registers that a write there must blend: those live into some later block
/// (where the lanes outside the mask wait: every running lane's cursor is at or past the
/// running block). A register no later block reads keeps nothing worth keeping.
fn blend_sets(prog: &Program, n: usize) -> Vec<Vec<u64>> {
    let words = n.div_ceil(64);
    let nb = prog.blocks.len();
    let live_in = super::refill::live_in(prog);
    let mut after = vec![vec![0u64; words]; nb];
    for b in (0..nb.saturating_sub(1)).rev() {
        let next: Vec<u64> = (0..words).map(|w| after[b + 1][w] | live_in[b + 1][w]).collect();
        after[b] = next;
    }
    after
}

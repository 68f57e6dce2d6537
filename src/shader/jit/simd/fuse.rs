//! A test against zero read only by a select (`(x & 1) != 0 ? a : b`, glslang's form of a
//! branch on a bit) is no op of its own: the select compares for equality and swaps its
//! operands, sparing the negation a vector not-equal costs.
use super::super::super::ir::{BinOp, Op, Program, Reg, Sc, Term};
use super::types::{defs_uses, Cls, Types};

/// Per register, the register a fused not-equal-zero test reads (`negated[cond]` for the
/// select that reads `cond`); per block and op, whether the op is such a test (not emitted).
pub(super) struct Fused {
    pub negated: Vec<Option<Reg>>,
    pub skip: Vec<Vec<bool>>,
}

pub(super) fn fuse(prog: &Program, types: &Types) -> Fused {
    let n = prog.reg_count as usize;
    let mut reads = vec![0u32; n];
    for blk in &prog.blocks {
        blk.ops.iter().filter_map(defs_uses).flat_map(|d| d.1).for_each(|r| reads[r as usize] += 1);
        blk.phi_in.iter().for_each(|&(_, t)| reads[t as usize] += 1);
        blk.edge_moves.iter().for_each(|m| reads[m.src as usize] += 1);
        if let Term::Cond { cond: r, .. } | Term::Switch { sel: r, .. } = blk.term {
            reads[r as usize] += 1;
        }
    }
    let mut fused = Fused { negated: vec![None; n], skip: prog.blocks.iter().map(|b| vec![false; b.ops.len()]).collect() };
    for (i, blk) in prog.blocks.iter().enumerate() {
        for (k, op) in blk.ops.iter().enumerate() {
            let Op::Bin { op: BinOp::INe, ty: Sc::I32, dst, a, b } = *op else { continue };
            let t = match (types.konst(a), types.konst(b)) {
                (_, Some(0)) => a,
                (Some(0), _) => b,
                _ => continue,
            };
            let vector = |r: Reg| types.konst(r).is_none() && types.cls(r) == Cls::W32;
            if reads[dst as usize] != 1 || !vector(t) || types.cls(dst) != Cls::B {
                continue;
            }
            // The one reader: a select of this block, before anything writes `t` or `dst` again.
            for later in &blk.ops[k + 1..] {
                if let Op::Select { dst: sd, cond, a, b } = *later {
                    if cond == dst && a != dst && b != dst && types.cls(sd) != Cls::W64 && types.cls(sd) != Cls::B {
                        fused.negated[dst as usize] = Some(t);
                        fused.skip[i][k] = true;
                        break;
                    }
                }
                if defs_uses(later).is_none_or(|d| d.0.iter().any(|&w| w == t || w == dst) || d.1.contains(&dst)) {
                    break;
                }
            }
        }
    }
    fused
}

//! ALU, composite, GLSL.std.450, atomic and subgroup instructions → IR ops. Vector ops become
//! one scalar op per component; composite ops only rearrange register lists.
use rspirv::dr::Instruction;
use spirv::Op;

use super::ir::{AtomicOp, BallotOp, BinOp, Op as IrOp, Reg, Sc, SgOp, TriOp, UnOp};
use super::lower::{Lowerer, Val};
use super::parse::{id_op, lit, Type};
use super::ShaderError;

/// The IR op family of a SPIR-V ALU opcode (shared with the spec-constant folder).
#[derive(Clone, Copy, Debug)]
pub enum Alu {
    Bin(BinOp),
    Un(UnOp),
}

pub fn alu_of(op: Op) -> Option<Alu> {
    use Alu::*;
    Some(match op {
        Op::IAdd => Bin(BinOp::IAdd),
        Op::ISub => Bin(BinOp::ISub),
        Op::IMul => Bin(BinOp::IMul),
        Op::UDiv => Bin(BinOp::UDiv),
        Op::SDiv => Bin(BinOp::SDiv),
        Op::UMod => Bin(BinOp::UMod),
        Op::SRem => Bin(BinOp::SRem),
        Op::SMod => Bin(BinOp::SMod),
        Op::ShiftLeftLogical => Bin(BinOp::Shl),
        Op::ShiftRightLogical => Bin(BinOp::ShrL),
        Op::ShiftRightArithmetic => Bin(BinOp::ShrA),
        Op::BitwiseAnd => Bin(BinOp::And),
        Op::BitwiseOr => Bin(BinOp::Or),
        Op::BitwiseXor => Bin(BinOp::Xor),
        Op::IEqual => Bin(BinOp::IEq),
        Op::INotEqual => Bin(BinOp::INe),
        Op::ULessThan => Bin(BinOp::ULt),
        Op::ULessThanEqual => Bin(BinOp::ULe),
        Op::UGreaterThan => Bin(BinOp::UGt),
        Op::UGreaterThanEqual => Bin(BinOp::UGe),
        Op::SLessThan => Bin(BinOp::SLt),
        Op::SLessThanEqual => Bin(BinOp::SLe),
        Op::SGreaterThan => Bin(BinOp::SGt),
        Op::SGreaterThanEqual => Bin(BinOp::SGe),
        Op::FAdd => Bin(BinOp::FAdd),
        Op::FSub => Bin(BinOp::FSub),
        Op::FMul => Bin(BinOp::FMul),
        Op::FDiv => Bin(BinOp::FDiv),
        Op::FRem => Bin(BinOp::FRem),
        Op::FMod => Bin(BinOp::FMod),
        Op::FOrdEqual => Bin(BinOp::FOrdEq),
        Op::FOrdNotEqual => Bin(BinOp::FOrdNe),
        Op::FOrdLessThan => Bin(BinOp::FOrdLt),
        Op::FOrdLessThanEqual => Bin(BinOp::FOrdLe),
        Op::FOrdGreaterThan => Bin(BinOp::FOrdGt),
        Op::FOrdGreaterThanEqual => Bin(BinOp::FOrdGe),
        Op::FUnordEqual => Bin(BinOp::FUnordEq),
        Op::FUnordNotEqual => Bin(BinOp::FUnordNe),
        Op::FUnordLessThan => Bin(BinOp::FUnordLt),
        Op::FUnordLessThanEqual => Bin(BinOp::FUnordLe),
        Op::FUnordGreaterThan => Bin(BinOp::FUnordGt),
        Op::FUnordGreaterThanEqual => Bin(BinOp::FUnordGe),
        Op::LogicalEqual => Bin(BinOp::LEq),
        Op::LogicalNotEqual => Bin(BinOp::LNe),
        Op::LogicalAnd => Bin(BinOp::LAnd),
        Op::LogicalOr => Bin(BinOp::LOr),
        Op::SNegate => Un(UnOp::SNeg),
        Op::FNegate => Un(UnOp::FNeg),
        Op::Not => Un(UnOp::Not),
        Op::LogicalNot => Un(UnOp::LNot),
        Op::Bitcast => Un(UnOp::Bitcast),
        Op::UConvert => Un(UnOp::UConvert),
        Op::SConvert => Un(UnOp::SConvert),
        Op::FConvert => Un(UnOp::FConvert),
        Op::ConvertFToU => Un(UnOp::ConvertFToU),
        Op::ConvertFToS => Un(UnOp::ConvertFToS),
        Op::ConvertUToF => Un(UnOp::ConvertUToF),
        Op::ConvertSToF => Un(UnOp::ConvertSToF),
        Op::IsNan => Un(UnOp::IsNan),
        Op::IsInf => Un(UnOp::IsInf),
        Op::BitCount => Un(UnOp::BitCount),
        Op::BitReverse => Un(UnOp::BitReverse),
        _ => return None,
    })
}

/// GLSL.std.450 instruction → one scalar op per component (the composite ones are in
/// `glsl_composite`).
fn glsl_alu(n: u32) -> Option<GlslOp> {
    use GlslOp::*;
    Some(match n {
        1 => U(UnOp::Round), 2 => U(UnOp::RoundEven), 3 => U(UnOp::Trunc), 4 => U(UnOp::FAbs),
        5 => U(UnOp::SAbs), 6 => U(UnOp::FSign), 7 => U(UnOp::SSign), 8 => U(UnOp::Floor),
        9 => U(UnOp::Ceil), 10 => U(UnOp::Fract), 11 => U(UnOp::Radians), 12 => U(UnOp::Degrees),
        13 => U(UnOp::Sin), 14 => U(UnOp::Cos), 15 => U(UnOp::Tan), 16 => U(UnOp::Asin),
        17 => U(UnOp::Acos), 18 => U(UnOp::Atan), 19 => U(UnOp::Sinh), 20 => U(UnOp::Cosh),
        21 => U(UnOp::Tanh), 22 => U(UnOp::Asinh), 23 => U(UnOp::Acosh), 24 => U(UnOp::Atanh),
        25 => B(BinOp::Atan2), 26 => B(BinOp::Pow), 27 => U(UnOp::Exp), 28 => U(UnOp::Log),
        29 => U(UnOp::Exp2), 30 => U(UnOp::Log2), 31 => U(UnOp::Sqrt), 32 => U(UnOp::InverseSqrt),
        37 => B(BinOp::FMin), 38 => B(BinOp::UMin), 39 => B(BinOp::SMin), 40 => B(BinOp::FMax),
        41 => B(BinOp::UMax), 42 => B(BinOp::SMax), 43 => T(TriOp::FClamp), 44 => T(TriOp::UClamp),
        45 => T(TriOp::SClamp), 46 => T(TriOp::FMix), 48 => B(BinOp::Step), 49 => T(TriOp::SmoothStep),
        50 => T(TriOp::Fma), 53 => B(BinOp::Ldexp), 73 => U(UnOp::FindILsb), 74 => U(UnOp::FindSMsb),
        75 => U(UnOp::FindUMsb), 79 => B(BinOp::NMin), 80 => B(BinOp::NMax), 81 => T(TriOp::NClamp),
        _ => return None,
    })
}

#[derive(Clone, Copy)]
enum GlslOp {
    U(UnOp),
    B(BinOp),
    T(TriOp),
}

impl Lowerer<'_> {
    fn sc_of(&self, id: u32) -> Result<Vec<Sc>, ShaderError> {
        let ty = self.type_of(id).ok_or_else(|| self.m.malformed(id, "value of unknown type"))?;
        self.l.components(ty)
    }

    /// The scalar type of `id`'s first component (the element type of a vector or matrix).
    fn sc1(&self, inst: &Instruction, id: u32) -> Result<Sc, ShaderError> {
        self.sc_of(id)?.first().copied().ok_or_else(|| shape_error(self, inst, "an operand without components"))
    }

    /// Rejects `inst` unless every operand length in `lens` is `n` and `n` is not 0: lowering
    /// indexes operands component by component, and a module that passes the parse checks may
    /// still give mismatched ones.
    fn same_counts(&self, inst: &Instruction, n: usize, lens: &[usize]) -> Result<(), ShaderError> {
        if n == 0 || lens.iter().any(|&l| l != n) {
            return Err(shape_error(self, inst, "operand and result component counts differ"));
        }
        Ok(())
    }

    /// Registers of `id`, repeated to `n` components when it is a scalar (VectorTimesScalar,
    /// a scalar Select condition).
    fn regs_splat(&mut self, id: u32, n: usize) -> Result<Vec<Reg>, ShaderError> {
        let r = self.regs(id)?;
        Ok(if r.len() == 1 && n > 1 { vec![r[0]; n] } else { r })
    }

    pub fn bin(&mut self, op: BinOp, ty: Sc, a: Reg, b: Reg) -> Reg {
        let dst = self.reg();
        self.emit(IrOp::Bin { op, ty, dst, a, b });
        dst
    }

    fn un(&mut self, op: UnOp, ty: Sc, from: Sc, a: Reg) -> Reg {
        let dst = self.reg();
        self.emit(IrOp::Un { op, ty, from, dst, a });
        dst
    }

    fn select(&mut self, cond: Reg, a: Reg, b: Reg) -> Reg {
        let dst = self.reg();
        self.emit(IrOp::Select { dst, cond, a, b });
        dst
    }

    /// Σ a[i]·b[i] in order (OpDot, matrix products); `inst` is rejected when the sizes differ.
    fn dot(&mut self, inst: &Instruction, ty: Sc, a: &[Reg], b: &[Reg]) -> Result<Reg, ShaderError> {
        self.same_counts(inst, a.len(), &[b.len()])?;
        let mut acc = self.bin(BinOp::FMul, ty, a[0], b[0]);
        for i in 1..a.len() {
            let p = self.bin(BinOp::FMul, ty, a[i], b[i]);
            acc = self.bin(BinOp::FAdd, ty, acc, p);
        }
        Ok(acc)
    }

    pub fn lower_op(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let rty = inst.result_type.unwrap_or(0);
        let op = inst.class.opcode;
        if let Some(kind) = alu_of(op) {
            let out = self.l.components(rty)?;
            let a_id = id_op(inst, 0)?;
            let a_sc = self.sc_of(a_id)?;
            let a = self.regs(a_id)?;
            let b = if inst.operands.len() > 1 { Some(self.regs_splat(id_op(inst, 1)?, a.len())?) } else { None };
            if a.len() != out.len() || a_sc.len() != a.len() || b.as_ref().is_some_and(|b| b.len() != a.len()) {
                return Err(self.m.malformed(id, "operand and result component counts differ"));
            }
            let mut dst = Vec::with_capacity(out.len());
            for i in 0..out.len() {
                dst.push(match (kind, &b) {
                    (Alu::Bin(bop), Some(b)) => self.bin(bop, a_sc[i], a[i], b[i]),
                    (Alu::Un(uop), _) => self.un(uop, out[i], a_sc[i], a[i]),
                    _ => return Err(self.m.malformed(id, "missing operand")),
                });
            }
            self.define(id, Val::Regs(dst));
            return Ok(());
        }
        self.lower_composite(inst)
    }

    /// Composite construction and access: register lists rearranged, plus selects.
    fn lower_composite(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let rty = inst.result_type.unwrap_or(0);
        let op = inst.class.opcode;
        let v = match op {
            Op::CopyObject | Op::CopyLogical => self.val(id_op(inst, 0)?)?,
            Op::Undef => Val::Regs({
                let n = self.l.count(rty)?;
                let z = self.konst(0);
                vec![z; n]
            }),
            Op::CompositeConstruct => {
                let mut r = Vec::new();
                for k in 0..inst.operands.len() {
                    r.extend(self.regs(id_op(inst, k)?)?);
                }
                Val::Regs(r)
            }
            Op::CompositeExtract => {
                let src = id_op(inst, 0)?;
                let idx: Vec<u32> = (1..inst.operands.len()).map(|k| lit(inst, k)).collect::<Result<_, _>>()?;
                let ty = self.type_of(src).unwrap_or(0);
                let (start, n, _) = self.l.sub_range(ty, &idx)?;
                let regs = self.regs(src)?;
                Val::Regs(regs.get(start..start + n).ok_or_else(|| self.m.malformed(id, "extract outside the composite"))?.to_vec())
            }
            Op::CompositeInsert => {
                let obj = self.regs(id_op(inst, 0)?)?;
                let mut r = self.regs(id_op(inst, 1)?)?;
                let idx: Vec<u32> = (2..inst.operands.len()).map(|k| lit(inst, k)).collect::<Result<_, _>>()?;
                let (start, n, _) = self.l.sub_range(rty, &idx)?;
                if obj.len() != n {
                    return Err(self.m.malformed(id, "inserted object of the wrong size"));
                }
                r.get_mut(start..start + n).ok_or_else(|| self.m.malformed(id, "insert outside the composite"))?.copy_from_slice(&obj);
                Val::Regs(r)
            }
            Op::VectorShuffle => {
                let mut joined = self.regs(id_op(inst, 0)?)?;
                joined.extend(self.regs(id_op(inst, 1)?)?);
                let zero = self.konst(0);
                let r = (2..inst.operands.len())
                    .map(|k| Ok(joined.get(lit(inst, k)? as usize).copied().unwrap_or(zero)))
                    .collect::<Result<_, ShaderError>>()?;
                Val::Regs(r)
            }
            Op::VectorExtractDynamic | Op::VectorInsertDynamic => Val::Regs(self.dynamic_component(inst)?),
            Op::Select => {
                let a = self.regs(id_op(inst, 1)?)?;
                let b = self.regs(id_op(inst, 2)?)?;
                let c = self.regs_splat(id_op(inst, 0)?, a.len())?;
                self.same_counts(inst, a.len(), &[b.len(), c.len()])?;
                Val::Regs((0..a.len()).map(|i| self.select(c[i], a[i], b[i])).collect())
            }
            Op::Transpose => {
                let src = id_op(inst, 0)?;
                let m = self.regs(src)?;
                let cols = match self.type_of(src).map(|t| self.m.ty(t)).transpose()? {
                    Some(Type::Matrix { n, .. }) => *n as usize,
                    _ => return Err(self.m.malformed(src, "transpose of a non-matrix")),
                };
                if cols == 0 || !m.len().is_multiple_of(cols) {
                    return Err(shape_error(self, inst, "matrix of no columns or uneven columns"));
                }
                let rows = m.len() / cols;
                Val::Regs((0..rows * cols).map(|k| m[(k % cols) * rows + k / cols]).collect())
            }
            Op::Any | Op::All => {
                let v = self.regs(id_op(inst, 0)?)?;
                let bop = if op == Op::Any { BinOp::LOr } else { BinOp::LAnd };
                let Some(&first) = v.first() else { return Err(shape_error(self, inst, "an empty vector")) };
                let mut acc = first;
                for &c in &v[1..] {
                    acc = self.bin(bop, Sc::Bool, acc, c);
                }
                Val::Regs(vec![acc])
            }
            _ => return self.lower_op2(inst),
        };
        self.define(id, v);
        Ok(())
    }

    /// OpVectorExtractDynamic / OpVectorInsertDynamic: a select per component, since registers
    /// cannot be indexed by a run-time value.
    fn dynamic_component(&mut self, inst: &Instruction) -> Result<Vec<Reg>, ShaderError> {
        let extract = inst.class.opcode == Op::VectorExtractDynamic;
        let v = self.regs(id_op(inst, 0)?)?;
        let idx_id = id_op(inst, if extract { 1 } else { 2 })?;
        let idx_sc = self.sc1(inst, idx_id)?;
        let idx = self.reg1(idx_id)?;
        let obj = if extract { None } else { Some(self.reg1(id_op(inst, 1)?)?) };
        let mut acc = v.first().copied().ok_or_else(|| self.m.malformed(idx_id, "empty vector"))?;
        let mut out = Vec::with_capacity(v.len());
        for (k, &c) in v.iter().enumerate() {
            let kr = self.konst(k as u64);
            let eq = self.bin(BinOp::IEq, idx_sc, idx, kr);
            match obj {
                None if k > 0 => acc = self.select(eq, c, acc),
                None => {}
                Some(o) => out.push(self.select(eq, o, c)),
            }
        }
        Ok(if extract { vec![acc] } else { out })
    }

    /// Arithmetic that does not map one-to-one onto components.
    fn lower_op2(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let rty = inst.result_type.unwrap_or(0);
        let op = inst.class.opcode;
        let v = match op {
            Op::Dot => {
                let (a, b) = (id_op(inst, 0)?, id_op(inst, 1)?);
                let ty = self.sc1(inst, a)?;
                let (a, b) = (self.regs(a)?, self.regs(b)?);
                if a.is_empty() || a.len() != b.len() {
                    return Err(self.m.malformed(id, "OpDot of vectors of different sizes"));
                }
                vec![self.dot(inst, ty, &a, &b)?]
            }
            Op::VectorTimesScalar | Op::MatrixTimesScalar => {
                let a = self.regs(id_op(inst, 0)?)?;
                let s = self.reg1(id_op(inst, 1)?)?;
                let ty = self.sc1(inst, id_op(inst, 1)?)?;
                a.iter().map(|&c| self.bin(BinOp::FMul, ty, c, s)).collect()
            }
            Op::MatrixTimesVector | Op::VectorTimesMatrix | Op::MatrixTimesMatrix => self.matrix_product(inst)?,
            Op::IAddCarry | Op::ISubBorrow | Op::UMulExtended | Op::SMulExtended => {
                let (a_id, b_id) = (id_op(inst, 0)?, id_op(inst, 1)?);
                let sc = self.sc_of(a_id)?;
                let (a, b) = (self.regs(a_id)?, self.regs(b_id)?);
                self.same_counts(inst, a.len(), &[b.len(), sc.len()])?;
                // The result is a struct of two members of the operands' type.
                self.same_counts(inst, 2 * a.len(), &[self.l.components(rty)?.len()])?;
                let (lo_op, hi_op) = match op {
                    Op::IAddCarry => (BinOp::IAdd, BinOp::AddCarry),
                    Op::ISubBorrow => (BinOp::ISub, BinOp::SubBorrow),
                    Op::UMulExtended => (BinOp::IMul, BinOp::UMulHi),
                    _ => (BinOp::IMul, BinOp::SMulHi),
                };
                let lo: Vec<Reg> = (0..a.len()).map(|i| self.bin(lo_op, sc[i], a[i], b[i])).collect();
                let hi: Vec<Reg> = (0..a.len()).map(|i| self.bin(hi_op, sc[i], a[i], b[i])).collect();
                lo.into_iter().chain(hi).collect()
            }
            Op::BitFieldInsert => {
                let sc = self.l.components(rty)?;
                let base = self.regs(id_op(inst, 0)?)?;
                let ins = self.regs(id_op(inst, 1)?)?;
                let (offset, count) = (self.reg1(id_op(inst, 2)?)?, self.reg1(id_op(inst, 3)?)?);
                self.same_counts(inst, base.len(), &[ins.len(), sc.len()])?;
                let mut out = Vec::new();
                for i in 0..base.len() {
                    let dst = self.reg();
                    self.emit(IrOp::BitInsert { ty: sc[i], dst, base: base[i], insert: ins[i], offset, count });
                    out.push(dst);
                }
                out
            }
            Op::BitFieldSExtract | Op::BitFieldUExtract => {
                let sc = self.l.components(rty)?;
                let base = self.regs(id_op(inst, 0)?)?;
                let (offset, count) = (self.reg1(id_op(inst, 1)?)?, self.reg1(id_op(inst, 2)?)?);
                self.same_counts(inst, base.len(), &[sc.len()])?;
                let top = if op == Op::BitFieldSExtract { TriOp::BitFieldSExtract } else { TriOp::BitFieldUExtract };
                let mut out = Vec::new();
                for i in 0..base.len() {
                    let dst = self.reg();
                    self.emit(IrOp::Tri { op: top, ty: sc[i], dst, a: base[i], b: offset, c: count });
                    out.push(dst);
                }
                out
            }
            Op::ExtInst => self.glsl(inst)?,
            _ => return self.lower_sync(inst),
        };
        self.define(id, Val::Regs(v));
        Ok(())
    }

    fn matrix_product(&mut self, inst: &Instruction) -> Result<Vec<Reg>, ShaderError> {
        let (a_id, b_id) = (id_op(inst, 0)?, id_op(inst, 1)?);
        let ty = self.sc1(inst, a_id)?;
        let (a, b) = (self.regs(a_id)?, self.regs(b_id)?);
        // Columns of a matrix operand (1 for a vector), which must divide its components.
        let cols = |lw: &Self, id: u32, len: usize| -> Result<usize, ShaderError> {
            let c = match lw.type_of(id).map(|t| lw.m.ty(t)).transpose()? {
                Some(Type::Matrix { n, .. }) => *n as usize,
                _ => 1,
            };
            if c == 0 || len == 0 || !len.is_multiple_of(c) {
                return Err(shape_error(lw, inst, "matrix of no columns or uneven columns"));
            }
            Ok(c)
        };
        Ok(match inst.class.opcode {
            // M (c columns of r rows) × v (c) → r
            Op::MatrixTimesVector => {
                let c = cols(self, a_id, a.len())?;
                let r = a.len() / c;
                (0..r).map(|i| {
                    let row: Vec<Reg> = (0..c).map(|j| a[j * r + i]).collect();
                    self.dot(inst, ty, &row, &b)
                }).collect::<Result<_, _>>()?
            }
            // v (r) × M (c columns of r rows) → c
            Op::VectorTimesMatrix => {
                let c = cols(self, b_id, b.len())?;
                let r = b.len() / c;
                (0..c).map(|j| self.dot(inst, ty, &a, &b[j * r..(j + 1) * r])).collect::<Result<_, _>>()?
            }
            _ => {
                let (ac, bc) = (cols(self, a_id, a.len())?, cols(self, b_id, b.len())?);
                self.same_counts(inst, ac * bc, &[b.len()])?;
                let r = a.len() / ac;
                let mut out = Vec::new();
                for j in 0..bc {
                    for i in 0..r {
                        let row: Vec<Reg> = (0..ac).map(|k| a[k * r + i]).collect();
                        out.push(self.dot(inst, ty, &row, &b[j * ac..(j + 1) * ac])?);
                    }
                }
                out
            }
        })
    }

    fn glsl(&mut self, inst: &Instruction) -> Result<Vec<Reg>, ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let n = lit(inst, 1)?;
        let args: Vec<u32> = (2..inst.operands.len()).map(|k| id_op(inst, k)).collect::<Result<_, _>>()?;
        let out = self.l.components(inst.result_type.unwrap_or(0))?;
        let a_sc = self.sc_of(*args.first().ok_or_else(|| self.m.malformed(id, "no operands"))?)?;
        let ty = self.sc1(inst, args[0])?;
        let regs: Vec<Vec<Reg>> = args.iter().map(|&a| self.regs_splat(a, a_sc.len())).collect::<Result<_, _>>()?;
        let arity = match (glsl_alu(n), n) {
            (Some(GlslOp::U(_)), _) | (None, 66 | 69) => 1,
            (Some(GlslOp::B(_)), _) | (None, 67 | 68 | 71) => 2,
            _ => 3,
        };
        let width = if matches!(n, 66 | 67) { a_sc.len() } else { out.len() };
        if regs.len() < arity || regs.iter().any(|r| r.len() != a_sc.len()) || a_sc.len() != width || (n == 68 && width != 3) {
            return Err(self.m.malformed(id, "GLSL.std.450 operand count or shape"));
        }
        if let Some(g) = glsl_alu(n) {
            let mut dst = Vec::new();
            for i in 0..out.len() {
                let d = self.reg();
                self.emit(match g {
                    GlslOp::U(op) => IrOp::Un { op, ty: out[i], from: a_sc[i], dst: d, a: regs[0][i] },
                    GlslOp::B(op) => IrOp::Bin { op, ty: a_sc[i], dst: d, a: regs[0][i], b: regs[1][i] },
                    GlslOp::T(op) => IrOp::Tri { op, ty: a_sc[i], dst: d, a: regs[0][i], b: regs[1][i], c: regs[2][i] },
                });
                dst.push(d);
            }
            return Ok(dst);
        }
        let length = |lw: &mut Self, v: &[Reg]| -> Result<Reg, ShaderError> {
            let d = lw.dot(inst, ty, v, v)?;
            Ok(lw.un(UnOp::Sqrt, ty, ty, d))
        };
        Ok(match n {
            66 => vec![length(self, &regs[0])?],
            67 => {
                let d: Vec<Reg> = (0..regs[0].len()).map(|i| self.bin(BinOp::FSub, ty, regs[0][i], regs[1][i])).collect();
                vec![length(self, &d)?]
            }
            68 => {
                let (a, b) = (&regs[0], &regs[1]);
                let mut c = Vec::new();
                for (i, j) in [(1, 2), (2, 0), (0, 1)] {
                    let p = self.bin(BinOp::FMul, ty, a[i], b[j]);
                    let q = self.bin(BinOp::FMul, ty, a[j], b[i]);
                    c.push(self.bin(BinOp::FSub, ty, p, q));
                }
                c
            }
            69 => {
                let len = length(self, &regs[0])?;
                regs[0].clone().into_iter().map(|c| self.bin(BinOp::FDiv, ty, c, len)).collect()
            }
            70 => {
                // faceforward(N, I, Nref) = dot(Nref, I) < 0 ? N : -N
                let d = self.dot(inst, ty, &regs[2], &regs[1])?;
                let zero = self.konst(0);
                let neg = self.bin(BinOp::FOrdLt, ty, d, zero);
                regs[0].clone().into_iter().map(|c| {
                    let m = self.un(UnOp::FNeg, ty, ty, c);
                    self.select(neg, c, m)
                }).collect()
            }
            71 => {
                // reflect(I, N) = I - 2·dot(N, I)·N
                let d = self.dot(inst, ty, &regs[1], &regs[0])?;
                let two = self.konst(super::alu::from_f(ty, 2.0));
                let d2 = self.bin(BinOp::FMul, ty, d, two);
                (0..regs[0].len()).map(|i| {
                    let t = self.bin(BinOp::FMul, ty, d2, regs[1][i]);
                    self.bin(BinOp::FSub, ty, regs[0][i], t)
                }).collect()
            }
            _ => return Err(ShaderError::UnsupportedExtInst { set: "GLSL.std.450".into(), number: n, offset: self.m.offset_of(id) }),
        })
    }

    /// Atomics and subgroup operations.
    fn lower_sync(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let rty = inst.result_type.unwrap_or(0);
        let op = inst.class.opcode;
        let atomic = match op {
            Op::AtomicExchange => Some(AtomicOp::Exchange),
            Op::AtomicCompareExchange => Some(AtomicOp::CompareExchange),
            Op::AtomicIAdd | Op::AtomicIIncrement => Some(AtomicOp::IAdd),
            Op::AtomicISub | Op::AtomicIDecrement => Some(AtomicOp::ISub),
            Op::AtomicSMin => Some(AtomicOp::SMin),
            Op::AtomicUMin => Some(AtomicOp::UMin),
            Op::AtomicSMax => Some(AtomicOp::SMax),
            Op::AtomicUMax => Some(AtomicOp::UMax),
            Op::AtomicAnd => Some(AtomicOp::And),
            Op::AtomicOr => Some(AtomicOp::Or),
            Op::AtomicXor => Some(AtomicOp::Xor),
            _ => None,
        };
        match op {
            Op::MemoryBarrier => return Ok(()), // one workgroup runs on one thread, in order
            Op::AtomicLoad => {
                let pid = id_op(inst, 0)?;
                let p = self.ptr(pid, self.type_of(pid))?;
                let v = self.load(&p)?;
                self.define(id, Val::Regs(v));
                return Ok(());
            }
            Op::AtomicStore => {
                let pid = id_op(inst, 0)?;
                let p = self.ptr(pid, self.type_of(pid))?;
                let v = self.regs(id_op(inst, 3)?)?;
                return self.store(&p, &v);
            }
            _ => {}
        }
        if let Some(aop) = atomic {
            let pid = id_op(inst, 0)?;
            let p = self.ptr(pid, self.type_of(pid))?;
            let ty = self.l.scalar(rty)?;
            let (a, b) = match op {
                Op::AtomicIIncrement | Op::AtomicIDecrement => (self.konst(1), 0),
                Op::AtomicCompareExchange => (self.reg1(id_op(inst, 4)?)?, self.reg1(id_op(inst, 5)?)?),
                _ => (self.reg1(id_op(inst, 3)?)?, 0),
            };
            let dst = self.reg();
            self.emit(IrOp::Atomic { op: aop, ty, space: p.space, dst, addr: p.addr, a, b });
            self.define(id, Val::Regs(vec![dst]));
            return Ok(());
        }
        self.lower_subgroup(inst)
    }

    fn lower_subgroup(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let rty = inst.result_type.unwrap_or(0);
        let op = inst.class.opcode;
        let scope = self.consts.value(id_op(inst, 0)?).and_then(|v| v.first().copied());
        if scope != Some(3) {
            return Err(self.err(id, format!("Op{} outside subgroup scope", inst.class.opname)));
        }
        let out = self.l.components(rty)?;
        let operand = |k: usize| id_op(inst, k);
        let simple = |o: SgOp| Some(o);
        let sg = match op {
            Op::GroupNonUniformElect => simple(SgOp::Elect),
            Op::GroupNonUniformAll => simple(SgOp::All),
            Op::GroupNonUniformAny => simple(SgOp::Any),
            Op::GroupNonUniformBroadcast => simple(SgOp::Broadcast),
            Op::GroupNonUniformBroadcastFirst => simple(SgOp::BroadcastFirst),
            Op::GroupNonUniformShuffle => simple(SgOp::Shuffle),
            Op::GroupNonUniformShuffleXor => simple(SgOp::ShuffleXor),
            Op::GroupNonUniformShuffleUp => simple(SgOp::ShuffleUp),
            Op::GroupNonUniformShuffleDown => simple(SgOp::ShuffleDown),
            _ => None,
        };
        let v: Vec<Reg> = if let Some(sg) = sg {
            let a = if inst.operands.len() > 1 { self.regs(operand(1)?)? } else { vec![0; out.len()] };
            let b = if inst.operands.len() > 2 { self.reg1(operand(2)?)? } else { 0 };
            self.same_counts(inst, out.len(), &[a.len()])?;
            (0..out.len())
                .map(|i| {
                    let dst = self.reg();
                    self.emit(IrOp::Subgroup { op: sg, ty: out[i], dst, a: a[i], b });
                    dst
                })
                .collect()
        } else {
            match op {
                Op::GroupNonUniformAllEqual => {
                    let a_id = operand(1)?;
                    let sc = self.sc_of(a_id)?;
                    let a = self.regs(a_id)?;
                    self.same_counts(inst, a.len(), &[sc.len()])?;
                    let mut acc = self.konst(1);
                    for i in 0..a.len() {
                        let dst = self.reg();
                        self.emit(IrOp::Subgroup { op: SgOp::AllEqual, ty: sc[i], dst, a: a[i], b: 0 });
                        acc = self.bin(BinOp::LAnd, Sc::Bool, acc, dst);
                    }
                    vec![acc]
                }
                Op::GroupNonUniformBallot => {
                    let a = self.reg1(operand(1)?)?;
                    let dst = [self.reg(), self.reg(), self.reg(), self.reg()];
                    self.emit(IrOp::Ballot { dst, a });
                    dst.to_vec()
                }
                Op::GroupNonUniformInverseBallot
                | Op::GroupNonUniformBallotBitExtract
                | Op::GroupNonUniformBallotFindLSB
                | Op::GroupNonUniformBallotFindMSB
                | Op::GroupNonUniformBallotBitCount => self.ballot_op(inst)?,
                _ => return self.lower_group_arith(inst),
            }
        };
        self.define(id, Val::Regs(v));
        Ok(())
    }

    fn ballot_op(&mut self, inst: &Instruction) -> Result<Vec<Reg>, ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let (bop, ballot_k, b_k) = match inst.class.opcode {
            Op::GroupNonUniformInverseBallot => (BallotOp::Inverse, 1, None),
            Op::GroupNonUniformBallotBitExtract => (BallotOp::BitExtract, 1, Some(2)),
            Op::GroupNonUniformBallotFindLSB => (BallotOp::FindLsb, 1, None),
            Op::GroupNonUniformBallotFindMSB => (BallotOp::FindMsb, 1, None),
            _ => {
                let bop = match inst.operands.get(1) {
                    Some(rspirv::dr::Operand::GroupOperation(spirv::GroupOperation::Reduce)) => BallotOp::BitCountReduce,
                    Some(rspirv::dr::Operand::GroupOperation(spirv::GroupOperation::InclusiveScan)) => BallotOp::BitCountInclusive,
                    Some(rspirv::dr::Operand::GroupOperation(spirv::GroupOperation::ExclusiveScan)) => BallotOp::BitCountExclusive,
                    _ => return Err(self.err(id, "ballot bit count group operation")),
                };
                (bop, 2, None)
            }
        };
        let v = self.regs(id_op(inst, ballot_k)?)?;
        if v.len() != 4 {
            return Err(self.m.malformed(id, "ballot is not a uvec4"));
        }
        let b = match b_k {
            Some(k) => self.reg1(id_op(inst, k)?)?,
            None => 0,
        };
        let dst = self.reg();
        self.emit(IrOp::BallotOp { op: bop, dst, ballot: [v[0], v[1], v[2], v[3]], b });
        Ok(vec![dst])
    }

    fn lower_group_arith(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let op = inst.class.opcode;
        let bop = match op {
            Op::GroupNonUniformIAdd => BinOp::IAdd,
            Op::GroupNonUniformFAdd => BinOp::FAdd,
            Op::GroupNonUniformIMul => BinOp::IMul,
            Op::GroupNonUniformFMul => BinOp::FMul,
            Op::GroupNonUniformSMin => BinOp::SMin,
            Op::GroupNonUniformUMin => BinOp::UMin,
            Op::GroupNonUniformFMin => BinOp::FMin,
            Op::GroupNonUniformSMax => BinOp::SMax,
            Op::GroupNonUniformUMax => BinOp::UMax,
            Op::GroupNonUniformFMax => BinOp::FMax,
            Op::GroupNonUniformBitwiseAnd | Op::GroupNonUniformLogicalAnd => BinOp::And,
            Op::GroupNonUniformBitwiseOr | Op::GroupNonUniformLogicalOr => BinOp::Or,
            Op::GroupNonUniformBitwiseXor | Op::GroupNonUniformLogicalXor => BinOp::Xor,
            _ => return Err(self.err(id, format!("Op{}", inst.class.opname))),
        };
        let sg = match inst.operands.get(1) {
            Some(rspirv::dr::Operand::GroupOperation(spirv::GroupOperation::Reduce)) => SgOp::Reduce(bop),
            Some(rspirv::dr::Operand::GroupOperation(spirv::GroupOperation::InclusiveScan)) => SgOp::InclusiveScan(bop),
            Some(rspirv::dr::Operand::GroupOperation(spirv::GroupOperation::ExclusiveScan)) => SgOp::ExclusiveScan(bop),
            other => return Err(self.err(id, format!("group operation {other:?}"))),
        };
        if inst.operands.len() > 3 {
            return Err(self.err(id, "clustered subgroup operation"));
        }
        let a_id = id_op(inst, 2)?;
        let sc = self.sc_of(a_id)?;
        let a = self.regs(a_id)?;
        let out = self.l.components(inst.result_type.unwrap_or(0))?;
        self.same_counts(inst, a.len(), &[sc.len(), out.len()])?;
        let v = (0..a.len())
            .map(|i| {
                let dst = self.reg();
                self.emit(IrOp::Subgroup { op: sg, ty: sc[i], dst, a: a[i], b: 0 });
                dst
            })
            .collect();
        self.define(id, Val::Regs(v));
        Ok(())
    }
}

/// A rejection of `inst` whose operands do not have the shape its lowering needs: names the
/// opcode; the offset is the instruction's word offset (through its result id).
fn shape_error(lw: &Lowerer<'_>, inst: &Instruction, what: &str) -> ShaderError {
    lw.m.malformed(inst.result_id.unwrap_or(0), &format!("Op{}: {what}", inst.class.opname))
}

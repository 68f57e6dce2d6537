//! Constant values after specialization: every OpConstant*, OpSpecConstant* (with the
//! pipeline's specialization data applied) and OpSpecConstantOp (folded with the executor's own
//! scalar semantics), flattened into register words like any other value.
use std::collections::HashMap;

use rspirv::dr::Operand;
use spirv::Op;

use super::alu;
use super::layout::Layout;
use super::lower_ops::{alu_of, Alu};
use super::parse::{id_op, lit, EntryPoint, Module};
use super::ShaderError;

#[derive(Debug, Default)]
pub struct Constants {
    values: HashMap<u32, Vec<u64>>,
}

impl Constants {
    pub fn new(m: &Module, spec: &[(u32, Vec<u8>)]) -> Result<Constants, ShaderError> {
        let mut c = Constants::default();
        for inst in &m.dr.types_global_values {
            let (Some(id), Some(ty)) = (inst.result_id, inst.result_type) else { continue };
            let spec_value = m.decorations.get(&id).and_then(|d| d.spec_id).and_then(|sid| {
                spec.iter().find(|(k, _)| *k == sid).map(|(_, bytes)| (sid, bytes))
            });
            let value = match inst.class.opcode {
                Op::ConstantTrue | Op::SpecConstantTrue => vec![1],
                Op::ConstantFalse | Op::SpecConstantFalse => vec![0],
                Op::Constant | Op::SpecConstant => vec![literal_value(m, inst)?],
                Op::ConstantNull | Op::Undef => vec![0; c.layout(m).count(ty)?],
                Op::ConstantComposite | Op::SpecConstantComposite => {
                    let mut v = Vec::new();
                    for k in 0..inst.operands.len() {
                        let part = id_op(inst, k)?;
                        v.extend(c.value(part).ok_or_else(|| m.malformed(part, "not a constant"))?);
                    }
                    v
                }
                Op::SpecConstantOp => c.fold(m, ty, inst)?,
                _ => continue, // variables
            };
            let value = match (inst.class.opcode, spec_value) {
                (Op::SpecConstant | Op::SpecConstantTrue | Op::SpecConstantFalse, Some((sid, bytes))) => {
                    let sc = c.layout(m).scalar(ty)?;
                    vec![spec_bytes(sid, bytes, sc.size())?]
                        .into_iter()
                        .map(|v| alu::norm(sc, v))
                        .collect()
                }
                _ => value,
            };
            c.values.insert(id, value);
        }
        Ok(c)
    }

    fn layout<'a>(&'a self, m: &'a Module) -> Layout<'a> {
        Layout { m, consts: self }
    }

    /// The flattened value of constant `id`.
    pub fn value(&self, id: u32) -> Option<&[u64]> {
        self.values.get(&id).map(Vec::as_slice)
    }

    /// The workgroup size: a constant decorated BuiltIn WorkgroupSize wins over LocalSizeId,
    /// which wins over LocalSize.
    pub fn local_size(&self, m: &Module, e: &EntryPoint) -> Result<[u32; 3], ShaderError> {
        let builtin = m.decorations.iter().find_map(|(id, d)| {
            (d.builtin == Some(spirv::BuiltIn::WorkgroupSize)).then(|| self.value(*id)).flatten()
        });
        let size = if let Some(v) = builtin.filter(|v| v.len() == 3) {
            [v[0] as u32, v[1] as u32, v[2] as u32]
        } else if let Some(ids) = e.local_size_id {
            let get = |id| self.value(id).and_then(|v| v.first().copied()).map(|v| v as u32);
            match (get(ids[0]), get(ids[1]), get(ids[2])) {
                (Some(x), Some(y), Some(z)) => [x, y, z],
                _ => return Err(m.malformed(e.function, "LocalSizeId operands are not constants")),
            }
        } else {
            e.local_size
        };
        let total = size.iter().try_fold(1u32, |acc, &s| acc.checked_mul(s));
        if size.contains(&0) || total.is_none_or(|t| t > 65536) {
            return Err(ShaderError::Unsupported { what: format!("workgroup size {size:?}"), offset: 0 });
        }
        Ok(size)
    }

    /// OpSpecConstantOp: the ALU opcodes the executor has, plus the composite ones.
    fn fold(&self, m: &Module, ty: u32, inst: &rspirv::dr::Instruction) -> Result<Vec<u64>, ShaderError> {
        let op = match inst.operands.first() {
            Some(Operand::LiteralSpecConstantOpInteger(op)) => *op,
            _ => return Err(m.malformed(inst.result_id.unwrap_or(0), "OpSpecConstantOp without an opcode")),
        };
        let id = inst.result_id.unwrap_or(0);
        let arg = |k: usize| -> Result<&[u64], ShaderError> {
            let a = id_op(inst, k)?;
            self.value(a).ok_or_else(|| m.malformed(a, "operand is not a constant"))
        };
        let arg_ty = |k: usize| -> Result<u32, ShaderError> {
            let a = id_op(inst, k)?;
            let def = m.globals.get(&a).and_then(|&i| m.dr.types_global_values[i].result_type);
            def.ok_or_else(|| m.malformed(a, "operand is not a constant"))
        };
        // Literal operands from the raw words (parse.rs: rspirv keeps only the first).
        let literals = |from: usize| -> Result<Vec<u32>, ShaderError> {
            match m.spec_literals.get(&id) {
                Some(v) => Ok(v.clone()),
                None => (from..inst.operands.len()).map(|k| lit(inst, k)).collect(),
            }
        };
        let l = self.layout(m);
        let out_sc = l.components(ty)?;
        match op {
            Op::CompositeExtract => {
                let base = arg(1)?;
                let idx = literals(2)?;
                let (start, n, _) = l.sub_range(arg_ty(1)?, &idx)?;
                Ok(base.get(start..start + n).ok_or_else(|| m.malformed(id, "extract"))?.to_vec())
            }
            Op::CompositeInsert => {
                let (obj, mut base) = (arg(1)?.to_vec(), arg(2)?.to_vec());
                let idx = literals(3)?;
                let (start, n, _) = l.sub_range(ty, &idx)?;
                let part = obj.get(..n).ok_or_else(|| m.malformed(id, "insert"))?;
                base.get_mut(start..start + n).ok_or_else(|| m.malformed(id, "insert"))?.copy_from_slice(part);
                Ok(base)
            }
            Op::VectorShuffle => {
                let joined: Vec<u64> = arg(1)?.iter().chain(arg(2)?).copied().collect();
                Ok(literals(3)?.into_iter().map(|k| joined.get(k as usize).copied().unwrap_or(0)).collect())
            }
            Op::Select => {
                let (c, a, b) = (arg(1)?, arg(2)?, arg(3)?);
                if c.is_empty() || b.len() != a.len() || (c.len() != 1 && c.len() != a.len()) {
                    return Err(m.malformed(id, "select operands of different sizes"));
                }
                Ok((0..a.len()).map(|i| if c[i.min(c.len() - 1)] != 0 { a[i] } else { b[i] }).collect())
            }
            _ => {
                let Some(kind) = alu_of(op) else {
                    return Err(ShaderError::Unsupported { what: format!("OpSpecConstantOp {op:?}"), offset: m.offset_of(id) });
                };
                let a = arg(1)?;
                let a_sc = l.components(arg_ty(1)?)?;
                let b = if inst.operands.len() > 2 { Some(arg(2)?) } else { None };
                let scalar_b = b.filter(|b| b.len() == 1 && a.len() > 1);
                let n = out_sc.len();
                if a.len() < n || a_sc.len() < n || b.is_some_and(|b| scalar_b.is_none() && b.len() < n) {
                    return Err(m.malformed(id, "operands smaller than the result"));
                }
                Ok((0..out_sc.len())
                    .map(|i| match (kind, b) {
                        (Alu::Bin(op), Some(b)) => alu::bin(op, a_sc[i], a[i], scalar_b.map_or(b[i], |s| s[0])),
                        (Alu::Un(op), _) => alu::un(op, out_sc[i], a_sc[i], a[i]),
                        _ => 0,
                    })
                    .collect())
            }
        }
    }
}

fn literal_value(m: &Module, inst: &rspirv::dr::Instruction) -> Result<u64, ShaderError> {
    match inst.operands.first() {
        Some(Operand::LiteralBit32(v)) => Ok(*v as u64),
        Some(Operand::LiteralBit64(v)) => Ok(*v),
        _ => Err(m.malformed(inst.result_id.unwrap_or(0), "constant without a literal")),
    }
}

fn spec_bytes(sid: u32, bytes: &[u8], size: u32) -> Result<u64, ShaderError> {
    if bytes.len() < size as usize {
        return Err(ShaderError::Specialization { id: sid, reason: format!("{} bytes given, {size} needed", bytes.len()) });
    }
    let mut w = [0u8; 8];
    w[..size as usize].copy_from_slice(&bytes[..size as usize]);
    Ok(u64::from_le_bytes(w))
}

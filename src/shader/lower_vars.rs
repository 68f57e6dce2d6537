//! Function-storage variables kept in registers instead of lane memory.
//!
//! Unoptimised SPIR-V keeps every local in an OpVariable and reaches it through OpLoad and
//! OpStore; lowered as lane memory, each of those is a checked per-lane access. A variable
//! whose pointer is only ever loaded from or stored to (whole, or through access chains with
//! constant indices) cannot be observed any other way, so it becomes a set of registers, one
//! per scalar component: a store is a masked register copy, a load copies the registers out
//! (so a later store cannot change a value already loaded). Registers are written under the
//! execution mask like lane memory is, so divergent lanes keep their own values. Any other use
//! of the pointer (a call argument, OpCopyMemory, an atomic, a dynamic index, a phi, a ray
//! query) leaves the variable in memory.
use std::collections::{HashMap, HashSet};

use rspirv::dr::{Function, Instruction, Operand};
use spirv::{Op, StorageClass};

use super::ir::{Op as IrOp, Reg};
use super::lower::{Lowerer, Val};
use super::parse::{id_op, Type};
use super::ShaderError;

/// Variables with more scalar components than this stay in memory: a whole-variable load or
/// store would cost one register copy per component.
const MAX_COMPONENTS: usize = 64;

/// A promoted variable or a constant access chain into one: its registers and pointee type.
#[derive(Clone, Debug)]
pub struct VarRegs {
    pub regs: Vec<Reg>,
    pub pointee: u32,
}

impl Lowerer<'_> {
    /// The Function variables of `f` (and the access chains into them) that can live in
    /// registers.
    pub(super) fn promotable(&self, f: &Function) -> HashSet<u32> {
        // A variable drops out on any use but those below.
        // Pointer id → (the variable it points into, its pointee type).
        let mut root: HashMap<u32, (u32, u32)> = HashMap::new();
        let mut rejected: HashSet<u32> = HashSet::new();
        for inst in f.blocks.iter().flat_map(|b| b.instructions.iter()) {
            let id = inst.result_id.unwrap_or(0);
            match inst.class.opcode {
                Op::Variable => {
                    if let Some(p) = self.promotable_variable(inst) {
                        root.insert(id, (id, p));
                        continue;
                    }
                }
                Op::AccessChain | Op::InBoundsAccessChain => {
                    if let Some(&(r, p)) = inst.operands.first().and_then(id_of).and_then(|b| root.get(&b)) {
                        let part = self.constant_chain(inst).and_then(|ix| self.l.sub_range(p, &ix).ok());
                        if let Some((_, _, pointee)) = part {
                            root.insert(id, (r, pointee));
                        } else {
                            rejected.insert(r);
                        }
                        continue;
                    }
                }
                _ => {}
            }
            // Allowed: the pointer operand of a load or store; every other pointer use escapes.
            let allowed = matches!(inst.class.opcode, Op::Load | Op::Store);
            for (k, o) in inst.operands.iter().enumerate() {
                if let Some(&(r, _)) = id_of(o).and_then(|v| root.get(&v)) {
                    if !(allowed && k == 0) {
                        rejected.insert(r);
                    }
                }
            }
        }
        root.into_iter().filter(|(_, (r, _))| !rejected.contains(r)).map(|(id, _)| id).collect()
    }

    /// A Function variable of a type made only of scalars, vectors, matrices, fixed arrays and
    /// structs, small enough to keep in registers: its pointee type.
    fn promotable_variable(&self, inst: &Instruction) -> Option<u32> {
        let class = super::parse::storage_class(inst, 0).ok()?;
        let p = self.pointee(inst.result_type?).ok()?;
        let small = self.l.count(p).is_ok_and(|n| n <= MAX_COMPONENTS);
        (class == StorageClass::Function && self.plain_type(p, 0) && small).then_some(p)
    }

    fn plain_type(&self, ty: u32, depth: u32) -> bool {
        if depth > 16 {
            return false;
        }
        match self.m.ty(ty) {
            Ok(Type::Bool | Type::Int { .. } | Type::Float { .. }) => true,
            Ok(Type::Vector { elem, .. } | Type::Matrix { column: elem, .. } | Type::Array { elem, .. }) => {
                self.plain_type(*elem, depth + 1)
            }
            Ok(Type::Struct { members }) => members.iter().all(|&m| self.plain_type(m, depth + 1)),
            _ => false,
        }
    }

    /// The literal indices of an access chain whose indices are all constants, if it has any.
    fn constant_chain(&self, inst: &Instruction) -> Option<Vec<u32>> {
        (1..inst.operands.len())
            .map(|k| {
                let idx = id_op(inst, k).ok()?;
                let c = *self.consts.value(idx)?.first()?;
                let bits = self.type_of(idx).and_then(|t| self.l.scalar(t).ok())?.bits();
                // Indices are signed: a negative constant is out of range, so not promotable.
                let c = if bits == 32 { c as u32 as i32 as i64 } else { c as i64 };
                u32::try_from(c).ok()
            })
            .collect()
    }

    /// OpVariable of a promoted variable: fresh registers holding its initializer, or zero
    /// (registers outlive a lane group's invocation, memory is re-zeroed per invocation).
    pub(super) fn promote_variable(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let pointee = self.pointee(inst.result_type.unwrap_or(0))?;
        let n = self.l.count(pointee)?;
        let init = match inst.operands.get(1) {
            Some(_) => self.regs(id_op(inst, 1)?)?,
            None => vec![self.konst(0); n],
        };
        if init.len() != n {
            return Err(self.m.malformed(id, "initializer of another type"));
        }
        let regs = self.regs_n(n);
        for (&dst, &src) in regs.iter().zip(&init) {
            self.emit(IrOp::Mov { dst, src });
        }
        self.define_var(id, VarRegs { regs, pointee });
        Ok(())
    }

    /// A constant access chain into a promoted variable: the registers of the part it names.
    pub(super) fn promote_chain(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let base = self.var(id_op(inst, 0)?).ok_or_else(|| self.m.malformed(id, "access chain base"))?;
        let indices = self.constant_chain(inst).ok_or_else(|| self.m.malformed(id, "access chain index"))?;
        let (start, n, pointee) = self.l.sub_range(base.pointee, &indices)?;
        let regs = base.regs.get(start..start + n).ok_or_else(|| self.m.malformed(id, "access chain range"))?.to_vec();
        self.define_var(id, VarRegs { regs, pointee });
        Ok(())
    }

    /// OpLoad of a promoted pointer: a copy of its registers.
    pub(super) fn load_var(&mut self, inst: &Instruction, v: VarRegs) -> Result<(), ShaderError> {
        let out = self.regs_n(v.regs.len());
        for (&dst, &src) in out.iter().zip(&v.regs) {
            self.emit(IrOp::Mov { dst, src });
        }
        self.define(inst.result_id.unwrap_or(0), Val::Regs(out));
        Ok(())
    }

    /// OpStore to a promoted pointer: masked copies into its registers.
    pub(super) fn store_var(&mut self, inst: &Instruction, v: VarRegs) -> Result<(), ShaderError> {
        let src = self.regs(id_op(inst, 1)?)?;
        if src.len() != v.regs.len() {
            return Err(self.m.malformed(v.pointee, "store of a value of another type"));
        }
        for (&dst, &src) in v.regs.iter().zip(&src) {
            self.emit(IrOp::Mov { dst, src });
        }
        Ok(())
    }
}

fn id_of(o: &Operand) -> Option<u32> {
    match o {
        Operand::IdRef(v) => Some(*v),
        _ => None,
    }
}

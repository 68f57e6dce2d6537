//! SPV_KHR_ray_query (and the ray-query halves of SPV_KHR_ray_tracing_position_fetch and
//! SPV_NV_cluster_acceleration_structure) → IR.
//!
//! A ray query is only ever reached through a pointer (a Private global from glslang, a
//! Function variable passed by pointer into helpers from naga): the pointer's lane-frame
//! address names the query, and each instruction becomes one [`IrOp::RayQuery`] that the
//! executor (`exec_rq`) runs against native traversal. An acceleration structure value is one
//! I64 register holding the structure's device address, from a descriptor (see
//! `Lowerer::accel_descriptor`) or from `OpConvertUToAccelerationStructureKHR`.
use rspirv::dr::Instruction;
use spirv::Op;

use super::ir::{BinOp, Op as IrOp, RayQueryOp, Reg, RqKind, RqValue, Sc, Space, UnOp};
use super::lower::{Lowerer, Val};
use super::parse::id_op;
use super::ShaderError;

/// Whether `op` is lowered here.
pub fn is_ray_query(op: Op) -> bool {
    op == Op::ConvertUToAccelerationStructureKHR || kind_of(op).is_some()
}

/// The IR kind of a ray-query opcode, and whether a getter takes the Intersection operand.
fn kind_of(op: Op) -> Option<(RqKind, bool)> {
    use RqValue::*;
    let get = |value, intersection| Some((RqKind::Get { value, committed: false }, intersection));
    match op {
        Op::RayQueryInitializeKHR => Some((RqKind::Initialize, false)),
        Op::RayQueryProceedKHR => Some((RqKind::Proceed, false)),
        Op::RayQueryTerminateKHR => Some((RqKind::Terminate, false)),
        Op::RayQueryConfirmIntersectionKHR => Some((RqKind::Confirm, false)),
        Op::RayQueryGenerateIntersectionKHR => Some((RqKind::Generate, false)),
        Op::RayQueryGetRayTMinKHR => get(TMin, false),
        Op::RayQueryGetRayFlagsKHR => get(RayFlags, false),
        Op::RayQueryGetWorldRayOriginKHR => get(WorldRayOrigin, false),
        Op::RayQueryGetWorldRayDirectionKHR => get(WorldRayDirection, false),
        Op::RayQueryGetIntersectionTypeKHR => get(Type, true),
        Op::RayQueryGetIntersectionTKHR => get(T, true),
        Op::RayQueryGetIntersectionInstanceCustomIndexKHR => get(InstanceCustomIndex, true),
        Op::RayQueryGetIntersectionInstanceIdKHR => get(InstanceId, true),
        Op::RayQueryGetIntersectionInstanceShaderBindingTableRecordOffsetKHR => get(SbtRecordOffset, true),
        Op::RayQueryGetIntersectionGeometryIndexKHR => get(GeometryIndex, true),
        Op::RayQueryGetIntersectionPrimitiveIndexKHR => get(PrimitiveIndex, true),
        Op::RayQueryGetIntersectionBarycentricsKHR => get(Barycentrics, true),
        Op::RayQueryGetIntersectionFrontFaceKHR => get(FrontFace, true),
        // Candidate-only by definition: no Intersection operand.
        Op::RayQueryGetIntersectionCandidateAABBOpaqueKHR => get(CandidateAabbOpaque, false),
        Op::RayQueryGetIntersectionObjectRayDirectionKHR => get(ObjectRayDirection, true),
        Op::RayQueryGetIntersectionObjectRayOriginKHR => get(ObjectRayOrigin, true),
        Op::RayQueryGetIntersectionObjectToWorldKHR => get(ObjectToWorld, true),
        Op::RayQueryGetIntersectionWorldToObjectKHR => get(WorldToObject, true),
        Op::RayQueryGetIntersectionTriangleVertexPositionsKHR => get(TriangleVertexPositions, true),
        Op::RayQueryGetIntersectionClusterIdNV => get(ClusterId, true),
        _ => None,
    }
}

impl Lowerer<'_> {
    pub fn lower_ray_query(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let rty = inst.result_type.unwrap_or(0);
        if inst.class.opcode == Op::ConvertUToAccelerationStructureKHR {
            let r = self.address_u64(id_op(inst, 0)?)?;
            self.define(id, Val::Regs(vec![r]));
            return Ok(());
        }
        let Some((mut kind, intersection)) = kind_of(inst.class.opcode) else {
            return Err(self.err(id, format!("Op{}", inst.class.opname)));
        };
        let qid = id_op(inst, 0)?;
        let q = self.ptr(qid, self.type_of(qid))?;
        if q.space != Space::Lane {
            return Err(self.err(qid, "ray query outside Private/Function storage"));
        }
        let mut args = Vec::new();
        let mut dst = Vec::new();
        match &mut kind {
            RqKind::Initialize => {
                args.push(self.reg1(id_op(inst, 1)?)?);
                for k in 2..8 {
                    args.extend(self.regs(id_op(inst, k)?)?);
                }
                if args.len() != 11 {
                    return Err(self.m.malformed(id, "OpRayQueryInitializeKHR operand shapes"));
                }
            }
            RqKind::Generate => args.push(self.reg1(id_op(inst, 1)?)?),
            RqKind::Proceed => dst.push(self.reg()),
            RqKind::Terminate | RqKind::Confirm => {}
            RqKind::Get { value, committed } => {
                if intersection {
                    let c = id_op(inst, 1)?;
                    let v = self.consts.value(c).and_then(|v| v.first().copied());
                    *committed = v.ok_or_else(|| self.m.malformed(c, "Intersection operand is not a constant"))? != 0;
                }
                let n = self.l.count(rty)?;
                if n != value.count() {
                    return Err(self.m.malformed(id, "ray-query getter result type"));
                }
                dst = self.regs_n(n);
            }
        }
        self.emit(IrOp::RayQuery(Box::new(RayQueryOp { kind, query: q.addr, args, dst: dst.clone() })));
        if !dst.is_empty() {
            self.define(id, Val::Regs(dst));
        }
        Ok(())
    }

    /// A 64-bit address from a u64 scalar or a uvec2 (low word first), as
    /// OpConvertUToAccelerationStructureKHR accepts both.
    fn address_u64(&mut self, src: u32) -> Result<Reg, ShaderError> {
        let r = self.regs(src)?;
        match r[..] {
            [a] => Ok(a),
            [lo, hi] => {
                let (lo64, hi64) = (self.reg(), self.reg());
                self.emit(IrOp::Un { op: UnOp::UConvert, ty: Sc::I64, from: Sc::I32, dst: lo64, a: lo });
                self.emit(IrOp::Un { op: UnOp::UConvert, ty: Sc::I64, from: Sc::I32, dst: hi64, a: hi });
                let k32 = self.konst(32);
                let shifted = self.bin(BinOp::Shl, Sc::I64, hi64, k32);
                Ok(self.bin(BinOp::Or, Sc::I64, shifted, lo64))
            }
            _ => Err(self.m.malformed(src, "acceleration structure address is not a u64 or uvec2")),
        }
    }
}

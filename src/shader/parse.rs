//! SPIR-V words → [`Module`]: the checks that make an unsupported module fail here, at
//! pipeline creation, and the indexes `lower` reads (types, decorations, definitions).
//!
//! A raw pass over the words finds each instruction's word offset (for error messages) and
//! rejects unknown capabilities, extensions, opcodes and GLSL.std.450 instructions; rspirv then
//! builds the data representation the rest of the module indexes. Nothing here panics on
//! malformed input: operand accessors return errors instead of rspirv's `unwrap_*`.
use std::collections::HashMap;

use rspirv::dr::{self, Instruction, Operand};
use spirv::{BuiltIn, Capability, Decoration, Op, StorageClass};

use super::ShaderError;

/// A SPIR-V type, as far as the compute subset needs it.
#[derive(Clone, Debug, PartialEq)]
pub enum Type {
    Void,
    Bool,
    Int { bits: u32, signed: bool },
    Float { bits: u32 },
    Vector { elem: u32, n: u32 },
    Matrix { column: u32, n: u32 },
    /// `len` is the id of a (possibly specialization) constant.
    Array { elem: u32, len: u32 },
    RuntimeArray { elem: u32 },
    Struct { members: Vec<u32> },
    Pointer { class: StorageClass, pointee: u32 },
    Function,
    /// A storage image (Sampled = 2): `sampled` is the component type id; the texel format
    /// comes from the bound view, so `Unknown` formats work too.
    Image { sampled: u32, dim: spirv::Dim, arrayed: bool },
    /// OpTypeAccelerationStructureKHR: a value is the structure's 64-bit device address.
    AccelerationStructure,
    /// OpTypeRayQueryKHR: only ever behind a pointer; the executor keeps its state per lane.
    RayQuery,
}

/// Decorations `lower` needs, per id.
#[derive(Clone, Debug, Default)]
pub struct Decorations {
    pub set: Option<u32>,
    pub binding: Option<u32>,
    pub builtin: Option<BuiltIn>,
    pub spec_id: Option<u32>,
    pub array_stride: Option<u32>,
}

#[derive(Clone, Debug)]
pub struct EntryPoint {
    pub name: String,
    pub function: u32,
    pub local_size: [u32; 3],
    /// LocalSizeId: constant ids (may be specialization constants).
    pub local_size_id: Option<[u32; 3]>,
}

/// A parsed, checked SPIR-V module. Cheap to keep; lowering happens per pipeline, once the
/// specialization constants are known.
#[derive(Clone, Debug)]
pub struct Module {
    pub(crate) dr: dr::Module,
    pub(crate) types: HashMap<u32, Type>,
    /// Constants, spec constants, global variables and OpUndef: id → index in
    /// `dr.types_global_values`.
    pub(crate) globals: HashMap<u32, usize>,
    pub(crate) functions: HashMap<u32, usize>,
    pub(crate) decorations: HashMap<u32, Decorations>,
    pub(crate) member_offset: HashMap<(u32, u32), u32>,
    pub(crate) member_matrix_stride: HashMap<(u32, u32), u32>,
    pub(crate) entry_points: Vec<EntryPoint>,
    pub(crate) glsl_ext: Option<u32>,
    /// Word offset of the instruction defining each result id (for error messages).
    pub(crate) offsets: HashMap<u32, usize>,
    /// Literal operands of composite OpSpecConstantOps, by result id (rspirv drops all but one).
    pub(crate) spec_literals: HashMap<u32, Vec<u32>>,
}

const CAPABILITIES: &[Capability] = &[
    Capability::Shader,
    Capability::Matrix,
    Capability::Int64,
    Capability::Float64,
    Capability::Int64Atomics,
    Capability::PhysicalStorageBufferAddresses,
    Capability::VulkanMemoryModel,
    Capability::VulkanMemoryModelDeviceScope,
    Capability::GroupNonUniform,
    Capability::GroupNonUniformVote,
    Capability::GroupNonUniformBallot,
    Capability::GroupNonUniformArithmetic,
    Capability::GroupNonUniformShuffle,
    Capability::GroupNonUniformShuffleRelative,
    Capability::Image1D,
    Capability::ImageQuery,
    Capability::StorageImageReadWithoutFormat,
    Capability::StorageImageWriteWithoutFormat,
    Capability::ImageBuffer,
    Capability::SampledBuffer,
    Capability::RayQueryKHR,
    Capability::RayQueryPositionFetchKHR,
    // OpRayQueryGetIntersectionClusterIdNV only (no ray-tracing pipelines, no hit objects).
    Capability::RayTracingClusterAccelerationStructureNV,
    // Arrays of storage and uniform buffer descriptors, indexed by any value (the executor
    // resolves the element per lane), sized or runtime.
    Capability::UniformBufferArrayDynamicIndexing,
    Capability::StorageBufferArrayDynamicIndexing,
    Capability::RuntimeDescriptorArray,
    Capability::ShaderNonUniform,
    Capability::UniformBufferArrayNonUniformIndexing,
    Capability::StorageBufferArrayNonUniformIndexing,
    // Arrays of storage images and texel buffers: each element's view resolved per dispatch.
    Capability::StorageImageArrayDynamicIndexing,
    Capability::StorageImageArrayNonUniformIndexing,
    Capability::UniformTexelBufferArrayDynamicIndexing,
    Capability::StorageTexelBufferArrayDynamicIndexing,
    Capability::UniformTexelBufferArrayNonUniformIndexing,
    Capability::StorageTexelBufferArrayNonUniformIndexing,
];

const EXTENSIONS: &[&str] = &[
    "SPV_KHR_storage_buffer_storage_class",
    "SPV_KHR_physical_storage_buffer",
    "SPV_EXT_physical_storage_buffer",
    "SPV_KHR_vulkan_memory_model",
    "SPV_KHR_non_semantic_info",
    "SPV_KHR_shader_ballot",
    "SPV_KHR_ray_query",
    "SPV_KHR_ray_tracing_position_fetch",
    "SPV_NV_cluster_acceleration_structure",
    "SPV_EXT_descriptor_indexing",
];

/// Opcodes the lowering handles; anything else is rejected with its word offset.
const OPCODES: &[Op] = {
    use Op::*;
    &[
        Nop, Undef, SourceContinued, Source, SourceExtension, Name, MemberName, String, Line,
        NoLine, ModuleProcessed, Extension, ExtInstImport, ExtInst, MemoryModel, EntryPoint,
        ExecutionMode, ExecutionModeId, Capability, TypeVoid, TypeBool, TypeInt, TypeFloat,
        TypeVector, TypeMatrix, TypeArray, TypeRuntimeArray, TypeStruct, TypePointer,
        TypeForwardPointer, TypeFunction, ConstantTrue, ConstantFalse, Constant,
        ConstantComposite, ConstantNull, SpecConstantTrue, SpecConstantFalse, SpecConstant,
        SpecConstantComposite, SpecConstantOp, Function, FunctionParameter, FunctionEnd,
        FunctionCall, Variable, Load, Store, CopyMemory, AccessChain, InBoundsAccessChain,
        PtrAccessChain, Decorate, MemberDecorate, DecorateId, DecorateString,
        MemberDecorateString, VectorExtractDynamic, VectorInsertDynamic, VectorShuffle,
        CompositeConstruct, CompositeExtract, CompositeInsert, CopyObject, CopyLogical,
        ConvertFToU, ConvertFToS, ConvertSToF, ConvertUToF, UConvert, SConvert, FConvert,
        ConvertUToPtr, ConvertPtrToU, Bitcast, SNegate, FNegate, IAdd, FAdd, ISub, FSub, IMul,
        FMul, UDiv, SDiv, FDiv, UMod, SRem, SMod, FRem, FMod, VectorTimesScalar,
        MatrixTimesScalar, VectorTimesMatrix, Transpose, MatrixTimesVector, MatrixTimesMatrix, Dot,
        IAddCarry, ISubBorrow, UMulExtended, SMulExtended, Any, All, IsNan, IsInf,
        LogicalEqual, LogicalNotEqual, LogicalOr, LogicalAnd, LogicalNot, Select, IEqual,
        INotEqual, UGreaterThan, SGreaterThan, UGreaterThanEqual, SGreaterThanEqual, ULessThan,
        SLessThan, ULessThanEqual, SLessThanEqual, FOrdEqual, FUnordEqual, FOrdNotEqual,
        FUnordNotEqual, FOrdLessThan, FUnordLessThan, FOrdGreaterThan, FUnordGreaterThan,
        FOrdLessThanEqual, FUnordLessThanEqual, FOrdGreaterThanEqual, FUnordGreaterThanEqual,
        ShiftRightLogical, ShiftRightArithmetic, ShiftLeftLogical, BitwiseOr, BitwiseXor,
        BitwiseAnd, Not, BitFieldInsert, BitFieldSExtract, BitFieldUExtract, BitReverse,
        BitCount, ControlBarrier, MemoryBarrier, AtomicLoad, AtomicStore, AtomicExchange,
        AtomicCompareExchange, AtomicIIncrement, AtomicIDecrement, AtomicIAdd, AtomicISub,
        AtomicSMin, AtomicUMin, AtomicSMax, AtomicUMax, AtomicAnd, AtomicOr, AtomicXor, Phi,
        LoopMerge, SelectionMerge, Label, Branch, BranchConditional, Switch, Return,
        ReturnValue, Unreachable, GroupNonUniformElect, GroupNonUniformAll,
        GroupNonUniformAny, GroupNonUniformAllEqual, GroupNonUniformBroadcast,
        GroupNonUniformBroadcastFirst, GroupNonUniformBallot, GroupNonUniformInverseBallot,
        GroupNonUniformBallotBitExtract, GroupNonUniformBallotBitCount,
        GroupNonUniformBallotFindLSB, GroupNonUniformBallotFindMSB, GroupNonUniformShuffle,
        GroupNonUniformShuffleXor, GroupNonUniformShuffleUp, GroupNonUniformShuffleDown,
        GroupNonUniformIAdd, GroupNonUniformFAdd, GroupNonUniformIMul, GroupNonUniformFMul,
        GroupNonUniformSMin, GroupNonUniformUMin, GroupNonUniformFMin, GroupNonUniformSMax,
        GroupNonUniformUMax, GroupNonUniformFMax, GroupNonUniformBitwiseAnd,
        GroupNonUniformBitwiseOr, GroupNonUniformBitwiseXor, GroupNonUniformLogicalAnd,
        GroupNonUniformLogicalOr, GroupNonUniformLogicalXor, TypeImage, ImageRead, ImageWrite, ImageFetch, ImageTexelPointer,
        ImageQuerySize,
        // SPV_KHR_ray_query (lowered in `lower_rq`) and SPV_KHR_ray_tracing_position_fetch.
        TypeAccelerationStructureKHR, TypeRayQueryKHR, ConvertUToAccelerationStructureKHR,
        RayQueryInitializeKHR, RayQueryTerminateKHR, RayQueryGenerateIntersectionKHR,
        RayQueryConfirmIntersectionKHR, RayQueryProceedKHR, RayQueryGetIntersectionTypeKHR,
        RayQueryGetRayTMinKHR, RayQueryGetRayFlagsKHR, RayQueryGetIntersectionTKHR,
        RayQueryGetIntersectionInstanceCustomIndexKHR, RayQueryGetIntersectionInstanceIdKHR,
        RayQueryGetIntersectionInstanceShaderBindingTableRecordOffsetKHR,
        RayQueryGetIntersectionGeometryIndexKHR, RayQueryGetIntersectionPrimitiveIndexKHR,
        RayQueryGetIntersectionBarycentricsKHR, RayQueryGetIntersectionFrontFaceKHR,
        RayQueryGetIntersectionCandidateAABBOpaqueKHR, RayQueryGetIntersectionObjectRayDirectionKHR,
        RayQueryGetIntersectionObjectRayOriginKHR, RayQueryGetWorldRayDirectionKHR,
        RayQueryGetWorldRayOriginKHR, RayQueryGetIntersectionObjectToWorldKHR,
        RayQueryGetIntersectionWorldToObjectKHR, RayQueryGetIntersectionTriangleVertexPositionsKHR,
        RayQueryGetIntersectionClusterIdNV,
    ]
};

/// GLSL.std.450 instruction numbers `lower` implements.
pub(crate) const GLSL_SUPPORTED: &[u32] = &[
    1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25,
    26, 27, 28, 29, 30, 31, 32, 33, 37, 38, 39, 40, 41, 42, 43, 44, 45, 46, 47, 48, 49, 50, 53,
    66, 67, 68, 69, 70, 71, 73, 74, 75, 79, 80, 81,
];

impl Module {
    /// Parses and checks a module. Fails on malformed SPIR-V and on anything Arbor cannot run,
    /// naming it and its word offset.
    pub fn parse(words: &[u32]) -> Result<Module, ShaderError> {
        let scan = scan(words)?;
        let dr = dr::load_words(scan.for_rspirv.as_deref().unwrap_or(words)).map_err(|e| ShaderError::Malformed {
            offset: 0,
            reason: format!("rspirv could not decode the module (byte offset, instruction index): {e:?}"),
        })?;
        let mut m = Module {
            dr,
            types: HashMap::new(),
            globals: HashMap::new(),
            functions: HashMap::new(),
            decorations: HashMap::new(),
            member_offset: HashMap::new(),
            member_matrix_stride: HashMap::new(),
            entry_points: Vec::new(),
            glsl_ext: scan.glsl_ext,
            offsets: scan.offsets,
            spec_literals: scan.spec_literals,
        };
        m.index_types()?;
        m.index_decorations()?;
        m.index_entry_points()?;
        for (i, f) in m.dr.functions.iter().enumerate() {
            if let Some(id) = f.def.as_ref().and_then(|d| d.result_id) {
                m.functions.insert(id, i);
            }
        }
        Ok(m)
    }

    /// Names of the GLCompute entry points.
    pub fn entry_point_names(&self) -> Vec<&str> {
        self.entry_points.iter().map(|e| e.name.as_str()).collect()
    }

    pub(crate) fn offset_of(&self, id: u32) -> usize {
        self.offsets.get(&id).copied().unwrap_or(0)
    }

    pub(crate) fn ty(&self, id: u32) -> Result<&Type, ShaderError> {
        self.types.get(&id).ok_or_else(|| self.malformed(id, "not a supported type"))
    }

    pub(crate) fn malformed(&self, id: u32, reason: &str) -> ShaderError {
        ShaderError::Malformed { offset: self.offset_of(id), reason: format!("%{id}: {reason}") }
    }

    fn index_types(&mut self) -> Result<(), ShaderError> {
        let pointers: std::collections::HashSet<u32> =
            self.dr.types_global_values.iter().filter(|i| i.class.opcode == Op::TypePointer).filter_map(|i| i.result_id).collect();
        for (i, inst) in self.dr.types_global_values.iter().enumerate() {
            let Some(id) = inst.result_id else { continue };
            let ty = match inst.class.opcode {
                Op::TypeVoid => Type::Void,
                Op::TypeBool => Type::Bool,
                Op::TypeInt => Type::Int { bits: lit(inst, 0)?, signed: lit(inst, 1)? != 0 },
                Op::TypeFloat => Type::Float { bits: lit(inst, 0)? },
                Op::TypeVector => Type::Vector { elem: id_op(inst, 0)?, n: lit(inst, 1)? },
                Op::TypeMatrix => Type::Matrix { column: id_op(inst, 0)?, n: lit(inst, 1)? },
                Op::TypeArray => Type::Array { elem: id_op(inst, 0)?, len: id_op(inst, 1)? },
                Op::TypeRuntimeArray => Type::RuntimeArray { elem: id_op(inst, 0)? },
                Op::TypeStruct => Type::Struct {
                    members: (0..inst.operands.len()).map(|k| id_op(inst, k)).collect::<Result<_, _>>()?,
                },
                Op::TypePointer => Type::Pointer { class: storage_class(inst, 0)?, pointee: id_op(inst, 1)? },
                Op::TypeFunction => Type::Function,
                Op::TypeImage => image_type(inst, self.offset_of(id))?,
                Op::TypeAccelerationStructureKHR => Type::AccelerationStructure,
                Op::TypeRayQueryKHR => Type::RayQuery,
                _ => {
                    self.globals.insert(id, i);
                    continue;
                }
            };
            if let Type::Int { bits, .. } | Type::Float { bits } = ty {
                if bits != 32 && bits != 64 {
                    return Err(ShaderError::Unsupported {
                        what: format!("{bits}-bit scalar type"),
                        offset: self.offset_of(id),
                    });
                }
            }
            // A composite's parts are declared before it (only pointers may be declared after,
            // through OpTypeForwardPointer), so no type contains itself: the layout's recursion
            // over parts (which stops at pointers) always ends.
            let parts: Vec<u32> = match &ty {
                Type::Vector { elem, .. } | Type::Array { elem, .. } | Type::RuntimeArray { elem } => vec![*elem],
                Type::Matrix { column, .. } => vec![*column],
                Type::Struct { members } => members.clone(),
                _ => Vec::new(),
            };
            if parts.iter().any(|p| !self.types.contains_key(p) && !pointers.contains(p)) || self.types.contains_key(&id) {
                return Err(self.malformed(id, "composite type of a type not declared before it"));
            }
            self.types.insert(id, ty);
        }
        Ok(())
    }

    fn index_decorations(&mut self) -> Result<(), ShaderError> {
        for inst in &self.dr.annotations {
            match inst.class.opcode {
                Op::Decorate => {
                    let target = id_op(inst, 0)?;
                    let d = self.decorations.entry(target).or_default();
                    match inst.operands.get(1) {
                        Some(Operand::Decoration(Decoration::DescriptorSet)) => d.set = Some(lit(inst, 2)?),
                        Some(Operand::Decoration(Decoration::Binding)) => d.binding = Some(lit(inst, 2)?),
                        Some(Operand::Decoration(Decoration::SpecId)) => d.spec_id = Some(lit(inst, 2)?),
                        Some(Operand::Decoration(Decoration::ArrayStride)) => d.array_stride = Some(lit(inst, 2)?),
                        Some(Operand::Decoration(Decoration::BuiltIn)) => match inst.operands.get(2) {
                            Some(Operand::BuiltIn(b)) => d.builtin = Some(*b),
                            _ => return Err(bad(inst, "BuiltIn operand")),
                        },
                        _ => {}
                    }
                }
                Op::MemberDecorate => {
                    let key = (id_op(inst, 0)?, lit(inst, 1)?);
                    match inst.operands.get(2) {
                        Some(Operand::Decoration(Decoration::Offset)) => {
                            self.member_offset.insert(key, lit(inst, 3)?);
                        }
                        Some(Operand::Decoration(Decoration::MatrixStride)) => {
                            self.member_matrix_stride.insert(key, lit(inst, 3)?);
                        }
                        Some(Operand::Decoration(Decoration::RowMajor)) => {
                            return Err(ShaderError::Unsupported {
                                what: "RowMajor matrix layout".into(),
                                offset: self.offset_of(key.0),
                            })
                        }
                        _ => {}
                    }
                }
                _ => {}
            }
        }
        Ok(())
    }

    fn index_entry_points(&mut self) -> Result<(), ShaderError> {
        for inst in &self.dr.entry_points {
            if !matches!(inst.operands.first(), Some(Operand::ExecutionModel(spirv::ExecutionModel::GLCompute))) {
                continue; // other stages are not run by this library (yet)
            }
            let function = id_op(inst, 1)?;
            let name = match inst.operands.get(2) {
                Some(Operand::LiteralString(s)) => s.clone(),
                _ => return Err(bad(inst, "entry point name")),
            };
            let mut e = EntryPoint { name, function, local_size: [1, 1, 1], local_size_id: None };
            for m in &self.dr.execution_modes {
                if id_op(m, 0)? != function {
                    continue;
                }
                match m.operands.get(1) {
                    Some(Operand::ExecutionMode(spirv::ExecutionMode::LocalSize)) => {
                        e.local_size = [lit(m, 2)?, lit(m, 3)?, lit(m, 4)?];
                    }
                    Some(Operand::ExecutionMode(spirv::ExecutionMode::LocalSizeId)) => {
                        e.local_size_id = Some([id_op(m, 2)?, id_op(m, 3)?, id_op(m, 4)?]);
                    }
                    _ => {}
                }
            }
            self.entry_points.push(e);
        }
        Ok(())
    }
}

struct Scan {
    offsets: HashMap<u32, usize>,
    glsl_ext: Option<u32>,
    /// Literal operands of OpSpecConstantOp VectorShuffle/CompositeExtract/CompositeInsert.
    spec_literals: HashMap<u32, Vec<u32>>,
    /// The words rspirv reads: the module with those literal lists cut to one (see
    /// `spec_op_literals`), or None when nothing had to be cut.
    for_rspirv: Option<Vec<u32>>,
}

/// The raw pass: instruction boundaries, word offsets, and the support checks.
fn scan(words: &[u32]) -> Result<Scan, ShaderError> {
    let malformed = |offset, reason: &str| ShaderError::Malformed { offset, reason: reason.into() };
    if words.len() < 5 || words[0] != spirv::MAGIC_NUMBER {
        return Err(malformed(0, "not a SPIR-V module (magic number)"));
    }
    if words[1] > 0x0001_0600 {
        return Err(malformed(1, "SPIR-V version above 1.6"));
    }
    let mut s = Scan { offsets: HashMap::new(), glsl_ext: None, spec_literals: HashMap::new(), for_rspirv: None };
    let mut at = 5;
    while at < words.len() {
        let count = (words[at] >> 16) as usize;
        let code = words[at] & 0xFFFF;
        if count == 0 || at + count > words.len() {
            return Err(malformed(at, "bad instruction word count"));
        }
        let operands = &words[at + 1..at + count];
        let op = Op::from_u32(code).filter(|op| OPCODES.contains(op));
        let Some(op) = op else {
            let name = rspirv::grammar::INSTRUCTION_TABLE
                .lookup_opcode(code)
                .map_or_else(|| format!("opcode {code}"), |g| format!("Op{}", g.opname));
            return Err(ShaderError::UnsupportedOpcode { opcode: name, offset: at });
        };
        check_instruction(op, operands, at, &mut s)?;
        if op == Op::SpecConstantOp {
            check_spec_op(&words[at..at + count], at)?;
            spec_op_literals(words, at, &mut s);
        }
        if let Some(g) = rspirv::grammar::INSTRUCTION_TABLE.lookup_opcode(code) {
            let pos = match g.operands.first().map(|o| o.kind) {
                Some(rspirv::grammar::OperandKind::IdResultType) => Some(1),
                Some(rspirv::grammar::OperandKind::IdResult) => Some(0),
                _ => None,
            };
            if let Some(&id) = pos.and_then(|p| operands.get(p)) {
                s.offsets.insert(id, at);
            }
        }
        at += count;
    }
    Ok(s)
}

/// OpSpecConstantOp wraps only what specialization folds (the composite opcodes and the ALU
/// ones; anything else fails there anyway): rspirv 0.13's parser panics on some other opcodes
/// (operand kinds it cannot read inside OpSpecConstantOp), so they are refused before it runs.
fn check_spec_op(inst: &[u32], at: usize) -> Result<(), ShaderError> {
    let Some(&code) = inst.get(3) else {
        return Err(ShaderError::Malformed { offset: at, reason: "OpSpecConstantOp without an opcode".into() });
    };
    let folded = Op::from_u32(code).is_some_and(|op| matches!(op, Op::VectorShuffle | Op::CompositeExtract | Op::CompositeInsert | Op::Select) || super::lower_ops::alu_of(op).is_some());
    if !folded {
        let name = rspirv::grammar::INSTRUCTION_TABLE.lookup_opcode(code).map_or_else(|| format!("opcode {code}"), |g| format!("Op{}", g.opname));
        return Err(ShaderError::Unsupported { what: format!("OpSpecConstantOp of {name}"), offset: at });
    }
    Ok(())
}

/// rspirv 0.13 reads each operand of the opcode nested in OpSpecConstantOp once, so a
/// VectorShuffle with several components or a CompositeExtract/Insert with several indices
/// fails to load (glslang emits these for swizzles of specialization-constant vectors). The
/// literals are kept here and rspirv gets a copy of the module with each list cut to one.
fn spec_op_literals(words: &[u32], at: usize, s: &mut Scan) {
    let count = (words[at] >> 16) as usize;
    let inst = &words[at..at + count];
    let ids = match inst.get(3).copied().and_then(Op::from_u32) {
        Some(Op::VectorShuffle | Op::CompositeInsert) => 2,
        Some(Op::CompositeExtract) => 1,
        _ => return,
    };
    let (Some(&result), Some(literals)) = (inst.get(2), inst.get(4 + ids..)) else { return };
    s.spec_literals.insert(result, literals.to_vec());
    if literals.len() > 1 {
        let copy = s.for_rspirv.get_or_insert_with(|| words.to_vec());
        let cut = 4 + ids + 1;
        let start = at - (words.len() - copy.len()); // earlier cuts shrank the copy
        copy[start] = ((cut as u32) << 16) | (Op::SpecConstantOp as u32);
        copy.drain(start + cut..start + count);
    }
}

fn check_instruction(op: Op, operands: &[u32], at: usize, s: &mut Scan) -> Result<(), ShaderError> {
    match op {
        Op::Capability => {
            let code = operands.first().copied().unwrap_or(u32::MAX);
            let cap = Capability::from_u32(code);
            if !cap.is_some_and(|c| CAPABILITIES.contains(&c)) {
                let capability = cap.map_or_else(|| format!("capability {code}"), |c| format!("{c:?}"));
                return Err(ShaderError::UnsupportedCapability { capability, offset: at });
            }
        }
        Op::Extension | Op::ExtInstImport => {
            let skip = usize::from(op == Op::ExtInstImport);
            let name = literal_string(operands.get(skip..).unwrap_or(&[]));
            if op == Op::ExtInstImport {
                if name == "GLSL.std.450" {
                    s.glsl_ext = operands.first().copied();
                } else if !name.starts_with("NonSemantic.") {
                    return Err(ShaderError::UnsupportedExtension { name, offset: at });
                }
            } else if !EXTENSIONS.contains(&name.as_str()) {
                return Err(ShaderError::UnsupportedExtension { name, offset: at });
            }
        }
        Op::ExtInst => {
            let (set, number) = (operands.get(2).copied(), operands.get(3).copied().unwrap_or(0));
            if set.is_some() && set == s.glsl_ext && !GLSL_SUPPORTED.contains(&number) {
                return Err(ShaderError::UnsupportedExtInst { set: "GLSL.std.450".into(), number, offset: at });
            }
        }
        Op::MemoryModel => {
            let addressing = operands.first().copied().unwrap_or(u32::MAX);
            // Logical (0) or PhysicalStorageBuffer64 (5348).
            if addressing != 0 && addressing != 5348 {
                return Err(ShaderError::Unsupported { what: format!("addressing model {addressing}"), offset: at });
            }
        }
        _ => {}
    }
    Ok(())
}

/// OpTypeImage operands: sampled type, Dim, Depth, Arrayed, MS, Sampled, Format. Only storage
/// images (Sampled = 2, single-sampled) of Dim 1D/2D/3D and texel buffers are run.
fn image_type(inst: &Instruction, offset: usize) -> Result<Type, ShaderError> {
    let dim = match inst.operands.get(1) {
        Some(Operand::Dim(d)) => *d,
        _ => return Err(bad(inst, "operand 1 (expected a Dim)")),
    };
    let (arrayed, ms, sampled) = (lit(inst, 3)?, lit(inst, 4)?, lit(inst, 5)?);
    // Texel buffers: storage (Sampled 2) and uniform (Sampled 1, read by OpImageFetch).
    let texel_buffer = dim == spirv::Dim::DimBuffer && arrayed == 0 && ms == 0 && (sampled == 1 || sampled == 2);
    let storage = matches!(dim, spirv::Dim::Dim1D | spirv::Dim::Dim2D | spirv::Dim::Dim3D) && ms == 0 && sampled == 2 && !(arrayed != 0 && dim == spirv::Dim::Dim3D);
    if !(texel_buffer || storage) {
        let what = format!("image type (Dim {dim:?}, arrayed {arrayed}, MS {ms}, Sampled {sampled}): only single-sampled 1D/2D/3D storage images and texel buffers");
        return Err(ShaderError::Unsupported { what, offset });
    }
    Ok(Type::Image { sampled: id_op(inst, 0)?, dim, arrayed: arrayed != 0 })
}

fn literal_string(words: &[u32]) -> String {
    let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).take_while(|&b| b != 0).collect();
    String::from_utf8_lossy(&bytes).into_owned()
}

fn bad(inst: &Instruction, what: &str) -> ShaderError {
    ShaderError::Malformed { offset: 0, reason: format!("Op{}: bad {what}", inst.class.opname) }
}

/// The `k`-th operand as an id.
pub(crate) fn id_op(inst: &Instruction, k: usize) -> Result<u32, ShaderError> {
    match inst.operands.get(k) {
        Some(Operand::IdRef(v)) | Some(Operand::IdScope(v)) | Some(Operand::IdMemorySemantics(v)) => Ok(*v),
        _ => Err(bad(inst, &format!("operand {k} (expected an id)"))),
    }
}

/// The `k`-th operand as a 32-bit literal.
pub(crate) fn lit(inst: &Instruction, k: usize) -> Result<u32, ShaderError> {
    match inst.operands.get(k) {
        Some(Operand::LiteralBit32(v)) | Some(Operand::LiteralExtInstInteger(v)) => Ok(*v),
        _ => Err(bad(inst, &format!("operand {k} (expected a literal)"))),
    }
}

pub(crate) fn storage_class(inst: &Instruction, k: usize) -> Result<StorageClass, ShaderError> {
    match inst.operands.get(k) {
        Some(Operand::StorageClass(c)) => Ok(*c),
        _ => Err(bad(inst, &format!("operand {k} (expected a storage class)"))),
    }
}

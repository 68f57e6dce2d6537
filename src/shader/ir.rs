//! Arbor's shader IR: what `lower` produces and `exec` runs.
//!
//! A [`Program`] is one entry point with every call inlined: a list of [`Block`]s in structured
//! order (SPIR-V's block order, which puts dominators first and a construct's blocks before its
//! merge block), each a flat list of [`Op`]s over typed virtual registers and one [`Term`].
//! Composite values do not exist here: `lower` flattens vectors, structs and arrays into their
//! scalar components, so extract/insert/shuffle/copy-logical cost nothing at run time. Memory is
//! bytes: every pointer is a register holding a byte address in one [`Space`], computed with
//! explicit offset arithmetic from the SPIR-V layout decorations.
//!
//! A register holds one 64-bit word per lane; the scalar type of an op says how to read it
//! (`I32`/`F32` values live in the low 32 bits, upper bits zero; `Bool` is 0 or 1).

/// A virtual register: an index into the lane group's register file.
pub type Reg = u32;

/// Scalar types of register contents.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Sc {
    Bool,
    I32,
    I64,
    F32,
    F64,
}

impl Sc {
    /// Size in bytes when stored in memory (Bool is stored as a 32-bit word).
    pub fn size(self) -> u32 {
        match self {
            Sc::Bool | Sc::I32 | Sc::F32 => 4,
            Sc::I64 | Sc::F64 => 8,
        }
    }
    pub fn bits(self) -> u32 {
        match self {
            Sc::Bool => 1,
            _ => self.size() * 8,
        }
    }
}

/// Where a pointer register's address points.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Space {
    /// Per-invocation memory: built-in inputs, Private and Function variables.
    Lane,
    /// The workgroup's shared memory.
    Workgroup,
    /// The push-constant block.
    Push,
    /// A descriptor binding: index into [`Program::bindings`], resolved once per dispatch. For
    /// an array of descriptors the address carries the array element above
    /// [`ELEMENT_SHIFT`] (the element's byte offset below it).
    Buffer(u16),
    /// PhysicalStorageBuffer64: the register holds a device address.
    Physical,
    /// An array of acceleration-structure descriptors, `Program::accel_arrays[slot]`: the
    /// address is element * 8 and a load gives that element's structure address.
    Accel(u16),
    /// A texel of storage image (or texel buffer) `Program::images[slot]`, from
    /// OpImageTexelPointer: the register holds the texel's byte offset in the view (from
    /// [`Op::ImageTexel`]; the array element above [`ELEMENT_SHIFT`], all ones below it for a
    /// coordinate outside the view).
    Image(u16),
}

/// Bit where the array element of a descriptor-array address starts (`Space::Buffer`):
/// 2^40 bytes per element is beyond any buffer range Arbor reports, so offset arithmetic stays
/// inside its element unless it goes out of bounds anyway.
pub const ELEMENT_SHIFT: u32 = 40;

/// Two-operand ALU ops. Signedness lives in the op, width in the [`Sc`] it is applied to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BinOp {
    IAdd, ISub, IMul, UDiv, SDiv, UMod, SRem, SMod,
    Shl, ShrL, ShrA, And, Or, Xor,
    IEq, INe, ULt, ULe, UGt, UGe, SLt, SLe, SGt, SGe,
    FAdd, FSub, FMul, FDiv, FRem, FMod,
    FOrdEq, FOrdNe, FOrdLt, FOrdLe, FOrdGt, FOrdGe,
    FUnordEq, FUnordNe, FUnordLt, FUnordLe, FUnordGt, FUnordGe,
    LEq, LNe, LAnd, LOr,
    FMin, FMax, NMin, NMax, UMin, UMax, SMin, SMax,
    Pow, Atan2, Step, Ldexp,
    /// High half of the full-width unsigned / signed product (OpUMulExtended, OpSMulExtended).
    UMulHi, SMulHi,
    /// Carry out of an unsigned add, borrow out of an unsigned subtract.
    AddCarry, SubBorrow,
}

/// One-operand ALU ops, including conversions (`from` is the source type; the op's `Sc` is
/// the destination type).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UnOp {
    SNeg, FNeg, Not, LNot,
    /// Reinterpret bits (same width) or zero-/sign-extend/truncate integers.
    Bitcast, UConvert, SConvert, FConvert,
    ConvertFToU, ConvertFToS, ConvertUToF, ConvertSToF,
    IsNan, IsInf,
    FAbs, SAbs, FSign, SSign, Floor, Ceil, Trunc, Round, RoundEven, Fract,
    Sqrt, InverseSqrt, Exp, Log, Exp2, Log2,
    Sin, Cos, Tan, Asin, Acos, Atan, Sinh, Cosh, Tanh, Asinh, Acosh, Atanh,
    Radians, Degrees,
    FindILsb, FindSMsb, FindUMsb, BitCount, BitReverse,
}

/// Three-operand ALU ops.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TriOp {
    Fma, FClamp, NClamp, UClamp, SClamp, FMix, SmoothStep,
    /// (base, offset, count); OpBitFieldInsert has four operands and is [`Op::BitInsert`].
    BitFieldUExtract, BitFieldSExtract,
}

/// Atomic read-modify-write operations.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AtomicOp {
    Exchange, CompareExchange, IAdd, ISub, SMin, UMin, SMax, UMax, And, Or, Xor,
}

/// Subgroup (lane group) operations; the subgroup is the lane group, its size `LANES`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SgOp {
    Elect,
    All,
    Any,
    AllEqual,
    /// Value of the lane whose index is in `b` (uniform across the active lanes).
    Broadcast,
    BroadcastFirst,
    /// Value of lane `b[l]` (OpGroupNonUniformShuffle); Xor/Up/Down compute the source lane
    /// from the lane's own index.
    Shuffle,
    ShuffleXor,
    ShuffleUp,
    ShuffleDown,
    Reduce(BinOp),
    InclusiveScan(BinOp),
    ExclusiveScan(BinOp),
}

#[derive(Clone, Debug, PartialEq)]
pub enum Op {
    Mov { dst: Reg, src: Reg },
    Un { op: UnOp, ty: Sc, from: Sc, dst: Reg, a: Reg },
    Bin { op: BinOp, ty: Sc, dst: Reg, a: Reg, b: Reg },
    Tri { op: TriOp, ty: Sc, dst: Reg, a: Reg, b: Reg, c: Reg },
    /// OpBitFieldInsert: dst = base with `count` bits at `offset` replaced by `insert`'s low bits.
    BitInsert { ty: Sc, dst: Reg, base: Reg, insert: Reg, offset: Reg, count: Reg },
    Select { dst: Reg, cond: Reg, a: Reg, b: Reg },
    /// dst = base + index * stride, index of type `index_ty` sign-extended (SPIR-V indices are
    /// signed), all in 64-bit wrapping arithmetic.
    Index { dst: Reg, base: Reg, index: Reg, index_ty: Sc, stride: u64 },
    /// dst = base + imm (64-bit wrapping): constant struct-member and array offsets.
    AddImm { dst: Reg, a: Reg, imm: u64 },
    Load { ty: Sc, space: Space, dst: Reg, addr: Reg },
    Store { ty: Sc, space: Space, addr: Reg, src: Reg },
    /// dst = old value; `b` is the comparator of CompareExchange.
    Atomic { op: AtomicOp, ty: Sc, space: Space, dst: Reg, addr: Reg, a: Reg, b: Reg },
    /// A subgroup op over the lanes in the mask: value `a`, lane index / delta / mask `b`.
    Subgroup { op: SgOp, ty: Sc, dst: Reg, a: Reg, b: Reg },
    /// Ballot results as four words: dst[0..4] from the predicate `a`.
    Ballot { dst: [Reg; 4], a: Reg },
    /// Operations on a ballot (four words): InverseBallot / BitExtract / BitCount / FindLSB /
    /// FindMSB.
    BallotOp { op: BallotOp, dst: Reg, ballot: [Reg; 4], b: Reg },
    /// OpImageRead of storage image `image` (index into [`Program::images`]) at `coord`
    /// (x, y, z, layer; I32, unused ones a zero constant): `n` components of type `ty` (I32 or
    /// F32) into `dst`, the texel converted from the view's format.
    /// `index` holds the element of an array of images (a zero constant for a single one).
    ImageRead { image: u16, index: Reg, ty: Sc, n: u8, dst: [Reg; 4], coord: [Reg; 4] },
    /// OpImageWrite: `src` (four components of `ty`) converted to the view's format.
    ImageWrite { image: u16, index: Reg, ty: Sc, coord: [Reg; 4], src: [Reg; 4] },
    /// OpImageQuerySize: width, height, depth, layers of the view, those of the image's
    /// dimensionality (`dims`: which of them, in order) into `dst`.
    ImageSize { image: u16, index: Reg, n: u8, dims: [u8; 4], dst: [Reg; 4] },
    /// OpImageTexelPointer: the byte offset of the texel at `coord` in storage image `image`
    /// (a `Space::Image` address, the array element above [`ELEMENT_SHIFT`]).
    ImageTexel { image: u16, index: Reg, dst: Reg, coord: [Reg; 4] },
    /// A ray-query instruction (boxed: rare, and larger than every other op).
    RayQuery(Box<RayQueryOp>),
}

impl Op {
    /// The registers the op writes.
    pub fn defs(&self) -> Vec<Reg> {
        match self {
            Op::Mov { dst, .. } | Op::Un { dst, .. } | Op::Bin { dst, .. } | Op::Tri { dst, .. } | Op::BitInsert { dst, .. } | Op::Select { dst, .. } => vec![*dst],
            Op::Index { dst, .. } | Op::AddImm { dst, .. } | Op::Load { dst, .. } | Op::Atomic { dst, .. } | Op::Subgroup { dst, .. } | Op::BallotOp { dst, .. } | Op::ImageTexel { dst, .. } => vec![*dst],
            Op::Ballot { dst, .. } => dst.to_vec(),
            Op::ImageRead { dst, n, .. } => dst[..*n as usize].to_vec(),
            Op::ImageSize { dst, .. } => dst.to_vec(),
            Op::RayQuery(rq) => rq.dst.clone(),
            Op::Store { .. } | Op::ImageWrite { .. } => vec![],
        }
    }
}

/// One `OpRayQuery*` instruction. `query` holds the lane-frame address of the ray-query
/// variable, which is the query's identity: the executor keeps each lane's traversal state
/// keyed by it.
#[derive(Clone, Debug, PartialEq)]
pub struct RayQueryOp {
    pub kind: RqKind,
    pub query: Reg,
    /// Initialize: structure address (I64), flags, cull mask, origin xyz, tmin, direction xyz,
    /// tmax. GenerateIntersection: t. Others: none.
    pub args: Vec<Reg>,
    /// Proceed: the Bool result. Getters: the result's scalars in component order.
    pub dst: Vec<Reg>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RqKind {
    Initialize,
    Proceed,
    Terminate,
    Confirm,
    Generate,
    /// A getter; `committed` selects the committed or the candidate intersection (ignored by
    /// the getters of the ray itself: tmin, flags, world origin/direction).
    Get { value: RqValue, committed: bool },
}

/// What a ray-query getter returns.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RqValue {
    Type,
    T,
    TMin,
    RayFlags,
    WorldRayOrigin,
    WorldRayDirection,
    InstanceCustomIndex,
    InstanceId,
    SbtRecordOffset,
    GeometryIndex,
    PrimitiveIndex,
    Barycentrics,
    FrontFace,
    CandidateAabbOpaque,
    ObjectRayOrigin,
    ObjectRayDirection,
    /// 4 columns of 3 floats (column-major mat4x3).
    ObjectToWorld,
    WorldToObject,
    /// Three vertices of 3 floats (VK_KHR_ray_tracing_position_fetch).
    TriangleVertexPositions,
    /// The hit cluster's ID, -1 for other geometry (SPV_NV_cluster_acceleration_structure).
    ClusterId,
}

impl RqValue {
    /// Scalars in the result.
    pub fn count(self) -> usize {
        match self {
            RqValue::Barycentrics => 2,
            RqValue::WorldRayOrigin | RqValue::WorldRayDirection | RqValue::ObjectRayOrigin | RqValue::ObjectRayDirection => 3,
            RqValue::TriangleVertexPositions => 9,
            RqValue::ObjectToWorld | RqValue::WorldToObject => 12,
            _ => 1,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BallotOp {
    Inverse,
    BitExtract,
    BitCountReduce,
    BitCountInclusive,
    BitCountExclusive,
    FindLsb,
    FindMsb,
}

/// How a block ends. Targets are block indices.
#[derive(Clone, Debug, PartialEq)]
pub enum Term {
    Jump(u32),
    Cond { cond: Reg, t: u32, f: u32 },
    /// Selector of type `ty`; cases compare the selector's bits.
    Switch { sel: Reg, default: u32, cases: Vec<(u64, u32)> },
    /// The lane is done (return from the entry point, OpUnreachable, OpKill).
    Exit,
    /// OpControlBarrier at workgroup scope: wait until every invocation of the workgroup has
    /// arrived (or exited), then continue at the block.
    Barrier(u32),
}

/// A basic block. `phi_in` copies phi temporaries into the phi registers when the block starts;
/// `edge_moves` fill those temporaries for lanes leaving by the edge to `target`. Going through
/// temporaries gives OpPhi its parallel-copy semantics.
#[derive(Clone, Debug, PartialEq)]
pub struct Block {
    pub ops: Vec<Op>,
    pub term: Term,
    pub phi_in: Vec<(Reg, Reg)>,
    pub edge_moves: Vec<EdgeMove>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EdgeMove {
    pub target: u32,
    pub dst: Reg,
    pub src: Reg,
}

/// Offsets of the built-in inputs at the start of every lane's frame (bytes).
pub mod builtin_offset {
    pub const GLOBAL_INVOCATION_ID: u32 = 0;
    pub const LOCAL_INVOCATION_ID: u32 = 12;
    pub const WORKGROUP_ID: u32 = 24;
    pub const NUM_WORKGROUPS: u32 = 36;
    pub const LOCAL_INVOCATION_INDEX: u32 = 48;
    pub const WORKGROUP_SIZE: u32 = 52;
    pub const SUBGROUP_SIZE: u32 = 64;
    pub const SUBGROUP_LOCAL_INVOCATION_ID: u32 = 68;
    pub const SUBGROUP_ID: u32 = 72;
    pub const NUM_SUBGROUPS: u32 = 76;
    /// Subgroup masks (eq, ge, gt, le, lt), each four words.
    pub const SUBGROUP_EQ_MASK: u32 = 80;
    pub const SUBGROUP_GE_MASK: u32 = 96;
    pub const SUBGROUP_GT_MASK: u32 = 112;
    pub const SUBGROUP_LE_MASK: u32 = 128;
    pub const SUBGROUP_LT_MASK: u32 = 144;
    /// Where Private and Function variables start.
    pub const END: u32 = 160;
}

/// One lowered entry point, specialised and ready to run.
#[derive(Clone, Debug)]
pub struct Program {
    pub blocks: Vec<Block>,
    pub reg_count: u32,
    /// Registers that hold constants: filled for every lane when a lane group starts.
    pub consts: Vec<(Reg, u64)>,
    /// Bytes of one lane's frame (built-ins, Private, Function) and its initial contents
    /// (Private initializers); built-ins are written over it per lane.
    pub lane_frame: Vec<u8>,
    pub workgroup_bytes: u32,
    /// Descriptor (set, binding) for each `Space::Buffer` index (and every acceleration
    /// structure descriptor, which is in `accel_bindings` too).
    pub bindings: Vec<(u32, u32)>,
    /// Array length of each `bindings` entry as the shader declares it: 1 for a single
    /// descriptor, 0 for a runtime array (as many elements as the bound set has).
    pub binding_counts: Vec<u32>,
    /// Descriptor (set, binding) of each storage image the image ops name.
    pub images: Vec<(u32, u32)>,
    /// Array length of each `images` entry as declared (1 for a single image, 0 for a
    /// runtime array).
    pub image_counts: Vec<u32>,
    /// Arrays of acceleration-structure descriptors: (set, binding) and the declared length
    /// (0 for a runtime array), by `Space::Accel` slot.
    pub accel_arrays: Vec<((u32, u32), u32)>,
    /// Registers holding the device address of the acceleration structure bound at (set,
    /// binding): resolved once per dispatch, filled for every lane when a lane group starts.
    pub accel_bindings: Vec<(Reg, (u32, u32))>,
}

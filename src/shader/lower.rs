//! One entry point → [`Program`]: control flow, calls, variables and memory access. ALU,
//! composite, atomic and subgroup instructions are in `lower_ops`, ray queries in `lower_rq`.
//!
//! Every call is inlined: the caller's block ends with a jump to the callee's first block, the
//! callee's blocks follow, and its returns jump to a continuation block after them, so the
//! structured order the scheduler relies on survives inlining. Branch targets are SPIR-V labels
//! while a function body is lowered and are patched to block indices when it is done.
//! OpPhi: each phi gets a temporary filled on the incoming edge and copied in at block start.
use std::collections::{HashMap, HashSet};

use rspirv::dr::Instruction;
use spirv::{BuiltIn, Op, StorageClass};

use super::ir::{builtin_offset as bo, Block, EdgeMove, Op as IrOp, Program, Reg, Sc, Space, Term};
use super::layout::Layout;
use super::lower_vars::VarRegs;
use super::parse::{id_op, EntryPoint, Module, Type};
use super::specialize::Constants;
use super::ShaderError;

#[cfg(test)]
#[path = "ifconv_tests.rs"]
mod ifconv_tests;

/// Marks a branch target that means "return to the caller's continuation".
const RET: u32 = u32::MAX;
/// Calls nested deeper than this are rejected (SPIR-V forbids recursion; this bounds a
/// malformed module).
const MAX_INLINE_DEPTH: u32 = 64;

/// A lowered SPIR-V value: scalar registers (composites flattened), or a logical pointer.
/// Physical pointers are values: one I64 register holding the address.
#[derive(Clone, Debug)]
pub enum Val {
    Regs(Vec<Reg>),
    Ptr(Ptr),
    /// A storage image (its variable or a load of it): index into `Program::images`, the
    /// OpTypeImage id (or the array type's, before an array of images is indexed), and the
    /// register holding the array element (a zero constant for a single image).
    Image { slot: u16, ty: u32, index: Reg },
}

#[derive(Clone, Copy, Debug)]
pub struct Ptr {
    pub space: Space,
    pub addr: Reg,
    /// The pointee type id.
    pub pointee: u32,
    /// MatrixStride of the struct member this points into, if any.
    pub matrix_stride: Option<u32>,
}

pub struct Lowered {
    pub program: Program,
    pub push_size: u32,
}

/// State of one inlined function body.
#[derive(Default)]
struct Frame {
    vals: HashMap<u32, Val>,
    /// SPIR-V label → index of its first IR block.
    labels: HashMap<u32, u32>,
    /// SPIR-V label → index of its last IR block (where its terminator and edge moves are).
    label_end: HashMap<u32, u32>,
    /// IR blocks whose terminator targets are still labels.
    unpatched: Vec<u32>,
    /// (target label, predecessor label, temporaries, incoming value id).
    phis: Vec<(u32, u32, Vec<Reg>, u32)>,
    /// Registers a callee's OpReturnValue writes.
    ret: Vec<Reg>,
    entry: bool,
    /// Variables and access chains kept in registers (`lower_vars`), and their registers.
    promoted: HashSet<u32>,
    vars: HashMap<u32, VarRegs>,
}

pub struct Lowerer<'a> {
    pub m: &'a Module,
    pub l: Layout<'a>,
    pub consts: &'a Constants,
    blocks: Vec<Block>,
    ops: Vec<IrOp>,
    phi_in: Vec<(Reg, Reg)>,
    regs: u32,
    const_regs: Vec<(Reg, u64)>,
    const_cache: HashMap<u64, Reg>,
    globals: HashMap<u32, Val>,
    /// Result type of every id in the module.
    types: HashMap<u32, u32>,
    frames: Vec<Frame>,
    lane_frame: Vec<u8>,
    workgroup_bytes: u32,
    pub(super) bindings: Vec<(u32, u32)>,
    /// Declared array length of each `bindings` entry (see `Program::binding_counts`).
    pub(super) binding_counts: Vec<u32>,
    /// Type ids of descriptor arrays of buffers (indexing one steps whole elements).
    pub(super) descriptor_arrays: Vec<u32>,
    pub(super) images: Vec<(u32, u32)>,
    pub(super) image_counts: Vec<u32>,
    accel_bindings: Vec<(Reg, (u32, u32))>,
    pub(super) accel_arrays: Vec<((u32, u32), u32)>,
    push_size: u32,
}

pub fn lower(m: &Module, consts: &Constants, e: &EntryPoint) -> Result<Lowered, ShaderError> {
    lower_with(m, consts, e, true)
}

/// `lower`, with `lower_select`'s if-conversion, merging and rotation only when `simplify`: the
/// tests compare the programs with and without it on the interpreter.
pub(super) fn lower_with(m: &Module, consts: &Constants, e: &EntryPoint, simplify: bool) -> Result<Lowered, ShaderError> {
    let mut lw = Lowerer {
        m,
        l: Layout { m, consts },
        consts,
        blocks: Vec::new(),
        ops: Vec::new(),
        phi_in: Vec::new(),
        regs: 0,
        const_regs: Vec::new(),
        const_cache: HashMap::new(),
        globals: HashMap::new(),
        types: result_types(m),
        frames: Vec::new(),
        lane_frame: vec![0; bo::END as usize],
        workgroup_bytes: 0,
        bindings: Vec::new(),
        binding_counts: Vec::new(),
        descriptor_arrays: Vec::new(),
        images: Vec::new(),
        image_counts: Vec::new(),
        accel_bindings: Vec::new(),
        accel_arrays: Vec::new(),
        push_size: 0,
    };
    lw.inline(e.function, Vec::new(), true)?;
    // A malformed module can leave a branch to a block that was never made (a call or a return
    // where none continues): refuse it here rather than let a lane jump past the last block.
    let n = lw.blocks.len() as u32;
    let inside = |t: &u32| *t < n;
    for b in &lw.blocks {
        let ok = match &b.term {
            Term::Jump(t) | Term::Barrier(t) => inside(t),
            Term::Cond { t, f, .. } => inside(t) && inside(f),
            Term::Switch { default, cases, .. } => inside(default) && cases.iter().all(|(_, t)| inside(t)),
            Term::Exit => true,
        };
        if !ok {
            return Err(m.malformed(e.function, "a branch leads past the function's last block"));
        }
    }
    let bounds = super::lower_select::Bounds { push: lw.push_size, frame: lw.lane_frame.len() as u32 };
    if simplify {
        super::lower_select::simplify(&mut lw.blocks, &mut lw.regs, &mut lw.const_regs, &bounds);
    }
    super::lower_copies::forward(&mut lw.blocks, lw.regs, &lw.const_regs);
    super::lower_copies::thread_jumps(&mut lw.blocks);
    let program = Program {
        blocks: lw.blocks,
        reg_count: lw.regs,
        consts: lw.const_regs,
        lane_frame: lw.lane_frame,
        workgroup_bytes: lw.workgroup_bytes,
        bindings: lw.bindings,
        binding_counts: lw.binding_counts,
        images: lw.images,
        image_counts: lw.image_counts,
        accel_bindings: lw.accel_bindings,
        accel_arrays: lw.accel_arrays,
    };
    Ok(Lowered { program, push_size: lw.push_size })
}

fn result_types(m: &Module) -> HashMap<u32, u32> {
    let functions = m.dr.functions.iter().flat_map(|f| {
        f.parameters.iter().chain(f.blocks.iter().flat_map(|b| b.instructions.iter()))
    });
    m.dr.types_global_values
        .iter()
        .chain(functions)
        .filter_map(|i| Some((i.result_id?, i.result_type?)))
        .collect()
}

impl<'a> Lowerer<'a> {
    pub fn reg(&mut self) -> Reg {
        self.regs += 1;
        self.regs - 1
    }

    pub fn regs_n(&mut self, n: usize) -> Vec<Reg> {
        (0..n).map(|_| self.reg()).collect()
    }

    pub fn emit(&mut self, op: IrOp) {
        self.ops.push(op);
    }

    /// A register holding `v` in every lane (shared between uses; constants are never written).
    pub fn konst(&mut self, v: u64) -> Reg {
        if let Some(&r) = self.const_cache.get(&v) {
            return r;
        }
        let r = self.reg();
        self.const_regs.push((r, v));
        self.const_cache.insert(v, r);
        r
    }

    pub fn err(&self, id: u32, what: impl Into<String>) -> ShaderError {
        ShaderError::Unsupported { what: what.into(), offset: self.m.offset_of(id) }
    }

    /// Ends the current block; returns its index.
    fn end_block(&mut self, term: Term) -> u32 {
        let block = Block {
            ops: std::mem::take(&mut self.ops),
            term,
            phi_in: std::mem::take(&mut self.phi_in),
            edge_moves: Vec::new(),
        };
        self.blocks.push(block);
        self.blocks.len() as u32 - 1
    }

    fn frame(&mut self) -> &mut Frame {
        self.frames.last_mut().expect("lowering always has a frame")
    }

    pub fn define(&mut self, id: u32, v: Val) {
        self.frame().vals.insert(id, v);
    }

    pub(super) fn define_var(&mut self, id: u32, v: VarRegs) {
        self.frame().vars.insert(id, v);
    }

    /// The registers of a promoted variable or access chain.
    pub(super) fn var(&self, id: u32) -> Option<VarRegs> {
        self.frames.last().and_then(|f| f.vars.get(&id)).cloned()
    }

    fn is_promoted(&self, id: u32) -> bool {
        self.frames.last().is_some_and(|f| f.promoted.contains(&id))
    }

    /// The lowered value of `id`: a local, a constant, or a global variable (created on first use).
    pub fn val(&mut self, id: u32) -> Result<Val, ShaderError> {
        if let Some(v) = self.frames.last().and_then(|f| f.vals.get(&id)) {
            return Ok(v.clone());
        }
        if let Some(v) = self.globals.get(&id) {
            return Ok(v.clone());
        }
        let v = if let Some(c) = self.consts.value(id) {
            let c = c.to_vec();
            Val::Regs(c.into_iter().map(|v| self.konst(v)).collect())
        } else if let Some(&i) = self.m.globals.get(&id) {
            let inst = &self.m.dr.types_global_values[i];
            self.global_variable(inst)?
        } else {
            return Err(self.m.malformed(id, "use of an undefined id"));
        };
        self.globals.insert(id, v.clone());
        Ok(v)
    }

    pub fn regs(&mut self, id: u32) -> Result<Vec<Reg>, ShaderError> {
        match self.val(id)? {
            Val::Regs(r) => Ok(r),
            Val::Ptr(_) | Val::Image { .. } => Err(self.m.malformed(id, "a logical pointer or image used as a value")),
        }
    }

    /// The one register of scalar value `id`.
    pub fn reg1(&mut self, id: u32) -> Result<Reg, ShaderError> {
        self.regs(id)?.first().copied().ok_or_else(|| self.m.malformed(id, "expected a scalar value"))
    }

    /// `id` as a pointer: logical pointers directly, physical ones from their address register.
    pub fn ptr(&mut self, id: u32, ty_of_id: Option<u32>) -> Result<Ptr, ShaderError> {
        match self.val(id)? {
            Val::Ptr(p) => Ok(p),
            Val::Image { .. } => Err(self.m.malformed(id, "an image used as a pointer")),
            Val::Regs(r) => {
                let ty = ty_of_id.ok_or_else(|| self.m.malformed(id, "pointer of unknown type"))?;
                match self.m.ty(ty)? {
                    Type::Pointer { class: StorageClass::PhysicalStorageBuffer, pointee } if r.len() == 1 => {
                        Ok(Ptr { space: Space::Physical, addr: r[0], pointee: *pointee, matrix_stride: None })
                    }
                    _ => Err(self.m.malformed(id, "not a pointer")),
                }
            }
        }
    }

    fn global_variable(&mut self, inst: &Instruction) -> Result<Val, ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        if inst.class.opcode != Op::Variable {
            return Err(self.m.malformed(id, "not a constant or variable"));
        }
        let pointee = self.pointee(inst.result_type.unwrap_or(0))?;
        let class = super::parse::storage_class(inst, 0)?;
        let deco = self.m.decorations.get(&id).cloned().unwrap_or_default();
        if class == StorageClass::UniformConstant {
            if let Some(v) = self.accel_array(id, (deco.set.unwrap_or(0), deco.binding.unwrap_or(0)), pointee)? {
                return Ok(v);
            }
        }
        if class == StorageClass::UniformConstant && matches!(self.m.ty(pointee)?, Type::AccelerationStructure) {
            return Ok(self.accel_descriptor(deco.set.unwrap_or(0), deco.binding.unwrap_or(0)));
        }
        if class == StorageClass::UniformConstant {
            return self.image_variable(id, pointee, (deco.set.unwrap_or(0), deco.binding.unwrap_or(0)));
        }
        let (space, addr) = match class {
            StorageClass::StorageBuffer | StorageClass::Uniform => {
                let key = (deco.set.unwrap_or(0), deco.binding.unwrap_or(0));
                (self.buffer_variable(id, key, pointee)?, 0)
            }
            StorageClass::PushConstant => {
                self.push_size = self.push_size.max(self.l.size_align(pointee)?.0);
                (Space::Push, 0)
            }
            StorageClass::Workgroup => {
                let (size, align) = self.l.size_align(pointee)?;
                let at = self.workgroup_bytes.div_ceil(align) * align;
                self.workgroup_bytes = at + size;
                (Space::Workgroup, at)
            }
            StorageClass::Private => {
                let at = self.alloc_lane(pointee)?;
                if let Some(init) = inst.operands.get(1).map(|_| id_op(inst, 1)).transpose()? {
                    self.write_lane_init(at, pointee, init)?;
                }
                (Space::Lane, at)
            }
            StorageClass::Input => (Space::Lane, self.builtin_offset(id, deco.builtin)?),
            other => return Err(self.err(id, format!("variable in storage class {other:?}"))),
        };
        let addr = self.konst(addr as u64);
        Ok(Val::Ptr(Ptr { space, addr, pointee, matrix_stride: None }))
    }

    /// An acceleration-structure descriptor variable: a register the executor fills with the
    /// bound structure's device address, standing for the variable itself (OpLoad of it
    /// yields the same register, since the descriptor cannot change during a dispatch).
    fn accel_descriptor(&mut self, set: u32, binding: u32) -> Val {
        let key = (set, binding);
        if !self.bindings.contains(&key) {
            self.bindings.push(key);
            self.binding_counts.push(1);
        }
        let r = match self.accel_bindings.iter().find(|(_, k)| *k == key) {
            Some(&(r, _)) => r,
            None => {
                let r = self.reg();
                self.accel_bindings.push((r, key));
                r
            }
        };
        Val::Regs(vec![r])
    }

    fn builtin_offset(&self, id: u32, b: Option<BuiltIn>) -> Result<u32, ShaderError> {
        Ok(match b {
            Some(BuiltIn::GlobalInvocationId) => bo::GLOBAL_INVOCATION_ID,
            Some(BuiltIn::LocalInvocationId) => bo::LOCAL_INVOCATION_ID,
            Some(BuiltIn::WorkgroupId) => bo::WORKGROUP_ID,
            Some(BuiltIn::NumWorkgroups) => bo::NUM_WORKGROUPS,
            Some(BuiltIn::LocalInvocationIndex) => bo::LOCAL_INVOCATION_INDEX,
            Some(BuiltIn::WorkgroupSize) => bo::WORKGROUP_SIZE,
            Some(BuiltIn::SubgroupSize) => bo::SUBGROUP_SIZE,
            Some(BuiltIn::SubgroupLocalInvocationId) => bo::SUBGROUP_LOCAL_INVOCATION_ID,
            Some(BuiltIn::SubgroupId) => bo::SUBGROUP_ID,
            Some(BuiltIn::NumSubgroups) => bo::NUM_SUBGROUPS,
            Some(BuiltIn::SubgroupEqMask) => bo::SUBGROUP_EQ_MASK,
            Some(BuiltIn::SubgroupGeMask) => bo::SUBGROUP_GE_MASK,
            Some(BuiltIn::SubgroupGtMask) => bo::SUBGROUP_GT_MASK,
            Some(BuiltIn::SubgroupLeMask) => bo::SUBGROUP_LE_MASK,
            Some(BuiltIn::SubgroupLtMask) => bo::SUBGROUP_LT_MASK,
            other => return Err(self.err(id, format!("input built-in {other:?}"))),
        })
    }

    fn alloc_lane(&mut self, ty: u32) -> Result<u32, ShaderError> {
        // Each invocation gets a copy of the frame: capped like a register value (found by the
        // SPIR-V fuzzer: a 4 GiB function variable aborted the process on allocation).
        const MAX_LANE_BYTES: u64 = 1 << 18;
        let (size, align) = self.l.size_align(ty)?;
        let at = (self.lane_frame.len() as u64).div_ceil(align.max(1) as u64) * align.max(1) as u64;
        let end = Some(at + size as u64).filter(|&e| e <= MAX_LANE_BYTES);
        let end = end.ok_or_else(|| self.err(ty, format!("private and function variables of more than {MAX_LANE_BYTES} bytes per invocation")))?;
        self.lane_frame.resize(end as usize, 0);
        Ok(at as u32)
    }

    fn write_lane_init(&mut self, at: u32, ty: u32, init: u32) -> Result<(), ShaderError> {
        let values = self.consts.value(init).ok_or_else(|| self.err(init, "non-constant initializer"))?.to_vec();
        for ((sc, off), v) in self.l.fields(ty, None)?.into_iter().zip(values) {
            let o = (at + off) as usize;
            self.lane_frame[o..o + sc.size() as usize].copy_from_slice(&v.to_le_bytes()[..sc.size() as usize]);
        }
        Ok(())
    }

    pub fn pointee(&self, ptr_ty: u32) -> Result<u32, ShaderError> {
        match self.m.ty(ptr_ty)? {
            Type::Pointer { pointee, .. } => Ok(*pointee),
            _ => Err(self.m.malformed(ptr_ty, "not a pointer type")),
        }
    }

    /// Address register for `p` plus `off` bytes.
    pub fn offset(&mut self, p: &Ptr, off: u32) -> Reg {
        if off == 0 {
            return p.addr;
        }
        let dst = self.reg();
        self.emit(IrOp::AddImm { dst, a: p.addr, imm: off as u64 });
        dst
    }

    pub fn load(&mut self, p: &Ptr) -> Result<Vec<Reg>, ShaderError> {
        let fields = self.l.fields(p.pointee, p.matrix_stride)?;
        let mut out = Vec::with_capacity(fields.len());
        for (ty, off) in fields {
            let addr = self.offset(p, off);
            let dst = self.reg();
            self.emit(IrOp::Load { ty, space: p.space, dst, addr });
            out.push(dst);
        }
        Ok(out)
    }

    pub fn store(&mut self, p: &Ptr, src: &[Reg]) -> Result<(), ShaderError> {
        let fields = self.l.fields(p.pointee, p.matrix_stride)?;
        if fields.len() != src.len() {
            return Err(self.m.malformed(p.pointee, "store of a value of another type"));
        }
        for ((ty, off), &src) in fields.into_iter().zip(src) {
            let addr = self.offset(p, off);
            self.emit(IrOp::Store { ty, space: p.space, addr, src });
        }
        Ok(())
    }

    /// OpAccessChain / OpPtrAccessChain: explicit byte-offset arithmetic over the layout.
    pub fn access_chain(&mut self, inst: &Instruction, element: bool) -> Result<Ptr, ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let base_id = id_op(inst, 0)?;
        let base_ty = self.type_of(base_id);
        let mut p = self.ptr(base_id, base_ty)?;
        let mut imm = 0u64;
        let mut first = 1;
        if element {
            let ptr_ty = base_ty.ok_or_else(|| self.m.malformed(id, "element pointer of unknown type"))?;
            let stride = self.l.stride(ptr_ty, p.pointee)? as u64;
            p.addr = self.index(p.addr, id_op(inst, 1)?, stride, &mut imm)?;
            first = 2;
        }
        for k in first..inst.operands.len() {
            let idx = id_op(inst, k)?;
            let (next, stride) = match self.m.ty(p.pointee)?.clone() {
                Type::Struct { members } => {
                    let c = self.consts.value(idx).and_then(|v| v.first().copied());
                    let k = c.ok_or_else(|| self.m.malformed(idx, "struct index is not a constant"))? as u32;
                    let member = *members.get(k as usize).ok_or_else(|| self.m.malformed(idx, "member index"))?;
                    imm = imm.wrapping_add(self.l.member_offset(p.pointee, k)? as u64);
                    p.matrix_stride = self.m.member_matrix_stride.get(&(p.pointee, k)).copied();
                    p.pointee = member;
                    continue;
                }
                Type::Array { elem, .. } | Type::RuntimeArray { elem } => match self.descriptor_stride(&p) {
                    Some(stride) => (elem, stride),
                    None => (elem, self.l.stride(p.pointee, elem)? as u64),
                },
                Type::Vector { elem, .. } => (elem, self.l.size_align(elem)?.0 as u64),
                Type::Matrix { column, .. } => {
                    (column, p.matrix_stride.unwrap_or(self.l.size_align(column)?.0) as u64)
                }
                _ => return Err(self.m.malformed(id, "access chain into a scalar")),
            };
            p.addr = self.index(p.addr, idx, stride, &mut imm)?;
            if !matches!(self.m.ty(p.pointee)?, Type::Array { .. } | Type::RuntimeArray { .. }) {
                p.matrix_stride = None;
            }
            p.pointee = next;
        }
        if imm != 0 {
            let dst = self.reg();
            self.emit(IrOp::AddImm { dst, a: p.addr, imm });
            p.addr = dst;
        }
        Ok(p)
    }

    /// Adds `index * stride` to `addr`: folded into `imm` for constants, an Index op otherwise.
    fn index(&mut self, addr: Reg, index: u32, stride: u64, imm: &mut u64) -> Result<Reg, ShaderError> {
        if let Some(&c) = self.consts.value(index).and_then(|v| v.first()) {
            let ty = self.type_of(index).map(|t| self.l.scalar(t)).transpose()?.unwrap_or(Sc::I32);
            let c = if ty == Sc::I32 { c as u32 as i32 as i64 } else { c as i64 };
            *imm = imm.wrapping_add((c as u64).wrapping_mul(stride));
            return Ok(addr);
        }
        let ty = self.type_of(index).ok_or_else(|| self.m.malformed(index, "index of unknown type"))?;
        let index_ty = self.l.scalar(ty)?;
        let reg = self.reg1(index)?;
        let dst = self.reg();
        self.emit(IrOp::Index { dst, base: addr, index: reg, index_ty, stride });
        Ok(dst)
    }

    /// Result type of the instruction defining `id` (constants, globals and locals alike).
    pub fn type_of(&self, id: u32) -> Option<u32> {
        self.types.get(&id).copied()
    }
}

/// Function bodies and control flow.
impl Lowerer<'_> {
    /// Inlines function `fid` at the current point. Returns the registers of its return value.
    fn inline(&mut self, fid: u32, args: Vec<Val>, entry: bool) -> Result<Vec<Reg>, ShaderError> {
        if self.frames.len() as u32 >= MAX_INLINE_DEPTH {
            return Err(self.err(fid, "call depth (recursion?)"));
        }
        let m = self.m;
        let f = m.functions.get(&fid).map(|&i| &m.dr.functions[i]).ok_or_else(|| m.malformed(fid, "no such function"))?;
        if f.parameters.len() != args.len() {
            return Err(m.malformed(fid, "argument count"));
        }
        let mut frame = Frame { entry, promoted: self.promotable(f), ..Frame::default() };
        for (p, a) in f.parameters.iter().zip(args) {
            frame.vals.insert(p.result_id.unwrap_or(0), a);
        }
        let ret_ty = f.def.as_ref().and_then(|d| d.result_type).unwrap_or(0);
        if !matches!(m.ty(ret_ty), Ok(Type::Void)) {
            frame.ret = self.regs_n(self.l.count(ret_ty)?);
        }
        self.frames.push(frame);
        // The caller's pending block falls through to the callee's first block.
        if !entry {
            let next = self.blocks.len() as u32 + 1;
            self.end_block(Term::Jump(next));
        }
        for b in &f.blocks {
            self.lower_block(b)?;
        }
        self.resolve_phis()?;
        let frame = self.frames.pop().expect("pushed above");
        let continuation = self.blocks.len() as u32;
        self.patch(&frame, continuation)?;
        Ok(frame.ret)
    }

    fn patch(&mut self, frame: &Frame, continuation: u32) -> Result<(), ShaderError> {
        let map = |t: u32| -> Result<u32, ShaderError> {
            if t == RET {
                return Ok(continuation);
            }
            frame.labels.get(&t).copied().ok_or_else(|| self.m.malformed(t, "branch to an unknown label"))
        };
        for &b in &frame.unpatched {
            let term = match &self.blocks[b as usize].term {
                Term::Jump(t) => Term::Jump(map(*t)?),
                Term::Cond { cond, t, f } => Term::Cond { cond: *cond, t: map(*t)?, f: map(*f)? },
                Term::Switch { sel, default, cases } => Term::Switch {
                    sel: *sel,
                    default: map(*default)?,
                    cases: cases.iter().map(|&(v, t)| Ok((v, map(t)?))).collect::<Result<_, ShaderError>>()?,
                },
                t => t.clone(),
            };
            self.blocks[b as usize].term = term;
        }
        Ok(())
    }

    /// Fills each phi's temporaries at the end of its predecessors (values may be defined
    /// after the phi, so this runs once the whole body is lowered).
    fn resolve_phis(&mut self) -> Result<(), ShaderError> {
        let phis = std::mem::take(&mut self.frame().phis);
        for (target, pred, temps, src) in phis {
            let f = self.frames.last().expect("inside a function");
            let (Some(&pb), Some(&tb)) = (f.label_end.get(&pred), f.labels.get(&target)) else {
                continue; // an unreachable predecessor never takes the edge
            };
            let src_regs = match self.val(src)? {
                Val::Regs(r) => r,
                Val::Ptr(_) | Val::Image { .. } => return Err(self.err(src, "OpPhi of a logical pointer or image (VariablePointers)")),
            };
            for (&dst, &src) in temps.iter().zip(&src_regs) {
                self.blocks[pb as usize].edge_moves.push(EdgeMove { target: tb, dst, src });
            }
        }
        Ok(())
    }

    fn lower_block(&mut self, b: &rspirv::dr::Block) -> Result<(), ShaderError> {
        let label = b.label.as_ref().and_then(|l| l.result_id).unwrap_or(0);
        let first = self.blocks.len() as u32;
        self.frame().labels.insert(label, first);
        for inst in &b.instructions {
            let id = inst.result_id.unwrap_or(0);
            match inst.class.opcode {
                Op::Phi => {
                    let n = self.l.count(inst.result_type.unwrap_or(0))?;
                    let (dst, temps) = (self.regs_n(n), self.regs_n(n));
                    for (&d, &t) in dst.iter().zip(&temps) {
                        self.phi_in.push((d, t));
                    }
                    for k in (0..inst.operands.len()).step_by(2) {
                        let (v, pred) = (id_op(inst, k)?, id_op(inst, k + 1)?);
                        self.frame().phis.push((label, pred, temps.clone(), v));
                    }
                    self.define(id, Val::Regs(dst));
                }
                Op::LoopMerge | Op::SelectionMerge | Op::Line | Op::NoLine | Op::Nop => {}
                Op::Branch | Op::BranchConditional | Op::Switch | Op::Return | Op::ReturnValue | Op::Unreachable => {
                    let term = self.terminator(inst)?;
                    let labelled = !matches!(term, Term::Exit);
                    let at = self.end_block(term);
                    if labelled {
                        self.frame().unpatched.push(at);
                    }
                    self.frame().label_end.insert(label, at);
                }
                Op::FunctionCall => {
                    let callee = id_op(inst, 0)?;
                    let args = (1..inst.operands.len()).map(|k| self.val(id_op(inst, k)?)).collect::<Result<_, _>>()?;
                    let ret = self.inline(callee, args, false)?;
                    self.define(id, Val::Regs(ret));
                }
                Op::ControlBarrier => {
                    let scope = self.consts.value(id_op(inst, 0)?).and_then(|v| v.first().copied());
                    // Workgroup (2) or wider waits for the workgroup; Subgroup (3) and
                    // Invocation (4) scopes: lanes of a group already run together.
                    if matches!(scope, Some(0..=2)) {
                        let next = self.blocks.len() as u32 + 1;
                        self.end_block(Term::Barrier(next));
                    }
                }
                _ => self.lower_inst(inst)?,
            }
        }
        Ok(())
    }

    fn terminator(&mut self, inst: &Instruction) -> Result<Term, ShaderError> {
        let entry = self.frames.last().is_some_and(|f| f.entry);
        Ok(match inst.class.opcode {
            Op::Branch => Term::Jump(id_op(inst, 0)?),
            Op::BranchConditional => {
                let cond = self.reg1(id_op(inst, 0)?)?;
                Term::Cond { cond, t: id_op(inst, 1)?, f: id_op(inst, 2)? }
            }
            Op::Switch => {
                let sel_id = id_op(inst, 0)?;
                let sel = self.reg1(sel_id)?;
                // Operands: selector, default, then (literal, label) pairs; rspirv decodes a
                // 64-bit selector's literals as one operand each.
                let mut cases = Vec::new();
                for k in (2..inst.operands.len()).step_by(2) {
                    let v = match inst.operands[k] {
                        rspirv::dr::Operand::LiteralBit32(v) => v as u64,
                        rspirv::dr::Operand::LiteralBit64(v) => v,
                        _ => return Err(self.m.malformed(sel_id, "switch literal")),
                    };
                    cases.push((v, id_op(inst, k + 1)?));
                }
                Term::Switch { sel, default: id_op(inst, 1)?, cases }
            }
            Op::Return | Op::Unreachable if entry => Term::Exit,
            Op::Return | Op::Unreachable => Term::Jump(RET),
            Op::ReturnValue if entry => Term::Exit,
            _ => {
                let v = self.regs(id_op(inst, 0)?)?;
                let ret = self.frame().ret.clone();
                for (dst, src) in ret.into_iter().zip(v) {
                    self.emit(IrOp::Mov { dst, src });
                }
                Term::Jump(RET)
            }
        })
    }

    /// Memory and pointer instructions; everything else goes to `lower_ops`.
    fn lower_inst(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let rty = inst.result_type.unwrap_or(0);
        match inst.class.opcode {
            Op::Variable if self.is_promoted(id) => self.promote_variable(inst)?,
            Op::AccessChain | Op::InBoundsAccessChain if self.is_promoted(id) => self.promote_chain(inst)?,
            Op::Load | Op::Store if self.var(id_op(inst, 0)?).is_some() => {
                let v = self.var(id_op(inst, 0)?).expect("checked by the guard");
                if inst.class.opcode == Op::Load {
                    self.load_var(inst, v)?;
                } else {
                    self.store_var(inst, v)?;
                }
            }
            Op::Variable => {
                let pointee = self.pointee(rty)?;
                let at = self.alloc_lane(pointee)?;
                let addr = self.konst(at as u64);
                let p = Ptr { space: Space::Lane, addr, pointee, matrix_stride: None };
                if inst.operands.len() > 1 {
                    let init = self.regs(id_op(inst, 1)?)?;
                    self.store(&p, &init)?;
                }
                self.define(id, Val::Ptr(p));
            }
            // A single structure descriptor is its address register; an element of an array of
            // them is a `Space::Accel` pointer, loaded like memory below.
            Op::Load if matches!(self.m.ty(rty)?, Type::AccelerationStructure) && !matches!(self.val(id_op(inst, 0)?)?, Val::Ptr(_)) => {
                let r = self.regs(id_op(inst, 0)?)?;
                self.define(id, Val::Regs(r));
            }
            Op::Load | Op::CopyObject if matches!(self.val(id_op(inst, 0)?)?, Val::Image { .. }) => {
                let v = self.val(id_op(inst, 0)?)?;
                self.define(id, v);
            }
            Op::ImageRead | Op::ImageFetch | Op::ImageWrite | Op::ImageQuerySize => self.lower_image(inst)?,
            Op::ImageTexelPointer => {
                let p = self.texel_pointer(inst)?;
                self.define(id, Val::Ptr(p));
            }
            Op::Load => {
                let src = id_op(inst, 0)?;
                let p = self.ptr(src, self.type_of(src))?;
                let v = self.load(&p)?;
                self.define(id, Val::Regs(v));
            }
            Op::Store => {
                let dst = id_op(inst, 0)?;
                let p = self.ptr(dst, self.type_of(dst))?;
                let v = self.regs(id_op(inst, 1)?)?;
                self.store(&p, &v)?;
            }
            Op::CopyMemory => {
                let (dst, src) = (id_op(inst, 0)?, id_op(inst, 1)?);
                let (pd, ps) = (self.ptr(dst, self.type_of(dst))?, self.ptr(src, self.type_of(src))?);
                let v = self.load(&ps)?;
                self.store(&pd, &v)?;
            }
            Op::AccessChain | Op::InBoundsAccessChain if matches!(self.val(id_op(inst, 0)?)?, Val::Image { .. }) => {
                let v = self.image_element(inst)?;
                self.define(id, v);
            }
            Op::AccessChain | Op::InBoundsAccessChain | Op::PtrAccessChain => {
                let p = self.access_chain(inst, inst.class.opcode == Op::PtrAccessChain)?;
                let v = if self.l.is_physical_pointer(rty) { Val::Regs(vec![p.addr]) } else { Val::Ptr(p) };
                self.define(id, v);
            }
            Op::ConvertUToPtr | Op::ConvertPtrToU => {
                let src = id_op(inst, 0)?;
                let r = self.regs(src)?;
                self.define(id, Val::Regs(r));
            }
            Op::ExtInst if Some(id_op(inst, 0)?) != self.m.glsl_ext => {} // non-semantic info
            op if super::lower_rq::is_ray_query(op) => self.lower_ray_query(inst)?,
            _ => self.lower_op(inst)?,
        }
        Ok(())
    }
}

//! Storage images and texel buffers in lowering: a UniformConstant image variable becomes [`Val::Image`] (a slot
//! in `Program::images`), and OpImageRead / OpImageWrite / OpImageQuerySize become the IR's
//! image ops with the coordinate spread into (x, y, z, layer) by the image's Dim and Arrayed.
use rspirv::dr::Instruction;
use spirv::{Dim, Op};

use super::ir::{Op as IrOp, Reg, Sc, Space};
use super::lower::{Lowerer, Ptr, Val};
use super::parse::{id_op, Type};
use super::ShaderError;

impl Lowerer<'_> {
    /// The value of a UniformConstant variable: a storage image or texel buffer, or an array
    /// of them (sized or runtime; indexed by `image_element`). Samplers and sampled images
    /// are not run.
    pub(super) fn image_variable(&mut self, id: u32, pointee: u32, key: (u32, u32)) -> Result<Val, ShaderError> {
        let (elem, count) = match self.m.ty(pointee)? {
            Type::Array { elem, len } => (*elem, self.consts.value(*len).and_then(|v| v.first().copied()).unwrap_or(0) as u32),
            Type::RuntimeArray { elem } => (*elem, 0),
            _ => (pointee, 1),
        };
        if !matches!(self.m.ty(elem), Ok(Type::Image { .. })) || (count == 0 && !matches!(self.m.ty(pointee)?, Type::RuntimeArray { .. })) {
            return Err(self.err(id, "UniformConstant variable that is not a storage image, a texel buffer or an array of them"));
        }
        let slot = match self.images.iter().position(|&b| b == key) {
            Some(s) => s,
            None => {
                self.images.push(key);
                self.image_counts.push(count);
                self.images.len() - 1
            }
        };
        let index = self.konst(0);
        Ok(Val::Image { slot: slot as u16, ty: pointee, index })
    }

    /// OpAccessChain into an array of images: the element's image, its index a register.
    pub(super) fn image_element(&mut self, inst: &Instruction) -> Result<Val, ShaderError> {
        let base = id_op(inst, 0)?;
        let Val::Image { slot, ty, .. } = self.val(base)? else {
            return Err(self.m.malformed(base, "not an image"));
        };
        let elem = match self.m.ty(ty)? {
            Type::Array { elem, .. } | Type::RuntimeArray { elem } if inst.operands.len() == 2 => *elem,
            _ => return Err(self.m.malformed(base, "access chain into an image that is not one index into an array of images")),
        };
        let idx = id_op(inst, 1)?;
        let reg = self.reg1(idx)?;
        // Indices are signed 32-bit (or 64-bit) integers; the executor reads the low 32 bits
        // as unsigned, so a negative index is past the end like any other.
        Ok(Val::Image { slot, ty: elem, index: reg })
    }

    pub(super) fn lower_image(&mut self, inst: &Instruction) -> Result<(), ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let img_id = id_op(inst, 0)?;
        let Val::Image { slot, ty, index } = self.val(img_id)? else {
            return Err(self.m.malformed(img_id, "image operand is not a storage image"));
        };
        let Type::Image { dim, arrayed, .. } = self.m.ty(ty)?.clone() else {
            return Err(self.m.malformed(img_id, "image operand is not a storage image"));
        };
        let zero = self.konst(0);
        match inst.class.opcode {
            // OpImageFetch of a uniform texel buffer reads like OpImageRead (no sampler, no
            // level: the image operands a buffer fetch may carry are none).
            Op::ImageRead | Op::ImageFetch => {
                let out = self.l.components(inst.result_type.unwrap_or(0))?;
                let ty = texel_type(self, id, &out)?;
                let coord = self.coordinate(id_op(inst, 1)?, dim, arrayed, zero)?;
                let regs = self.regs_n(out.len());
                let mut dst = [zero; 4];
                dst[..regs.len()].copy_from_slice(&regs);
                self.emit(IrOp::ImageRead { image: slot, index, ty, n: out.len() as u8, dst, coord });
                self.define(id, Val::Regs(regs));
            }
            Op::ImageWrite => {
                let coord = self.coordinate(id_op(inst, 1)?, dim, arrayed, zero)?;
                let texel_id = id_op(inst, 2)?;
                let comps = self.type_of(texel_id).map(|t| self.l.components(t)).transpose()?.unwrap_or_default();
                let ty = texel_type(self, texel_id, &comps)?;
                let regs = self.regs(texel_id)?;
                let mut src = [zero; 4];
                src[..regs.len().min(4)].copy_from_slice(&regs[..regs.len().min(4)]);
                self.emit(IrOp::ImageWrite { image: slot, index, ty, coord, src });
            }
            _ => {
                // OpImageQuerySize: width[, height][, depth][, layers].
                let dims: &[u8] = match (dim, arrayed) {
                    (Dim::Dim1D | Dim::DimBuffer, false) => &[0],
                    (Dim::Dim1D, true) => &[0, 3],
                    (Dim::Dim2D, false) => &[0, 1],
                    (Dim::Dim2D, true) => &[0, 1, 3],
                    _ => &[0, 1, 2],
                };
                let out = self.l.components(inst.result_type.unwrap_or(0))?;
                if out.len() != dims.len() || out.iter().any(|&s| s != Sc::I32) {
                    return Err(self.m.malformed(id, "OpImageQuerySize result does not match the image's dimensions"));
                }
                let regs = self.regs_n(out.len());
                let (mut dst, mut d) = ([zero; 4], [0u8; 4]);
                dst[..regs.len()].copy_from_slice(&regs);
                d[..dims.len()].copy_from_slice(dims);
                self.emit(IrOp::ImageSize { image: slot, index, n: dims.len() as u8, dims: d, dst });
                self.define(id, Val::Regs(regs));
            }
        }
        Ok(())
    }

    /// OpImageTexelPointer: a `Space::Image` pointer to one texel (for image atomics), its
    /// address the texel's offset in the view as the executor computes it.
    pub(super) fn texel_pointer(&mut self, inst: &Instruction) -> Result<Ptr, ShaderError> {
        let id = inst.result_id.unwrap_or(0);
        let img_id = id_op(inst, 0)?;
        let Val::Image { slot, ty, index } = self.val(img_id)? else {
            return Err(self.m.malformed(img_id, "OpImageTexelPointer of something that is not a storage image"));
        };
        let Type::Image { dim, arrayed, .. } = self.m.ty(ty)?.clone() else {
            return Err(self.m.malformed(img_id, "OpImageTexelPointer of something that is not a storage image"));
        };
        let zero = self.konst(0);
        let coord = self.coordinate(id_op(inst, 1)?, dim, arrayed, zero)?;
        let pointee = self.pointee(inst.result_type.unwrap_or(0))?;
        if !matches!(self.m.ty(pointee)?, Type::Int { bits: 32, .. }) {
            return Err(self.err(id, "image atomics on texels other than 32-bit integers"));
        }
        let dst = self.reg();
        self.emit(IrOp::ImageTexel { image: slot, index, dst, coord });
        Ok(Ptr { space: Space::Image(slot), addr: dst, pointee, matrix_stride: None })
    }

    /// The coordinate operand as (x, y, z, layer), missing ones `zero`.
    fn coordinate(&mut self, id: u32, dim: Dim, arrayed: bool, zero: Reg) -> Result<[Reg; 4], ShaderError> {
        let c = self.regs(id)?;
        let n = match dim {
            Dim::Dim1D | Dim::DimBuffer => 1,
            Dim::Dim2D => 2,
            _ => 3,
        };
        if c.len() != n + usize::from(arrayed) {
            return Err(self.m.malformed(id, "image coordinate has the wrong number of components"));
        }
        let mut out = [zero; 4];
        out[..n].copy_from_slice(&c[..n]);
        if arrayed {
            out[3] = c[n];
        }
        Ok(out)
    }
}

/// The component type of a texel value: 32-bit integer or float, 1 to 4 components.
fn texel_type(lw: &Lowerer, id: u32, comps: &[Sc]) -> Result<Sc, ShaderError> {
    match comps.first() {
        Some(&t @ (Sc::I32 | Sc::F32)) if comps.len() <= 4 && comps.iter().all(|&c| c == t) => Ok(t),
        _ => Err(lw.err(id, "image texel that is not 1-4 components of 32-bit int or float")),
    }
}

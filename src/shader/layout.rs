//! Types as registers and as bytes: how a SPIR-V type flattens into scalar registers, and where
//! each scalar lives in memory (Offset/ArrayStride/MatrixStride decorations where present,
//! otherwise a natural packed layout for memory only Arbor sees: Private, Function, Workgroup).
use super::ir::Sc;
use super::parse::{Module, Type};
use super::specialize::Constants;
use super::ShaderError;

/// Nested types deeper than this are rejected (a malformed module could loop otherwise).
const MAX_DEPTH: u32 = 32;
/// Scalars in one register value (a whole-composite load, store or constant): far above what
/// real shaders hold, and a bound on what a malformed array length can make lowering allocate.
const MAX_SCALARS: usize = 1 << 16;

pub struct Layout<'a> {
    pub m: &'a Module,
    pub consts: &'a Constants,
}

impl Layout<'_> {
    /// The register type of a scalar (or physical pointer, held as a 64-bit address).
    pub fn scalar(&self, ty: u32) -> Result<Sc, ShaderError> {
        Ok(match self.m.ty(ty)? {
            Type::Bool => Sc::Bool,
            Type::Int { bits: 64, .. } => Sc::I64,
            Type::Int { .. } => Sc::I32,
            Type::Float { bits: 64 } => Sc::F64,
            Type::Float { .. } => Sc::F32,
            Type::Pointer { class: spirv::StorageClass::PhysicalStorageBuffer, .. } => Sc::I64,
            Type::AccelerationStructure => Sc::I64,
            _ => return Err(self.m.malformed(ty, "expected a scalar type")),
        })
    }

    pub fn is_physical_pointer(&self, ty: u32) -> bool {
        matches!(self.m.types.get(&ty), Some(Type::Pointer { class: spirv::StorageClass::PhysicalStorageBuffer, .. }))
    }

    pub fn array_len(&self, len_id: u32) -> Result<u32, ShaderError> {
        let v = self.consts.value(len_id).and_then(|v| v.first().copied());
        v.map(|v| v as u32).ok_or_else(|| self.m.malformed(len_id, "array length is not a constant"))
    }

    /// The scalars a value of `ty` flattens into, in order.
    pub fn components(&self, ty: u32) -> Result<Vec<Sc>, ShaderError> {
        let mut out = Vec::new();
        self.components_into(ty, &mut out, 0)?;
        Ok(out)
    }

    fn components_into(&self, ty: u32, out: &mut Vec<Sc>, depth: u32) -> Result<(), ShaderError> {
        if depth > MAX_DEPTH {
            return Err(self.m.malformed(ty, "type nesting too deep"));
        }
        match self.m.ty(ty)?.clone() {
            Type::Vector { elem, n } | Type::Matrix { column: elem, n } => {
                for _ in 0..n {
                    self.components_into(elem, out, depth + 1)?;
                }
            }
            Type::Array { elem, len } => {
                for _ in 0..self.array_len(len)? {
                    self.components_into(elem, out, depth + 1)?;
                }
            }
            Type::Struct { members } => {
                for m in members {
                    self.components_into(m, out, depth + 1)?;
                }
            }
            Type::Void | Type::RuntimeArray { .. } | Type::Function | Type::Image { .. } | Type::RayQuery => {
                return Err(self.m.malformed(ty, "type has no register value"))
            }
            _ => {
                if out.len() >= MAX_SCALARS {
                    return Err(ShaderError::Unsupported { what: format!("a value of more than {MAX_SCALARS} scalars"), offset: self.m.offset_of(ty) });
                }
                out.push(self.scalar(ty)?);
            }
        }
        Ok(())
    }

    pub fn count(&self, ty: u32) -> Result<usize, ShaderError> {
        Ok(self.components(ty)?.len())
    }

    /// The component range of `indices` (OpCompositeExtract/Insert literals) inside `ty`, and
    /// the type found there.
    pub fn sub_range(&self, mut ty: u32, indices: &[u32]) -> Result<(usize, usize, u32), ShaderError> {
        let mut start = 0;
        for &k in indices {
            // Homogeneous composites are not expanded: their length may be any literal.
            let (len, elem_ty, before) = match self.m.ty(ty)?.clone() {
                Type::Vector { elem, n } | Type::Matrix { column: elem, n } => (n as u64, elem, None),
                Type::Array { elem, len } => (self.array_len(len)? as u64, elem, None),
                Type::Struct { members } => {
                    let t = *members.get(k as usize).ok_or_else(|| self.m.malformed(ty, "member index"))?;
                    (members.len() as u64, t, Some(members[..k as usize].to_vec()))
                }
                _ => return Err(self.m.malformed(ty, "index into a scalar")),
            };
            if k as u64 >= len {
                return Err(self.m.malformed(ty, "composite index out of range"));
            }
            start += match before {
                Some(members) => members.iter().map(|&e| self.count(e)).sum::<Result<usize, _>>()?,
                None => (k as usize).saturating_mul(self.count(elem_ty)?),
            };
            if start > MAX_SCALARS {
                return Err(ShaderError::Unsupported { what: format!("a value of more than {MAX_SCALARS} scalars"), offset: self.m.offset_of(ty) });
            }
            ty = elem_ty;
        }
        Ok((start, self.count(ty)?, ty))
    }

    /// (size, alignment) in bytes.
    pub fn size_align(&self, ty: u32) -> Result<(u32, u32), ShaderError> {
        Ok(match self.m.ty(ty)?.clone() {
            Type::Bool => (4, 4),
            Type::Int { bits, .. } | Type::Float { bits } => (bits / 8, bits / 8),
            Type::Pointer { .. } | Type::AccelerationStructure => (8, 8),
            // A ray query's bytes in the lane frame only give it an address (its identity for
            // the executor's per-lane traversal state); nothing reads or writes them.
            Type::RayQuery => (4, 4),
            Type::Vector { elem, n } => {
                let (s, a) = self.size_align(elem)?;
                (s * n, a)
            }
            Type::Matrix { column, n } => {
                let (s, a) = self.size_align(column)?;
                (s * n, a)
            }
            Type::Array { elem, len } => {
                let (_, a) = self.size_align(elem)?;
                (self.stride(ty, elem)?.saturating_mul(self.array_len(len)?), a)
            }
            Type::RuntimeArray { elem } => (0, self.size_align(elem)?.1),
            Type::Struct { members } => {
                let (mut end, mut align) = (0u32, 1u32);
                for (k, &member) in members.iter().enumerate() {
                    let (mut s, a) = self.size_align(member)?;
                    // A matrix member's MatrixStride (naga writes 16 for mat4x3) sets its size.
                    if let (Type::Matrix { n, .. }, Some(&ms)) = (self.m.ty(member)?, self.m.member_matrix_stride.get(&(ty, k as u32))) {
                        s = s.max(ms.saturating_mul(*n));
                    }
                    end = end.max(self.member_offset(ty, k as u32)? + s);
                    align = align.max(a);
                }
                (end.div_ceil(align) * align, align)
            }
            Type::Void | Type::Function | Type::Image { .. } => return Err(self.m.malformed(ty, "type has no size")),
        })
    }

    /// Stride of an array (or runtime array, or pointer for OpPtrAccessChain) type whose element
    /// is `elem`.
    pub fn stride(&self, array_ty: u32, elem: u32) -> Result<u32, ShaderError> {
        if let Some(s) = self.m.decorations.get(&array_ty).and_then(|d| d.array_stride) {
            return Ok(s);
        }
        let (s, a) = self.size_align(elem)?;
        Ok(s.div_ceil(a.max(1)) * a.max(1))
    }

    /// Offset of member `k` of struct `ty`: its Offset decoration, or packed after the previous.
    pub fn member_offset(&self, ty: u32, k: u32) -> Result<u32, ShaderError> {
        if let Some(&o) = self.m.member_offset.get(&(ty, k)) {
            return Ok(o);
        }
        let Type::Struct { members } = self.m.ty(ty)?.clone() else {
            return Err(self.m.malformed(ty, "not a struct"));
        };
        let mut at = 0u32;
        for (i, &mt) in members.iter().enumerate().take(k as usize + 1) {
            let (s, a) = self.size_align(mt)?;
            at = at.div_ceil(a) * a;
            if i == k as usize {
                return Ok(at);
            }
            at += s;
        }
        Err(self.m.malformed(ty, "member index out of range"))
    }

    /// Every scalar of `ty` with its byte offset, in component order. `matrix_stride` comes
    /// from the enclosing struct member's MatrixStride decoration.
    pub fn fields(&self, ty: u32, matrix_stride: Option<u32>) -> Result<Vec<(Sc, u32)>, ShaderError> {
        let mut out = Vec::new();
        self.fields_into(ty, matrix_stride, 0, &mut out, 0)?;
        Ok(out)
    }

    fn fields_into(&self, ty: u32, ms: Option<u32>, base: u32, out: &mut Vec<(Sc, u32)>, depth: u32) -> Result<(), ShaderError> {
        if depth > MAX_DEPTH {
            return Err(self.m.malformed(ty, "type nesting too deep"));
        }
        match self.m.ty(ty)?.clone() {
            Type::Vector { elem, n } => {
                let s = self.size_align(elem)?.0;
                for i in 0..n {
                    self.fields_into(elem, None, base + i * s, out, depth + 1)?;
                }
            }
            Type::Matrix { column, n } => {
                let stride = match ms {
                    Some(s) => s,
                    None => self.size_align(column)?.0,
                };
                for i in 0..n {
                    self.fields_into(column, None, base + i * stride, out, depth + 1)?;
                }
            }
            Type::Array { elem, len } => {
                let stride = self.stride(ty, elem)?;
                for i in 0..self.array_len(len)? {
                    self.fields_into(elem, ms, base + i * stride, out, depth + 1)?;
                }
            }
            Type::Struct { members } => {
                for (k, &mt) in members.iter().enumerate() {
                    let off = self.member_offset(ty, k as u32)?;
                    let ms = self.m.member_matrix_stride.get(&(ty, k as u32)).copied();
                    self.fields_into(mt, ms, base + off, out, depth + 1)?;
                }
            }
            _ => {
                if out.len() >= MAX_SCALARS {
                    return Err(ShaderError::Unsupported { what: format!("a value of more than {MAX_SCALARS} scalars"), offset: self.m.offset_of(ty) });
                }
                out.push((self.scalar(ty)?, base));
            }
        }
        Ok(())
    }
}

//! Arrays of buffer descriptors in lowering (`buffer B {..} bufs[4];`, runtime arrays too): the
//! variable is one `Space::Buffer` slot whose addresses carry the array element above
//! [`ELEMENT_SHIFT`], so indexing the array, constant or not, uniform or not, is ordinary
//! address arithmetic and the executor picks the element's region per lane.
use super::ir::{Space, ELEMENT_SHIFT};
use super::lower::{Lowerer, Ptr, Val};
use super::parse::Type;
use super::ShaderError;

/// Longest descriptor array the library indexes: the element must fit above `ELEMENT_SHIFT`
/// in a 64-bit address with room for the sign of a negative index.
const MAX_ELEMENTS: u64 = 1 << (63 - ELEMENT_SHIFT);

impl Lowerer<'_> {
    /// The slot of a StorageBuffer/Uniform variable at `key`, registering it (and its array
    /// length, for a descriptor array) on first use.
    pub(super) fn buffer_variable(&mut self, id: u32, key: (u32, u32), pointee: u32) -> Result<Space, ShaderError> {
        let count = match self.m.ty(pointee)? {
            Type::Array { len, .. } => {
                let n = self.consts.value(*len).and_then(|v| v.first().copied()).ok_or_else(|| self.err(id, "descriptor array of unknown length"))?;
                if n == 0 || n > MAX_ELEMENTS {
                    return Err(self.err(id, format!("descriptor array of {n} elements")));
                }
                n as u32
            }
            Type::RuntimeArray { .. } => 0,
            _ => 1,
        };
        if count != 1 && !self.descriptor_arrays.contains(&pointee) {
            self.descriptor_arrays.push(pointee);
        }
        let slot = match self.bindings.iter().position(|&b| b == key) {
            Some(s) => s,
            None => {
                self.bindings.push(key);
                self.binding_counts.push(count);
                self.bindings.len() - 1
            }
        };
        if self.binding_counts[slot] != count {
            return Err(self.err(id, "two variables of different array lengths at one (set, binding)"));
        }
        Ok(Space::Buffer(slot as u16))
    }

    /// The stride of indexing `p` when it points to a whole descriptor array: one element.
    /// Arrays inside a buffer block have an explicit ArrayStride and another type id, so they
    /// never match.
    pub(super) fn descriptor_stride(&self, p: &Ptr) -> Option<u64> {
        (matches!(p.space, Space::Buffer(_)) && self.descriptor_arrays.contains(&p.pointee)).then_some(1 << ELEMENT_SHIFT)
    }

    /// An array of acceleration-structure descriptors (None for any other variable): a
    /// `Space::Accel` pointer whose elements load as structure addresses. The binding is
    /// listed in `bindings` too, with its length, for the pipeline-layout checks.
    pub(super) fn accel_array(&mut self, id: u32, key: (u32, u32), pointee: u32) -> Result<Option<Val>, ShaderError> {
        let (elem, count) = match self.m.ty(pointee)? {
            Type::Array { elem, len } => (*elem, self.consts.value(*len).and_then(|v| v.first().copied()).unwrap_or(0) as u32),
            Type::RuntimeArray { elem } => (*elem, 0),
            _ => return Ok(None),
        };
        if !matches!(self.m.ty(elem)?, Type::AccelerationStructure) {
            return Ok(None);
        }
        if matches!(self.m.ty(pointee)?, Type::Array { .. }) && count == 0 {
            return Err(self.err(id, "acceleration-structure array of unknown length"));
        }
        let slot = match self.accel_arrays.iter().position(|(k, _)| *k == key) {
            Some(s) => s,
            None => {
                self.accel_arrays.push((key, count));
                if !self.bindings.contains(&key) {
                    self.bindings.push(key);
                    self.binding_counts.push(count);
                }
                self.accel_arrays.len() - 1
            }
        };
        let addr = self.konst(0);
        Ok(Some(Val::Ptr(Ptr { space: Space::Accel(slot as u16), addr, pointee, matrix_stride: None })))
    }
}

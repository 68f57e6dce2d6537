//! Image storage: one `VkImage`'s texels laid out linearly in the device memory it is bound
//! to, whatever its tiling (optimal tiling is opaque to the application, so the same layout
//! serves both). Level by level, each level's layers one after another, each layer's depth
//! slices, rows tightly packed. This module knows texel sizes and extents, not formats: what
//! a texel means is for the layers above.
use std::sync::{Arc, OnceLock};

use super::{AccessError, BindError, Memory};

/// Images are bound at offsets aligned to this; subresources start 16-aligned inside.
pub const IMAGE_ALIGNMENT: u64 = 256;

/// Where one (level, layer) subresource lies, relative to the image's start.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Subresource {
    pub offset: u64,
    pub size: u64,
    pub row_pitch: u64,
    /// Bytes from one depth slice to the next (3D images; equals `size` otherwise).
    pub depth_pitch: u64,
    /// Bytes from one array layer to the next.
    pub array_pitch: u64,
}

/// One `VkImage`: geometry, texel size and its binding to memory.
pub struct Image {
    pub texel_size: u32,
    /// Width, height, depth of level 0.
    pub extent: [u32; 3],
    pub levels: u32,
    pub layers: u32,
    /// Bytes the whole image occupies.
    pub size: u64,
    /// Start of each level, relative to the image.
    level_offsets: Vec<u64>,
    binding: OnceLock<(Arc<Memory>, u64)>,
}

impl Image {
    /// An image of `levels` mip levels (at most the full chain, the caller checks) and `layers`
    /// layers. None when the size overflows.
    pub fn new(texel_size: u32, extent: [u32; 3], levels: u32, layers: u32) -> Option<Image> {
        let mut level_offsets = Vec::with_capacity(levels as usize);
        let mut at = 0u64;
        for level in 0..levels {
            level_offsets.push(at);
            let [w, h, d] = level_extent(extent, level);
            let layer = (w as u64).checked_mul(h as u64)?.checked_mul(d as u64)?.checked_mul(texel_size as u64)?;
            at = at.checked_add(layer.checked_mul(layers as u64)?)?.checked_next_multiple_of(16)?;
        }
        Some(Image { texel_size, extent, levels, layers, size: at, level_offsets, binding: OnceLock::new() })
    }

    /// Extent of mip level `level`.
    pub fn level_extent(&self, level: u32) -> [u32; 3] {
        level_extent(self.extent, level)
    }

    /// Layout of (level, layer); None outside the image.
    pub fn subresource(&self, level: u32, layer: u32) -> Option<Subresource> {
        if level >= self.levels || layer >= self.layers {
            return None;
        }
        let [w, h, d] = self.level_extent(level);
        let row_pitch = w as u64 * self.texel_size as u64;
        let depth_pitch = row_pitch * h as u64;
        let array_pitch = depth_pitch * d as u64;
        let offset = self.level_offsets[level as usize] + layer as u64 * array_pitch;
        Some(Subresource { offset, size: array_pitch, row_pitch, depth_pitch, array_pitch })
    }

    /// Memory requirements (size, alignment).
    pub fn requirements(&self) -> (u64, u64) {
        (self.size.next_multiple_of(IMAGE_ALIGNMENT).max(IMAGE_ALIGNMENT), IMAGE_ALIGNMENT)
    }

    /// Bind to `memory` at `offset` (once).
    pub fn bind(&self, memory: Arc<Memory>, offset: u64) -> Result<(), BindError> {
        if self.binding.get().is_some() {
            return Err(BindError::AlreadyBound);
        }
        if !offset.is_multiple_of(IMAGE_ALIGNMENT) {
            return Err(BindError::Misaligned);
        }
        memory.check(offset, self.size).map_err(BindError::Access)?;
        self.binding.set((memory, offset)).map_err(|_| BindError::AlreadyBound)
    }

    pub fn is_bound(&self) -> bool {
        self.binding.get().is_some()
    }

    fn locate(&self, offset: u64, len: u64) -> Result<(&Arc<Memory>, u64), AccessError> {
        let (m, base) = self.binding.get().ok_or(AccessError::Unbound)?;
        match offset.checked_add(len) {
            Some(end) if end <= self.size => Ok((m, base + offset)),
            _ => Err(AccessError::BufferRange { offset, len, size: self.size }),
        }
    }

    /// Copy bytes out of the image (offset relative to the image's start, checked).
    pub fn read(&self, offset: u64, out: &mut [u8]) -> Result<(), AccessError> {
        let (m, o) = self.locate(offset, out.len() as u64)?;
        m.read(o, out)
    }

    /// Copy bytes into the image (offset relative to the image's start, checked).
    pub fn write(&self, offset: u64, data: &[u8]) -> Result<(), AccessError> {
        let (m, o) = self.locate(offset, data.len() as u64)?;
        m.write(o, data)
    }

    /// Atomic read-modify-write of a 4- or 8-byte texel word (offset relative to the image's
    /// start, checked): image atomics in shaders.
    pub fn atomic(&self, offset: u64, size: usize, update: &dyn Fn(u64) -> u64) -> Result<u64, AccessError> {
        let (m, o) = self.locate(offset, size as u64)?;
        m.atomic(o, size, update)
    }
}

/// Extent of mip level `level` of an image whose level 0 is `extent`.
pub fn level_extent(extent: [u32; 3], level: u32) -> [u32; 3] {
    extent.map(|e| (e.checked_shr(level).unwrap_or(0)).max(1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_and_layers_are_packed_and_aligned() {
        let img = Image::new(4, [5, 3, 1], 3, 2).unwrap();
        let s00 = img.subresource(0, 0).unwrap();
        assert_eq!((s00.offset, s00.row_pitch, s00.size), (0, 20, 60));
        assert_eq!(img.subresource(0, 1).unwrap().offset, 60);
        // Level 1 is 2x1, starting after 120 bytes rounded to 16.
        assert_eq!(img.subresource(1, 0).unwrap(), Subresource { offset: 128, size: 8, row_pitch: 8, depth_pitch: 8, array_pitch: 8 });
        assert_eq!(img.level_extent(2), [1, 1, 1]);
        assert!(img.subresource(3, 0).is_none() && img.subresource(0, 2).is_none());
        assert!(Image::new(16, [u32::MAX, u32::MAX, u32::MAX], 1, u32::MAX).is_none());
    }
}

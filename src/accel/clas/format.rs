//! The stored cluster formats: one 112-byte header shared by CLAS, cluster templates and
//! cluster BLAS, and the sections each kind derives from its counts. Every offset is relative to
//! the blob start and no blob holds its own address, so a move is a byte copy. The header's first
//! three words sit where a KHR structure keeps magic, version and type: `layout::parse` refuses
//! the cluster kinds, `open` below accepts only them.
use super::super::layout::{KIND_CLAS, KIND_CLUSTER_BLAS, KIND_CLUSTER_TEMPLATE, MAGIC};
use super::tree::local_node_count;
use crate::accel::layout::WideNode;
use bytemuck::{Pod, Zeroable};

/// Bump whenever a cluster layout or its meaning changes.
pub const CLUSTER_FORMAT_VERSION: u32 = 3;
const VALID: u32 = 0x434c_5553;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct ClusterHeader {
    pub magic: u32,
    pub version: u32,
    pub kind: u32,
    pub valid: u32,
    /// Bytes of the blob (what a move copies and COMPUTE_SIZES of a move reports).
    pub used_size: u64,
    /// CLAS and template: the cluster ID. Cluster BLAS: 0.
    pub cluster_id: u32,
    pub cluster_flags: u32,
    pub triangle_count: u32,
    pub vertex_count: u32,
    pub truncate_bits: u32,
    /// Template: bytes per index of the build (1, 2 or 4); others 0.
    pub index_bytes: u32,
    /// Template: the VkFormat of its vertices.
    pub vertex_format: i32,
    /// Template: 1 when it stores vertices (built with a vertex buffer).
    pub has_vertices: u32,
    /// Cluster BLAS: the CLAS references it was built over.
    pub cluster_count: u32,
    /// Cluster BLAS: how many of them hold triangles (the top tree's leaves).
    pub live_count: u32,
    /// Cluster BLAS: offset of the embedded bottom-level BVH; others 0.
    pub bvh_offset: u64,
    pub bvh_size: u64,
    /// CLAS and cluster BLAS: the box of the stored triangles; template: the instantiation
    /// bounding-box limit when one was given, else zero.
    pub bounds: [f32; 6],
    pub spare: [u32; 2],
}
pub const HEADER_SIZE: u64 = 112;
const _: () = assert!(std::mem::size_of::<ClusterHeader>() == HEADER_SIZE as usize);

/// Stored triangle: v0, v1, v2 after position truncation.
pub const TRIANGLE_SIZE: u64 = 36;
/// Per-triangle geometry word: geometry index (bits 0-23) | geometry flags << 29.
pub const WORD_SIZE: u64 = 4;
/// A CLAS tree node (`layout::WideNode`).
pub const NODE_SIZE: u64 = 64;

/// What the kinds hold, beside the header:
/// CLAS: triangles (36 B each), then geometry words (4 B each), the slot order of its tree (one
/// byte per triangle, padded to 4) and the tree's nodes (`tree::local_node_count`).
/// Template: raw indices as u32 (12 B per triangle), geometry words, then (with vertices) the
/// truncated triangles as a CLAS stores them.
/// Cluster BLAS: CLAS address table (8 B per reference), the table of non-empty CLASes (8 B
/// each: reference ordinal, triangle count), then at a 64-byte boundary an embedded BVH that
/// holds the top tree over them. The CLASes are referenced, not copied.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Clas,
    Template,
    ClusterBlas,
}
impl Kind {
    pub fn code(self) -> u32 {
        match self {
            Kind::Clas => KIND_CLAS,
            Kind::Template => KIND_CLUSTER_TEMPLATE,
            Kind::ClusterBlas => KIND_CLUSTER_BLAS,
        }
    }
    fn from_code(code: u32) -> Option<Kind> {
        [Kind::Clas, Kind::Template, Kind::ClusterBlas].into_iter().find(|k| k.code() == code)
    }
}

pub fn clas_size(triangles: u64) -> u64 {
    clas_nodes_offset(triangles).saturating_add(local_node_count(triangles).saturating_mul(NODE_SIZE))
}
/// CLAS: offset of the tree's slot order.
pub fn clas_order_offset(triangles: u64) -> u64 {
    HEADER_SIZE.saturating_add(triangles.saturating_mul(TRIANGLE_SIZE + WORD_SIZE))
}
/// CLAS: offset of the tree's nodes.
pub fn clas_nodes_offset(triangles: u64) -> u64 {
    clas_order_offset(triangles).saturating_add(triangles.next_multiple_of(4))
}
pub fn template_size(triangles: u64, has_vertices: bool) -> u64 {
    HEADER_SIZE + triangles * (12 + WORD_SIZE) + if has_vertices { triangles * TRIANGLE_SIZE } else { 0 }
}
pub fn align_up(v: u64, a: u64) -> u64 {
    v.div_ceil(a).saturating_mul(a)
}

pub fn new_header(kind: Kind) -> ClusterHeader {
    ClusterHeader { magic: MAGIC, version: CLUSTER_FORMAT_VERSION, kind: kind.code(), valid: VALID, ..Zeroable::zeroed() }
}

/// A cluster blob: its header and its `used_size` bytes.
#[derive(Clone, Copy, Debug)]
pub struct Blob<'a> {
    pub kind: Kind,
    pub header: ClusterHeader,
    pub bytes: &'a [u8],
}

/// The cluster blob at the start of `bytes`, when its header is valid and its sections fit.
pub fn open(bytes: &[u8]) -> Option<Blob<'_>> {
    let h: ClusterHeader = bytemuck::pod_read_unaligned(bytes.get(..HEADER_SIZE as usize)?);
    if h.magic != MAGIC || h.version != CLUSTER_FORMAT_VERSION || h.valid != VALID {
        return None;
    }
    let kind = Kind::from_code(h.kind)?;
    let t = h.triangle_count as u64;
    // A CLAS tree's slots are bytes.
    if kind == Kind::Clas && t > super::MAX_TRIANGLES as u64 {
        return None;
    }
    let need = match kind {
        Kind::Clas => clas_size(t),
        Kind::Template => template_size(t, h.has_vertices != 0),
        Kind::ClusterBlas => {
            let tables = HEADER_SIZE + 16 * h.cluster_count as u64;
            if h.bvh_offset < tables || h.live_count > h.cluster_count {
                return None;
            }
            h.bvh_offset.checked_add(h.bvh_size)?
        }
    };
    if need != h.used_size || h.used_size > bytes.len() as u64 {
        return None;
    }
    Some(Blob { kind, header: h, bytes: &bytes[..h.used_size as usize] })
}

pub fn write_header(dst: &mut [u8], h: &ClusterHeader) {
    dst[..HEADER_SIZE as usize].copy_from_slice(bytemuck::bytes_of(h));
}

/// Clears `bits` low bits of an fp32 coordinate (32 gives +0.0): positionTruncateBitCount.
pub fn truncate(x: f32, bits: u32) -> f32 {
    let mask = !((1u64 << bits.min(32)) - 1) as u32;
    f32::from_bits(x.to_bits() & mask)
}

pub fn rd_u32(b: &[u8], off: u64) -> u32 {
    let o = off as usize;
    u32::from_le_bytes(b[o..o + 4].try_into().unwrap_or([0; 4]))
}
pub fn rd_f32(b: &[u8], off: u64) -> f32 {
    f32::from_bits(rd_u32(b, off))
}
impl Blob<'_> {
    /// CLAS (and a template with vertices): triangle `i`'s stored vertices.
    pub fn triangle(&self, i: u32) -> [f32; 9] {
        let base = match self.kind {
            Kind::Clas => HEADER_SIZE,
            _ => HEADER_SIZE + self.header.triangle_count as u64 * (12 + WORD_SIZE),
        };
        std::array::from_fn(|k| rd_f32(self.bytes, base + i as u64 * TRIANGLE_SIZE + 4 * k as u64))
    }
    /// CLAS or template: triangle `i`'s geometry word.
    pub fn word(&self, i: u32) -> u32 {
        let t = self.header.triangle_count as u64;
        let base = match self.kind {
            Kind::Clas => HEADER_SIZE + t * TRIANGLE_SIZE,
            _ => HEADER_SIZE + t * 12,
        };
        rd_u32(self.bytes, base + i as u64 * WORD_SIZE)
    }
    /// CLAS: the triangle in slot `s` of its tree.
    pub fn slot(&self, s: u32) -> u32 {
        self.bytes[(clas_order_offset(self.header.triangle_count as u64) + s as u64) as usize] as u32
    }
    /// CLAS: the slot order of its tree (one byte per triangle).
    pub fn order(&self) -> &[u8] {
        let at = clas_order_offset(self.header.triangle_count as u64) as usize;
        &self.bytes[at..at + self.header.triangle_count as usize]
    }
    /// CLAS: node `i` of its tree (local indices).
    pub fn node(&self, i: u32) -> WideNode {
        let at = (clas_nodes_offset(self.header.triangle_count as u64) + i as u64 * NODE_SIZE) as usize;
        bytemuck::pod_read_unaligned(&self.bytes[at..at + NODE_SIZE as usize])
    }
    /// CLAS: the bytes of its tree's nodes.
    pub fn node_bytes(&self) -> &[u8] {
        &self.bytes[clas_nodes_offset(self.header.triangle_count as u64) as usize..]
    }
    /// Template: the k-th raw index (3 per triangle).
    pub fn index(&self, k: u32) -> u32 {
        rd_u32(self.bytes, HEADER_SIZE + 4 * k as u64)
    }
}

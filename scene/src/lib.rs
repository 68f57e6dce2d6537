//! Scenes for tests, benches and the benchmark CLI: triangle meshes loaded from PLY and
//! Wavefront OBJ files (optionally gzip-compressed), deterministic procedural scenes, TLAS
//! instance records, and the byte views that feed `arbor::accel::Geometry`.
//!
//! This crate owns no Vulkan state and does not depend on Arbor: it only produces plain data
//! (positions, indices, bytes) so that tests can feed the same input to the library under test
//! and to independent references. It is not part of the driver that applications load.

mod obj;
mod ply;
mod procedural;

use std::fmt;
use std::io::Read;
use std::path::Path;

pub use obj::parse_obj;
pub use ply::parse_ply;
pub use procedural::{instance_records, primary_rays, random_soup, terrain, CameraRay, InstanceRecord, Rng};

/// An indexed triangle mesh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    pub indices: Vec<[u32; 3]>,
}

/// Why a scene could not be loaded.
#[derive(Debug)]
pub enum SceneError {
    Io(std::io::Error),
    /// The file's content does not follow its format; the message says where.
    Parse(String),
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SceneError::Io(e) => write!(f, "i/o error: {e}"),
            SceneError::Parse(m) => write!(f, "parse error: {m}"),
        }
    }
}

impl std::error::Error for SceneError {}

impl From<std::io::Error> for SceneError {
    fn from(e: std::io::Error) -> Self {
        SceneError::Io(e)
    }
}

pub(crate) fn parse_err<T>(msg: impl Into<String>) -> Result<T, SceneError> {
    Err(SceneError::Parse(msg.into()))
}

const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];

/// Returns `bytes` decompressed when they start with the gzip magic, unchanged otherwise.
pub fn maybe_gunzip(bytes: Vec<u8>) -> Result<Vec<u8>, SceneError> {
    if bytes.len() >= 2 && bytes[..2] == GZIP_MAGIC {
        let mut out = Vec::with_capacity(bytes.len() * 4);
        flate2::read::MultiGzDecoder::new(&bytes[..]).read_to_end(&mut out)?;
        Ok(out)
    } else {
        Ok(bytes)
    }
}

/// Loads a PLY or OBJ mesh. The format is taken from the extension (after a `.gz`, if any),
/// else from the content (`ply` magic). Gzip is recognised by its magic, whatever the name.
pub fn load(path: impl AsRef<Path>) -> Result<Mesh, SceneError> {
    let path = path.as_ref();
    let bytes = maybe_gunzip(std::fs::read(path)?)?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let name = name.strip_suffix(".gz").unwrap_or(&name);
    if name.ends_with(".ply") {
        parse_ply(&bytes)
    } else if name.ends_with(".obj") {
        parse_obj(&bytes)
    } else if bytes.starts_with(b"ply") {
        parse_ply(&bytes)
    } else {
        parse_obj(&bytes)
    }
}

impl Mesh {
    pub fn triangle_count(&self) -> usize {
        self.indices.len()
    }

    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }

    /// Axis-aligned bounds `[min_x, min_y, min_z, max_x, max_y, max_z]` of the finite
    /// positions (all infinite when there are none).
    pub fn bounds(&self) -> [f32; 6] {
        let mut b = [f32::INFINITY, f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY];
        for p in &self.positions {
            if p.iter().all(|c| c.is_finite()) {
                for k in 0..3 {
                    b[k] = b[k].min(p[k]);
                    b[k + 3] = b[k + 3].max(p[k]);
                }
            }
        }
        b
    }

    /// The three corners of triangle `i`.
    pub fn triangle(&self, i: usize) -> [[f32; 3]; 3] {
        let [a, b, c] = self.indices[i];
        [self.positions[a as usize], self.positions[b as usize], self.positions[c as usize]]
    }

    /// Vertex bytes as VK_FORMAT_R32G32B32_SFLOAT, stride 12 (little endian, like the device).
    pub fn vertex_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.positions.len() * 12);
        for p in &self.positions {
            for c in p {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        out
    }

    /// Index bytes as VK_INDEX_TYPE_UINT32 (3 per triangle).
    pub fn index_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.indices.len() * 12);
        for t in &self.indices {
            for i in t {
                out.extend_from_slice(&i.to_le_bytes());
            }
        }
        out
    }

    /// Index bytes as VK_INDEX_TYPE_UINT16, or None when a vertex index does not fit.
    pub fn index_bytes_u16(&self) -> Option<Vec<u8>> {
        let mut out = Vec::with_capacity(self.indices.len() * 6);
        for t in &self.indices {
            for &i in t {
                out.extend_from_slice(&u16::try_from(i).ok()?.to_le_bytes());
            }
        }
        Some(out)
    }

    /// Non-indexed vertex bytes (R32G32B32_SFLOAT, stride 12): three vertices per triangle,
    /// for VK_INDEX_TYPE_NONE_KHR geometries.
    pub fn unindexed_vertex_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.indices.len() * 36);
        for i in 0..self.indices.len() {
            for p in self.triangle(i) {
                for c in p {
                    out.extend_from_slice(&c.to_le_bytes());
                }
            }
        }
        out
    }

    /// Highest index referenced by a triangle (0 for an empty mesh): `max_vertex` of a build.
    pub fn max_index(&self) -> u32 {
        self.indices.iter().flat_map(|t| t.iter().copied()).max().unwrap_or(0)
    }
}

#[cfg(test)]
mod tests;

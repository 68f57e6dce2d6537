//! Wavefront OBJ reader: `v x y z [w]` and `f` with `v`, `v/vt`, `v/vt/vn`, `v//vn` corners,
//! 1-based or negative (relative) indices. Polygons become triangle fans; other statements
//! (vt, vn, o, g, s, usemtl, mtllib, l, p, …) are ignored.

use super::{parse_err, Mesh, SceneError};

pub fn parse_obj(data: &[u8]) -> Result<Mesh, SceneError> {
    let text = std::str::from_utf8(data).or_else(|_| parse_err("OBJ: not UTF-8 text"))?;
    let mut mesh = Mesh::default();
    let mut poly: Vec<u32> = Vec::with_capacity(8);
    // Join lines continued with a trailing backslash.
    let mut logical = String::new();
    for (lineno, raw) in text.lines().enumerate() {
        let raw = raw.trim_end_matches('\r');
        if let Some(head) = raw.strip_suffix('\\') {
            logical.push_str(head);
            logical.push(' ');
            continue;
        }
        logical.push_str(raw);
        let line = logical.split('#').next().unwrap_or("").trim();
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let mut p = [0f32; 3];
                for c in &mut p {
                    let w = words.next().ok_or_else(|| err(lineno, "vertex with fewer than 3 coordinates"))?;
                    *c = w.parse().map_err(|_| err(lineno, "bad vertex coordinate"))?;
                }
                mesh.positions.push(p);
            }
            Some("f") => {
                poly.clear();
                for corner in words {
                    let first = corner.split('/').next().unwrap_or("");
                    let i: i64 = first.parse().map_err(|_| err(lineno, "bad face index"))?;
                    let n = mesh.positions.len() as i64;
                    let abs = if i > 0 { i - 1 } else if i < 0 { n + i } else { -1 };
                    if abs < 0 || abs >= n {
                        return Err(err(lineno, "face index out of range"));
                    }
                    poly.push(abs as u32);
                }
                if poly.len() < 3 {
                    return Err(err(lineno, "face with fewer than 3 corners"));
                }
                for j in 2..poly.len() {
                    mesh.indices.push([poly[0], poly[j - 1], poly[j]]);
                }
            }
            _ => {}
        }
        logical.clear();
    }
    Ok(mesh)
}

fn err(lineno: usize, what: &str) -> SceneError {
    SceneError::Parse(format!("OBJ line {}: {what}", lineno + 1))
}

//! PLY (Stanford polygon file) reader: ASCII, binary little endian and binary big endian.
//! Reads x/y/z of the `vertex` element and the first list property of the `face` element
//! (preferring `vertex_indices`/`vertex_index`); every other element and property is skipped.
//! Polygons are triangulated as fans around their first corner.

use super::{parse_err, Mesh, SceneError};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Encoding {
    Ascii,
    BinaryLe,
    BinaryBe,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
}

#[derive(Clone, Debug)]
enum Property {
    Scalar { name: String, ty: Scalar },
    List { name: String, count: Scalar, item: Scalar },
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

/// A cursor over the body that yields numbers in the file's encoding.
struct Reader<'a> {
    data: &'a [u8],
    pos: usize,
    encoding: Encoding,
}

impl<'a> Reader<'a> {
    fn next_ascii_token(&mut self) -> Result<&'a str, SceneError> {
        let d = self.data;
        while self.pos < d.len() && d[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        let start = self.pos;
        while self.pos < d.len() && !d[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        if start == self.pos {
            return parse_err("PLY: unexpected end of data");
        }
        std::str::from_utf8(&d[start..self.pos]).or_else(|_| parse_err("PLY: non-UTF-8 token"))
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], SceneError> {
        if self.data.len() - self.pos < n {
            return parse_err("PLY: unexpected end of binary data");
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn read(&mut self, ty: Scalar) -> Result<f64, SceneError> {
        if self.encoding == Encoding::Ascii {
            let tok = self.next_ascii_token()?;
            return match ty {
                Scalar::F32 | Scalar::F64 => tok.parse::<f64>().or_else(|_| parse_err(format!("PLY: bad number {tok:?}"))),
                _ => tok.parse::<i64>().map(|v| v as f64).or_else(|_| parse_err(format!("PLY: bad integer {tok:?}"))),
            };
        }
        let bytes = self.take(ty.size())?;
        let le = self.encoding == Encoding::BinaryLe;
        macro_rules! num {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(bytes);
                if le { <$t>::from_le_bytes(a) } else { <$t>::from_be_bytes(a) }
            }};
        }
        Ok(match ty {
            Scalar::I8 => bytes[0] as i8 as f64,
            Scalar::U8 => bytes[0] as f64,
            Scalar::I16 => num!(i16, 2) as f64,
            Scalar::U16 => num!(u16, 2) as f64,
            Scalar::I32 => num!(i32, 4) as f64,
            Scalar::U32 => num!(u32, 4) as f64,
            Scalar::F32 => num!(f32, 4) as f64,
            Scalar::F64 => num!(f64, 8),
        })
    }

    /// Skips one value, fast for binary.
    fn skip(&mut self, ty: Scalar) -> Result<(), SceneError> {
        if self.encoding == Encoding::Ascii {
            self.next_ascii_token().map(|_| ())
        } else {
            self.take(ty.size()).map(|_| ())
        }
    }
}

fn read_index(r: &mut Reader, ty: Scalar) -> Result<u32, SceneError> {
    let v = r.read(ty)?;
    if v < 0.0 || v > u32::MAX as f64 || v.fract() != 0.0 {
        return parse_err(format!("PLY: invalid vertex index {v}"));
    }
    Ok(v as u32)
}

/// Parses a PLY file held in memory (already decompressed).
pub fn parse_ply(data: &[u8]) -> Result<Mesh, SceneError> {
    let (encoding, elements, pos) = parse_header(data)?;
    let mut r = Reader { data, pos, encoding };
    let mut mesh = Mesh::default();
    for el in &elements {
        match el.name.as_str() {
            "vertex" => read_vertices(&mut r, el, &mut mesh.positions)?,
            "face" => read_faces(&mut r, el, &mut mesh.indices)?,
            _ => {
                for _ in 0..el.count {
                    for prop in &el.properties {
                        skip_property(&mut r, prop)?;
                    }
                }
            }
        }
    }
    let nv = mesh.positions.len() as u32;
    if let Some(bad) = mesh.indices.iter().flat_map(|t| t.iter()).find(|&&i| i >= nv) {
        return parse_err(format!("PLY: face refers to vertex {bad} of {nv}"));
    }
    Ok(mesh)
}

/// The header: the body's encoding, its elements and the offset where the body starts.
fn parse_header(data: &[u8]) -> Result<(Encoding, Vec<Element>, usize), SceneError> {
    let (lines, pos) = header_lines(data)?;
    if lines.first().map(String::as_str) != Some("ply") {
        return parse_err("PLY: missing 'ply' magic");
    }
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    for line in &lines[1..] {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.first().copied() {
            Some("format") => {
                encoding = Some(match words.get(1).copied() {
                    Some("ascii") => Encoding::Ascii,
                    Some("binary_little_endian") => Encoding::BinaryLe,
                    Some("binary_big_endian") => Encoding::BinaryBe,
                    other => return parse_err(format!("PLY: unknown format {other:?}")),
                })
            }
            Some("element") => {
                let (Some(name), Some(count)) = (words.get(1), words.get(2)) else {
                    return parse_err(format!("PLY: bad element line {line:?}"));
                };
                let count = count.parse().or_else(|_| parse_err(format!("PLY: bad element count {line:?}")))?;
                elements.push(Element { name: name.to_string(), count, properties: Vec::new() });
            }
            Some("property") => {
                let Some(el) = elements.last_mut() else {
                    return parse_err("PLY: property before any element");
                };
                el.properties.push(parse_property(&words, line)?);
            }
            Some("comment") | Some("obj_info") | None => {}
            Some(other) => return parse_err(format!("PLY: unknown header keyword {other:?}")),
        }
    }
    let Some(encoding) = encoding else {
        return parse_err("PLY: no format line");
    };
    Ok((encoding, elements, pos))
}

/// Text lines up to and including "end_header" (trimmed, without it), and the offset after it.
fn header_lines(data: &[u8]) -> Result<(Vec<String>, usize), SceneError> {
    let mut pos = 0usize;
    let mut lines = Vec::new();
    loop {
        let rest = &data[pos..];
        let Some(nl) = rest.iter().position(|&b| b == b'\n') else {
            return parse_err("PLY: header has no end_header line");
        };
        let line = std::str::from_utf8(&rest[..nl]).or_else(|_| parse_err("PLY: header is not text"))?;
        let line = line.trim_end_matches('\r').trim();
        pos += nl + 1;
        if line == "end_header" {
            return Ok((lines, pos));
        }
        lines.push(line.to_string());
    }
}

/// One `property` line, split into `words`.
fn parse_property(words: &[&str], line: &str) -> Result<Property, SceneError> {
    Ok(if words.get(1) == Some(&"list") {
        match (words.get(2).and_then(|w| Scalar::parse(w)), words.get(3).and_then(|w| Scalar::parse(w)), words.get(4)) {
            (Some(count), Some(item), Some(name)) => Property::List { name: name.to_string(), count, item },
            _ => return parse_err(format!("PLY: bad list property {line:?}")),
        }
    } else {
        match (words.get(1).and_then(|w| Scalar::parse(w)), words.get(2)) {
            (Some(ty), Some(name)) => Property::Scalar { name: name.to_string(), ty },
            _ => return parse_err(format!("PLY: bad property {line:?}")),
        }
    })
}

/// Skips one property's value (a scalar, or a list with its count).
fn skip_property(r: &mut Reader, prop: &Property) -> Result<(), SceneError> {
    match prop {
        Property::Scalar { ty, .. } => r.skip(*ty),
        Property::List { count, item, .. } => {
            let n = read_index(r, *count)?;
            for _ in 0..n {
                r.skip(*item)?;
            }
            Ok(())
        }
    }
}

/// The `vertex` element: x, y and z of each vertex, every other property skipped.
fn read_vertices(r: &mut Reader, el: &Element, positions: &mut Vec<[f32; 3]>) -> Result<(), SceneError> {
    let find = |axis: &str| el.properties.iter().position(|p| matches!(p, Property::Scalar { name, .. } if name == axis));
    let (Some(ix), Some(iy), Some(iz)) = (find("x"), find("y"), find("z")) else {
        return parse_err("PLY: vertex element lacks x, y or z");
    };
    // Bounded by the data actually present, so a lying header cannot over-allocate.
    positions.reserve(el.count.min(r.data.len() / 3));
    for _ in 0..el.count {
        let mut p = [0f32; 3];
        for (k, prop) in el.properties.iter().enumerate() {
            match prop {
                Property::Scalar { ty, .. } if k == ix || k == iy || k == iz => {
                    let v = r.read(*ty)? as f32;
                    p[if k == ix { 0 } else if k == iy { 1 } else { 2 }] = v;
                }
                _ => skip_property(r, prop)?,
            }
        }
        positions.push(p);
    }
    Ok(())
}

/// The `face` element: its vertex-index list (fan-triangulated), every other property skipped.
fn read_faces(r: &mut Reader, el: &Element, indices: &mut Vec<[u32; 3]>) -> Result<(), SceneError> {
    let list_pos = el
        .properties
        .iter()
        .position(|p| matches!(p, Property::List { name, .. } if name == "vertex_indices" || name == "vertex_index"))
        .or_else(|| el.properties.iter().position(|p| matches!(p, Property::List { .. })));
    let Some(list_pos) = list_pos else {
        return parse_err("PLY: face element has no list property");
    };
    indices.reserve(el.count.min(r.data.len() / 4));
    let mut poly = Vec::with_capacity(8);
    for _ in 0..el.count {
        for (k, prop) in el.properties.iter().enumerate() {
            match prop {
                Property::List { count, item, .. } if k == list_pos => {
                    let n = read_index(r, *count)?;
                    poly.clear();
                    for _ in 0..n {
                        poly.push(read_index(r, *item)?);
                    }
                }
                _ => skip_property(r, prop)?,
            }
        }
        for j in 2..poly.len() {
            indices.push([poly[0], poly[j - 1], poly[j]]);
        }
    }
    Ok(())
}

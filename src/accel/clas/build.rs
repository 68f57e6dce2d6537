//! CLAS and template builds, instantiation and the template index fetch. Inputs are read through
//! `DeviceView::bytes` at the addresses the argument records name; every read is checked and a
//! failure is a typed `ClusterError`, never a panic. The bytes written depend on the input only.
use super::args::{BuildTriangleClusterInfo, GeometryIndexAndFlags, InstantiateClusterInfo};
use super::format::{self, clas_nodes_offset, clas_order_offset, clas_size, new_header, open, template_size, truncate, ClusterHeader, Kind, HEADER_SIZE, TRIANGLE_SIZE};
use super::tree::build_local;
use super::{ClusterError, MAX_TRIANGLES, MAX_VERTICES};
use crate::accel::input::decode_vertex;
use crate::accel::{DeviceView, VertexFormat};

/// What a CLAS or template build reads: indices, per-triangle geometry words and (if present)
/// the truncated triangles.
struct Gathered {
    indices: Vec<u32>,
    words: Vec<u32>,
    triangles: Option<Vec<[f32; 9]>>,
}

fn read<'a>(view: &'a dyn DeviceView, address: u64, len: u64, what: &'static str) -> Result<&'a [u8], ClusterError> {
    view.bytes(address, len).ok_or(ClusterError::Unreadable { what, address })
}

fn vertex(view: &dyn DeviceView, format: VertexFormat, start: u64, stride: u64, index: u32, bits: u32) -> Result<[f32; 3], ClusterError> {
    let address = start.wrapping_add(index as u64 * stride);
    let b = read(view, address, format.size() as u64, "vertex")?;
    let v = decode_vertex(format, b).ok_or(ClusterError::Unreadable { what: "vertex", address })?;
    Ok([truncate(v.x, bits), truncate(v.y, bits), truncate(v.z, bits)])
}

/// The triangles of `indices` read from `start` + index × `stride`, truncated.
fn fetch_triangles(view: &dyn DeviceView, format: VertexFormat, start: u64, stride: u64, indices: &[u32], bits: u32) -> Result<Vec<[f32; 9]>, ClusterError> {
    let stride = if stride == 0 { format.size() as u64 } else { stride & 0xffff_ffff };
    // One read of the span the indices reach (a cluster's vertices are usually one small
    // range), decoded from there; the per-vertex reads below remain for a span that is not.
    let max = indices.iter().copied().max().unwrap_or(0) as u64;
    let span = (max * stride).checked_add(format.size() as u64);
    if let Some(b) = span.and_then(|len| view.bytes(start, len)) {
        let one = |i: u64| -> Option<[f32; 3]> {
            let at = (i * stride) as usize;
            let v = decode_vertex(format, b.get(at..at + format.size() as usize)?)?;
            Some([truncate(v.x, bits), truncate(v.y, bits), truncate(v.z, bits)])
        };
        // Local indices (few, each used several times): every vertex decoded once; indices into
        // a large shared buffer: each corner decoded where it is used.
        let table: Option<Vec<Option<[f32; 3]>>> = (max < 2 * indices.len() as u64).then(|| (0..=max).map(one).collect());
        let fetch = |i: u32| match &table {
            Some(t) => t.get(i as usize).copied().flatten(),
            None => one(i as u64),
        };
        let tris: Option<Vec<[f32; 9]>> = indices
            .chunks_exact(3)
            .map(|t| {
                let (p, q, r) = (fetch(t[0])?, fetch(t[1])?, fetch(t[2])?);
                Some([p[0], p[1], p[2], q[0], q[1], q[2], r[0], r[1], r[2]])
            })
            .collect();
        if let Some(t) = tris {
            return Ok(t);
        }
    }
    indices
        .chunks_exact(3)
        .map(|t| {
            let mut out = [0f32; 9];
            for (k, &i) in t.iter().enumerate() {
                out[3 * k..3 * k + 3].copy_from_slice(&vertex(view, format, start, stride, i, bits)?);
            }
            Ok(out)
        })
        .collect()
}

fn gather(a: &BuildTriangleClusterInfo, format: VertexFormat, view: &dyn DeviceView, need_vertices: bool) -> Result<Gathered, ClusterError> {
    let t = a.triangle_count();
    if t > MAX_TRIANGLES {
        return Err(ClusterError::TooManyTriangles(t));
    }
    if a.vertex_count() > MAX_VERTICES {
        return Err(ClusterError::TooManyVertices(a.vertex_count()));
    }
    let isize = a.index_type();
    if !matches!(isize, 1 | 2 | 4) {
        return Err(ClusterError::BadIndexType(isize));
    }
    let bits = a.position_truncate_bit_count();
    if bits > 32 {
        return Err(ClusterError::BadTruncation(bits));
    }
    let istride = if a.index_buffer_stride == 0 { isize as u64 } else { a.index_buffer_stride as u64 };
    let mut indices = Vec::with_capacity(3 * t as usize);
    let le = |b: &[u8]| b.iter().rev().fold(0u32, |acc, &x| (acc << 8) | x as u32);
    // All indices in one read where the span is readable, else one read each.
    let span = (3 * t as u64).saturating_sub(1) * istride + isize as u64;
    match view.bytes(a.index_buffer, span).filter(|_| t > 0) {
        Some(b) => indices.extend((0..3 * t as usize).map(|k| le(&b[k * istride as usize..][..isize as usize]))),
        None => {
            for k in 0..3 * t as u64 {
                indices.push(le(read(view, a.index_buffer.wrapping_add(k * istride), isize as u64, "index")?));
            }
        }
    }
    let base = a.base_geometry_index_and_geometry_flags;
    let gstride = if a.geometry_index_and_flags_buffer_stride == 0 { 4 } else { a.geometry_index_and_flags_buffer_stride as u64 };
    let mut words = Vec::with_capacity(t as usize);
    for i in 0..t as u64 {
        let own = if a.geometry_index_and_flags_buffer == 0 {
            GeometryIndexAndFlags(0)
        } else {
            let b = read(view, a.geometry_index_and_flags_buffer.wrapping_add(i * gstride), 4, "geometry index and flags")?;
            GeometryIndexAndFlags(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        };
        // The cluster's base plus the triangle's own index; flags are the union (nv-usage.md).
        let index = base.geometry_index().wrapping_add(own.geometry_index());
        words.push(GeometryIndexAndFlags::new(index, base.geometry_flags() | own.geometry_flags()).0);
    }
    let triangles = match (need_vertices, a.vertex_buffer) {
        (false, 0) => None,
        _ => Some(fetch_triangles(view, format, a.vertex_buffer, a.vertex_buffer_stride as u64, &indices, bits)?),
    };
    Ok(Gathered { indices, words, triangles })
}

fn check_dst(dst: &[u8], needed: u64) -> Result<(), ClusterError> {
    if (dst.len() as u64) < needed {
        return Err(ClusterError::DestinationTooSmall { needed, got: dst.len() as u64 });
    }
    Ok(())
}

fn put_triangles(dst: &mut [u8], at: u64, tris: &[[f32; 9]]) {
    let out = &mut dst[at as usize..][..tris.len() * TRIANGLE_SIZE as usize];
    for (d, x) in out.chunks_exact_mut(4).zip(tris.iter().flatten()) {
        d.copy_from_slice(&x.to_le_bytes());
    }
}

fn put_words(dst: &mut [u8], at: u64, words: &[u32]) {
    let out = &mut dst[at as usize..][..4 * words.len()];
    for (d, w) in out.chunks_exact_mut(4).zip(words) {
        d.copy_from_slice(&w.to_le_bytes());
    }
}

/// Writes a CLAS of `tris` (geometry words `words`) and its tree at the start of `dst`;
/// returns its size.
fn write_clas(dst: &mut [u8], mut h: ClusterHeader, tris: &[[f32; 9]], words: &[u32]) -> Result<u64, ClusterError> {
    let t = tris.len() as u64;
    if t > MAX_TRIANGLES as u64 {
        return Err(ClusterError::TooManyTriangles(t as u32));
    }
    let size = clas_size(t);
    check_dst(dst, size)?;
    let tree = build_local(tris);
    h.used_size = size;
    h.triangle_count = t as u32;
    h.bounds = tree.bounds;
    format::write_header(dst, &h);
    put_triangles(dst, HEADER_SIZE, tris);
    put_words(dst, HEADER_SIZE + t * TRIANGLE_SIZE, words);
    let order_at = clas_order_offset(t) as usize;
    let nodes_at = clas_nodes_offset(t) as usize;
    dst[order_at..order_at + tree.order.len()].copy_from_slice(&tree.order);
    dst[order_at + tree.order.len()..nodes_at].fill(0);
    dst[nodes_at..size as usize].copy_from_slice(bytemuck::cast_slice(&tree.nodes));
    Ok(size)
}

/// BUILD_TRIANGLE_CLUSTER: one CLAS from its argument record; returns its size.
pub fn build_clas(a: &BuildTriangleClusterInfo, format: VertexFormat, view: &dyn DeviceView, dst: &mut [u8]) -> Result<u64, ClusterError> {
    check_dst(dst, clas_size(a.triangle_count() as u64))?;
    let g = gather(a, format, view, true)?;
    let mut h = new_header(Kind::Clas);
    h.cluster_id = a.cluster_id;
    h.cluster_flags = a.cluster_flags;
    h.vertex_count = a.vertex_count();
    h.truncate_bits = a.position_truncate_bit_count();
    write_clas(dst, h, g.triangles.as_deref().unwrap_or(&[]), &g.words)
}

/// BUILD_TRIANGLE_CLUSTER_TEMPLATE: topology, geometry words, truncation and (with a vertex
/// buffer) the truncated triangles; `limit` is the instantiation bounding box when given.
pub fn build_template(a: &BuildTriangleClusterInfo, format: VertexFormat, limit: Option<[f32; 6]>, view: &dyn DeviceView, dst: &mut [u8]) -> Result<u64, ClusterError> {
    let t = a.triangle_count() as u64;
    check_dst(dst, template_size(t, a.vertex_buffer != 0))?;
    let g = gather(a, format, view, false)?;
    let size = template_size(t, g.triangles.is_some());
    let mut h = new_header(Kind::Template);
    h.used_size = size;
    h.cluster_id = a.cluster_id;
    h.cluster_flags = a.cluster_flags;
    h.triangle_count = t as u32;
    h.vertex_count = a.vertex_count();
    h.truncate_bits = a.position_truncate_bit_count();
    h.index_bytes = a.index_type();
    h.vertex_format = format.to_vk();
    h.has_vertices = g.triangles.is_some() as u32;
    h.bounds = limit.unwrap_or([0.0; 6]);
    format::write_header(dst, &h);
    put_words(dst, HEADER_SIZE, &g.indices);
    put_words(dst, HEADER_SIZE + 12 * t, &g.words);
    if let Some(tris) = &g.triangles {
        put_triangles(dst, HEADER_SIZE + 16 * t, tris);
    }
    Ok(size)
}

/// The template at the start of `bytes`.
fn template(bytes: &[u8]) -> Result<format::Blob<'_>, ClusterError> {
    open(bytes).filter(|b| b.kind == Kind::Template).ok_or(ClusterError::NotA("cluster template"))
}

/// INSTANTIATE_TRIANGLE_CLUSTER: a CLAS from the template in `template_bytes` with the vertices
/// the record names (or, with vertexBuffer 0, the template's own); returns its size.
pub fn instantiate(template_bytes: &[u8], a: &InstantiateClusterInfo, view: &dyn DeviceView, dst: &mut [u8]) -> Result<u64, ClusterError> {
    let tp = template(template_bytes)?;
    let th = tp.header;
    let t = th.triangle_count;
    check_dst(dst, clas_size(t as u64))?;
    let tris: Vec<[f32; 9]> = if a.vertex_buffer.start_address != 0 {
        let format = VertexFormat::from_vk(th.vertex_format).ok_or(ClusterError::NotA("cluster template"))?;
        let indices: Vec<u32> = (0..3 * t).map(|k| tp.index(k)).collect();
        fetch_triangles(view, format, a.vertex_buffer.start_address, a.vertex_buffer.stride_in_bytes, &indices, th.truncate_bits)?
    } else if th.has_vertices != 0 {
        (0..t).map(|i| tp.triangle(i)).collect()
    } else {
        return Err(ClusterError::NoVertices);
    };
    let offset = a.geometry_index_offset();
    let words: Vec<u32> = (0..t)
        .map(|i| {
            let w = GeometryIndexAndFlags(tp.word(i));
            GeometryIndexAndFlags::new(w.geometry_index().wrapping_add_signed(offset), w.geometry_flags()).0
        })
        .collect();
    let mut h = new_header(Kind::Clas);
    h.cluster_id = th.cluster_id.wrapping_add(a.cluster_id_offset);
    h.cluster_flags = th.cluster_flags;
    h.vertex_count = th.vertex_count;
    h.truncate_bits = th.truncate_bits;
    write_clas(dst, h, &tris, &words)
}

/// Bytes GET_CLUSTER_TEMPLATE_INDICES writes for a template: 3 × triangles × index size.
pub fn template_indices_size(template_bytes: &[u8]) -> Result<u64, ClusterError> {
    let h = template(template_bytes)?.header;
    Ok(3 * h.triangle_count as u64 * h.index_bytes as u64)
}

/// GET_CLUSTER_TEMPLATE_INDICES: the template's raw indices in its index type; returns the size.
pub fn template_indices(template_bytes: &[u8], dst: &mut [u8]) -> Result<u64, ClusterError> {
    let tp = template(template_bytes)?;
    let n = tp.header.index_bytes as usize;
    let size = template_indices_size(template_bytes)?;
    check_dst(dst, size)?;
    for k in 0..3 * tp.header.triangle_count {
        let v = tp.index(k).to_le_bytes();
        dst[k as usize * n..(k as usize + 1) * n].copy_from_slice(&v[..n]);
    }
    Ok(size)
}

/// The size of the cluster object (CLAS, template or cluster BLAS) at the start of `bytes`.
pub fn object_size(bytes: &[u8]) -> Option<(Kind, u64)> {
    open(bytes).map(|b| (b.kind, b.header.used_size))
}

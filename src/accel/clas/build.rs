//! CLAS and template builds, instantiation and the template index fetch. Inputs are read through
//! `DeviceView::bytes` at the addresses the argument records name; every read is checked and a
//! failure is a typed `ClusterError`, never a panic. The bytes written depend on the input only.
use super::args::{BuildTriangleClusterInfo, GeometryIndexAndFlags, InstantiateClusterInfo};
use super::format::{self, clas_nodes_offset, clas_order_offset, clas_size, new_header, open, template_size, truncate, ClusterHeader, Kind, HEADER_SIZE, TRIANGLE_SIZE};
use super::tree::{with_scratch, write_local};
use super::{ClusterError, MAX_TRIANGLES, MAX_VERTICES};
use crate::accel::input::decode_vertex;
use crate::accel::{DeviceView, VertexFormat};

/// What a CLAS or template build reads: indices, per-triangle geometry words and (if present)
/// the truncated triangles. One per thread, reused: a command fills one per cluster,
/// thousands of times.
#[derive(Default)]
struct Gathered {
    indices: Vec<u32>,
    words: Vec<u32>,
    triangles: Vec<[f32; 9]>,
    has_triangles: bool,
}

impl Gathered {
    fn tris(&self) -> &[[f32; 9]] {
        if self.has_triangles {
            &self.triangles
        } else {
            &[]
        }
    }
    /// Cleared and sized for `t` triangles.
    fn reset(&mut self, t: usize) {
        self.indices.clear();
        self.indices.resize(3 * t, 0);
        self.words.clear();
        self.words.resize(t, 0);
        self.triangles.clear();
        self.triangles.resize(t, [0.0; 9]);
        self.has_triangles = false;
    }
}

thread_local! {
    static GATHERED: std::cell::RefCell<Gathered> = std::cell::RefCell::new(Gathered::default());
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

/// Vertex `i` of `b` (read from `i` × `stride`), truncated; None past the end.
#[inline(always)]
fn decode_at(b: &[u8], format: VertexFormat, stride: usize, i: u32, bits: u32) -> Option<[f32; 3]> {
    let at = i as usize * stride;
    let v = match format {
        // The common format, read straight (what `decode_vertex` does, without its dispatch).
        VertexFormat::R32G32B32Sfloat => {
            let w = b.get(at..at + 12)?;
            let f = |k: usize| f32::from_le_bytes([w[4 * k], w[4 * k + 1], w[4 * k + 2], w[4 * k + 3]]);
            [f(0), f(1), f(2)]
        }
        _ => decode_vertex(format, b.get(at..at + format.size() as usize)?)?.to_array(),
    };
    if bits == 0 {
        return Some(v);
    }
    Some([truncate(v[0], bits), truncate(v[1], bits), truncate(v[2], bits)])
}

/// The triangles of `indices` read from `start` + index × `stride`, truncated, into `out`.
fn fetch_triangles(view: &dyn DeviceView, format: VertexFormat, start: u64, stride: u64, indices: &[u32], bits: u32, out: &mut [[f32; 9]]) -> Result<(), ClusterError> {
    let stride = if stride == 0 { format.size() as u64 } else { stride & 0xffff_ffff };
    // One read of the span the indices reach (a cluster's vertices are usually one small
    // range), decoded from there; the per-vertex reads below remain for a span that is not.
    let max = indices.iter().copied().max().unwrap_or(0) as u64;
    let span = (max * stride).checked_add(format.size() as u64);
    if let Some(b) = span.and_then(|len| view.bytes(start, len)) {
        // The common case, fp32 positions kept whole: every corner lies inside the span read.
        if format == VertexFormat::R32G32B32Sfloat && bits == 0 && cfg!(target_endian = "little") {
            let at = |i: u32| -> [f32; 3] { bytemuck::pod_read_unaligned(&b[i as usize * stride as usize..][..12]) };
            for (o, t) in out.iter_mut().zip(indices.chunks_exact(3)) {
                let (p, q, r) = (at(t[0]), at(t[1]), at(t[2]));
                *o = [p[0], p[1], p[2], q[0], q[1], q[2], r[0], r[1], r[2]];
            }
            return Ok(());
        }
        let mut ok = true;
        for (o, t) in out.iter_mut().zip(indices.chunks_exact(3)) {
            let (Some(p), Some(q), Some(r)) = (decode_at(b, format, stride as usize, t[0], bits), decode_at(b, format, stride as usize, t[1], bits), decode_at(b, format, stride as usize, t[2], bits)) else {
                ok = false;
                break;
            };
            *o = [p[0], p[1], p[2], q[0], q[1], q[2], r[0], r[1], r[2]];
        }
        if ok {
            return Ok(());
        }
    }
    for (o, t) in out.iter_mut().zip(indices.chunks_exact(3)) {
        for (k, &i) in t.iter().enumerate() {
            o[3 * k..3 * k + 3].copy_from_slice(&vertex(view, format, start, stride, i, bits)?);
        }
    }
    Ok(())
}

fn gather(a: &BuildTriangleClusterInfo, format: VertexFormat, view: &dyn DeviceView, need_vertices: bool, g: &mut Gathered) -> Result<(), ClusterError> {
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
    g.reset(t as usize);
    let istride = if a.index_buffer_stride == 0 { isize as u64 } else { a.index_buffer_stride as u64 };
    let indices = &mut g.indices[..];
    let le = |b: &[u8]| b.iter().rev().fold(0u32, |acc, &x| (acc << 8) | x as u32);
    // All indices in one read where the span is readable, else one read each.
    let span = (3 * t as u64).saturating_sub(1) * istride + isize as u64;
    match view.bytes(a.index_buffer, span).filter(|_| t > 0) {
        Some(b) => match (isize, istride) {
            (2, 2) => indices.iter_mut().zip(b.chunks_exact(2)).for_each(|(i, c)| *i = u16::from_le_bytes([c[0], c[1]]) as u32),
            (4, 4) => indices.iter_mut().zip(b.chunks_exact(4)).for_each(|(i, c)| *i = u32::from_le_bytes([c[0], c[1], c[2], c[3]])),
            _ => indices.iter_mut().enumerate().for_each(|(k, i)| *i = le(&b[k * istride as usize..][..isize as usize])),
        },
        None => {
            for (k, i) in indices.iter_mut().enumerate() {
                *i = le(read(view, a.index_buffer.wrapping_add(k as u64 * istride), isize as u64, "index")?);
            }
        }
    }
    let base = a.base_geometry_index_and_geometry_flags;
    let gstride = if a.geometry_index_and_flags_buffer_stride == 0 { 4 } else { a.geometry_index_and_flags_buffer_stride as u64 };
    for (i, w) in g.words.iter_mut().enumerate() {
        let own = if a.geometry_index_and_flags_buffer == 0 {
            GeometryIndexAndFlags(0)
        } else {
            let b = read(view, a.geometry_index_and_flags_buffer.wrapping_add(i as u64 * gstride), 4, "geometry index and flags")?;
            GeometryIndexAndFlags(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        };
        // The cluster's base plus the triangle's own index; flags are the union (nv-usage.md).
        let index = base.geometry_index().wrapping_add(own.geometry_index());
        *w = GeometryIndexAndFlags::new(index, base.geometry_flags() | own.geometry_flags()).0;
    }
    g.has_triangles = need_vertices || a.vertex_buffer != 0;
    if g.has_triangles {
        fetch_triangles(view, format, a.vertex_buffer, a.vertex_buffer_stride as u64, &g.indices, bits, &mut g.triangles)?;
    }
    Ok(())
}

fn check_dst(dst: &[u8], needed: u64) -> Result<(), ClusterError> {
    if (dst.len() as u64) < needed {
        return Err(ClusterError::DestinationTooSmall { needed, got: dst.len() as u64 });
    }
    Ok(())
}

fn put_triangles(dst: &mut [u8], at: u64, tris: &[[f32; 9]]) {
    let out = &mut dst[at as usize..][..tris.len() * TRIANGLE_SIZE as usize];
    if cfg!(target_endian = "little") {
        out.copy_from_slice(bytemuck::cast_slice(tris));
        return;
    }
    for (d, x) in out.chunks_exact_mut(4).zip(tris.iter().flatten()) {
        d.copy_from_slice(&x.to_le_bytes());
    }
}

fn put_words(dst: &mut [u8], at: u64, words: &[u32]) {
    let out = &mut dst[at as usize..][..4 * words.len()];
    if cfg!(target_endian = "little") {
        out.copy_from_slice(bytemuck::cast_slice(words));
        return;
    }
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
    let order_at = clas_order_offset(t) as usize;
    let nodes_at = clas_nodes_offset(t) as usize;
    let (head, nodes) = dst[..size as usize].split_at_mut(nodes_at);
    let (head, order) = head.split_at_mut(order_at);
    let (order, pad) = order.split_at_mut(t as usize);
    h.used_size = size;
    h.triangle_count = t as u32;
    h.bounds = write_local(tris, order, nodes);
    pad.fill(0);
    format::write_header(head, &h);
    put_triangles(head, HEADER_SIZE, tris);
    put_words(head, HEADER_SIZE + t * TRIANGLE_SIZE, words);
    Ok(size)
}

/// BUILD_TRIANGLE_CLUSTER: one CLAS from its argument record; returns its size.
pub fn build_clas(a: &BuildTriangleClusterInfo, format: VertexFormat, view: &dyn DeviceView, dst: &mut [u8]) -> Result<u64, ClusterError> {
    check_dst(dst, clas_size(a.triangle_count() as u64))?;
    with_scratch(&GATHERED, |g| {
        gather(a, format, view, true, g)?;
        let mut h = new_header(Kind::Clas);
        h.cluster_id = a.cluster_id;
        h.cluster_flags = a.cluster_flags;
        h.vertex_count = a.vertex_count();
        h.truncate_bits = a.position_truncate_bit_count();
        write_clas(dst, h, g.tris(), &g.words)
    })
}

/// BUILD_TRIANGLE_CLUSTER_TEMPLATE: topology, geometry words, truncation and (with a vertex
/// buffer) the truncated triangles; `limit` is the instantiation bounding box when given.
pub fn build_template(a: &BuildTriangleClusterInfo, format: VertexFormat, limit: Option<[f32; 6]>, view: &dyn DeviceView, dst: &mut [u8]) -> Result<u64, ClusterError> {
    let t = a.triangle_count() as u64;
    check_dst(dst, template_size(t, a.vertex_buffer != 0))?;
    with_scratch(&GATHERED, |g| {
        gather(a, format, view, false, g)?;
        let size = template_size(t, g.has_triangles);
        let mut h = new_header(Kind::Template);
        h.used_size = size;
        h.cluster_id = a.cluster_id;
        h.cluster_flags = a.cluster_flags;
        h.triangle_count = t as u32;
        h.vertex_count = a.vertex_count();
        h.truncate_bits = a.position_truncate_bit_count();
        h.index_bytes = a.index_type();
        h.vertex_format = format.to_vk();
        h.has_vertices = g.has_triangles as u32;
        h.bounds = limit.unwrap_or([0.0; 6]);
        format::write_header(dst, &h);
        put_words(dst, HEADER_SIZE, &g.indices);
        put_words(dst, HEADER_SIZE + 12 * t, &g.words);
        if g.has_triangles {
            put_triangles(dst, HEADER_SIZE + 16 * t, g.tris());
        }
        Ok(size)
    })
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
    let t = th.triangle_count as usize;
    check_dst(dst, clas_size(t as u64))?;
    with_scratch(&GATHERED, |g| {
        g.reset(t);
        if a.vertex_buffer.start_address != 0 {
            let format = VertexFormat::from_vk(th.vertex_format).ok_or(ClusterError::NotA("cluster template"))?;
            let raw = &tp.bytes[HEADER_SIZE as usize..][..12 * t];
            g.indices.iter_mut().zip(raw.chunks_exact(4)).for_each(|(i, c)| *i = u32::from_le_bytes([c[0], c[1], c[2], c[3]]));
            fetch_triangles(view, format, a.vertex_buffer.start_address, a.vertex_buffer.stride_in_bytes, &g.indices, th.truncate_bits, &mut g.triangles)?;
        } else if th.has_vertices != 0 {
            g.triangles.iter_mut().enumerate().for_each(|(i, x)| *x = tp.triangle(i as u32));
        } else {
            return Err(ClusterError::NoVertices);
        }
        let offset = a.geometry_index_offset();
        for (i, w) in g.words.iter_mut().enumerate() {
            let gw = GeometryIndexAndFlags(tp.word(i as u32));
            *w = GeometryIndexAndFlags::new(gw.geometry_index().wrapping_add_signed(offset), gw.geometry_flags()).0;
        }
        let mut h = new_header(Kind::Clas);
        h.cluster_id = th.cluster_id.wrapping_add(a.cluster_id_offset);
        h.cluster_flags = th.cluster_flags;
        h.vertex_count = th.vertex_count;
        h.truncate_bits = th.truncate_bits;
        write_clas(dst, h, &g.triangles, &g.words)
    })
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

//! `--render`: primary rays through Arbor's built structure on the host
//! (`arbor::accel::closest_hit`, BLAS payloads at their device addresses for a TLAS), shaded by
//! the geometric normal with a head light.
use arbor::accel::{self, MapView, Ray, RayFlags};
use glam::Vec3;

use crate::work::RenderData;

fn mul3(m: &[f32; 12], v: Vec3) -> Vec3 {
    Vec3::new(
        m[0] * v.x + m[1] * v.y + m[2] * v.z,
        m[4] * v.x + m[5] * v.y + m[6] * v.z,
        m[8] * v.x + m[9] * v.y + m[10] * v.z,
    )
}

/// RGB pixels (row by row) of the scene seen from a fixed direction, framing its bounds.
pub fn render(data: &RenderData, width: u32, height: u32) -> Result<Vec<u8>, String> {
    let h = accel::header(&data.top).ok_or("the structure to render has no valid header")?;
    let b = h.bounds;
    let lo = Vec3::new(b[0], b[1], b[2]);
    let hi = Vec3::new(b[3], b[4], b[5]);
    let center = (lo + hi) * 0.5;
    let radius = ((hi - lo) * 0.5).length().max(1e-6);
    let eye_dir = Vec3::new(0.55, 0.5, 1.0).normalize();
    let eye = center + eye_dir * radius * 2.3;
    let forward = (center - eye).normalize();
    let right = forward.cross(Vec3::Y).normalize();
    let up = right.cross(forward);
    let tan = (22.5f32).to_radians().tan();
    let aspect = width as f32 / height as f32;
    let mut view = MapView::new();
    for (addr, p) in &data.blases {
        view.insert(*addr, p.clone());
    }
    let light = (-forward + up * 0.6 + right * -0.3).normalize();
    let shade_row = |y: u32, out: &mut [u8]| {
        for x in 0..width {
            let sx = (2.0 * (x as f32 + 0.5) / width as f32 - 1.0) * tan * aspect;
            let sy = (1.0 - 2.0 * (y as f32 + 0.5) / height as f32) * tan;
            let dir = (forward + right * sx + up * sy).normalize();
            let ray = Ray { origin: eye, direction: dir, tmin: 0.0, tmax: f32::INFINITY };
            let px = &mut out[3 * x as usize..3 * x as usize + 3];
            let hit = accel::closest_hit(&data.top, &view, ray, RayFlags(0), 0xFF);
            let color = match hit {
                Some(hit) => {
                    let mesh_index = if data.records.is_empty() {
                        0
                    } else {
                        let r = data.records.get(hit.instance_index as usize).map(|r| r.reference).unwrap_or(0);
                        data.blases.iter().position(|(a, _)| *a == r).unwrap_or(0)
                    };
                    let n = match data.meshes.get(mesh_index) {
                        Some(m) if (hit.primitive_index as usize) < m.triangle_count() => {
                            let t = m.triangle(hit.primitive_index as usize);
                            let (v0, v1, v2) = (Vec3::from(t[0]), Vec3::from(t[1]), Vec3::from(t[2]));
                            let n = (v1 - v0).cross(v2 - v0);
                            let n = if data.records.is_empty() { n } else { mul3(&hit.object_to_world, n) };
                            n.normalize_or(Vec3::Y)
                        }
                        _ => Vec3::Y,
                    };
                    let n = if n.dot(dir) > 0.0 { -n } else { n };
                    let diffuse = n.dot(light).max(0.0);
                    let base = Vec3::new(0.55, 0.6, 0.68) + n * 0.25;
                    let c = base * (0.2 + 0.8 * diffuse) + Vec3::splat(0.25 * diffuse.powi(24));
                    [c.x, c.y, c.z]
                }
                None => {
                    let g = 0.5 + 0.5 * sy / tan;
                    [0.08 + 0.10 * g, 0.09 + 0.12 * g, 0.13 + 0.2 * g]
                }
            };
            for k in 0..3 {
                px[k] = (color[k].clamp(0.0, 1.0).powf(1.0 / 2.2) * 255.0 + 0.5) as u8;
            }
        }
    };
    let mut rgb = vec![0u8; (width * height * 3) as usize];
    let workers = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1).max(1);
    let row_bytes = width as usize * 3;
    let rows_per = (height as usize).div_ceil(workers).max(1);
    std::thread::scope(|sc| {
        for (k, block) in rgb.chunks_mut(rows_per * row_bytes).enumerate() {
            let shade_row = &shade_row;
            sc.spawn(move || {
                for (j, row) in block.chunks_mut(row_bytes).enumerate() {
                    shade_row((k * rows_per + j) as u32, row);
                }
            });
        }
    });
    Ok(rgb)
}

// WGSL twin of vk_arith_f.comp (naga → SPIR-V).
@group(0) @binding(0) var<storage, read> src: array<f32>;
@group(0) @binding(1) var<storage, read_write> dst: array<f32>;

@compute @workgroup_size(32)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let x = src[i];
    let y = x * 1.5 + f32(i) / 4.0;
    dst[i] = sqrt(abs(y)) + floor(x) - min(x, 2.0) * max(y, -1.0);
}

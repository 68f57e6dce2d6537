// WGSL twin of vk_shared.comp (naga → SPIR-V).
@group(0) @binding(0) var<storage, read> src: array<u32>;
@group(0) @binding(1) var<storage, read_write> sums: array<u32>;
@group(0) @binding(2) var<storage, read_write> rot: array<u32>;
var<workgroup> tile: array<u32, 128>;

@compute @workgroup_size(128)
fn main(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(global_invocation_id) gid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let l = lid.x;
    tile[l] = src[gid.x];
    workgroupBarrier();
    rot[gid.x] = tile[(l + 1u) % 128u];
    workgroupBarrier();
    for (var stride = 64u; stride > 0u; stride = stride >> 1u) {
        if (l < stride) { tile[l] += tile[l + stride]; }
        workgroupBarrier();
    }
    if (l == 0u) { sums[wid.x] = tile[0]; }
}

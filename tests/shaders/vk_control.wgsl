// WGSL twin of vk_control.comp (naga → SPIR-V).
@group(0) @binding(0) var<storage, read> src: array<u32>;
@group(0) @binding(1) var<storage, read_write> dst: array<u32>;

fn collatz(x0: u32) -> u32 {
    var x = x0;
    var steps = 0u;
    while (x != 1u && steps < 500u) {
        if ((x & 1u) == 1u) { x = 3u * x + 1u; } else { x = x / 2u; }
        steps++;
    }
    return steps;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let x = src[i];
    var acc = 0u;
    for (var k = 0u; k < (x & 31u); k++) {
        if (k % 3u == 0u) { continue; }
        if (acc > 1000u) { break; }
        acc += k * k;
    }
    switch (x % 4u) {
        case 0u: { acc += 7u; }
        case 1u: { acc ^= 0xFFu; }
        case 2u: { acc = acc * 3u; }
        default: { acc += collatz(x + 1u); }
    }
    dst[i] = acc;
}

#version 450
// Control flow through the Vulkan API: loops with break/continue, a switch, a function call,
// divergent branches between lanes of one subgroup.
layout(local_size_x = 64) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint a[]; } src;
layout(set = 0, binding = 1, std430) buffer Out { uint u[]; } dst;

uint collatz(uint x) {
    uint steps = 0u;
    while (x != 1u && steps < 500u) {
        x = (x & 1u) == 1u ? 3u * x + 1u : x / 2u;
        steps++;
    }
    return steps;
}

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint x = src.a[i];
    uint acc = 0u;
    for (uint k = 0u; k < (x & 31u); k++) {
        if (k % 3u == 0u) continue;
        if (acc > 1000u) break;
        acc += k * k;
    }
    switch (x % 4u) {
        case 0u: acc += 7u; break;
        case 1u: acc ^= 0xFFu; break;
        case 2u: acc = acc * 3u; break;
        default: acc += collatz(x + 1u); break;
    }
    dst.u[i] = acc;
}

#version 450
// Branches that if-conversion turns into selects (diamonds, triangles, && and ||, a swap, a
// division whose divisor is zero on the lanes that do not take it) beside branches it must
// keep (a store, a subgroup op), and loops whose lanes leave at different rounds.
#extension GL_KHR_shader_subgroup_arithmetic : require
layout(local_size_x = 64) in;
layout(std430, set = 0, binding = 0) buffer Out { uint r[]; };
layout(std430, set = 0, binding = 1) buffer In { uint v[]; };
layout(push_constant) uniform P { uint n; uint k; };

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= n) {
        return;
    }
    uint a = v[i];
    uint b = a * 2654435761u;
    uint c;
    if ((b & 7u) != 0u) {
        c = a / (b & 7u);
    } else {
        c = a + k;
    }
    if (a > k) {
        c += a % 13u;
    }
    bool p = (a & 16u) != 0u && (b >> 28) > 3u;
    bool q = (a & 32u) != 0u || c < 1000u;
    uint d = (p ? 5u : 0u) + (q ? 7u : 0u);
    if (p) {
        if (q) {
            d += 100u;
        } else {
            d += 200u;
        }
    }
    uint u = a;
    uint w = b;
    if ((a & 128u) != 0u) {
        uint t = u;
        u = w;
        w = t;
    }
    if ((a & 64u) != 0u) {
        r[n + i] = c;
    }
    uint e = 0u;
    if ((a & 1u) != 0u) {
        e = subgroupAdd(1u);
    }
    uint s = 0u;
    for (uint j = 0u; j < (a & 31u); j++) {
        if ((j & 3u) == 2u) {
            continue;
        }
        if (s > 200u + k) {
            break;
        }
        s += j * (c & 7u);
    }
    uint x = a + 1u;
    uint steps = 0u;
    while (x > 1u && steps < 64u) {
        if ((x & 1u) != 0u) {
            x = 3u * x + 1u;
        } else {
            x >>= 1u;
        }
        steps++;
    }
    r[i] = c ^ (d << 8) ^ (s << 12) ^ (steps << 24) ^ (u - w) ^ (e << 20);
}

#version 450
// Structured control flow: if/else, loops with break/continue, a switch, function calls,
// structs, arrays and vectors.
layout(local_size_x = 32) in;
struct Pair { uint a; float b; uvec2 v; };
layout(set = 0, binding = 0, std430) readonly buffer In { uint n[]; };
layout(set = 0, binding = 1, std430) buffer Out { Pair p[]; };

uint collatz(uint x) {
    uint steps = 0u;
    while (x != 1u && steps < 1000u) {
        if ((x & 1u) == 0u) { x /= 2u; } else { x = 3u * x + 1u; }
        steps++;
    }
    return steps;
}

float weird(uint x) {
    float acc = 0.0;
    for (uint k = 0u; k < 16u; k++) {
        if (k == x % 7u) continue;
        if (k > 4u + x % 9u) break;
        acc += float(k) * 0.25;
    }
    return acc;
}

uint pick(uint x) {
    switch (x % 5u) {
        case 0u: return 10u;
        case 1u: return 20u;
        case 3u: x = x * 2u; break;
        default: x = x + 7u;
    }
    return x;
}

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint x = n[i];
    uint arr[4] = uint[4](x, x + 1u, x + 2u, x + 3u);
    uint s = 0u;
    for (int k = 0; k < 4; k++) s += arr[(k + int(x)) & 3] * uint(k + 1);
    Pair q;
    q.a = collatz(x + 1u) + s;
    q.b = weird(x);
    q.v = uvec2(pick(x), pick(x + 1u)).yx;
    p[i] = q;
}

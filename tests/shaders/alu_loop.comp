#version 450
// ALU-heavy loop for the bench: float and integer work, divergent trip counts.
layout(local_size_x = 64) in;
layout(set = 0, binding = 0, std430) buffer Out { uint o[]; };

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint h = i * 2654435761u;
    float x = float(i & 1023u) * 0.001;
    uint n = 64u + (h >> 26);
    for (uint k = 0u; k < n; k++) {
        h ^= h << 13; h ^= h >> 17; h ^= h << 5;
        x = x * 0.75 + float(h & 255u) * 0.01;
        if ((h & 3u) == 0u) x = sqrt(x + 1.0);
    }
    o[i] = h ^ floatBitsToUint(x);
}

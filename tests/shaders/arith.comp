#version 450
// Integer and float arithmetic on an SSBO: the thinnest end-to-end path.
layout(local_size_x = 64) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint a[]; } src;
layout(set = 0, binding = 1, std430) buffer Out { uint u[]; } dst;
layout(set = 0, binding = 2, std430) buffer OutF { float g[]; } dstf;

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint x = src.a[i];
    dst.u[i] = x * 3u + (x >> 2) - (x ^ 0x55u) + i;
    dstf.g[i] = float(x) * 0.5 + 1.25 / (float(i) + 1.0);
}

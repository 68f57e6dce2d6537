#version 450
// Workgroup shared memory and barriers: a tree reduction per workgroup, then each invocation
// reads a neighbour's value written before a barrier.
layout(local_size_x = 128) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint a[]; } src;
layout(set = 0, binding = 1, std430) buffer Sums { uint s[]; } sums;
layout(set = 0, binding = 2, std430) buffer Rot { uint r[]; } rot;
shared uint tile[128];

void main() {
    uint l = gl_LocalInvocationID.x;
    uint i = gl_GlobalInvocationID.x;
    tile[l] = src.a[i];
    barrier();
    rot.r[i] = tile[(l + 1u) % 128u];
    barrier();
    for (uint stride = 64u; stride > 0u; stride >>= 1) {
        if (l < stride) tile[l] += tile[l + stride];
        barrier();
    }
    if (l == 0u) sums.s[gl_WorkGroupID.x] = tile[0];
}

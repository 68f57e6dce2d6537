#version 450
// Atomics on storage buffers (32- and 64-bit) and on shared memory.
#extension GL_EXT_shader_atomic_int64 : require
#extension GL_ARB_gpu_shader_int64 : require
layout(local_size_x = 64) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint a[]; } src;
layout(set = 0, binding = 1, std430) buffer Counters { uint count; uint maxv; uint minv; uint orv; uint64_t sum64; uint bins[16]; } c;
layout(set = 0, binding = 2, std430) buffer Groups { uint g[]; } groups;
shared uint local_sum;

void main() {
    uint x = src.a[gl_GlobalInvocationID.x];
    if (gl_LocalInvocationID.x == 0u) local_sum = 0u;
    barrier();
    atomicAdd(local_sum, x & 0xFFFFu);
    atomicAdd(c.count, 1u);
    atomicMax(c.maxv, x);
    atomicMin(c.minv, x);
    atomicOr(c.orv, 1u << (x % 32u));
    atomicAdd(c.sum64, uint64_t(x) << 8);
    atomicAdd(c.bins[x % 16u], 1u);
    barrier();
    if (gl_LocalInvocationID.x == 0u) groups.g[gl_WorkGroupID.x] = local_sum;
}

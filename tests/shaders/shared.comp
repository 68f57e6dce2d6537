#version 450
// Workgroup shared memory, barriers (a tree reduction), and atomics on storage buffers and on
// shared memory.
layout(local_size_x = 64) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint v[]; };
layout(set = 0, binding = 1, std430) buffer Out { uint reversed[]; };
layout(set = 0, binding = 2, std430) buffer Sums { uint sums[]; };
layout(set = 0, binding = 3, std430) buffer Global { uint total; uint maxv; uint minv; uint ored; uint swapped; int signed_min; };

shared uint tile[64];
shared uint counter;
shared uint bits;

void main() {
    uint l = gl_LocalInvocationID.x;
    uint g = gl_GlobalInvocationID.x;
    uint x = v[g];
    if (l == 0u) { counter = 0u; bits = 0u; }
    tile[l] = x;
    barrier();
    reversed[g] = tile[63u - l];
    atomicAdd(counter, x & 0xFFu);
    atomicOr(bits, 1u << (x % 32u));
    barrier();
    for (uint stride = 32u; stride > 0u; stride >>= 1) {
        if (l < stride) tile[l] += tile[l + stride];
        barrier();
    }
    if (l == 0u) {
        sums[3u * gl_WorkGroupID.x] = tile[0];
        sums[3u * gl_WorkGroupID.x + 1u] = counter;
        sums[3u * gl_WorkGroupID.x + 2u] = bits;
    }
    atomicAdd(total, x & 0xFFFu);
    atomicMax(maxv, x);
    atomicMin(minv, x);
    atomicOr(ored, x & 0xF0F0u);
    atomicCompSwap(swapped, 0u, g + 1u);
    atomicMin(signed_min, int(x));
}

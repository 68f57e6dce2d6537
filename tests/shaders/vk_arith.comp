#version 450
// SSBO arithmetic through the Vulkan API: 32-bit integer and float ops, 64-bit integers.
#extension GL_ARB_gpu_shader_int64 : require
layout(local_size_x = 64) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint a[]; } src;
layout(set = 0, binding = 1, std430) buffer Out { uint u[]; } dst;
layout(set = 0, binding = 2, std430) buffer Out64 { uint64_t w[]; } dst64;

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint x = src.a[i];
    dst.u[i] = x * 2654435761u + (x >> 3) - (x ^ 0xA5A5u) + i;
    dst64.w[i] = uint64_t(x) * uint64_t(0x100000001ul) + uint64_t(i);
}

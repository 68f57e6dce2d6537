#version 450
// Subgroup operations on 64-bit integers and doubles (shaderSubgroupExtendedTypes with
// shaderInt64/shaderFloat64): reduction and broadcast per subgroup.
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_ballot : require
#extension GL_EXT_shader_subgroup_extended_types_int64 : require
#extension GL_ARB_gpu_shader_int64 : require
layout(local_size_x = 32) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint64_t a[]; } src;
// Per invocation: global subgroup id, sum, max, broadcast-first, double sum.
layout(set = 0, binding = 1, std430) buffer Out { uint64_t r[]; } dst;

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint64_t x = src.a[i];
    double d = double(x & 0xFFFFFul) * 0.5;
    dst.r[i * 5u + 0u] = uint64_t(gl_SubgroupID + gl_WorkGroupID.x * gl_NumSubgroups);
    dst.r[i * 5u + 1u] = subgroupAdd(x);
    dst.r[i * 5u + 2u] = subgroupMax(x);
    dst.r[i * 5u + 3u] = subgroupBroadcastFirst(x);
    dst.r[i * 5u + 4u] = uint64_t(subgroupAdd(d) * 2.0);
}

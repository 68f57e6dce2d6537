#version 450
// Subgroups: arithmetic, ballot, vote, elect, broadcast, shuffle. Each invocation also writes
// its subgroup id and invocation id so the test groups lanes exactly as the driver did.
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_ballot : require
#extension GL_KHR_shader_subgroup_vote : require
#extension GL_KHR_shader_subgroup_shuffle : require
layout(local_size_x = 64) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint a[]; } src;
// Per invocation: subgroup id, invocation id, sum, inclusive sum, max, ballot count of odd
// values, all-equal flag of x/1000, elect, broadcast of lane 0, shuffle xor 1.
layout(set = 0, binding = 1, std430) buffer Out { uint r[]; } dst;

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint x = src.a[i];
    uint base = i * 10u;
    dst.r[base + 0u] = gl_SubgroupID + gl_WorkGroupID.x * gl_NumSubgroups;
    dst.r[base + 1u] = gl_SubgroupInvocationID;
    dst.r[base + 2u] = subgroupAdd(x);
    dst.r[base + 3u] = subgroupInclusiveAdd(x);
    dst.r[base + 4u] = subgroupMax(x);
    dst.r[base + 5u] = subgroupBallotBitCount(subgroupBallot((x & 1u) == 1u));
    dst.r[base + 6u] = subgroupAllEqual(x / 1000u) ? 1u : 0u;
    dst.r[base + 7u] = subgroupElect() ? 1u : 0u;
    dst.r[base + 8u] = subgroupBroadcast(x, 0u);
    dst.r[base + 9u] = subgroupShuffleXor(x, 1u);
}

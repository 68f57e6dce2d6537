#version 450
// Subgroup basic, vote, ballot and arithmetic operations, uniform and divergent.
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_vote : require
#extension GL_KHR_shader_subgroup_ballot : require
#extension GL_KHR_shader_subgroup_arithmetic : require
layout(local_size_x = 32) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint v[]; };
layout(set = 0, binding = 1, std430) buffer Out { uint o[]; };

void main() {
    uint g = gl_GlobalInvocationID.x;
    uint x = v[g];
    uint b = 16u * g;
    o[b + 0] = gl_SubgroupSize * 1000u + gl_SubgroupInvocationID * 10u + (subgroupElect() ? 1u : 0u);
    o[b + 1] = (subgroupAll(x > 5u) ? 1u : 0u) + (subgroupAny(x > 90u) ? 2u : 0u) + (subgroupAllEqual(x / 1000u) ? 4u : 0u);
    o[b + 2] = subgroupBroadcast(x, 3u) + subgroupBroadcastFirst(x * 2u);
    uvec4 ballot = subgroupBallot((x & 1u) == 1u);
    o[b + 3] = ballot.x;
    o[b + 4] = subgroupBallotBitCount(ballot) + 100u * subgroupBallotInclusiveBitCount(ballot) + 10000u * subgroupBallotExclusiveBitCount(ballot);
    o[b + 5] = subgroupBallotFindLSB(ballot) + 100u * subgroupBallotFindMSB(ballot) + (subgroupBallotBitExtract(ballot, 2u) ? 10000u : 0u);
    o[b + 6] = subgroupAdd(x) ;
    o[b + 7] = subgroupMin(x) + subgroupMax(x) * 3u;
    o[b + 8] = subgroupAnd(x | 0x100u) ^ subgroupOr(x) ^ subgroupXor(x);
    o[b + 9] = subgroupInclusiveAdd(x);
    o[b + 10] = subgroupExclusiveAdd(x);
    o[b + 11] = floatBitsToUint(subgroupAdd(float(x) * 0.5));
    if (x % 3u == 0u) {
        o[b + 12] = subgroupAdd(x) + (subgroupElect() ? 1u : 0u);
        o[b + 13] = subgroupBallot(true).x;
    } else {
        o[b + 12] = subgroupMul(x % 4u + 1u);
        o[b + 13] = subgroupExclusiveAdd(1u);
    }
    o[b + 14] = uint(subgroupMin(int(x) - 50));
    o[b + 15] = gl_SubgroupEqMask.x | (gl_SubgroupLtMask.x << 8);
}

#version 450
// Subgroup shuffles: by index, xor, up and down.
#extension GL_KHR_shader_subgroup_shuffle : require
#extension GL_KHR_shader_subgroup_shuffle_relative : require
layout(local_size_x = 32) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint v[]; };
layout(set = 0, binding = 1, std430) buffer Out { uvec4 o[]; };

void main() {
    uint g = gl_GlobalInvocationID.x;
    uint x = v[g];
    uint l = gl_SubgroupInvocationID;
    o[g] = uvec4(subgroupShuffle(x, (l + 3u) % gl_SubgroupSize),
                 subgroupShuffleXor(x, 5u),
                 subgroupShuffleUp(x, 1u),
                 subgroupShuffleDown(x, 2u));
}

#version 450
// Dispatch geometry: what each invocation sees of its workgroup and the dispatch. For
// vkCmdDispatchBase, gl_WorkGroupID includes the base; the test indexes by it.
layout(local_size_x = 4, local_size_y = 2, local_size_z = 1) in;
layout(set = 0, binding = 0, std430) buffer Out { uint r[]; } dst;

void main() {
    uvec3 g = gl_WorkGroupID;
    uint group = g.x + 8u * (g.y + 8u * g.z);
    uint slot = (group * 8u + gl_LocalInvocationIndex) * 4u;
    dst.r[slot + 0u] = 1u + gl_GlobalInvocationID.x + 100u * gl_GlobalInvocationID.y + 10000u * gl_GlobalInvocationID.z;
    dst.r[slot + 1u] = gl_NumWorkGroups.x + 100u * gl_NumWorkGroups.y + 10000u * gl_NumWorkGroups.z;
    dst.r[slot + 2u] = gl_LocalInvocationIndex;
    dst.r[slot + 3u] = group;
}

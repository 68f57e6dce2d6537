#version 460
// An array of acceleration-structure descriptors indexed by a push constant: lanes trace
// down at x = 0.5 or x = 5.5; the test puts a quad under one of them in each structure.
#extension GL_EXT_ray_query : require
layout(local_size_x = 8) in;
layout(set = 0, binding = 0, std430) buffer Out { uint o[]; };
layout(set = 0, binding = 1) uniform accelerationStructureEXT tlases[2];
layout(push_constant) uniform Push { uint pick; } pc;

void main() {
    uint i = gl_GlobalInvocationID.x;
    float x = i % 2u == 0u ? 0.5 : 5.5;
    rayQueryEXT rq;
    rayQueryInitializeEXT(rq, tlases[pc.pick], gl_RayFlagsOpaqueEXT, 0xFF, vec3(x, 0.5, -1.0), 0.0, vec3(0.0, 0.0, 1.0), 100.0);
    while (rayQueryProceedEXT(rq)) { }
    o[i] = rayQueryGetIntersectionTypeEXT(rq, true);
}

#version 460
// A ray query on a structure named by a 64-bit device address from push constants
// (OpConvertUToAccelerationStructureKHR); with -DUNINITIALIZED, committed getters on a query
// that was never initialised.
#extension GL_EXT_ray_query : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require

layout(local_size_x = 8) in;

layout(set = 0, binding = 0, std430) buffer Out { uint o[]; };
layout(push_constant) uniform Push { uint64_t address; } pc;

void main() {
    uint i = gl_GlobalInvocationID.x;
    rayQueryEXT rq;
#ifndef UNINITIALIZED
    vec3 origin = vec3(0.25 + 0.0625 * float(i), 0.3, -1.0);
    rayQueryInitializeEXT(rq, accelerationStructureEXT(pc.address), gl_RayFlagsNoneEXT, 0xFF,
                          origin, 0.0, vec3(0.0, 0.0, 1.0), 100.0);
    uint n = 0u;
    while (rayQueryProceedEXT(rq)) {
        rayQueryConfirmIntersectionEXT(rq);
        n++;
    }
    o[4 * i + 3] = n;
#endif
    o[4 * i + 0] = rayQueryGetIntersectionTypeEXT(rq, true);
    o[4 * i + 1] = floatBitsToUint(rayQueryGetIntersectionTEXT(rq, true));
    o[4 * i + 2] = rayQueryGetIntersectionPrimitiveIndexEXT(rq, true);
}

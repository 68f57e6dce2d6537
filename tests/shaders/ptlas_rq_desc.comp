#version 460
// One ray per invocation through the structure bound at binding 2 (a PTLAS or a KHR TLAS
// descriptor: the shader type is the same) or, when pc.by_address is set, through the
// structure at a device address (OpConvertUToAccelerationStructureKHR); opaque, cull mask 0xFF:
// the committed hit's t, primitive, instance id and custom index.
#extension GL_EXT_ray_query : require

layout(local_size_x = 64) in;

struct Ray { vec4 origin_tmin; vec4 dir_tmax; };
layout(set = 0, binding = 0, std430) readonly buffer Rays { Ray rays[]; };

struct Hit { float t; uint prim; uint inst; uint custom; };
layout(set = 0, binding = 1, std430) writeonly buffer Hits { Hit hits[]; };

layout(set = 0, binding = 2) uniform accelerationStructureEXT scene;

layout(push_constant) uniform Push { uvec2 address; uint ray_count; uint by_address; } pc;

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= pc.ray_count) return;
    Ray r = rays[i];
    rayQueryEXT rq;
    if (pc.by_address != 0u) {
        rayQueryInitializeEXT(rq, accelerationStructureEXT(pc.address), gl_RayFlagsOpaqueEXT, 0xFF,
                              r.origin_tmin.xyz, r.origin_tmin.w, r.dir_tmax.xyz, r.dir_tmax.w);
    } else {
        rayQueryInitializeEXT(rq, scene, gl_RayFlagsOpaqueEXT, 0xFF,
                              r.origin_tmin.xyz, r.origin_tmin.w, r.dir_tmax.xyz, r.dir_tmax.w);
    }
    while (rayQueryProceedEXT(rq)) { }
    Hit h;
    if (rayQueryGetIntersectionTypeEXT(rq, true) == gl_RayQueryCommittedIntersectionTriangleEXT) {
        h.t = rayQueryGetIntersectionTEXT(rq, true);
        h.prim = rayQueryGetIntersectionPrimitiveIndexEXT(rq, true);
        h.inst = rayQueryGetIntersectionInstanceIdEXT(rq, true);
        h.custom = rayQueryGetIntersectionInstanceCustomIndexEXT(rq, true);
    } else {
        h.t = -1.0; h.prim = 0xFFFFFFFFu; h.inst = 0xFFFFFFFFu; h.custom = 0xFFFFFFFFu;
    }
    hits[i] = h;
}

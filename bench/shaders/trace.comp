#version 460
// arbor-bench's trace workloads: one ray per invocation through the TLAS, closest hit (opaque),
// every committed getter the comparison checks written per ray.
#extension GL_EXT_ray_query : require

layout(local_size_x = 64) in;

layout(set = 0, binding = 0) uniform accelerationStructureEXT tlas;

struct Ray { vec4 origin_tmin; vec4 dir_tmax; };
layout(set = 0, binding = 1, std430) readonly buffer Rays { Ray rays[]; };

// 32 bytes per ray; kind 0 = miss (the other fields are then 0).
struct Hit { float t; uint prim; uint inst; uint geom; vec2 bary; uint kind; uint custom; };
layout(set = 0, binding = 2, std430) writeonly buffer Hits { Hit hits[]; };

layout(push_constant) uniform Push { uint ray_count; uint flags; } pc;

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= pc.ray_count) return;
    Ray r = rays[i];

    rayQueryEXT rq;
    rayQueryInitializeEXT(rq, tlas, pc.flags | gl_RayFlagsOpaqueEXT, 0xFF,
                          r.origin_tmin.xyz, r.origin_tmin.w, r.dir_tmax.xyz, r.dir_tmax.w);
    while (rayQueryProceedEXT(rq)) { }

    Hit h;
    h.kind = rayQueryGetIntersectionTypeEXT(rq, true);
    // Committed getters only after a hit: reading them after a miss is undefined.
    if (h.kind != gl_RayQueryCommittedIntersectionNoneEXT) {
        h.t = rayQueryGetIntersectionTEXT(rq, true);
        h.prim = rayQueryGetIntersectionPrimitiveIndexEXT(rq, true);
        h.inst = rayQueryGetIntersectionInstanceIdEXT(rq, true);
        h.geom = rayQueryGetIntersectionGeometryIndexEXT(rq, true);
        h.bary = rayQueryGetIntersectionBarycentricsEXT(rq, true);
        h.custom = rayQueryGetIntersectionInstanceCustomIndexEXT(rq, true);
    } else {
        h.t = 0.0; h.prim = 0u; h.inst = 0u; h.geom = 0u; h.bary = vec2(0.0); h.custom = 0u;
    }
    hits[i] = h;
}

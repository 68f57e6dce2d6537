#version 460
// Every ray-query getter, one ray per invocation: ray flags and cull mask from push constants,
// every triangle candidate confirmed and every AABB candidate generated at its candidate t, so
// the committed hit is the closest one the traversal rules allow. Remembers whether the
// committed hit was a candidate (non-opaque) and the AABB candidate's opacity. Writes 64 words
// per ray.
#extension GL_EXT_ray_query : require

layout(local_size_x = 16) in;

layout(set = 0, binding = 0) uniform accelerationStructureEXT tlas;

struct Ray { vec4 origin_tmin; vec4 dir_tmax; };
layout(set = 0, binding = 1, std430) readonly buffer Rays { Ray rays[]; };
layout(set = 0, binding = 2, std430) writeonly buffer Out { uint o[]; };

layout(push_constant) uniform Push { uint ray_count; uint flags; uint cull; } pc;

void put3(uint at, vec3 v) { o[at] = floatBitsToUint(v.x); o[at + 1] = floatBitsToUint(v.y); o[at + 2] = floatBitsToUint(v.z); }

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= pc.ray_count) return;
    Ray r = rays[i];
    rayQueryEXT rq;
    rayQueryInitializeEXT(rq, tlas, pc.flags, pc.cull, r.origin_tmin.xyz, r.origin_tmin.w, r.dir_tmax.xyz, r.dir_tmax.w);
    uint candidates = 0u;
    uvec3 confirmed = uvec3(~0u);
    uint confirmed_opaque = 0u;
    while (rayQueryProceedEXT(rq)) {
        candidates++;
        uvec3 id = uvec3(rayQueryGetIntersectionInstanceIdEXT(rq, false),
                         rayQueryGetIntersectionGeometryIndexEXT(rq, false),
                         rayQueryGetIntersectionPrimitiveIndexEXT(rq, false));
        if (rayQueryGetIntersectionTypeEXT(rq, false) == gl_RayQueryCandidateIntersectionTriangleEXT) {
            rayQueryConfirmIntersectionEXT(rq);
            confirmed_opaque = 0u;
        } else {
            float t = rayQueryGetIntersectionTEXT(rq, false);
            if (t < rayQueryGetIntersectionTEXT(rq, true)) {
                rayQueryGenerateIntersectionEXT(rq, t);
                confirmed_opaque = rayQueryGetIntersectionCandidateAABBOpaqueEXT(rq) ? 1u : 0u;
            } else {
                continue;
            }
        }
        confirmed = id;
    }
    uint b = i * 64u;
    uint kind = rayQueryGetIntersectionTypeEXT(rq, true);
    o[b + 0] = kind;
    o[b + 1] = candidates;
    o[b + 2] = rayQueryGetRayFlagsEXT(rq);
    o[b + 3] = floatBitsToUint(rayQueryGetRayTMinEXT(rq));
    put3(b + 4, rayQueryGetWorldRayOriginEXT(rq));
    put3(b + 7, rayQueryGetWorldRayDirectionEXT(rq));
    o[b + 10] = floatBitsToUint(rayQueryGetIntersectionTEXT(rq, true));
    if (kind != gl_RayQueryCommittedIntersectionNoneEXT) {
        uvec3 id = uvec3(rayQueryGetIntersectionInstanceIdEXT(rq, true),
                         rayQueryGetIntersectionGeometryIndexEXT(rq, true),
                         rayQueryGetIntersectionPrimitiveIndexEXT(rq, true));
        o[b + 11] = id.x;
        o[b + 12] = id.y;
        o[b + 13] = id.z;
        o[b + 14] = rayQueryGetIntersectionInstanceCustomIndexEXT(rq, true);
        o[b + 15] = rayQueryGetIntersectionInstanceShaderBindingTableRecordOffsetEXT(rq, true);
        o[b + 16] = rayQueryGetIntersectionFrontFaceEXT(rq, true) ? 1u : 0u;
        vec2 bc = rayQueryGetIntersectionBarycentricsEXT(rq, true);
        o[b + 17] = floatBitsToUint(bc.x);
        o[b + 18] = floatBitsToUint(bc.y);
        o[b + 19] = (id == confirmed) ? 1u : 0u;
        o[b + 20] = confirmed_opaque;
        put3(b + 21, rayQueryGetIntersectionObjectRayOriginEXT(rq, true));
        put3(b + 24, rayQueryGetIntersectionObjectRayDirectionEXT(rq, true));
        mat4x3 m = rayQueryGetIntersectionObjectToWorldEXT(rq, true);
        mat4x3 w = rayQueryGetIntersectionWorldToObjectEXT(rq, true);
        for (int c = 0; c < 4; c++) {
            put3(b + 27 + 3 * c, m[c]);
            put3(b + 39 + 3 * c, w[c]);
        }
    }
}

#version 460
// The differential shader of the API ray-query tests (tests/rq_api_*.rs): one ray per
// invocation, each with its own ray flags, cull mask and mode. Non-opaque triangle candidates
// are confirmed (with mode bit 0: only those of even primitive index, an alpha test the
// reference can repeat exactly); AABB candidates are spheres from a table (centre, radius in
// object space; geometry g's primitive p at g * sphere_stride + p), intersected with the object
// ray and generated at their nearer t. The nearest accepted t is kept here, so no committed
// getter is read while nothing is committed (lavapipe crashes on that), and committed getters
// are read only for a committed hit. Writes 16 words per ray.
#extension GL_EXT_ray_query : require

layout(local_size_x = 32) in;

layout(set = 0, binding = 0) uniform accelerationStructureEXT tlas;

struct Ray { vec4 origin_tmin; vec4 dir_tmax; uvec4 flags_cull_mode; };
layout(set = 0, binding = 1, std430) readonly buffer Rays { Ray rays[]; };
layout(set = 0, binding = 2, std430) writeonly buffer Out { uint o[]; };
layout(set = 0, binding = 3, std430) readonly buffer Spheres { vec4 spheres[]; };

layout(push_constant) uniform Push { uint ray_count; uint sphere_stride; } pc;

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= pc.ray_count) return;
    Ray r = rays[i];
    uint flags = r.flags_cull_mode.x;
    uint mode = r.flags_cull_mode.z;
    rayQueryEXT rq;
    rayQueryInitializeEXT(rq, tlas, flags, r.flags_cull_mode.y & 0xFFu, r.origin_tmin.xyz, r.origin_tmin.w, r.dir_tmax.xyz, r.dir_tmax.w);
    float best = r.dir_tmax.w;
    uint candidates = 0u;
    uvec3 decided = uvec3(~0u);
    uint decided_opaque = 0u;
    while (rayQueryProceedEXT(rq)) {
        candidates++;
        uvec3 id = uvec3(rayQueryGetIntersectionInstanceIdEXT(rq, false),
                         rayQueryGetIntersectionGeometryIndexEXT(rq, false),
                         rayQueryGetIntersectionPrimitiveIndexEXT(rq, false));
        if (rayQueryGetIntersectionTypeEXT(rq, false) == gl_RayQueryCandidateIntersectionTriangleEXT) {
            if ((mode & 1u) != 0u && (id.z & 1u) != 0u) continue;
            float t = rayQueryGetIntersectionTEXT(rq, false);
            rayQueryConfirmIntersectionEXT(rq);
            best = t;
            decided = id;
            decided_opaque = 0u;
        } else {
            vec4 s = spheres[id.y * pc.sphere_stride + id.z];
            vec3 oc = rayQueryGetIntersectionObjectRayOriginEXT(rq, false) - s.xyz;
            vec3 d = rayQueryGetIntersectionObjectRayDirectionEXT(rq, false);
            float a = dot(d, d), b = dot(oc, d), c = dot(oc, oc) - s.w * s.w;
            float disc = b * b - a * c;
            if (disc < 0.0) continue;
            float t = (-b - sqrt(disc)) / a;
            if (t < rayQueryGetRayTMinEXT(rq) || t > best) continue;
            rayQueryGenerateIntersectionEXT(rq, t);
            best = t;
            decided = id;
            decided_opaque = rayQueryGetIntersectionCandidateAABBOpaqueEXT(rq) ? 1u : 0u;
        }
    }
    uint b = i * 16u;
    uint kind = rayQueryGetIntersectionTypeEXT(rq, true);
    for (uint k = 0u; k < 16u; k++) o[b + k] = 0u;
    o[b + 0] = kind;
    o[b + 12] = candidates;
    if (kind != gl_RayQueryCommittedIntersectionNoneEXT) {
        uvec3 id = uvec3(rayQueryGetIntersectionInstanceIdEXT(rq, true),
                         rayQueryGetIntersectionGeometryIndexEXT(rq, true),
                         rayQueryGetIntersectionPrimitiveIndexEXT(rq, true));
        o[b + 1] = floatBitsToUint(rayQueryGetIntersectionTEXT(rq, true));
        o[b + 2] = id.x;
        o[b + 3] = rayQueryGetIntersectionInstanceCustomIndexEXT(rq, true);
        o[b + 4] = id.y;
        o[b + 5] = id.z;
        o[b + 9] = rayQueryGetIntersectionInstanceShaderBindingTableRecordOffsetEXT(rq, true);
        o[b + 10] = (id == decided) ? 1u : 0u;
        o[b + 11] = decided_opaque;
    }
    if (kind == gl_RayQueryCommittedIntersectionTriangleEXT) {
        vec2 bc = rayQueryGetIntersectionBarycentricsEXT(rq, true);
        o[b + 6] = floatBitsToUint(bc.x);
        o[b + 7] = floatBitsToUint(bc.y);
        o[b + 8] = rayQueryGetIntersectionFrontFaceEXT(rq, true) ? 1u : 0u;
    }
}

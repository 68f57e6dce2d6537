#version 460
// OpRayQueryGetIntersectionClusterIdNV through a ray query. glslang 12 has no
// GL_NV_cluster_acceleration_structure and this SPIRV-Tools (2023.1) predates the extension, so
// rayQueryGetIntersectionInstanceShaderBindingTableRecordOffsetEXT stands in for
// rayQueryGetIntersectionClusterIdNV: tests/clas_rq.rs patches its opcode and adds the capability
// RayTracingClusterAccelerationStructureNV and the extension (no other use of the stand-in here).
// Ray i (origin.xyz, tmin, direction.xyz, tmax at rays[2i], rays[2i + 1]) confirms every
// candidate; hits[6i..6i + 6] = committed cluster ID, the cluster ID of the nearest candidate
// (-2: no candidate), committed primitive index, geometry index, type, t bits.
#extension GL_EXT_ray_query : require
layout(local_size_x = 64) in;
layout(set = 0, binding = 0) uniform accelerationStructureEXT tlas;
layout(set = 0, binding = 1) readonly buffer Rays { vec4 rays[]; };
layout(set = 0, binding = 2) writeonly buffer Hits { int hits[]; };
layout(push_constant) uniform Push { uint count; uint pad; };

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= count) {
        return;
    }
    vec4 o = rays[2 * i];
    vec4 d = rays[2 * i + 1];
    rayQueryEXT q;
    rayQueryInitializeEXT(q, tlas, 0, 0xFF, o.xyz, o.w, d.xyz, d.w);
    float best = d.w;
    int nearest = -2;
    while (rayQueryProceedEXT(q)) {
        float t = rayQueryGetIntersectionTEXT(q, false);
        int c = int(rayQueryGetIntersectionInstanceShaderBindingTableRecordOffsetEXT(q, false));
        if (t < best) {
            best = t;
            nearest = c;
        }
        rayQueryConfirmIntersectionEXT(q);
    }
    hits[6 * i] = int(rayQueryGetIntersectionInstanceShaderBindingTableRecordOffsetEXT(q, true));
    hits[6 * i + 1] = nearest;
    hits[6 * i + 2] = rayQueryGetIntersectionPrimitiveIndexEXT(q, true);
    hits[6 * i + 3] = rayQueryGetIntersectionGeometryIndexEXT(q, true);
    hits[6 * i + 4] = int(rayQueryGetIntersectionTypeEXT(q, true));
    hits[6 * i + 5] = floatBitsToInt(rayQueryGetIntersectionTEXT(q, true));
}

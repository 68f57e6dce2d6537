#version 450
// Odds and ends: a 3D workgroup with dispatch-base built-ins, matrices, dynamic vector and
// constant-array indexing, Private globals with initializers, struct copies, do-while and
// nested loops left through a flag, 64-bit atomics, shared arrays of structs.
#extension GL_EXT_shader_atomic_int64 : require
#extension GL_ARB_gpu_shader_int64 : require
layout(local_size_x = 4, local_size_y = 2, local_size_z = 2) in;
struct Item { uvec2 id; float w; };
layout(set = 0, binding = 0, std430) buffer Out { uint o[]; };
layout(set = 0, binding = 1, std430) buffer Acc { uint64_t sum64; uint64_t max64; Item items[]; };

const uint TABLE[5] = uint[5](3u, 1u, 4u, 1u, 5u);
uint g_seed = 17u;
shared Item tile[16];

uint next() { g_seed = g_seed * 1103515245u + 12345u; return g_seed >> 8; }

void main() {
    uint li = gl_LocalInvocationIndex;
    uvec3 wg = gl_WorkGroupID;
    uint flat_wg = wg.x + gl_NumWorkGroups.x * (wg.y + gl_NumWorkGroups.y * wg.z);
    uint g = flat_wg * 16u + li;
    uint b = 8u * g;
    o[b + 0] = gl_GlobalInvocationID.x + 100u * gl_GlobalInvocationID.y + 10000u * gl_GlobalInvocationID.z;
    o[b + 1] = gl_LocalInvocationID.x + 10u * gl_LocalInvocationID.y + 100u * gl_LocalInvocationID.z + 1000u * li;
    mat3 m = mat3(vec3(1.0, 2.0, 3.0), vec3(0.5, float(li), 1.0), vec3(-1.0, 0.0, 2.0));
    vec3 v = vec3(float(g), 1.0, 2.0);
    vec3 mv = m * v;
    vec3 vm = v * m;
    mat3 mm = m * transpose(m);
    o[b + 2] = floatBitsToUint(mv.x + mv.y * 2.0 + mv.z * 3.0 + vm.x + vm.y * 5.0 + vm.z * 7.0 + mm[1][2] + mm[2][0]);
    uvec4 q = uvec4(g, g * 2u, g * 3u, g * 4u);
    q[li % 4u] = 77u;
    o[b + 3] = q[(li + 1u) % 4u] + q[li % 4u] * 1000u + TABLE[g % 5u] * 100000u;
    uint r = 0u;
    for (int k = 0; k < 3; k++) r += next();
    o[b + 4] = r;
    uint steps = 0u;
    uint x = g;
    do { x = x / 2u + (x & 1u); steps++; } while (x > 1u && steps < 50u);
    bool found = false;
    for (uint i = 0u; i < 6u && !found; i++) {
        for (uint j = 0u; j < 6u; j++) {
            if (i * j == g % 17u) { found = true; steps += 100u * i + 10u * j; break; }
        }
    }
    o[b + 5] = steps;
    tile[li] = Item(uvec2(g, li), float(g) * 0.25);
    barrier();
    Item it = tile[15u - li];
    items[g] = it;
    o[b + 6] = it.id.x + it.id.y;
    atomicAdd(sum64, uint64_t(g) << 32 | uint64_t(g));
    atomicMax(max64, uint64_t(g) * 0x100000000ul);
    o[b + 7] = ((li > 7u) ? g : ~g) + (uvec4(g, 2u, 3u, 4u) * 2u)[li % 4u];
}

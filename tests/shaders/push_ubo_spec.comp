#version 450
// Push constants, a std140 uniform buffer, specialization constants (one used in
// OpSpecConstantOp) and a specialised workgroup size.
layout(local_size_x_id = 2) in;
layout(constant_id = 0) const uint K = 3u;
layout(constant_id = 1) const bool FLAG = false;
const uint K2 = K * 2u + 1u;
layout(push_constant) uniform Push { uint scale; float bias; uint count; } pc;
layout(set = 0, binding = 0, std140) uniform Params { vec4 tint; uint table[4]; mat2 m; } ubo;
layout(set = 0, binding = 1, std430) buffer Out { uint o[]; };

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= pc.count) return;
    uint t = ubo.table[i % 4u];
    vec2 mv = ubo.m * vec2(float(i), 1.0);
    float f = ubo.tint.y * float(i) + pc.bias + mv.x + mv.y * 0.5;
    o[2u * i] = i * pc.scale + t * K2 + (FLAG ? 1000u : 0u) + gl_WorkGroupSize.x * 100000u;
    o[2u * i + 1u] = floatBitsToUint(f);
}

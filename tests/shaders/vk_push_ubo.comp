#version 450
// Push constants, a uniform buffer (bound with a dynamic offset by the test) and
// specialization constants (one scalar, one in the workgroup size).
layout(local_size_x_id = 0) in;
layout(constant_id = 1) const uint MULTIPLIER = 1u;
layout(constant_id = 2) const bool NEGATE = false;
layout(push_constant) uniform Push { uint add; float scale; } pc;
layout(set = 0, binding = 0, std140) uniform Params { uvec4 bias; vec4 weight; } params;
layout(set = 0, binding = 1, std430) buffer Out { uint u[]; } dst;

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint v = i * MULTIPLIER + pc.add + params.bias[i % 4u];
    dst.u[i] = NEGATE ? ~v : v;
    dst.u[i + gl_NumWorkGroups.x * gl_WorkGroupSize.x] = floatBitsToUint(float(i) * pc.scale + params.weight[i % 4u]);
}

#version 450
// Out-of-bounds reads and writes driven by a push constant: contained and reported.
layout(local_size_x = 16) in;
layout(set = 0, binding = 0, std430) readonly buffer In { uint v[]; };
layout(set = 0, binding = 1, std430) buffer Out { uint o[]; };
layout(push_constant) uniform Push { uint shift; } pc;

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint x = v[i + pc.shift];
    o[i + pc.shift] = x + 1u;
}

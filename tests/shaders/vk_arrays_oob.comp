#version 450
// A descriptor-array index from a push constant that the test puts past the array's end.
layout(local_size_x = 16) in;
layout(push_constant) uniform Push { uint index; } pc;
layout(set = 0, binding = 0, std430) buffer Out { uint v[]; } outs[2];

void main() {
    uint i = gl_GlobalInvocationID.x;
    outs[pc.index].v[i] = i + 7u;
}

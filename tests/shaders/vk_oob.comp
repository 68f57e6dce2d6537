#version 450
// Out-of-bounds accesses: invocation i writes element i + offset (push constant) of a buffer
// whose descriptor range the test makes smaller than the dispatch.
layout(local_size_x = 16) in;
layout(push_constant) uniform Push { uint offset; } pc;
layout(set = 0, binding = 0, std430) buffer Out { uint u[]; } dst;
layout(set = 0, binding = 1, std430) readonly buffer In { uint a[]; } src;

void main() {
    uint i = gl_GlobalInvocationID.x;
    dst.u[i + pc.offset] = src.a[i + pc.offset] + 1u;
}

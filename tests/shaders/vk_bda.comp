#version 450
// Buffer device address: a linked structure reached through an address in push constants;
// node.next is itself an address read from device memory.
#extension GL_EXT_buffer_reference : require
#extension GL_ARB_gpu_shader_int64 : require
layout(local_size_x = 32) in;
layout(buffer_reference, std430, buffer_reference_align = 8) buffer Values { uint v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) buffer Header { Values values; uint count; uint pad; };
layout(push_constant) uniform Push { Header header; } pc;
layout(set = 0, binding = 0, std430) buffer Out { uint u[]; } dst;

void main() {
    uint i = gl_GlobalInvocationID.x;
    Header h = pc.header;
    if (i < h.count) {
        uint x = h.values.v[i];
        h.values.v[i] = x * 2u + 1u;
        dst.u[i] = x + h.count;
    }
}

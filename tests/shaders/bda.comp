#version 460
// Buffer device address: a pointer in push constants, pointer chasing through a pointer stored
// in memory, and pointer arithmetic on buffer_reference arrays and pointers.
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#extension GL_EXT_buffer_reference2 : require
layout(local_size_x = 32) in;
layout(buffer_reference, std430, buffer_reference_align = 16) buffer Vals { float s; uint pad; vec2 v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) buffer Table { Vals vals; uint n; };
layout(buffer_reference, std430, buffer_reference_align = 4) buffer Words { uint w[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) buffer Vec2Ref { vec2 v; };
layout(push_constant) uniform Push { Table table; Words out_words; uint64_t raw; } pc;

void main() {
    uint i = gl_GlobalInvocationID.x;
    Vals vals = pc.table.vals;
    if (i >= pc.table.n) return;
    vec2 v = vals.v[i];
    Words ow = Words(pc.raw + 8ul * uint64_t(i));
    ow.w[0] = floatBitsToUint(v.x * vals.s + v.y);
    // The same element again, through pointer arithmetic (OpPtrAccessChain): adds +0.0's bits.
    Vec2Ref base = Vec2Ref(uint64_t(vals) + 8ul);
    ow.w[1] = i * 7u + floatBitsToUint(base[i].v.y - v.y);
    pc.out_words.w[i] = uint(uint64_t(vals) & 0xFFFFu) + i;
}

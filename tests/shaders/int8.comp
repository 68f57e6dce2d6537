#version 450
// Uses 8-bit integers, a capability Arbor does not run: rejected at module parse.
#extension GL_EXT_shader_explicit_arithmetic_types_int8 : require
layout(local_size_x = 1) in;
layout(set = 0, binding = 0, std430) buffer Buf { uint v[]; };
void main() { int8_t a = int8_t(v[0]); v[1] = uint(a * a); }

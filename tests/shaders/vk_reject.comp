#version 450
// A valid compute shader Arbor cannot run: packHalf2x16 (GLSL.std.450 PackHalf2x16, 58) is
// not implemented by the shader library, so pipeline creation must fail and say so.
layout(local_size_x = 1) in;
layout(set = 0, binding = 0, std430) buffer Out { uint u[]; } dst;

void main() {
    dst.u[0] = packHalf2x16(vec2(uintBitsToFloat(dst.u[1]), 1.0));
}

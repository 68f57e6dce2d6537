#version 450
// Float arithmetic and GLSL.std.450 through the Vulkan API (exact ops only: + - * / sqrt
// min max floor abs are correctly rounded, so any IEEE implementation gives the same bits).
layout(local_size_x = 32) in;
layout(set = 0, binding = 0, std430) readonly buffer In { float a[]; } src;
layout(set = 0, binding = 1, std430) buffer Out { float f[]; } dst;

void main() {
    uint i = gl_GlobalInvocationID.x;
    float x = src.a[i];
    float y = x * 1.5 + float(i) / 4.0;
    dst.f[i] = sqrt(abs(y)) + floor(x) - min(x, 2.0) * max(y, -1.0);
}

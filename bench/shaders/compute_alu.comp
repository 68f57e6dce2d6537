#version 450
// ALU-bound: per invocation, `iters` rounds of 6 FMAs, sin, cos, exp and sqrt on two floats.
// The map is contractive (|x|, |y| stay small), so float rounding differences between drivers
// stay within the harness's tolerance. SALT makes every first-dispatch pipeline new.
layout(local_size_x = 64) in;
layout(constant_id = 0) const uint SALT = 0u;
layout(std430, set = 0, binding = 0) buffer Out { float v[]; };
layout(push_constant) uniform Params { uint n; uint iters; };

void main() {
    // Rows of gl_NumWorkGroups.x groups: more than maxComputeWorkGroupCount[0] groups in all.
    uint i = gl_GlobalInvocationID.y * (gl_NumWorkGroups.x * 64u) + gl_GlobalInvocationID.x;
    if (i >= n) {
        return;
    }
    float x = float(i & 1023u) * (1.0 / 1024.0);
    float y = 0.25;
    for (uint k = 0u; k < iters; ++k) {
        x = fma(x, 0.75, y * 0.125) + 0.0625;
        y = fma(y, 0.5, x * 0.25);
        float s = sin(x);
        float c = cos(y);
        x = fma(s, 0.5, x * 0.25);
        y = fma(c, 0.25, y * 0.5);
        x = fma(sqrt(x * x + 1.0), 0.25, exp(-y) * 0.125);
        y = fma(y, 0.75, x * -0.125);
    }
    v[i] = x + y + float(SALT) * (1.0 / 65536.0);
}

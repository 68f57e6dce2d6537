#version 450
// Memory-bound: one streaming read-modify-write of a uvec4 per invocation (an LCG step on
// each word), exact in integers.
layout(local_size_x = 64) in;
layout(std430, set = 0, binding = 0) buffer Data { uvec4 d[]; };
layout(push_constant) uniform Params { uint n; uint unused; };

void main() {
    // Rows of gl_NumWorkGroups.x groups: more than maxComputeWorkGroupCount[0] groups in all.
    uint i = gl_GlobalInvocationID.y * (gl_NumWorkGroups.x * 64u) + gl_GlobalInvocationID.x;
    if (i >= n) {
        return;
    }
    d[i] = d[i] * 1664525u + 1013904223u;
}

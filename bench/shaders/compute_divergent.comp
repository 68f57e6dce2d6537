#version 450
// Divergent: the Collatz step count of `first + i` (capped at `cap` steps): neighbouring
// invocations run very different loop counts and take the odd/even branch independently.
// Integer arithmetic wraps, as the CPU reference does, so the result is exact.
layout(local_size_x = 64) in;
layout(std430, set = 0, binding = 0) buffer Out { uint steps[]; };
layout(push_constant) uniform Params { uint n; uint cap; uint first; };

void main() {
    // Rows of gl_NumWorkGroups.x groups: more than maxComputeWorkGroupCount[0] groups in all.
    uint i = gl_GlobalInvocationID.y * (gl_NumWorkGroups.x * 64u) + gl_GlobalInvocationID.x;
    if (i >= n) {
        return;
    }
    uint x = first + i;
    uint s = 0u;
    while (x > 1u && s < cap) {
        if ((x & 1u) != 0u) {
            x = 3u * x + 1u;
        } else {
            x = x >> 1u;
        }
        s += 1u;
    }
    steps[i] = s;
}

#version 450
// One workgroup of 1024 invocations over 32 KiB of shared memory, with barriers between the
// phases: every invocation reads values other invocations (other lane groups) wrote, then a
// tree reduction.
layout(local_size_x = 1024) in;
layout(std430, set = 0, binding = 0) readonly buffer In { uint src[]; };
layout(std430, set = 0, binding = 1) buffer Out { uint dst[]; };
layout(std430, set = 0, binding = 2) buffer Sums { uint sums[]; };

shared uint s[8192];

void main() {
    uint l = gl_LocalInvocationIndex;
    uint base = gl_WorkGroupID.x * 8192u;
    for (uint k = 0u; k < 8u; ++k) {
        s[l + 1024u * k] = src[base + l + 1024u * k];
    }
    barrier();
    for (uint k = 0u; k < 8u; ++k) {
        uint i = l + 1024u * k;
        dst[base + i] = s[8191u - i] * 3u + l;
    }
    uint acc = 0u;
    for (uint k = 0u; k < 8u; ++k) {
        acc += s[l * 8u + k];
    }
    barrier();
    s[l] = acc;
    barrier();
    for (uint stride = 512u; stride > 0u; stride >>= 1u) {
        if (l < stride) {
            s[l] += s[l + stride];
        }
        barrier();
    }
    if (l == 0u) {
        sums[gl_WorkGroupID.x] = s[0];
    }
}

#version 450
// Image atomics (OpImageTexelPointer + OpAtomic*): a histogram in an R32_UINT storage image,
// per-bin minimum and maximum in an R32_SINT texel buffer, and a compare-exchange claim.
layout(local_size_x = 64) in;
layout(set = 0, binding = 0, r32ui) uniform uimage2D hist;
layout(set = 0, binding = 1, r32i) uniform iimageBuffer minmax;
layout(set = 0, binding = 2, std430) readonly buffer In { int values[]; };
layout(set = 0, binding = 3, std430) buffer Out { uint old[]; };

void main() {
    uint i = gl_GlobalInvocationID.x;
    int v = values[i];
    uint bin = uint(v) & 15u;
    imageAtomicAdd(hist, ivec2(int(bin % 4u), int(bin / 4u)), 1u);
    imageAtomicMin(minmax, int(2u * bin), v);
    imageAtomicMax(minmax, int(2u * bin + 1u), v);
    imageAtomicOr(hist, ivec2(int(bin % 4u), 4), 1u << (i % 32u));
    // Texel (0, 5) starts at 0: exactly one invocation swaps its id in; everyone returns the old value.
    old[i] = imageAtomicCompSwap(hist, ivec2(0, 5), 0u, i + 1u);
}

#version 450
#extension GL_EXT_nonuniform_qualifier : require
#extension GL_EXT_samplerless_texture_functions : require
// Arrays of texel buffers: uniform texel buffers read through a dynamically uniform index and
// a constant one, storage texel buffers written through a non-uniform index, with image
// atomics on an element, and each element's size queried.
layout(local_size_x = 16) in;
layout(push_constant) uniform Push { uint pick; } pc;
layout(set = 0, binding = 0) uniform utextureBuffer srcs[3];
layout(set = 0, binding = 1, r32ui) uniform uimageBuffer dsts[4];
layout(set = 0, binding = 2, std430) buffer Sizes { uint sizes[8]; };

void main() {
    int i = int(gl_GlobalInvocationID.x);
    uint a = texelFetch(srcs[pc.pick], i).x;
    uint b = texelFetch(srcs[2], i).x;
    uint e = uint(i) % 4u;
    imageStore(dsts[nonuniformEXT(e)], i / 4, uvec4(a * 10u + b));
    imageAtomicAdd(dsts[nonuniformEXT(e)], 60 + i % 4, 1u);
    if (i < 3) {
        sizes[i] = uint(textureSize(srcs[i]));
    } else if (i < 7) {
        sizes[i] = uint(imageSize(dsts[nonuniformEXT(i - 3)]));
    }
}

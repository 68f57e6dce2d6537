#version 450
#extension GL_EXT_samplerless_texture_functions : require
// Texel buffers: a uniform texel buffer read with texelFetch (OpImageFetch), a float storage
// texel buffer written, an RGBA8 storage texel buffer read and written back swizzled, and the
// sizes of both (OpImageQuerySize) recorded.
layout(local_size_x = 16) in;
layout(set = 0, binding = 0) uniform utextureBuffer src;
layout(set = 0, binding = 1, r32f) uniform writeonly imageBuffer dst;
layout(set = 0, binding = 2, rgba8) uniform imageBuffer io;
layout(set = 0, binding = 3, std430) buffer Sizes { uint sizes[2]; };

void main() {
    int i = int(gl_GlobalInvocationID.x);
    uint v = texelFetch(src, i).x;
    imageStore(dst, i, vec4(float(v) * 0.5 + 0.25));
    vec4 c = imageLoad(io, i);
    imageStore(io, i, c.wzyx);
    if (i == 0) {
        sizes[0] = uint(textureSize(src));
        sizes[1] = uint(imageSize(io));
    }
}

#version 450
// imageSize / imageLoad / imageStore on a 2D R32_UINT and a smaller 2D RGBA8 image: every
// invocation rewrites its own texel of each image it lies inside.
layout(local_size_x = 4, local_size_y = 4) in;
layout(set = 0, binding = 0, r32ui) uniform uimage2D counts;
layout(set = 0, binding = 1, rgba8) uniform image2D colors;
layout(set = 0, binding = 2) buffer Sizes { uint sizes[4]; };

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    ivec2 a = imageSize(counts);
    ivec2 b = imageSize(colors);
    if (p == ivec2(0)) {
        sizes[0] = uint(a.x);
        sizes[1] = uint(a.y);
        sizes[2] = uint(b.x);
        sizes[3] = uint(b.y);
    }
    if (all(lessThan(p, a))) {
        uint v = imageLoad(counts, p).x;
        imageStore(counts, p, uvec4(v * 3u + uint(p.x) + 100u * uint(p.y)));
    }
    if (all(lessThan(p, b))) {
        vec4 c = imageLoad(colors, p);
        imageStore(colors, p, vec4(c.g, c.r, 1.0 - c.b, c.a));
    }
}

#version 450
// Storage-image load/store/size, compiled once per (format, dimensionality) with defines:
// IMG (e.g. uimage2DArray), FMT (e.g. r32ui), T (uvec4/ivec4/vec4), DIM (1 = 1D, 2 = 2D,
// 3 = 3D, 4 = 1D array, 5 = 2D array), KIND (0 uint, 1 int, 2 float); NOGUARD skips the
// bounds check so invocations past the edge access outside the image.
layout(local_size_x = 4, local_size_y = 2, local_size_z = 1) in;
layout(set = 0, binding = 0, FMT) uniform readonly IMG src;
layout(set = 0, binding = 1, FMT) uniform writeonly IMG dst;
layout(set = 0, binding = 2) buffer Size { ivec4 size; };

#if DIM == 1
#define COORD(g) (g).x
#define SIZE4(s) ivec4(s, 0, 0, 0)
#elif DIM == 2 || DIM == 4
#define COORD(g) (g).xy
#define SIZE4(s) ivec4(s, 0, 0)
#else
#define COORD(g) (g).xyz
#define SIZE4(s) ivec4(s, 0)
#endif

T op(T v) {
#if KIND == 0
    return v * 3u + uvec4(1u, 2u, 3u, 4u);
#elif KIND == 1
    return ivec4(5, -6, 7, -8) - v;
#else
    return v * 0.5 + 0.25;
#endif
}

void main() {
    ivec3 g = ivec3(gl_GlobalInvocationID);
    ivec4 s = SIZE4(imageSize(src));
    if (g == ivec3(0)) {
        size = s;
    }
#ifndef NOGUARD
    ivec3 lim = ivec3(s.x, max(s.y, 1), max(s.z, 1));
    if (any(greaterThanEqual(g, lim))) {
        return;
    }
#endif
    imageStore(dst, COORD(g), op(imageLoad(src, COORD(g))));
}

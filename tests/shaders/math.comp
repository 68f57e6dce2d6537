#version 450
// GLSL.std.450 functions, conversions, bit operations, 64-bit integers and doubles.
#extension GL_ARB_gpu_shader_int64 : require
layout(local_size_x = 16) in;
layout(set = 0, binding = 0, std430) readonly buffer In { vec4 v[]; };
layout(set = 0, binding = 1, std430) buffer Out { uint o[]; };
layout(set = 0, binding = 2, std430) buffer Out64 { uint64_t w[]; };

void main() {
    uint i = gl_GlobalInvocationID.x;
    vec4 a = v[i];
    float x = a.x, y = a.y;
    uint u = floatBitsToUint(a.z);
    int s = int(u);
    uint b = 32u * i;
    // exactly rounded float ops
    o[b + 0] = floatBitsToUint(sqrt(abs(x)));
    o[b + 1] = floatBitsToUint(floor(x) + ceil(y) * 2.0);
    o[b + 2] = floatBitsToUint(fract(x));
    o[b + 3] = floatBitsToUint(clamp(x, -1.0, 1.0) + min(x, y) - max(x, y));
    o[b + 4] = floatBitsToUint(fma(x, y, 0.5));
    o[b + 5] = floatBitsToUint(mix(x, y, 0.25) + step(0.0, x) + sign(y));
    o[b + 6] = floatBitsToUint(trunc(x) + round(y) + roundEven(x * 3.0));
    o[b + 7] = floatBitsToUint(mod(x, 1.5) + abs(y));
    // approximate (libm) float ops
    o[b + 8] = floatBitsToUint(exp(x * 0.1) + log(abs(y) + 1.0));
    o[b + 9] = floatBitsToUint(sin(x) * cos(y) + atan(y, x) + pow(abs(x) + 1.0, 1.5));
    vec3 p = vec3(a.xy, 1.0) * vec3(1.0, 0.5, 1.0);
    vec3 q = vec3(y, 1.0, x);
    o[b + 10] = floatBitsToUint(length(p) + dot(p, q) + distance(p, q));
    vec3 n = normalize(p);
    vec3 c = cross(p, q);
    vec3 r = reflect(q, n);
    o[b + 11] = floatBitsToUint(n.x + n.y * 2.0 + c.x * 3.0 + c.y + c.z * 0.5 + r.x + r.z);
    o[b + 12] = floatBitsToUint(smoothstep(-1.0, 2.0, x) + inversesqrt(abs(y) + 1.0));
    // integer and bit ops
    o[b + 13] = uint(findLSB(u)) + uint(findMSB(u)) * 100u + uint(findMSB(s)) * 10000u;
    o[b + 14] = uint(bitCount(u)) + bitfieldReverse(u);
    o[b + 15] = bitfieldExtract(u, 3, 9) + uint(bitfieldExtract(s, 5, 7));
    o[b + 16] = bitfieldInsert(u, 0x1234u, 4, 13);
    uint hi, lo;
    umulExtended(u, 0x9E3779B9u, hi, lo);
    o[b + 17] = hi ^ lo;
    uint carry;
    uint sum = uaddCarry(u, 0xF0000000u, carry);
    o[b + 18] = sum + carry;
    o[b + 19] = uint(min(s, -5) + max(s, 7) + clamp(s, -100, 100)) + min(u, 77u) + clamp(u, 5u, 9u);
    o[b + 20] = uint(abs(s) + sign(s)) + (u % 7u) + (u / 13u);
    o[b + 21] = uint(s >> 3) ^ (u << 5) ^ ~u;
    // conversions
    o[b + 22] = uint(int(x * 100.0)) + uint(abs(y) * 10.0);
    o[b + 23] = floatBitsToUint(float(s) + float(u));
    o[b + 24] = uint(x < y) + uint(x >= y) * 2u + uint(isnan(x / 0.0)) * 4u + uint(isinf(y / 0.0)) * 8u;
    // 64-bit integers and doubles
    uint64_t big = uint64_t(u) * 0x100000001ul + uint64_t(i);
    int64_t sb = int64_t(s) * -3l;
    w[4 * i + 0] = big ^ (big >> 17) ^ (big << 9);
    w[4 * i + 1] = uint64_t(sb / 7l + sb % 5l);
    double d = double(x) * double(y) + 1.0lf / 3.0lf;
    w[4 * i + 2] = doubleBitsToUint64(d + sqrt(abs(d)));
    w[4 * i + 3] = uint64_t(int64_t(d * 1000.0lf)) + uint64_t(uint(big >> 32));
}

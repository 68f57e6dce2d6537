#version 450
// A storage texel buffer (R32_UINT) read and written at i + offset, with the offset from push
// constants putting some invocations past the view.
layout(local_size_x = 16) in;
layout(push_constant) uniform Push { int offset; } pc;
layout(set = 0, binding = 0, r32ui) uniform uimageBuffer texels;
layout(set = 0, binding = 1, std430) buffer Out { uint o[]; };

void main() {
    int i = int(gl_GlobalInvocationID.x);
    o[i] = imageLoad(texels, i + pc.offset).x;
    imageStore(texels, i + pc.offset, uvec4(uint(i) + 100u));
}

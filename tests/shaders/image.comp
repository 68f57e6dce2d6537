#version 450
// Fetches from a sampled texture: sampled images are not supported, rejected with the opcode.
layout(local_size_x = 1) in;
layout(set = 0, binding = 0) uniform sampler2D tex;
layout(set = 0, binding = 1) buffer Out { vec4 o; };
void main() { o = texelFetch(tex, ivec2(0), 0); }

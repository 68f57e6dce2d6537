#version 450
// Writes a storage image: not supported by the library yet, rejected with the opcode.
layout(local_size_x = 1) in;
layout(set = 0, binding = 0, r32ui) uniform writeonly uimage2D img;
void main() { imageStore(img, ivec2(0), uvec4(1u)); }

#version 450
// Swizzles and component reads of specialization-constant vectors: glslang emits
// OpSpecConstantOp VectorShuffle and CompositeExtract for them.
layout(local_size_x_id = 0, local_size_y_id = 1) in;
layout(constant_id = 2) const uint K = 3u;
layout(set = 0, binding = 0, std430) buffer Out { uint o[]; };
const uvec2 S = gl_WorkGroupSize.yx;
const uvec3 V = uvec3(K, 2u, 1u);
const uint E = V.y + V.x * 10u;
void main() { o[gl_LocalInvocationIndex] = S.x * 100u + S.y + E * 1000u; }

#version 450
#extension GL_EXT_nonuniform_qualifier : require
// Arrays of buffer descriptors: a storage array written through a non-uniform index, a
// uniform array read with a constant and a dynamically uniform (push-constant) index, and a
// runtime array read through a non-uniform index.
layout(local_size_x = 16) in;
layout(push_constant) uniform Push { uint pick; uint shift; } pc;
layout(set = 0, binding = 0, std430) buffer Out { uint v[]; } outs[4];
layout(set = 0, binding = 1, std140) uniform Params { uvec4 k; } params[3];
layout(set = 0, binding = 2, std430) readonly buffer In { uint a[]; } ins[];

void main() {
    uint i = gl_GlobalInvocationID.x;
    uint c = params[2].k.x;
    uint u = params[pc.pick].k.y;
    uint j = (i + pc.shift) % 3u;
    uint n = ins[nonuniformEXT(j)].a[i];
    outs[nonuniformEXT(i % 4u)].v[i / 4u] = n * 3u + c + u * j;
}

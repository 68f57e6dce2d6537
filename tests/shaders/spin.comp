#version 450
// Never terminates unless the buffer holds the magic value: for the watchdog.
layout(local_size_x = 8) in;
layout(set = 0, binding = 0, std430) buffer Buf { uint v[]; };

void main() {
    uint k = 0u;
    while (v[0] != 12345u) { k++; if (k == 0xFFFFFFFFu) v[1] = k; }
}

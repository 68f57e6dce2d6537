#version 450
// Never terminates for the input the test gives (flag = 0): the watchdog must stop it.
layout(local_size_x = 8) in;
layout(set = 0, binding = 0, std430) buffer Data { uint flag; uint n; } d;

void main() {
    uint k = 0u;
    while (d.flag == 0u) {
        k++;
    }
    d.n = k;
}

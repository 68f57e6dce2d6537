//! Ops with a constant operand that the SIMD backend lowers its own way (unsigned compares of
//! sign-flipped operands, multiplies by 2^s and 2^s ± 1 as shift and add), against the
//! interpreter over edge values and a spread of others.
use super::refill_tests::{compile, run};
use crate::shader::Watchdog;

const CONSTS: &str = "#version 450
layout(local_size_x = 64) in;
layout(std430, set = 0, binding = 0) buffer Out { uint r[]; };
void main() {
    uint i = gl_GlobalInvocationID.x;
    uint edge[8] = uint[8](0u, 1u, 2u, 0x7FFFFFFFu, 0x80000000u, 0x80000001u, 0xFFFFFFFEu, 0xFFFFFFFFu);
    uint x = (i & 8u) != 0u ? edge[i & 7u] : i * 2654435761u;
    uint m = x * 3u + x * 5u * 7u + x * 8u - x * 15u + x * 0x80000000u + x * 0x7FFFFFFFu;
    uint c = 0u;
    if (x < 5u) c |= 1u;
    if (x > 0x80000001u) c |= 2u;
    if (0x7FFFFFFFu < x) c |= 4u;
    if (0xFFFFFFFEu > x) c |= 8u;
    if (x < 0u) c |= 16u;
    if (x > 0xFFFFFFFFu) c |= 32u;
    if (x < m) c |= 64u;
    if (m > x) c |= 128u;
    r[i] = m ^ (c << 24);
}
";

#[test]
fn constant_multiplies_and_unsigned_compares_match_the_interpreter() {
    for (what, p) in compile("consts", CONSTS) {
        let want = run(&p.interpreted(), 64, 4, &Watchdog::default());
        let got = run(&p, 64, 4, &Watchdog::default());
        assert!(got.1 == want.1, "{what}: results");
        assert_eq!(got.0, want.0, "{what}: reports");
        // Not a constant shader: the compares see both outcomes.
        assert!(want.1.chunks(4).map(|c| c[3]).collect::<std::collections::BTreeSet<_>>().len() > 4, "{what}");
    }
}

/// NaNs born in the middle of add/multiply/fma/sqrt chains (inf - inf, 0 * inf, sqrt of a
/// negative, NaN inputs with payloads) reach the output only through ops that carry them: the
/// chain's intermediate results go untested (`nan::covered`), and the output bits must still be
/// the interpreter's.
const NAN_CHAINS: &str = "#version 450
layout(local_size_x = 64) in;
layout(std430, set = 0, binding = 0) buffer Out { uint r[]; };
void main() {
    uint i = gl_GlobalInvocationID.x;
    float inf = uintBitsToFloat(0x7F800000u);
    float pick[8] = float[8](0.0, -0.0, inf, -inf, uintBitsToFloat(0x7FC01234u), uintBitsToFloat(0xFF800001u), -2.5, 3.0);
    float a = pick[i & 7u];
    float b = pick[(i >> 3) & 7u];
    float t = a * b + a;
    float u = fma(t, b, a - b) * 0.5;
    float v = sqrt(u * a) + t;
    float w = -(v / b) * (u + 1.0);
    r[i] = floatBitsToUint(w) ^ floatBitsToUint(v * 3.0);
}
";

#[test]
fn nans_born_inside_float_chains_keep_the_interpreters_bits() {
    for (what, p) in compile("nan_chains", NAN_CHAINS) {
        let want = run(&p.interpreted(), 64, 2, &Watchdog::default());
        let got = run(&p, 64, 2, &Watchdog::default());
        assert!(got.1 == want.1, "{what}: results");
        assert_eq!(got.0, want.0, "{what}: reports");
    }
}

/// Push constants at constant offsets are loaded once for every lane; pushed bytes that cover
/// none, one or both of the words (the dispatch pads the rest with zeros).
const PUSHED: &str = "#version 450
layout(local_size_x = 64) in;
layout(std430, set = 0, binding = 0) buffer Out { uint r[]; };
layout(push_constant) uniform P { uint a; uint b; };
void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i % 3u == 2u) {
        return;
    }
    r[i] = a * 7u + (b ^ i);
}
";

#[test]
fn push_constants_at_constant_offsets_match_the_interpreter_in_and_out_of_range() {
    use crate::shader::{dispatch, HostMemory, Pipeline};
    let go = |p: &Pipeline, push: &[u8]| {
        let p = Pipeline { local_size: [20, 1, 1], ..p.clone() };
        let mut mem = HostMemory::new();
        let out = mem.add_buffer(&[0xA5; 60 * 4]);
        mem.bind(0, 0, out);
        (dispatch(&p, &mem, push, [3, 1, 1], [0; 3], &Watchdog::default()), mem.bytes(out))
    };
    let bytes: Vec<u8> = [0x1234_5678u32, 0x9ABC_DEF0].iter().flat_map(|w| w.to_le_bytes()).collect();
    for (what, p) in compile("pushed", PUSHED) {
        let mut outputs = Vec::new();
        for n in [0, 4, 8] {
            let want = go(&p.interpreted(), &bytes[..n]);
            let got = go(&p, &bytes[..n]);
            assert!(got.0 == want.0, "{what}, {n} bytes pushed: {:?} vs {:?}", got.0, want.0);
            assert!(got.1 == want.1, "{what}, {n} bytes pushed: output");
            outputs.push(want.1);
        }
        assert!(outputs[0] != outputs[1] && outputs[1] != outputs[2], "{what}: both words reach the output");
    }
}

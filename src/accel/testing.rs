//! Deterministic random streams for the unit tests of src/accel.

/// A deterministic xorshift64 stream.
pub fn xorshift(mut seed: u64) -> impl FnMut() -> u64 {
    move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    }
}

/// Xorshift floats in [0, 1) from `seed`.
pub fn unit_floats(seed: u64) -> impl FnMut() -> f32 {
    let mut next = xorshift(seed);
    move || (next() >> 40) as f32 / (1u64 << 24) as f32
}

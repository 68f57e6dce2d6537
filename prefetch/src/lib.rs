//! A safe software-prefetch hint. Arbor's acceleration-structure library contains no `unsafe`
//! (it is `#[forbid(unsafe_code)]`), but its gathers read in orders no hardware prefetcher can
//! follow (leaf order, vertices by index); the one intrinsic they need lives here, behind a
//! function that cannot be misused.
#![no_std]

/// Hints that `bytes[at]` will be read soon (into all cache levels). Does nothing when `at` is
/// out of range or the target has no prefetch instruction; never faults, never changes memory.
#[inline(always)]
pub fn read(bytes: &[u8], at: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(b) = bytes.get(at) {
        // SAFETY: SSE is part of the x86-64 baseline, so the instruction exists; a prefetch
        // never faults and has no architectural effect, and the address is inside `bytes`.
        unsafe { core::arch::x86_64::_mm_prefetch::<{ core::arch::x86_64::_MM_HINT_T0 }>(b as *const u8 as *const i8) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (bytes, at);
}

#[cfg(test)]
mod tests {
    #[test]
    fn any_position_is_safe() {
        let bytes = [1u8, 2, 3];
        for at in [0, 2, 3, usize::MAX] {
            super::read(&bytes, at);
        }
        super::read(&[], 0);
        assert_eq!(bytes, [1, 2, 3]);
    }
}

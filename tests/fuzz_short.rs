//! A short run of the seeded mutation fuzzer (`bench/src/fuzz.rs`, long runs with
//! `cargo run --release --bin arbor-fuzz`): a fixed seed, a few seconds, zero crashes, and
//! every rejection named.
#[path = "../bench/src/fuzz.rs"]
#[allow(dead_code)]
mod fuzz;

#[test]
fn fixed_seed_fuzz_run_has_no_crash_and_names_every_rejection() {
    let counts = fuzz::run(20_000, 7);
    assert_eq!(counts.executions, 20_000);
    let rejected: u64 = counts.rejections.values().sum();
    assert_eq!(counts.accepted + rejected, counts.executions);
    assert!(counts.rejections.keys().all(|r| !r.is_empty()));
    // Both kinds of input are exercised and both outcomes happen.
    assert!(counts.accepted > 0 && rejected > 0, "{counts:?}");
    assert!(counts.rejections.keys().any(|r| r.starts_with("deserialize: ")), "{counts:?}");
}

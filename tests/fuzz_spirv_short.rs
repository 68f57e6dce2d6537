//! A short run of the SPIR-V mutation fuzzer (`bench/src/fuzz_spirv.rs`, long runs with
//! `cargo run --release --bin arbor-fuzz -- --spirv`): a fixed seed, zero crashes, every
//! rejection named, and accepted mutants dispatched to a contained end.
#[path = "../bench/src/fuzz.rs"]
#[allow(dead_code)]
mod fuzz;
#[path = "../bench/src/fuzz_spirv.rs"]
mod fuzz_spirv;

#[test]
fn seeds_are_accepted_unmutated() {
    for (name, words) in fuzz_spirv::seeds() {
        let module = arbor::shader::Module::parse(&words).unwrap_or_else(|e| panic!("seed {name}: {e}"));
        arbor::shader::Pipeline::compute(&module, "main", &[]).unwrap_or_else(|e| panic!("seed {name}: {e}"));
    }
}

#[test]
fn fixed_seed_spirv_fuzz_run_has_no_crash_and_names_every_rejection() {
    let (counts, outcomes) = fuzz_spirv::run(3_000, 11);
    assert_eq!(counts.executions, 3_000);
    let rejected: u64 = counts.rejections.values().sum();
    assert_eq!(counts.accepted + rejected, counts.executions);
    assert_eq!(outcomes.values().sum::<u64>(), counts.accepted, "every accepted module was dispatched");
    assert!(counts.rejections.keys().all(|r| r.len() > "parse: ".len()), "{counts:?}");
    // Both outcomes happen: the mutants reach the executor, and the front end rejects others.
    assert!(counts.accepted > 0 && rejected > 0, "{counts:?}");
    assert!(counts.rejections.keys().any(|r| r.starts_with("parse: ")), "{counts:?}");
    assert!(outcomes.contains_key("clean"), "{outcomes:?}");
}


//! Seeded mutation fuzzing on the stable toolchain, at the library level (no loader): by default
//! `arbor::accel`'s deserializer and build inputs (see `fuzz.rs`); with `--spirv`, the SPIR-V
//! front end and executor of `arbor::shader` (see `fuzz_spirv.rs`).
//!
//!   cargo run --release --bin arbor-fuzz -- [--spirv] --iterations N --seed S
//!       [--save-rejection TEXT --save-to FILE]
//!
//! With `--spirv`, `--save-rejection` writes the first module whose rejection reason contains
//! TEXT to FILE (little-endian words), to keep a case as a seed or test.
//!
//! Prints executions, accepted inputs and rejections by reason. A crash is a panic (the process
//! fails); a hang would be a run that never ends (traversal and checks are bounded).
#[path = "../fuzz.rs"]
mod fuzz;
#[path = "../fuzz_spirv.rs"]
mod fuzz_spirv;

fn arg(args: &[String], name: &str, default: u64) -> u64 {
    args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).and_then(|v| v.parse().ok()).unwrap_or(default)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let iterations = arg(&args, "--iterations", 1_000_000);
    let seed = arg(&args, "--seed", 1);
    let spirv = args.iter().any(|a| a == "--spirv");
    let start = std::time::Instant::now();
    let wanted = args.iter().position(|a| a == "--save-rejection").and_then(|i| args.get(i + 1));
    let save_to = args.iter().position(|a| a == "--save-to").and_then(|i| args.get(i + 1));
    let (counts, outcomes) = if spirv && wanted.is_none() {
        fuzz_spirv::run(iterations, seed)
    } else if spirv {
        let (counts, outcomes, saved) = fuzz_spirv::run_saving(iterations, seed, wanted.map(String::as_str));
        if let (Some(words), Some(path)) = (saved, save_to) {
            let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
            std::fs::write(path, bytes).unwrap_or_else(|e| panic!("writing {path}: {e}"));
            println!("saved the first module rejected with {:?} to {path}", wanted.map_or("", |w| w.as_str()));
        }
        (counts, outcomes)
    } else {
        (fuzz::run(iterations, seed), Default::default())
    };
    let secs = start.elapsed().as_secs_f64();
    let what = if spirv { " --spirv" } else { "" };
    println!("arbor-fuzz{what} --iterations {iterations} --seed {seed}: {} executions in {secs:.1} s ({:.0}/s)", counts.executions, counts.executions as f64 / secs);
    println!("accepted: {}", counts.accepted);
    for (outcome, n) in &outcomes {
        println!("  {n:>10}  {outcome}");
    }
    let rejected: u64 = counts.rejections.values().sum();
    println!("rejected: {rejected}");
    for (reason, n) in &counts.rejections {
        println!("  {n:>10}  {reason}");
    }
}

//! Seeded mutation fuzzing of `arbor::accel` on the stable toolchain (see `fuzz.rs`): the
//! deserializer and the build inputs, at the library level (no loader).
//!
//!   cargo run --release --bin arbor-fuzz -- --iterations N --seed S
//!
//! Prints executions, accepted inputs and rejections by reason. A crash is a panic (the process
//! fails); a hang would be a run that never ends (traversal and checks are bounded).
#[path = "../fuzz.rs"]
mod fuzz;

fn arg(args: &[String], name: &str, default: u64) -> u64 {
    args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).and_then(|v| v.parse().ok()).unwrap_or(default)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let iterations = arg(&args, "--iterations", 1_000_000);
    let seed = arg(&args, "--seed", 1);
    let start = std::time::Instant::now();
    let counts = fuzz::run(iterations, seed);
    let secs = start.elapsed().as_secs_f64();
    println!("arbor-fuzz --iterations {iterations} --seed {seed}: {} executions in {secs:.1} s ({:.0}/s)", counts.executions, counts.executions as f64 / secs);
    println!("accepted: {}", counts.accepted);
    let rejected: u64 = counts.rejections.values().sum();
    println!("rejected: {rejected}");
    for (reason, n) in &counts.rejections {
        println!("  {n:>10}  {reason}");
    }
}

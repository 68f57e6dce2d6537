//! Lane refill against the interpreter (the reference): loops whose lanes end at very different
//! times, early returns before the loop, nested loops, faults in refilled lanes and in many
//! lanes at once, at workgroup sizes that are and are not multiples of the lane count; the
//! fault records must be the interpreter's, in its order. Also thread-count independence and
//! the watchdog under refill.
use std::process::Command;
use std::sync::Arc;

use crate::shader::{dispatch, DispatchReport, HostMemory, Module, Pipeline, Stop, Watchdog};

/// Collatz step counts of scattered starts (lanes end hundreds of rounds apart), a quarter of
/// the invocations returning before the loop, and a fault before it in a third of the lanes
/// (refilled ones included), where every lane of a group has run the same blocks.
const COLLATZ: &str = "#version 450
layout(local_size_x = 64) in;
layout(std430, set = 0, binding = 0) buffer Out { uint r[]; };
layout(std430, set = 0, binding = 1) buffer Small { uint small[]; };
void main() {
    uint i = gl_GlobalInvocationID.x;
    uint x = i * 2654435761u;
    if (i % 3u == 1u) {
        small[200u + i] = x;
    }
    if ((x >> 30) == 1u) {
        return;
    }
    x = (x >> 20) + 1u;
    uint s = 0u;
    while (x > 1u && s < 400u) {
        x = (x & 1u) != 0u ? 3u * x + 1u : x >> 1u;
        s += 1u;
    }
    r[i] = s;
    if (i < 48u) {
        small[2u * i + (s & 1u)] = x + s;
    }
}
";

/// As `COLLATZ`, with faults inside the loop (at a step count that differs per lane) and after
/// it in most lanes.
const COLLATZ_LATE: &str = "#version 450
layout(local_size_x = 64) in;
layout(std430, set = 0, binding = 0) buffer Out { uint r[]; };
layout(std430, set = 0, binding = 1) buffer Small { uint small[]; };
void main() {
    uint i = gl_GlobalInvocationID.x;
    uint x = (i * 2654435761u >> 20) + 1u;
    uint s = 0u;
    while (x > 1u && s < 400u) {
        x = (x & 1u) != 0u ? 3u * x + 1u : x >> 1u;
        s += 1u;
        if (s == (i % 9u) + 2u && (i % 5u) == 1u) {
            small[2u * i + 1u] += s;
        }
    }
    r[i] = s;
    small[2u * i] = x + s;
}
";

/// An outer loop of 0 to 6 rounds around an inner loop of data-dependent length, with the
/// registers of both live across the refills; faults after the loops in some lanes.
const NESTED: &str = "#version 450
layout(local_size_x = 64) in;
layout(std430, set = 0, binding = 0) buffer Out { uint r[]; };
layout(std430, set = 0, binding = 1) buffer Small { uint small[]; };
void main() {
    uint i = gl_GlobalInvocationID.x;
    uint acc = i;
    for (uint a = 0u; a < (i * 7u) % 11u % 7u; a++) {
        uint b = i * 31u + a * 977u;
        while (b > 3u) {
            b = (b & 1u) != 0u ? b - 3u : b / 2u;
            acc += b;
        }
        acc ^= a << 3;
    }
    r[i] = acc;
    if (acc % 3u == 0u) {
        small[100u + i] = acc;
    }
}
";

/// Half the lanes never end.
const SPIN: &str = "#version 450
layout(local_size_x = 64) in;
layout(std430, set = 0, binding = 0) buffer Out { uint r[]; };
void main() {
    uint i = gl_GlobalInvocationID.x;
    uint x = i;
    while ((i & 1u) == 1u || x > 0u) {
        x = x / 2u;
        r[i] = x;
    }
}
";

/// `src` compiled by glslang, and again through `spirv-opt -O`.
pub(super) fn compile(name: &str, src: &str) -> Vec<(String, Pipeline)> {
    let dir = std::env::temp_dir().join(format!("arbor-refill-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (glsl, spv, opt) = (dir.join(format!("{name}.comp")), dir.join(format!("{name}.spv")), dir.join(format!("{name}.opt.spv")));
    std::fs::write(&glsl, src).unwrap();
    let out = Command::new("glslangValidator").args(["-V", "--target-env", "vulkan1.2", "-o"]).arg(&spv).arg(&glsl).output().expect("glslangValidator (glslang-tools)");
    assert!(out.status.success(), "{name}: {}", String::from_utf8_lossy(&out.stdout));
    let out = Command::new("spirv-opt").arg("-O").arg(&spv).arg("-o").arg(&opt).output().expect("spirv-opt (spirv-tools)");
    assert!(out.status.success(), "{name}: {}", String::from_utf8_lossy(&out.stderr));
    [("glslang", spv), ("spirv-opt -O", opt)]
        .into_iter()
        .map(|(what, path)| {
            let words: Vec<u32> = std::fs::read(&path).unwrap().chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
            let p = Pipeline::compute(&Module::parse(&words).unwrap(), "main", &[]).unwrap();
            let jit = super::super::compile_simd(&p.program).unwrap_or_else(|| panic!("{name} ({what}) compiles for the SIMD backend"));
            assert_eq!(jit.lanes, super::W);
            (format!("{name} ({what})"), Pipeline { jit: Some(Arc::new(jit)), ..p })
        })
        .collect()
}

/// Runs `p` over `groups` workgroups of `local` invocations: an output word per invocation
/// and a small buffer that many accesses overrun.
pub(super) fn run(p: &Pipeline, local: u32, groups: u32, watchdog: &Watchdog) -> (DispatchReport, Vec<u8>, Vec<u8>) {
    let p = Pipeline { local_size: [local, 1, 1], ..p.clone() };
    let mut mem = HostMemory::new();
    let (out, small) = (mem.add_buffer(&vec![0xA5; (local * groups) as usize * 4]), mem.add_buffer(&[0; 96 * 4]));
    mem.bind(0, 0, out);
    mem.bind(0, 1, small);
    let report = dispatch(&p, &mem, &[], [groups, 1, 1], [0; 3], watchdog);
    (report, mem.bytes(out), mem.bytes(small))
}

const SIZES: [u32; 7] = [1, 3, 5, 64, 100, 256, 7];

/// Results, and fault records in the interpreter's order, equal to the interpreter's at every
/// size (the fault key follows the interpreter's in-step loop rounds: `refill::outermost_loops`).
fn check_against_interpreter(name: &str, src: &str) {
    for (what, p) in compile(name, src) {
        let mut faulted = false;
        for local in SIZES {
            let want = run(&p.interpreted(), local, 3, &Watchdog::default());
            let got = run(&p, local, 3, &Watchdog::default());
            assert!(want.0.stopped.is_none(), "{what} {local}");
            assert!(got.0 == want.0, "{what}, workgroups of {local}: {:?} vs {:?}", got.0, want.0);
            assert!(got.1 == want.1, "{what}, workgroups of {local}: output");
            assert!(got.2 == want.2, "{what}, workgroups of {local}: small buffer");
            faulted |= want.0.faults.iter().any(|f| f.invocation != want.0.faults[0].invocation && f.invocation >= super::W as u32);
        }
        assert!(faulted, "{what}: some size faults in several lanes, refilled ones among them");
    }
}

#[test]
fn divergent_loops_give_the_interpreters_results_and_fault_records() {
    check_against_interpreter("collatz", COLLATZ);
    check_against_interpreter("collatz_late", COLLATZ_LATE);
}

#[test]
fn nested_divergent_loops_give_the_interpreters_results_and_fault_records() {
    check_against_interpreter("nested", NESTED);
}

#[test]
fn refilled_results_do_not_depend_on_thread_count() {
    for (what, p) in compile("collatz_threads", COLLATZ) {
        let run_on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| run(&p, 100, 9, &Watchdog::default()))
        };
        let one = run_on(1);
        assert!(one.0.fault_count > 0, "{what}");
        for threads in [2, 3] {
            let other = run_on(threads);
            assert_eq!(other.0, one.0, "{what}: {threads} threads");
            assert!(other.1 == one.1 && other.2 == one.2, "{what}: {threads} threads");
        }
    }
}

#[test]
fn the_watchdog_stops_endless_lanes_while_others_are_refilled() {
    for (what, p) in compile("spin", SPIN) {
        let budget = Watchdog { step_budget: Some(200_000), ..Watchdog::default() };
        assert_eq!(run(&p, 64, 2, &budget).0.stopped, Some(Stop::StepBudget), "{what}");
        let deadline = Watchdog { deadline: Some(std::time::Instant::now() + std::time::Duration::from_millis(50)), ..Watchdog::default() };
        assert_eq!(run(&p, 100, 2, &deadline).0.stopped, Some(Stop::Deadline), "{what}");
    }
}

//! Seeded mutation fuzzing of the SPIR-V front end and executor (`arbor::shader`) on the stable
//! toolchain: modules compiled by glslang (and `spirv-opt -O`) from the test shaders, committed
//! in `bench/fuzz-seeds/`, are mutated — bit flips, interesting words, instructions deleted,
//! duplicated, swapped, spliced in from another seed, opcodes and word counts rewritten,
//! truncation — then parsed, lowered into a pipeline and, when accepted, dispatched over
//! host buffers and images with a watchdog. Every execution must end in a named rejection or a
//! dispatch that returns (faults and watchdog stops are contained outcomes, counted by kind); a
//! panic escapes to the caller (a crash). Used by `arbor-fuzz --spirv` and
//! tests/fuzz_spirv_short.rs.
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use arbor::shader::{dispatch, HostMemory, ImageBinding, ImageFormat, Module, Pipeline, ShaderError, Watchdog};

use crate::fuzz::{Counts, Rng};

/// The seed modules, embedded so the fuzzer needs no compiler at run time
/// (`glslangValidator -V --target-env vulkan1.2` of tests/shaders/NAME.comp; `.opt` through
/// `spirv-opt -O`).
const SEEDS: &[(&str, &[u8])] = &[
    ("arith", include_bytes!("../fuzz-seeds/arith.spv")),
    ("bda", include_bytes!("../fuzz-seeds/bda.spv")),
    ("control", include_bytes!("../fuzz-seeds/control.spv")),
    ("control.opt", include_bytes!("../fuzz-seeds/control.opt.spv")),
    ("image_rw", include_bytes!("../fuzz-seeds/image_rw.spv")),
    ("math", include_bytes!("../fuzz-seeds/math.spv")),
    ("misc", include_bytes!("../fuzz-seeds/misc.spv")),
    ("rq_anyhit", include_bytes!("../fuzz-seeds/rq_anyhit.spv")),
    ("rq_anyhit.opt", include_bytes!("../fuzz-seeds/rq_anyhit.opt.spv")),
    ("rq_closest", include_bytes!("../fuzz-seeds/rq_closest.spv")),
    ("shared", include_bytes!("../fuzz-seeds/shared.spv")),
    ("spec_swizzle", include_bytes!("../fuzz-seeds/spec_swizzle.spv")),
    ("subgroup", include_bytes!("../fuzz-seeds/subgroup.spv")),
];

/// The device limits a Vulkan pipeline would be checked against before it could be dispatched
/// (the runtime refuses larger ones at pipeline creation).
const MAX_INVOCATIONS: u64 = 1024;
const MAX_SHARED_BYTES: u32 = 32 * 1024;

/// Words of the seed modules.
pub fn seeds() -> Vec<(&'static str, Vec<u32>)> {
    SEEDS.iter().map(|(name, bytes)| (*name, bytes.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())).collect()
}

/// Word offsets of the instructions after the 5-word header, stopping at the first word count
/// that is zero or runs past the end.
fn instructions(words: &[u32]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut at = 5;
    while at < words.len() {
        let n = (words[at] >> 16) as usize;
        if n == 0 || at + n > words.len() {
            break;
        }
        out.push((at, n));
        at += n;
    }
    out
}

const INTERESTING: [u32; 10] = [0, 1, 2, 3, 4, 0xFF, 0xFFFF, 0x7FFF_FFFF, 0x8000_0000, 0xFFFF_FFFF];

/// One mutation of `w`; `other` is a second seed to splice from.
fn mutate(rng: &mut Rng, w: &mut Vec<u32>, other: &[u32]) {
    let len = w.len().max(6);
    let at = 5 + rng.below(len as u64 - 5) as usize;
    let insts = instructions(w);
    let pick = |rng: &mut Rng, v: &[(usize, usize)]| v.get(rng.below(v.len() as u64) as usize).copied();
    match rng.below(9) {
        0 if at < w.len() => w[at] ^= 1 << rng.below(32),
        1 if at < w.len() => w[at] = INTERESTING[rng.below(INTERESTING.len() as u64) as usize],
        // A small id or literal: most words of a module are ids below the bound.
        2 if at < w.len() => w[at] = rng.below(w[3].max(1) as u64 + 2) as u32,
        3 => {
            if let Some((s, n)) = pick(rng, &insts) {
                w.drain(s..s + n);
            }
        }
        4 => {
            if let Some((s, n)) = pick(rng, &insts) {
                let copy: Vec<u32> = w[s..s + n].to_vec();
                let to = pick(rng, &insts).map_or(w.len(), |(t, _)| t);
                w.splice(to..to, copy);
            }
        }
        5 => {
            let from = instructions(other);
            if let (Some((s, n)), Some((t, _))) = (pick(rng, &from), pick(rng, &insts)) {
                w.splice(t..t, other[s..s + n].iter().copied());
            }
        }
        6 => {
            if let Some((s, _)) = pick(rng, &insts) {
                w[s] = (w[s] & 0xFFFF_0000) | rng.below(420) as u32;
            }
        }
        7 => {
            if let Some((s, n)) = pick(rng, &insts) {
                let count = (n as i64 + rng.below(5) as i64 - 2).max(0) as u32;
                w[s] = (count << 16) | (w[s] & 0xFFFF);
            }
        }
        _ => {
            let keep = 5 + rng.below(len as u64 - 4) as usize;
            w.truncate(keep.min(w.len()));
        }
    }
}

/// The reason a rejection is counted under: the kind of error, with the fixed text of a
/// malformed-module reason (ids, offsets and names left out so one check counts once).
fn reason(stage: &str, e: &ShaderError) -> String {
    let kind = match e {
        ShaderError::Malformed { reason, .. } => {
            let fixed: String = reason.chars().filter(|c| !c.is_ascii_digit()).collect();
            // rspirv's errors nest their variant names in parentheses: keep the first two.
            let fixed = fixed.trim_start_matches(['%', ':', ' ']);
            let named = fixed.split(['"', '%']).next().unwrap_or("").splitn(4, '(').take(3).collect::<Vec<_>>().join("(");
            format!("malformed: {}", named.trim_end_matches([',', ' ', ')', '(']).trim())
        }
        ShaderError::UnsupportedCapability { .. } => "unsupported capability".into(),
        ShaderError::UnsupportedExtension { .. } => "unsupported extension".into(),
        ShaderError::UnsupportedOpcode { .. } => "unsupported instruction".into(),
        ShaderError::UnsupportedExtInst { .. } => "unsupported extended instruction".into(),
        ShaderError::Unsupported { what, .. } => format!("unsupported: {}", what.split(|c: char| c.is_ascii_digit() || c == '[').next().unwrap_or("").trim()),
        ShaderError::NoEntryPoint { .. } => "no entry point".into(),
        ShaderError::Specialization { .. } => "specialization".into(),
    };
    format!("{stage}: {kind}")
}

/// Binds a 4 KiB buffer and an 8×8 image at every binding the pipeline uses (the executor picks
/// what the shader declares; a mismatch is the shader's fault and must be contained).
fn memory_for(p: &Pipeline, rng: &mut Rng) -> HostMemory {
    let mut mem = HostMemory::new();
    let formats = [ImageFormat::R32Uint, ImageFormat::R32Sfloat, ImageFormat::Rgba32Sfloat, ImageFormat::Rgba8Unorm];
    for b in p.bindings() {
        let bytes: Vec<u8> = (0..4096).map(|_| rng.next() as u8).collect();
        let i = mem.add_buffer(&bytes);
        mem.bind(b.set, b.binding, i);
        let format = formats[rng.below(formats.len() as u64) as usize];
        let texels = mem.add_buffer(&vec![0u8; 8 * 8 * 16]);
        mem.bind_image(b.set, b.binding, ImageBinding::packed(texels as u64, 0, format, [8, 8, 1], 1));
    }
    mem
}

/// The rejection `Pipeline::compute` gives when its backstop caught a panic in lowering: a
/// check missing, counted as a crash.
pub const BACKSTOP: &str = "lowering failed";

/// Parses, lowers and (when accepted and within the device limits) dispatches one module;
/// returns the rejection reason, if any.
fn execute(words: &[u32], rng: &mut Rng, counts: &mut Counts, outcomes: &mut BTreeMap<String, u64>) -> Option<String> {
    counts.executions += 1;
    let module = match Module::parse(words) {
        Ok(m) => m,
        Err(e) => return Some(reason("parse", &e)),
    };
    let spec: Vec<(u32, Vec<u8>)> = if rng.below(4) == 0 { vec![(rng.below(4) as u32, (rng.next() as u32).to_le_bytes().to_vec())] } else { Vec::new() };
    let pipeline = match Pipeline::compute(&module, "main", &spec) {
        Ok(p) => p,
        Err(e) if e.to_string().contains(BACKSTOP) => panic!("the lowering backstop caught a panic: {e}"),
        Err(e) => return Some(reason("pipeline", &e)),
    };
    let invocations: u64 = pipeline.local_size.iter().map(|&n| n as u64).product();
    if invocations == 0 || invocations > MAX_INVOCATIONS || pipeline.workgroup_memory_size() > MAX_SHARED_BYTES {
        return Some("pipeline: beyond the device limits".into());
    }
    counts.accepted += 1;
    let mem = memory_for(&pipeline, rng);
    let push: Vec<u8> = (0..128).map(|_| rng.next() as u8).collect();
    let watchdog = Watchdog { deadline: Some(Instant::now() + Duration::from_millis(500)), step_budget: Some(20_000), ..Watchdog::default() };
    let groups = [1 + rng.below(2) as u32, 1, 1];
    let report = dispatch(&pipeline, &mem, &push, groups, [0; 3], &watchdog);
    let outcome = match (report.stopped, report.faults.first()) {
        (Some(stop), _) => format!("stopped: {stop:?}"),
        (None, Some(f)) => format!("fault: {:?} in {:?}", f.kind, f.space),
        (None, None) => "clean".to_string(),
    };
    *outcomes.entry(outcome).or_default() += 1;
    None
}

/// `iterations` executions from `seed`: one to four mutations of a seed module each (one in
/// sixteen runs unmutated, so the seeds' own paths stay covered). Returns the counts and the
/// dispatch outcomes of accepted modules.
pub fn run(iterations: u64, seed: u64) -> (Counts, BTreeMap<String, u64>) {
    let (counts, outcomes, _) = run_saving(iterations, seed, None);
    (counts, outcomes)
}

/// `run`, also returning the first module whose rejection reason contains `wanted` (to keep a
/// case as a test). A crash (a panic, or a panic the lowering backstop caught) prints the
/// execution's index and the module's words before it fails the run.
pub fn run_saving(iterations: u64, seed: u64, wanted: Option<&str>) -> (Counts, BTreeMap<String, u64>, Option<Vec<u32>>) {
    let seeds = seeds();
    let mut saved = None;
    let mut rng = Rng::new(seed ^ 0x5350_4952_5621);
    let mut counts = Counts::default();
    let mut outcomes = BTreeMap::new();
    for _ in 0..iterations {
        let (_, base) = &seeds[rng.below(seeds.len() as u64) as usize];
        let (_, other) = &seeds[rng.below(seeds.len() as u64) as usize];
        let mut words = base.clone();
        if rng.below(16) != 0 {
            for _ in 0..1 + rng.below(4) {
                mutate(&mut rng, &mut words, other);
            }
        }
        let index = counts.executions;
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| execute(&words, &mut rng, &mut counts, &mut outcomes)));
        match result {
            Ok(Some(r)) => {
                if saved.is_none() && wanted.is_some_and(|w| r.contains(w)) {
                    saved = Some(words.clone());
                }
                counts.reject(r);
            }
            Ok(None) => {}
            Err(panic) => {
                eprintln!("crash at execution {index} (seed {seed}); module words: {words:08x?}");
                std::panic::resume_unwind(panic);
            }
        }
    }
    (counts, outcomes, saved)
}


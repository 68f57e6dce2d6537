//! Teardown releases what Arbor allocated: a create/build/destroy program (instance, device,
//! buffers, a build, everything destroyed, three times) runs under valgrind's leak checker in a
//! child process. It must show 0 bytes definitely lost, and no possibly-lost block allocated
//! from an Arbor frame beyond `ARBOR_POSSIBLY_LOST_MAX` bytes (what docs/ROBUSTNESS.md says stays
//! for the process: the build pool's threads). Skipped, saying so, where valgrind is not
//! installed (scripts/deps.sh installs it; CI has it). About 10 s.
mod harness;

use std::process::Command;

use harness::vuid::*;

const CHILD: &str = "teardown_child_create_build_destroy";

/// Bytes of possibly-lost blocks allocated under an Arbor frame that may remain: glibc's
/// thread-local record (304 B) of each thread of the process-wide build pool, which lives until
/// the process ends (docs/ROBUSTNESS.md, section 3), for the child's `ARBOR_THREADS=2`, with
/// slack. It does not grow with the number of instances, devices or builds.
const ARBOR_POSSIBLY_LOST_MAX: u64 = 2 * 512;

/// crossbeam-epoch's records: its process-global collector (allocated once, 2 KB) and the
/// per-thread record (2.3 KB) of each thread that ran rayon's worker loop (the two pool threads
/// and the queue worker of each of the three devices). crossbeam unlinks an exited thread's record
/// from its global list lazily, when another thread next pins, so whether these show as possibly
/// lost at exit depends on timing; at most one per thread the child started, plus the collector.
const CROSSBEAM_RECORDS_MAX: usize = 2 + 3 + 1;

#[test]
fn create_build_destroy_leaks_nothing_under_valgrind() {
    if Command::new("valgrind").arg("--version").output().is_err() {
        eprintln!("SKIPPED: valgrind is not installed (apt-get install valgrind; scripts/deps.sh does it)");
        return;
    }
    let exe = std::env::current_exe().unwrap();
    let log = exe.with_file_name(format!("teardown-valgrind-{}.log", std::process::id()));
    let out = Command::new("valgrind")
        .args(["--leak-check=full", "--show-leak-kinds=definite,possible", "--num-callers=40"])
        .arg(format!("--log-file={}", log.display()))
        .arg(&exe)
        .args([CHILD, "--exact", "--ignored", "--nocapture", "--test-threads=1"])
        .env("ARBOR_THREADS", "2")
        .output()
        .expect("run valgrind");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success() && text.contains("teardown child: done"), "the child failed under valgrind:\n{text}");
    let report = std::fs::read_to_string(&log).expect("valgrind log");
    let _ = std::fs::remove_file(&log);
    let definitely = summary_bytes(&report, "definitely lost:");
    assert_eq!(definitely, Some(0), "definitely lost:\n{report}");
    let (crossbeam, arbor): (Vec<LossRecord>, Vec<LossRecord>) =
        loss_records(&report).into_iter().filter(|r| r.kind == "possibly" && r.arbor).partition(|r| r.crossbeam_local);
    let bytes: u64 = arbor.iter().map(|r| r.bytes).sum();
    eprintln!(
        "valgrind: definitely lost 0 bytes; possibly lost from Arbor frames {bytes} bytes in {} records, plus {} crossbeam-epoch thread records",
        arbor.len(),
        crossbeam.len()
    );
    assert!(
        crossbeam.len() <= CROSSBEAM_RECORDS_MAX,
        "{} crossbeam-epoch thread records (bound {CROSSBEAM_RECORDS_MAX}): threads are not being joined",
        crossbeam.len()
    );
    assert!(
        bytes <= ARBOR_POSSIBLY_LOST_MAX,
        "{bytes} bytes possibly lost from Arbor frames (bound {ARBOR_POSSIBLY_LOST_MAX}):\n{}",
        arbor.iter().map(|r| r.text).collect::<Vec<_>>().join("\n\n")
    );
}

#[test]
#[ignore = "run by create_build_destroy_leaks_nothing_under_valgrind under valgrind"]
fn teardown_child_create_build_destroy() {
    for _ in 0..3 {
        let ctx = context();
        let a = Accel::new(&ctx);
        let m = upload_grid(&a);
        valid_blas(&a, &m, NO_FLAGS);
        a.destroy();
        ctx.finish();
    }
    println!("teardown child: done");
}

/// The byte count of a LEAK SUMMARY line ("definitely lost: 1,234 bytes in 5 blocks").
fn summary_bytes(report: &str, label: &str) -> Option<u64> {
    let line = report.lines().find(|l| l.contains(label))?;
    let after = line.split(label).nth(1)?.trim();
    after.split_whitespace().next()?.replace(',', "").parse().ok()
}

#[derive(Clone, Copy)]
struct LossRecord<'a> {
    kind: &'a str,
    bytes: u64,
    arbor: bool,
    /// Allocated by crossbeam-epoch (see `CROSSBEAM_RECORDS_MAX`).
    crossbeam_local: bool,
    text: &'a str,
}

/// The loss records of a valgrind log ("N bytes in M blocks are possibly lost in loss record
/// ..." and the stack below it), with whether an Arbor frame allocated the block.
fn loss_records(report: &str) -> Vec<LossRecord<'_>> {
    let mut records = Vec::new();
    let mut starts: Vec<usize> = report.match_indices(" are ").map(|(i, _)| i).collect();
    starts.retain(|&i| report[i..].starts_with(" are possibly lost") || report[i..].starts_with(" are definitely lost"));
    for i in starts {
        let line_start = report[..i].rfind('\n').map_or(0, |p| p + 1);
        // The record ends at the first line holding only the "==pid==" prefix.
        let rest = &report[line_start..];
        let end = rest.find("== \n").or_else(|| rest.find("==\n")).unwrap_or(rest.len());
        let text = &rest[..end];
        let head = text.lines().next().unwrap_or("");
        let bytes = head.split("==").last().and_then(|h| h.split_whitespace().next()).map(|b| b.replace(',', "")).and_then(|b| b.parse().ok()).unwrap_or(0);
        let kind = if head.contains("possibly lost") { "possibly" } else { "definitely" };
        let arbor = text.lines().skip(1).any(|l| l.contains("arbor::") || l.contains("libvulkan_arbor") || l.contains("vulkan_arbor::"));
        let crossbeam_local = text.contains("crossbeam_epoch::");
        records.push(LossRecord { kind, bytes, arbor, crossbeam_local, text });
    }
    records
}

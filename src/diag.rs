//! The diagnostics channel: one line per problem the driver detects.
//!
//! `ARBOR_DIAG` selects the level (`off`, `error`, `warn` (default), `info`, `debug`);
//! `ARBOR_DIAG_FILE` a file to append to instead of stderr. `ARBOR_STRICT=1` turns valid-usage
//! violations into `VK_ERROR_DEVICE_LOST` for the submission that contained them.
use std::fs::OpenOptions;
use std::io::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, OnceLock};

#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Debug)]
pub enum Level {
    Off = 0,
    Error = 1,
    Warn = 2,
    Info = 3,
    Debug = 4,
}

struct Channel {
    level: Level,
    file: Option<Mutex<std::fs::File>>,
    strict: bool,
}

fn channel() -> &'static Channel {
    static CHANNEL: OnceLock<Channel> = OnceLock::new();
    CHANNEL.get_or_init(|| {
        let level = match std::env::var("ARBOR_DIAG").as_deref() {
            Ok("off") | Ok("0") => Level::Off,
            Ok("error") => Level::Error,
            Ok("info") => Level::Info,
            Ok("debug") => Level::Debug,
            _ => Level::Warn,
        };
        let file = std::env::var_os("ARBOR_DIAG_FILE")
            .and_then(|p| OpenOptions::new().create(true).append(true).open(p).ok())
            .map(Mutex::new);
        let strict = matches!(std::env::var("ARBOR_STRICT").as_deref(), Ok("1") | Ok("true"));
        Channel { level, file, strict }
    })
}

static COUNT: AtomicU64 = AtomicU64::new(0);

/// Number of problems reported at Warn level or above since the process started.
pub fn reported_count() -> u64 {
    COUNT.load(Ordering::Relaxed)
}

pub fn enabled(level: Level) -> bool {
    level != Level::Off && level <= channel().level
}

/// Whether strict mode is on (violations make the submission report DEVICE_LOST).
pub fn strict() -> bool {
    channel().strict
}

/// Report one problem. `what` is the command or object concerned.
pub fn report(level: Level, what: &str, message: &str) {
    if level <= Level::Warn {
        COUNT.fetch_add(1, Ordering::Relaxed);
    }
    if !enabled(level) {
        return;
    }
    let tag = match level {
        Level::Error => "error",
        Level::Warn => "warning",
        Level::Info => "info",
        Level::Debug => "debug",
        Level::Off => return,
    };
    let line = format!("arbor: {tag}: {what}: {message}\n");
    let ch = channel();
    match &ch.file {
        Some(f) => {
            if let Ok(mut f) = f.lock() {
                let _ = f.write_all(line.as_bytes());
            }
        }
        None => {
            let _ = std::io::stderr().write_all(line.as_bytes());
        }
    }
}

/// A valid-usage violation: reported with its VUID at Error level.
pub fn vuid(vuid: &str, what: &str, message: &str) {
    report(Level::Error, what, &format!("[{vuid}] {message}"));
}

/// A command Arbor does not implement was called.
pub fn unsupported(command: &str) {
    report(Level::Warn, command, "not supported by Arbor (no graphics, no images yet)");
}

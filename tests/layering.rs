//! The layering the design asks for, checked on the source: `src/accel` (and the coming
//! `src/shader`) are pure libraries. Every `.rs` file below them may name no other part of the
//! driver (`crate::` paths outside `crate::accel`), neither ash nor the public `arbor::` facade,
//! and contains no `unsafe` (the module is also `#[forbid(unsafe_code)]`; this catches an
//! `allow` slipped in). Comments are not code: words in `//` comments do not count.
use std::path::{Path, PathBuf};

/// Every `.rs` file below `dir`, sorted.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display())) {
            let path = entry.expect("directory entry").path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

/// Whether `word` occurs in `code` as a whole identifier-like token.
fn has_token(code: &str, word: &str) -> bool {
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    code.match_indices(word).any(|(i, _)| {
        let before = code[..i].chars().next_back();
        let after = code[i + word.len()..].chars().next();
        !before.is_some_and(ident) && !after.is_some_and(ident)
    })
}

/// The layering violations of one line of code (comment already removed); `allowed_crate` are
/// the `crate::` prefixes the layer may use.
fn violations(code: &str, allowed_crate: &[&str]) -> Vec<String> {
    let mut found = Vec::new();
    for (i, _) in code.match_indices("crate::") {
        let preceded = code[..i].chars().next_back().is_some_and(|c| c.is_alphanumeric() || c == '_');
        let rest = &code[i + "crate::".len()..];
        if !preceded && !allowed_crate.iter().any(|a| rest.starts_with(a) && !rest[a.len()..].starts_with(|c: char| c.is_alphanumeric() || c == '_')) {
            found.push(format!("a driver path `crate::{}`", rest.split(|c: char| !(c.is_alphanumeric() || c == '_' || c == ':')).next().unwrap_or("")));
        }
    }
    if has_token(code, "unsafe") {
        found.push("`unsafe`".into());
    }
    if code.contains("use ash") || has_token(code, "ash") && code.contains("ash::") {
        found.push("ash".into());
    }
    if has_token(code, "arbor") && code.contains("arbor::") {
        found.push("an `arbor::` path".into());
    }
    found
}

/// Checks every file below `layer` (relative to the crate) and returns what it finds.
fn check_layer(layer: &str, allowed_crate: &[&str]) -> Vec<String> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join(layer);
    let mut problems = Vec::new();
    for file in rust_files(&dir) {
        let text = std::fs::read_to_string(&file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        for (n, line) in text.lines().enumerate() {
            let code = line.split("//").next().unwrap_or("");
            for v in violations(code, allowed_crate) {
                problems.push(format!("{}:{}: {v}: {}", file.strip_prefix(env!("CARGO_MANIFEST_DIR")).unwrap_or(&file).display(), n + 1, line.trim()));
            }
        }
    }
    problems
}

#[test]
fn accel_imports_nothing_of_the_driver() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/accel");
    assert!(rust_files(&dir).len() > 10, "src/accel should hold the library's modules");
    let problems = check_layer("src/accel", &["accel"]);
    assert!(problems.is_empty(), "src/accel must stay pure:\n{}", problems.join("\n"));
}

/// The shader layer (when it exists) may use the acceleration-structure library, nothing else.
#[test]
fn shader_imports_only_accel() {
    if !Path::new(env!("CARGO_MANIFEST_DIR")).join("src/shader").is_dir() {
        return;
    }
    let problems = check_layer("src/shader", &["accel", "shader"]);
    assert!(problems.is_empty(), "src/shader must stay pure:\n{}", problems.join("\n"));
}

/// The checker itself: each kind of violation is seen, comments and allowed paths are not.
#[test]
fn the_checker_sees_violations() {
    assert!(violations("use crate::accel::layout;", &["accel"]).is_empty());
    assert!(violations("let x = crate::accel_x::y;", &["accel"]).len() == 1);
    assert!(violations("crate::memory::prefetch_read(b, 0);", &["accel"]).len() == 1);
    assert!(violations("unsafe { f() }", &["accel"]).len() == 1);
    assert!(violations("use ash::vk;", &["accel"]).len() == 1);
    assert!(violations("let d = arbor::accel::build;", &["accel"]).len() == 1);
    assert!(violations("fn not_unsafe_code() {}", &["accel"]).is_empty());
    let line = "let a = 1; // crate::memory and unsafe in a comment";
    assert!(violations(line.split("//").next().unwrap(), &["accel"]).is_empty());
}

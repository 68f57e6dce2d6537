//! scripts/install.sh: the manifest it writes for the already-built release driver, the loader
//! finding Arbor through it without VK_ICD_FILENAMES (vulkaninfo), and --uninstall. HOME and
//! XDG_DATA_HOME point into a temporary directory, so the real system is never touched.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn checkout() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// target/ of this test run (CARGO_TARGET_DIR may move it): the script is told the same.
fn target_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/install-<hash>
    exe.parent().and_then(|d| d.parent()).and_then(|d| d.parent()).expect("target/").to_path_buf()
}

fn release_library() -> PathBuf {
    let lib = target_dir().join("release").join("libvulkan_arbor.so");
    assert!(
        lib.exists(),
        "{} is missing: build the driver first (`cargo build --release --workspace`, as the README's test command does)",
        lib.display()
    );
    lib
}

/// A fresh directory of this test under the system temp directory, removed by Drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> TempDir {
        let d = std::env::temp_dir().join(format!("arbor-install-test-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        TempDir(d)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// scripts/install.sh with `args`, HOME and XDG_DATA_HOME inside `tmp`, never building.
fn install_sh(tmp: &Path, args: &[&str]) -> Output {
    let out = Command::new("bash")
        .arg(checkout().join("scripts/install.sh"))
        .args(args)
        .env("HOME", tmp.join("home"))
        .env("XDG_DATA_HOME", tmp.join("data"))
        .env("CARGO_TARGET_DIR", target_dir())
        .env_remove("VK_ICD_FILENAMES")
        .env_remove("VK_DRIVER_FILES")
        .output()
        .expect("run bash scripts/install.sh");
    assert!(out.status.success(), "install.sh {args:?} failed:\n{}", text(&out));
    out
}

fn text(out: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

#[test]
fn install_user_manifest_is_found_by_the_loader_and_uninstall_removes_it() {
    let library = release_library();
    let tmp = TempDir::new("user");
    let manifest = tmp.0.join("data/vulkan/icd.d/arbor_icd.json");

    let out = install_sh(&tmp.0, &["--user", "--no-build"]);
    assert!(text(&out).contains(&manifest.display().to_string()), "the script says where it wrote:\n{}", text(&out));
    check_manifest(&manifest, &library);

    // The loader searches $XDG_DATA_HOME/vulkan/icd.d; other drivers of the machine may be listed too.
    let out = Command::new("vulkaninfo")
        .arg("--summary")
        .env("HOME", tmp.0.join("home"))
        .env("XDG_DATA_HOME", tmp.0.join("data"))
        .env_remove("VK_ICD_FILENAMES")
        .env_remove("VK_DRIVER_FILES")
        // Mesa's implicit device-select layer may be installed; it is not under test.
        .env("NODEVICE_SELECT", "1")
        .env("VK_LOADER_DEBUG", "driver")
        .output()
        .unwrap_or_else(|e| panic!("vulkaninfo could not run ({e}): install the package vulkan-tools (scripts/deps.sh does)"));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "vulkaninfo --summary failed:\n{stdout}\n{stderr}");
    assert!(
        stdout.lines().any(|l| l.trim().starts_with("deviceName") && l.contains("= Arbor (software)")),
        "vulkaninfo lists no Arbor device through the installed manifest:\n{stdout}\n{stderr}"
    );
    assert!(stderr.contains(&manifest.display().to_string()), "the loader did not report reading {}:\n{stderr}", manifest.display());

    let out = install_sh(&tmp.0, &["--user", "--uninstall"]);
    assert!(!manifest.exists(), "--uninstall left {}", manifest.display());
    assert!(text(&out).contains(&format!("Removed {}", manifest.display())), "{}", text(&out));
    // A second --uninstall has nothing to do and says so.
    let out = install_sh(&tmp.0, &["--user", "--uninstall"]);
    assert!(text(&out).contains("Nothing to remove"), "{}", text(&out));
}

#[test]
fn install_prefix_writes_under_the_prefix() {
    let library = release_library();
    let tmp = TempDir::new("prefix");
    let prefix = tmp.0.join("prefix");
    let p = prefix.to_str().unwrap();
    install_sh(&tmp.0, &["--prefix", p, "--no-build"]);
    let manifest = prefix.join("share/vulkan/icd.d/arbor_icd.json");
    check_manifest(&manifest, &library);
    assert!(!tmp.0.join("data/vulkan").exists(), "--prefix also wrote into XDG_DATA_HOME");
    install_sh(&tmp.0, &["--prefix", p, "--uninstall"]);
    assert!(!manifest.exists(), "--uninstall --prefix left {}", manifest.display());
}

/// The manifest is the repository's icd.json with an absolute library_path to the built driver.
fn check_manifest(manifest: &Path, library: &Path) {
    let text = std::fs::read_to_string(manifest).unwrap_or_else(|e| panic!("{}: {e}", manifest.display()));
    let json = Json::parse(&text).unwrap_or_else(|e| panic!("{} is not JSON ({e}):\n{text}", manifest.display()));
    let repo = Json::parse(&std::fs::read_to_string(checkout().join("icd.json")).unwrap()).expect("icd.json is JSON");
    assert_eq!(json.get("file_format_version"), repo.get("file_format_version"), "{text}");
    let (icd, repo_icd) = (json.get("ICD").expect("an ICD object"), repo.get("ICD").unwrap());
    assert_eq!(icd.get("api_version"), repo_icd.get("api_version"), "{text}");
    let Some(Json::Str(path)) = icd.get("library_path") else { panic!("no library_path string:\n{text}") };
    let path = Path::new(path);
    assert!(path.is_absolute(), "library_path {} is not absolute", path.display());
    assert!(path.is_file(), "library_path {} does not exist", path.display());
    assert_eq!(path.canonicalize().unwrap(), library.canonicalize().unwrap(), "library_path is not the built release driver");
}

/// Just enough JSON for a manifest: objects, strings (no escapes beyond \" and \\), numbers and
/// literals, so the test needs no JSON crate.
#[derive(Debug, PartialEq)]
enum Json {
    Object(BTreeMap<String, Json>),
    Str(String),
    Other(String),
}

impl Json {
    fn parse(text: &str) -> Result<Json, String> {
        let mut chars = text.chars().peekable();
        let value = Self::value(&mut chars)?;
        Self::skip_ws(&mut chars);
        match chars.next() {
            None => Ok(value),
            Some(c) => Err(format!("trailing {c:?}")),
        }
    }

    fn get(&self, key: &str) -> Option<&Json> {
        match self {
            Json::Object(m) => m.get(key),
            _ => None,
        }
    }

    fn skip_ws(chars: &mut std::iter::Peekable<std::str::Chars>) {
        while chars.peek().is_some_and(|c| c.is_whitespace()) {
            chars.next();
        }
    }

    fn value(chars: &mut std::iter::Peekable<std::str::Chars>) -> Result<Json, String> {
        Self::skip_ws(chars);
        match chars.peek().copied() {
            Some('{') => {
                chars.next();
                let mut m = BTreeMap::new();
                loop {
                    Self::skip_ws(chars);
                    if chars.peek() == Some(&'}') && m.is_empty() {
                        chars.next();
                        return Ok(Json::Object(m));
                    }
                    let Json::Str(key) = Self::value(chars)? else { return Err("an object key is not a string".into()) };
                    Self::skip_ws(chars);
                    if chars.next() != Some(':') {
                        return Err(format!("no ':' after {key:?}"));
                    }
                    let v = Self::value(chars)?;
                    if m.insert(key.clone(), v).is_some() {
                        return Err(format!("duplicate key {key:?}"));
                    }
                    Self::skip_ws(chars);
                    match chars.next() {
                        Some(',') => {}
                        Some('}') => return Ok(Json::Object(m)),
                        c => return Err(format!("expected ',' or '}}', found {c:?}")),
                    }
                }
            }
            Some('"') => {
                chars.next();
                let mut s = String::new();
                loop {
                    match chars.next() {
                        Some('"') => return Ok(Json::Str(s)),
                        Some('\\') => match chars.next() {
                            Some(c @ ('"' | '\\' | '/')) => s.push(c),
                            c => return Err(format!("unsupported escape {c:?}")),
                        },
                        Some(c) => s.push(c),
                        None => return Err("unterminated string".into()),
                    }
                }
            }
            Some(c) if c == '-' || c.is_ascii_alphanumeric() => {
                let mut s = String::new();
                while chars.peek().is_some_and(|c| *c == '-' || *c == '.' || *c == '+' || c.is_ascii_alphanumeric()) {
                    s.push(chars.next().unwrap());
                }
                match s.as_str() {
                    "true" | "false" | "null" => Ok(Json::Other(s)),
                    _ if s.parse::<f64>().is_ok() => Ok(Json::Other(s)),
                    _ => Err(format!("not a JSON value: {s}")),
                }
            }
            c => Err(format!("unexpected {c:?}")),
        }
    }
}

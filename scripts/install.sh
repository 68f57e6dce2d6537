#!/usr/bin/env bash
# Installs Arbor for the Vulkan loader: builds the release driver and writes the ICD manifest
# arbor_icd.json, whose library_path is the absolute path of this checkout's
# target/release/libvulkan_arbor.so, where the loader searches without VK_ICD_FILENAMES:
#   a normal user:           ${XDG_DATA_HOME:-$HOME/.local/share}/vulkan/icd.d/
#   root (unless --user):    /etc/vulkan/icd.d/
#   --prefix DIR:            DIR/share/vulkan/icd.d/ (DIR/share must be in XDG_DATA_DIRS;
#                            /usr/local and /usr are by default)
# The library stays in the checkout: rebuilding updates the installed driver, and moving or
# deleting the checkout breaks it (run --uninstall first).
set -euo pipefail

usage() {
  cat <<'EOF'
Usage: scripts/install.sh [--user | --prefix DIR] [--no-build] [--uninstall]

  --user        install for the current user even when run as root
  --prefix DIR  write the manifest into DIR/share/vulkan/icd.d
  --no-build    do not build; use the already-built target/release/libvulkan_arbor.so
  --uninstall   remove the manifest this script writes (same location rules)
EOF
}

root="$(cd "$(dirname "$0")/.." && pwd)"
user=0
prefix=""
build=1
uninstall=0
while [ $# -gt 0 ]; do
  case "$1" in
    --user) user=1 ;;
    --prefix)
      [ $# -ge 2 ] || { echo "install.sh: --prefix needs a directory" >&2; exit 2; }
      prefix="$2"
      shift
      ;;
    --prefix=*) prefix="${1#--prefix=}" ;;
    --no-build) build=0 ;;
    --uninstall) uninstall=1 ;;
    -h | --help) usage; exit 0 ;;
    *) echo "install.sh: unknown argument: $1" >&2; usage >&2; exit 2 ;;
  esac
  shift
done
if [ "$user" -eq 1 ] && [ -n "$prefix" ]; then
  echo "install.sh: --user and --prefix choose different places; give one" >&2
  exit 2
fi

if [ -n "$prefix" ]; then
  dir="$prefix/share/vulkan/icd.d"
elif [ "$(id -u)" -eq 0 ] && [ "$user" -eq 0 ]; then
  dir="/etc/vulkan/icd.d"
else
  # The loader reads $XDG_DATA_HOME/vulkan/icd.d, or ~/.local/share/vulkan/icd.d when it is unset.
  [ -n "${XDG_DATA_HOME:-}" ] || [ -n "${HOME:-}" ] || { echo "install.sh: neither XDG_DATA_HOME nor HOME is set" >&2; exit 1; }
  dir="${XDG_DATA_HOME:-$HOME/.local/share}/vulkan/icd.d"
fi
manifest="$dir/arbor_icd.json"

if [ "$uninstall" -eq 1 ]; then
  if [ -e "$manifest" ]; then
    rm -f "$manifest"
    echo "Removed $manifest"
  else
    echo "Nothing to remove: $manifest does not exist"
  fi
  exit 0
fi

if [ "$build" -eq 1 ]; then
  # Only the driver: applications need nothing else of the workspace.
  echo "Building the release driver: cargo build --release -p vulkan_arbor"
  (cd "$root" && cargo build --release -p vulkan_arbor)
fi

# CARGO_TARGET_DIR moves target/ as it does for cargo (relative to the checkout, as cargo reads it there).
target="${CARGO_TARGET_DIR:-target}"
case "$target" in /*) ;; *) target="$root/$target" ;; esac
library="$(cd "$target/release" 2>/dev/null && pwd)/libvulkan_arbor.so" || library="$target/release/libvulkan_arbor.so"
if [ ! -f "$library" ]; then
  echo "install.sh: $library is missing: build it (cargo build --release -p vulkan_arbor) or drop --no-build" >&2
  exit 1
fi

# The repository's icd.json with the absolute library path: the same format version, API
# version and fields.
case "$library" in *'|'* | *'\'* | *'"'*)
  echo "install.sh: the library path contains a character JSON or sed would need escaped: $library" >&2
  exit 1
  ;;
esac
mkdir -p "$dir"
tmp="$(mktemp "$dir/.arbor_icd.json.XXXXXX")"
sed -E 's|"library_path": *"[^"]*"|"library_path": "'"$library"'"|' "$root/icd.json" >"$tmp"
grep -qF "\"library_path\": \"$library\"" "$tmp" || { rm -f "$tmp"; echo "install.sh: could not write library_path from $root/icd.json" >&2; exit 1; }
chmod 644 "$tmp"
mv -f "$tmp" "$manifest"

echo "Wrote $manifest"
echo "  library_path: $library"
echo "The Vulkan loader now finds Arbor without VK_ICD_FILENAMES: vulkaninfo --summary lists \"Arbor (software)\"."
if [ -n "${VK_ICD_FILENAMES:-}${VK_DRIVER_FILES:-}" ]; then
  echo "Note: VK_ICD_FILENAMES or VK_DRIVER_FILES is set in this shell; the loader then reads only those files." >&2
fi
echo "Remove it with: scripts/install.sh --uninstall${prefix:+ --prefix $prefix}$([ "$user" -eq 1 ] && echo ' --user')"

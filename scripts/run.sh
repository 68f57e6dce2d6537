#!/usr/bin/env bash
# The main job (README): builds Arbor and runs arbor-bench through the Vulkan loader.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/deps.sh
cargo build --release --workspace --locked
exec target/release/arbor-bench "$@"

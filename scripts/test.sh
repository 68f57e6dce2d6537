#!/usr/bin/env bash
# The test command (README, .ci/run): installs the Vulkan loader, vulkan-tools and the validation
# layer if missing, builds the driver (release), then runs the whole suite in release mode.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/deps.sh
cargo build --release --workspace --locked
cargo test --release --workspace --locked

#!/usr/bin/env bash
# The test command: installs the pinned toolchain, builds everything in
# release (Enzyme needs it) under the Enzyme log guard, runs the test suite
# (the command line included), and builds and runs the template user crate.
set -euo pipefail
cd "$(dirname "$0")/.."
guard=scripts/cargo-enzyme

$guard build --release --all-targets
$guard test --release

# The template crate builds with its own settings and runs its checks.
(cd examples/user-crate && CARGO_TARGET_DIR=../../target/user-crate ../../scripts/cargo-enzyme run --release)
echo "all tests passed"

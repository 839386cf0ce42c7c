#!/usr/bin/env bash
# The test command: installs the pinned toolchain, builds everything in
# release (Enzyme needs it) under the Enzyme log guard, runs the test suite
# (the command line included), and makes a crate of one's own with
# `diffsim new` in a temporary folder, then builds and runs it.
set -euo pipefail
cd "$(dirname "$0")/.."
guard=scripts/cargo-enzyme

$guard build --release --all-targets
$guard test --release

# A crate of one's own, as a new user makes it (docs/own-solver.md): it
# builds under its copy of the guard (into this checkout's target folder,
# as `diffsim new` sets up), checks its gradients and fits its parameters.
own=$(mktemp -d)/my-solver
trap 'rm -rf "$(dirname "$own")"' EXIT
target/release/diffsim new "$own"
(cd "$own" && ./cargo-enzyme run --release)
echo "all tests passed"

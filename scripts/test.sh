#!/usr/bin/env bash
# The test command: installs the pinned toolchain, builds everything in
# release (Enzyme needs it) under the Enzyme log guard, runs the test suite
# (the command line included), and makes a crate of one's own with
# `diffsim new` in a temporary folder, then builds and runs it.
set -euo pipefail
cd "$(dirname "$0")/.."
# Open MPI and libclang, installed when missing (the `mpi` feature links them).
scripts/system-packages
guard=scripts/cargo-enzyme

$guard build --release --all-targets
$guard test --release

# The Python package (python/): built under the guard, installed into .venv
# with NumPy, JAX and pytest, and its tests run (docs/python.md).
scripts/python-install
"${DIFFSIM_VENV:-.venv}/bin/python" -m pytest -q python/tests

# A crate of one's own, as a new user makes it (docs/own-solver.md): it
# builds under its copy of the guard (into this checkout's target folder,
# as `diffsim new` sets up), checks its gradients and fits its parameters.
own=$(mktemp -d)/my-solver
trap 'rm -rf "$(dirname "$own")"' EXIT
target/release/diffsim new "$own"
(cd "$own" && ./cargo-enzyme run --release && ./cargo-enzyme test --release)
# The implicit template (docs/own-solver.md, "An implicit step"): the same.
target/release/diffsim new "$own-implicit" --template implicit
(cd "$own-implicit" && ./cargo-enzyme run --release && ./cargo-enzyme test --release)
# A debug build there stops at once and says what to run instead.
if (cd "$own" && cargo build >"$own.debug.log" 2>&1); then
    echo "a debug build of the new crate did not stop" >&2
    exit 1
fi
grep -q "diffsim needs a release build" "$own.debug.log" || { cat "$own.debug.log" >&2; exit 1; }
echo "all tests passed"

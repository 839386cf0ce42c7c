#!/usr/bin/env bash
# The test command: installs the pinned toolchain, builds everything in
# release (Enzyme needs it) under the Enzyme log guard, runs the test suite,
# checks the command line, and builds and runs the template user crate.
set -euo pipefail
cd "$(dirname "$0")/.."
guard=scripts/cargo-enzyme

$guard build --release --all-targets
$guard test --release

# Command line: bad input is a clear error with a non-zero exit, no panic.
bin=target/release/diffsim
expect_fail() {
    local needle=$1; shift
    if out=$("$bin" "$@" 2>&1); then echo "FAIL: diffsim $* succeeded" >&2; exit 1; fi
    grep -q -- "$needle" <<<"$out" || { echo "FAIL: diffsim $*: expected '$needle' in: $out" >&2; exit 1; }
    if grep -q panicked <<<"$out"; then echo "FAIL: diffsim $* panicked: $out" >&2; exit 1; fi
}
expect_fail "invalid argument --n" bench p1 --n 2
expect_fail "invalid argument --steps" bench p1 --steps 0
expect_fail "invalid argument --threads" bench p1 --threads 0
expect_fail "unknown checkpointing" bench p1 --checkpoint sometimes
expect_fail "invalid value 'many'" bench p1 --n many
line=$("$bin" bench p1 --n 37 --steps 5 --threads 1 --json)
python3 - "$line" <<'PY'
import json, sys
d = json.loads(sys.argv[1])
keys = ["problem", "n", "steps", "threads", "forward_s", "grad_s", "hand_grad_s", "grad_over_forward",
        "enzyme_over_hand", "peak_rss_bytes", "loss", "grad_l2", "grad_0", "grad_n2"]
missing = [k for k in keys if k not in d]
assert not missing, f"missing keys {missing} in {d}"
assert d["problem"] == "p1" and d["n"] == 37 and d["steps"] == 5 and d["threads"] == 1, d
assert abs(d["loss"] - d["forward_loss"]) < 1e-15, d
assert d["enzyme_hand_max_diff"] < 1e-14, d
print("cli: ok")
PY

# The template crate builds with its own settings and runs its checks.
(cd examples/user-crate && CARGO_TARGET_DIR=../../target/user-crate ../../scripts/cargo-enzyme run --release)
echo "all tests passed"

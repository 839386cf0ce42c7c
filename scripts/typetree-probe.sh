#!/usr/bin/env bash
# Reproduces the table in docs/pitfalls.md ("rustc aborts in Enzyme's type
# analysis"): which snippets of ordinary code abort rustc in a crate built
# with -Zautodiff=Enable, and that the aborting ones build in the program
# crate (src/, no flag) of the layout `diffsim new` writes. Run it again
# after a toolchain update. Takes a few minutes; not part of the tests.
set -uo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
scripts/cargo-enzyme build --release --bin diffsim >/dev/null 2>&1 || { echo "building diffsim failed (scripts/cargo-enzyme build --release)"; exit 1; }
dir=$(mktemp -d)
trap 'rm -rf "$dir"' EXIT
"$repo/target/release/diffsim" new "$dir/probe" >/dev/null || exit 1
cd "$dir/probe"
cp solver/src/lib.rs "$dir/solver.rs"
cp src/lib.rs "$dir/program.rs"

# One snippet per line; each runs inside a function.
snippets=(
  'for (which, idx) in [("p", 0usize), ("p", 1)] { println!("{which}{idx}"); }'
  'for (which, idx) in black_box([("p", 0usize), ("p", 1)]) { println!("{which}{idx}"); }'
  'let cases = black_box([(1usize, 2usize, 0.5f64), (3, 4, 1.5)]); for (a, b, c) in cases { println!("{a}{b}{c}"); }'
  'let cases = black_box([(1usize, 2usize, 0.5f64), (3, 4, 1.5)]); for &(a, b, c) in cases.iter() { println!("{a}{b}{c}"); }'
  'let pairs = black_box([(String::from("a"), 1.0f64), (String::from("b"), 2.0)]); for (s, v) in pairs { println!("{s}{v}"); }'
  'for (which, idx) in [("p", 0usize), ("p", 1)].iter() { println!("{which}{idx}"); }'
  'let names = black_box(["a", "bc"]); for n in names { println!("{n}"); }'
  'let v = black_box([vec![1.0f64], vec![2.0]]).concat(); println!("{v:?}");'
  'fn f(x: f64) -> Result<Vec<f64>, String> { if x > 0.0 { Ok(vec![x]) } else { Err(format!("bad {x}")) } } println!("{:?}", f(black_box(1.0)));'
  'let xs: Vec<(usize, f64)> = black_box(vec![(1, 0.5), (2, 1.5)]); for (i, v) in xs { println!("{i}{v}"); }'
)

# Builds and reports: builds, ABORTS (the type-tree abort), or fails otherwise.
outcome() {
    if cargo build --release >"$dir/log" 2>&1; then echo "builds"
    elif grep -qE 'TypeTree\.h|illegal insertion|signal: 6' "$dir/log"; then echo "ABORTS"
    else echo "fails otherwise (see below)"; tail -5 "$dir/log"; fi
}

echo "In the flagged crate (solver/, a public function beside the differentiated step):"
aborting=()
for s in "${snippets[@]}"; do
    cp "$dir/solver.rs" solver/src/lib.rs
    printf '\n/// A probe.\npub fn probe() {\n    use std::hint::black_box;\n    %s\n}\n' "$s" >> solver/src/lib.rs
    r=$(outcome)
    echo "  $r: $s"
    [ "$r" = "ABORTS" ] && aborting+=("$s")
done
cp "$dir/solver.rs" solver/src/lib.rs

echo "The ${#aborting[@]} aborting snippets together in the program crate (src/, no flag):"
cp "$dir/program.rs" src/lib.rs
{
    printf '\n/// The probes.\npub fn probe() {\n    use std::hint::black_box;\n'
    for s in "${aborting[@]}"; do printf '    {\n        %s\n    }\n' "$s"; done
    printf '}\n'
} >> src/lib.rs
echo "  $(outcome)"
if cargo run --release >"$dir/run.log" 2>&1; then echo "  and the crate's checks and fit pass"; else echo "  but its run failed:"; tail -5 "$dir/run.log"; fi

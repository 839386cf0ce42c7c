#!/usr/bin/env bash
# The demo: P1 burgers1d loss and gradient (Enzyme and hand-written),
# through the gradient checks and against the reference table, with timings
# at sizes S, M and L; then a smoke plume around an obstacle as a PNG, in
# 2D and in 3D; then a short training run through the solver.
set -euo pipefail
cd "$(dirname "$0")/.."
# Open MPI and libclang, installed when missing (the `mpi` feature links them).
scripts/system-packages
scripts/cargo-enzyme build --release --bin diffsim
# The gradient of a whole P1 rollout through the three checks.
target/release/diffsim check --n 256 --steps 256
echo
for size in "256 256" "2048 2048" "16384 1000"; do
    set -- $size
    target/release/diffsim bench p1 --n "$1" --steps "$2" --checkpoint periodic
    echo
done

# A smoke plume rising around an obstacle (P2's solver with an obstacle and
# an inflow), written to out/demo/plume.png (the demo's own folders: a
# second run replaces its results, never another run's).
target/release/diffsim demo plume --out out/demo

# The same in 3D: a scene file (64³ cells, 200 steps, about 10 s): smoke
# rises around a sphere; writes out/demo/plume3d/smoke.npy and the middle slice
# and the maximum along z as PNGs.
target/release/diffsim run scenes/plume3d.toml --out out/demo/plume3d

# Training through the solver: a correction network trained through 16
# unrolled steps of the coarse Burgers solver (600 updates, about 20 s);
# writes out/demo/train/loss.csv, loss.png, model.json, checkpoint.json.
target/release/diffsim train configs/sol_burgers.toml --out out/demo/train --overwrite

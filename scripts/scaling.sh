#!/usr/bin/env bash
# Data-parallel scaling on this machine (docs/distributed.md): for P3 and
# the 2D wake training, the time per iteration of one process on one
# thread, one process on two threads, and two MPI ranks on one thread each,
# with the efficiencies and the model's predictions from the two-rank run.
# Usage: scripts/scaling.sh [ITERATIONS]   (after a release build)
set -euo pipefail
cd "$(dirname "$0")/.."
bin=target/release/diffsim
iterations=${1:-20}
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
for w in p3 wake; do
    one=$($bin bench scaling --workload "$w" --threads 1 --iterations "$iterations" --json)
    two=$($bin bench scaling --workload "$w" --threads 2 --iterations "$iterations" --json)
    ranks=$(mpirun --oversubscribe -np 2 $bin bench scaling --workload "$w" --threads 1 --iterations "$iterations" --json)
    python3 - "$w" "$one" "$two" "$ranks" <<'PY'
import json, sys
w, one, two, ranks = sys.argv[1], *(json.loads(a) for a in sys.argv[2:])
t1, tt, tr = one["iteration_s"], two["iteration_s"], ranks["iteration_s"]
print(f"| {w} | {one['batch']} | {one['params']} | {1e3*t1:.2f} | {1e3*tt:.2f} ({t1/(2*tt):.0%}) | {1e3*tr:.2f} ({t1/(2*tr):.0%}) "
      f"| {1e3*ranks['exchange_s']:.3f} | {ranks['bytes_in_per_rank']} |")
m = ranks["model"]
print(f"  model from the two-rank run: t_s {1e3*m['sample_s']:.3f} ms, t_0 {1e3*m['fixed_s']:.3f} ms, "
      f"alpha {1e6*m['latency_s']:.2f} us, beta {m['bandwidth_bytes_s']/1e9:.2f} GB/s; "
      + ", ".join(f"{k} ranks {ranks[f'efficiency_{k}']:.0%} (batch {ranks['batch']}) / {ranks[f'efficiency_{k}_batch_per_rank']:.0%} "
                  f"(batch {ranks['batch']}x{k}), 50% needs batch {ranks[f'batch_for_half_{k}']}" for k in (8, 64, 512))
      + f"; rank limit {ranks['rank_limit']:.0f}")
PY
done

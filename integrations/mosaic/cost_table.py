"""The cost suites' results as the tables of docs/mosaic.md: seconds per call
(the harness's mean over its trials) for every solver that ran, and the
exponent of cost against N (least squares on log-log). Run from the
repository root after `scripts/mosaic ... --suites cost`:

    python3 integrations/mosaic/cost_table.py [RESULTS_DIR]

(RESULTS_DIR defaults to target/mosaic-results.)"""

import json
import math
import pathlib
import sys

root = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "target/mosaic-results")
experiments = [
    ("ns-grid", "spatial_cost", "2D forward, 100 steps"),
    ("ns-grid", "vjp_cost/by_N", "2D VJP, 100 steps"),
    ("ns-grid", "temporal_cost", "2D forward at N = 128"),
    ("ns-grid", "vjp_cost/by_steps", "2D VJP at N = 128"),
    ("ns-3d-grid", "spatial_cost", "3D forward"),
    ("ns-3d-grid", "vjp_cost/by_N", "3D VJP"),
    ("ns-3d-grid", "temporal_cost", "3D forward against steps"),
    ("ns-3d-grid", "vjp_cost/by_steps", "3D VJP against steps"),
]


def slope(points: list[tuple[float, float]]) -> float:
    xs = [math.log(x) for x, _ in points]
    ys = [math.log(y) for _, y in points]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)


for problem, name, title in experiments:
    path = root / problem / "cost" / name / "result.json"
    if not path.exists():
        continue
    result = json.loads(path.read_text())
    rows: dict[str, dict[str, float | None]] = {}
    for entry in result["results"]:
        metrics = entry.get("metrics") or {}
        rows.setdefault(entry["solver"], {})[entry["sweep_value"]] = metrics.get("mean")
    sweep = [str(v) for v in result["sweep"]["values"]]
    by_n = "steps" not in name and "temporal" not in name
    print(f"\n{title} ({problem}/cost/{name}), seconds")
    print("| " + ("N" if by_n else "steps") + " | " + " | ".join(sweep) + (" | exponent |" if by_n else " |"))
    print("|---|" + "---|" * (len(sweep) + (1 if by_n else 0)))
    for solver, values in rows.items():
        cells = [f"{values[v]:.3g}" if values.get(v) else "—" for v in sweep]
        line = f"| {solver} | " + " | ".join(cells)
        if by_n:
            points = [(float(v), values[v]) for v in sweep if values.get(v)]
            line += f" | {slope(points):.2f}" if len(points) > 1 else " | —"
        print(line + " |")

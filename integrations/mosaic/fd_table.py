"""The fd_check of Mosaic's ns-grid at more ε, two ways (docs/mosaic.md):
as the harness computes it (float32 inputs and outputs, float32 sum of
result²) through diffsim's Tesseract, and in float64 throughout through the
same rollout operator. Run from the repository root with the test
environment: .venv/bin/python integrations/mosaic/fd_table.py (the scheme
the Tesseract's: DIFFSIM_MOSAIC_SCHEME=central, maccormack or
semi_lagrangian)."""

import pathlib
import sys

import numpy as np

root = pathlib.Path(__file__).resolve().parents[2]
sys.path[:0] = [str(root / "python/tests"), str(root / "integrations/mosaic/navier-stokes-grid/diffsim")]

import tesseract_api as api  # noqa: E402
from test_mosaic import API, Tesseract, inputs, multimode  # noqa: E402

n, nu, dt, steps = 16, 0.001, 0.05, 20
v0 = multimode(n)
rng = np.random.default_rng(0)
dirs = [rng.standard_normal(v0.shape).astype(np.float32) for _ in range(20)]
dirs = [d / np.linalg.norm(d) for d in dirs]
scale = float(np.sqrt(np.mean(v0.astype(np.float64) ** 2)))
eps_values = [5, 1, 0.3, 0.1, 0.01, 0.001]

# As the harness: float32 in and out.
tess = Tesseract.from_tesseract_api(API)
base = inputs(v0, nu, dt, steps)
out = tess.apply(base)["result"]
g = tess.vector_jacobian_product(base, ["v0"], ["result"], {"result": 2 * out})["v0"]
vjp = np.array([float(np.sum(g * d)) for d in dirs])


def loss32(v):
    return float(np.sum(tess.apply({**base, "v0": v.astype(np.float32)})["result"].astype(np.float32) ** 2))


# float64 throughout: the same rollout, packed as the Tesseract packs it.
op = api._centred(v0.shape, 2 * np.pi, steps)
p = np.array([nu, dt])
x0 = api._pack(v0.astype(np.float64))
d64 = [api._pack(d.astype(np.float64)) for d in dirs]
g64, _ = op.vjp(x0, p, 2 * op.forward(x0, p))
vjp64 = np.array([g64 @ d for d in d64])


def loss64(x):
    return float(np.sum(op.forward(x, p) ** 2))


def median_rel(fd, ref):
    return float(np.median(np.abs(fd - ref) / np.maximum(np.maximum(np.abs(fd), np.abs(ref)), 1e-30)))


rows = {"float32 in and out, float32 sum (as the harness)": [], "float64 throughout": []}
for eps in eps_values:
    h = eps * scale
    fd32 = np.array([(loss32(v0 + h * d) - loss32(v0 - h * d)) / (2 * h) for d in dirs])
    fd64 = np.array([(loss64(x0 + h * d) - loss64(x0 - h * d)) / (2 * h) for d in d64])
    rows["float32 in and out, float32 sum (as the harness)"].append(median_rel(fd32, vjp))
    rows["float64 throughout"].append(median_rel(fd64, vjp64))
print("| ε (× the field's RMS) | " + " | ".join(f"{e:g}" for e in eps_values) + " |")
print("|---|" + "---|" * len(eps_values))
for name, values in rows.items():
    print(f"| {name} | " + " | ".join(f"{v:.1e}" for v in values) + " |")

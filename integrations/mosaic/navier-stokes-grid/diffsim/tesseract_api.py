# diffsim as a solver of Mosaic's navier-stokes-grid problems (ns-grid,
# ns-3d-grid), in Mosaic's Tesseract layout.
"""diffsim's incompressible Navier–Stokes for Mosaic.

The canonical schema (``mosaic_shared.problems.navier_stokes_grid``): ``v0``
of shape (N, N, 1, 2) or (N, N, N, 3), float32, sampled at x_i = i·L/N; on a
periodic box those samples are diffsim's cell centres (the origin of a
periodic box is arbitrary), moved to and from the MAC faces by a spectral
half-cell shift, so that a smooth field survives the round trip without the
sin²(π/N) damping of a linear average. ``viscosity`` and ``dt`` are the
step's parameters; a ``dt`` larger than the stable step is split into
stable sub-steps inside each step (their number fixed per call, so the
gradient is of one function). The whole rollout is one call into Rust
(``Operator.repeat``); its VJP is one backward pass there, its states kept
as the memory budget allows. Everything is computed in float64; results are
returned as float32, as the schema says.

NumPy only: importing ``diffsim.jax`` would switch the harness's own JAX to
float64.

This slice serves periodic boxes (every ns-grid and ns-3d-grid experiment
without an obstacle). Walls, an obstacle, an inflow profile and the drag are
refused with a message saying so; they are the next slice.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
from mosaic_shared.problems.navier_stokes_grid import (
    InputSchema as _CanonicalInputSchema,
)
from mosaic_shared.problems.navier_stokes_grid import (
    OutputSchema as _CanonicalOutputSchema,
)
from mosaic_shared.schema_types import make_differentiable
from pydantic import model_validator

import diffsim

_DIFFERENTIABLE = ["v0", "viscosity", "dt", "inflow_profile"]


class InputSchema(make_differentiable(_CanonicalInputSchema, _DIFFERENTIABLE)):
    """The canonical inputs; what this slice cannot run is refused here."""

    @model_validator(mode="after")
    def _check_supported(self) -> "InputSchema":
        shape = tuple(np.shape(self.v0))
        if not (
            (len(shape) == 4 and shape[2:] == (1, 2) and shape[0] == shape[1])
            or (len(shape) == 4 and shape[3] == 3 and shape[0] == shape[1] == shape[2])
        ):
            raise ValueError(f"diffsim: v0 has shape {shape}; expected (N, N, 1, 2) or (N, N, N, 3)")
        if not 4 <= shape[0] <= 512:
            raise ValueError(f"diffsim: N = {shape[0]}; need 4 ≤ N ≤ 512")
        if not self.boundary_conditions.is_fully_periodic or self.obstacle is not None or self.inflow_profile is not None:
            raise ValueError(
                "diffsim: this Tesseract runs periodic boxes only so far "
                "(walls, obstacles and inflow profiles are not wired up yet)"
            )
        if self.steps < 0:
            raise ValueError(f"diffsim: steps = {self.steps}; must be ≥ 0")
        if not self.domain_extent > 0:
            raise ValueError(f"diffsim: domain_extent = {self.domain_extent}; must be positive")
        return self


class OutputSchema(make_differentiable(_CanonicalOutputSchema, ["result", "drag"])):
    """The canonical outputs (``drag`` is zero: no obstacle in this slice)."""


def _dim(shape: tuple[int, ...]) -> int:
    return 2 if shape[2:] == (1, 2) else 3


@lru_cache(maxsize=32)
def _operator(shape: tuple[int, ...], length: float, steps: int) -> diffsim.Operator:
    """The rollout of ``steps`` steps on cell-centred values, one per box."""
    step = diffsim.navier_stokes_step([shape[0]] * _dim(shape), length=length, centred=True)
    return step.repeat(steps)


def _pack(v: np.ndarray) -> np.ndarray:
    """(N, N, 1, 2) or (N, N, N, 3) → diffsim's layout: component after
    component, x fastest; float64."""
    d = _dim(v.shape)
    fields = v[:, :, 0, :] if d == 2 else v
    return np.concatenate([np.asarray(fields[..., c], dtype=np.float64).ravel(order="F") for c in range(d)])


def _unpack(x: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """The inverse of :func:`_pack`, in float64."""
    d = _dim(shape)
    grid = shape[:2] if d == 2 else shape[:3]
    cells = int(np.prod(grid))
    comps = [x[c * cells : (c + 1) * cells].reshape(grid, order="F") for c in range(d)]
    v = np.stack(comps, axis=-1)
    return v[:, :, None, :] if d == 2 else v


def _params(inputs: dict) -> np.ndarray:
    return np.array([float(np.asarray(inputs["viscosity"]).reshape(-1)[0]), float(np.asarray(inputs["dt"]).reshape(-1)[0])])


def _finite(name: str, a: np.ndarray) -> None:
    if not np.all(np.isfinite(a)):
        raise ValueError(f"diffsim: {name} holds a value that is not finite")


def _run(inputs: dict) -> tuple[np.ndarray, np.ndarray, diffsim.Operator | None]:
    v0 = np.asarray(inputs["v0"])
    _finite("v0", v0)
    p = _params(inputs)
    _finite("viscosity, dt", p)
    steps = int(inputs["steps"])
    x0 = _pack(v0)
    if steps == 0:
        return x0, p, None
    return x0, p, _operator(tuple(v0.shape), float(inputs["domain_extent"]), steps)


# An unforced flow in a periodic box cannot gain kinetic energy (viscosity
# only removes it); a rollout whose energy more than doubles has gone
# unstable (MacCormack advection without its limiter, at a resolution too
# coarse for the viscosity: docs/mosaic.md), and is refused rather than
# passed on.
_ENERGY_GROWTH_LIMIT = 2.0


def _float32(name: str, a: np.ndarray) -> np.ndarray:
    out = a.astype(np.float32)
    if not np.all(np.isfinite(out)):
        raise RuntimeError(f"diffsim: {name} does not fit in float32 (largest magnitude {np.max(np.abs(a)):.3e})")
    return out


def apply(inputs: InputSchema) -> OutputSchema:
    """``v0`` advanced ``steps`` steps of ``dt``."""
    raw = inputs.model_dump()
    x0, p, op = _run(raw)
    x = x0 if op is None else op.forward(x0, p)
    e0, e = float(np.sum(x0**2)), float(np.sum(x**2))
    if e > _ENERGY_GROWTH_LIMIT * e0:
        raise RuntimeError(
            f"diffsim: the kinetic energy grew {e / e0:.3g}-fold over {raw['steps']} steps of an unforced "
            "periodic flow; the advection is unstable at this resolution and viscosity"
        )
    result = _unpack(x, tuple(np.shape(raw["v0"])))
    return {"result": _float32("result", result), "drag": np.zeros((1,), dtype=np.float32)}


def abstract_eval(abstract_inputs: InputSchema) -> dict:
    """``result`` has ``v0``'s shape; ``drag`` one value."""
    v0 = abstract_inputs.model_dump()["v0"]
    shape = tuple(v0["shape"]) if isinstance(v0, dict) else tuple(np.shape(v0))
    return {"result": {"shape": shape, "dtype": "float32"}, "drag": {"shape": (1,), "dtype": "float32"}}


def vector_jacobian_product(
    inputs: InputSchema,
    vjp_inputs: set[str],
    vjp_outputs: set[str],
    cotangent_vector: dict[str, Any],
) -> dict[str, Any]:
    """The cotangent of ``result`` (``drag`` is constant here) pulled back
    to ``v0``, ``viscosity`` and ``dt``, through the whole rollout."""
    raw = inputs.model_dump()
    shape = tuple(np.shape(raw["v0"]))
    x0, p, op = _run(raw)
    if "result" in vjp_outputs and cotangent_vector.get("result") is not None:
        seed = _pack(np.asarray(cotangent_vector["result"]).reshape(shape))
        _finite("the cotangent of result", seed)
    else:
        seed = np.zeros_like(x0)
    if op is None:
        dx, dp = seed, np.zeros(2)
    else:
        dx, dp = op.vjp(x0, p, seed)
    out: dict[str, Any] = {}
    for name in vjp_inputs:
        if name == "v0":
            out[name] = _float32("the gradient with respect to v0", _unpack(dx, shape))
        elif name == "viscosity":
            out[name] = _float32("the gradient with respect to viscosity", np.array([dp[0]]))
        elif name == "dt":
            out[name] = _float32("the gradient with respect to dt", np.array([dp[1]]))
        elif name == "inflow_profile":
            raise ValueError("diffsim: no inflow profile in this slice")
    return out

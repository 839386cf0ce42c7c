"""diffsim from Python: differentiable physics in Rust, gradients by Enzyme.

Operators take and return NumPy float64 arrays; a leading batch axis runs
its elements in parallel. ``diffsim.jax`` wraps them as JAX functions whose
gradients diffsim computes.

>>> import numpy as np, diffsim
>>> p1 = diffsim.p1_problem(64, 32)
>>> loss = diffsim.p1_loss(64, 32)
>>> value = loss.forward(p1["u0"])            # shape (1,)
>>> du0, _ = loss.vjp(p1["u0"], None, np.ones(1))   # dL/du0, shape (64,)

Errors: ``DiffsimError`` (a ``ValueError``) for inputs diffsim cannot use,
``SimulationError`` (a ``RuntimeError``) for a run that failed,
``InternalError`` for a panic inside diffsim. Long calls release the GIL
and stop at Ctrl-C (``KeyboardInterrupt``).
"""

from __future__ import annotations

import os

import numpy as np

from ._diffsim import (
    DiffsimError,
    InternalError,
    Operator,
    SceneFile,
    SimulationError,
    burgers_step,
    keep_freed_memory,
    navier_stokes_step,
    oscillators,
    p1_loss,
    p1_problem,
    p2_loss,
    p2_problem,
    p4_loss,
    p4_problem,
    smoke_step,
)

__all__ = [
    "DiffsimError",
    "InternalError",
    "Operator",
    "SceneFile",
    "SimulationError",
    "burgers_step",
    "check",
    "keep_freed_memory",
    "navier_stokes_step",
    "oscillators",
    "p1_loss",
    "p1_problem",
    "p2_loss",
    "p2_problem",
    "p4_loss",
    "p4_problem",
    "run_scene",
    "scene_gradient",
    "smoke_step",
]


def run_scene(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Runs the scene file at ``path``; returns its final fields by name."""
    return SceneFile(path).run()


def scene_gradient(path: str | os.PathLike[str]) -> tuple[float, dict[str, np.ndarray]]:
    """The loss of the scene at ``path`` and its gradient with respect to
    every input its ``[loss]`` table names (``with_respect_to``)."""
    return SceneFile(path).gradient()


def check(op: Operator, x: np.ndarray, p: np.ndarray | None = None) -> str:
    """Runs the three gradient checks (finite differences, Taylor remainder,
    dot product) on ``op`` at ``(x, p)`` and returns the report; raises
    ``AssertionError`` with the report when a check fails. A check that
    meets a kink (a fluid at rest puts every traced point on a cell face)
    is inconclusive, not failed: the report says so."""
    verdict, report = op.check(np.asarray(x, dtype=np.float64), None if p is None else np.asarray(p, dtype=np.float64))
    if verdict == "fail":
        raise AssertionError(report)
    return report

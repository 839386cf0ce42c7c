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

Boxes with walls (Mosaic's ``no_slip``; ``neumann`` is diffsim's outflow
side: zero gradient of the velocity across it, zero pressure beyond;
``dirichlet`` a uniform inflow through the side, or a wall when its value
is zero) and an obstacle (a cylinder or a box, cells whose centre lies
inside are solid) run on diffsim's MAC faces directly: the sample at x_i =
i·h (and y_j = j·h) is the face at that position along its own axis.
An ``inflow_profile`` makes x_lo an inflow side whose face speeds are the
profile (x_hi an outflow side when it was periodic: a channel), and its
gradient is the gradient with respect to those speeds. With an obstacle,
``drag`` is Mosaic's surface sum (pressure and ``ν·u_x`` on the fluid
cells beside the obstacle along x), averaged over the last half of the
steps as PhiFlow's Tesseract does; diffsim carries it through the rollout
exactly, the pressure from the projection's velocity change, with its
gradient (``navier_stokes_step(..., drag=True)``, docs/mosaic.md).
"""

from __future__ import annotations

import json
import os
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

# The scheme of the periodic boxes: central differences with RK3 (smooth
# and stable at any horizon, docs/navier-stokes.md), or a traced scheme
# ("maccormack", "semi_lagrangian") for comparison.
SCHEME = os.environ.get("DIFFSIM_MOSAIC_SCHEME", "central")
if SCHEME not in ("central", "maccormack", "semi_lagrangian"):
    raise ValueError(f"DIFFSIM_MOSAIC_SCHEME = {SCHEME!r}: expected central, maccormack or semi_lagrangian")
_FACES = (("x_lo", "x_hi"), ("y_lo", "y_hi"), ("z_lo", "z_hi"))


class InputSchema(make_differentiable(_CanonicalInputSchema, _DIFFERENTIABLE)):
    """The canonical inputs; what diffsim cannot run is refused here."""

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
        if self.steps < 0:
            raise ValueError(f"diffsim: steps = {self.steps}; must be ≥ 0")
        if not self.domain_extent > 0:
            raise ValueError(f"diffsim: domain_extent = {self.domain_extent}; must be positive")
        # The sides, the obstacle and the profile: errors before any work.
        _Box(self.model_dump())
        return self


class OutputSchema(make_differentiable(_CanonicalOutputSchema, ["result", "drag"])):
    """The canonical outputs (``drag`` is zero without an obstacle)."""


def _shape(a: Any) -> tuple[int, ...]:
    """An array's shape, or an abstract one's (``abstract_eval``)."""
    return tuple(a["shape"]) if isinstance(a, dict) else tuple(np.shape(a))


def _dim(shape: tuple[int, ...]) -> int:
    return 2 if shape[2:] == (1, 2) else 3


def _kind(face: Any) -> str:
    t = face["type"] if isinstance(face, dict) else face.type
    return str(getattr(t, "value", t))


class _Box:
    """What a call runs on besides the velocity: the sides as diffsim names
    them, the inflow speeds they fix (with where the profile's go), the
    solid cells, and the key of the operator cache."""

    def __init__(self, raw: dict) -> None:
        shape = _shape(raw["v0"])
        d = _dim(shape)
        n = shape[0]
        self.d, self.n = d, n
        bc = raw.get("boundary_conditions") or {}
        profile = raw.get("inflow_profile")
        sides: list[list[str]] = []
        # Inflow sides in the order of their speeds in the parameters: (axis,
        # side, value per face or None for the profile).
        inflow: list[tuple[int, int, float | None]] = []
        for a in range(d):
            pair = []
            for h, name in enumerate(_FACES[a]):
                face = bc.get(name, {"type": "periodic"})
                kind = _kind(face)
                if kind == "periodic":
                    pair.append("periodic")
                elif kind == "no_slip":
                    pair.append("no_slip")
                elif kind == "neumann":
                    pair.append("outflow")
                elif kind == "dirichlet":
                    value = face.get("value") if isinstance(face, dict) else face.value
                    v = np.zeros(d) if value is None else np.asarray(value, dtype=np.float64)
                    if v.shape != (d,) or not np.all(np.isfinite(v)):
                        raise ValueError(f"diffsim: {name}'s dirichlet value {value!r}: need {d} finite components")
                    tangential = np.delete(v, a)
                    if np.any(tangential != 0.0):
                        raise ValueError(
                            f"diffsim: {name}'s dirichlet value {value!r} moves along the side; "
                            "diffsim's inflow sides set the normal velocity only"
                        )
                    if v[a] == 0.0:
                        pair.append("no_slip")
                    else:
                        pair.append("inflow")
                        inflow.append((a, h, float(v[a]) * (1.0 if h == 0 else -1.0)))
                else:
                    raise ValueError(f"diffsim: {name} has the boundary type {kind!r}")
            sides.append(pair)
        if profile is not None:
            if d != 2:
                raise ValueError("diffsim: an inflow_profile u_x(y) needs a 2-D box")
            if _shape(profile) != (n,):
                raise ValueError(f"diffsim: inflow_profile has shape {_shape(profile)}; expected ({n},), one speed per cell along y")
            if not isinstance(profile, dict) and not np.all(np.isfinite(np.asarray(profile, dtype=np.float64))):
                raise ValueError("diffsim: inflow_profile holds a value that is not finite")
            if sides[0][0] == "inflow":
                inflow = [f for f in inflow if (f[0], f[1]) != (0, 0)]
            sides[0][0] = "inflow"
            if sides[0][1] == "periodic":
                sides[0][1] = "outflow"
            inflow.insert(0, (0, 0, None))
        for a, pair in enumerate(sides):
            if pair.count("periodic") == 1:
                raise ValueError(f"diffsim: {_FACES[a][0]} and {_FACES[a][1]}: a periodic side needs its opposite periodic")
        self.periodic = all(s == "periodic" for pair in sides for s in pair)
        self.sides = sides
        self.inflow = inflow
        obstacle = raw.get("obstacle")
        self.obstacle = obstacle if obstacle and obstacle.get("shape") else None
        self.solid = None if self.obstacle is None else _solid(self.obstacle, d, n)
        if self.solid is not None and self.solid.all():
            raise ValueError("diffsim: the obstacle covers every cell")
        self.length = float(raw["domain_extent"])
        self.key = (shape, self.length, json.dumps(sides), json.dumps(self.obstacle, sort_keys=True, default=str))

    def params(self, raw: dict) -> np.ndarray:
        """``[ν, dt, q…]``: the inflow sides' speeds, the profile's first."""
        p = [float(np.asarray(raw["viscosity"]).reshape(-1)[0]), float(np.asarray(raw["dt"]).reshape(-1)[0])]
        for a, _, value in self.inflow:
            if value is None:
                p.extend(np.asarray(raw["inflow_profile"], dtype=np.float64))
            else:
                p.extend([value] * self.n ** (self.d - 1))
        return np.array(p)


def _solid(obstacle: dict, d: int, n: int) -> np.ndarray:
    """The cells whose centre lies inside the obstacle (x fastest, flat)."""
    centre = np.asarray(obstacle.get("center", [0.5] * d), dtype=np.float64)
    if centre.shape[0] < 2:
        raise ValueError(f"diffsim: obstacle centre {obstacle.get('center')!r}: need at least 2 coordinates")
    if d == 3 and centre.shape[0] == 2:
        centre = np.append(centre, 0.5)
    axes = np.meshgrid(*[(np.arange(n) + 0.5) / n] * d, indexing="ij")
    shape = str(getattr(obstacle["shape"], "value", obstacle["shape"]))
    if shape == "cylinder":
        r = obstacle.get("radius")
        if r is None or not r > 0:
            raise ValueError(f"diffsim: a cylinder obstacle needs a positive radius, got {r!r}")
        inside = (axes[0] - centre[0]) ** 2 + (axes[1] - centre[1]) ** 2 < r**2
    elif shape == "box":
        hw = obstacle.get("half_widths")
        if hw is None or len(hw) < d or not all(w > 0 for w in hw[:d]):
            raise ValueError(f"diffsim: a box obstacle needs {d} positive half_widths, got {hw!r}")
        inside = np.ones_like(axes[0], dtype=bool)
        for a in range(d):
            inside &= np.abs(axes[a] - centre[a]) < hw[a]
    else:
        raise ValueError(f"diffsim: obstacle shape {shape!r}: expected cylinder or box")
    if not inside.any():
        raise ValueError("diffsim: the obstacle covers no cell centre at this resolution")
    return inside.ravel(order="F")


@lru_cache(maxsize=32)
def _centred(shape: tuple[int, ...], length: float, steps: int) -> diffsim.Operator:
    """The rollout of ``steps`` steps on cell-centred values of a periodic box."""
    step = diffsim.navier_stokes_step([shape[0]] * _dim(shape), scheme=SCHEME, length=length, centred=True)
    return step.repeat(steps)


_BOXES: dict[tuple, diffsim.Operator] = {}


def _walled(box: _Box, steps: int) -> diffsim.Operator:
    """The rollout of ``steps`` steps on the faces of a walled box (with the
    drag carried when there is an obstacle)."""
    key = (*box.key, steps)
    if key not in _BOXES:
        if len(_BOXES) > 32:
            _BOXES.clear()
        step = diffsim.navier_stokes_step(
            [box.n] * box.d,
            length=box.length,
            boundary=box.sides,
            solid=None if box.solid is None else box.solid.tolist(),
            drag=box.solid is not None,
        )
        _BOXES[key] = step.repeat(steps)
    return _BOXES[key]


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


def _to_faces(v: np.ndarray, box: _Box) -> np.ndarray:
    """Samples → MAC faces: component ``a``'s face ``i`` along ``a`` is the
    sample ``i``; its last face (``N``) the copy of face 0 on a periodic
    axis, else the last sample (the sides then set it)."""
    d, n = box.d, box.n
    fields = v[:, :, 0, :] if d == 2 else v
    out = []
    for a in range(d):
        f = np.asarray(fields[..., a], dtype=np.float64)
        last = np.take(f, [0 if box.sides[a][0] == "periodic" else n - 1], axis=a)
        out.append(np.concatenate([f, last], axis=a).ravel(order="F"))
    return np.concatenate(out)


def _face_arrays(x: np.ndarray, box: _Box) -> list[np.ndarray]:
    """The packed faces as one array per component (``N + 1`` faces along
    its own axis, ``N`` along the others)."""
    d, n = box.d, box.n
    arrays, at = [], 0
    for a in range(d):
        dims = [n] * d
        dims[a] += 1
        size = int(np.prod(dims))
        arrays.append(x[at : at + size].reshape(dims, order="F"))
        at += size
    return arrays


def _samples(comps: list[np.ndarray], d: int) -> np.ndarray:
    v = np.stack(comps, axis=-1)
    return v[:, :, None, :] if d == 2 else v


def _from_faces(x: np.ndarray, box: _Box) -> np.ndarray:
    """MAC faces → samples (faces 0…N−1 of each component)."""
    return _samples([np.take(f, np.arange(box.n), axis=a) for a, f in enumerate(_face_arrays(x, box))], box.d)


def _from_faces_transpose(g: np.ndarray, box: _Box) -> np.ndarray:
    """The transpose of :func:`_from_faces`: sample cotangents → face
    cotangents (none on a component's last face)."""
    d = box.d
    fields = g[:, :, 0, :] if d == 2 else g
    out = []
    for a in range(d):
        f = np.asarray(fields[..., a], dtype=np.float64)
        pad = [(0, 0)] * d
        pad[a] = (0, 1)
        out.append(np.pad(f, pad).ravel(order="F"))
    return np.concatenate(out)


def _to_faces_transpose(g: np.ndarray, box: _Box) -> np.ndarray:
    """The transpose of :func:`_to_faces`: face cotangents → sample
    cotangents (a component's last face adds to the sample it copied)."""
    d, n = box.d, box.n
    comps = []
    for a, f in enumerate(_face_arrays(g, box)):
        s = np.take(f, np.arange(n), axis=a).copy()
        idx = [slice(None)] * d
        idx[a] = 0 if box.sides[a][0] == "periodic" else n - 1
        s[tuple(idx)] += np.take(f, n, axis=a)
        comps.append(s)
    return _samples(comps, d)


def _finite(name: str, a: np.ndarray) -> None:
    if not np.all(np.isfinite(a)):
        raise ValueError(f"diffsim: {name} holds a value that is not finite")


# An unforced flow in a periodic box cannot gain kinetic energy (viscosity
# only removes it); a rollout whose energy more than doubles has gone
# unstable (MacCormack advection without its limiter, at a resolution too
# coarse for the viscosity: docs/mosaic.md), and is refused rather than
# passed on.
_ENERGY_GROWTH_LIMIT = 2.0


def _float32(name: str, a: np.ndarray) -> np.ndarray:
    out = np.asarray(a).astype(np.float32)
    if not np.all(np.isfinite(out)):
        raise RuntimeError(f"diffsim: {name} does not fit in float32 (largest magnitude {np.max(np.abs(a)):.3e})")
    return out


class _Call:
    """One call's inputs, validated, in diffsim's terms."""

    def __init__(self, raw: dict) -> None:
        self.shape = tuple(np.shape(raw["v0"]))
        v0 = np.asarray(raw["v0"])
        _finite("v0", v0)
        self.box = _Box(raw)
        self.p = self.box.params(raw)
        _finite("viscosity, dt", self.p[:2])
        if self.p[0] < 0 or self.p[1] < 0:
            raise ValueError(f"diffsim: viscosity = {self.p[0]}, dt = {self.p[1]}: must be ≥ 0")
        self.steps = int(raw["steps"])
        self.drag = self.box.solid is not None
        if self.drag and self.steps > 0 and not self.p[1] > 0:
            raise ValueError("diffsim: the drag is a mean force over time: dt must be positive")
        if self.box.periodic and not self.drag:
            self.x0 = _pack(v0)
        else:
            self.x0 = _to_faces(v0, self.box)
            if self.drag:
                self.x0 = np.concatenate([self.x0, [0.0, 0.0]])
        # With the drag: the first steps, then the last half whose mean
        # force is the drag (its sums restarted between the two).
        self.tail = max(1, self.steps // 2) if self.drag else self.steps
        self.head = self.steps - self.tail

    def rollout(self, steps: int) -> diffsim.Operator | None:
        if steps == 0:
            return None
        if self.box.periodic and not self.drag:
            return _centred(self.shape, self.box.length, steps)
        return _walled(self.box, steps)

    def result(self, x: np.ndarray) -> np.ndarray:
        if self.box.periodic and not self.drag:
            return _unpack(x, self.shape)
        return _from_faces(x[: len(x) - (2 if self.drag else 0)], self.box)

    def forward(self) -> tuple[np.ndarray, np.ndarray, float]:
        """The state after the first steps (sums restarted), the final state
        and the drag."""
        head, tail = self.rollout(self.head), self.rollout(self.tail)
        mid = self.x0 if head is None else head.forward(self.x0, self.p)
        if self.drag:
            mid = mid.copy()
            mid[-2:] = 0.0
        x = mid if tail is None else tail.forward(mid, self.p)
        drag = 0.0
        if self.drag and self.steps > 0:
            drag = x[-2] / (self.tail * self.p[1]) - self.p[0] * x[-1] / self.tail
        return mid, x, drag


def apply(inputs: InputSchema) -> OutputSchema:
    """``v0`` advanced ``steps`` steps of ``dt``; the drag on the obstacle."""
    raw = inputs.model_dump()
    call = _Call(raw)
    _, x, drag = call.forward()
    if call.box.periodic and not call.drag:
        e0, e = float(np.sum(call.x0**2)), float(np.sum(x**2))
        if e > _ENERGY_GROWTH_LIMIT * e0:
            raise RuntimeError(
                f"diffsim: the kinetic energy grew {e / e0:.3g}-fold over {raw['steps']} steps of an unforced "
                "periodic flow; the advection is unstable at this resolution and viscosity"
            )
    return {"result": _float32("result", call.result(x)), "drag": _float32("drag", np.array([drag]))}


def abstract_eval(abstract_inputs: InputSchema) -> dict:
    """``result`` has ``v0``'s shape; ``drag`` one value."""
    shape = _shape(abstract_inputs.model_dump()["v0"])
    return {"result": {"shape": shape, "dtype": "float32"}, "drag": {"shape": (1,), "dtype": "float32"}}


def vector_jacobian_product(
    inputs: InputSchema,
    vjp_inputs: set[str],
    vjp_outputs: set[str],
    cotangent_vector: dict[str, Any],
) -> dict[str, Any]:
    """The cotangents of ``result`` and ``drag`` pulled back to ``v0``,
    ``viscosity``, ``dt`` and ``inflow_profile``, through the whole
    rollout."""
    raw = inputs.model_dump()
    call = _Call(raw)
    shape = call.shape
    p = call.p
    dp = np.zeros_like(p)
    seed = np.zeros_like(call.x0)
    if "result" in vjp_outputs and cotangent_vector.get("result") is not None:
        g = np.asarray(cotangent_vector["result"], dtype=np.float64).reshape(shape)
        _finite("the cotangent of result", g)
        if call.box.periodic and not call.drag:
            seed = _pack(g)
        else:
            seed[: len(seed) - (2 if call.drag else 0)] = _from_faces_transpose(g, call.box)
    if call.drag and call.steps > 0 and "drag" in vjp_outputs and cotangent_vector.get("drag") is not None:
        gd = float(np.asarray(cotangent_vector["drag"], dtype=np.float64).reshape(-1)[0])
        _finite("the cotangent of drag", np.array([gd]))
        mid, x, _ = call.forward()
        n, dt, nu = call.tail, p[1], p[0]
        seed[-2] += gd / (n * dt)
        seed[-1] += -nu * gd / n
        dp[0] += -gd * x[-1] / n
        dp[1] += -gd * x[-2] / (n * dt * dt)
    else:
        mid = None
    head, tail = call.rollout(call.head), call.rollout(call.tail)
    g = seed
    if tail is not None:
        if mid is None:
            mid = call.x0 if head is None else head.forward(call.x0, p)
            if call.drag:
                mid = mid.copy()
                mid[-2:] = 0.0
        g, dpt = tail.vjp(mid, p, g)
        dp += dpt
    if call.drag:
        g = g.copy()
        g[-2:] = 0.0
    if head is not None:
        g, dph = head.vjp(call.x0, p, g)
        dp += dph
    out: dict[str, Any] = {}
    for name in vjp_inputs:
        if name == "v0":
            gv = _unpack(g, shape) if call.box.periodic and not call.drag else _to_faces_transpose(g[: len(g) - (2 if call.drag else 0)], call.box)
            out[name] = _float32("the gradient with respect to v0", gv)
        elif name == "viscosity":
            out[name] = _float32("the gradient with respect to viscosity", np.array([dp[0]]))
        elif name == "dt":
            out[name] = _float32("the gradient with respect to dt", np.array([dp[1]]))
        elif name == "inflow_profile":
            if raw.get("inflow_profile") is None:
                raise ValueError("diffsim: no inflow_profile in the inputs")
            out[name] = _float32("the gradient with respect to inflow_profile", dp[2 : 2 + call.box.n])
    return out

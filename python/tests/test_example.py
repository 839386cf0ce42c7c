"""The worked example (examples/sol_jax.py) on a small size: the JAX
network trained through 16 diffsim steps learns, and follows the same
losses as the program written entirely in JAX."""

import importlib.util
import pathlib

import numpy as np


def load():
    path = pathlib.Path(__file__).resolve().parents[1] / "examples" / "sol_jax.py"
    spec = importlib.util.spec_from_file_location("sol_jax", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_example_trains_through_diffsim_as_through_jax():
    sol = load()
    mixed, _ = sol.train("diffsim", 12, batch=4)
    plain, _ = sol.train("jax", 12, batch=4)
    assert mixed[-1] < 0.9 * mixed[0], mixed
    # Same step, same gradients: the same training, to rounding.
    np.testing.assert_allclose(mixed, plain, rtol=1e-9)


def test_a_jax_program_around_the_smoke_solver_matches_the_same_in_jax():
    path = pathlib.Path(__file__).resolve().parents[1] / "examples" / "smoke_jax.py"
    spec = importlib.util.spec_from_file_location("smoke_jax", path)
    smoke = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(smoke)
    (f, theta), (g, _) = smoke.make("diffsim", 16, 4), smoke.make("jax", 16, 4)
    (lv, gv), (lj, gj) = f(theta), g(theta)
    # Both solve the pressure to a relative residual of 1e-8.
    assert abs(lv - lj) <= 1e-9 * abs(lj)
    assert np.linalg.norm(gv - gj) <= 1e-8 * np.linalg.norm(gj)

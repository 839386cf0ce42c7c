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

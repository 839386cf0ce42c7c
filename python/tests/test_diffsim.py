"""diffsim's Python module on NumPy arrays: values and gradients against
independent computations, the three checks, errors as exceptions, the GIL
released and Ctrl-C honoured."""

import os
import signal
import threading
import time

import jax
import numpy as np
import pytest

import diffsim
from conftest import jax_p1_loss


def test_p1_loss_and_gradient_match_plain_jax():
    n, steps = 64, 40
    p1 = diffsim.p1_problem(n, steps)
    assert p1["u0"].shape == (n,) and p1["steps"] == steps
    op = diffsim.p1_loss(n, steps)
    assert (op.n_in, op.n_out, op.n_params) == (n, 1, 0)
    value = op.forward(p1["u0"])
    du0, dp = op.vjp(p1["u0"], None, np.ones(1))
    ref = jax_p1_loss(n, steps)
    ref_value, ref_grad = jax.value_and_grad(ref)(p1["u0"])
    assert value.shape == (1,) and dp.shape == (0,)
    assert abs(value[0] - ref_value) <= 1e-12 * abs(ref_value)
    assert np.linalg.norm(du0 - ref_grad) <= 1e-10 * np.linalg.norm(ref_grad)


def test_a_batch_runs_each_element():
    op = diffsim.burgers_step(32, 0.01, 0.01)
    rng = np.random.default_rng(0)
    x = rng.standard_normal((3, 2, 32))
    y = op.forward(x)
    assert y.shape == (3, 2, 32)
    for i in range(3):
        for j in range(2):
            np.testing.assert_array_equal(y[i, j], op.forward(x[i, j]))
    dy = rng.standard_normal(y.shape)
    dx, dp = op.vjp(x, None, dy)
    assert dx.shape == x.shape and dp.shape == (3, 2, 0)
    # The VJP is the transpose of the JVP: <dy, J tx> = <J^T dy, tx>.
    tx = rng.standard_normal(x.shape)
    _, ty = op.jvp(x, None, tx)
    assert abs(np.sum(dy * ty) - np.sum(dx * tx)) <= 1e-12 * np.sum(np.abs(dy * ty))


def test_the_three_checks_pass_from_python(scenes):
    p1 = diffsim.p1_problem(32, 20)
    report = diffsim.check(diffsim.p1_loss(32, 20), p1["u0"])
    assert report.count("→ pass") == 3, report
    rng = np.random.default_rng(1)
    diffsim.check(diffsim.burgers_step(16, 0.05, 0.01), rng.standard_normal(16))
    smoke = diffsim.SceneFile(scenes / "tests/scenes_moving/moving2d.toml")
    diffsim.check(smoke.loss_operator(), smoke.x0)


def test_the_smoke_benchmarks_losses_pass_the_checks():
    rng = np.random.default_rng(5)
    # P2 (8², 3 steps): from rest every traced point sits on a cell face,
    # a kink the checks say; from a moving state all three pass.
    data, op = diffsim.p2_problem(8, 3), diffsim.p2_loss(8, 3)
    assert op.n_in == data["x0"].size and op.n_out == 1 and data["target"].size == 64
    verdict, report = op.check(data["x0"])
    assert verdict in ("pass", "inconclusive") and "FAIL" not in report, report
    x = data["x0"].copy()
    x[64:] += 0.05 * rng.standard_normal(x.size - 64)
    verdict, report = op.check(x)
    assert verdict == "pass", report
    # P4 (6³, 2 steps) from a moving state: no check fails (the closed
    # box's walls may leave one inconclusive), and the gradient's
    # directional derivative matches central differences of the loss.
    data, op = diffsim.p4_problem(6, 2), diffsim.p4_loss(6, 2)
    x = data["x0"].copy()
    x[216:] += 0.05 * rng.standard_normal(x.size - 216)
    verdict, report = op.check(x)
    assert verdict != "fail", report
    g, _ = op.vjp(x, None, np.ones(1))
    v = rng.standard_normal(x.size)
    # (The pressure solves stop at relative residual 1e-8: the loss is that
    # accurate, which bounds the differences' accuracy.)
    h = 1e-5
    fd = (op.forward(x + h * v)[0] - op.forward(x - h * v)[0]) / (2 * h)
    assert abs(fd - g @ v) <= 1e-5 * abs(g @ v), (fd, g @ v)


def test_scenes_run_and_differentiate(scenes):
    fields = diffsim.run_scene(scenes / "tests/scenes_moving/moving2d.toml")
    assert fields["smoke"].shape == (16, 16) and set(fields) == {"smoke", "velocity_u", "velocity_v"}
    loss, grads = diffsim.scene_gradient(scenes / "tests/scenes_moving/moving2d.toml")
    assert loss > 0 and grads["smoke_init"].shape == (16, 16)
    # The loss operator's VJP at the scene's own state is that gradient.
    scene = diffsim.SceneFile(scenes / "tests/scenes_moving/moving2d.toml")
    op = scene.loss_operator()
    assert abs(op.forward(scene.x0)[0] - loss) <= 1e-12 * loss
    dx0, _ = op.vjp(scene.x0, None, np.ones(1))
    np.testing.assert_allclose(scene.unpack(dx0)["smoke"], grads["smoke_init"], rtol=1e-12, atol=1e-15)


def test_mistakes_are_exceptions_with_diffsim_messages(tmp_path, scenes):
    op = diffsim.burgers_step(16, 0.05, 0.01)
    with pytest.raises(ValueError, match=r"x has shape \[15\]; its last axis must have length 16"):
        op.forward(np.zeros(15))
    with pytest.raises(diffsim.DiffsimError, match="non-finite"):
        op.forward(np.full(16, np.nan))
    with pytest.raises(diffsim.DiffsimError, match="unstable"):
        diffsim.burgers_step(64, 1.0, 0.1)
    # A rollout that blows up is a SimulationError naming where, in every pass.
    loss = diffsim.p1_loss(32, 200)
    huge = np.full(32, 1e200)
    for call in (lambda: loss.forward(huge), lambda: loss.vjp(huge, None, np.ones(1)), lambda: loss.jvp(huge, None, np.ones(32))):
        with pytest.raises(diffsim.SimulationError, match="not finite|non-finite"):
            call()
    bad = tmp_path / "bad.toml"
    bad.write_text('[domain]\nsize = [8, 8]\n[time]\ndt = 0.1\nsteps = 2\n[[effects]]\nkind = "advection"\nschem = "maccormack"\n')
    with pytest.raises(diffsim.DiffsimError, match="did you mean `scheme`"):
        diffsim.SceneFile(bad)
    with pytest.raises(diffsim.DiffsimError, match="cannot read"):
        diffsim.SceneFile(tmp_path / "missing.toml")
    with pytest.raises(diffsim.DiffsimError, match="no \\[loss\\]"):
        diffsim.SceneFile(scenes / "scenes/plume.toml").loss_operator()


def test_a_panic_inside_diffsim_is_an_internal_error():
    op = diffsim._diffsim._panicking_operator()
    x, one = np.zeros(1), np.ones(1)
    calls = {"forward": lambda: op.forward(x), "vjp": lambda: op.vjp(x, None, one), "jvp": lambda: op.jvp(x, None, one), "check": lambda: op.check(x)}
    for name, call in calls.items():
        with pytest.raises(diffsim.InternalError, match=f"diffsim panicked: a deliberate panic in {name}"):
            call()
    # The interpreter goes on.
    assert diffsim.burgers_step(8, 0.01, 0.01).forward(np.ones(8)).shape == (8,)


def test_the_vector_cap_is_read_at_import():
    """DIFFSIM_MAX_ISA caps the vector instructions (same values); a value
    that names none fails the import with a message saying so."""
    import subprocess
    import sys

    code = "import numpy as np, diffsim; print(repr(diffsim.burgers_step(16, 0.01, 0.01).forward(np.sin(np.arange(16.0)))[3]))"
    runs = {}
    for isa in ["baseline", "avx2", None]:
        env = {k: v for k, v in os.environ.items() if k != "DIFFSIM_MAX_ISA"}
        if isa:
            env["DIFFSIM_MAX_ISA"] = isa
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        runs[isa] = out.stdout
    assert runs["baseline"] == runs["avx2"] == runs[None]
    env = dict(os.environ, DIFFSIM_MAX_ISA="sse9")
    out = subprocess.run([sys.executable, "-c", "import diffsim"], env=env, capture_output=True, text=True)
    assert out.returncode != 0 and 'DIFFSIM_MAX_ISA="sse9": expected avx512, avx2 or baseline' in out.stderr, out.stderr


def test_long_calls_release_the_gil_and_stop_at_ctrl_c():
    op = diffsim.p1_loss(2048, 4000)
    u0 = diffsim.p1_problem(2048, 4000)["u0"]
    ticks = []
    stop = threading.Event()

    def count():
        while not stop.is_set():
            ticks.append(1)
            time.sleep(0.001)

    t = threading.Thread(target=count)
    t.start()
    start = time.perf_counter()
    op.forward(u0)
    elapsed = time.perf_counter() - start
    stop.set()
    t.join()
    # The other thread ran while diffsim computed.
    assert len(ticks) > 0.2 * elapsed / 0.001, (len(ticks), elapsed)
    # Ctrl-C in the middle of a gradient: KeyboardInterrupt, promptly.
    # (Python's own handler, as in a terminal: a run in the background of
    # a script starts with SIGINT ignored.)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        timer = threading.Timer(0.3, lambda: os.kill(os.getpid(), signal.SIGINT))
        timer.start()
        start = time.perf_counter()
        with pytest.raises(KeyboardInterrupt):
            for _ in range(100):
                op.vjp(u0, None, np.ones(1))
        assert time.perf_counter() - start < 0.3 + 1.0
    finally:
        signal.signal(signal.SIGINT, previous)


def test_the_periodic_navier_stokes_step_decays_taylor_green_and_passes_the_checks():
    n, nu, dt = 16, 0.05, 0.1
    op = diffsim.navier_stokes_step([n, n])
    h = 2 * np.pi / n
    # The packed MAC velocity: u on the x-faces (i·h, (j+½)·h), v on the
    # y-faces ((i+½)·h, j·h), x fastest, the last face the copy of the first.
    xu, yu = np.meshgrid(np.arange(n + 1) * h, (np.arange(n) + 0.5) * h)
    xv, yv = np.meshgrid((np.arange(n) + 0.5) * h, np.arange(n + 1) * h)
    tg = np.concatenate([(np.sin(xu) * np.cos(yu)).ravel(), (-np.cos(xv) * np.sin(yv)).ravel()])
    assert op.n_in == tg.size == 2 * n * (n + 1) and op.n_params == 2
    y = op.forward(tg, np.array([nu, dt]))
    # The exact solution decays as exp(−2νt); one step at 16² is within 1e-2.
    assert np.max(np.abs(y - tg * np.exp(-2 * nu * dt))) < 1e-2
    # The gradient with respect to the velocity, ν and dt: the three checks,
    # at a state moving through the box (no trace lands on a lattice line).
    x = tg + 0.3
    verdict, report = op.check(x, np.array([nu, dt]))
    assert verdict == "pass", report
    # A negative viscosity is an error, not a result.
    with pytest.raises(diffsim.SimulationError, match="viscosity"):
        op.forward(x, np.array([-1.0, dt]))
    assert diffsim.navier_stokes_step([4, 4, 4]).n_in == 3 * 4 * 4 * 5
    # With a body force f = 2ν·u₀ the vortex holds (Δu₀ = −2u₀).
    forced = diffsim.navier_stokes_step([n, n], forced=True)
    assert forced.n_params == 2 + tg.size
    held = forced.forward(tg, np.concatenate([[nu, dt], 2 * nu * tg]))
    assert np.max(np.abs(held - tg)) < 0.5 * np.max(np.abs(y - tg))
    # On the cell centres: one vector per cell in and out, the same decay.
    centred = diffsim.navier_stokes_step([n, n], centred=True)
    assert centred.n_in == 2 * n * n
    xc, yc = np.meshgrid((np.arange(n) + 0.5) * h, (np.arange(n) + 0.5) * h)
    tgc = np.concatenate([(np.sin(xc) * np.cos(yc)).ravel(), (-np.cos(xc) * np.sin(yc)).ravel()])
    yc1 = centred.forward(tgc, np.array([nu, dt]))
    assert np.max(np.abs(yc1 - tgc * np.exp(-2 * nu * dt))) < 1e-2
    verdict, report = centred.check(tgc + 0.3, np.array([nu, dt]))
    assert verdict == "pass", report
    with pytest.raises(diffsim.DiffsimError, match="2 or 3"):
        diffsim.navier_stokes_step([8])


def test_the_central_navier_stokes_step_decays_taylor_green_and_passes_the_checks():
    n, nu, dt = 16, 0.05, 0.1
    h = 2 * np.pi / n
    xu, yu = np.meshgrid(np.arange(n + 1) * h, (np.arange(n) + 0.5) * h)
    xv, yv = np.meshgrid((np.arange(n) + 0.5) * h, np.arange(n + 1) * h)
    tg = np.concatenate([(np.sin(xu) * np.cos(yu)).ravel(), (-np.cos(xv) * np.sin(yv)).ravel()])
    op = diffsim.navier_stokes_step([n, n], scheme="central")
    y = op.forward(tg, np.array([nu, dt]))
    # Second order in space: one step at 16² within 2e-3 of the exact decay.
    assert np.max(np.abs(y - tg * np.exp(-2 * nu * dt))) < 2e-3
    # A smooth map: the checks pass at the vortex itself (no kinks).
    verdict, report = op.check(tg, np.array([nu, dt]))
    assert verdict == "pass", report
    verdict, report = diffsim.navier_stokes_step([6, 4, 5], scheme="central").check(np.cos(np.arange(3 * 6 * 4 * 5 + 4 * 5 + 6 * 5 + 6 * 4) * 0.37) * 0.3, np.array([nu, dt]))
    assert verdict == "pass", report
    with pytest.raises(diffsim.DiffsimError, match="central"):
        diffsim.navier_stokes_step([8, 8], scheme="central", forced=True)
    with pytest.raises(diffsim.DiffsimError, match="central"):
        diffsim.navier_stokes_step([8, 8], scheme="central", boundary=[["periodic", "periodic"], ["no_slip", "no_slip"]])


def test_the_navier_stokes_step_in_a_channel_keeps_poiseuille_flow_and_checks():
    # A channel 2 × 1: a parabolic inflow on the left (its speeds are the
    # parameters after [ν, dt]), an outflow on the right, no-slip walls.
    nx, ny = 16, 8
    channel = [["inflow", "outflow"], ["no_slip", "no_slip"]]
    op = diffsim.navier_stokes_step([nx, ny], length=2.0, boundary=channel)
    h = 1.0 / ny
    yc = (np.arange(ny) + 0.5) * h
    profile = 4 * yc * (1 - yc)
    assert op.n_params == 2 + ny and op.n_in == (nx + 1) * ny + nx * (ny + 1)
    u = np.tile(profile[:, None], (1, nx + 1)).ravel()
    x = np.concatenate([u, np.zeros(nx * (ny + 1))])
    p = np.concatenate([[0.1, 0.1], profile])
    y = x
    for _ in range(10):
        y = op.forward(y, p)
    # Off by the no-slip walls' discretisation error at 8 cells across.
    assert np.max(np.abs(y - x)) < 0.015
    # The three checks, the inflow speeds among the parameters, with
    # implicit viscosity.
    implicit = diffsim.navier_stokes_step([nx, ny], length=2.0, boundary=channel, viscosity="implicit")
    verdict, report = implicit.check(x + 0.1 * np.cos(0.7 * np.arange(x.size)), p)
    assert verdict == "pass", report
    with pytest.raises(diffsim.DiffsimError, match="no_slip"):
        diffsim.navier_stokes_step([8, 8], boundary=[["periodic", "periodic"], ["wall", "wall"]])
    with pytest.raises(diffsim.DiffsimError, match="outflow"):
        diffsim.navier_stokes_step([8, 8], boundary=[["inflow", "free_slip"], ["no_slip", "no_slip"]])


def test_a_repeated_step_is_one_operator_of_the_initial_state_and_the_parameters():
    """``op.repeat(T)``: the rollout of T steps in one call, its VJP one
    backward pass in Rust; against the steps chained here in Python."""
    n, steps = 12, 6
    op = diffsim.navier_stokes_step([n, n])
    rng = np.random.default_rng(3)
    x0 = 0.3 * rng.standard_normal(op.n_in) + 0.2
    p = np.array([0.05, 0.1])
    rolled = op.repeat(steps)
    assert (rolled.n_in, rolled.n_out, rolled.n_params) == (op.n_in, op.n_out, 2)
    assert rolled.name.endswith(".repeat(6)")
    states = [x0]
    for _ in range(steps):
        states.append(op.forward(states[-1], p))
    y = rolled.forward(x0, p)
    assert np.array_equal(y, states[-1])
    w = rng.standard_normal(op.n_out)
    dx, dp = rolled.vjp(x0, p, w)
    g, gp = w, np.zeros(2)
    for t in reversed(range(steps)):
        g, dpt = op.vjp(states[t], p, g)
        gp += dpt
    assert np.allclose(dx, g, rtol=1e-12, atol=1e-14) and np.allclose(dp, gp, rtol=1e-12)
    # Named checkpointing gives the same numbers; a batch runs element-wise.
    dx2, dp2 = op.repeat(steps, checkpoint="binomial:2").vjp(x0, p, w)
    assert np.array_equal(dx2, dx) and np.array_equal(dp2, dp)
    ys = rolled.forward(np.stack([x0, x0 + 0.01]), p)
    assert ys.shape == (2, op.n_out) and np.array_equal(ys[0], y)
    verdict, report = op.repeat(3).check(x0, p)
    assert verdict == "pass", report
    # On cell-centred values the rollout moves to the faces once: for a
    # smooth field the same as converting at every step, to rounding.
    centred = diffsim.navier_stokes_step([n, n], centred=True)
    i, j = np.meshgrid(np.arange(n), np.arange(n))
    x, yy = 2 * np.pi * (i + 0.5) / n, 2 * np.pi * (j + 0.5) / n
    c0 = np.concatenate([(np.sin(x) * np.cos(yy) + 0.3).ravel(), (-np.cos(x) * np.sin(yy) + 0.2).ravel()])
    chained = c0
    for _ in range(steps):
        chained = centred.forward(chained, p)
    once = centred.repeat(steps).forward(c0, p)
    assert np.max(np.abs(once - chained)) < 1e-3 * np.max(np.abs(chained)), np.max(np.abs(once - chained))
    verdict, report = centred.repeat(3).check(c0, p)
    assert verdict == "pass", report
    # Mistakes are errors that say what.
    with pytest.raises(diffsim.DiffsimError, match="steps = 0"):
        op.repeat(0)
    with pytest.raises(diffsim.DiffsimError, match="unknown checkpointing"):
        op.repeat(3, checkpoint="sometimes")
    with pytest.raises(diffsim.DiffsimError, match="a state to a state"):
        diffsim.p1_loss(16, 4).repeat(2)
    with pytest.raises(diffsim.SimulationError, match="viscosity"):
        rolled.forward(x0, np.array([-1.0, 0.1]))

"""diffsim inside JAX programs: under jit, grad and vmap, against the same
programs written entirely in JAX."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffsim
import diffsim.jax as djax
from conftest import jax_oscillators, jax_p1_loss


def mlp(theta, z):
    """A small JAX network: z (n) -> a correction of u0 (n)."""
    w1, b1, w2 = theta
    return jnp.tanh(z @ w1 + b1) @ w2


def test_a_jax_network_then_diffsim_p1_has_the_gradient_of_all_jax():
    n, steps, width = 32, 30, 8
    p1 = diffsim.p1_problem(n, steps)
    key = jax.random.PRNGKey(0)
    k1, k2, k3 = jax.random.split(key, 3)
    theta = (0.3 * jax.random.normal(k1, (n, width)), 0.1 * jax.random.normal(k2, (width,)), 0.3 * jax.random.normal(k3, (width, n)))
    z = jnp.sin(jnp.arange(n) * 0.7)
    u0 = jnp.asarray(p1["u0"])

    def program(loss):
        def f(theta):
            u = u0 + mlp(theta, z)
            return loss(u) + 0.01 * jnp.sum(u**2)

        return f

    mixed = jax.jit(jax.value_and_grad(program(djax.p1_loss(n, steps))))
    plain = jax.jit(jax.value_and_grad(program(jax_p1_loss(n, steps))))
    (v, g), (rv, rg) = mixed(theta), plain(theta)
    assert abs(v - rv) <= 1e-12 * abs(rv)
    for a, b in zip(g, rg):
        assert jnp.linalg.norm(a - b) <= 1e-10 * jnp.linalg.norm(b), (a, b)


def test_vmap_batches_reach_diffsim_as_one_call():
    n, steps = 16, 10
    loss = djax.p1_loss(n, steps)
    rng = np.random.default_rng(2)
    us = jnp.asarray(rng.standard_normal((5, n)) * 0.5)
    batched = jax.jit(jax.vmap(jax.grad(loss)))(us)
    ref = jax.vmap(jax.grad(jax_p1_loss(n, steps)))(us)
    assert batched.shape == (5, n)
    assert jnp.linalg.norm(batched - ref) <= 1e-10 * jnp.linalg.norm(ref)


def close(a, b, rtol):
    a, b = np.asarray(a), np.asarray(b)
    assert np.linalg.norm(a - b) <= rtol * np.linalg.norm(b), (a, b)


def test_forward_mode_is_diffsims_jvp():
    n, steps = 24, 12
    loss, ref = djax.p1_loss(n, steps), jax_p1_loss(n, steps)
    rng = np.random.default_rng(5)
    u = jnp.asarray(diffsim.p1_problem(n, steps)["u0"])
    t = jnp.asarray(rng.standard_normal(n))
    v, tv = jax.jit(lambda u, t: jax.jvp(loss, (u,), (t,)))(u, t)
    rv, rtv = jax.jvp(ref, (u,), (t,))
    close(v, rv, 1e-12)
    close(tv, rtv, 1e-10)
    # jacfwd (diffsim's JVP, one column per tangent) against jacrev
    # (diffsim's VJP) and against the Jacobian of P1's step in JAX.
    step = djax.burgers_step(12, 0.02, 0.01)
    x = jnp.asarray(1.0 + 0.5 * np.sin(np.arange(12) * 0.5))
    fwd, rev = jax.jit(jax.jacfwd(step))(x), jax.jacrev(step)(x)
    # Reverse mode transposes the JVP's call, never runs it; forward mode
    # runs it, never the VJP.
    grad_text = jax.jit(jax.grad(lambda x: jnp.sum(step(x)))).lower(x).as_text()
    jvp_text = jax.jit(lambda x: jax.jvp(step, (x,), (x,))).lower(x).as_text()
    assert "diffsim_vjp" in grad_text and "diffsim_jvp" not in grad_text
    assert "diffsim_jvp" in jvp_text and "diffsim_vjp" not in jvp_text
    close(fwd, rev, 1e-13)
    assert np.count_nonzero(np.asarray(fwd)) == 3 * 12
    # The same through the callback path, and under vmap.
    via_callback = djax.operator(step.operator, via="callback")
    empty = jnp.zeros((0,))
    close(jax.jacfwd(lambda x: via_callback(x, empty))(x), rev, 1e-13)
    xs = jnp.stack([x, 1.1 * x])
    ts = jnp.asarray(rng.standard_normal((2, 12)))
    ys, tys = jax.vmap(lambda x, t: jax.jvp(step, (x,), (t,)))(xs, ts)
    for k in range(2):
        close(ys[k], step(xs[k]), 1e-15)
        close(tys[k], jax.jacrev(step)(xs[k]) @ ts[k], 1e-12)


@pytest.mark.parametrize("via", ["ffi", "callback"])
def test_parameters_shared_or_batched_have_diffsims_derivatives(via):
    f = djax.operator(diffsim.oscillators("nonlinear"), via)
    ref = jax_oscillators("nonlinear")
    rng = np.random.default_rng(6)
    xs = jnp.asarray(rng.standard_normal((5, 4)) * 0.5)
    u = jnp.asarray(rng.standard_normal(96) * 0.3)
    us = jnp.asarray(rng.standard_normal((5, 96)) * 0.3)
    # Forward, p shared by a batch of states.
    close(jax.jit(f)(xs, u), jax.vmap(ref, (0, None))(xs, u), 1e-13)

    # Reverse mode: a shared p's gradient sums over the batch.
    def loss(g):
        return lambda x, u: jnp.sum(jnp.sin(g(x, u)))

    gx, gu = jax.jit(jax.grad(loss(f), argnums=(0, 1)))(xs, u)
    rx, ru = jax.grad(loss(jax.vmap(ref, (0, None))), argnums=(0, 1))(xs, u)
    close(gx, rx, 1e-11)
    close(gu, ru, 1e-11)
    # p batched by vmap, one gradient per sample.
    per = jax.jit(jax.vmap(jax.grad(loss(f), argnums=(0, 1))))(xs, us)
    ref_per = jax.vmap(jax.grad(loss(ref), argnums=(0, 1)))(xs, us)
    for a, b in zip(per, ref_per):
        close(a, b, 1e-11)
    # Forward mode in the parameters.
    tu = jnp.asarray(rng.standard_normal(96))
    _, ty = jax.jit(lambda u, t: jax.jvp(lambda u: f(xs, u), (u,), (t,)))(u, tu)
    _, rty = jax.jvp(lambda u: jax.vmap(ref, (0, None))(xs, u), (u,), (tu,))
    close(ty, rty, 1e-11)

    # Nested vmaps: controls batched by the inner one only.
    def tangent_in_u(g):
        return lambda x, u, t: jax.jvp(lambda u: g(x, u), (u,), (t,))[1]

    grid = jnp.asarray(rng.standard_normal((3, 5, 4)) * 0.5)
    ts = jnp.asarray(rng.standard_normal((5, 96)))
    nested = jax.vmap(jax.vmap(tangent_in_u(f)), in_axes=(0, None, None))
    ref_nested = jax.vmap(jax.vmap(tangent_in_u(ref)), in_axes=(0, None, None))
    close(jax.jit(nested)(grid, us, ts), ref_nested(grid, us, ts), 1e-11)
    gnested = jax.vmap(jax.vmap(jax.grad(loss(f), argnums=1)), in_axes=(0, None))
    ref_gnested = jax.vmap(jax.vmap(jax.grad(loss(ref), argnums=1)), in_axes=(0, None))
    close(jax.jit(gnested)(grid, us), ref_gnested(grid, us), 1e-11)


def test_a_jax_network_acts_between_smoke_steps():
    n = 8
    step = djax.smoke_step(n)
    op = step.operator
    rng = np.random.default_rng(3)
    x0 = rng.random(op.n_in) * 0.1

    def rollout(scale):
        x = jnp.asarray(x0)
        for _ in range(3):
            x = step(x) * scale
        return jnp.sum(x**2)

    value, grad = jax.value_and_grad(rollout)(1.1)
    # Against central differences of the same program.
    h = 1e-6
    fd = (rollout(1.1 + h) - rollout(1.1 - h)) / (2 * h)
    assert abs(grad - fd) <= 1e-6 * abs(fd), (grad, fd)
    assert value > 0


def test_scene_loss_is_a_jax_function_of_the_initial_state(scenes):
    loss = djax.scene_loss(scenes / "tests/scenes_moving/moving2d.toml")
    g = jax.jit(jax.grad(loss))(loss.x0)
    value, grads = loss.scene.gradient()
    assert abs(loss(loss.x0) - value) <= 1e-12 * value
    np.testing.assert_allclose(np.asarray(loss.scene.unpack(np.asarray(g))["smoke"]), grads["smoke_init"], rtol=1e-12, atol=1e-15)


def test_the_ffi_and_the_callback_give_the_same_values_and_gradients():
    op = diffsim.burgers_step(24, 0.02, 0.01)
    via_ffi, via_callback = djax.operator(op), djax.operator(op, via="callback")
    rng = np.random.default_rng(4)
    x = jnp.asarray(rng.standard_normal((3, 24)))
    empty = jnp.zeros((0,))
    a = jax.jit(via_ffi)(x, empty)
    b = jax.jit(via_callback)(x, empty)
    np.testing.assert_array_equal(np.asarray(a), op.forward(np.asarray(x)))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    ga = jax.grad(lambda x: jnp.sum(via_ffi(x, empty) ** 2))(x)
    gb = jax.grad(lambda x: jnp.sum(via_callback(x, empty) ** 2))(x)
    np.testing.assert_array_equal(np.asarray(ga), np.asarray(gb))


def test_mistakes_inside_jax_are_diffsim_errors():
    step = djax.burgers_step(16, 0.05, 0.01)
    with pytest.raises(diffsim.DiffsimError, match="last axis must have length 16"):
        jax.jit(step)(jnp.zeros(15))
    # A non-finite state is refused at run time, naming it.
    with pytest.raises(Exception, match="x holds a non-finite value"):
        jax.block_until_ready(jax.jit(step)(jnp.full(16, jnp.nan)))
    # So is a non-finite tangent or cotangent.
    with pytest.raises(Exception, match="tx holds a non-finite value"):
        jax.block_until_ready(jax.jit(lambda t: jax.jvp(step, (jnp.ones(16),), (t,))[1])(jnp.full(16, jnp.inf)))
    with pytest.raises(Exception, match="dy holds a non-finite value"):
        jax.block_until_ready(jax.jit(lambda c: jax.vjp(step, jnp.ones(16))[1](c)[0])(jnp.full(16, jnp.nan)))


def test_a_panic_inside_diffsim_is_an_error_in_jax_too():
    f = djax.operator(diffsim._diffsim._panicking_operator())
    x, empty = jnp.zeros(1), jnp.zeros((0,))
    with pytest.raises(Exception, match="diffsim panicked: a deliberate panic in forward"):
        jax.block_until_ready(jax.jit(f)(x, empty))
    # (The gradient and the tangent alone: XLA drops the unused forward.)
    with pytest.raises(Exception, match="diffsim panicked: a deliberate panic in vjp"):
        jax.block_until_ready(jax.jit(jax.grad(lambda x: jnp.sum(f(x, empty))))(x))
    with pytest.raises(Exception, match="diffsim panicked: a deliberate panic in jvp"):
        jax.block_until_ready(jax.jit(lambda x: jax.jvp(lambda x: f(x, empty), (x,), (x,))[1])(x))
    # The process goes on.
    step = djax.burgers_step(8, 0.01, 0.01)
    assert jax.jit(step)(jnp.ones(8)).shape == (8,)

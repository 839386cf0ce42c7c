"""diffsim operators inside JAX programs.

``operator(op)`` turns a :class:`diffsim.Operator` into a JAX function
``(x, p) -> y`` whose derivatives diffsim computes: the forward, the JVP and
the VJP are called from compiled JAX code through XLA's FFI
(``jax.ffi.ffi_call`` into the custom-call targets ``diffsim_forward``,
``diffsim_jvp`` and ``diffsim_vjp``, with XLA's buffers: no Python and no
copies in between). ``operator(op, via="callback")`` uses
``jax.pure_callback`` instead (host callbacks on NumPy arrays).

The function has a custom JVP whose tangent part is a JAX primitive of its
own: diffsim's JVP, declared linear in the tangents, with diffsim's VJP as
its transpose. So ``jax.jvp`` and ``jax.jacfwd`` run diffsim's forward
mode, ``jax.grad``, ``jax.vjp`` and ``jax.jacrev`` its reverse mode (JAX
transposes the tangent; the JVP is never evaluated then), and both work
under ``jax.jit`` and ``jax.vmap`` (``vmap_method="broadcast_all"``: a
batch reaches diffsim as a leading axis and runs in parallel there).
``jax.jvp`` costs one forward and one JVP call (the JVP computes the value
again: JAX needs the value from a call it does not have to transpose).
First derivatives only.

Needs ``jax`` with float64 enabled (``jax.config.update("jax_enable_x64",
True)``; this module turns it on when imported).
"""

from __future__ import annotations

import ctypes
import os
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from . import _diffsim

jax.config.update("jax_enable_x64", True)

# The FFI targets, registered once per process.
_HANDLER = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p)
_TARGETS = [_HANDLER(address) for _, address in _diffsim.ffi_targets()]
for (_name, _), _fn in zip(_diffsim.ffi_targets(), _TARGETS):
    jax.ffi.register_ffi_target(_name, jax.ffi.pycapsule(_fn), platform="cpu")

__all__ = ["operator", "p1_loss", "scene_loss", "smoke_step", "burgers_step"]


def _batched_p(x: np.ndarray, p: np.ndarray, n_params: int) -> np.ndarray:
    """``p`` broadcast to ``x``'s batch axes (``[..., n_params]``)."""
    batch = x.shape[:-1]
    if p.ndim == 1:
        return np.broadcast_to(p, batch + (n_params,))
    # p batched by vmap over the leading axes: extend to x's native batch axes.
    extra = len(batch) - (p.ndim - 1)
    return np.broadcast_to(p.reshape(p.shape[:-1] + (1,) * extra + p.shape[-1:]), batch + (n_params,))


def _linear_primitive(name: str, jvp: Callable, vjp: Callable, n_out: int) -> Primitive:
    """A JAX primitive ``t(x, p, tx, tp) = jvp(x, p, tx, tp)``, linear in
    the tangents ``(tx, tp)``, whose transpose is ``vjp(x, p, ct) -> (dx,
    dp)``: the tangent part of an operator's JVP rule. Forward mode
    evaluates it; reverse mode transposes it (``jvp`` is never called
    then). Under ``vmap`` it binds itself again on the batch-first layout
    diffsim takes, so that a batched tangent stays transposable. First
    derivatives only: it has no JVP of its own."""
    prim = Primitive(name)
    prim.def_impl(jvp)
    prim.def_abstract_eval(lambda x, p, tx, tp: jax.core.ShapedArray(x.shape[:-1] + (n_out,), jnp.float64))
    mlir.register_lowering(prim, mlir.lower_fun(jvp, multiple_results=False))

    def batch(args, dims):
        # The batch axis first on x and tx (broadcast where absent), and on
        # p and tp when either is batched here or was by an inner vmap
        # (diffsim reads a batched p's blocks along x's leading axes); a p
        # shared so far stays shared.
        size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)

        def front(a, d):
            return jnp.moveaxis(a, d, 0) if d is not None else jnp.broadcast_to(a, (size,) + a.shape)

        x, p, tx, tp = args
        x, tx = front(x, dims[0]), front(tx, dims[2])
        if dims[1] is not None or dims[3] is not None or p.ndim > 1:
            p, tp = front(p, dims[1]), front(tp, dims[3])
        return prim.bind(x, p, tx, tp), 0

    def transpose(ct, x, p, tx, tp):
        if ad.is_undefined_primal(x) or ad.is_undefined_primal(p):
            raise NotImplementedError("diffsim's JVP is linear in the tangents only")
        dx, dp = vjp(x, p, ad.instantiate_zeros(ct))
        return None, None, dx if ad.is_undefined_primal(tx) else None, dp if ad.is_undefined_primal(tp) else None

    batching.primitive_batchers[prim] = batch
    ad.primitive_transposes[prim] = transpose
    return prim


def operator(op: _diffsim.Operator, via: str = "ffi") -> Callable[[jax.Array, jax.Array], jax.Array]:
    """``op`` as a JAX function ``f(x, p) -> y`` (``y``: ``x``'s batch axes
    and ``n_out``) whose JVP and VJP are diffsim's. ``p`` has ``op.n_params`` values
    (an empty array when there are none). ``via``: ``"ffi"`` (XLA's FFI,
    the default) or ``"callback"`` (``jax.pure_callback``)."""
    n_in, n_out, n_params = op.n_in, op.n_out, op.n_params
    if n_in == 0:
        raise _diffsim.DiffsimError("an operator without inputs cannot be a JAX function of x")
    if via not in ("ffi", "callback"):
        raise _diffsim.DiffsimError(f"via must be 'ffi' or 'callback', got {via!r}")

    def check(x, p):
        # Shapes are known when JAX traces: refuse mistakes here, in words.
        if x.ndim < 1 or x.shape[-1] != n_in:
            raise _diffsim.DiffsimError(f"x has shape {tuple(x.shape)}; its last axis must have length {n_in}")
        if p.ndim != 1 or p.shape[0] != n_params:
            raise _diffsim.DiffsimError(f"p has shape {tuple(p.shape)}; this operator has {n_params} parameters")

    def y_shape(x):
        return jax.ShapeDtypeStruct(x.shape[:-1] + (n_out,), jnp.float64)

    def grad_shapes(x):
        return (jax.ShapeDtypeStruct(x.shape, jnp.float64), jax.ShapeDtypeStruct(x.shape[:-1] + (n_params,), jnp.float64))

    if via == "ffi":
        op_id = np.int64(op.ffi_id())

        def call_forward(x, p):
            return jax.ffi.ffi_call("diffsim_forward", y_shape(x), vmap_method="broadcast_all")(x, p, op_id=op_id)

        def call_jvp(x, p, tx, tp):
            return jax.ffi.ffi_call("diffsim_jvp", y_shape(x), vmap_method="broadcast_all")(x, p, tx, tp, op_id=op_id)

        def call_vjp(x, p, dy):
            return jax.ffi.ffi_call("diffsim_vjp", grad_shapes(x), vmap_method="broadcast_all")(x, p, dy, op_id=op_id)

    else:

        def params(x, p):
            # No parameters: nothing to pass (the common case, and the fastest).
            return None if n_params == 0 else np.ascontiguousarray(_batched_p(x, np.asarray(p, dtype=np.float64), n_params))

        def forward_host(x, p):
            x = np.asarray(x, dtype=np.float64)
            return op.forward(x, params(x, p))

        def jvp_host(x, p, tx, tp):
            x = np.asarray(x, dtype=np.float64)
            return op.jvp(x, params(x, p), np.asarray(tx, dtype=np.float64), params(x, tp))[1]

        def vjp_host(x, p, dy):
            x = np.asarray(x, dtype=np.float64)
            return op.vjp(x, params(x, p), np.asarray(dy, dtype=np.float64))

        def call_forward(x, p):
            return jax.pure_callback(forward_host, y_shape(x), x, p, vmap_method="broadcast_all")

        def call_jvp(x, p, tx, tp):
            return jax.pure_callback(jvp_host, y_shape(x), x, p, tx, tp, vmap_method="broadcast_all")

        def call_vjp(x, p, dy):
            return jax.pure_callback(vjp_host, grad_shapes(x), x, p, dy, vmap_method="broadcast_all")

    def cotangent(x, p, dy):
        """``(J_xᵀ·dy, J_pᵀ·dy)``, shaped as ``x`` and ``p``."""
        dx, dp = call_vjp(x, p, dy)
        # p shared by some of x's batch axes (all of them for p of shape
        # [n_params]): its gradient is the sum over those.
        return dx, dp.sum(axis=tuple(range(p.ndim - 1, dp.ndim - 1)))

    tangent = _linear_primitive(f"diffsim_jvp[{op.name}]", call_jvp, cotangent, n_out)

    def as_f64(x, p):
        return jnp.asarray(x, jnp.float64), jnp.asarray(p, jnp.float64)

    @jax.custom_jvp
    def f(x, p):
        check(x, p)
        return call_forward(*as_f64(x, p))

    @f.defjvp
    def f_jvp(primals, tangents):
        x, p = as_f64(*primals)
        check(x, p)
        t = as_f64(*tangents)
        return call_forward(x, p), tangent.bind(x, p, *t)

    f.__doc__ = f"{op!r} as a JAX function (x, p) -> y."
    return f


def _of_x(op: _diffsim.Operator, squeeze: bool, via: str = "ffi") -> Callable[[jax.Array], jax.Array]:
    f = operator(op, via)
    empty = jnp.zeros((0,), dtype=jnp.float64)

    def g(x):
        y = f(x, empty)
        return y[..., 0] if squeeze else y

    g.operator = op
    return g


def p1_loss(n: int, steps: int) -> Callable[[jax.Array], jax.Array]:
    """P1 (``docs/benchmarks.md``): ``u0 -> L`` for ``u0`` of ``n``
    cells, ``steps`` steps of viscous Burgers, ``L = ½·dx·Σ (u_T − u*)²``;
    forward and gradient by diffsim. ``u0`` may have batch axes."""
    return _of_x(_diffsim.p1_loss(n, steps), squeeze=True)


def scene_loss(path: str | os.PathLike[str]) -> Callable[[jax.Array], jax.Array]:
    """The loss of the scene file at ``path`` (its ``[loss]`` table) as a
    function of its packed initial state; ``.x0`` is the scene's own
    initial state and ``.scene`` the :class:`diffsim.SceneFile`."""
    scene = _diffsim.SceneFile(path)
    g = _of_x(scene.loss_operator(), squeeze=True)
    g.x0 = jnp.asarray(scene.x0)
    g.scene = scene
    return g


def smoke_step(n: int) -> Callable[[jax.Array], jax.Array]:
    """One step of P2's 2D smoke solver on ``n × n`` cells: packed state in,
    packed state out (``n·n`` smoke values, then the face velocities)."""
    return _of_x(_diffsim.smoke_step(n), squeeze=False)


def burgers_step(n: int, dt: float, nu: float, length: float = 2 * np.pi) -> Callable[[jax.Array], jax.Array]:
    """One step of P1's Burgers scheme: ``u -> u_next``."""
    return _of_x(_diffsim.burgers_step(n, dt, nu, length), squeeze=False)

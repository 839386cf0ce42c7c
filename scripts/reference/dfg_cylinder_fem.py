"""An independent reference for the Schäfer–Turek "flow around a cylinder"
benchmark (cases 2D-1 and 2D-2): Taylor–Hood P2/P1 finite elements on a
body-fitted triangulation, written apart from diffsim's solver so that the
two share nothing but the problem's definition.

- Mesh: Shewchuk's Triangle (the `triangle` package) on the channel minus a
  polygon of `--segments` sides inscribed in the cylinder (the polygon's
  area error is O(1/segments²)), graded from `h` at the body to 8h far away.
- Discretisation: P2 velocity, P1 pressure (inf-sup stable), the Laplacian
  form of the viscous term, so the natural condition at the outlet is the
  benchmark's "do-nothing" condition ν ∂u/∂n − p n = 0.
- 2D-1: Newton's method on the steady equations. 2D-2 (`--scheme`): BDF2
  with the advecting velocity extrapolated (2uⁿ − uⁿ⁻¹), one linear solve
  per step, or Crank–Nicolson with the convection implicit, by Newton's
  method; from rest with the inflow ramped up over the first time unit,
  or from a saved state (`--load-state`, interpolated from its own mesh
  when that differs, so a finer mesh starts on the limit cycle).
- `--length` changes the channel's length (the outlet's place; the
  benchmark's is 2.2).
- Forces: the volume (weak-residual) form of John & Matthies: c = −20 ·
  R(u, p; v) with v a finite-element function equal to the unit vector on
  the body and zero on every other node; superconvergent, and free of any
  derivative evaluated on the boundary.

Reproduce (docs/cylinder.md, "An independent reference"; `dfg-fem` beside
this file makes the virtual environment with the pinned packages):

    scripts/reference/dfg-fem --case 2d-1 --h 0.005
    scripts/reference/dfg-fem --case 2d-2 --h 0.0075 --dt 0.0025 --save-state s.npz
    scripts/reference/dfg-fem --case 2d-2 --h 0.0075 --scheme cn --load-state s.npz --t-end 11 --t-measure 10

Prints one JSON line with the same keys as `diffsim experiment cylinder`.
"""

import argparse
import json
import sys
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import triangle
from skfem import Basis, BilinearForm, ElementTriP1, ElementTriP2, ElementVector, MeshTri, asm
from skfem.helpers import dot, grad, div, ddot

LENGTH, HEIGHT = 2.2, 0.41
CENTER, RADIUS = (0.2, 0.2), 0.05
NU = 1e-3
P_FRONT, P_BACK = (0.15, 0.2), (0.25, 0.2)


def build_mesh(h, segments, length=LENGTH):
    """The channel of `length` minus the cylinder's inscribed polygon,
    graded from `h` at the body to `8h` (and `2h` in the near wake)."""
    theta = 2 * np.pi * np.arange(segments) / segments
    circle = np.c_[CENTER[0] + RADIUS * np.cos(theta), CENTER[1] + RADIUS * np.sin(theta)]
    corners = np.array([[0, 0], [length, 0], [length, HEIGHT], [0, HEIGHT]], dtype=float)
    vertices = np.vstack([corners, circle])
    seg_box = [[i, (i + 1) % 4] for i in range(4)]
    seg_circle = [[4 + i, 4 + (i + 1) % segments] for i in range(segments)]
    pslg = dict(vertices=vertices, segments=np.array(seg_box + seg_circle), holes=np.array([CENTER]))

    def size(x, y):
        d = np.hypot(x - CENTER[0], y - CENTER[1]) - RADIUS
        s = np.minimum(8 * h, h + 0.25 * np.maximum(d, 0))
        wake = (x > CENTER[0]) & (x < 1.2) & (np.abs(y - CENTER[1]) < 0.12)
        return np.where(wake, np.minimum(s, 2 * h), s)

    mesh = triangle.triangulate(pslg, f"pq30a{(8 * h) ** 2 * 0.433:.3e}")
    for _ in range(12):
        p, t = mesh["vertices"], mesh["triangles"]
        c = p[t].mean(axis=1)
        target = 0.433 * size(c[:, 0], c[:, 1]) ** 2
        e1, e2 = p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]
        area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        if np.all(area <= 1.2 * target):
            break
        mesh = triangle.triangulate(dict(mesh, triangle_max_area=target), "rpq30a")
    return MeshTri(mesh["vertices"].T.copy(), mesh["triangles"].T.copy())


@BilinearForm
def viscous(u, v, w):
    return NU * ddot(grad(u), grad(v))


@BilinearForm
def mass(u, v, w):
    return dot(u, v)


@BilinearForm
def divergence_form(u, q, w):
    return div(u) * q


@BilinearForm
def convection(u, v, w):
    # ((a·∇)u, v) with a the advecting velocity w.a.
    conv = np.einsum("ij...,j...->i...", grad(u), w["a"])
    return dot(conv, v)


@BilinearForm
def convection_jacobian(u, v, w):
    # Newton's second term ((u·∇)a, v).
    conv = np.einsum("ij...,j...->i...", grad(w["a"]), u)
    return dot(conv, v)


class Problem:
    def __init__(self, h, segments, umax, length=LENGTH):
        self.mesh = build_mesh(h, segments, length)
        self.vb = Basis(self.mesh, ElementVector(ElementTriP2()), intorder=4)
        self.pb = Basis(self.mesh, ElementTriP1(), intorder=4)
        self.nu_, self.np_ = self.vb.N, self.pb.N
        self.umax = umax
        x = self.vb.doflocs
        ix, iy = self.vb.split_indices()
        # Boundary DOFs: every velocity DOF on the boundary except the outlet.
        facets = self.mesh.boundary_facets()
        mid = self.mesh.p[:, self.mesh.facets[:, facets]].mean(axis=1)
        self.body_facets = facets[np.hypot(mid[0] - CENTER[0], mid[1] - CENTER[1]) < 2 * RADIUS]
        dirichlet_facets = facets[mid[0] < length - 1e-9]
        self.dirichlet = self.vb.get_dofs(dirichlet_facets).all()
        self.body = self.vb.get_dofs(self.body_facets).all()
        inlet = np.zeros(self.nu_)
        at_inlet = ix[x[0, ix] < 1e-9]
        inlet[at_inlet] = 4 * umax * x[1, at_inlet] * (HEIGHT - x[1, at_inlet]) / HEIGHT**2
        self.inflow = inlet
        self.M = asm(mass, self.vb)
        self.K = asm(viscous, self.vb)
        self.B = asm(divergence_form, self.vb, self.pb)  # np × nu
        self.free = np.setdiff1d(np.arange(self.nu_ + self.np_), self.dirichlet)
        # Test functions for drag and lift: the unit vectors on the body's nodes.
        self.vd, self.vl = np.zeros(self.nu_), np.zeros(self.nu_)
        self.vd[np.intersect1d(self.body, ix)] = 1.0
        self.vl[np.intersect1d(self.body, iy)] = 1.0
        self.probe = self.pb.probes(np.array([P_FRONT, P_BACK]).T)

    def conv_matrix(self, a, form=convection):
        return asm(form, self.vb, a=self.vb.interpolate(a))

    def solve(self, A, rhs, x_bc):
        """Solves the saddle system [[A, −Bᵀ], [−B, 0]] with the Dirichlet
        values of `x_bc` (velocity part) imposed."""
        n = self.nu_
        S = sp.bmat([[A, -self.B.T], [-self.B, None]], format="csc")
        x = np.zeros(n + self.np_)
        x[:n] = x_bc
        b = np.concatenate([rhs, np.zeros(self.np_)]) - S @ x
        f = self.free
        x[f] = spla.splu(S[f][:, f].tocsc(), permc_spec="COLAMD").solve(b[f])
        return x[:n], x[n:]

    def spatial(self, u):
        """The viscous and convective terms K u + C(u) u."""
        return self.K @ u + self.conv_matrix(u) @ u

    def coefficients(self, spatial, p, dudt):
        """c_D and c_L from the weak residual tested with the body's unit
        vectors (2/(Ū² D) = 20 for Ū = 2/3·umax, D = 0.1, scaled to Ū);
        `spatial` is `self.spatial` of the state (for Crank–Nicolson, the
        mean over the step's two ends)."""
        ubar = 2.0 * self.umax / 3.0
        scale = 2.0 / (ubar**2 * 2 * RADIUS)
        r = self.M @ dudt + spatial - self.B.T @ p
        return -scale * (self.vd @ r), -scale * (self.vl @ r)

    def dp(self, p):
        v = self.probe @ p
        return v[0] - v[1]


def steady(prob):
    u, p = prob.solve(prob.K, np.zeros(prob.nu_), prob.inflow)  # Stokes start
    for it in range(30):
        # Newton: (K + C(u) + C'(u)) u_new = C'(u) u, as (u·∇)u = C'(u) u.
        jac = prob.conv_matrix(u, convection_jacobian)
        u_new, p = prob.solve(prob.K + prob.conv_matrix(u) + jac, jac @ u, prob.inflow)
        step = np.linalg.norm(u_new - u) / np.linalg.norm(u_new)
        u = u_new
        if step < 1e-11:
            break
    return u, p, it + 1


def periodic(prob, dt, t_end, t_measure, state=None, scheme="bdf2"):
    """Time steps from rest (or from `state` = (t, u, u_old) on this mesh,
    as `load_state` gives it); returns the rows (t, c_D, c_L, Δp) from `t_measure` on, the
    step count and the final state.

    - "bdf2": BDF2 with the advecting velocity extrapolated (2uⁿ − uⁿ⁻¹),
      one linear solve per step; the first step (and the first after a
      restart) is backward Euler.
    - "cn": Crank–Nicolson with the convection fully implicit, solved by
      Newton's method to a relative change below 1e-6 (two linear solves a
      step; converging quadratically, a third would move it by about
      1e-14); the pressure and the forces belong to the half step t − Δt/2,
      where the scheme is second order. Neither damps (BDF2 does) nor lags
      (the extrapolation does)."""
    n = prob.nu_
    t, u, u_old = (0.0, np.zeros(n), np.zeros(n)) if state is None else state
    rows = []
    steps = 0
    s_u = prob.spatial(u) if scheme == "cn" else None  # carried from step to step
    while t < t_end - 1e-12:
        t += dt
        steps += 1
        bc = min(1.0, t) * prob.inflow
        if scheme == "cn":
            # The first step from rest guesses u itself (no history yet).
            u_new, p = cn_step(prob, dt, u, s_u, u_old if steps > 1 or state else u, bc)
            s_new = prob.spatial(u_new)
            dudt, at, spatial = (u_new - u) / dt, t - 0.5 * dt, 0.5 * (s_u + s_new)
            s_u = s_new
        else:
            if steps > 1:  # BDF2, the advecting velocity extrapolated
                a, c_new, hist = 2 * u - u_old, 1.5 / dt, (4 * u - u_old) / (2 * dt)
            else:  # backward Euler
                a, c_new, hist = u, 1.0 / dt, u / dt
            A = c_new * prob.M + prob.K + prob.conv_matrix(a)
            u_new, p = prob.solve(A, prob.M @ hist, bc)
            dudt, at, spatial = c_new * u_new - hist, t, None
        u_old, u = u, u_new
        if at >= t_measure - 1e-12:
            cd, cl = prob.coefficients(prob.spatial(u) if spatial is None else spatial, p, dudt)
            rows.append((at, cd, cl, prob.dp(p)))
        if steps % 200 == 0:
            print(f"t = {t:.3f}", file=sys.stderr, flush=True)
    return np.array(rows), steps, (t, u, u_old)


def cn_step(prob, dt, u, s_u, u_prev, bc):
    """One Crank–Nicolson step: M(u' − u)/Δt + ½(K + C(u'))u' + ½(K + C(u))u
    − Bᵀq = 0, B u' = 0, by Newton from the extrapolation 2u − u_prev
    (C(w)w is quadratic, so C(w)w ≈ (C(g) + C'(g))w − C'(g)g about g).
    `s_u` is `prob.spatial(u)`. Returns u' and the half-step pressure q."""
    explicit = prob.M @ u / dt - 0.5 * s_u
    guess = 2 * u - u_prev
    for _ in range(20):
        jac = prob.conv_matrix(guess, convection_jacobian)
        A = prob.M / dt + 0.5 * (prob.K + prob.conv_matrix(guess) + jac)
        u_new, p = prob.solve(A, explicit + 0.5 * (jac @ guess), bc)
        change = np.linalg.norm(u_new - guess) / max(np.linalg.norm(u_new), 1e-300)
        guess = u_new
        if change < 1e-6:  # quadratic: the next iterate would move by ~1e-14
            break
    else:
        sys.exit("Crank–Nicolson: Newton did not converge in 20 iterations; lower --dt")
    return u_new, p


def load_state(prob, path):
    """A state saved by `--save-state`: as it is on the same mesh, else
    interpolated from the mesh saved with it onto this one (both velocities
    become the interpolant; the first Crank–Nicolson step projects it onto
    this mesh's divergence-free fields). Points of this mesh that fall just
    outside the other's, between the two inscribed polygons, are read 10⁻⁴
    off the body, where the velocity is within 10⁻³ of the wall's zero."""
    z = np.load(path)
    t, u, u_old = float(z["t"]), z["u"], z["u_old"]
    same = "mesh_p" not in z or (z["mesh_p"].shape == prob.mesh.p.shape and np.array_equal(z["mesh_p"], prob.mesh.p))
    if same:
        if u.size != prob.nu_:
            sys.exit(f"{path}: a state of {u.size} velocity unknowns without its mesh cannot start a mesh of {prob.nu_}")
        return t, u, u_old
    source = Basis(MeshTri(z["mesh_p"], z["mesh_t"]), ElementVector(ElementTriP2()), intorder=4)
    x = prob.vb.doflocs.copy()
    off = np.hypot(x[0] - CENTER[0], x[1] - CENTER[1])
    near = off < RADIUS + 1e-4
    for k in range(2):
        x[k, near] = CENTER[k] + (x[k, near] - CENTER[k]) * (RADIUS + 1e-4) / off[near]
    ix, iy = prob.vb.split_indices()
    v = np.zeros(prob.nu_)
    v[ix] = (source.probes(x[:, ix]) @ u)[: ix.size]
    v[iy] = (source.probes(x[:, iy]) @ u)[iy.size :]
    v[prob.body] = 0.0
    return t, v, v


def measures(series):
    """Extrema of c_D and c_L over the recorded window (refined by a parabola
    through three samples), St from the period between the lift's first and
    last upward crossings of its sample mean, the lift's mean over those
    whole periods, and Δp half a period after the lift's last maximum."""
    t, cd, cl, dpv = series.T
    s = cl - cl.mean()
    ups = [t[i] - s[i] * (t[i + 1] - t[i]) / (s[i + 1] - s[i]) for i in range(len(t) - 1) if s[i] < 0 <= s[i + 1]]
    if len(ups) < 2:
        sys.exit(f"the window t = {t[0]:.3f}..{t[-1]:.3f} holds less than one period of the lift: lengthen --t-end or lower --t-measure")
    period = (ups[-1] - ups[0]) / (len(ups) - 1)
    grid = np.linspace(ups[0], ups[-1], 20001)
    mean = np.trapezoid(np.interp(grid, t, cl), grid) / (ups[-1] - ups[0])

    def peak(y, i):
        a, b, c = y[i - 1], y[i], y[i + 1]
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den != 0 else 0.0
        return b - 0.25 * (a - c) * off, t[i] + off * (t[i + 1] - t[i])

    def extreme(y, sign):
        i = int(np.argmax(sign * y[1:-1])) + 1
        return sign * peak(sign * y, i)[0]

    last = max(i for i in range(1, len(t) - 1) if cl[i] >= cl[i - 1] and cl[i] >= cl[i + 1] and t[i] + period / 2 <= t[-1])
    t0 = peak(cl, last)[1]
    return dict(
        cd_max=extreme(cd, 1), cl_max=extreme(cl, 1), cl_min=extreme(cl, -1), cl_mean=float(mean),
        st=0.1 / period, dp=float(np.interp(t0 + period / 2, t, dpv)),
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--case", choices=["2d-1", "2d-2"], default="2d-1")
    ap.add_argument("--h", type=float, default=0.005, help="element size at the body")
    ap.add_argument("--segments", type=int, default=0, help="polygon sides for the body (default: 2πr/(h/4))")
    ap.add_argument("--length", type=float, default=LENGTH, help="the channel's length (the benchmark's is 2.2), to see what the outflow's place does")
    ap.add_argument("--dt", type=float, default=0.0025)
    ap.add_argument("--scheme", choices=["bdf2", "cn"], default="bdf2", help="time stepping of 2d-2 (see `periodic`)")
    ap.add_argument("--t-end", type=float, default=8.0)
    ap.add_argument("--t-measure", type=float, default=6.0)
    ap.add_argument("--out", help="CSV of t, c_D, c_L, Δp (2d-2)")
    ap.add_argument("--save-state", help="write the final (t, u, u_old) to this .npz (2d-2)")
    ap.add_argument("--load-state", help="start from a saved state instead of rest, interpolated if its mesh differs (2d-2)")
    args = ap.parse_args()
    segments = args.segments or int(np.ceil(2 * np.pi * RADIUS / (args.h / 4)))
    start = time.time()
    prob = Problem(args.h, segments, 0.3 if args.case == "2d-1" else 1.5, args.length)
    out = dict(case=args.case, h=args.h, segments=segments, triangles=prob.mesh.t.shape[1],
               unknowns=prob.nu_ + prob.np_)
    if args.case == "2d-1":
        u, p, its = steady(prob)
        cd, cl = prob.coefficients(prob.spatial(u), p, np.zeros_like(u))
        out.update(cd=cd, cl=cl, dp=prob.dp(p), newton=its)
    else:
        state = load_state(prob, args.load_state) if args.load_state else None
        series, steps, (t, u, u_old) = periodic(prob, args.dt, args.t_end, args.t_measure, state, args.scheme)
        if args.save_state:
            np.savez(args.save_state, t=t, u=u, u_old=u_old, mesh_p=prob.mesh.p, mesh_t=prob.mesh.t)
        if args.out:
            np.savetxt(args.out, series, delimiter=",", header="t,cd,cl,dp", comments="")
        out.update(measures(series), dt=args.dt, scheme=args.scheme, steps=steps)
    out["time_s"] = time.time() - start
    print(json.dumps({k: (v.item() if hasattr(v, "item") else v) for k, v in out.items()}))


if __name__ == "__main__":
    main()

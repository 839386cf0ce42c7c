//! The pressure projection in 2D and 3D: divergence and its transpose, the
//! pressure gradient and its transpose, and the projection with its adjoint
//! (the same solve, by [`super::PressureSolver`]).

use super::*;

/// Calls `f(c, face, first)` for every cell `c` of the box with the index
/// of its lower face along `a` (the upper one a stride of the face array
/// further) and whether it is the first cell along `a`: the closed boxes'
/// plain loops.
#[inline(always)]
fn cell_faces<const D: usize>(cfg: &MacGrid<D>, a: usize, mut f: impl FnMut(usize, usize, bool)) {
    let mac = cfg.bounded();
    let (cells, faces) = (mac.lattice(At::Centre), mac.lattice(At::Face(a)));
    for k in 0..cells.n[D - 1] {
        for r in 0..cells.rows_per_slab() {
            let mut q = cells.row_start(k, r);
            for i in 0..cells.n[0] {
                q[0] = i;
                f(cells.index(q), faces.index(q), q[a] == 0);
            }
        }
    }
}

/// Divergence of a MAC velocity, `d[c] = Σ` outward flux over the faces
/// of cell `c` (overwrites `d`): `Σ_a u_a[upper face] − u_a[lower face]`
/// inside the box; a periodic axis's face `N` is not read (face `0` wraps).
/// In 2D and 3D, `vel` the components.
pub fn divergence<const D: usize>(cfg: &MacGrid<D>, vel: [&[f64]; D], d: &mut [f64]) {
    if cfg.is_closed() {
        // P2's and P4's box in plain loops.
        d.fill(0.0);
        for (a, u) in vel.into_iter().enumerate() {
            let up = cfg.face_dims(a)[..a].iter().product::<usize>();
            cell_faces(cfg, a, |c, f, _| d[c] += u[f + up] - u[f]);
        }
        return;
    }
    d.fill(0.0);
    for (axis, u) in vel.into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            let w = u[f.index];
            if let Some(c) = f.lower {
                d[c] += w;
            }
            if let Some(c) = f.upper {
                d[c] -= w;
            }
        });
    }
}

/// Transpose of [`divergence`]: `vel += Dᵀ·d` (accumulates).
pub fn divergence_transpose<const D: usize>(cfg: &MacGrid<D>, d: &[f64], vel: [&mut [f64]; D]) {
    if cfg.is_closed() {
        for (a, u) in vel.into_iter().enumerate() {
            let up = cfg.face_dims(a)[..a].iter().product::<usize>();
            cell_faces(cfg, a, |c, f, _| {
                u[f + up] += d[c];
                u[f] -= d[c];
            });
        }
        return;
    }
    for (axis, u) in vel.into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| u[f.index] += f.lower.map_or(0.0, |c| d[c]) - f.upper.map_or(0.0, |c| d[c]));
    }
}

/// `vel −= G·p` on the faces the projection changes (interior, periodic,
/// outflow; with `fluid`, scaled by the face's openness, fluid–fluid only):
/// the pressure difference across each face, upper cell minus lower (`p = 0`
/// beyond an outflow side); periodic copies refreshed. In 2D and 3D.
pub fn subtract_gradient<const D: usize>(cfg: &MacGrid<D>, fluid: Option<&[f64]>, p: &[f64], vel: [&mut [f64]; D]) {
    if cfg.is_closed() && fluid.is_none() {
        // P2's and P4's box: the interior faces, each the lower face of a
        // cell past the first along its axis.
        for (a, u) in vel.into_iter().enumerate() {
            let down = cfg.n[..a].iter().product::<usize>();
            cell_faces(cfg, a, |c, f, first| {
                if !first {
                    u[f] -= p[c] - p[c - down];
                }
            });
        }
        return;
    }
    for (axis, u) in vel.into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            if f.projected {
                u[f.index] -= open(fluid, &f) * (f.upper.map_or(0.0, |c| p[c]) - f.lower.map_or(0.0, |c| p[c]));
                if let Some(k) = f.copy {
                    u[k] = u[f.index];
                }
            }
        });
    }
}

/// Transpose of [`subtract_gradient`]'s `G` (with `fluid`'s openness) on
/// the faces the projection changes: `out = Gᵀ·g` (overwrites), after each
/// periodic copy's adjoint is handed to its face `0` (the copy is written
/// from it, never read).
pub fn gradient_transpose<const D: usize>(cfg: &MacGrid<D>, fluid: Option<&[f64]>, vel: [&mut [f64]; D], out: &mut [f64]) {
    out.fill(0.0);
    if cfg.is_closed() && fluid.is_none() {
        for (a, g) in vel.into_iter().enumerate() {
            let down = cfg.n[..a].iter().product::<usize>();
            cell_faces(cfg, a, |c, f, first| {
                if !first {
                    out[c] += g[f];
                    out[c - down] -= g[f];
                }
            });
        }
        return;
    }
    for (axis, g) in vel.into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            if !f.projected {
                return;
            }
            if let Some(k) = f.copy {
                g[f.index] += g[k];
                g[k] = 0.0;
            }
            let l = open(fluid, &f) * g[f.index];
            if let Some(c) = f.upper {
                out[c] += l;
            }
            if let Some(c) = f.lower {
                out[c] -= l;
            }
        });
    }
}

/// Scratch of the projection (2D and 3D): divergence and pressure.
#[derive(Clone, Debug)]
pub struct ProjectScratch {
    pub(crate) d: Vec<f64>,
    pub(crate) p: Vec<f64>,
}

impl ProjectScratch {
    /// Scratch for a box of `cells` cells.
    pub fn new(cells: usize) -> Self {
        Self { d: vec![0.0; cells], p: vec![0.0; cells] }
    }

    /// The pressure of the last projection, in the projection's units: the
    /// velocity changed by its unit-spaced differences (`u −= p[c+1] − p[c]`).
    pub fn pressure(&self) -> &[f64] {
        &self.p
    }

    /// Multiplies the kept pressure by `r` (a warm start for a projection
    /// whose step is `r` times the last one's).
    pub fn scale_pressure(&mut self, r: f64) {
        self.p.iter_mut().for_each(|p| *p *= r);
    }
}

/// The projection (step 5 of P2 and P4), for any boundary and dimension,
/// in place on the velocity part of the packed state `y`: `d = D·vel`,
/// solve `A·p = −W·d` (`W` the fluid mask), `vel −= G·p` on the faces the
/// projection changes (interior, periodic, outflow; fluid–fluid only),
/// periodic copies refreshed. The solver must be built for `cfg`. Returns
/// the CG iterations.
pub fn project<const D: usize>(cfg: &MacGrid<D>, y: &mut [f64], solver: &mut PressureSolver<D>, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    let (_, vel) = cfg.split_mut(y);
    project_velocity(cfg, vel, None, None, solver, scratch, false)
}

/// [`project`] on separate velocity arrays. With `warm`, the solve starts
/// from the pressure left in `scratch` by the previous call (fewer
/// iterations when consecutive projections are alike, as in a march to a
/// steady state) instead of from zero; either way it ends at the same
/// tolerance. The pressure stays in `scratch` ([`ProjectScratch::pressure`]).
///
/// With `apertures` (per axis, in the layout of its faces), the divergence
/// weighs each face's flux by its open fraction and every face open by any
/// fraction takes the pressure gradient (cut cells), scaled per face by
/// `grad_scale` (packed as the velocity; 1 without): the projection `y −
/// M·G·p` with `D_a·M·G·p = D_a·y`, whose solver
/// [`PressureSolver::with_apertures`] builds from the products `a_f·M_f`.
pub fn project_velocity<const D: usize>(
    cfg: &MacGrid<D>,
    mut vel: [&mut [f64]; D],
    apertures: Option<[&[f64]; D]>,
    grad_scale: Option<&[f64]>,
    solver: &mut PressureSolver<D>,
    scratch: &mut ProjectScratch,
    warm: bool,
) -> Result<usize, NoConvergence> {
    debug_assert_eq!(solver.grid().boundary, cfg.boundary, "pressure solver built for another boundary");
    match apertures {
        None => divergence(cfg, vel.each_ref().map(|v| &**v), &mut scratch.d),
        Some(ap) => {
            let d = &mut scratch.d;
            d.fill(0.0);
            for (axis, u) in vel.iter().enumerate() {
                for_each_face(cfg.n, &cfg.boundary, axis, |f| {
                    let w = ap[axis][f.index] * u[f.index];
                    if let Some(c) = f.lower {
                        d[c] += w;
                    }
                    if let Some(c) = f.upper {
                        d[c] -= w;
                    }
                });
            }
        }
    }
    for d in scratch.d.iter_mut() {
        *d = -*d;
    }
    if let Some(w) = solver.fluid() {
        for (d, &wv) in scratch.d.iter_mut().zip(w) {
            *d *= wv;
        }
    }
    let iterations = if warm { solver.solve_from(&scratch.d, &mut scratch.p)? } else { solver.solve(&scratch.d, &mut scratch.p)? };
    let (p, fluid) = (&scratch.p, solver.fluid());
    let Some(ap) = apertures else {
        debug_assert!(grad_scale.is_none(), "a gradient scale goes with apertures");
        subtract_gradient(cfg, fluid, p, vel);
        return Ok(iterations);
    };
    // Cut cells: every face open by any fraction takes the gradient, scaled.
    let mut offset = 0;
    for (axis, u) in vel.iter_mut().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            if f.projected {
                let grad = f.upper.map_or(0.0, |c| p[c]) - f.lower.map_or(0.0, |c| p[c]);
                let open = (ap[axis][f.index] > 0.0) as u8 as f64 * grad_scale.map_or(1.0, |m| m[offset + f.index]);
                u[f.index] -= open * grad;
                if let Some(k) = f.copy {
                    u[k] = u[f.index];
                }
            }
        });
        offset += cfg.n_face(axis);
    }
    Ok(iterations)
}

/// Adjoint of [`project`] (a linear map), in place on the velocity part of
/// the adjoint `g`: periodic copies handed to their originals;
/// `λ_p = −Gᵀ·λ`; solve `A·μ = λ_p` (the transposed system — `A` is
/// symmetric — to the same tolerance; never a backward pass through the
/// iterations); since the solve's right-hand side was `−W·D·vel`,
/// `λ_vel += −Dᵀ·W·μ`. Returns the CG iterations.
pub fn project_adjoint<const D: usize>(
    cfg: &MacGrid<D>,
    g: &mut [f64],
    solver: &mut PressureSolver<D>,
    scratch: &mut ProjectScratch,
) -> Result<usize, NoConvergence> {
    let (_, vel) = cfg.split_mut(g);
    project_velocity_adjoint(cfg, vel, solver, scratch)
}

/// [`project_adjoint`] on separate velocity adjoint arrays (the adjoint of
/// [`project_velocity`] without apertures).
pub fn project_velocity_adjoint<const D: usize>(
    cfg: &MacGrid<D>,
    mut vel: [&mut [f64]; D],
    solver: &mut PressureSolver<D>,
    scratch: &mut ProjectScratch,
) -> Result<usize, NoConvergence> {
    let lp = &mut scratch.d;
    gradient_transpose(cfg, solver.fluid(), vel.each_mut().map(|v| &mut **v), lp);
    for l in lp.iter_mut() {
        *l = -*l;
    }
    let iterations = solver.solve(lp, &mut scratch.p)?;
    for (c, m) in scratch.p.iter_mut().enumerate() {
        *m = -*m * solver.fluid().map_or(1.0, |w| w[c]);
    }
    divergence_transpose(cfg, &scratch.p, vel);
    Ok(iterations)
}

//! Viscous Burgers `u_t + u·u_x = ν·u_xx` on the periodic line `[0, 2π)`
//! from `u₀ = sin x`, against the Cole–Hopf solution.

use std::f64::consts::PI;

use diffsim_solvers::burgers::{self, Advection1d, Burgers1d};
use diffsim_solvers::diffusion::{self, Grid, ImplicitSolver};
use diffsim_solvers::exact::ColeHopf;

use super::{AccuracyError, Diffusion, all_finite, positive, relative_l2, steps_to};
use diffsim::op::OpError;

/// The scheme of a run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BurgersScheme {
    /// P1's step: upwind advection and explicit central diffusion from the
    /// same state ([`burgers::step`]).
    Fused,
    /// Advection, then diffusion (Lie splitting).
    Split(Advection1d, Diffusion),
}

impl BurgersScheme {
    /// Short name of the advection (`upwind`, `semi-lagrangian`, `maccormack`).
    pub fn advection_name(&self) -> &'static str {
        match self {
            BurgersScheme::Fused | BurgersScheme::Split(Advection1d::Upwind, _) => "upwind",
            BurgersScheme::Split(Advection1d::SemiLagrangian, _) => "semi-lagrangian",
            BurgersScheme::Split(Advection1d::MacCormack, _) => "maccormack",
        }
    }

    /// The diffusion (the fused step's is explicit).
    pub fn diffusion(&self) -> Diffusion {
        match self {
            BurgersScheme::Fused => Diffusion::Explicit,
            BurgersScheme::Split(_, d) => *d,
        }
    }
}

/// One run: `n` cells, viscosity `nu`, to time `t_end`, time step
/// `dt = cfl·dx` (`|u| ≤ 1` throughout), for explicit diffusion also at
/// most `diffusion_number·dx²/ν`, then shortened to reach `t_end` exactly.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BurgersRun {
    /// Cells.
    pub n: usize,
    /// Viscosity ν.
    pub nu: f64,
    /// Final time.
    pub t_end: f64,
    /// Courant number `dt·max|u|/dx`.
    pub cfl: f64,
    /// Largest `ν·dt/dx²` of explicit diffusion (P1: 0.25; stable to 0.5).
    pub diffusion_number: f64,
    /// The scheme.
    pub scheme: BurgersScheme,
}

impl BurgersRun {
    /// A run with P1's diffusion number 0.25.
    pub fn new(n: usize, nu: f64, t_end: f64, cfl: f64, scheme: BurgersScheme) -> Self {
        Self { n, nu, t_end, cfl, diffusion_number: 0.25, scheme }
    }

    /// Cell width `2π/n`.
    pub fn dx(&self) -> f64 {
        2.0 * PI / self.n as f64
    }

    /// Number of steps and the time step.
    pub fn steps(&self) -> (usize, f64) {
        let dx = self.dx();
        let mut dt = self.cfl * dx;
        if self.scheme.diffusion() == Diffusion::Explicit {
            dt = dt.min(self.diffusion_number * dx * dx / self.nu);
        }
        steps_to(self.t_end, dt)
    }

    fn validate(&self) -> Result<(), AccuracyError> {
        if self.n < 3 {
            return Err(AccuracyError::Invalid { what: "n", reason: format!("need at least 3 cells, got {}", self.n) });
        }
        positive("nu", self.nu)?;
        positive("t_end", self.t_end)?;
        positive("cfl", self.cfl)?;
        positive("diffusion_number", self.diffusion_number)?;
        if let Diffusion::Implicit { tolerance } = self.scheme.diffusion() {
            positive("tolerance", tolerance)?;
        }
        Ok(())
    }

    /// The solution at `t_end` on the cells `x_i = i·dx`.
    pub fn run(&self) -> Result<Vec<f64>, AccuracyError> {
        self.validate()?;
        let (n, dx) = (self.n, self.dx());
        let (steps, dt) = self.steps();
        let kappa = self.nu * dt / (dx * dx);
        let line = Grid::line(n, true);
        if self.scheme.diffusion() == Diffusion::Explicit && kappa > line.explicit_limit() {
            return Err(AccuracyError::Operator { stage: "diffusion", step: 0, error: OpError::Unstable { value: kappa, limit: line.explicit_limit() } });
        }
        let mut u: Vec<f64> = (0..n).map(|i| (i as f64 * dx).sin()).collect();
        let mut tmp = vec![0.0; n];
        let mut scratch = vec![0.0; n];
        let mut implicit = match self.scheme.diffusion() {
            Diffusion::Implicit { tolerance } => Some(ImplicitSolver::new(line, tolerance, 10 * n + 100)),
            Diffusion::Explicit => None,
        };
        let fused = Burgers1d { n, dx, dt, nu: self.nu };
        for step in 0..steps {
            match self.scheme {
                BurgersScheme::Fused => {
                    burgers::step(&fused, &u, &mut tmp);
                    std::mem::swap(&mut u, &mut tmp);
                }
                BurgersScheme::Split(advection, _) => {
                    burgers::advect_line(advection, dt / dx, &u, &mut tmp, &mut scratch);
                    if !all_finite(&tmp) {
                        return Err(AccuracyError::NonFinite { stage: "advection", step });
                    }
                    match implicit.as_mut() {
                        None => diffusion::explicit(&line, kappa, &tmp, &mut u),
                        Some(solver) => {
                            solver.solve(kappa, &tmp, &mut u).map_err(|e| AccuracyError::Operator { stage: "diffusion", step, error: e.into() })?;
                        }
                    }
                }
            }
            if !all_finite(&u) {
                return Err(AccuracyError::NonFinite { stage: if self.scheme == BurgersScheme::Fused { "step" } else { "diffusion" }, step });
            }
        }
        Ok(u)
    }

    /// The exact solution at `t_end` on the same cells.
    pub fn exact(&self) -> Vec<f64> {
        ColeHopf::new(self.nu).on_grid(self.n, self.t_end)
    }

    /// Relative L2 error of `u` (a result of [`BurgersRun::run`]) against
    /// the exact solution at `t_end`.
    pub fn error_of(&self, u: &[f64]) -> f64 {
        relative_l2(u, &self.exact())
    }

    /// Runs and returns the relative L2 error at `t_end`.
    pub fn error(&self) -> Result<f64, AccuracyError> {
        Ok(self.error_of(&self.run()?))
    }
}

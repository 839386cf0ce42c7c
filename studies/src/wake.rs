//! Solver-in-the-loop in 2D: flow past a disc in a channel (the unsteady
//! wake of Um et al., NeurIPS 2020), corrected toward a 4× finer reference.
//!
//! - Domain: `64 × 32` coarse cells (x along the channel), uniform inflow
//!   on the left, outflow on the right, closed walls; a disc of radius 4
//!   centred at `(16, 15)` (off the centre line, so the wake turns
//!   unsteady sooner).
//! - Step ([`WakeStep`]): semi-Lagrangian advection of the velocity,
//!   explicit viscosity, pressure projection with the disc as an obstacle.
//! - Reference: the same step on `4·64 × 4·32` cells with a quarter of the
//!   time step, four fine steps per coarse step; velocities downsampled by
//!   averaging each coarse face's fine faces (fluxes add up, so a
//!   divergence-free fine field gives a divergence-free coarse one).
//! - Initial states: the inflow speed everywhere plus a random
//!   divergence-free perturbation (a stream function of three random
//!   sine modes), run `warmup` coarse steps on the fine grid before the
//!   trajectory starts.
//! - The network sees and corrects the two velocity components as image
//!   channels ([`diffsim::nn::presets::mac_conv_stack`]).
//!
//! The study itself is [`crate::sol`]'s, the same as on Burgers.

use std::cell::RefCell;
use std::f64::consts::PI;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use diffsim_solvers::boundary::{Boundary, Profile, Side, for_each_face};
use diffsim_solvers::smoke::{MacGrid, Scheme, Solid, solid_cells};

use crate::sol::{Method, SolProblem, StudyParams, TrainParams, Trajectory};
use diffsim::fluids::{Advect, Diffuse, DiffuseExplicit, Project};
use diffsim::nn::{Activation, Net, presets};
use diffsim::op::{Forward, Jvp, OpError, Operator, PerThread, Vjp, validate_forward, validate_jvp, validate_vjp};

/// One step of the channel flow: advection of the velocity, explicit
/// viscosity `κ = ν·dt`, projection with the obstacle. Derivatives chain
/// the parts' own: Enzyme's for advection and viscosity, the projection's
/// implicit adjoint. Owns solver buffers (not `Sync`: use one per thread,
/// [`PerThread`]).
#[derive(Debug)]
pub struct WakeStep {
    advect: Advect<2>,
    diffuse: Diffuse<DiffuseExplicit>,
    kappa: [f64; 1],
    /// The projection (with the disc).
    pub project: Project<2>,
    /// The advected state and its adjoint or tangent (the VJP and JVP
    /// recompute the advection).
    mid: RefCell<[Vec<f64>; 2]>,
}

impl WakeStep {
    /// The step on `cfg` with advection `scheme`, time step `dt`, viscosity
    /// `nu` (cell units), solid cells `solid`, pressure solves to relative
    /// `tolerance`.
    pub fn new(cfg: MacGrid<2>, scheme: Scheme, dt: f64, nu: f64, solid: &[bool], tolerance: f64) -> Self {
        let advect = Advect { dt, smoke: false, ..Advect::new(cfg, scheme) };
        let n = cfg.n_state();
        Self {
            advect,
            diffuse: Diffuse::explicit(cfg, false, true),
            kappa: [nu * dt],
            project: Project::with_obstacles(cfg, tolerance, 10_000, diffsim_solvers::smoke::Preconditioner::Mic0, solid),
            mid: RefCell::new([vec![0.0; n], vec![0.0; n]]),
        }
    }
}

impl Operator for WakeStep {
    fn n_in(&self) -> usize {
        self.advect.cfg.n_state()
    }
    fn n_out(&self) -> usize {
        self.advect.cfg.n_state()
    }
}

impl Forward for WakeStep {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "WakeStep", x, p, y);
        let mut mid = self.mid.borrow_mut();
        let [a, _] = &mut *mid;
        self.advect.forward(x, &[], a);
        self.diffuse.forward(a, &self.kappa, y);
        self.project.apply(y);
    }
    /// The viscosity's (an unstable κ) or else the projection's; both are
    /// cleared.
    fn take_error(&self) -> Option<OpError> {
        let viscosity = self.diffuse.take_error();
        let projection = self.project.take_error();
        viscosity.or(projection)
    }
}

impl Vjp for WakeStep {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "WakeStep", x, p, dy, dx, dp);
        let mut mid = self.mid.borrow_mut();
        let [a, ga] = &mut *mid;
        self.advect.forward(x, &[], a);
        // Projection (linear, in place), viscosity at the advected state,
        // advection at x.
        self.project.apply_adjoint(dy);
        ga.fill(0.0);
        let mut dk = [0.0];
        self.diffuse.vjp(a, &self.kappa, dy, ga, &mut dk);
        self.advect.vjp(x, &[], ga, dx, &mut []);
    }
}

impl Jvp for WakeStep {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "WakeStep", x, p, tx, tp, y, ty);
        let mut mid = self.mid.borrow_mut();
        let [a, ta] = &mut *mid;
        self.advect.jvp(x, &[], tx, &[], a, ta);
        self.diffuse.jvp(a, &self.kappa, ta, &[0.0], y, ty);
        self.project.apply(y);
        self.project.apply(ty);
    }
}

/// The study's grids, flow and data.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WakeSetup {
    /// The coarse box (the source solver's) with its boundary.
    pub coarse: MacGrid<2>,
    /// Refinement of the reference in space (and in time: `factor` fine
    /// steps per coarse step).
    pub factor: usize,
    /// Advection scheme (both grids).
    pub scheme: Scheme,
    /// Coarse time step.
    pub dt: f64,
    /// Viscosity in coarse cell units (Reynolds number `speed·2·radius/ν`).
    pub nu: f64,
    /// Inflow speed (coarse cells per unit time).
    pub speed: f64,
    /// Disc centre (coarse cells, x first).
    pub center: [f64; 2],
    /// Disc radius (coarse cells).
    pub radius: f64,
    /// Coarse steps run on the fine grid before a trajectory starts.
    pub warmup: usize,
    /// Relative tolerance of the pressure solves.
    pub tolerance: f64,
}

impl WakeSetup {
    /// `64 × 32` cells, 4× finer reference, semi-Lagrangian advection,
    /// `dt = 0.5`, inflow speed 1,
    /// disc of radius 4 at `(16, 15)`, `ν = 0.04` (Re = 200), 40 warm-up
    /// steps, solves to 1e-6.
    pub fn standard() -> Self {
        let speed = 1.0;
        let boundary = Boundary::CLOSED.with_lower(0, Side::Inflow(Profile::Uniform(speed))).with_upper(0, Side::Outflow);
        Self {
            coarse: MacGrid::new([64, 32]).with_boundary(boundary),
            factor: 4,
            scheme: Scheme::SemiLagrangian,
            dt: 0.5,
            nu: 0.04,
            speed,
            center: [16.0, 15.0],
            radius: 4.0,
            warmup: 40,
            tolerance: 1e-6,
        }
    }

    /// The fine box: `factor` times the cells, inflow in fine cells per unit time.
    pub fn fine(&self) -> MacGrid<2> {
        let f = self.factor;
        let boundary = self.coarse.boundary.with_lower(0, Side::Inflow(Profile::Uniform(self.speed * f as f64)));
        MacGrid::new([self.coarse.n[0] * f, self.coarse.n[1] * f]).with_boundary(boundary)
    }

    /// Solid cells of the disc on the box `cfg`, `scale` cells per coarse cell.
    fn solid(&self, cfg: &MacGrid<2>, scale: f64) -> Vec<bool> {
        let c = [self.center[0] * scale, self.center[1] * scale];
        solid_cells(cfg, &[Solid::Ball { center: c, radius: self.radius * scale }])
    }

    /// The reference solver (fine grid, `dt / factor`, viscosity in fine cells).
    pub fn reference_step(&self) -> WakeStep {
        let f = self.factor as f64;
        let fine = self.fine();
        WakeStep::new(fine, self.scheme, self.dt / f, self.nu * f * f, &self.solid(&fine, f), self.tolerance)
    }

    /// A random fine initial state: the inflow speed everywhere plus the
    /// discrete curl of `ψ = Σ_{3 modes} a·sin(π·m·X/Lx)·sin(π·l·Y/Ly)`
    /// (exactly divergence-free, no flow through the walls), `a` up to
    /// 1.5 coarse cells² per unit time.
    pub fn initial(&self, rng: &mut impl Rng) -> Vec<f64> {
        let fine = self.fine();
        let f = self.factor as f64;
        let (lx, ly) = (self.coarse.n[0] as f64, self.coarse.n[1] as f64);
        let modes: Vec<(f64, f64, f64)> =
            (0..3).map(|_| (rng.random_range(-1.5..1.5), rng.random_range(1..=4) as f64, rng.random_range(1..=3) as f64)).collect();
        // ψ at fine node (i, j), in coarse units.
        let psi = |i: usize, j: usize| {
            let (x, y) = (i as f64 / f, j as f64 / f);
            modes.iter().map(|(a, m, l)| a * (PI * m * x / lx).sin() * (PI * l * y / ly).sin()).sum::<f64>()
        };
        let mut x = vec![0.0; fine.n_state()];
        let (nx, ny) = (fine.n[0], fine.n[1]);
        let (_, [u, v]) = fine.split_mut(&mut x);
        // Velocity in fine cells per unit time: f·(∂ψ/∂Y) ≈ f²·Δψ.
        for j in 0..ny {
            for i in 0..=nx {
                u[j * (nx + 1) + i] = self.speed * f + f * f * (psi(i, j + 1) - psi(i, j));
            }
        }
        for j in 0..=ny {
            for i in 0..nx {
                v[j * nx + i] = -f * f * (psi(i + 1, j) - psi(i, j));
            }
        }
        x
    }

    /// A fine state averaged to the coarse grid: each coarse face's
    /// velocity is the mean of the `factor` fine faces on it, in coarse
    /// cells per unit time; no smoke.
    pub fn downsample(&self, fine_x: &[f64]) -> Vec<f64> {
        let (c, fine, f) = (self.coarse, self.fine(), self.factor);
        let (_, [fu, fv]) = fine.split(fine_x);
        let mut x = vec![0.0; c.n_state()];
        let (_, [u, v]) = c.split_mut(&mut x);
        let scale = 1.0 / (f * f) as f64;
        for j in 0..c.n[1] {
            for i in 0..=c.n[0] {
                u[j * (c.n[0] + 1) + i] = scale * (0..f).map(|r| fu[(f * j + r) * (fine.n[0] + 1) + f * i]).sum::<f64>();
            }
        }
        for j in 0..=c.n[1] {
            for i in 0..c.n[0] {
                v[j * c.n[0] + i] = scale * (0..f).map(|r| fv[f * j * fine.n[0] + f * i + r]).sum::<f64>();
            }
        }
        x
    }

    /// One reference trajectory from a fine initial state: `warmup` coarse
    /// steps, then coarse states `0..=steps`. A solve that fails is an error.
    pub fn reference(&self, x0: &[f64], steps: usize) -> Result<Trajectory, OpError> {
        let step = self.reference_step();
        let mut x = x0.to_vec();
        let mut y = vec![0.0; x.len()];
        let mut out = Vec::with_capacity(steps + 1);
        for t in 0..self.warmup + steps + 1 {
            if t >= self.warmup {
                out.push(self.downsample(&x));
            }
            if t == self.warmup + steps {
                break;
            }
            for _ in 0..self.factor {
                step.forward(&x, &[], &mut y);
                if let Some(e) = step.take_error() {
                    return Err(e);
                }
                std::mem::swap(&mut x, &mut y);
            }
        }
        Ok(out)
    }

    /// The state entries a correction may change: the velocity faces the
    /// projection owns (interior and outflow) that touch no solid cell; not
    /// the smoke, the inflow faces or the walls, whose values the solver sets.
    pub fn correctable(&self) -> Vec<bool> {
        let c = &self.coarse;
        let solid = self.solid(c, 1.0);
        let mut keep = vec![false; c.n_state()];
        for (axis, start) in [(0, c.n_s()), (1, c.n_s() + c.n_face(0))] {
            for_each_face(c.n, &c.boundary, axis, |f| {
                let open = [f.lower, f.upper].iter().all(|cell| cell.is_none_or(|k| !solid[k]));
                keep[start + f.index] = f.projected && open;
            });
        }
        keep
    }

    /// The correction network: [`presets::mac_conv_stack`] with channels
    /// 2 → 16 → 16 → 2, kernel 3, activation `act` (2 898 parameters),
    /// writing only the [correctable](Self::correctable) faces.
    pub fn network(&self, act: Activation) -> Net {
        let keep = self.correctable();
        presets::mac_conv_stack(self.coarse.n[0], self.coarse.n[1], &[2, 16, 16, 2], 3, act, Some(&keep)).expect("the preset is well formed")
    }
}

impl SolProblem for WakeSetup {
    type Solver = PerThread<WakeStep>;

    fn source(&self) -> PerThread<WakeStep> {
        let solid = self.solid(&self.coarse, 1.0);
        PerThread::new(|| WakeStep::new(self.coarse, self.scheme, self.dt, self.nu, &solid, self.tolerance))
    }

    /// Initial states drawn in order from `rng`, the trajectories computed
    /// in parallel (each is independent of the thread count).
    ///
    /// # Panics
    /// If a reference pressure solve fails (the standard setup's do not).
    fn dataset(&self, count: usize, steps: usize, rng: &mut StdRng) -> Vec<Trajectory> {
        self.dataset_share(count, steps, rng, 0..count)
    }

    fn dataset_share(&self, count: usize, steps: usize, rng: &mut StdRng, share: std::ops::Range<usize>) -> Vec<Trajectory> {
        let seeds: Vec<u64> = (0..count).map(|_| rng.random()).collect();
        seeds[share]
            .par_iter()
            .map(|&s| {
                let x0 = self.initial(&mut StdRng::seed_from_u64(s));
                self.reference(&x0, steps).unwrap_or_else(|e| panic!("wake reference: {e}"))
            })
            .collect()
    }

    fn with_viscosity(&self, nu: f64) -> Self {
        Self { nu, ..*self }
    }
}

/// The activation of the study's network.
pub const STUDY_ACTIVATION: Activation = Activation::Relu;

impl StudyParams<WakeSetup> {
    /// The 2D study: 16 training and 8 test trajectories, 64-step
    /// evaluation, PRE / NOISE / SOL-4 / SOL-16, 1000 updates of batch 8
    /// with Adam, learning rate 1e-3 decaying to 1e-5. `quick`: 300
    /// updates, 6 + 3 trajectories, 32-step evaluation.
    pub fn wake(quick: bool) -> Self {
        let iterations = if quick { 300 } else { 1000 };
        let setup = WakeSetup::standard();
        let eval_steps = if quick { 32 } else { 64 };
        Self {
            setup,
            train: if quick { 6 } else { 16 },
            train_base: if quick { 6 } else { 16 },
            test: if quick { 3 } else { 8 },
            train_steps: eval_steps + 16,
            eval_steps,
            methods: Method::standard(),
            settings: TrainParams::adam(8, iterations),
            net: setup.network(STUDY_ACTIVATION),
        }
    }
}

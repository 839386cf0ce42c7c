//! Robertson's kinetics with diffsol 0.18: the loss
//! `G = ½ Σ_i ‖u(t_i) − d_i‖²` at t = 0.4, 4, 40 (d: ODEPACK's published
//! solution) and its gradient with respect to the log-rates `p = ln k`, at
//! `p` off the published rates by (0.3, −0.4, 0.3) (where a fit starts), by
//! diffsol's adjoint (BDF forward with checkpointing, BDF backward), the
//! right-hand side and its three derivative products written by hand as
//! diffsol's closure interface asks. Prints one JSON line:
//! `{"peer", "rtol", "grad_s", "loss", "gradient"}`.
//!
//! `diffsol-robertson RTOL REPS`: relative tolerance (the absolute one the
//! same; the backward pass uses them too), repetitions timed (the median
//! is reported). Below an absolute tolerance of about 1e-11 diffsol's
//! backward pass stops with "Step size is too small at time = 40" on this
//! problem, so RTOL 1e-10 is the tightest that runs.

use diffsol::{AdjointOdeSolverMethod, DenseMatrix, Matrix, NalgebraLU, NalgebraMat, OdeBuilder, OdeSolverMethod, OdeSolverState, Vector};
use std::time::Instant;

type M = NalgebraMat<f64>;
type LS = NalgebraLU<f64>;

const TIMES: [f64; 3] = [0.4, 4.0, 40.0];
const DATA: [[f64; 3]; 3] =
    [[9.851726e-01, 3.386406e-05, 1.479357e-02], [9.055142e-01, 2.240418e-05, 9.446344e-02], [7.158050e-01, 9.184616e-06, 2.841858e-01]];

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let usage = "usage: diffsol-robertson RTOL REPS";
    let rtol: f64 = args.get(1).and_then(|a| a.parse().ok()).filter(|r: &f64| *r > 0.0 && *r < 1.0).unwrap_or_else(|| {
        eprintln!("{usage}: RTOL must be a number in (0, 1)");
        std::process::exit(2)
    });
    let reps: usize = args.get(2).and_then(|a| a.parse().ok()).filter(|r| *r >= 1).unwrap_or_else(|| {
        eprintln!("{usage}: REPS must be a whole number ≥ 1");
        std::process::exit(2)
    });
    // Where a fit to the published solution starts: the log-rates off by
    // (0.3, −0.4, 0.3), as in diffsim's test of the fit.
    let p = [0.04f64.ln() + 0.3, 3.0e7f64.ln() - 0.4, 1.0e4f64.ln() + 0.3];
    let problem = OdeBuilder::<M>::new()
        .p(p)
        .rtol(rtol)
        .atol([rtol; 3])
        .rhs_adjoint_implicit(
            |u: &[f64], p: &[f64], _t: f64, f: &mut [f64]| {
                let (k1, k2, k3) = (p[0].exp(), p[1].exp(), p[2].exp());
                f[0] = -k1 * u[0] + k3 * u[1] * u[2];
                f[1] = k1 * u[0] - k3 * u[1] * u[2] - k2 * u[1] * u[1];
                f[2] = k2 * u[1] * u[1];
            },
            // J·v
            |u: &[f64], p: &[f64], _t: f64, v: &[f64], y: &mut [f64]| {
                let (k1, k2, k3) = (p[0].exp(), p[1].exp(), p[2].exp());
                let (b, c) = (u[1], u[2]);
                y[0] = -k1 * v[0] + k3 * c * v[1] + k3 * b * v[2];
                y[1] = k1 * v[0] - (k3 * c + 2.0 * k2 * b) * v[1] - k3 * b * v[2];
                y[2] = 2.0 * k2 * b * v[1];
            },
            // −Jᵀ·v
            |u: &[f64], p: &[f64], _t: f64, v: &[f64], y: &mut [f64]| {
                let (k1, k2, k3) = (p[0].exp(), p[1].exp(), p[2].exp());
                let (b, c) = (u[1], u[2]);
                y[0] = -(-k1 * v[0] + k1 * v[1]);
                y[1] = -(k3 * c * v[0] - (k3 * c + 2.0 * k2 * b) * v[1] + 2.0 * k2 * b * v[2]);
                y[2] = -(k3 * b * v[0] - k3 * b * v[1]);
            },
            // −(∂f/∂p)ᵀ·v
            |u: &[f64], p: &[f64], _t: f64, v: &[f64], y: &mut [f64]| {
                let (k1, k2, k3) = (p[0].exp(), p[1].exp(), p[2].exp());
                let (a, b, c) = (u[0], u[1], u[2]);
                y[0] = -(k1 * a * (v[1] - v[0]));
                y[1] = -(k2 * b * b * (v[2] - v[1]));
                y[2] = -(k3 * b * c * (v[0] - v[1]));
            },
        )
        .init_adjoint(
            |_p: &[f64], _t: f64, u: &mut [f64]| {
                u[0] = 1.0;
                u[1] = 0.0;
                u[2] = 0.0;
            },
            |_p: &[f64], _t: f64, _v: &[f64], y: &mut [f64]| y.fill(0.0),
            3,
        )
        .build()
        .unwrap_or_else(|e| {
            eprintln!("diffsol-robertson: building the problem failed: {e}");
            std::process::exit(1)
        });
    let gradient = || -> Result<(f64, Vec<f64>), diffsol::DiffsolError> {
        let mut solver = problem.bdf::<LS>()?;
        let (checkpoints, soln, _) = solver.solve_dense_with_checkpointing(&TIMES, None)?;
        let mut dgdu = <M as Matrix>::zeros(3, TIMES.len(), problem.context().clone());
        let mut loss = 0.0;
        for j in 0..TIMES.len() {
            for i in 0..3 {
                let d = soln.get_index(i, j) - DATA[j][i];
                loss += 0.5 * d * d;
                dgdu.set_index(i, j, d);
            }
        }
        let adjoint = problem.bdf_solver_adjoint::<LS, _>(checkpoints, Some(solver), Some(1))?;
        let (state, _) = adjoint.solve_adjoint_backwards_pass(&TIMES, &[&dgdu])?;
        let sg = state.into_common().sg;
        Ok((loss, sg.clone_as_vec()))
    };
    let mut times = Vec::with_capacity(reps);
    let mut last = None;
    for _ in 0..reps {
        let t = Instant::now();
        let r = gradient();
        times.push(t.elapsed().as_secs_f64());
        match r {
            Ok(r) => last = Some(r),
            Err(e) => {
                eprintln!("diffsol-robertson: the solve failed at rtol {rtol:e}: {e}");
                std::process::exit(1)
            }
        }
    }
    times.sort_by(f64::total_cmp);
    let (loss, g) = last.expect("at least one repetition");
    if !loss.is_finite() || g.iter().any(|v| !v.is_finite()) {
        eprintln!("diffsol-robertson: the loss or gradient is not finite at rtol {rtol:e}");
        std::process::exit(1)
    }
    println!(
        "{{\"peer\": \"diffsol 0.18.0 BDF\", \"rtol\": {rtol:e}, \"grad_s\": {:e}, \"loss\": {loss:e}, \"gradient\": [{:e}, {:e}, {:e}]}}",
        times[reps / 2],
        g[0],
        g[1],
        g[2]
    );
}

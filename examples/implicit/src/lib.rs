//! The program around the implicit step: the gradient checks of one step,
//! the checks through a 20-step rollout for the initial state and every
//! cell's conductivity, and a fit that recovers the conductivities from the
//! temperatures.
//!
//! This crate is built *without* the autodiff flag (../Cargo.toml), so its
//! ordinary code never meets Enzyme's type analysis; the differentiated
//! code is in ../solver.

use std::error::Error;

use diffsim::prelude::*;
use diffsim::implicit::Integrator;
use diffsim::train::{LbfgsStep, TrainError};
use starter_solver::{Heat, step};

/// What the program returns on failure: any error, printed by `main`.
pub type Result<T> = std::result::Result<T, Box<dyn Error>>;

/// Runs every part in order; stops at the first that fails.
pub fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => {
            println!("\nall checks passed and the fit recovered the conductivities");
            std::process::ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Every part in order (what `main` runs, and the test in `run/tests`).
pub fn run() -> Result<()> {
    one_step_checks()?;
    checks_through_the_rollout()?;
    fit()?;
    Ok(())
}

// ANCHOR: problem
/// Cells per side, the time step, the steps of every rollout, and the
/// steps at which the temperature is observed.
pub const N: usize = 8;
/// The time step.
pub const DT: f64 = 0.05;
/// Steps of every rollout.
pub const STEPS: usize = 20;
/// Observations at these steps.
pub const OBSERVED: [usize; 4] = [5, 10, 15, 20];

/// The problem: the step, an initial temperature, the conductivities to
/// recover, and the temperatures they produce at the observed steps.
pub struct Problem {
    /// The backward-Euler step.
    pub step: Integrator<Heat>,
    /// The initial temperature.
    pub u0: Vec<f64>,
    /// The log-conductivities to recover.
    pub truth: Vec<f64>,
    /// The temperatures at the steps of [`OBSERVED`] under `truth`.
    pub observations: Vec<Vec<f64>>,
}

/// The problem, its observations computed by running the step.
pub fn problem() -> Problem {
    let step = step(N, DT);
    let cell = |k: usize| ((k % N) as f64 + 0.5, (k / N) as f64 + 0.5);
    let u0: Vec<f64> = (0..N * N).map(|k| cell(k)).map(|(x, y)| (0.9 * x).sin() * (0.6 * y).cos() + 0.1 * x).collect();
    let truth: Vec<f64> = (0..N * N).map(|k| cell(k)).map(|(x, y)| 0.5 * (0.4 * x).sin() + 0.3 * (0.5 * y).cos()).collect();
    let mut u = u0.clone();
    let mut observations = Vec::new();
    for t in 1..=STEPS {
        u = step.eval(&u, &truth);
        if OBSERVED.contains(&t) {
            observations.push(u.clone());
        }
    }
    Problem { step, u0, truth, observations }
}

/// The misfit to the observations, `L = Σ_t ½‖u_t − obs_t‖²`.
pub fn misfit(observations: &[Vec<f64>]) -> AtSteps<impl Fn(usize, &[f64], &mut [f64]) -> f64 + '_> {
    AtSteps {
        steps: OBSERVED.to_vec(),
        f: move |t: usize, u: &[f64], grad: &mut [f64]| -> f64 {
            let k = OBSERVED.iter().position(|&s| s == t).expect("a term only at observed steps");
            let mut value = 0.0;
            for ((g, u), o) in grad.iter_mut().zip(u).zip(&observations[k]) {
                *g = u - o;
                value += 0.5 * (u - o) * (u - o);
            }
            value
        },
    }
}
// ANCHOR_END: problem

fn passed(what: &str, report: diffsim::check::FullReport) -> Result<()> {
    if report.passed() {
        println!("  {what}: finite differences, Taylor and dot product pass");
        Ok(())
    } else {
        Err(format!("{what}: a gradient check failed:\n{report}").into())
    }
}

// ANCHOR: checks
/// The three checks on one step, then through all 20 steps for the initial
/// temperature and the 64 conductivities at once. The step declares its
/// solver tolerance, so the checks judge at that level, not at rounding.
fn one_step_checks() -> Result<()> {
    println!("1. one backward-Euler step");
    let pb = problem();
    passed("∂u₁/∂u₀ and ∂u₁/∂θ", check_all(&pb.step, &pb.u0, &pb.truth, &CheckParams::default()))
}

fn checks_through_the_rollout() -> Result<()> {
    println!("2. checks through {STEPS} steps");
    let pb = problem();
    let loss = misfit(&pb.observations);
    let guess = vec![0.0; N * N];
    let rollout = Rollout::new(&pb.step, &guess, STEPS)?;
    let as_op = RolloutLoss::new(rollout, &pb.u0, &loss, Checkpointing::periodic_sqrt(STEPS), Wrt::Both)?;
    let (x, p) = as_op.point();
    passed("∂L/∂u₀ and ∂L/∂θ", check_all(&as_op, x, p, &CheckParams::default()))
}
// ANCHOR_END: checks

// ANCHOR: fit
/// Recovers the 64 log-conductivities from the observed temperatures,
/// starting from a uniform conductivity, by L-BFGS on the gradient through
/// the rollout (one adjoint solve a step, by the implicit rule). The misfit
/// falls by more than ten orders of magnitude; θ is recovered to about
/// 10⁻³ (where little heat flows, the temperatures say little about the
/// conductivity).
fn fit() -> Result<()> {
    println!("3. fit θ with L-BFGS");
    let pb = problem();
    let loss = misfit(&pb.observations);
    let mut objective = FnObjective {
        n: N * N,
        f: |theta: &[f64]| -> std::result::Result<(f64, Vec<f64>), TrainError> {
            let g = Rollout::new(&pb.step, theta, STEPS)?.value_and_grad(&pb.u0, &loss, Checkpointing::Store)?;
            Ok((g.loss, g.dp))
        },
    };
    let mut theta = vec![0.0; N * N];
    let first = Rollout::new(&pb.step, &theta, STEPS)?.loss(&pb.u0, &loss)?;
    let mut rule = Lbfgs::new(LbfgsParams { tolerance_grad: 1e-14, ..LbfgsParams::default() })?;
    let mut iterations = 0;
    while iterations < 300 {
        iterations += 1;
        if let LbfgsStep::Converged { .. } = rule.iterate(&mut objective, &mut theta)? {
            break;
        }
    }
    let last = Rollout::new(&pb.step, &theta, STEPS)?.loss(&pb.u0, &loss)?;
    let error = theta.iter().zip(&pb.truth).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    println!("  loss {first:.3e} → {last:.3e} in {iterations} iterations; largest error in θ {error:.1e}");
    if last > 1e-10 * first || error > 1e-2 {
        return Err(format!("the fit did not recover the conductivities (loss {last:.1e}, largest error in θ {error:.1e})").into());
    }
    Ok(())
}
// ANCHOR_END: fit

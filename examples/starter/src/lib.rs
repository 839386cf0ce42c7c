//! The program around the solver: gradient checks of one step, a rollout
//! with a loss at several steps, checks through the whole rollout for the
//! initial state and the parameters, and a fit of the parameters with Adam.
//!
//! This crate is built *without* the autodiff flag (../Cargo.toml), so its
//! ordinary code (tables, loops over tuples, error handling) never meets
//! Enzyme's type analysis; the differentiated code is in ../solver.

use std::error::Error;
use std::time::Instant;

use diffsim::check::{CheckParams, FullReport, check_all, dot_product_between};
use diffsim::op::{Forward, OperatorExt};
use diffsim::rollout::{AtSteps, Checkpointing, Rollout, RolloutLoss, Wrt};
use diffsim::distributed::World;
use diffsim::train::{Adam, AdamParams, FnObjective, Schedule, TrainError, Trainer, TrainerParams};
use starter_solver::{Fkpp, FkppHand, FkppHeun, FkppStencil};

/// What the program returns on failure: any error, printed by `main`.
pub type Result<T> = std::result::Result<T, Box<dyn Error>>;

/// Runs every part in order; stops at the first that fails.
pub fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => {
            println!("\nall checks passed and the fit converged");
            std::process::ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Every part in order: the checks of one step, a rollout, the checks
/// through it, the fit (what `main` runs, and the test in `run/tests`).
pub fn run() -> Result<()> {
    one_step_checks()?;
    rollout_and_its_gradient()?;
    checks_through_the_rollout()?;
    fit_with_adam()?;
    Ok(())
}

// ANCHOR: problem
/// The problem: 64 cells, a bump of population on a background, the
/// parameters `[ν, r]` that generate the observations, a first guess, and
/// the observations at three steps.
pub struct Problem {
    /// The step.
    pub op: Fkpp,
    /// The initial state.
    pub u0: Vec<f64>,
    /// The parameters to recover.
    pub truth: [f64; 2],
    /// Where the fit starts.
    pub guess: [f64; 2],
    /// The states at the steps of [`OBSERVED`] under `truth`.
    pub observations: Vec<Vec<f64>>,
}

/// Observations at these steps; the rollouts run to the last.
pub const OBSERVED: [usize; 3] = [20, 40, 60];
/// Steps of every rollout.
pub const STEPS: usize = 60;

/// The problem, its observations computed by running the step.
pub fn problem() -> Problem {
    let op = Fkpp { n: 64, dt: 0.01 };
    let u0: Vec<f64> = (0..op.n)
        .map(|i| {
            let x = (i as f64 + 0.5) / op.n as f64;
            0.1 + 0.7 * (-((x - 0.4) / 0.08).powi(2)).exp()
        })
        .collect();
    let truth = [0.2, 2.0];
    let (mut u, mut next) = (u0.clone(), vec![0.0; op.n]);
    let mut observations = Vec::new();
    for t in 1..=STEPS {
        op.forward(&u, &truth, &mut next);
        std::mem::swap(&mut u, &mut next);
        if OBSERVED.contains(&t) {
            observations.push(u.clone());
        }
    }
    Problem { op, u0, truth, guess: [0.3, 1.0], observations }
}
// ANCHOR_END: problem

fn passed(what: &str, report: FullReport) -> Result<()> {
    if report.passed() {
        println!("  {what}: finite differences, Taylor and dot product pass");
        Ok(())
    } else {
        Err(format!("{what}: a gradient check failed:\n{report}").into())
    }
}

// ANCHOR: one_step
/// The three gradient checks on one step, for each way of writing it, and
/// the hand-written adjoint against Enzyme's.
fn one_step_checks() -> Result<()> {
    println!("1. one step");
    let Problem { op, u0, truth: p, .. } = problem();
    let opts = CheckParams::default();
    passed("Euler step (differentiable!)", check_all(&op, &u0, &p, &opts))?;
    passed("Euler step (stencil3!)", check_all(&FkppStencil(op), &u0, &p, &opts))?;
    passed("Heun step (lent scratch)", check_all(&FkppHeun(op), &u0, &p, &opts))?;
    passed("Euler step (hand adjoint)", check_all(&FkppHand(op), &u0, &p, &opts))?;

    // The hand adjoint and Enzyme's are two implementations of one VJP:
    // the JVP of one against the VJP of the other, to rounding.
    let tight = CheckParams { tol: 1e-12, ..opts };
    let between = dot_product_between(&FkppHand(op), &op, &u0, &p, &tight);
    if !between.verdict.passed() {
        return Err(format!("hand and Enzyme adjoints differ: {between}").into());
    }
    let w: Vec<f64> = (0..op.n).map(|i| (0.3 * i as f64).cos()).collect();
    let (enzyme, hand) = (op.vjp_new(&u0, &p, &w), FkppHand(op).vjp_new(&u0, &p, &w));
    let diff = enzyme.0.iter().zip(&hand.0).chain(enzyme.1.iter().zip(&hand.1)).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    println!("  hand vs Enzyme VJP: largest difference {diff:.1e}");

    // Their speed, measured here (not asserted: machines are noisy).
    let time = |f: &dyn Fn()| {
        let start = Instant::now();
        for _ in 0..2000 {
            f();
        }
        start.elapsed().as_secs_f64() / 2000.0
    };
    let t_fwd = time(&|| drop(std::hint::black_box(op.eval(&u0, &p))));
    let t_enzyme = time(&|| drop(std::hint::black_box(op.vjp_new(&u0, &p, &w))));
    let t_hand = time(&|| drop(std::hint::black_box(FkppHand(op).vjp_new(&u0, &p, &w))));
    println!("  forward {:.2} µs, Enzyme VJP {:.2} µs, hand VJP {:.2} µs", 1e6 * t_fwd, 1e6 * t_enzyme, 1e6 * t_hand);
    Ok(())
}
// ANCHOR_END: one_step

// ANCHOR: loss
/// The misfit to the observations, a term at each observed step:
/// `L = Σ_t ½‖u_t − obs_t‖²`. `AtSteps` takes the steps and a function
/// `f(t, u_t, grad) -> ℓ_t` that also writes `∂ℓ_t/∂u_t` into `grad`.
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

// ANCHOR_END: loss

// ANCHOR: rollout
/// A rollout of 60 steps from the first guess of the parameters, its loss and
/// gradient under each way of keeping the states for the backward pass.
fn rollout_and_its_gradient() -> Result<()> {
    println!("2. a rollout and its gradient");
    let pb = problem();
    let loss = misfit(&pb.observations);
    let rollout = Rollout::new(&pb.op, &pb.guess, STEPS)?;
    let mut first: Option<Vec<f64>> = None;
    for mode in [Checkpointing::Store, Checkpointing::periodic_sqrt(STEPS), Checkpointing::binomial_log(STEPS)] {
        let g = rollout.value_and_grad(&pb.u0, &loss, mode)?;
        println!(
            "  {mode}: L = {:.6e}, ∂L/∂p = [{:.6e}, {:.6e}], {} states held, {} step evaluations",
            g.loss, g.dp[0], g.dp[1], g.stats.peak_states, g.stats.step_evaluations
        );
        // Every mode computes the same operations on the same states.
        let all: Vec<f64> = g.dx0.iter().chain(&g.dp).copied().collect();
        if let Some(f) = &first
            && f.iter().zip(&all).any(|(a, b)| (a - b).abs() > 1e-12 * a.abs().max(1e-300))
        {
            return Err(format!("{mode} gives another gradient than storing every state").into());
        }
        first.get_or_insert(all);
    }
    Ok(())
}
// ANCHOR_END: rollout

// ANCHOR: through
/// The three checks through the whole rollout, with respect to the initial
/// state and the parameters at once: `RolloutLoss` is the map
/// `(u_0, p) ↦ L` as an operator.
fn checks_through_the_rollout() -> Result<()> {
    println!("3. checks through the rollout");
    let pb = problem();
    let loss = misfit(&pb.observations);
    let rollout = Rollout::new(&pb.op, &pb.guess, STEPS)?;
    let as_op = RolloutLoss::new(rollout, &pb.u0, &loss, Checkpointing::periodic_sqrt(STEPS), Wrt::Both)?;
    let (x, p) = as_op.point();
    passed("∂L/∂u0 and ∂L/∂p through 60 steps", check_all(&as_op, x, p, &CheckParams::default()))
}
// ANCHOR_END: through

// ANCHOR: fit
/// Recovers the parameters from the observations with the library's
/// trainer: the objective is `L(p)` with its gradient through the rollout,
/// the rule Adam, the learning rate decaying from 0.02 by 0.3 % per
/// iteration. Any other rule takes Adam's place unchanged (L-BFGS:
/// `Lbfgs::new(LbfgsParams::default())?`).
fn fit_with_adam() -> Result<()> {
    println!("4. fit [ν, r] with Adam");
    let pb = problem();
    let loss = misfit(&pb.observations);
    let mut p = pb.guess.to_vec();
    let first = Rollout::new(&pb.op, &p, STEPS)?.loss(&pb.u0, &loss)?;
    let objective = |_iteration: usize| -> std::result::Result<_, TrainError> {
        Ok(FnObjective {
            n: 2,
            f: |p: &[f64]| {
                let g = Rollout::new(&pb.op, p, STEPS)?.value_and_grad(&pb.u0, &loss, Checkpointing::Store)?;
                Ok((g.loss, g.dp))
            },
        })
    };
    let mut adam = Adam::new(AdamParams { lr: 0.02, ..AdamParams::default() });
    let schedule = Schedule::Exponential { start: 0.02, factor: 0.997 };
    let world = World::single();
    let trainer = Trainer::new(TrainerParams { iterations: 401, schedule, ..TrainerParams::default() }, &world);
    trainer.run(&mut adam, &mut p, objective, |row, _, _| {
        if row.iteration % 100 == 1 {
            println!("  iteration {:4}: L = {:.3e}", row.iteration, row.loss);
        }
        std::ops::ControlFlow::Continue(())
    })?;
    let last = Rollout::new(&pb.op, &p, STEPS)?.loss(&pb.u0, &loss)?;
    let error = p.iter().zip(&pb.truth).map(|(a, b)| ((a - b) / b).abs()).fold(0.0, f64::max);
    println!("  loss {first:.3e} → {last:.3e}; p = [{:.5}, {:.5}], truth {:?}, largest relative error {error:.1e}", p[0], p[1], pb.truth);
    if error > 1e-5 {
        return Err(format!("the fit did not recover the parameters (relative error {error:.1e})").into());
    }
    Ok(())
}
// ANCHOR_END: fit

//! The 2D solver-in-the-loop problem (flow past a disc): its step passes
//! the gradient checks on an oblong channel with an obstacle, the
//! reference's initial states and their downsampling keep the flow
//! divergence-free, the MAC gathers of the correction network pass the
//! checks, and one operator per thread gives the same batch gradient as a
//! single one.

use diffsim::nn::{Activation, presets};
use diffsim::op::{OperatorExt, PerThread};
use diffsim::rollout::{AtSteps, Checkpointing, Rollout};
use diffsim::train::{Coupled, Coupling, Sample, batch_gradient};
use diffsim_solvers::boundary::{Boundary, Profile, Side};
use diffsim_solvers::smoke::{MacGrid, Scheme, Solid, divergence, solid_cells};
use diffsim_studies::sol::SolProblem;
use diffsim_studies::wake::{WakeSetup, WakeStep};
use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::checks::{assert_passes, smoke_state};

fn channel(nx: usize, ny: usize) -> (MacGrid<2>, Vec<bool>) {
    let b = Boundary::CLOSED.with_lower(0, Side::Inflow(Profile::Uniform(0.7))).with_upper(0, Side::Outflow);
    let cfg = MacGrid::new([nx, ny]).with_boundary(b);
    let solid = solid_cells(&cfg, &[Solid::Ball { center: [3.0, 2.6], radius: 1.2 }]);
    (cfg, solid)
}

#[test]
fn the_wake_step_passes_all_checks_on_an_oblong_channel_with_a_disc() {
    let (cfg, solid) = channel(11, 6);
    let x = smoke_state(&cfg, 41);
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        assert_passes(&format!("WakeStep {scheme:?}"), &WakeStep::new(cfg, scheme, 0.5, 0.05, &solid, 1e-13), &x, &[]);
    }
}

fn max_divergence(cfg: &MacGrid<2>, x: &[f64], solid: &[bool]) -> f64 {
    let (_, [u, v]) = cfg.split(x);
    let mut d = vec![0.0; cfg.n_s()];
    divergence(cfg, [u, v], &mut d);
    d.iter().zip(solid).filter(|(_, s)| !**s).map(|(d, _)| d.abs()).fold(0.0, f64::max)
}

#[test]
fn reference_states_and_their_downsampling_stay_divergence_free() {
    let setup = WakeSetup { warmup: 2, ..WakeSetup::standard() };
    let fine = setup.fine();
    let x0 = setup.initial(&mut StdRng::seed_from_u64(3));
    // The curl of a stream function plus a uniform flow: exactly divergence-free.
    assert!(max_divergence(&fine, &x0, &vec![false; fine.n_s()]) < 1e-12);
    let coarse0 = setup.downsample(&x0);
    assert!(max_divergence(&setup.coarse, &coarse0, &vec![false; setup.coarse.n_s()]) < 1e-12);
    // After projected fine steps, the averaged coarse flow has no divergence
    // outside the (coarse) disc's neighbourhood either: fluxes add up.
    let traj = setup.reference(&x0, 1).unwrap();
    assert_eq!(traj.len(), 2);
    let solid = solid_cells(&setup.coarse, &[Solid::Ball { center: setup.center, radius: setup.radius + 1.5 }]);
    let d = max_divergence(&setup.coarse, &traj[1], &solid);
    assert!(d < 1e-4, "coarse divergence {d:e}");
    // The inflow arrives at the coarse inflow faces in coarse units.
    let (_, [u, _]) = setup.coarse.split(&traj[1]);
    assert!((u[0] - setup.speed).abs() < 1e-12, "{}", u[0]);
}

#[test]
fn mac_gathers_and_the_correction_network_pass_all_checks() {
    let (nx, ny) = (6, 4);
    let cfg = MacGrid::new([nx, ny]);
    let to = presets::mac_to_channels(nx, ny);
    let back = presets::channels_to_mac(nx, ny, None);
    let net = diffsim::nn::Net::new(vec![to, back]).unwrap();
    // The round trip keeps u on each cell's left face and v on its bottom face.
    let x = smoke_state(&cfg, 7);
    let y = net.eval(&x, &[]);
    let (_, [u, v]) = cfg.split(&y);
    let (_, [xu, xv]) = cfg.split(&x);
    assert!(y[..cfg.n_s()].iter().all(|&s| s == 0.0));
    assert_eq!((u[nx + 1 + 2], u[nx + 1 + nx], v[nx + 3], v[ny * nx + 3]), (xu[nx + 1 + 2], 0.0, xv[nx + 3], 0.0));
    let stack = presets::mac_conv_stack(nx, ny, &[2, 3, 2], 3, Activation::Tanh, None).unwrap();
    // A fresh correction network starts from the source solver: it outputs
    // zero although its last layer is a parameter-free gather.
    let zero = diffsim_studies::sol::initial_params(&stack, 1);
    assert!(zero.iter().any(|&w| w != 0.0));
    assert!(stack.eval(&x, &zero).iter().all(|&c| c == 0.0));
    let theta = crate::checks::state(diffsim::op::Operator::n_params(&stack), 5);
    assert_passes("mac_conv_stack", &stack, &x, &theta);
}

#[test]
fn one_operator_per_thread_gives_the_single_operators_batch_gradient() {
    let (cfg, solid) = channel(10, 6);
    let single = WakeStep::new(cfg, Scheme::SemiLagrangian, 0.5, 0.05, &solid, 1e-10);
    let shared = PerThread::new(|| WakeStep::new(cfg, Scheme::SemiLagrangian, 0.5, 0.05, &solid, 1e-10));
    let net = presets::mac_conv_stack(10, 6, &[2, 3, 2], 3, Activation::Tanh, None).unwrap();
    let theta = crate::checks::state(diffsim::op::Operator::n_params(&net), 9);
    let batch: Vec<Sample> = (0..6)
        .map(|k| {
            let x0 = smoke_state(&cfg, 60 + k);
            let targets = (0..3).map(|t| smoke_state(&cfg, 90 + 3 * k + t)).collect();
            Sample { x0, targets }
        })
        .collect();
    // The plain operator, one sample after another, with the same loss as
    // `batch_gradient` (mean over the loss steps and values).
    let run_single = || {
        let op = Coupled::new(&single, &[], &net, Coupling::Add).unwrap();
        let rollout = Rollout::new(&op, &theta, 3).unwrap();
        let scale = 1.0 / (3 * cfg.n_state()) as f64;
        let mut loss = 0.0;
        let mut grad = vec![0.0; theta.len()];
        for s in &batch {
            let l = AtSteps {
                steps: vec![1, 2, 3],
                f: |t: usize, x: &[f64], g: &mut [f64]| {
                    let mut v = 0.0;
                    for ((g, &x), &r) in g.iter_mut().zip(x).zip(&s.targets[t - 1]) {
                        *g = 2.0 * scale * (x - r);
                        v += scale * (x - r) * (x - r);
                    }
                    v
                },
            };
            let r = rollout.value_and_grad(&s.x0, &l, Checkpointing::Store).unwrap();
            loss += r.loss / batch.len() as f64;
            for (a, b) in grad.iter_mut().zip(&r.dp) {
                *a += b / batch.len() as f64;
            }
        }
        (loss, grad)
    };
    let op = Coupled::new(&shared, &[], &net, Coupling::Add).unwrap();
    let (loss, grad) = batch_gradient(&op, &theta, 3, &[1, 2, 3], &batch, Checkpointing::Store).unwrap();
    let (l1, g1) = run_single();
    assert!((loss - l1).abs() <= 1e-12 * l1.abs(), "{loss} vs {l1}");
    let err = grad.iter().zip(&g1).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    let scale = g1.iter().map(|b| b.abs()).fold(0.0, f64::max);
    assert!(err <= 1e-10 * scale, "gradient differs by {err:e} (scale {scale:e})");
    // Sizes pass through.
    assert_eq!(diffsim::op::Operator::n_in(&shared), cfg.n_state());
    let _ = WakeSetup::standard().source();
}

//! Checkpointed rollouts give the stored rollout's gradient; memory and
//! time of each mode are reported.

use std::time::Instant;

use diffsim::op::{OpName, Operator};
use diffsim::problems::burgers::P1;
use diffsim::rollout::{Argument, Checkpointing, Pass, Rollout, RolloutError};

#[test]
fn checkpointing_modes_agree_and_report_memory() {
    // Off a power of two on purpose.
    let p = P1::new(300, 777);
    let t = Instant::now();
    let stored = p.grad_enzyme(Checkpointing::Store).unwrap();
    let t_store = t.elapsed().as_secs_f64();
    let scale = stored.dx0.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let modes = [
        Checkpointing::Periodic { every: 1 },
        Checkpointing::Periodic { every: 7 },
        Checkpointing::periodic_sqrt(p.steps),
        Checkpointing::Periodic { every: 1000 },
        Checkpointing::Binomial { snapshots: 1 },
        Checkpointing::Binomial { snapshots: 3 },
        Checkpointing::binomial_log(p.steps),
    ];
    eprintln!("{:>14} {:>8} {:>12} {:>10} {:>10}", "mode", "states", "bytes", "step evals", "time ms");
    eprintln!(
        "{:>14} {:>8} {:>12} {:>10} {:>10.2}",
        "store",
        stored.stats.peak_states,
        stored.stats.peak_state_bytes,
        stored.stats.step_evaluations,
        t_store * 1e3
    );
    for mode in modes {
        for hand in [false, true] {
            let t = Instant::now();
            let g = if hand { p.grad_hand(mode) } else { p.grad_enzyme(mode) }.unwrap();
            let dt = t.elapsed().as_secs_f64();
            let err = g.dx0.iter().zip(&stored.dx0).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max) / scale;
            assert!(err <= 1e-13, "{mode} (hand = {hand}): relative difference {err:.2e} from the stored gradient");
            assert_eq!(g.loss, stored.loss);
            if !hand {
                eprintln!(
                    "{:>14} {:>8} {:>12} {:>10} {:>10.2}",
                    mode.to_string(),
                    g.stats.peak_states,
                    g.stats.peak_state_bytes,
                    g.stats.step_evaluations,
                    dt * 1e3
                );
            }
            // Memory bounds each mode promises.
            match mode {
                Checkpointing::Binomial { snapshots } => assert!(g.stats.peak_states <= snapshots + 2, "{mode}: {} states", g.stats.peak_states),
                // (P1's gradients pipeline when rayon has two threads,
                // which holds one more segment.)
                Checkpointing::Periodic { every } => {
                    assert!(g.stats.peak_states <= p.steps.div_ceil(every) + 2 * every + 1, "{mode}: {} states", g.stats.peak_states)
                }
                Checkpointing::Store => {}
            }
        }
    }
    // log T growth: binomial with ⌈log₂ T⌉ snapshots holds far fewer states
    // than T and recomputes a bounded multiple of T.
    let b = p.grad_hand(Checkpointing::binomial_log(p.steps)).unwrap();
    assert!(b.stats.peak_states <= 12, "{} states", b.stats.peak_states);
    assert!(b.stats.step_evaluations <= 6 * p.steps, "{} step evaluations", b.stats.step_evaluations);
}

#[test]
fn pipelined_gradient_equals_the_one_thread_gradient_bit_for_bit() {
    // Two threads even on a one-core machine, so that the pipeline runs.
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    let p = P1::new(96, 101);
    let hand = diffsim::problems::burgers::BurgersHand(p.cfg);
    let enzyme = diffsim::problems::burgers::BurgersEnzyme(p.cfg);
    let modes = [1, 2, 7, 10, 100, 101, 500].map(|every| Checkpointing::Periodic { every });
    for mode in modes.into_iter().chain([Checkpointing::Store, Checkpointing::binomial_log(p.steps)]) {
        for enzyme_op in [false, true] {
            let (serial, piped) = if enzyme_op {
                let r = Rollout::new(&enzyme, &[], p.steps).unwrap();
                (r.value_and_grad(&p.u0, &p.loss(), mode), pool.install(|| r.value_and_grad_pipelined_in(&mut Default::default(), &p.u0, &p.loss(), mode)))
            } else {
                let r = Rollout::new(&hand, &[], p.steps).unwrap();
                (r.value_and_grad(&p.u0, &p.loss(), mode), pool.install(|| r.value_and_grad_pipelined_in(&mut Default::default(), &p.u0, &p.loss(), mode)))
            };
            let (serial, piped) = (serial.unwrap(), piped.unwrap());
            assert_eq!(serial.loss, piped.loss, "{mode}");
            assert_eq!(serial.dx0, piped.dx0, "{mode} (enzyme = {enzyme_op})");
            assert_eq!(serial.stats.step_evaluations, piped.stats.step_evaluations, "{mode}");
        }
    }
}

/// Burgers' hand step whose VJP panics on its `n`-th call (counted from
/// 1), or whose recomputation panics at that forward call.
struct PanicsAt {
    op: diffsim::problems::burgers::BurgersHand,
    calls: std::sync::atomic::AtomicUsize,
    at: usize,
    in_vjp: bool,
}

impl PanicsAt {
    fn tick(&self, vjp: bool) {
        if vjp == self.in_vjp && self.calls.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1 == self.at {
            panic!("deliberate panic in call {}", self.at);
        }
    }
}

impl Operator for PanicsAt {
    fn n_in(&self) -> usize {
        self.op.n_in()
    }
    fn n_out(&self) -> usize {
        self.op.n_out()
    }
}

impl diffsim::op::Forward for PanicsAt {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        self.tick(false);
        self.op.forward(x, p, y)
    }
}

impl diffsim::op::Vjp for PanicsAt {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        self.tick(true);
        self.op.vjp(x, p, dy, dx, dp)
    }
}

#[test]
fn a_panic_on_either_thread_of_the_two_thread_backward_pass_reaches_the_caller() {
    // Both threads wait on each other once per segment: a panic in one must
    // stop the other rather than leave it waiting for ever.
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    let p = P1::new(64, 200);
    let mode = Checkpointing::Periodic { every: 10 };
    // Forward calls: 200 in the forward pass, then recomputations; VJP calls
    // 1..=200. Early, middle and late in the backward pass.
    for (at, in_vjp) in [(205, false), (290, false), (3, true), (95, true), (199, true)] {
        let op = PanicsAt { op: diffsim::problems::burgers::BurgersHand(p.cfg), calls: 0.into(), at, in_vjp };
        let r = Rollout::new(&op, &[], p.steps).unwrap();
        let out = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            pool.install(|| r.value_and_grad_pipelined_in(&mut Default::default(), &p.u0, &p.loss(), mode))
        }));
        let err = out.expect_err("the panic reaches the caller");
        let msg = err.downcast_ref::<String>().map(String::as_str).unwrap_or("");
        assert_eq!(msg, format!("deliberate panic in call {at}"), "at {at}, vjp {in_vjp}");
    }
    // And the pool still works afterwards.
    let g = pool.install(|| p.grad_hand_in(&mut Default::default(), mode)).unwrap();
    assert!(g.loss.is_finite());
}

#[test]
fn rollout_edge_cases() {
    let p = P1::new(5, 1);
    for mode in [Checkpointing::Store, Checkpointing::Periodic { every: 3 }, Checkpointing::Binomial { snapshots: 2 }] {
        let g = p.grad_hand(mode).unwrap();
        assert_eq!(g.stats.steps, 1);
    }
    let zero = P1::new(5, 0);
    let g = zero.grad_enzyme(Checkpointing::binomial_log(0)).unwrap();
    // With no steps the gradient is the loss gradient itself: dx·(u0 − u*).
    for ((d, u), t) in g.dx0.iter().zip(&zero.u0).zip(&zero.target) {
        assert!((d - zero.cfg.dx * (u - t)).abs() < 1e-15);
    }
}

#[test]
fn bad_inputs_are_errors() {
    let p = P1::new(16, 10);
    let op = diffsim::problems::burgers::BurgersHand(p.cfg);
    let r = Rollout::new(&op, &[], 10).unwrap();
    let err = r.value_and_grad(&[0.0; 15], &p.loss(), Checkpointing::Store).unwrap_err();
    assert_eq!(err, RolloutError::Length { what: Argument::X0, got: 15, expected: 16 });
    assert!(matches!(Rollout::new(&op, &[1.0], 3), Err(RolloutError::Length { what: Argument::P, .. })));
    // A state that blows up is reported with the step where it first did.
    let mut u0 = p.u0.clone();
    u0[3] = f64::NAN;
    let err = r.value_and_grad(&u0, &p.loss(), Checkpointing::Store).unwrap_err();
    assert_eq!(err, RolloutError::NonFinite { pass: Pass::Forward, step: 0, operator: OpName::new("BurgersHand") });
    assert!(err.to_string().contains("forward pass at step 0 (operator BurgersHand)"), "{err}");
    // In a solver coupled to a network, the part that produced it is named.
    let net = diffsim::nn::presets::mlp(&[16, 8, 16], diffsim::nn::Activation::Tanh).unwrap();
    let mut theta = vec![0.0; net.n_params()];
    theta[0] = f64::NAN;
    let coupled = diffsim::train::Coupled::new(&op, &[], &net, diffsim::train::Coupling::Add).unwrap();
    let err = Rollout::new(&coupled, &theta, 4).unwrap().final_state(&p.u0).unwrap_err();
    assert_eq!(err, RolloutError::NonFinite { pass: Pass::Forward, step: 0, operator: OpName::new("Net") });
    // A NaN entering the adjoint is found at the backward pass's periodic
    // check and then named exactly, under every checkpointing mode.
    let nan_at = |t: usize, x: &[f64], g: &mut [f64]| {
        for (g, &a) in g.iter_mut().zip(x) {
            *g = if t == 37 { f64::NAN } else { a };
        }
        0.0
    };
    let loss = diffsim::rollout::AtSteps { steps: vec![37, 100], f: nan_at };
    let r100 = Rollout::new(&op, &[], 100).unwrap();
    for mode in [Checkpointing::Store, Checkpointing::Periodic { every: 10 }, Checkpointing::binomial_log(100)] {
        let err = r100.value_and_grad(&p.u0, &loss, mode).unwrap_err();
        assert_eq!(err, RolloutError::NonFinite { pass: Pass::Backward, step: 37, operator: OpName::new("BurgersHand") }, "{mode}");
    }
    assert!("binomial:0".parse::<Checkpointing>().is_err());
    assert!("sometimes".parse::<Checkpointing>().is_err());
    assert_eq!("periodic:5".parse::<Checkpointing>(), Ok(Checkpointing::Periodic { every: 5 }));
}

#[test]
fn losses_at_listed_steps_and_parameters_per_step_under_every_checkpointing() {
    use diffsim::op::{AddParams, Chain, Effect};
    use diffsim::rollout::AtSteps;
    // A Burgers step followed by a per-step source (a control): the loss
    // at steps 2, 5 and 7 of 7, differentiated with respect to the initial
    // state and every step's source.
    let p1 = P1::new(16, 7);
    let n = 16;
    let ops: Vec<Box<dyn Effect>> = vec![Box::new(diffsim::problems::burgers::BurgersHand(p1.cfg)), Box::new(AddParams { n, range: 0..n, scale: 0.1 })];
    let step = Chain::new(ops);
    let p: Vec<f64> = (0..7 * n).map(|k| ((k as f64) * 0.37).sin()).collect();
    let loss = AtSteps {
        steps: vec![2, 5, 7],
        f: |t: usize, x: &[f64], g: &mut [f64]| -> f64 {
            let mut v = 0.0;
            for (i, (g, x)) in g.iter_mut().zip(x).enumerate() {
                let d = x - 0.1 * t as f64 * (i as f64).cos();
                *g = d;
                v += 0.5 * d * d;
            }
            v
        },
    };
    let r = Rollout::per_step(&step, &p, 7).unwrap();
    let modes = [Checkpointing::Store, Checkpointing::Periodic { every: 3 }, Checkpointing::Binomial { snapshots: 2 }];
    let all: Vec<_> = modes.iter().map(|&m| r.value_and_grad(&p1.u0, &loss, m).unwrap()).collect();
    for g in &all[1..] {
        assert_eq!(g.loss, all[0].loss);
        assert_eq!(g.dx0, all[0].dx0);
        assert_eq!(g.dp, all[0].dp);
    }
    assert_eq!(all[0].dp.len(), 7 * n);
    assert!((r.loss(&p1.u0, &loss).unwrap() - all[0].loss).abs() < 1e-14 * all[0].loss);
    // Against central differences, in the first, a middle and the last step.
    let h = 1e-6;
    for i in [3, 4 * n + 7, 6 * n + 15] {
        let (mut up, mut down) = (p.clone(), p.clone());
        up[i] += h;
        down[i] -= h;
        let value = |q: &[f64]| Rollout::per_step(&step, q, 7).unwrap().loss(&p1.u0, &loss).unwrap();
        let fd = (value(&up) - value(&down)) / (2.0 * h);
        assert!((fd - all[0].dp[i]).abs() < 1e-6 * fd.abs().max(1e-3), "p[{i}]: {fd} vs {}", all[0].dp[i]);
    }
    // A per-step parameter vector of the wrong length is an error.
    assert!(Rollout::per_step(&step, &p[..n], 7).is_err());
}

#[test]
fn a_repeated_step_is_an_operator_of_the_initial_state_and_the_shared_parameters() {
    use diffsim::check::{CheckParams, check_all};
    use diffsim::op::{AddParams, Chain, Effect, Forward, Jvp, Vjp};
    use diffsim::rollout::Repeat;
    // A Burgers step then a source held the same at every step (the
    // parameters): x_T as a function of x_0 and the source.
    let (n, steps) = (16, 9);
    let p1 = P1::new(n, steps);
    let step = || {
        let ops: Vec<Box<dyn Effect>> = vec![Box::new(diffsim::problems::burgers::BurgersHand(p1.cfg)), Box::new(AddParams { n, range: 0..n, scale: 0.1 })];
        Chain::new(ops)
    };
    let p: Vec<f64> = (0..n).map(|k| ((k as f64) * 0.37).sin()).collect();
    let repeat = Repeat::new(step(), steps).unwrap();
    assert_eq!((repeat.n_in(), repeat.n_out(), repeat.n_params()), (n, n, n));
    // The forward pass is the rollout's final state.
    let mut y = vec![0.0; n];
    repeat.forward(&p1.u0, &p, &mut y);
    let op = step();
    assert_eq!(y, Rollout::new(&op, &p, steps).unwrap().final_state(&p1.u0).unwrap());
    // The VJP against central differences of one output weighted by w.
    let w: Vec<f64> = (0..n).map(|k| ((k as f64) * 1.3).cos()).collect();
    let (mut dx, mut dp, mut dy) = (vec![0.0; n], vec![0.0; n], w.clone());
    repeat.vjp(&p1.u0, &p, &mut dy, &mut dx, &mut dp);
    assert!(dy.iter().all(|&v| v == 0.0), "the seed is consumed");
    let value = |x: &[f64], q: &[f64]| {
        let mut y = vec![0.0; n];
        repeat.forward(x, q, &mut y);
        y.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
    };
    let h = 1e-6;
    for i in [0, 7, 15] {
        let (mut up, mut down) = (p1.u0.clone(), p1.u0.clone());
        up[i] += h;
        down[i] -= h;
        let fd = (value(&up, &p) - value(&down, &p)) / (2.0 * h);
        assert!((fd - dx[i]).abs() < 1e-7 * fd.abs().max(1e-2), "x0[{i}]: {fd} vs {}", dx[i]);
        let (mut up, mut down) = (p.clone(), p.clone());
        up[i] += h;
        down[i] -= h;
        let fd = (value(&p1.u0, &up) - value(&p1.u0, &down)) / (2.0 * h);
        assert!((fd - dp[i]).abs() < 1e-7 * fd.abs().max(1e-2), "p[{i}]: {fd} vs {}", dp[i]);
    }
    // Every checkpointing gives the same bits as the budget's choice.
    for mode in [Checkpointing::Store, Checkpointing::Periodic { every: 3 }, Checkpointing::Binomial { snapshots: 2 }] {
        let r = Repeat::new(step(), steps).unwrap().with_checkpointing(mode);
        let (mut dx2, mut dp2, mut dy) = (vec![0.0; n], vec![0.0; n], w.clone());
        r.vjp(&p1.u0, &p, &mut dy, &mut dx2, &mut dp2);
        assert_eq!((&dx2, &dp2), (&dx, &dp), "{mode}");
    }
    // The JVP carries both tangents: ⟨w, J·(tx, tp)⟩ = ⟨dx, tx⟩ + ⟨dp, tp⟩.
    let (tx, tp): (Vec<f64>, Vec<f64>) = ((0..n).map(|k| (k as f64 * 0.7).sin()).collect(), (0..n).map(|k| (k as f64 * 0.2).cos()).collect());
    let (mut y2, mut ty) = (vec![0.0; n], vec![0.0; n]);
    repeat.jvp(&p1.u0, &p, &tx, &tp, &mut y2, &mut ty);
    assert_eq!(y2, y);
    let left: f64 = ty.iter().zip(&w).map(|(a, b)| a * b).sum();
    let right: f64 = dx.iter().zip(&tx).chain(dp.iter().zip(&tp)).map(|(a, b)| a * b).sum();
    assert!((left - right).abs() < 1e-12 * left.abs(), "{left} vs {right}");
    // And the library's three checks pass on it.
    let report = check_all(&repeat, &p1.u0, &p, &CheckParams::default());
    assert!(report.passed(), "{report}");
    // Bad uses: not a state map, no steps; a state that is not finite is
    // the rollout's error, kept for the caller.
    struct Total;
    impl Operator for Total {
        fn n_in(&self) -> usize {
            3
        }
        fn n_out(&self) -> usize {
            1
        }
    }
    impl Forward for Total {
        fn forward(&self, x: &[f64], _: &[f64], y: &mut [f64]) {
            y[0] = x.iter().sum();
        }
    }
    assert!(matches!(Repeat::new(Total, 2), Err(RolloutError::NotAStateMap { n_in: 3, n_out: 1 })));
    assert!(matches!(Repeat::new(step(), 0), Err(RolloutError::Length { what: Argument::Steps, got: 0, expected: 1 })));
    let infinite = vec![f64::INFINITY; n];
    repeat.forward(&p1.u0, &infinite, &mut y);
    assert!(y.iter().all(|v| v.is_nan()));
    assert!(matches!(repeat.take_rollout_error(), Some(RolloutError::NonFinite { pass: Pass::Forward, .. })), "a non-finite state is an error");
    assert!(repeat.take_rollout_error().is_none(), "taken once");
}

//! The one criterion binary: a group per benchmark problem, with forward,
//! Enzyme gradient and hand-written gradient as members.

use criterion::{BenchmarkId, Criterion, criterion_group};
use diffsim::op::Vjp;
use diffsim::problems::burgers::{BurgersEnzyme, BurgersEnzymeWholeStep, BurgersHand, P1};
use diffsim::problems::smoke::P2;
use diffsim::rollout::{Checkpointing, Workspace};
use diffsim_solvers::burgers::{self, Burgers1d};
use diffsim_solvers::smoke::Preconditioner;

/// One P1 size: forward, Enzyme gradient (stencil map), Enzyme gradient
/// (whole step) and hand-written gradient.
fn p1_size(c: &mut Criterion, n: usize, steps: usize) {
    let mut g = c.benchmark_group("p1_burgers1d");
    g.sample_size(10);
    let p = P1::new(n, steps);
    let mode = Checkpointing::periodic_sqrt(steps);
    let size = format!("{n}x{steps}");
    g.bench_function(BenchmarkId::new("forward", &size), |b| b.iter(|| std::hint::black_box(p.value().unwrap())));
    g.bench_function(BenchmarkId::new("enzyme_grad", &size), |b| b.iter(|| std::hint::black_box(p.grad_enzyme(mode).unwrap())));
    g.bench_function(BenchmarkId::new("enzyme_whole_step_grad", &size), |b| b.iter(|| std::hint::black_box(p.grad_enzyme_whole_step(mode).unwrap())));
    g.bench_function(BenchmarkId::new("hand_grad", &size), |b| b.iter(|| std::hint::black_box(p.grad_hand(mode).unwrap())));
    g.finish();
}

fn p1(c: &mut Criterion) {
    // The sizes S, M, L of docs/benchmarks.md. (Reading them from the solvers'
    // `P1_SIZES` table here aborted rustc's Enzyme type trees; docs/pitfalls.md.)
    for (n, steps) in [(256, 256), (2048, 2048), (16384, 1000)] {
        p1_size(c, n, steps);
    }
}

/// One step at size L: forward and VJP of each implementation, so that the
/// per-step costs behind the rollout numbers are visible.
fn p1_step(c: &mut Criterion) {
    let cfg = Burgers1d::p1(16384);
    let x = burgers::p1_initial(&cfg);
    let mut g = c.benchmark_group("p1_step_16384");
    step_pair(&mut g, "enzyme_stencil", &BurgersEnzyme(cfg), &x);
    step_pair(&mut g, "enzyme_whole_step", &BurgersEnzymeWholeStep(cfg), &x);
    step_pair(&mut g, "hand", &BurgersHand(cfg), &x);
    g.finish();
}

fn step_pair<O: Vjp>(g: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>, name: &str, op: &O, x: &[f64]) {
    let n = x.len();
    let (mut y, mut seed, mut dx) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    g.bench_function(BenchmarkId::new("forward", name), |b| b.iter(|| op.forward(x, &[], std::hint::black_box(&mut y))));
    g.bench_function(BenchmarkId::new("vjp", name), |b| {
        b.iter(|| {
            seed.copy_from_slice(x);
            op.vjp(x, &[], &mut seed, std::hint::black_box(&mut dx), &mut []);
        })
    });
    g.bench_function(BenchmarkId::new("vjp_overwrite", name), |b| {
        b.iter(|| {
            seed.copy_from_slice(x);
            op.vjp_overwrite(x, &[], &mut seed, std::hint::black_box(&mut dx), &mut []);
        })
    });
}

/// P2 smoke2d at 64² and 128², 20 steps: forward and gradient, with and
/// without preconditioning, with MIC(0) and with multigrid.
fn p2(c: &mut Criterion) {
    let mut g = c.benchmark_group("p2_smoke2d");
    g.sample_size(10);
    for n in [64, 128] {
        for precond in [Preconditioner::Multigrid, Preconditioner::None, Preconditioner::Mic0] {
            let p = P2::new(n, 20, precond);
            let size = format!("{n}x20_{precond}");
            g.bench_function(BenchmarkId::new("forward", &size), |b| b.iter(|| std::hint::black_box(p.value().unwrap())));
            let mut ws = Workspace::new();
            g.bench_function(BenchmarkId::new("grad", &size), |b| b.iter(|| std::hint::black_box(p.grad_in(&mut ws, Checkpointing::Store).unwrap())));
        }
    }
    g.finish();
}

/// P4 smoke3d at 32³ × 10 (the spec's first size): forward, Enzyme gradient,
/// hand-adjoint gradient.
fn p4(c: &mut Criterion) {
    use diffsim::problems::smoke::P4;
    let mut g = c.benchmark_group("p4_smoke3d");
    g.sample_size(10);
    let p = P4::new(32, 10, Preconditioner::Multigrid);
    g.bench_function("forward/32x10", |b| b.iter(|| std::hint::black_box(p.value().unwrap())));
    let mut ws = Workspace::new();
    g.bench_function("grad/32x10", |b| b.iter(|| std::hint::black_box(p.grad_in(&mut ws, Checkpointing::Store).unwrap())));
    let hand = P4::new(32, 10, Preconditioner::Multigrid).with_hand_adjoint();
    g.bench_function("hand_grad/32x10", |b| b.iter(|| std::hint::black_box(hand.grad_in(&mut ws, Checkpointing::Store).unwrap())));
    g.finish();
}

/// P3 sol1d: one training iteration (16 coupled steps, batch 32, Adam).
fn p3(c: &mut Criterion) {
    let mut g = c.benchmark_group("p3_sol1d");
    g.sample_size(20);
    use diffsim_studies::p3::{Dtype, P3};
    for dtype in [Dtype::F64, Dtype::F32, Dtype::Mixed] {
        let mut p = P3::new(0, dtype);
        g.bench_function(format!("iteration_{}", dtype.name()), |b| b.iter(|| std::hint::black_box(p.iteration().unwrap())));
    }
    g.finish();
}

criterion_group!(benches, p1, p1_step, p2, p3, p4, solver_parts, periodic_projection, periodic_advection, scene_effects, nn_layers, hig_adam);

/// criterion's `main`, after the vector-instruction cap of `DIFFSIM_MAX_ISA`
/// (as the command line reads it).
fn main() {
    if let Err(e) = diffsim_solvers::simd::max_isa_from_env() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
    benches();
    Criterion::default().configure_from_args().final_summary();
}

/// The projection of a fully periodic box, by FFT against conjugate
/// gradients to 1e-8 preconditioned by multigrid (the aggregation V-cycle),
/// at 64², 128² and 32³ (docs/fluids.md, "Periodic boxes").
fn periodic_projection(c: &mut Criterion) {
    let mut g = c.benchmark_group("periodic_projection");
    g.sample_size(20);
    for n in [64, 128] {
        periodic_projection_at(&mut g, [n, n]);
    }
    periodic_projection_at(&mut g, [32; 3]);
    g.finish();
}

/// [`periodic_projection`] on a box of `n` cells.
fn periodic_projection_at<const D: usize>(g: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>, n: [usize; D]) {
    use diffsim_solvers::boundary::{Boundary, Side};
    use diffsim_solvers::mac::fft::FftProjection;
    use diffsim_solvers::smoke::{self, MacGrid, PressureSolver, ProjectScratch};
    let cfg = MacGrid::new(n).with_boundary(Boundary::all(Side::Periodic));
    let x: Vec<f64> = (0..cfg.n_state()).map(|k| ((k as f64) * 0.618).fract() - 0.5).collect();
    let mut y = x.clone();
    let mut solver = PressureSolver::new(&cfg, 1e-8, 5000, Preconditioner::Multigrid);
    let mut scratch = ProjectScratch::new(cfg.n_s());
    g.bench_function(BenchmarkId::new(format!("cg_{D}d"), n[0]), |b| {
        b.iter(|| {
            y.copy_from_slice(&x);
            smoke::project(&cfg, &mut y, &mut solver, &mut scratch).unwrap()
        })
    });
    let mut fft = FftProjection::new(n);
    g.bench_function(BenchmarkId::new(format!("fft_{D}d"), n[0]), |b| {
        b.iter(|| {
            y.copy_from_slice(&x);
            fft.project(cfg.split_mut(&mut y).1)
        })
    });
}

/// The Navier–Stokes step's advection on a fully periodic box (MacCormack,
/// unlimited, Courant 0.5): the general traces against the traces shorter
/// than a cell (baseline x86-64 and the widest vectors), forward, and the
/// latter's adjoint by Enzyme (the operator's VJP) against the hand-written
/// one, at 64² and 32³ (docs/navier-stokes.md).
fn periodic_advection(c: &mut Criterion) {
    // As the command line and the Python package's benchmark script: the
    // generated adjoints' tapes reused, not mapped afresh per call (it stays
    // on for the groups after this one).
    diffsim::memory::keep_freed_memory();
    let mut g = c.benchmark_group("periodic_advection");
    g.sample_size(20);
    periodic_advection_at(&mut g, [64, 64]);
    periodic_advection_at(&mut g, [32; 3]);
    g.finish();
}

/// [`periodic_advection`] on a box of `n` cells.
fn periodic_advection_at<const D: usize>(g: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>, n: [usize; D])
where
    diffsim::navier_stokes::AdvectVelocity<D>: Vjp,
{
    use diffsim::navier_stokes::AdvectVelocity;
    use diffsim_solvers::boundary::{Boundary, Side};
    use diffsim_solvers::mac::periodic::refresh_periodic_copies;
    use diffsim_solvers::smoke::{self, MacGrid, Scheme};
    let cfg = MacGrid::new(n).with_boundary(Boundary::all(Side::Periodic));
    let scheme = Scheme::MacCormack { limiter: false };
    let mut x: Vec<f64> = (0..cfg.n_vel()).map(|k| ((k as f64) * 0.618).fract() - 0.5).collect();
    refresh_periodic_copies(&cfg, &mut x);
    // Courant 0.5: the largest face moves half a cell.
    let dt = 0.5 / x.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let mut y = vec![0.0; x.len()];
    let mut scratch = vec![0.0; smoke::advect_velocity_scratch_len(&cfg, scheme).max(smoke::advect_velocity_near_scratch_len(&cfg))];
    g.bench_function(BenchmarkId::new(format!("traces_forward_{D}d"), n[0]), |b| {
        b.iter(|| {
            smoke::advect_velocity(&cfg, scheme, dt, &x, &mut y, &mut scratch);
            refresh_periodic_copies(&cfg, &mut y);
        })
    });
    g.bench_function(BenchmarkId::new(format!("near_forward_{D}d"), n[0]), |b| {
        b.iter(|| smoke::advect_velocity_near(&cfg, scheme, dt, &x, &mut y, &mut scratch))
    });
    g.bench_function(BenchmarkId::new(format!("near_widest_forward_{D}d"), n[0]), |b| {
        b.iter(|| smoke::advect_velocity_near_widest(&cfg, scheme, dt, &x, &mut y, &mut scratch))
    });
    let op = AdvectVelocity { grid: cfg, h: 1.0, scheme };
    let w: Vec<f64> = (0..x.len()).map(|k| ((k as f64) * 0.377).fract() - 0.5).collect();
    let (mut dx, mut dp) = (vec![0.0; x.len()], [0.0]);
    g.bench_function(BenchmarkId::new(format!("near_vjp_enzyme_{D}d"), n[0]), |b| {
        b.iter(|| {
            dx.fill(0.0);
            op.vjp(&x, &[dt], &mut w.clone(), &mut dx, &mut dp)
        })
    });
    g.bench_function(BenchmarkId::new(format!("near_vjp_hand_{D}d"), n[0]), |b| {
        b.iter(|| {
            dx.fill(0.0);
            smoke::advect_velocity_near_adjoint(&cfg, scheme, dt, &x, &w, &mut dx)
        })
    });
}

/// One multigrid V-cycle and one plain CG matrix product at 64² and 128²,
/// the costs behind the P2 solve times.
fn solver_parts(c: &mut Criterion) {
    use diffsim_solvers::multigrid::Multigrid;
    use diffsim_solvers::smoke::apply_pressure_matrix;
    let mut g = c.benchmark_group("pressure_solver_parts");
    for n in [64, 128] {
        let r: Vec<f64> = (0..n * n).map(|k| ((k as f64) * 0.618).fract() - 0.5).collect();
        let mut z = vec![0.0; n * n];
        let mut mg = Multigrid::new(n);
        g.bench_function(BenchmarkId::new("vcycle", n), |b| b.iter(|| mg.apply(&r, std::hint::black_box(&mut z))));
        g.bench_function(BenchmarkId::new("matvec", n), |b| b.iter(|| apply_pressure_matrix(n, n, &r, std::hint::black_box(&mut z))));
    }
    g.finish();
}

/// The plume scene's step against its effects one by one, each at the
/// state it sees inside the step (after 30 steps of flow): the per-effect
/// times add up to the step's (`diffsim run --profile` prints the same
/// split for any scene).
fn scene_effects(c: &mut Criterion) {
    use diffsim::op::Forward;
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/plume.toml");
    let mut scene = diffsim::scene::Scene::load(&path).expect("scenes/plume.toml");
    scene.steps = 30;
    let x = scene.run(|_, _| {}).expect("the plume runs");
    let mut g = c.benchmark_group("scene_effects_plume");
    g.sample_size(20);
    let mut y = vec![0.0; x.len()];
    g.bench_function("whole_step", |b| b.iter(|| scene.step.forward(&x, &scene.params, std::hint::black_box(&mut y))));
    let mut input = x.clone();
    for (e, op) in scene.step.ops().iter().enumerate() {
        let p = &scene.params[scene.step.param_range(e)];
        let at = input.clone();
        g.bench_function(BenchmarkId::new("effect", format!("{e}_{}", scene.effects[e])), |b| b.iter(|| op.forward(&at, p, std::hint::black_box(&mut y))));
        op.forward(&at, p, &mut y);
        input.copy_from_slice(&y);
    }
    g.finish();
}

/// Dense and 1D convolution layers: forward, hand-written VJP (the default
/// in `nn::Layer`) and Enzyme-generated VJP, at the sizes of the Burgers
/// correction network (P3's) and of the oscillator MLP.
fn nn_layers(c: &mut Criterion) {
    use diffsim::nn::enzyme::{Conv1dEnzyme, DenseEnzyme};
    use diffsim::nn::{Conv1d, Layer, Net, Padding};
    use diffsim::op::{Forward, Operator};
    let mut g = c.benchmark_group("nn_layers");
    let vjp_of = |op: &dyn diffsim::op::Effect, x: &[f64], p: &[f64], dx: &mut [f64], dp: &mut [f64]| {
        let mut seed = vec![1.0; op.n_out()];
        op.vjp(x, p, &mut seed, dx, dp);
    };
    let conv = Conv1d { c_in: 32, c_out: 32, k: 5, len: 32, padding: Padding::Periodic };
    let dense_sizes = vec![(20usize, 20usize), (256, 256)];
    for (n_in, n_out) in dense_sizes {
        let hand = Net::new(vec![Layer::Dense { n_in, n_out }]).unwrap();
        let enz = DenseEnzyme { n_in, n_out };
        let p: Vec<f64> = (0..hand.n_params()).map(|k| ((k as f64) * 0.37).sin() * 0.1).collect();
        let x: Vec<f64> = (0..n_in).map(|k| ((k as f64) * 0.11).cos()).collect();
        let (mut dx, mut dp, mut y) = (vec![0.0; n_in], vec![0.0; p.len()], vec![0.0; n_out]);
        let size = format!("{n_in}x{n_out}");
        g.bench_function(BenchmarkId::new("dense_forward", &size), |b| b.iter(|| hand.forward(&x, &p, std::hint::black_box(&mut y))));
        g.bench_function(BenchmarkId::new("dense_vjp_hand", &size), |b| b.iter(|| vjp_of(&hand, &x, &p, &mut dx, &mut dp)));
        g.bench_function(BenchmarkId::new("dense_vjp_enzyme", &size), |b| b.iter(|| vjp_of(&enz, &x, &p, &mut dx, &mut dp)));
    }
    let hand = Net::new(vec![Layer::Conv1d(conv)]).unwrap();
    let enz = Conv1dEnzyme(conv);
    let p: Vec<f64> = (0..hand.n_params()).map(|k| ((k as f64) * 0.37).sin() * 0.1).collect();
    let x: Vec<f64> = (0..hand.n_in()).map(|k| ((k as f64) * 0.11).cos()).collect();
    let (mut dx, mut dp, mut y) = (vec![0.0; x.len()], vec![0.0; p.len()], vec![0.0; hand.n_out()]);
    g.bench_function("conv1d_32x32_k5_forward", |b| b.iter(|| hand.forward(&x, &p, std::hint::black_box(&mut y))));
    g.bench_function("conv1d_32x32_k5_vjp_hand", |b| b.iter(|| vjp_of(&hand, &x, &p, &mut dx, &mut dp)));
    g.bench_function("conv1d_32x32_k5_vjp_enzyme", |b| b.iter(|| vjp_of(&enz, &x, &p, &mut dx, &mut dp)));
    // conv2d: the blocked kernels against the plain loops they replaced.
    use diffsim_solvers::nn as kernel;
    let s = diffsim::nn::Conv2d { c_in: 16, c_out: 16, k: 3, nx: 32, ny: 32, padding: Padding::Zero };
    let w: Vec<f64> = (0..s.n_weights()).map(|k| ((k as f64) * 0.37).sin() * 0.1).collect();
    let b = vec![0.1; 16];
    let x: Vec<f64> = (0..16 * 32 * 32).map(|k| ((k as f64) * 0.11).cos()).collect();
    let (mut y, mut gx, mut gw, mut gb) = (vec![0.0; x.len()], vec![0.0; x.len()], vec![0.0; w.len()], vec![0.0; 16]);
    g.bench_function("conv2d_16x16_k3_32x32_forward", |bch| bch.iter(|| kernel::conv2d(&s, &w, &b, &x, std::hint::black_box(&mut y))));
    g.bench_function("conv2d_16x16_k3_32x32_forward_plain", |bch| bch.iter(|| kernel::conv2d_simple(&s, &w, &b, &x, std::hint::black_box(&mut y))));
    g.bench_function("conv2d_16x16_k3_32x32_vjp", |bch| bch.iter(|| kernel::conv2d_adjoint(&s, &w, &x, &y, &mut gx, &mut gw, &mut gb)));
    g.bench_function("conv2d_16x16_k3_32x32_vjp_plain", |bch| bch.iter(|| kernel::conv2d_adjoint_simple(&s, &w, &x, &y, &mut gx, &mut gw, &mut gb)));
    g.finish();
}

/// `diffsim bench hig`'s Adam update on a published HIG problem: its
/// data, network, batch and learning rate.
fn adam_update(g: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>, label: &str, cfg: diffsim_studies::oscillators::OscParams) {
    use diffsim::train::hig::loss_and_gradient;
    let (data, _) = diffsim_studies::oscillators::datasets(&cfg);
    let net = cfg.network();
    let mut t = cfg.initial_params(&net);
    let mut adam = diffsim::train::Optimizer::adam(cfg.adam_lr);
    let batch = &data[..cfg.adam_batch];
    g.bench_function(BenchmarkId::new("adam_update", label), |b| {
        b.iter(|| {
            let (_, grad) = loss_and_gradient(&cfg.problem, &net, &t, batch);
            adam.step(&mut t, &grad);
        })
    });
}

/// The gradient of an Adam update on both published HIG problems, whole
/// and in its parts: the network's batched forward and VJP, and the
/// physics' forward and Enzyme VJP for every sample on one thread, sample
/// by sample and through the lane form; and the whole Adam update.
fn hig_adam(c: &mut Criterion) {
    use diffsim::nn::Activation;
    use diffsim::problems::oscillators::Oscillators;
    let mut g = c.benchmark_group("hig_adam");
    // The whole Adam update of `diffsim bench hig` on both published
    // problems (one call each: an array of tuples iterated by value aborts
    // Enzyme's type analysis in this flagged crate).
    adam_update(&mut g, "linear", diffsim_studies::oscillators::OscParams::linear(1.0));
    adam_update(&mut g, "nonlinear", diffsim_studies::oscillators::OscParams::nonlinear(1.0));
    // The linear problem: batch 256, the MLP 4→20→20→20→24 with tanh, 24
    // steps; the nonlinear one: batch 512, 4→20→20→20→96 with ReLU, 96.
    hig_adam_parts(&mut g, "linear_256", &Oscillators::linear(), 256, Activation::Tanh);
    hig_adam_parts(&mut g, "nonlinear_512", &Oscillators::nonlinear(), 512, Activation::Relu);
    g.finish();
}

/// The parts of one Adam update's gradient on `physics` with a batch of
/// `batch_len` samples (synthetic states; the timings do not depend on
/// them).
fn hig_adam_parts(
    g: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>,
    label: &str,
    physics: &diffsim::problems::oscillators::Oscillators,
    batch_len: usize,
    activation: diffsim::nn::Activation,
) {
    use diffsim::nn::{Init, presets};
    use diffsim::op::{Forward, Operator};
    use diffsim::train::hig::{ControlSample, loss_and_gradient};
    use rand::SeedableRng;
    let steps = physics.n_params();
    let net = presets::mlp(&[4, 20, 20, 20, steps], activation).unwrap();
    let theta = net.init(&mut rand::rngs::StdRng::seed_from_u64(1), Init::Glorot);
    let batch: Vec<ControlSample> = (0..batch_len)
        .map(|k| {
            let x: Vec<f64> = (0..4).map(|i| (0.5 + 0.4 * ((k * 4 + i) as f64 * 0.37).sin()).abs()).collect();
            ControlSample { x0: x.clone(), target: x }
        })
        .collect();
    let inputs: Vec<f64> = batch.iter().flat_map(|s| s.target.iter().copied()).collect();
    let mut us = vec![0.0; batch_len * steps];
    g.bench_function(format!("gradient_{label}"), |b| b.iter(|| loss_and_gradient(physics, &net, &theta, std::hint::black_box(&batch))));
    g.bench_function(format!("net_forward_batch_{label}"), |b| b.iter(|| net.forward_batch(&inputs, &theta, std::hint::black_box(&mut us))));
    let (mut dus, mut dxs, mut dtheta) = (vec![0.01; us.len()], vec![0.0; inputs.len()], vec![0.0; theta.len()]);
    g.bench_function(format!("net_vjp_batch_{label}"), |b| {
        b.iter(|| {
            dus.fill(0.01);
            net.vjp_batch(&inputs, &theta, &mut dus, &mut dxs, &mut dtheta)
        })
    });
    net.forward_batch(&inputs, &theta, &mut us);
    let (mut y, mut seed, mut dx, mut du) = (vec![0.0; 4], vec![0.0; 4], vec![0.0; 4], vec![0.0; steps]);
    g.bench_function(format!("physics_forward_vjp_{label}_one_thread"), |b| {
        b.iter(|| {
            for (s, u) in batch.iter().zip(us.chunks_exact(steps)) {
                physics.forward(&s.x0, u, &mut y);
                seed.copy_from_slice(&y);
                physics.vjp(&s.x0, u, &mut seed, &mut dx, &mut du);
            }
        })
    });
    // The same through the lane form, eight samples per call.
    let x0s: Vec<f64> = batch.iter().flat_map(|s| s.x0.iter().copied()).collect();
    let (mut ys, mut dxs, mut dus_each) = (vec![0.0; batch_len * 4], vec![0.0; batch_len * 4], vec![0.0; us.len()]);
    g.bench_function(format!("physics_lanes_forward_vjp_{label}_one_thread"), |b| {
        b.iter(|| {
            physics.forward_each(&x0s, &us, &mut ys);
            physics.vjp_each(&x0s, &us, &mut ys, &mut dxs, &mut dus_each);
        })
    });
}

//! `diffsim bench`: the shared benchmark problems.

use clap::{Args, Subcommand};
use serde_json::json;

use super::{CliError, interleaved_times, median_time, peak_rss_bytes};
use diffsim::problems::SmokeBenchmark;
use diffsim::problems::burgers::P1;
use diffsim::problems::smoke::{P2, P4, SmokeStep};
use diffsim::rollout::{Gradient, Rollout, RolloutError, Workspace};
use diffsim_solvers::smoke::{P2_SIZES, P4_SIZES, Preconditioner};

#[derive(Debug, Subcommand)]
pub(super) enum BenchCommand {
    /// P1 burgers1d: loss and gradient of an unrolled 1D Burgers rollout,
    /// forward vs Enzyme gradient vs hand-written gradient.
    P1(P1Args),
    /// P2 smoke2d: loss and gradient of buoyant smoke with pressure
    /// projection, forward vs gradient (Enzyme + implicit adjoint solves).
    P2(P2Args),
    /// P4 smoke3d: P2 in three dimensions, forward vs gradient (Enzyme +
    /// implicit adjoint solves) vs the hand-written adjoint.
    P4(P4Args),
    /// P3 sol1d: one training iteration (loss, gradient through 16 coupled
    /// solver + network steps for a batch of 32, Adam update).
    P3(P3Args),
    /// Time and peak memory of P1's gradient under each checkpointing mode
    /// and under the budget's choice, for several T (each run in its own
    /// process, so that its peak memory is its own); writes memory.md and
    /// memory.png.
    Memory(MemoryArgs),
    /// P4's cost against its size: one `bench p4 --json` process per
    /// (N, T), forward and gradient times, CG iterations and peak memory;
    /// writes p4_cost.md and p4_cost.png (time against cells × steps).
    P4Cost(P4CostArgs),
    /// One HIG update on the coupled oscillators (linear and nonlinear, the
    /// published settings): the Jacobian, each decomposition (f64 SVD, f64
    /// Gram eigendecomposition, f32 SVD, the checked default) with its
    /// error against the f64 SVD on the real batch and on a near-singular
    /// one, the whole update and an Adam update.
    Hig(HigBenchArgs),
    /// Implicit heat conduction (backward Euler, a conductivity per cell,
    /// CG): forward against the gradient by the implicit rule, with the CG
    /// iterations; `--compare` adds Enzyme through the CG iterations.
    ImplicitHeat(ImplicitHeatArgs),
    /// Robertson's stiff kinetics: the gradient of a fit to ODEPACK's
    /// published solution with respect to the three log-rates, by fixed
    /// SDIRK steps and the implicit rule, checked against central
    /// differences (`scripts/bench-robertson` runs diffsol beside it).
    Robertson(RobertsonArgs),
    /// The exchange between MPI ranks (`mpirun -np K diffsim bench
    /// exchange`): the time of an all-gather of n values per rank over a
    /// range of n, its latency and bandwidth (the inputs of the scaling
    /// model in docs/distributed.md).
    Exchange(ExchangeArgs),
    /// Data-parallel training iterations (`mpirun -np K diffsim bench
    /// scaling`): time per iteration, the share of the gradient and the
    /// exchange alone, and the scaling model's predicted efficiency at 8,
    /// 64 and 512 ranks.
    Scaling(super::scaling::ScalingArgs),
}

#[derive(Debug, Args)]
pub(super) struct ExchangeArgs {
    /// Timed exchanges per size at the smallest size (fewer at large sizes,
    /// about 64 MB moved per size at most); the median is reported.
    #[arg(long, default_value_t = 200)]
    repetitions: usize,
    /// Print one JSON line per size instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
pub(super) struct HigBenchArgs {
    /// Timed repetitions of each part (after one warm-up; the Adam update
    /// repeats for at least a second as well); the median is reported.
    #[arg(long, default_value_t = 10)]
    iterations: usize,
    /// Print one JSON line instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
pub(super) struct MemoryArgs {
    /// Cells N.
    #[arg(long, default_value_t = 2048)]
    n: usize,
    /// The rollout lengths T, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1000,10000,100000")]
    steps: Vec<usize>,
    /// The budget of the `auto` runs (the fixed modes run under the
    /// default budget).
    #[arg(long, default_value = "50MB")]
    budget: String,
    /// Output directory.
    #[arg(long, default_value = "out/memory")]
    out: std::path::PathBuf,
    #[command(flatten)]
    overwrite: super::Overwrite,
}

#[derive(Debug, Args)]
pub(super) struct P4CostArgs {
    /// Cells per side N, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "16,32,64")]
    sizes: Vec<usize>,
    /// Steps T, comma-separated (every N runs every T).
    #[arg(long, value_delimiter = ',', default_value = "5,10,20")]
    steps: Vec<usize>,
    /// Checkpointing of every run (see `bench p4 --checkpoint`).
    #[arg(long, default_value = "auto")]
    checkpoint: String,
    /// Output directory.
    #[arg(long, default_value = "out/p4-cost")]
    out: std::path::PathBuf,
    #[command(flatten)]
    overwrite: super::Overwrite,
}

#[derive(Debug, Args)]
pub(super) struct P3Args {
    /// Precision: f64 (everything in float64), f32 (everything in float32)
    /// or mixed (the network in float32, the solver in float64).
    #[arg(long, default_value = "f64")]
    dtype: String,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Timed iterations (after one warm-up); the median is reported.
    #[arg(long, default_value_t = 30)]
    iterations: usize,
    /// Print one JSON line instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
pub(super) struct P2Args {
    /// Cells per side N (≥ 8).
    #[arg(long, default_value_t = 64)]
    n: usize,
    /// Number of steps T (≥ 1).
    #[arg(long, default_value_t = 20)]
    steps: usize,
    #[command(flatten)]
    run: SmokeRun,
}

#[derive(Debug, Args)]
pub(super) struct P4Args {
    /// Cells per side N (≥ 8).
    #[arg(long, default_value_t = 32)]
    n: usize,
    /// Number of steps T (≥ 1).
    #[arg(long, default_value_t = 10)]
    steps: usize,
    #[command(flatten)]
    run: SmokeRun,
}

/// The options P2 and P4 share.
#[derive(Debug, Args)]
pub(super) struct SmokeRun {
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Preconditioner of the pressure solves: multigrid (a V-cycle; the
    /// fastest), mic0 (2D only) or none.
    #[arg(long, default_value = "multigrid")]
    preconditioner: String,
    /// How states are kept for the backward pass: `auto` (the fastest mode
    /// within --memory-budget), store, periodic[:K], binomial[:S].
    #[arg(long, default_value = "auto")]
    checkpoint: String,
    /// Print one JSON line instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
pub(super) struct P1Args {
    /// Number of cells N (≥ 3).
    #[arg(long, default_value_t = 2048)]
    n: usize,
    /// Number of steps T (≥ 1).
    #[arg(long, default_value_t = 2048)]
    steps: usize,
    /// Worker threads (default: all cores). With two or more, the
    /// gradients' backward passes run on two threads (each recomputes a
    /// checkpoint segment and reverses it while the other does the next),
    /// and on grids of at least 16384 cells each forward and VJP step is
    /// split over two threads.
    #[arg(long)]
    threads: Option<usize>,
    /// How states are kept for the backward pass: `auto` (the fastest mode
    /// within --memory-budget, by the cost model of docs/memory.md), store,
    /// periodic[:K], binomial[:S] (without a number: every ⌈√T⌉ steps,
    /// ⌈log₂ T⌉ snapshots).
    #[arg(long, default_value = "auto")]
    checkpoint: String,
    /// Print one JSON line instead of a table.
    #[arg(long)]
    json: bool,
}

pub(super) fn run(cmd: BenchCommand, world: &diffsim::distributed::World) -> Result<(), CliError> {
    match cmd {
        BenchCommand::Exchange(a) => exchange(a, world),
        BenchCommand::Scaling(a) => super::scaling::scaling(a, world),
        BenchCommand::P1(a) => p1(a),
        BenchCommand::P2(a) => p2(a),
        BenchCommand::P4(a) => p4(a),
        BenchCommand::P3(a) => p3(a),
        BenchCommand::Memory(a) => memory(a),
        BenchCommand::P4Cost(a) => p4_cost(a),
        BenchCommand::Hig(a) => hig(a),
        BenchCommand::ImplicitHeat(a) => implicit_heat(a),
        BenchCommand::Robertson(a) => robertson(a),
    }
}

/// `bench exchange`: the median time of an all-gather of `n` values per
/// rank for n from 1 to 2²⁰, measured on rank 0 (every rank takes part;
/// the exchange itself keeps them in step), with the bytes each rank
/// receives and the bandwidth that makes; the latency is the time at n = 1.
fn exchange(a: ExchangeArgs, world: &diffsim::distributed::World) -> Result<(), CliError> {
    if a.repetitions == 0 {
        return Err(CliError::Argument { arg: "--repetitions", reason: "need at least 1".into() });
    }
    let k = world.size();
    if world.is_root() && !a.json {
        println!("all-gather over {k} rank(s), median of timed repetitions (rank 0's clock)");
        println!("{:>9} {:>14} {:>12} {:>14}", "values", "bytes in/rank", "time µs", "bandwidth MB/s");
    }
    for n in [1usize, 16, 256, 4096, 65536, 1 << 20] {
        let mine = vec![world.rank() as f64; n];
        let reps = a.repetitions.min((1 << 23) / (n * k.max(1))).max(3);
        // One exchange to warm up and to check what arrives.
        let all = world.all_gather(&mine);
        if all.len() != n * k || (0..k).any(|r| all[r * n] != r as f64) {
            return Err(CliError::Argument { arg: "bench exchange", reason: format!("the all-gather of {n} values per rank returned wrong data") });
        }
        let mut times = Vec::with_capacity(reps);
        for _ in 0..reps {
            let t0 = std::time::Instant::now();
            std::hint::black_box(world.all_gather(&mine));
            times.push(t0.elapsed().as_secs_f64());
        }
        times.sort_by(f64::total_cmp);
        let t = times[reps / 2];
        let bytes = (k - 1) * n * 8;
        let bandwidth = if t > 0.0 { bytes as f64 / t / 1e6 } else { 0.0 };
        if world.is_root() {
            if a.json {
                println!(
                    "{}",
                    json!({"bench": "exchange", "ranks": k, "values": n, "bytes_in_per_rank": bytes, "time_s": t, "bandwidth_mb_s": bandwidth, "repetitions": reps})
                );
            } else {
                println!("{n:>9} {bytes:>14} {:>12.2} {bandwidth:>14.1}", t * 1e6);
            }
        }
    }
    Ok(())
}

/// The JSON keys of P3's time shares, in order.
const SHARE_NAMES: [&str; 5] = ["solver_fwd", "solver_bwd", "net_fwd", "net_bwd", "optimizer"];

fn p3(a: P3Args) -> Result<(), CliError> {
    use diffsim::train::TimeShares;
    use diffsim_studies::p3::{BATCH, Dtype, P3, UNROLL};
    let dtype: Dtype = a.dtype.parse().map_err(|reason| CliError::Argument { arg: "--dtype", reason })?;
    if a.iterations < 1 {
        return Err(CliError::Argument { arg: "--iterations", reason: "need at least 1".into() });
    }
    let threads = threads(a.threads)?;
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().map_err(|source| CliError::Threads { threads, source })?;
    pool.install(|| -> Result<(), CliError> {
        let mut p = P3::new(0, dtype);
        p.iteration()?;
        let mut runs: Vec<(f64, TimeShares)> = Vec::with_capacity(a.iterations);
        let mut loss = 0.0;
        for _ in 0..a.iterations {
            let (l, b) = p.iteration()?;
            loss = l;
            runs.push((b.total, b));
        }
        runs.sort_by(|x, y| x.0.total_cmp(&y.0));
        let (s_per_iter, _) = runs[runs.len() / 2];
        // Shares over all timed iterations: thread-seconds of the parallel
        // parts over thread-seconds available, the optimizer over wall time.
        let total: f64 = runs.iter().map(|r| r.1.total).sum();
        let sum = |f: fn(&TimeShares) -> f64| runs.iter().map(|r| f(&r.1)).sum::<f64>();
        let par = total * threads.min(BATCH) as f64;
        let shares =
            [sum(|b| b.solver_fwd) / par, sum(|b| b.solver_bwd) / par, sum(|b| b.net_fwd) / par, sum(|b| b.net_bwd) / par, sum(|b| b.optimizer) / total];
        if a.json {
            let mut m = serde_json::Map::new();
            m.insert("problem".into(), json!("p3"));
            m.insert("dtype".into(), json!(dtype.name()));
            m.insert("threads".into(), json!(threads));
            m.insert("s_per_iter".into(), json!(s_per_iter));
            m.insert("params".into(), json!(p.params()));
            m.insert("batch".into(), json!(BATCH));
            m.insert("unroll".into(), json!(UNROLL));
            for (name, v) in SHARE_NAMES.iter().zip(shares) {
                m.insert((*name).into(), json!(v));
            }
            m.insert("loss".into(), json!(loss));
            println!("{}", serde_json::Value::Object(m));
        } else {
            println!(
                "P3 sol1d ({}, {threads} threads): {:.2} ms per iteration (median of {}), {} parameters, batch {BATCH}, unroll {UNROLL}",
                dtype.name(),
                s_per_iter * 1e3,
                a.iterations,
                p.params()
            );
            for (name, v) in SHARE_NAMES.iter().zip(shares) {
                println!("  {name:<11} {:5.1} %", 100.0 * v);
            }
            println!("  rest        {:5.1} % (chaining, loss, reduction, idle threads)", 100.0 * (1.0 - shares.iter().sum::<f64>()));
        }
        Ok(())
    })
}

fn p1(a: P1Args) -> Result<(), CliError> {
    if a.n < 3 {
        return Err(CliError::Argument { arg: "--n", reason: format!("need at least 3 cells, got {}", a.n) });
    }
    if a.steps < 1 {
        return Err(CliError::Argument { arg: "--steps", reason: "need at least 1 step".into() });
    }
    let threads = threads(a.threads)?;
    // The problem's own arrays (u₀, the target, the gradient, the adjoint buffers).
    let other = diffsim::memory::f64s(&[a.n as u64, 8]);
    diffsim::memory::check("P1", format!("{} cells", a.n), other, None)?;
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().map_err(|source| CliError::Threads { threads, source })?;
    pool.install(|| -> Result<(), CliError> {
        let p = P1::new(a.n, a.steps);
        // One forward pass times a step for the cost model.
        let step_s = {
            let t = std::time::Instant::now();
            let _ = p.value();
            t.elapsed().as_secs_f64() / a.steps as f64
        };
        // The bench holds three gradients' states at once (Enzyme, Enzyme on
        // the whole step, hand-written; each keeps its workspace between
        // rounds).
        let job = diffsim::rollout::plan::Job { steps: a.steps, state_bytes: 8 * a.n as u64, copies: 3, forward_s: step_s };
        let (plan, chosen) = super::checkpointing(&a.checkpoint, &job, other.unwrap_or(0), "P1's gradient")?;
        let mode = plan.mode;
        // The four computations in interleaved rounds: the ratios are
        // medians of per-round ratios (robust on a shared machine).
        let (mut ws_e, mut ws_w, mut ws_h) = (Workspace::new(), Workspace::new(), Workspace::new());
        let (mut loss, mut g, mut w, mut h) = (None, None, None, None);
        let (times, ratios) = interleaved_times(
            8.0,
            3,
            31,
            &mut [
                &mut || loss = Some(p.value()),
                &mut || g = Some(p.grad_enzyme_in(&mut ws_e, mode)),
                &mut || w = Some(p.grad_enzyme_whole_step_in(&mut ws_w, mode)),
                &mut || h = Some(p.grad_hand_in(&mut ws_h, mode)),
            ],
        );
        let (forward_s, grad_s, whole_s, hand_grad_s) = (times[0], times[1], times[2], times[3]);
        let (grad_over_forward, whole_over_forward, hand_over_forward) = (ratios[1], ratios[2], ratios[3]);
        let loss = loss.expect("measured at least once")?;
        let g = g.expect("measured at least once")?;
        w.expect("measured at least once")?;
        let h = h.expect("measured at least once")?;
        let grad_l2 = g.dx0.iter().map(|v| v * v).sum::<f64>().sqrt();
        let hand_diff = g.dx0.iter().zip(&h.dx0).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        let out = json!({
            "problem": "p1", "n": a.n, "steps": a.steps, "threads": threads,
            "checkpoint": mode.to_string(), "checkpoint_chosen": chosen,
            "memory_budget_bytes": diffsim::memory::budget(), "estimate_bytes": plan.bytes, "estimate_grad_s": plan.seconds,
            "forward_s": forward_s, "grad_s": grad_s, "hand_grad_s": hand_grad_s,
            "grad_over_forward": grad_over_forward, "hand_over_forward": hand_over_forward,
            "enzyme_over_hand": grad_over_forward / hand_over_forward,
            "peak_rss_bytes": peak_rss_bytes(),
            "loss": g.loss, "grad_l2": grad_l2, "grad_0": g.dx0[0], "grad_n2": g.dx0[a.n / 2],
            "forward_loss": loss, "enzyme_whole_step_grad_s": whole_s, "enzyme_hand_max_diff": hand_diff,
            "peak_state_bytes": g.stats.peak_state_bytes, "step_evaluations": g.stats.step_evaluations,
        });
        if a.json {
            println!("{out}");
        } else {
            let cell_steps = (a.n * a.steps) as f64;
            println!("P1 burgers1d  N = {}  T = {}  threads = {}  checkpointing = {}", a.n, a.steps, threads, mode);
            let how = if chosen { "chosen within" } else { "given; budget" };
            println!("  memory plan ({how} {}): {plan}", diffsim::memory::human(diffsim::memory::budget()));
            println!("  forward          {:10.3} ms   {:6.2} Gcell-steps/s", forward_s * 1e3, cell_steps / forward_s / 1e9);
            println!("  Enzyme gradient  {:10.3} ms   {:6.2}× forward", grad_s * 1e3, grad_over_forward);
            println!("  Enzyme (whole step) {:7.3} ms   {:6.2}× forward", whole_s * 1e3, whole_over_forward);
            println!(
                "  hand gradient    {:10.3} ms   {:6.2}× forward   Enzyme/hand {:.2}",
                hand_grad_s * 1e3,
                hand_over_forward,
                grad_over_forward / hand_over_forward
            );
            println!("  (times: medians over interleaved rounds; ratios: medians of per-round ratios)");
            println!("  loss {:.13}  ‖∇L‖ {:.14}  ∂L/∂u0[0] {:.12e}  ∂L/∂u0[N/2] {:.12e}", g.loss, grad_l2, g.dx0[0], g.dx0[a.n / 2]);
            if let Some(r) = diffsim_solvers::burgers::P1_SIZES.iter().find(|r| r.n == a.n && r.steps == a.steps) {
                let rel = |got: f64, want: f64| (got - want).abs() / want.abs();
                let worst = rel(g.loss, r.loss).max(rel(grad_l2, r.grad_l2)).max(rel(g.dx0[0], r.grad_0)).max(rel(g.dx0[a.n / 2], r.grad_n2));
                println!("  reference (size {}): loss {:.13}  ‖∇L‖ {:.14}  worst relative difference {:.1e}", r.name, r.loss, r.grad_l2, worst);
            }
            println!(
                "  max |Enzyme − hand| {:.2e}   states held {} ({:.1} MB)   peak RSS {:.1} MB",
                hand_diff,
                g.stats.peak_states,
                g.stats.peak_state_bytes as f64 / 1e6,
                peak_rss_bytes() as f64 / 1e6
            );
        }
        Ok(())
    })
}

fn p2(a: P2Args) -> Result<(), CliError> {
    smoke_bench::<SmokeStep<2>>(a.n, a.steps, a.run)
}

fn p4(a: P4Args) -> Result<(), CliError> {
    smoke_bench::<SmokeStep<3>>(a.n, a.steps, a.run)
}

/// What the smoke benchmarks (P2 in 2D, P4 in 3D) need beyond
/// [`SmokeBenchmark`]: implemented by each one's step operator.
trait SmokeBench: diffsim::op::Vjp + Sized {
    /// `"p2"`, `"p4"`.
    const NAME: &'static str;
    /// The heading, e.g. `"P2 smoke2d"`.
    const TITLE: &'static str;
    /// Spatial dimensions (cells = N^DIM).
    const DIM: u32;
    /// The JSON key of the probed gradient entry and how it is printed.
    const PROBE: (&'static str, &'static str);
    /// The preconditioners the solves accept, as `--preconditioner` spells them.
    const PRECONDITIONERS: &'static [(&'static str, Preconditioner)];
    fn build(n: usize, steps: usize, precond: Preconditioner) -> SmokeBenchmark<Self>;
    fn hand(p: SmokeBenchmark<Self>) -> SmokeBenchmark<Self>;
    fn log(&self) -> &diffsim::fluids::SolveLog;
    /// The flat index of the probed gradient entry.
    fn probe(n: usize) -> usize;
    /// Reference loss and ‖∇L‖ of this size, if docs/benchmarks.md has them.
    fn reference(n: usize, steps: usize) -> Option<(f64, f64)>;
}

impl SmokeBench for SmokeStep<2> {
    const NAME: &'static str = "p2";
    const TITLE: &'static str = "P2 smoke2d";
    const DIM: u32 = 2;
    const PROBE: (&'static str, &'static str) = ("grad_n2", "∂L/∂s[N²/2]");
    const PRECONDITIONERS: &'static [(&'static str, Preconditioner)] =
        &[("multigrid", Preconditioner::Multigrid), ("mic0", Preconditioner::Mic0), ("none", Preconditioner::None)];
    fn build(n: usize, steps: usize, precond: Preconditioner) -> P2 {
        P2::new(n, steps, precond)
    }
    fn hand(p: P2) -> P2 {
        p.with_hand_adjoint()
    }
    fn log(&self) -> &diffsim::fluids::SolveLog {
        &self.project.log
    }
    fn probe(n: usize) -> usize {
        diffsim_solvers::smoke::probe::<2>(n)
    }
    fn reference(n: usize, steps: usize) -> Option<(f64, f64)> {
        P2_SIZES.iter().find(|r| r.n == n && r.steps == steps).map(|r| (r.loss, r.grad_l2))
    }
}

impl SmokeBench for SmokeStep<3> {
    const NAME: &'static str = "p4";
    const TITLE: &'static str = "P4 smoke3d";
    const DIM: u32 = 3;
    const PROBE: (&'static str, &'static str) = ("grad_mid", "∂L/∂s[mid]");
    const PRECONDITIONERS: &'static [(&'static str, Preconditioner)] =
        &[("multigrid", Preconditioner::Multigrid), ("mic0", Preconditioner::Mic0), ("none", Preconditioner::None)];
    fn build(n: usize, steps: usize, precond: Preconditioner) -> P4 {
        P4::new(n, steps, precond)
    }
    fn hand(p: P4) -> P4 {
        p.with_hand_adjoint()
    }
    fn log(&self) -> &diffsim::fluids::SolveLog {
        &self.project.log
    }
    fn probe(n: usize) -> usize {
        diffsim_solvers::smoke::probe::<3>(n)
    }
    fn reference(n: usize, steps: usize) -> Option<(f64, f64)> {
        P4_SIZES.iter().find(|r| r.n == n && r.steps == steps).map(|r| (r.loss, r.grad_l2))
    }
}

/// P2 or P4: forward, Enzyme gradient and hand gradient timed in one run,
/// CG iteration totals of one gradient, the loss and gradient checksums
/// against the reference, peak memory.
fn smoke_bench<P: SmokeBench>(n: usize, steps: usize, a: SmokeRun) -> Result<(), CliError> {
    if n < 8 {
        return Err(CliError::Argument { arg: "--n", reason: format!("need at least 8 cells per side, got {}", n) });
    }
    if steps < 1 {
        return Err(CliError::Argument { arg: "--steps", reason: "need at least 1 step".into() });
    }
    let threads = threads(a.threads)?;
    let Some(&(_, precond)) = P::PRECONDITIONERS.iter().find(|(name, _)| *name == a.preconditioner) else {
        let names: Vec<&str> = P::PRECONDITIONERS.iter().map(|(name, _)| *name).collect();
        return Err(CliError::Argument {
            arg: "--preconditioner",
            reason: format!("unknown preconditioner `{}` (expected {})", a.preconditioner, names.join(", ")),
        });
    };
    let title = P::TITLE;
    // Two problems (Enzyme, hand) with their solvers: the grids, the
    // multigrid hierarchy, CG's vectors and the adjoint buffers.
    let other = (n as u64).checked_pow(P::DIM).and_then(|cells| diffsim::memory::f64s(&[cells, SMOKE_ARRAYS]));
    diffsim::memory::check(title, format!("two problems of {}^{} cells", n, P::DIM), other, None)?;
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().map_err(|source| CliError::Threads { threads, source })?;
    pool.install(|| -> Result<(), CliError> {
        let p = P::build(n, steps, precond);
        let budget = 2.0;
        let (forward_s, loss) = median_time(budget, 3, 21, || p.value());
        loss?;
        // One gradient's states at a time (Enzyme's, then the hand adjoint's).
        let job = diffsim::rollout::plan::Job { steps, state_bytes: 8 * p.x0.len() as u64, copies: 1, forward_s: forward_s / steps as f64 };
        let (plan, chosen) = super::checkpointing(&a.checkpoint, &job, other.unwrap_or(0), &format!("{title}'s gradient"))?;
        let mode = plan.mode;
        let mut ws = Workspace::new();
        let (grad_s, g) = median_time(budget, 3, 21, || p.grad_in(&mut ws, mode));
        g?;
        // Iteration totals of one gradient computation (forward and adjoint solves).
        p.step.log().cg_forward.set(0);
        p.step.log().cg_adjoint.set(0);
        let g = p.grad_in(&mut ws, mode)?;
        let (cg_f, cg_a) = (p.step.log().cg_forward.get(), p.step.log().cg_adjoint.get());
        // The hand-written adjoint's run after the generated one's states are
        // freed: the peak is one gradient's, not two side by side.
        drop(ws);
        let hand = P::hand(P::build(n, steps, precond));
        let mut ws_hand = Workspace::new();
        let (hand_grad_s, h) = median_time(budget, 3, 21, || hand.grad_in(&mut ws_hand, mode));
        let h = h?;
        let gs = p.smoke_gradient(&g);
        let grad_l2 = gs.iter().map(|v| v * v).sum::<f64>().sqrt();
        let probe = gs[P::probe(n)];
        let mut out = json!({
            "problem": P::NAME, "n": n, "steps": steps, "threads": threads,
            "checkpoint": mode.to_string(), "checkpoint_chosen": chosen, "preconditioner": precond.to_string(),
            "memory_budget_bytes": diffsim::memory::budget(), "estimate_bytes": plan.bytes,
            "forward_s": forward_s, "grad_s": grad_s, "grad_over_forward": grad_s / forward_s,
            "hand_grad_s": hand_grad_s, "enzyme_over_hand": grad_s / hand_grad_s,
            "enzyme_hand_max_diff": g.dx0.iter().zip(&h.dx0).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max),
            "peak_rss_bytes": peak_rss_bytes(),
            "loss": g.loss, "grad_l2": grad_l2, "grad_0": gs[0],
            "cg_iterations_forward": cg_f, "cg_iterations_adjoint": cg_a,
        });
        out[P::PROBE.0] = json!(probe);
        if a.json {
            println!("{out}");
        } else {
            println!("{title}  N = {}  T = {}  threads = {}  preconditioner = {}  checkpointing = {}", n, steps, threads, precond, mode);
            let how = if chosen { "chosen within" } else { "given; budget" };
            println!("  memory plan ({how} {}): {plan}", diffsim::memory::human(diffsim::memory::budget()));
            println!("  forward          {:10.3} ms", forward_s * 1e3);
            println!("  gradient         {:10.3} ms   {:6.2}× forward", grad_s * 1e3, grad_s / forward_s);
            println!("  hand gradient    {:10.3} ms   {:6.2}× forward   Enzyme/hand {:.2}", hand_grad_s * 1e3, hand_grad_s / forward_s, grad_s / hand_grad_s);
            println!("  loss {:.10}  ‖∇L‖ {:.10}  ∂L/∂s[0] {:.8e}  {} {:.8e}", g.loss, grad_l2, gs[0], P::PROBE.1, probe);
            println!("  CG iterations per gradient: {cg_f} forward, {cg_a} adjoint ({:.1} per solve)", (cg_f + cg_a) as f64 / (2 * steps) as f64);
            if let Some((loss, l2)) = P::reference(n, steps) {
                let rel = |got: f64, want: f64| (got - want).abs() / want.abs();
                println!("  reference: loss {loss:.10}  ‖∇L‖ {l2:.10}  relative differences {:.1e}, {:.1e}", rel(g.loss, loss), rel(grad_l2, l2));
            }
            println!("  peak RSS {:.1} MB", peak_rss_bytes() as f64 / 1e6);
        }
        Ok(())
    })
}

/// Arrays of `N^d` values P2 or P4 holds besides the gradient's states
/// (both problems: grids, multigrid levels, CG and adjoint vectors).
const SMOKE_ARRAYS: u64 = 64;

/// More threads than this per core only add switching.
const MAX_THREADS_PER_CORE: usize = 8;

pub(super) fn threads(requested: Option<usize>) -> Result<usize, CliError> {
    let threads = requested.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    if threads < 1 {
        return Err(CliError::Argument { arg: "--threads", reason: "need at least 1 thread".into() });
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if threads > MAX_THREADS_PER_CORE * cores {
        return Err(CliError::Argument {
            arg: "--threads",
            reason: format!("{threads} threads on {cores} core(s) would only wait for each other; at most {} here", MAX_THREADS_PER_CORE * cores),
        });
    }
    Ok(threads)
}

/// The decompositions `bench hig` compares, with their JSON names; the
/// first (the f64 SVD) is the reference.
const DECOMPOSITIONS: [(&str, diffsim::train::hig::PowerMethod); 4] = [
    ("svd_f64", diffsim::train::hig::PowerMethod::SVD_F64),
    ("gram_f64", diffsim::train::hig::PowerMethod::GRAM_F64),
    ("svd_f32", diffsim::train::hig::PowerMethod::SVD_F32),
    ("auto", diffsim::train::hig::PowerMethod::AUTO),
];

/// `diffsim bench hig`.
fn hig(a: HigBenchArgs) -> Result<(), CliError> {
    use diffsim::train::Optimizer;
    use diffsim::train::hig::{ControlSample, PowerMethod, batch_jacobian, hig_step, loss_and_gradient};
    use diffsim_solvers::linalg::pseudo_inverse_power_apply_with as apply;
    use diffsim_studies::oscillators::{OscParams, datasets};
    if a.iterations < 1 {
        return Err(CliError::Argument { arg: "--iterations", reason: "need at least 1".into() });
    }
    let fail = |e: diffsim::train::hig::HigError| CliError::Argument { arg: "bench hig", reason: e.to_string() };
    let rel = |x: &[f64], r: &[f64]| {
        let d: f64 = x.iter().zip(r).map(|(p, q)| (p - q) * (p - q)).sum::<f64>().sqrt();
        d / r.iter().map(|q| q * q).sum::<f64>().sqrt().max(f64::MIN_POSITIVE)
    };
    let mut out = serde_json::Map::new();
    for problem in 0..2 {
        let (label, cfg) = if problem == 0 { ("linear", OscParams::linear(1.0)) } else { ("nonlinear", OscParams::nonlinear(1.0)) };
        let (data, _) = datasets(&cfg);
        let net = cfg.network();
        let theta = cfg.initial_params(&net);
        let batch = &data[..cfg.hig_batch];
        let h = cfg.hig;
        // The Adam update first, before the decompositions' large buffers.
        let n = a.iterations;
        let mut t = theta.clone();
        let mut adam = Optimizer::adam(cfg.adam_lr);
        let adam_batch = &data[..cfg.adam_batch];
        // At least `n` updates and up to a second of them: an update takes
        // about a millisecond, and the first few pay for waking threads and
        // first-touch pages.
        let adam_s = median_time(1.0, n, 100_000, || {
            let (_, g) = loss_and_gradient(&cfg.problem, &net, &t, adam_batch);
            adam.step(&mut t, &g);
        })
        .0;
        let j = batch_jacobian(&cfg.problem, &net, &theta, batch, h.memory_budget).map_err(fail)?;
        // A near-singular batch: each sample beside a copy moved by 1e-7.
        let near: Vec<ControlSample> = batch
            .iter()
            .enumerate()
            .map(|(k, s)| {
                if k % 2 == 0 {
                    s.clone()
                } else {
                    ControlSample { x0: batch[k - 1].x0.iter().map(|v| v + 1e-7).collect(), target: batch[k - 1].target.clone() }
                }
            })
            .collect();
        let jn = batch_jacobian(&cfg.problem, &net, &theta, &near, h.memory_budget).map_err(fail)?;
        let solve = |jb: &diffsim::train::hig::BatchJacobian, m: PowerMethod| {
            apply(jb.rows, jb.cols, &jb.jac, &jb.grad, h.power, h.truncation, m).map_err(|_| fail(diffsim::train::hig::HigError::Svd))
        };
        let mut row = serde_json::Map::new();
        row.insert("rows".into(), json!(j.rows));
        row.insert("cols".into(), json!(j.cols));
        row.insert("truncation".into(), json!(h.truncation));
        row.insert("jacobian_s".into(), json!(median_time(0.0, n, n, || batch_jacobian(&cfg.problem, &net, &theta, batch, h.memory_budget)).0));
        // Each decomposition's update on both batches, once (the first,
        // the f64 SVD, is the reference).
        let mut updates: Vec<(Vec<f64>, Vec<f64>)> = Vec::with_capacity(4);
        for (name, m) in DECOMPOSITIONS {
            let (seconds, x) = median_time(0.0, n, n, || solve(&j, m));
            let (x, xn) = (x?, solve(&jn, m)?);
            let (reference, near_reference) = updates.first().map_or((&x, &xn), |(r, rn)| (r, rn));
            row.insert(format!("{name}_s"), json!(seconds));
            row.insert(format!("{name}_error"), json!(rel(&x, reference)));
            row.insert(format!("{name}_near_singular_error"), json!(rel(&xn, near_reference)));
            updates.push((x, xn));
        }
        // The route the default (checked) method took: the Gram route's
        // update or not.
        let route = |same: bool| if same { "gram" } else { "svd" };
        row.insert("auto_route".into(), json!(route(updates[3].0 == updates[1].0)));
        row.insert("auto_route_near_singular".into(), json!(route(updates[3].1 == updates[1].1)));
        let mut t = theta.clone();
        row.insert("hig_s_per_update".into(), json!(median_time(0.0, n, n, || hig_step(&cfg.problem, &net, &mut t, batch, &h)).0));
        row.insert("adam_s_per_update".into(), json!(adam_s));
        out.insert(label.into(), serde_json::Value::Object(row));
    }
    if a.json {
        println!("{}", serde_json::Value::Object(out));
    } else {
        for (label, row) in &out {
            println!(
                "{label}: Jacobian {} × {}, truncation {}; auto takes the {} route (near-singular batch: {})",
                row["rows"], row["cols"], row["truncation"], row["auto_route"], row["auto_route_near_singular"]
            );
            println!("  Jacobian      {:8.2} ms", row["jacobian_s"].as_f64().unwrap_or(f64::NAN) * 1e3);
            for (name, _) in DECOMPOSITIONS {
                let f = |k: &str| row[format!("{name}{k}")].as_f64().unwrap_or(f64::NAN);
                println!("  {name:<12}  {:8.2} ms, error {:.1e} (near-singular batch {:.1e})", f("_s") * 1e3, f("_error"), f("_near_singular_error"));
            }
            println!("  HIG update    {:8.2} ms", row["hig_s_per_update"].as_f64().unwrap_or(f64::NAN) * 1e3);
            println!("  Adam update   {:8.2} ms", row["adam_s_per_update"].as_f64().unwrap_or(f64::NAN) * 1e3);
        }
    }
    Ok(())
}

/// `diffsim bench memory`: one `bench p1 --json` process per T and mode.
fn memory(a: MemoryArgs) -> Result<(), CliError> {
    use crate::plot::{Axes, Series};
    let budget = diffsim::memory::parse_bytes(&a.budget)?;
    let exe = std::env::current_exe().map_err(|source| CliError::Io { path: "diffsim".into(), source })?;
    // Held to the end: the folder is this run's while it writes.
    let _out = super::claim_out(&a.out, a.overwrite, &[])?;
    let modes = ["store", "periodic", "binomial", "auto"];
    let mut table =
        "| T | mode | checkpointing | gradient ms | × forward | peak RSS MB | states MB (one gradient) | model ms | model MB (three gradients) |\n|---|---|---|---|---|---|---|---|---|\n"
            .to_string();
    let mut series: Vec<Series> = modes.iter().enumerate().map(|(k, m)| Series { name: m.to_string(), points: Vec::new(), color: k, markers: true }).collect();
    for &t in &a.steps {
        for (k, mode) in modes.iter().enumerate() {
            let mut cmd = std::process::Command::new(&exe);
            cmd.args(["bench", "p1", "--n", &a.n.to_string(), "--steps", &t.to_string(), "--checkpoint", mode, "--json"]);
            if *mode == "auto" {
                cmd.args(["--memory-budget", &budget.to_string()]);
            }
            let j = match json_run(&exe, cmd)? {
                Ok(j) => j,
                Err(why) => {
                    eprintln!("T = {t}, {mode}: {why}");
                    table += &format!("| {t} | {mode} | — | {} | | | | | |\n", diffsim::files::shorten(&why, 90));
                    continue;
                }
            };
            let f = |key: &str| j[key].as_f64().unwrap_or(f64::NAN);
            let (grad_ms, rss) = (f("grad_s") * 1e3, f("peak_rss_bytes") / 1e6);
            table += &format!(
                "| {t} | {mode} | {} | {grad_ms:.2} | {:.1} | {rss:.0} | {:.1} | {:.2} | {:.1} |\n",
                j["checkpoint"].as_str().unwrap_or("?"),
                f("grad_over_forward"),
                f("peak_state_bytes") / 1e6,
                f("estimate_grad_s") * 1e3,
                f("estimate_bytes") / 1e6,
            );
            series[k].points.push((rss, grad_ms / t as f64 * 1e3));
            eprintln!("T = {t}, {mode} ({}): {grad_ms:.2} ms, peak RSS {rss:.0} MB", j["checkpoint"].as_str().unwrap_or("?"));
        }
    }
    let md = a.out.join("memory.md");
    diffsim::files::write(&md, &table).map_err(|source| CliError::Io { path: md.clone(), source })?;
    let axes = Axes { title: "P1 gradient: time per step against peak memory", x: "peak RSS (MB)", y: "gradient µs per step", log_x: true, log_y: true };
    super::plot_or_warn(&a.out.join("memory.png"), &axes, &series);
    println!("{table}");
    println!("wrote memory.md and memory.png to {}", a.out.display());
    Ok(())
}

/// Runs `cmd` (a `diffsim bench ... --json` process) and parses its JSON
/// line; `Ok(Err(why))` when the run failed (the first line of its stderr).
fn json_run(exe: &std::path::Path, mut cmd: std::process::Command) -> Result<Result<serde_json::Value, String>, CliError> {
    let out = cmd.output().map_err(|source| CliError::Io { path: exe.to_path_buf(), source })?;
    let text = String::from_utf8_lossy(&out.stdout);
    let row = if out.status.success() { serde_json::from_str::<serde_json::Value>(text.trim()).ok() } else { None };
    Ok(row.ok_or_else(|| String::from_utf8_lossy(&out.stderr).lines().next().unwrap_or("failed").to_string()))
}

/// `diffsim bench p4-cost`: one `bench p4 --json` process per (N, T), so
/// that each peak RSS is that run's own.
fn p4_cost(a: P4CostArgs) -> Result<(), CliError> {
    use crate::plot::{Axes, Series};
    let exe = std::env::current_exe().map_err(|source| CliError::Io { path: "diffsim".into(), source })?;
    // Held to the end: the folder is this run's while it writes.
    let _out = super::claim_out(&a.out, a.overwrite, &[])?;
    let mut table = "| N | T | cells × steps | forward ms | gradient ms | × forward | µs per cell-step (gradient) | CG iterations per step, fwd (with recomputed steps) / adj | checkpointing | peak RSS MB |\n|---|---|---|---|---|---|---|---|---|---|\n".to_string();
    let mut series = vec![
        Series { name: "forward".into(), points: Vec::new(), color: 0, markers: true },
        Series { name: "gradient".into(), points: Vec::new(), color: 1, markers: true },
    ];
    for &n in &a.sizes {
        for &t in &a.steps {
            let mut cmd = std::process::Command::new(&exe);
            cmd.args(["bench", "p4", "--n", &n.to_string(), "--steps", &t.to_string(), "--checkpoint", &a.checkpoint, "--json"]);
            let j = match json_run(&exe, cmd)? {
                Ok(j) => j,
                Err(why) => {
                    eprintln!("N = {n}, T = {t}: {why}");
                    table += &format!("| {n} | {t} | | {} | | | | | | |\n", diffsim::files::shorten(&why, 90));
                    continue;
                }
            };
            let f = |key: &str| j[key].as_f64().unwrap_or(f64::NAN);
            let work = (n as f64).powi(3) * t as f64;
            let (fwd_ms, grad_ms) = (f("forward_s") * 1e3, f("grad_s") * 1e3);
            // A gradient's forward solves include recomputed ones (checkpointing).
            let (cg_f, cg_a) = (f("cg_iterations_forward"), f("cg_iterations_adjoint"));
            table += &format!(
                "| {n} | {t} | {work:.3e} | {fwd_ms:.1} | {grad_ms:.1} | {:.2} | {:.3} | {:.1} / {:.1} | {} | {:.0} |\n",
                grad_ms / fwd_ms,
                grad_ms * 1e3 / work,
                cg_f / t as f64,
                cg_a / t as f64,
                j["checkpoint"].as_str().unwrap_or("?"),
                f("peak_rss_bytes") / 1e6,
            );
            series[0].points.push((work, fwd_ms));
            series[1].points.push((work, grad_ms));
            eprintln!("N = {n}, T = {t}: forward {fwd_ms:.1} ms, gradient {grad_ms:.1} ms");
        }
    }
    let md = a.out.join("p4_cost.md");
    diffsim::files::write(&md, &table).map_err(|source| CliError::Io { path: md.clone(), source })?;
    let axes = Axes { title: "P4 smoke3d: time against cells × steps", x: "cells × steps", y: "ms", log_x: true, log_y: true };
    super::plot_or_warn(&a.out.join("p4_cost.png"), &axes, &series);
    println!("{table}");
    println!("wrote p4_cost.md and p4_cost.png to {}", a.out.display());
    Ok(())
}

/// Arguments of `diffsim bench implicit-heat`.
#[derive(Debug, Args)]
pub(super) struct ImplicitHeatArgs {
    /// Cells per side.
    #[arg(long, default_value_t = 64)]
    n: usize,
    /// Backward-Euler steps.
    #[arg(long, default_value_t = 20)]
    steps: usize,
    /// Seconds of repeats for each median (at least three runs each).
    #[arg(long, default_value_t = 2.0)]
    budget: f64,
    /// Where CG starts: `zero`, or `rhs` (the right-hand side, close to
    /// the solution of a time step).
    #[arg(long, value_enum, default_value_t = StartArg::Zero)]
    start: StartArg,
    /// CG's preconditioner: `none`, or `jacobi` (the matrix's diagonal,
    /// `problems::implicit_heat::PreconditionedHeat`).
    #[arg(long, value_enum, default_value_t = HeatPreconditioner::None)]
    preconditioner: HeatPreconditioner,
    /// Also differentiate through the CG iterations with Enzyme (the route
    /// without the implicit rule) at tolerances 1e-6 … 1e-12: each
    /// gradient's error against the implicit one at 1e-13, and its time.
    #[arg(long)]
    compare: bool,
    /// Print one JSON line instead of a table.
    #[arg(long)]
    json: bool,
}

/// Arguments of `diffsim bench robertson`.
#[derive(Debug, Args)]
pub(super) struct RobertsonArgs {
    /// Steps in each of the three segments (0–0.4, 0.4–4, 4–40).
    #[arg(long, default_value_t = 100)]
    steps: usize,
    /// The integrator: `sdirk2`, `sdirk3`, `backward-euler`, `crank-nicolson`.
    #[arg(long, value_enum, default_value_t = RobertsonScheme::Sdirk2)]
    scheme: RobertsonScheme,
    /// Seconds of repeats for the median (at least three runs).
    #[arg(long, default_value_t = 2.0)]
    budget: f64,
    /// Print one JSON line instead of a table.
    #[arg(long)]
    json: bool,
}

/// The one-step schemes `bench robertson` offers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub(super) enum RobertsonScheme {
    /// Backward Euler (order 1).
    BackwardEuler,
    /// Crank–Nicolson (order 2, not L-stable).
    CrankNicolson,
    /// Two-stage L-stable SDIRK (order 2).
    Sdirk2,
    /// Three-stage L-stable SDIRK (order 3).
    Sdirk3,
}

/// `diffsim bench robertson`: the loss `½ Σ_i ‖u(t_i) − d_i‖²` of
/// Robertson's kinetics at ODEPACK's three printed times (`d_i` its
/// published states) and its gradient with respect to the three log-rates
/// where a fit starts (off the published ones by 0.3, −0.4, 0.3),
/// by `--steps` fixed steps of `--scheme` in each of the three segments
/// (graded steps for the stiff start): one rollout of `3·steps` steps
/// whose step operator picks the segment's integrator from a step counter
/// carried in the state ([`Segments`]), with its loss terms at the
/// segments' ends, so that it runs forward once and backward once. The
/// gradient is checked against central differences of the same
/// computation before it is reported. `scripts/bench-robertson` runs it
/// beside diffsol's adjoint.
fn robertson(a: RobertsonArgs) -> Result<(), CliError> {
    use diffsim::implicit::{Integrator, IntegratorParams, Scheme};
    use diffsim::problems::robertson::{LSODE_STATES, LSODE_TIMES, Robertson, START, log_rates};
    use diffsim::rollout::{AtSteps, Checkpointing};
    if !(1..=1_000_000).contains(&a.steps) {
        return Err(CliError::Argument { arg: "--steps", reason: format!("must be between 1 and 1000000, got {}", a.steps) });
    }
    if !(a.budget.is_finite() && (0.0..=3600.0).contains(&a.budget)) {
        return Err(CliError::Argument { arg: "--budget", reason: format!("must be between 0 and 3600 seconds, got {}", a.budget) });
    }
    let scheme = match a.scheme {
        RobertsonScheme::BackwardEuler => Scheme::BackwardEuler,
        RobertsonScheme::CrankNicolson => Scheme::CrankNicolson,
        RobertsonScheme::Sdirk2 => Scheme::Sdirk2,
        RobertsonScheme::Sdirk3 => Scheme::Sdirk3,
    };
    let m = a.steps;
    let mut t0 = 0.0;
    let ops: Vec<Integrator<Robertson>> = LSODE_TIMES
        .iter()
        .map(|&t| {
            let op = Integrator::new(Robertson, IntegratorParams::new(scheme, (t - t0) / m as f64));
            t0 = t;
            op
        })
        .collect();
    // One rollout of the three segments (a step counter in the state picks
    // each step's integrator): forward once, backward once.
    let segments = Segments { ops: &ops, m };
    let x0 = [START[0], START[1], START[2], 0.0];
    let loss = AtSteps {
        steps: vec![m, 2 * m, 3 * m],
        f: |t: usize, x: &[f64], g: &mut [f64]| -> f64 {
            let d = &LSODE_STATES[t / m - 1];
            g.fill(0.0);
            let mut v = 0.0;
            for i in 0..3 {
                g[i] = x[i] - d[i];
                v += 0.5 * (x[i] - d[i]) * (x[i] - d[i]);
            }
            v
        },
    };
    let run = |p: &[f64]| -> Result<(f64, Vec<f64>), RolloutError> {
        let g = Rollout::new(&segments, p, 3 * m)?.value_and_grad(&x0, &loss, Checkpointing::Store)?;
        Ok((g.loss, g.dp))
    };
    let not_reported = |reason: String| CliError::NotReported { what: "bench robertson".into(), reason };
    // Where a fit to the published solution starts (the test of the fit
    // starts here too): the log-rates off by (0.3, −0.4, 0.3).
    let truth = log_rates();
    let p = [truth[0] + 0.3, truth[1] - 0.4, truth[2] + 0.3];
    let (value, grad) = run(&p).map_err(|e| not_reported(e.to_string()))?;
    if !value.is_finite() || !diffsim::op::all_finite(&grad) {
        return Err(not_reported("the loss or its gradient is not finite".into()));
    }
    // Central differences of the same computation (h = 1e-5 on ln k).
    let h = 1e-5;
    let mut fd_error: f64 = 0.0;
    let scale = grad.iter().fold(0.0f64, |s, g| s.max(g.abs()));
    for i in 0..3 {
        let (mut up, mut down) = (p, p);
        up[i] += h;
        down[i] -= h;
        let (fu, _) = run(&up).map_err(|e| not_reported(e.to_string()))?;
        let (fd, _) = run(&down).map_err(|e| not_reported(e.to_string()))?;
        fd_error = fd_error.max(((fu - fd) / (2.0 * h) - grad[i]).abs() / scale);
    }
    if !(fd_error < 1e-5) {
        return Err(not_reported(format!("the gradient disagrees with central differences (relative {fd_error:.1e})")));
    }
    let (grad_s, _) = median_time(a.budget, 3, 100_000, || run(&p));
    let scheme_name = format!("{:?}", a.scheme).to_lowercase();
    let row = serde_json::json!({
        "problem": "robertson", "scheme": scheme_name, "steps_per_segment": m, "grad_s": grad_s,
        "loss": value, "gradient": grad, "fd_relative_error": fd_error,
    });
    if a.json {
        println!("{row}");
    } else {
        println!("Robertson, loss at t = 0.4, 4, 40, {m} {scheme_name} steps a segment");
        println!("  loss      {value:.10e}");
        println!("  gradient  [{:.10e}, {:.10e}, {:.10e}] (central differences agree to {fd_error:.1e})", grad[0], grad[1], grad[2]);
        println!("  time      {:9.3} ms", 1e3 * grad_s);
    }
    Ok(())
}

/// Robertson's three segments as one step operator: the state is the
/// three species and a step counter, and each step is the integrator of
/// the segment the counter is in (`m` steps each), so that one rollout of
/// `3m` steps covers them (with its losses at the segments' ends). The
/// counter takes whole values and has no derivative: its cotangent is 0.
struct Segments<'a> {
    ops: &'a [diffsim::implicit::Integrator<diffsim::problems::robertson::Robertson>],
    m: usize,
}

impl Segments<'_> {
    fn at(&self, x: &[f64]) -> &diffsim::implicit::Integrator<diffsim::problems::robertson::Robertson> {
        &self.ops[(x[3] as usize / self.m).min(self.ops.len() - 1)]
    }
}

impl diffsim::op::Operator for Segments<'_> {
    fn n_in(&self) -> usize {
        4
    }
    fn n_out(&self) -> usize {
        4
    }
    fn n_params(&self) -> usize {
        3
    }
}

impl diffsim::op::Forward for Segments<'_> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        self.at(x).forward(&x[..3], p, &mut y[..3]);
        y[3] = x[3] + 1.0;
    }
    fn solve_tolerance(&self) -> f64 {
        self.ops.iter().map(|o| o.solve_tolerance()).fold(0.0, f64::max)
    }
    fn take_error(&self) -> Option<diffsim::op::OpError> {
        let mut first = None;
        for op in self.ops {
            if let Some(e) = op.take_error() {
                first.get_or_insert(e);
            }
        }
        first
    }
}

impl diffsim::op::Vjp for Segments<'_> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        self.at(x).vjp(&x[..3], p, &mut dy[..3], &mut dx[..3], dp);
        dy[3] = 0.0;
    }
    fn vjp_overwrite_given(&self, x: &[f64], p: &[f64], y: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        self.at(x).vjp_overwrite_given(&x[..3], p, &y[..3], &mut dy[..3], &mut dx[..3], dp);
        dx[3] = 0.0;
    }
}

/// A heat step of the bench, plain or preconditioned: its rollout's loss
/// and gradient, and its CG iterations so far (forward, adjoint).
trait HeatStep {
    fn loss(&self, x0: &[f64], theta: &[f64], steps: usize, loss: HeatLoss<'_>) -> Result<f64, RolloutError>;
    fn value_and_grad(&self, x0: &[f64], theta: &[f64], steps: usize, loss: HeatLoss<'_>) -> Result<Gradient, RolloutError>;
    fn counts(&self) -> (usize, usize);
}

type HeatLoss<'a> = &'a dyn Fn(&[f64], &mut [f64]) -> f64;

impl<S: diffsim::implicit::SystemFunctions> HeatStep for diffsim::implicit::LinearSolve<S> {
    fn loss(&self, x0: &[f64], theta: &[f64], steps: usize, loss: HeatLoss<'_>) -> Result<f64, RolloutError> {
        Rollout::new(self, theta, steps)?.loss(x0, &loss)
    }
    fn value_and_grad(&self, x0: &[f64], theta: &[f64], steps: usize, loss: HeatLoss<'_>) -> Result<Gradient, RolloutError> {
        Rollout::new(self, theta, steps)?.value_and_grad(x0, &loss, diffsim::rollout::Checkpointing::Store)
    }
    fn counts(&self) -> (usize, usize) {
        use std::sync::atomic::Ordering;
        (self.info.forward.load(Ordering::Relaxed), self.info.adjoint.load(Ordering::Relaxed))
    }
}

/// The implicit heat bench's preconditioner.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub(super) enum HeatPreconditioner {
    /// Plain CG.
    None,
    /// The diagonal.
    Jacobi,
}

/// [`diffsim::implicit::Start`] on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub(super) enum StartArg {
    /// From zero.
    Zero,
    /// From the right-hand side.
    Rhs,
}

/// `diffsim bench implicit-heat`: the loss `½‖x_T − x*‖²` of `steps`
/// backward-Euler steps of heat conduction with a conductivity per cell
/// (`problems::implicit_heat`, CG to 1e-10), forward against the gradient
/// with respect to the initial state and every cell's conductivity (the
/// implicit rule: one adjoint solve a step, the rollout handing each step
/// its solution), with the CG iterations of each.
fn implicit_heat(a: ImplicitHeatArgs) -> Result<(), CliError> {
    use diffsim::implicit::SolveParams;
    use diffsim::problems::implicit_heat::ImplicitHeat;
    use diffsim::rollout::{Checkpointing, Rollout};
    if !(2..=2048).contains(&a.n) {
        return Err(CliError::Argument { arg: "--n", reason: format!("must be between 2 and 2048 cells per side, got {}", a.n) });
    }
    if !(1..=100_000).contains(&a.steps) {
        return Err(CliError::Argument { arg: "--steps", reason: format!("must be between 1 and 100000, got {}", a.steps) });
    }
    if !(a.budget.is_finite() && (0.0..=3600.0).contains(&a.budget)) {
        return Err(CliError::Argument { arg: "--budget", reason: format!("must be between 0 and 3600 seconds, got {}", a.budget) });
    }
    let cells = (a.n * a.n) as u64;
    // The stored states and a few vectors of the solves.
    diffsim::memory::check(
        "bench implicit-heat",
        format!("{} states of {cells} cells", a.steps + 1),
        diffsim::memory::f64s(&[cells, a.steps as u64 + 16]),
        Some("a smaller --n or --steps".into()),
    )?;
    let (n, steps) = (a.n, a.steps);
    let start = match a.start {
        StartArg::Zero => diffsim::implicit::Start::Zero,
        StartArg::Rhs => diffsim::implicit::Start::Rhs,
    };
    let params = SolveParams { start, ..SolveParams::default() };
    let (plain, jacobi);
    let op: &dyn HeatStep = match a.preconditioner {
        HeatPreconditioner::None => {
            plain = ImplicitHeat::step(n, 0.1, params);
            &plain
        }
        HeatPreconditioner::Jacobi => {
            jacobi = diffsim::problems::implicit_heat::PreconditionedHeat::step(n, 0.1, params);
            &jacobi
        }
    };
    let wave = |k: usize, a: f64, b: f64| a * (0.37 * (k % n) as f64).sin() * (0.23 * (k / n) as f64).cos() + b;
    let x0: Vec<f64> = (0..n * n).map(|k| wave(k, 1.0, 0.5)).collect();
    let theta: Vec<f64> = (0..n * n).map(|k| wave(k, 0.5, 0.0)).collect();
    let target: Vec<f64> = (0..n * n).map(|k| wave(k, 0.2, 0.5)).collect();
    let loss = |x: &[f64], g: &mut [f64]| -> f64 {
        let mut value = 0.0;
        for ((g, a), b) in g.iter_mut().zip(x).zip(&target) {
            *g = a - b;
            value += 0.5 * (a - b) * (a - b);
        }
        value
    };
    // One of each, counted.
    let c0 = op.counts();
    let value = op.loss(&x0, &theta, steps, &loss)?;
    let c1 = op.counts();
    let g = op.value_and_grad(&x0, &theta, steps, &loss)?;
    let c2 = op.counts();
    if !value.is_finite() || !diffsim::op::all_finite(&g.dx0) || !diffsim::op::all_finite(&g.dp) {
        return Err(CliError::NotReported { what: "bench implicit-heat".into(), reason: "the loss or its gradient is not finite".into() });
    }
    let (forward_s, _) = median_time(a.budget, 3, 100_000, || op.loss(&x0, &theta, steps, &loss));
    let (grad_s, _) = median_time(a.budget, 3, 100_000, || op.value_and_grad(&x0, &theta, steps, &loss));
    let mut row = serde_json::json!({
        "problem": "implicit-heat", "n": n, "steps": steps, "tolerance": params.tolerance, "start": format!("{:?}", a.start).to_lowercase(),
        "preconditioner": format!("{:?}", a.preconditioner).to_lowercase(),
        "forward_s": forward_s, "grad_s": grad_s, "grad_over_forward": grad_s / forward_s,
        "cg_forward_iterations": c1.0 - c0.0, "cg_gradient_forward_iterations": c2.0 - c1.0, "cg_adjoint_iterations": c2.1 - c1.1,
        "loss": value,
    });
    if !a.json {
        println!(
            "implicit heat, {n}² cells, {steps} backward-Euler steps, CG to {:.0e} from {:?}, preconditioner {:?}",
            params.tolerance, a.start, a.preconditioner
        );
        println!("  forward    {:9.3} ms  ({} CG iterations)", 1e3 * forward_s, c1.0 - c0.0);
        println!("  gradient   {:9.3} ms  ({} forward and {} adjoint CG iterations)", 1e3 * grad_s, c2.0 - c1.0, c2.1 - c1.1);
        println!("  gradient / forward  {:.2}", grad_s / forward_s);
    }
    if a.compare {
        use diffsim::problems::implicit_heat::HeatThroughCg;
        let flat = |g: &diffsim::rollout::Gradient| g.dx0.iter().chain(&g.dp).copied().collect::<Vec<f64>>();
        let tight = ImplicitHeat::step(n, 0.1, SolveParams { tolerance: 1e-13, ..SolveParams::default() });
        let reference = flat(&Rollout::new(&tight, &theta, steps)?.value_and_grad(&x0, &loss, Checkpointing::Store)?);
        let error = |g: &[f64]| diffsim_studies::accuracy::relative_l2(g, &reference);
        let mut rows = Vec::new();
        if !a.json {
            println!("\n| CG tolerance | implicit rule: error | time (ms) | Enzyme through CG: error | time (ms) |\n|---|---|---|---|---|");
        }
        for tolerance in [1e-6, 1e-8, 1e-10, 1e-12] {
            let implicit = ImplicitHeat::step(n, 0.1, SolveParams { tolerance, ..SolveParams::default() });
            let through = HeatThroughCg { n, dt: 0.1, tolerance, max_iterations: 10_000 };
            let (r1, r2) = (Rollout::new(&implicit, &theta, steps)?, Rollout::new(&through, &theta, steps)?);
            let (t1, g1) = median_time(a.budget / 4.0, 1, 1000, || r1.value_and_grad(&x0, &loss, Checkpointing::Store));
            let (t2, g2) = median_time(a.budget / 4.0, 1, 1000, || r2.value_and_grad(&x0, &loss, Checkpointing::Store));
            let (e1, e2) = (error(&flat(&g1?)), error(&flat(&g2?)));
            if !a.json {
                println!("| {tolerance:.0e} | {e1:.1e} | {:.2} | {e2:.1e} | {:.2} |", 1e3 * t1, 1e3 * t2);
            }
            rows.push(
                serde_json::json!({"tolerance": tolerance, "implicit_error": e1, "implicit_grad_s": t1, "through_cg_error": e2, "through_cg_grad_s": t2}),
            );
        }
        row["compare"] = serde_json::Value::Array(rows);
    }
    if a.json {
        println!("{row}");
    }
    Ok(())
}

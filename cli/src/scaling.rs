//! `diffsim bench scaling`: data-parallel training iterations over the
//! ranks of an `mpirun` (or one process), timed, with what the exchange
//! costs, and the model that carries the measurement past this machine
//! ([`diffsim::distributed::ScalingModel`]).

use clap::Args;
use serde_json::json;

use super::CliError;
use diffsim::distributed::{ScalingModel, World};
use diffsim::nn::Activation;
use diffsim::op::Vjp;
use diffsim::rollout::Checkpointing;
use diffsim::train::{Coupled, Coupling, Optimizer, RolloutBatch, Sample, Trainer, TrainerParams, batch_gradient_over};
use diffsim_studies::sol::SolProblem;

#[derive(Debug, Args)]
pub(super) struct ScalingArgs {
    /// The training: p3 (P3 sol1d: batch 32, 16 unrolled steps of a 1D
    /// solver and conv net) or wake (the 2D solver-in-the-loop study: batch
    /// 8, SOL-4 through the 64 × 32 flow past a disc with its pressure
    /// solve).
    #[arg(long, default_value = "p3")]
    workload: String,
    /// Timed iterations (after one warm-up); the median is reported.
    #[arg(long, default_value_t = 10)]
    iterations: usize,
    /// Threads per rank (default: one per core).
    #[arg(long)]
    threads: Option<usize>,
    /// The model's all-gather latency in µs, for the predictions at 8, 64
    /// and 512 ranks (default: measured here; give a cluster network's).
    #[arg(long)]
    latency_us: Option<f64>,
    /// The model's all-gather bandwidth in GB/s (default: measured here).
    #[arg(long)]
    bandwidth_gbs: Option<f64>,
    /// Print one JSON line instead of the summary.
    #[arg(long)]
    json: bool,
}

/// One workload: a coupled solver and network, its parameters and a batch.
struct Workload<S> {
    op: S,
    theta: Vec<f64>,
    batch: Vec<Sample>,
    unroll: usize,
}

/// `diffsim bench scaling`.
pub(super) fn scaling(a: ScalingArgs, world: &World) -> Result<(), CliError> {
    if a.iterations == 0 {
        return Err(CliError::Argument { arg: "--iterations", reason: "need at least 1".into() });
    }
    let threads = super::bench::threads(a.threads)?;
    // The global pool: MPI is called from this (the main) thread only.
    rayon::ThreadPoolBuilder::new().num_threads(threads).build_global().map_err(|source| CliError::Threads { threads, source })?;
    match a.workload.as_str() {
        "p3" => {
            use diffsim_studies::p3::{P3, UNROLL};
            let p = P3::new(0, diffsim_studies::p3::Dtype::F64);
            let op = Coupled::new(&p.step, &[], &p.net, Coupling::Add).expect("the network fits the solver");
            measure(&a, world, threads, Workload { op, theta: p.theta.clone(), batch: p.batch.clone(), unroll: UNROLL })
        }
        "wake" => {
            use rand::SeedableRng;
            let setup = diffsim_studies::wake::WakeSetup::standard();
            let net = setup.network(Activation::Relu);
            let theta = diffsim_studies::sol::initial_params(&net, 1);
            let mut rng = rand::rngs::StdRng::seed_from_u64(1);
            let unroll = 4;
            // Start states from the study's distribution; the targets only
            // shape the loss, not the work.
            let batch = (0..8)
                .map(|_| {
                    let x0 = setup.downsample(&setup.initial(&mut rng));
                    Sample { targets: vec![x0.clone(); unroll], x0 }
                })
                .collect();
            let source = setup.source();
            let op = Coupled::new(&source, &[], &net, Coupling::Add).expect("the network fits the solver");
            measure(&a, world, threads, Workload { op, theta, batch, unroll })
        }
        other => Err(CliError::Argument { arg: "--workload", reason: diffsim::words::unknown("workload", other, &["p3", "wake"]) }),
    }
}

/// Times `iterations` data-parallel iterations (gradient and Adam update)
/// on rank 0's clock, each after a barrier; beside them, each rank's share
/// of the gradient alone and an all-gather of the iteration's payload
/// alone; rank 0 prints.
fn measure<S: Vjp + Sync>(a: &ScalingArgs, world: &World, threads: usize, w: Workload<S>) -> Result<(), CliError> {
    let batch_len = w.batch.len();
    let mine = &w.batch[world.share(batch_len)];
    let steps: Vec<usize> = (1..=w.unroll).collect();
    let mut theta = w.theta.clone();
    let mut adam = Optimizer::adam(1e-4);
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    // The library's trainer runs the iterations (the first a warm-up);
    // after each, the ranks wait for each other, so every timed iteration
    // starts together.
    let mut iteration = Vec::new();
    let trainer = Trainer::new(TrainerParams { iterations: a.iterations + 1, ..TrainerParams::default() }, world);
    let batch_at = |_| Ok(RolloutBatch::new(&w.op, w.unroll, &steps, mine, Checkpointing::Store).over(world, batch_len));
    world.barrier();
    trainer.run(&mut adam, &mut theta, batch_at, |row, _, _| {
        if row.iteration > 1 {
            iteration.push(row.step_seconds);
        }
        world.barrier();
        std::ops::ControlFlow::Continue(())
    })?;
    // This rank's share alone (no exchange), then the slowest rank's.
    let mut share = Vec::new();
    for _ in 0..a.iterations.min(5) {
        let t = std::time::Instant::now();
        batch_gradient_over(&World::single(), &w.op, &theta, w.unroll, &steps, mine, mine.len(), Checkpointing::Store)?;
        share.push(t.elapsed().as_secs_f64());
    }
    let share_s = world.all_gather(&[median(share)]).into_iter().fold(0.0, f64::max);
    // The exchange alone: each rank's per-sample rows, as in an iteration.
    let values = 1 + theta.len();
    let rows = vec![0.0; mine.len() * values];
    let mut exchange = Vec::new();
    for _ in 0..a.iterations.max(20) {
        world.barrier();
        let t = std::time::Instant::now();
        std::hint::black_box(world.all_gather(&rows));
        exchange.push(t.elapsed().as_secs_f64());
    }
    // The latency: an all-gather of one value.
    let mut tiny = Vec::new();
    for _ in 0..50 {
        world.barrier();
        let t = std::time::Instant::now();
        std::hint::black_box(world.all_gather(&[0.0]));
        tiny.push(t.elapsed().as_secs_f64());
    }
    let (iteration_s, exchange_s, latency_s) = (median(iteration), median(exchange), median(tiny));
    let k = world.size();
    let bytes_in = (batch_len - mine.len()) * values * 8;
    if !world.is_root() {
        return Ok(());
    }
    let model = ScalingModel {
        sample_s: share_s * threads as f64 / world.share(batch_len).len().max(1) as f64,
        fixed_s: (iteration_s - share_s - exchange_s).max(0.0),
        values_per_sample: values,
        latency_s: a.latency_us.map_or(latency_s, |l| l * 1e-6),
        bandwidth: a.bandwidth_gbs.map_or(if k > 1 { bytes_in as f64 / (exchange_s - latency_s).max(1e-9) } else { f64::NAN }, |b| b * 1e9),
    };
    let predicted: Vec<_> =
        [8usize, 64, 512].iter().map(|&r| (r, model.efficiency(r, batch_len), model.efficiency(r, batch_len * r), model.batch_for(r, 0.5))).collect();
    let modelled = model.bandwidth.is_finite();
    if a.json {
        let mut line = json!({
            "bench": "scaling", "workload": a.workload, "ranks": k, "threads_per_rank": threads, "batch": batch_len,
            "params": theta.len(), "unroll": w.unroll, "iteration_s": iteration_s, "share_s": share_s,
            "exchange_s": exchange_s, "latency_s": latency_s, "bytes_in_per_rank": bytes_in,
            "model": {"sample_s": model.sample_s, "fixed_s": model.fixed_s, "values_per_sample": values,
                      "latency_s": model.latency_s, "bandwidth_bytes_s": if modelled { json!(model.bandwidth) } else { json!(null) }},
        });
        if modelled {
            for (r, strong, weak, b) in &predicted {
                line[format!("efficiency_{r}")] = json!(strong);
                line[format!("efficiency_{r}_batch_per_rank")] = json!(weak);
                line[format!("batch_for_half_{r}")] = json!(b);
            }
            line["rank_limit"] = json!(model.rank_limit());
        }
        println!("{line}");
        return Ok(());
    }
    println!(
        "{} over {k} rank(s) × {threads} thread(s): {:.2} ms per iteration (median of {}); batch {batch_len}, {} parameters, unroll {}",
        a.workload,
        iteration_s * 1e3,
        a.iterations,
        theta.len(),
        w.unroll
    );
    println!(
        "  the slowest rank's share alone {:.2} ms; the exchange alone {:.3} ms ({bytes_in} bytes in per rank; one value: {:.1} µs)",
        share_s * 1e3,
        exchange_s * 1e3,
        latency_s * 1e6
    );
    if !modelled {
        println!("  (run over 2 or more ranks, or give --latency-us and --bandwidth-gbs, for the model's predictions)");
        return Ok(());
    }
    println!(
        "  model: t_s {:.3} ms per sample, t_0 {:.3} ms, α {:.1} µs, β {:.2} GB/s, {values} values per sample",
        model.sample_s * 1e3,
        model.fixed_s * 1e3,
        model.latency_s * 1e6,
        model.bandwidth / 1e9
    );
    for (r, strong, weak, b) in predicted {
        let needed = b.map_or("none reaches it".to_string(), |b| format!("batch {b}"));
        println!(
            "  {r:>4} ranks: efficiency {:.0}% at batch {batch_len}, {:.0}% at batch {} ({batch_len} per rank); 50% needs {needed}",
            100.0 * strong,
            100.0 * weak,
            batch_len * r
        );
    }
    println!("  past about {:.0} ranks no batch reaches 50% (every sample's gradient is exchanged)", model.rank_limit());
    Ok(())
}

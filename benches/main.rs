//! The one criterion binary: a group per benchmark problem, with forward,
//! Enzyme gradient and hand-written gradient as members.
#![feature(autodiff)]

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use diffsim::problems::burgers::P1;
use diffsim::rollout::Checkpointing;

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
    // The sizes S, M, L of benchmarks.md. (Reading them from the solvers'
    // `P1_SIZES` table here aborted rustc's Enzyme type trees; README, Enzyme
    // notes.)
    for (n, steps) in [(256, 256), (2048, 2048), (16384, 1000)] {
        p1_size(c, n, steps);
    }
}

criterion_group!(benches, p1);
criterion_main!(benches);

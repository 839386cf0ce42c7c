//! P1 burgers1d: the reference table of benchmarks.md, by both gradients.

use diffsim::problems::burgers::P1;
use diffsim::rollout::{Checkpointing, Gradient};
use diffsim_solvers::burgers::{P1_SIZES, P1Reference};

#[track_caller]
fn close(got: f64, want: f64) {
    let err = (got - want).abs() / want.abs();
    assert!(err <= 1e-10, "got {got:.15e}, reference {want:.15e}, relative error {err:.2e} > 1e-10");
}

/// The gradients of one size, computed apart from the table (see the note
/// in the test).
#[inline(never)]
fn gradients(n: usize, steps: usize) -> (f64, Gradient, Gradient) {
    let p = P1::new(n, steps);
    let mode = Checkpointing::periodic_sqrt(steps);
    (p.value().unwrap(), p.grad_enzyme(mode).unwrap(), p.grad_hand(mode).unwrap())
}

#[inline(never)]
fn compare(r: &P1Reference, value: f64, g: &Gradient) {
    eprintln!("P1 {}: loss {:.13}", r.name, g.loss);
    close(value, r.loss);
    close(g.loss, r.loss);
    close(g.dx0.iter().map(|v| v * v).sum::<f64>().sqrt(), r.grad_l2);
    close(g.dx0[0], r.grad_0);
    close(g.dx0[r.n / 2], r.grad_n2);
}

#[test]
fn reference_table_enzyme_and_hand() {
    // Iterating the constant table in the same function as the gradient
    // calls crashed Enzyme's type analysis at the link (README, "Enzyme
    // notes"); the calls therefore sit in their own non-inlined function.
    for (n, steps) in [(256, 256), (2048, 2048), (16384, 1000)] {
        let (value, enzyme, hand) = gradients(n, steps);
        let r = P1_SIZES.iter().find(|r| r.n == n).unwrap();
        compare(r, value, &enzyme);
        compare(r, value, &hand);
    }
}

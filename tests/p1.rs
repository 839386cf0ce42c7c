//! P1 burgers1d: the reference table of docs/benchmarks.md, by both gradients.

use diffsim::problems::burgers::P1;
use diffsim::rollout::{Checkpointing, Gradient};
use diffsim_solvers::burgers::{P1_SIZES, P1Reference};

#[track_caller]
fn close(got: f64, want: f64) {
    let err = (got - want).abs() / want.abs();
    assert!(err <= 1e-10, "got {got:.15e}, reference {want:.15e}, relative error {err:.2e} > 1e-10");
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
#[allow(clippy::needless_range_loop)] // by index on purpose, see below
fn reference_table_enzyme_and_hand() {
    // No arrays of `Gradient` or of the reference structs here: rustc's
    // Enzyme type trees for arrays of structs that mix pointers and numbers
    // abort the build (docs/pitfalls.md).
    for i in 0..P1_SIZES.len() {
        let r = &P1_SIZES[i];
        let p = P1::new(r.n, r.steps);
        let mode = Checkpointing::periodic_sqrt(r.steps);
        let value = p.value().unwrap();
        compare(r, value, &p.grad_enzyme(mode).unwrap());
        compare(r, value, &p.grad_enzyme_whole_step(mode).unwrap());
        compare(r, value, &p.grad_hand(mode).unwrap());
    }
}

#[test]
fn forward_and_vjp_split_over_two_threads_are_bit_identical() {
    use diffsim::op::Forward;
    use diffsim::problems::burgers::{BurgersEnzyme, BurgersHand};
    // Large enough to split (and odd, so that the halves differ in length).
    let n = diffsim::op::stencil::PAR_MIN_CELLS + 3;
    let p = P1::new(n, 1);
    let mut want = vec![0.0; n];
    diffsim_solvers::burgers::step(&p.cfg, &p.u0, &mut want);
    let two = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    let (mut hand, mut enzyme) = (vec![0.0; n], vec![0.0; n]);
    two.install(|| {
        assert_eq!(rayon::current_num_threads(), 2);
        BurgersHand(p.cfg).forward(&p.u0, &[], &mut hand);
        BurgersEnzyme(p.cfg).forward(&p.u0, &[], &mut enzyme);
    });
    assert_eq!(hand, want);
    assert_eq!(enzyme, want);
    // The VJPs split the same way: equal to one thread's, bit for bit.
    use diffsim::op::Vjp;
    let g: Vec<f64> = p.u0.iter().map(|u| u * u - 0.3).collect();
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let vjp = |pool: &rayon::ThreadPool, enzyme_op: bool| {
        let (mut dy, mut dx) = (g.clone(), vec![0.0; n]);
        pool.install(|| {
            if enzyme_op {
                BurgersEnzyme(p.cfg).vjp_overwrite(&p.u0, &[], &mut dy, &mut dx, &mut []);
            } else {
                BurgersHand(p.cfg).vjp_overwrite(&p.u0, &[], &mut dy, &mut dx, &mut []);
            }
        });
        dx
    };
    let mut want = vec![0.0; n];
    diffsim_solvers::burgers::step_adjoint_overwrite(&p.cfg, &p.u0, &g, &mut want);
    assert_eq!(vjp(&two, false), want);
    assert_eq!(vjp(&two, true), vjp(&one, true));
}

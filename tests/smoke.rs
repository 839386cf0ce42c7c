//! Benchmarks P2 and P4 and their step (`problems::smoke`), written once
//! and run in 2D and 3D: the reference tables of docs/benchmarks.md (loss
//! and ‖∇L‖ to 1e-6 relative, entries to 1e-6·‖∇L‖) with each
//! preconditioner and with Enzyme's and the hand-written adjoint; the
//! explicit part and its slab ranges (the parallel VJP), the hand-written
//! adjoint against Enzyme's, the projection and the whole step under the
//! three checks, the multigrid preconditioner, checkpointing, a solve that
//! cannot converge, and results that do not depend on the thread count.

use diffsim::check::{CheckParams, check_all, dot_product_between, finite_differences, taylor};
use diffsim::fluids::Project;
use diffsim::op::{Jvp, OperatorExt, Vjp};
use diffsim::problems::SmokeBenchmark;
use diffsim::problems::ranges::split_ranges;
use diffsim::problems::smoke::{SmokeAdvect, SmokeAdvectHand, SmokeAdvectSlabs, SmokeStep};
use diffsim::rollout::{Checkpointing, Workspace};
use diffsim_solvers::boundary::{Boundary, Side};
use diffsim_solvers::smoke::{MacGrid, P2_SIZES, P4_SIZES, Preconditioner, Reference, advect_buoyancy, advect_buoyancy_parallel, divergence, probe};

use crate::boundaries::signed_state;

/// Seeded values in [−1, 1].
pub(crate) fn field(n: usize, seed: u64) -> Vec<f64> {
    (0..n).map(|k| (((k as f64 + 1.0) * 0.6180339887 * (seed as f64 + 0.7)).fract() - 0.5) * 2.0).collect()
}

/// The benchmark on the box `cfg` against its reference `r`, with
/// `precond`, Enzyme's adjoint of the explicit part or the hand-written one.
fn reference<const D: usize>(cfg: MacGrid<D>, r: &Reference, precond: Preconditioner, hand: bool)
where
    SmokeAdvect<D>: Vjp + Jvp,
    SmokeAdvectHand<D>: Vjp,
{
    assert_eq!(cfg.n, [r.n; D]);
    let mut p = SmokeBenchmark::on(cfg, r.steps, precond);
    if hand {
        p = p.with_hand_adjoint();
    }
    let g = p.grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
    let gs = p.smoke_gradient(&g);
    let l2 = gs.iter().map(|v| v * v).sum::<f64>().sqrt();
    let mid = probe::<D>(r.n);
    let (log, name) = (&p.step.project.log, format!("{D}D {} {precond} hand {hand}", r.n));
    eprintln!("{name}: loss {:.10} ‖∇L‖ {l2:.10} g0 {:.8e} probe {:.8e} cg {} / {}", g.loss, gs[0], gs[mid], log.cg_forward.get(), log.cg_adjoint.get());
    assert!((g.loss - r.loss).abs() <= 1e-6 * r.loss, "{name}: loss {} vs {}", g.loss, r.loss);
    assert!((l2 - r.grad_l2).abs() <= 1e-6 * r.grad_l2, "{name}: ‖∇L‖ {l2} vs {}", r.grad_l2);
    assert!((gs[0] - r.grad_0).abs() <= 1e-6 * r.grad_l2, "{name}: g0 {} vs {}", gs[0], r.grad_0);
    assert!((gs[mid] - r.grad_probe).abs() <= 1e-6 * r.grad_l2, "{name}: probe {} vs {}", gs[mid], r.grad_probe);
}

#[test]
fn p2_reference_table_64_all_preconditioners() {
    for precond in [Preconditioner::Multigrid, Preconditioner::Mic0, Preconditioner::None] {
        reference(MacGrid::p2(64), &P2_SIZES[0], precond, false);
    }
}

#[test]
fn p2_reference_table_128() {
    reference(MacGrid::p2(128), &P2_SIZES[1], Preconditioner::Multigrid, false);
}

#[test]
fn p4_reference_table_32_enzyme_and_hand() {
    for hand in [false, true] {
        reference(MacGrid::p4(32), &P4_SIZES[0], Preconditioner::Multigrid, hand);
    }
}

#[test]
fn p4_reference_table_48() {
    reference(MacGrid::p4(48), &P4_SIZES[1], Preconditioner::Multigrid, false);
}

/// The explicit part of the step in the box `cfg` and its slab ranges
/// (`ranges`, tiling the last axis) put back field by field give the whole
/// step bit for bit; the `checked` ranges pass the three checks at the
/// state of `seed` (the whole step: [`projection_and_step_pass`]).
fn explicit_part_and_its_ranges<const D: usize>(cfg: MacGrid<D>, ranges: &[std::ops::Range<usize>], checked: &[std::ops::Range<usize>], seed: u64)
where
    SmokeAdvect<D>: Vjp + Jvp,
    SmokeAdvectSlabs<D>: Vjp + Jvp,
{
    let x = signed_state(&cfg, seed);
    let whole = SmokeAdvect(cfg).eval(&x, &[]);
    let mut joined = vec![0.0; x.len()];
    for ks in ranges {
        let y = SmokeAdvectSlabs::new(cfg, ks.clone()).eval(&x, &[]);
        let mut o = 0;
        for (start, len) in cfg.slab_pieces(ks.clone()) {
            joined[start..start + len].copy_from_slice(&y[o..o + len]);
            o += len;
        }
    }
    assert!(joined.iter().zip(&whole).all(|(a, b)| a.to_bits() == b.to_bits()), "{:?}: the slab ranges do not give the step", cfg.n);
    for ks in checked {
        let r = check_all(&SmokeAdvectSlabs::new(cfg, ks.clone()), &x, &[], &CheckParams::default());
        assert!(r.passed(), "{:?} slabs {ks:?}:\n{r}", cfg.n);
    }
}

#[test]
fn the_explicit_part_by_slab_ranges_is_the_step_and_passes_all_checks() {
    // First rows and last rows (which hold the last faces); a middle range
    // and the top one in 3D.
    explicit_part_and_its_ranges(MacGrid::p2(20), &[0..7, 7..8, 8..20], &[0..5, 12..20], 5);
    // A state where the first rows' Taylor remainder changes sign within
    // the steps (judged by 4R(h) − R(2h); the plain rates had failed).
    explicit_part_and_its_ranges(MacGrid::p2(20), &[0..7, 7..20], std::slice::from_ref(&(0..7)), 9);
    explicit_part_and_its_ranges(MacGrid::p4(8), &[0..3, 3..5, 5..8], &[3..5, 5..8], 3);
    explicit_part_and_its_ranges(MacGrid::p4(16), &split_ranges(16), &[], 9);
}

/// The hand-written adjoint of the explicit part in the box `cfg`: the
/// dot-product test against Enzyme's JVP (an independent pair), finite
/// differences and Taylor of its own, and Enzyme's VJP (over slab ranges in
/// parallel where the box is large enough) equal to it entry by entry.
fn hand_adjoint_is_enzymes<const D: usize>(cfg: MacGrid<D>, seed: u64)
where
    SmokeAdvect<D>: Vjp + Jvp,
    SmokeAdvectHand<D>: Vjp,
{
    let x = signed_state(&cfg, seed);
    let n = cfg.n;
    let r = dot_product_between(&SmokeAdvect(cfg), &SmokeAdvectHand(cfg), &x, &[], &CheckParams { tol: 1e-12, ..Default::default() });
    assert!(r.verdict.passed(), "{n:?}: {r}");
    let fd = finite_differences(&SmokeAdvectHand(cfg), &x, &[], &CheckParams::default());
    assert!(fd.verdict.passed(), "{n:?}: {fd}");
    let t = taylor(&SmokeAdvectHand(cfg), &x, &[], &CheckParams::default());
    assert!(t.verdict.passed(), "{n:?}: {t}");
    let g = field(cfg.n_state(), 4);
    let (mut dy, mut a) = (g.clone(), vec![0.0; cfg.n_state()]);
    SmokeAdvect(cfg).vjp(&x, &[], &mut dy, &mut a, &mut []);
    assert!(dy.iter().all(|&v| v == 0.0), "{n:?}: the seed was not consumed");
    let mut b = vec![0.0; cfg.n_state()];
    SmokeAdvectHand(cfg).vjp(&x, &[], &mut g.clone(), &mut b, &mut []);
    let scale = a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let diff = a.iter().zip(&b).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(diff <= 1e-13 * scale, "{n:?}: Enzyme and hand differ by {diff:e} (scale {scale:e})");
}

#[test]
fn hand_adjoint_passes_the_checks_against_enzyme() {
    for n in [5, 8, 20] {
        hand_adjoint_is_enzymes(MacGrid::p2(n), 40 + n as u64);
    }
    // 16³: Enzyme's adjoint over two slab ranges summed (the parallel path).
    assert_eq!(split_ranges(16).len(), 2);
    for n in [6, 8, 16] {
        hand_adjoint_is_enzymes(MacGrid::p4(n), 40 + n as u64);
    }
}

/// The explicit part, the projection (each preconditioner) and the whole
/// step in P2's or P4's box `cfg` pass the three checks, and the projection of a velocity
/// with closed walls leaves no divergence.
fn projection_and_step_pass<const D: usize>(cfg: MacGrid<D>, seed: u64)
where
    SmokeAdvect<D>: Vjp + Jvp,
{
    let x = signed_state(&cfg, seed);
    let r = check_all(&SmokeAdvect(cfg), &x, &[], &CheckParams::default());
    assert!(r.passed(), "explicit part {:?}:\n{r}", cfg.n);
    for precond in [Preconditioner::Multigrid, Preconditioner::Mic0, Preconditioner::None] {
        let r = check_all(&Project::new(cfg, 1e-13, 500, precond), &x, &[], &CheckParams::default());
        assert!(r.passed(), "projection {:?} {precond}:\n{r}", cfg.n);
        let r = check_all(&SmokeStep::new(cfg, 1e-13, 2000, precond), &x, &[], &CheckParams::default());
        assert!(r.passed(), "step {:?} {precond}:\n{r}", cfg.n);
    }
    let mut x = x;
    let ns = cfg.n_s();
    diffsim_solvers::smoke::enforce_boundary(&cfg, &mut x[ns..]);
    let norm = |y: &[f64]| {
        let mut d = vec![0.0; ns];
        divergence(&cfg, cfg.split(y).1, &mut d);
        d.iter().map(|v| v * v).sum::<f64>().sqrt()
    };
    let y = Project::new(cfg, 1e-12, 500, Preconditioner::Multigrid).eval(&x, &[]);
    assert!(norm(&y) <= 1e-9 * norm(&x), "{:?}: divergence {:e} → {:e}", cfg.n, norm(&x), norm(&y));
}

#[test]
fn projection_and_full_step_pass_all_checks() {
    // 5: odd, no coarse level; 8 and 12: two levels.
    for n in [5, 8, 12] {
        projection_and_step_pass(MacGrid::p2(n), n as u64);
    }
    for n in [6, 8] {
        projection_and_step_pass(MacGrid::p4(n), 10 + n as u64);
    }
}

#[test]
fn multigrid_preconditioner_is_symmetric_and_positive() {
    // CG needs a symmetric positive definite preconditioner: ⟨Mr, s⟩ = ⟨r, Ms⟩
    // and ⟨Mr, r⟩ > 0 for mean-free r (the V-cycle is built to be both).
    // One slab is the square.
    use diffsim_solvers::multigrid::Multigrid;
    for (n, slabs) in [(8, 1), (12, 1), (32, 1), (8, 8), (12, 12)] {
        let mut mg = Multigrid::slabs(n, slabs);
        crate::checks::assert_symmetric_positive(&format!("{n}² × {slabs}"), n * n * slabs, true, |r, z| mg.apply(r, z));
    }
}

/// P2's or P4's gradient on the box `cfg` over `steps` steps is the same
/// for 1, 2 and 3 threads, and the parallel explicit step is the serial
/// one, value for value, on the closed box and with periodic sides.
fn identical_for_any_thread_count<const D: usize>(cfg: MacGrid<D>, steps: usize)
where
    SmokeAdvect<D>: Vjp + Jvp,
{
    crate::checks::assert_identical_for_any_thread_count(|threads| {
        let p = SmokeBenchmark::on(cfg, steps, Preconditioner::Multigrid);
        let g = p.grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
        let periodic_x = Boundary::<D>::CLOSED.with_lower(0, Side::Periodic).with_upper(0, Side::Periodic);
        for boundary in [Boundary::CLOSED, periodic_x, Boundary::all(Side::Periodic)] {
            let cfg = cfg.with_boundary(boundary);
            let x = signed_state(&cfg, 17);
            let (mut serial, mut parallel) = (vec![0.0; x.len()], vec![0.0; x.len()]);
            advect_buoyancy(&cfg, &x, &mut serial);
            advect_buoyancy_parallel(&cfg, &x, &mut parallel);
            assert!(serial.iter().zip(&parallel).all(|(a, b)| a.to_bits() == b.to_bits()), "{threads} threads, {boundary:?}");
        }
        (g.loss, g.dx0)
    });
}

#[test]
fn results_are_identical_for_any_thread_count() {
    // Boxes large enough that the forward advection, CG's sums and (in 3D)
    // the V-cycle's finest level run split over threads (the 2D V-cycle
    // stays on one: split by rows it lost its vector code and ran slower,
    // docs/p2.md).
    const N2: usize = 96;
    const N3: usize = 24;
    const _: () = assert!(N2 * N2 > 2 * diffsim_solvers::par::MIN_PARALLEL && N3 * N3 * N3 > 3 * diffsim_solvers::par::MIN_PARALLEL);
    identical_for_any_thread_count(MacGrid::p2(N2), 4);
    identical_for_any_thread_count(MacGrid::p4(N3), 3);
}

#[test]
fn checkpointing_gives_the_stored_gradient() {
    let p = diffsim::problems::smoke::P2::new(16, 6, Preconditioner::Multigrid);
    let stored = p.grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
    let binomial = p.grad_in(&mut Workspace::new(), Checkpointing::Binomial { snapshots: 2 }).unwrap();
    let scale = stored.dx0.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let diff = stored.dx0.iter().zip(&binomial.dx0).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(diff <= 1e-13 * scale, "{diff:e}");
}

#[test]
fn a_solve_that_cannot_converge_is_an_error() {
    use diffsim::op::OpError;
    use diffsim::rollout::{Pass, RolloutError};
    let mut p = diffsim::problems::smoke::P2::new(16, 3, Preconditioner::None);
    p.step = diffsim::problems::smoke::SmokeStep::new(MacGrid::p2(16), 1e-12, 3, Preconditioner::None);
    match p.value() {
        Err(RolloutError::Operator { pass: Pass::Forward, error: OpError::NoConvergence { iterations: 3, relative_residual, .. } }) => {
            assert!(relative_residual > 1e-12 && relative_residual.is_finite())
        }
        other => panic!("expected a non-convergence error, got {other:?}"),
    }
}

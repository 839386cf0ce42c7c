//! P4 smoke3d: the reference table of docs/benchmarks.md (loss and ‖∇L‖ to 1e-6
//! relative, entries to 1e-6·‖∇L‖) with Enzyme's and the hand-written
//! adjoint; the 3D operators under the three gradient checks; the shared
//! multigrid preconditioner in 3D.

use diffsim::check::{CheckParams, check_all};
use diffsim::problems::ranges::split_ranges as slab_ranges;
use diffsim::problems::smoke::{SmokeAdvect, SmokeAdvectHand, SmokeAdvectSlabs};
use diffsim::problems::smoke3d::{P4, Project3, SmokeStep3};
use diffsim::rollout::{Checkpointing, Workspace};
use diffsim_solvers::smoke::MacGrid;
use diffsim_solvers::smoke::Preconditioner;
use diffsim_solvers::smoke::{P4_SIZES, probe};

fn check_size(k: usize, hand: bool) {
    let r = &P4_SIZES[k];
    let mut p = P4::new(r.n, r.steps, Preconditioner::Multigrid);
    if hand {
        p = p.with_hand_adjoint();
    }
    let g = p.grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
    let gs = p.smoke_gradient(&g);
    let l2 = gs.iter().map(|v| v * v).sum::<f64>().sqrt();
    let mid = probe::<3>(r.n);
    eprintln!(
        "P4 {} hand {hand}: loss {:.10} ‖∇L‖ {:.10} g0 {:.8e} gmid {:.8e} cg {} / {}",
        r.n,
        g.loss,
        l2,
        gs[0],
        gs[mid],
        p.step.project.log.cg_forward.get(),
        p.step.project.log.cg_adjoint.get()
    );
    assert!((g.loss - r.loss).abs() <= 1e-6 * r.loss, "loss {} vs {}", g.loss, r.loss);
    assert!((l2 - r.grad_l2).abs() <= 1e-6 * r.grad_l2, "‖∇L‖ {} vs {}", l2, r.grad_l2);
    assert!((gs[0] - r.grad_0).abs() <= 1e-6 * r.grad_l2, "g0 {} vs {}", gs[0], r.grad_0);
    assert!((gs[mid] - r.grad_probe).abs() <= 1e-6 * r.grad_l2, "gmid {} vs {}", gs[mid], r.grad_probe);
}

#[test]
fn reference_table_32_enzyme_and_hand() {
    check_size(0, false);
    check_size(0, true);
}

#[test]
fn reference_table_48() {
    check_size(1, false);
}

pub(crate) fn field(n: usize, seed: u64) -> Vec<f64> {
    (0..n).map(|k| (((k as f64 + 1.0) * 0.6180339887 * (seed as f64 + 0.7)).fract() - 0.5) * 2.0).collect()
}

/// A state with smoke in [0, 2] and each velocity component of one sign
/// (u and w positive, v negative) with speeds in [0.15, 0.45] cells per
/// step: the means a trace uses stay as far from 0, so every traced point
/// lies at least 0.15 cells from the lattice planes where trilinear
/// sampling kinks, as the Taylor test needs.
pub(crate) fn state(cfg: &MacGrid<3>, seed: u64) -> Vec<f64> {
    let (ns, nu, nv) = (cfg.n_s(), cfg.n_face(0), cfg.n_face(1));
    field(cfg.n_state(), seed)
        .iter()
        .enumerate()
        .map(|(k, v)| {
            let speed = 0.3 + 0.15 * v;
            if k < ns {
                1.0 + v
            } else if k < ns + nu || k >= ns + nu + nv {
                speed
            } else {
                -speed
            }
        })
        .collect()
}

#[test]
fn explicit_part_passes_all_checks() {
    for n in [6, 7] {
        let cfg = MacGrid::p4(n);
        let x = state(&cfg, n as u64);
        let r = check_all(&SmokeAdvect(cfg), &x, &[], &CheckParams::default());
        assert!(r.passed(), "Enzyme n = {n}:\n{r}");
    }
    // The slab ranges whose adjoints the parallel VJP sums: a middle range
    // and the top one (which also holds the last z-faces).
    let cfg = MacGrid::p4(8);
    let x = state(&cfg, 3);
    for ks in [3..5, 5..8] {
        let r = check_all(&SmokeAdvectSlabs::new(cfg, ks.clone()), &x, &[], &CheckParams::default());
        assert!(r.passed(), "slabs {ks:?}:\n{r}");
    }
}

#[test]
fn slab_ranges_tile_the_step() {
    use diffsim::op::OperatorExt;
    let cfg = MacGrid::p4(16);
    let x = state(&cfg, 9);
    let full = SmokeAdvect(cfg).eval(&x, &[]);
    let ranges = slab_ranges(cfg.n[2]);
    assert_eq!(ranges.len(), 2);
    let mut pieces: Vec<Vec<f64>> = vec![Vec::new(); 4];
    for ks in &ranges {
        let y = SmokeAdvectSlabs::new(cfg, ks.clone()).eval(&x, &[]);
        let mut o = 0;
        for (f, (_, len)) in cfg.slab_pieces(ks.clone()).into_iter().enumerate() {
            pieces[f].extend_from_slice(&y[o..o + len]);
            o += len;
        }
    }
    let joined: Vec<f64> = pieces.concat();
    assert!(joined.iter().zip(&full).all(|(a, b)| a.to_bits() == b.to_bits()), "the slab ranges do not give the step");
}

#[test]
fn hand_adjoint_passes_the_checks_against_enzyme() {
    use diffsim::check::{dot_product_between, finite_differences, taylor};
    use diffsim::op::Vjp;
    for n in [6, 8, 16] {
        let cfg = MacGrid::p4(n);
        let x = state(&cfg, 40 + n as u64);
        if n == 16 {
            // Enzyme's adjoint over two slab ranges summed (the parallel
            // path) against the hand adjoint, entry by entry, below.
            assert_eq!(slab_ranges(n).len(), 2);
        }
        // Enzyme's JVP against the hand VJP: an independent pair.
        let r = dot_product_between(&SmokeAdvect(cfg), &SmokeAdvectHand(cfg), &x, &[], &CheckParams { tol: 1e-12, ..Default::default() });
        assert!(r.verdict.passed(), "n = {n}: {r}");
        let fd = finite_differences(&SmokeAdvectHand(cfg), &x, &[], &CheckParams::default());
        assert!(fd.verdict.passed(), "n = {n}: {fd}");
        let t = taylor(&SmokeAdvectHand(cfg), &x, &[], &CheckParams::default());
        assert!(t.verdict.passed(), "n = {n}: {t}");
        // And the two VJPs themselves, entry by entry.
        let seed = field(cfg.n_state(), 4);
        let (mut a, mut b) = (vec![0.0; cfg.n_state()], vec![0.0; cfg.n_state()]);
        SmokeAdvect(cfg).vjp(&x, &[], &mut seed.clone(), &mut a, &mut []);
        SmokeAdvectHand(cfg).vjp(&x, &[], &mut seed.clone(), &mut b, &mut []);
        let scale = a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let diff = a.iter().zip(&b).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        assert!(diff <= 1e-13 * scale, "n = {n}: Enzyme and hand differ by {diff:e} (scale {scale:e})");
    }
}

#[test]
fn projection_and_full_step_pass_all_checks() {
    for n in [6, 8] {
        let cfg = MacGrid::p4(n);
        let x = state(&cfg, 10 + n as u64);
        for precond in [Preconditioner::Multigrid, Preconditioner::None] {
            let r = check_all(&Project3::new(cfg, 1e-13, 500, precond), &x, &[], &CheckParams::default());
            assert!(r.passed(), "projection n = {n} {precond}:\n{r}");
        }
        let r = check_all(&SmokeStep3::new(cfg, 1e-13, 500, Preconditioner::Multigrid), &x, &[], &CheckParams::default());
        assert!(r.passed(), "step n = {n}:\n{r}");
    }
}

#[test]
fn projection_leaves_no_divergence() {
    use diffsim::op::OperatorExt;
    let cfg = MacGrid::p4(12);
    // A velocity with closed walls (the projection changes interior faces only).
    let mut x = state(&cfg, 5);
    let ns = cfg.n_s();
    diffsim_solvers::smoke::enforce_boundary(&cfg, &mut x[ns..]);
    let y = Project3::new(cfg, 1e-12, 500, Preconditioner::Multigrid).eval(&x, &[]);
    let (_, [u, v, w]) = cfg.split(&y);
    let mut d = vec![0.0; cfg.n_s()];
    diffsim_solvers::smoke::divergence(&cfg, [u, v, w], &mut d);
    let before = {
        let (_, [u, v, w]) = cfg.split(&x);
        let mut d0 = vec![0.0; cfg.n_s()];
        diffsim_solvers::smoke::divergence(&cfg, [u, v, w], &mut d0);
        d0.iter().map(|v| v * v).sum::<f64>().sqrt()
    };
    let after = d.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!(after <= 1e-9 * before, "divergence {before:e} → {after:e}");
}

#[test]
fn multigrid_preconditioner_is_symmetric_and_positive_in_3d() {
    use diffsim_solvers::multigrid::Multigrid;
    for n in [8, 12] {
        let mut mg = Multigrid::cube(n);
        crate::checks::assert_symmetric_positive(&format!("n = {n}"), n * n * n, true, |r, z| mg.apply(r, z));
    }
}

/// The grid of the thread-count test: large enough that the forward
/// advection, the V-cycle's finest level and CG's sums run split over
/// threads.
const THREADED_N: usize = 24;
const _: () = assert!(THREADED_N * THREADED_N * THREADED_N > 3 * diffsim_solvers::par::MIN_PARALLEL);

#[test]
fn results_are_identical_for_any_thread_count() {
    crate::checks::assert_identical_for_any_thread_count(|threads| {
        let p = P4::new(THREADED_N, 3, Preconditioner::Multigrid);
        let g = p.grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
        let cfg = MacGrid::p4(THREADED_N);
        let x = state(&cfg, 5);
        let (mut serial, mut parallel) = (vec![0.0; x.len()], vec![0.0; x.len()]);
        diffsim_solvers::smoke::advect_buoyancy(&cfg, &x, &mut serial);
        diffsim_solvers::smoke::advect_buoyancy_parallel(&cfg, &x, &mut parallel);
        assert!(serial.iter().zip(&parallel).all(|(a, b)| a.to_bits() == b.to_bits()), "{threads} threads: the parallel advection differs from the serial one");
        (g.loss, g.dx0)
    });
}

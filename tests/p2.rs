//! P2 smoke2d: the reference table of docs/benchmarks.md (loss and ‖∇L‖ to 1e-6
//! relative, entries to 1e-6·‖∇L‖), with both preconditioners.

use diffsim::problems::smoke::P2;
use diffsim::rollout::{Checkpointing, Workspace};
use diffsim_solvers::smoke::{P2_SIZES, Preconditioner};

fn check_size(k: usize, preconds: &[Preconditioner]) {
    let r = &P2_SIZES[k];
    for &precond in preconds {
        let p = P2::new(r.n, r.steps, precond);
        let g = p.grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
        let gs = p.smoke_gradient(&g);
        let l2 = gs.iter().map(|v| v * v).sum::<f64>().sqrt();
        eprintln!(
            "P2 {} {precond}: loss {:.10} ‖∇L‖ {:.10} g0 {:.8e} gn2 {:.8e} cg {} / {}",
            r.n,
            g.loss,
            l2,
            gs[0],
            gs[r.n * r.n / 2],
            p.step.project.log.cg_forward.get(),
            p.step.project.log.cg_adjoint.get()
        );
        assert!((g.loss - r.loss).abs() <= 1e-6 * r.loss, "loss {} vs {}", g.loss, r.loss);
        assert!((l2 - r.grad_l2).abs() <= 1e-6 * r.grad_l2, "‖∇L‖ {} vs {}", l2, r.grad_l2);
        assert!((gs[0] - r.grad_0).abs() <= 1e-6 * r.grad_l2, "g0 {} vs {}", gs[0], r.grad_0);
        assert!((gs[r.n * r.n / 2] - r.grad_probe).abs() <= 1e-6 * r.grad_l2, "gN2 {} vs {}", gs[r.n * r.n / 2], r.grad_probe);
    }
}

#[test]
fn reference_table_64_all_preconditioners() {
    check_size(0, &[Preconditioner::Multigrid, Preconditioner::Mic0, Preconditioner::None]);
}

#[test]
fn reference_table_128() {
    check_size(1, &[Preconditioner::Multigrid]);
}

#[test]
fn checkpointing_gives_the_stored_gradient() {
    let p = P2::new(16, 6, Preconditioner::Multigrid);
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
    use diffsim_solvers::smoke::MacGrid;
    let mut p = P2::new(16, 3, Preconditioner::None);
    p.step = diffsim::problems::smoke::SmokeStep::new(MacGrid::p2(16), 1e-12, 3, Preconditioner::None);
    match p.value() {
        Err(RolloutError::Operator { pass: Pass::Forward, error: OpError::NoConvergence { iterations: 3, relative_residual, .. } }) => {
            assert!(relative_residual > 1e-12 && relative_residual.is_finite())
        }
        other => panic!("expected a non-convergence error, got {other:?}"),
    }
}

#[test]
fn multigrid_preconditioner_is_symmetric_and_positive() {
    // CG needs a symmetric positive definite preconditioner: ⟨Mr, s⟩ = ⟨r, Ms⟩
    // and ⟨Mr, r⟩ > 0 for mean-free r (the V-cycle is built to be both).
    use diffsim_solvers::multigrid::Multigrid;
    for n in [8, 12, 32] {
        let mut mg = Multigrid::new(n);
        crate::checks::assert_symmetric_positive(&format!("n = {n}"), n * n, true, |r, z| mg.apply(r, z));
    }
}

#[test]
fn obstacles_block_the_flow_and_the_projection_keeps_the_fluid_divergence_free() {
    use diffsim::op::OperatorExt;
    use diffsim::problems::smoke::SmokeStep;
    use diffsim_solvers::smoke::{MacGrid, divergence, initial};
    let n = 24;
    let cfg = MacGrid::p2(n);
    let solid: Vec<bool> = (0..n * n).map(|c| (8..16).contains(&(c % n)) && (10..12).contains(&(c / n))).collect();
    let step = SmokeStep::with_obstacles(cfg, 1e-10, 2000, &solid);
    let mut x = initial(&cfg);
    for _ in 0..8 {
        x = step.eval(&x, &[]);
    }
    let (s, [u, v]) = cfg.split(&x);
    let nu = n + 1;
    for j in 0..n {
        for i in 0..n {
            let c = j * n + i;
            if solid[c] {
                assert_eq!(s[c], 0.0);
                assert_eq!((u[j * nu + i], u[j * nu + i + 1], v[j * n + i], v[(j + 1) * n + i]), (0.0, 0.0, 0.0, 0.0), "flow through the solid cell {i},{j}");
            }
        }
    }
    let mut d = vec![0.0; n * n];
    divergence(&cfg, [u, v], &mut d);
    let worst = d.iter().zip(&solid).filter(|(_, s)| !**s).map(|(d, _)| d.abs()).fold(0.0, f64::max);
    assert!(worst < 1e-8, "divergence {worst:e} in the fluid");
    assert!(s.iter().any(|&v| v > 0.1), "the smoke should still be there");
}

#[test]
fn obstacle_shapes() {
    use diffsim_solvers::smoke::{MacGrid, Solid, solid_cells};
    let obstacle_box =
        |cfg: &MacGrid<2>, lower: [f64; 2], upper: [f64; 2]| Some(solid_cells(cfg, &[Solid::Box { lower, upper }])).filter(|c| c.contains(&true));
    let obstacle_disc =
        |cfg: &MacGrid<2>, center: [f64; 2], radius: f64| Some(solid_cells(cfg, &[Solid::Ball { center, radius }])).filter(|c| c.contains(&true));
    let b = obstacle_box(&MacGrid::p2(8), [2.0, 3.0], [5.0, 4.0]).unwrap();
    let cells: Vec<usize> = (0..64).filter(|&c| b[c]).collect();
    assert_eq!(cells, vec![3 * 8 + 2, 3 * 8 + 3, 3 * 8 + 4]);
    // Partly outside: clipped; wholly outside: none.
    assert_eq!(obstacle_box(&MacGrid::p2(8), [6.0, 6.0], [20.0, 20.0]).unwrap().iter().filter(|&&s| s).count(), 4);
    assert!(obstacle_box(&MacGrid::p2(8), [9.0, 9.0], [12.0, 12.0]).is_none());
    let d = obstacle_disc(&MacGrid::p2(16), [8.0, 8.0], 2.0).unwrap();
    assert_eq!(d.iter().filter(|&&s| s).count(), 12);
    assert!(obstacle_disc(&MacGrid::p2(16), [40.0, 40.0], 2.0).is_none());
    // On an oblong box cells are counted along rows of `nx`.
    let r = obstacle_box(&MacGrid::new([8, 4]), [6.0, 1.0], [20.0, 2.0]).unwrap();
    assert_eq!((r.len(), (0..32).filter(|&c| r[c]).collect::<Vec<_>>()), (32, vec![14, 15]));
}

#[test]
fn the_2d_step_is_identical_for_any_thread_count() {
    use diffsim_solvers::boundary::{Boundary, Side};
    use diffsim_solvers::smoke::{MacGrid, advect_buoyancy, advect_buoyancy_parallel};
    // 96² cells: the forward advection and CG's sums run split over
    // threads (the 2D V-cycle stays on one: split by rows it lost its
    // vector code and ran slower, docs/p2.md).
    const N: usize = 96;
    const _: () = assert!(N * N > 2 * diffsim_solvers::par::MIN_PARALLEL);
    crate::checks::assert_identical_for_any_thread_count(|threads| {
        let p = P2::new(N, 4, Preconditioner::Multigrid);
        let g = p.grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
        // The parallel advection is the serial one, value for value, on the
        // closed box and with periodic sides.
        for boundary in [Boundary::CLOSED, Boundary::axes([Side::Periodic, Side::Closed]), Boundary::all(Side::Periodic)] {
            let cfg = MacGrid::p2(N).with_boundary(boundary);
            let x = crate::checks::smoke_state(&cfg, 17);
            let (mut serial, mut parallel) = (vec![0.0; x.len()], vec![0.0; x.len()]);
            advect_buoyancy(&cfg, &x, &mut serial);
            advect_buoyancy_parallel(&cfg, &x, &mut parallel);
            assert!(serial.iter().zip(&parallel).all(|(a, b)| a.to_bits() == b.to_bits()), "{threads} threads, {boundary:?}");
        }
        (g.loss, g.dx0)
    });
}

#[test]
fn the_step_by_row_ranges_is_the_step_and_its_parallel_adjoint_is_the_hand_one() {
    use diffsim::check::{CheckParams, check_all};
    use diffsim::op::{OperatorExt, Vjp};
    use diffsim::problems::smoke::{SmokeAdvect, SmokeAdvectSlabs};
    use diffsim_solvers::smoke::{MacGrid, advect_buoyancy, advect_buoyancy_adjoint};
    let cfg = MacGrid::p2(20);
    let x = crate::checks::smoke_state(&cfg, 29);
    let mut whole = vec![0.0; x.len()];
    advect_buoyancy(&cfg, &x, &mut whole);
    // Row ranges put back field by field give the whole step, bit for bit.
    let mut joined = vec![0.0; x.len()];
    for js in [0..7, 7..8, 8..20] {
        let y = SmokeAdvectSlabs::new(cfg, js.clone()).eval(&x, &[]);
        let mut o = 0;
        for (start, len) in cfg.slab_pieces(js.clone()) {
            joined[start..start + len].copy_from_slice(&y[o..o + len]);
            o += len;
        }
    }
    assert!(joined.iter().zip(&whole).all(|(a, b)| a.to_bits() == b.to_bits()), "row ranges differ from the step");
    // A range's own derivatives pass the checks (first rows, last rows), at
    // a state whose traced points all lie away from the lattice lines (u of
    // one sign, v of the other, speeds in [0.15, 0.45]).
    let (ns, nu) = (cfg.n_s(), cfg.n_face(0));
    let away: Vec<f64> = crate::p4::field(cfg.n_state(), 5)
        .iter()
        .enumerate()
        .map(|(k, v)| {
            if k < ns {
                1.0 + v
            } else if k < ns + nu {
                0.3 + 0.15 * v
            } else {
                -0.3 - 0.15 * v
            }
        })
        .collect();
    for js in [0..5, 12..20] {
        let r = check_all(&SmokeAdvectSlabs::new(cfg, js.clone()), &away, &[], &CheckParams::default());
        assert!(r.passed(), "rows {js:?}:\n{r}");
    }
    // The VJP over two ranges in parallel equals the hand-written adjoint.
    let g = crate::checks::smoke_state(&cfg, 31);
    let (mut dy, mut enzyme) = (g.clone(), vec![0.0; x.len()]);
    SmokeAdvect(cfg).vjp(&x, &[], &mut dy, &mut enzyme, &mut []);
    assert!(dy.iter().all(|&v| v == 0.0), "the seed was not consumed");
    let (mut gy, mut hand) = (g.clone(), vec![0.0; x.len()]);
    advect_buoyancy_adjoint(&cfg, &x, &mut gy, &mut hand);
    let scale = hand.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let worst = enzyme.iter().zip(&hand).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-13 * scale, "parallel Enzyme adjoint vs hand: {worst:e}");
}

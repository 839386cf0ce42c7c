//! Obstacles, in 2D and 3D: solid cells from shapes, the boundary
//! condition they impose (no smoke in them, no flow through their faces)
//! and the projection that couples fluid cells only, under the three
//! gradient checks, against the hand adjoint through a whole rollout, and
//! what each preconditioner costs around them.

use diffsim::check::{CheckParams, check_all};
use diffsim::fluids::Project;
use diffsim::op::{Forward, OperatorExt};
use diffsim::problems::SmokeBenchmark;
use diffsim::problems::smoke::{SmokeAdvect, SmokeAdvectHand, SmokeStep};
use diffsim::rollout::{Checkpointing, Workspace};
use diffsim_solvers::smoke::{MacGrid, Preconditioner, Solid, open_faces, solid_cells};

use crate::boundaries::{max_divergence, signed_state};

/// A ball and a box, away from each other and from the walls of a box of
/// `n` cells a side.
fn shapes<const D: usize>(n: usize) -> Vec<Solid<D>> {
    let h = n as f64;
    let at = |v: [f64; 3]| -> [f64; D] { std::array::from_fn(|a| v[a] * h) };
    vec![Solid::Ball { center: at([0.35, 0.5, 0.5]), radius: 0.2 * h }, Solid::Box { lower: at([0.65, 0.25, 0.3]), upper: at([0.8, 0.5, 0.6]) }]
}

#[test]
fn shapes_cover_the_cells_they_should() {
    let n = 24;
    let cfg = MacGrid::p4(n);
    let h = n as f64;
    // A sphere of radius 0.3·N: its volume in cells to a few percent.
    let r = 0.3 * h;
    let ball = solid_cells(&cfg, &[Solid::Ball { center: [h / 2.0; 3], radius: r }]);
    let count = ball.iter().filter(|&&s| s).count() as f64;
    let exact = 4.0 / 3.0 * std::f64::consts::PI * r.powi(3);
    assert!((count - exact).abs() < 0.05 * exact, "sphere: {count} cells, volume {exact}");
    // A cylinder along each axis is the same set of cells turned.
    let cyl = |axis: usize| solid_cells(&cfg, &[Solid::Cylinder { axis, center: [0.4 * h, 0.4 * h, 0.4 * h], radius: 0.25 * h, extent: [2.0, 20.0] }]);
    let (cx, cz) = (cyl(0), cyl(2));
    let at = |i: usize, j: usize, k: usize| (k * n + j) * n + i;
    let mut cells = 0;
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                // Along z at (i, j, k) is along x at (k, j, i) with x and z swapped.
                assert_eq!(cz[at(i, j, k)], cx[at(k, j, i)], "cylinder cell ({i}, {j}, {k})");
                cells += cz[at(i, j, k)] as usize;
            }
        }
    }
    // 18 slabs (centres 2.5..=19.5) of the disc's cells.
    let disc = (0..n * n).filter(|c| ((c % n) as f64 + 0.5 - 0.4 * h).powi(2) + ((c / n) as f64 + 0.5 - 0.4 * h).powi(2) <= (0.25 * h).powi(2)).count();
    assert!(disc > 100);
    assert_eq!(cells, 18 * disc, "cylinder cells");
    // A box is the cells whose centres lie inside, clipped to the domain.
    let b = solid_cells(&cfg, &[Solid::Box { lower: [-5.0, 3.0, 20.0], upper: [2.0, 5.0, 30.0] }]);
    assert_eq!(b.iter().filter(|&&s| s).count(), 2 * 2 * 4);
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

/// In the closed box `cfg` with the solid cells `solid`: the projection
/// leaves no divergence in the fluid, no smoke in the solids and no flow
/// through their faces, and changes the flow (it is not the closed box's
/// projection); whole steps from P2's or P4's start keep all of it.
fn obstacles_block_the_flow<const D: usize>(cfg: MacGrid<D>, solid: &[bool])
where
    SmokeAdvect<D>: Forward,
{
    let fluid: Vec<f64> = solid.iter().map(|&s| if s { 0.0 } else { 1.0 }).collect();
    let open = open_faces(&cfg, &fluid);
    for precond in [Preconditioner::Multigrid, Preconditioner::Mic0] {
        let op = Project::with_obstacles(cfg, 1e-12, 1000, precond, solid);
        // Closed walls (the projection changes interior faces only).
        let mut x = signed_state(&cfg, 7);
        let ns = cfg.n_s();
        diffsim_solvers::smoke::enforce_boundary(&cfg, &mut x[ns..]);
        let step = SmokeStep::new(cfg, 1e-10, 2000, precond).with_obstacles(solid);
        let mut z = diffsim_solvers::smoke::initial(&cfg);
        for _ in 0..8 {
            z = step.eval(&z, &[]);
        }
        assert!(z[..ns].iter().any(|&v| v > 0.1), "the smoke should still be there");
        for y in [op.eval(&x, &[]), z] {
            assert!(op.take_error().is_none());
            let s = &y[..ns];
            let speed = y[ns..].iter().map(|v| v * v).sum::<f64>().sqrt();
            let worst = max_divergence(&cfg, &y, Some(solid));
            assert!(worst <= 1e-8 * speed.max(1.0), "{:?} {precond}: divergence {worst:e} (speed {speed:e})", cfg.n);
            for (c, &sv) in s.iter().enumerate() {
                assert!(!solid[c] || sv == 0.0, "smoke in solid cell {c}");
            }
            for (k, (&v, &o)) in y[ns..].iter().zip(&open).enumerate() {
                assert!(o != 0.0 || v == 0.0, "{:?}: velocity sample {k} touches a solid and carries {v}", cfg.n);
            }
        }
        // The obstacles change the flow: the masked projection is not the
        // closed box's.
        let plain = Project::new(cfg, 1e-12, 1000, precond).eval(&x, &[]);
        assert!(plain.iter().zip(&op.eval(&x, &[])).any(|(a, b)| (a - b).abs() > 1e-3));
        eprintln!("projection with obstacles at {:?}, {precond}: {} CG iterations", cfg.n, op.log.cg_forward.get());
    }
}

#[test]
fn obstacles_block_the_flow_and_the_projection_keeps_the_fluid_divergence_free() {
    let n = 24;
    let solid: Vec<bool> = (0..n * n).map(|c| (8..16).contains(&(c % n)) && (10..12).contains(&(c / n))).collect();
    obstacles_block_the_flow(MacGrid::p2(n), &solid);
    obstacles_block_the_flow(MacGrid::p4(16), &solid_cells(&MacGrid::p4(16), &shapes(16)));
}

/// The three checks of the projection (each preconditioner) and of the
/// whole step, with the [`shapes`], in P2's or P4's box of `n` cells a side.
fn projection_and_step_with_obstacles_pass<const D: usize>(cfg: MacGrid<D>, seed: u64)
where
    SmokeAdvect<D>: diffsim::op::Vjp + diffsim::op::Jvp,
{
    let solid = solid_cells(&cfg, &shapes(cfg.n[0]));
    assert!(solid.iter().any(|&s| s), "{:?}: the shapes cover no cell", cfg.n);
    let x = signed_state(&cfg, seed);
    for precond in [Preconditioner::Multigrid, Preconditioner::Mic0, Preconditioner::None] {
        let r = check_all(&Project::with_obstacles(cfg, 1e-13, 500, precond, &solid), &x, &[], &CheckParams::default());
        assert!(r.passed(), "projection {:?} {precond}:\n{r}", cfg.n);
    }
    let step = SmokeStep::new(cfg, 1e-13, 500, Preconditioner::Multigrid).with_obstacles(&solid);
    let r = check_all(&step, &x, &[], &CheckParams::default());
    assert!(r.passed(), "step {:?}:\n{r}", cfg.n);
}

#[test]
fn projection_and_step_with_obstacles_pass_all_checks() {
    for n in [6, 9] {
        projection_and_step_with_obstacles_pass(MacGrid::p2(n), 70 + n as u64);
    }
    for n in [6, 8] {
        projection_and_step_with_obstacles_pass(MacGrid::p4(n), 20 + n as u64);
    }
}

/// P2 or P4 on the box `cfg` over 6 steps with a ball above the smoke:
/// Enzyme's explicit adjoint and the hand-written one, chained with the
/// masked projection's implicit adjoint, give the same gradient, and none
/// reaches the initial smoke inside the solid.
fn rollout_with_obstacles_enzyme_is_hand<const D: usize>(cfg: MacGrid<D>)
where
    SmokeAdvect<D>: diffsim::op::Vjp + diffsim::op::Jvp,
    SmokeAdvectHand<D>: diffsim::op::Vjp,
{
    let h = cfg.n[0] as f64;
    let center = std::array::from_fn(|a| if a == 1 { 0.55 * h } else { 0.5 * h });
    let solid = solid_cells(&cfg, &[Solid::Ball { center, radius: 0.15 * h }]);
    let run = |hand: bool| {
        let mut p = SmokeBenchmark::on(cfg, 6, Preconditioner::Multigrid);
        p.step = p.step.with_obstacles(&solid);
        if hand {
            p = p.with_hand_adjoint();
        }
        let g = p.grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
        (g.loss, p.smoke_gradient(&g).to_vec())
    };
    let (la, ga) = run(false);
    let (lb, gb) = run(true);
    let plain = SmokeBenchmark::on(cfg, 6, Preconditioner::Multigrid).grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
    assert!((la - plain.loss).abs() > 1e-6 * plain.loss, "{:?}: the ball does not change the loss ({la} vs {})", cfg.n, plain.loss);
    assert!((la - lb).abs() <= 1e-13 * la.abs(), "{:?}: loss {la} vs {lb}", cfg.n);
    let scale = ga.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let diff = ga.iter().zip(&gb).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(diff <= 1e-10 * scale, "{:?}: Enzyme and hand gradients differ by {diff:e} (scale {scale:e})", cfg.n);
    for (c, &s) in solid.iter().enumerate() {
        if s {
            assert_eq!(ga[c], 0.0, "{:?}: gradient in solid cell {c}", cfg.n);
        }
    }
}

#[test]
fn rollout_with_obstacles_enzyme_matches_the_hand_adjoint() {
    rollout_with_obstacles_enzyme_is_hand(MacGrid::p2(32));
    rollout_with_obstacles_enzyme_is_hand(MacGrid::p4(16));
}

/// In a box whose sides all differ, with a ball: the projection passes the
/// checks with MIC(0) of its own matrix, the aggregation V-cycle on the
/// fluid cells and none; leaves no divergence; and the MIC(0) factor is
/// symmetric and positive (CG needs both).
fn projection_of_any_box_passes<const D: usize>(n: [usize; D], ball: Solid<D>) {
    use diffsim_solvers::smoke::{Coefficients, Mic};
    let cfg = MacGrid::new(n);
    let solid = solid_cells(&cfg, &[ball]);
    assert!(solid.iter().any(|&s| s));
    let x = signed_state(&cfg, 61);
    for precond in [Preconditioner::Mic0, Preconditioner::Multigrid, Preconditioner::None] {
        let r = check_all(&Project::with_obstacles(cfg, 1e-13, 500, precond, &solid), &x, &[], &CheckParams::default());
        assert!(r.passed(), "projection {n:?} {precond}:\n{r}");
    }
    let mut x = x;
    let ns = cfg.n_s();
    diffsim_solvers::smoke::enforce_boundary(&cfg, &mut x[ns..]);
    let op = Project::with_obstacles(cfg, 1e-12, 500, Preconditioner::Mic0, &solid);
    let y = op.eval(&x, &[]);
    let worst = max_divergence(&cfg, &y, None);
    assert!(worst < 1e-9, "{n:?}: divergence left: {worst:e}");
    let fluid: Vec<f64> = solid.iter().map(|&s| if s { 0.0 } else { 1.0 }).collect();
    let mut mic = Mic::new(&Coefficients::new(&cfg, Some(&fluid)));
    crate::checks::assert_symmetric_positive("MIC(0)", ns, false, |r, z| mic.apply(r, z));
}

#[test]
fn projection_of_any_box_with_mic0_passes_the_checks() {
    projection_of_any_box_passes([11, 7], Solid::Ball { center: [5.5, 3.5], radius: 1.6 });
    projection_of_any_box_passes([7, 9, 5], Solid::Ball { center: [3.5, 4.5, 2.5], radius: 1.6 });
}

/// What each preconditioner costs in iterations in P2's or P4's box with a
/// ball (printed; the solves must converge): multigrid of the box on the
/// fluid cells, MIC(0) of the matrix, none.
fn iterations_per_preconditioner<const D: usize>(cfg: MacGrid<D>, ball: Solid<D>) {
    let solid = solid_cells(&cfg, &[ball]);
    let mut x = signed_state(&cfg, 71);
    let ns = cfg.n_s();
    diffsim_solvers::smoke::enforce_boundary(&cfg, &mut x[ns..]);
    let mut counts = Vec::new();
    for precond in [Preconditioner::Multigrid, Preconditioner::Mic0, Preconditioner::None] {
        for obstacles in [false, true] {
            let op = if obstacles { Project::with_obstacles(cfg, 1e-8, 2000, precond, &solid) } else { Project::new(cfg, 1e-8, 2000, precond) };
            op.eval(&x, &[]);
            assert!(op.take_error().is_none(), "{:?} {precond} obstacles {obstacles}", cfg.n);
            counts.push(format!("{precond}{}: {}", if obstacles { " + ball" } else { "" }, op.log.cg_forward.get()));
        }
    }
    eprintln!("CG iterations at {:?}, tolerance 1e-8: {}", cfg.n, counts.join(", "));
}

#[test]
fn iterations_per_preconditioner_in_2d_and_3d() {
    iterations_per_preconditioner(MacGrid::p2(64), Solid::Ball { center: [32.0, 38.0], radius: 12.0 });
    iterations_per_preconditioner(MacGrid::p4(24), Solid::Ball { center: [12.0, 14.0, 12.0], radius: 5.0 });
}

#[test]
fn multigrid_takes_any_box_with_two_equal_sides() {
    use diffsim_solvers::multigrid::Multigrid;
    // Square slabs stacked along z, y and x (the field reordered so the
    // slabs come last): the projection passes the checks with obstacles,
    // and the V-cycle of a stack of slabs is symmetric and positive.
    for dims in [[8, 8, 12], [6, 10, 6], [10, 6, 6]] {
        let cfg = MacGrid::new([dims[0], dims[1], dims[2]]).with_dt(1.0);
        let solid = solid_cells(&cfg, &[Solid::Ball { center: [dims[0] as f64 / 2.0, dims[1] as f64 / 2.0, dims[2] as f64 / 2.0], radius: 1.8 }]);
        let op = Project::with_obstacles(cfg, 1e-13, 500, Preconditioner::Multigrid, &solid);
        assert_eq!(op.preconditioner(), Preconditioner::Multigrid);
        let x = signed_state(&cfg, 81);
        let r = check_all(&op, &x, &[], &CheckParams::default());
        assert!(r.passed(), "{dims:?}:\n{r}");
    }
    let (n, nz) = (8, 24);
    let mut mg = Multigrid::slabs(n, nz);
    assert!(mg.depth() >= 2);
    crate::checks::assert_symmetric_positive("slabs 8² × 24", n * n * nz, true, |r, z| mg.apply(r, z));
}

//! Boundary kinds of the 3D fluid (closed, periodic, inflow with a profile,
//! outflow on any of the six sides): validation, agreement with the 2D
//! solver on flows that do not vary along a periodic z, the exact
//! behaviour each kind promises, and the three gradient checks of every 3D
//! operator under every kind, with and without an obstacle.

use diffsim::check::{CheckParams, check_all};
use diffsim::fluids::Advect;
use diffsim::fluids::{Diffuse, DiffuseExplicit, DiffuseImplicit};
use diffsim::op::{Forward, OperatorExt};
use diffsim::problems::smoke3d::Project3;
use diffsim_solvers::boundary::for_each_face;
use diffsim_solvers::boundary::{Boundary, BoundaryError, Profile, Side};
use diffsim_solvers::smoke::divergence;
use diffsim_solvers::smoke::{self, MacGrid, Preconditioner, PressureSolver, ProjectScratch, Scheme};
use diffsim_solvers::smoke::{Solid, solid_cells};

use crate::p4::{field, state};

/// One boundary of each kind on every axis, and mixtures.
pub(crate) fn boundaries() -> Vec<Boundary<3>> {
    vec![
        Boundary::<3>::all(Side::Periodic),
        Boundary::axes([Side::Closed, Side::Closed, Side::Periodic]).with_lower(0, Side::Inflow(Profile::Parabolic(0.4))).with_upper(0, Side::Outflow),
        Boundary::axes([Side::Periodic, Side::Closed, Side::Closed]).with_upper(2, Side::Inflow(Profile::Uniform(0.3))).with_upper(1, Side::Outflow),
        Boundary::<3>::all(Side::Outflow).with_lower(2, Side::Outflow),
    ]
}

#[test]
fn invalid_3d_boundaries_are_refused_with_the_reason() {
    let half = Boundary::<3>::CLOSED.with_upper(2, Side::Periodic);
    assert_eq!(half.validate(), Err(BoundaryError::HalfPeriodic { axis: "z" }));
    let inflow = Boundary::<3>::CLOSED.with_lower(2, Side::Inflow(Profile::Uniform(1.0)));
    assert_eq!(inflow.validate(), Err(BoundaryError::InflowWithoutOutflow));
    for b in boundaries() {
        assert!(b.validate().is_ok(), "{b:?}");
    }
}

#[test]
fn faces_of_a_periodic_axis_wrap_and_skip_the_copy() {
    let cfg = MacGrid::new([3, 4, 5]).with_dt(1.0).with_boundary(Boundary::axes([Side::Closed, Side::Outflow, Side::Periodic]));
    let mut z = Vec::new();
    for_each_face(cfg.n, &cfg.boundary, 2, |f| z.push(f));
    assert_eq!(z.len(), 3 * 4 * 5, "periodic z: Nz face slabs");
    // Face (0, 0, 0) wraps from the last slab's cell to the first's; its copy is face (0, 0, 5).
    assert_eq!((z[0].lower, z[0].upper, z[0].projected, z[0].copy), (Some(4 * 12), Some(0), true, Some(5 * 12)));
    let mut y = Vec::new();
    for_each_face(cfg.n, &cfg.boundary, 1, |f| y.push(f));
    assert_eq!(y.len(), 3 * 5 * 5);
    // The outflow bottom and top faces are projected with one cell each.
    assert_eq!((y[0].lower, y[0].upper, y[0].projected), (None, Some(0), true));
    assert_eq!((y[4 * 3].lower, y[4 * 3].upper, y[4 * 3].projected), (Some(9), None, true));
}

/// The 2D box `nx × ny` and the 3D box `nx × ny × nz` with the same x and
/// y sides and a periodic z.
fn twins(nx: usize, ny: usize, nz: usize, b: Boundary) -> (MacGrid<2>, MacGrid<3>) {
    let cfg2 = MacGrid::new([nx, ny]).with_boundary(b);
    let b3 = Boundary { sides: [b.axis(0), b.axis(1), [Side::Periodic; 2]] };
    (cfg2, MacGrid::new([nx, ny, nz]).with_dt(0.8).with_boundary(b3))
}

/// A 2D state lifted to the 3D twin: the same in every z slab, `w = 0`.
fn lift(cfg2: &MacGrid<2>, cfg3: &MacGrid<3>, x: &[f64]) -> Vec<f64> {
    let (s, [u, v]) = cfg2.split(x);
    let nz = cfg3.n[2];
    let mut y = Vec::with_capacity(cfg3.n_state());
    for f in [s, u, v] {
        for _ in 0..nz {
            y.extend_from_slice(f);
        }
    }
    y.resize(cfg3.n_state(), 0.0);
    y
}

#[test]
fn flows_that_do_not_vary_along_a_periodic_z_match_the_2d_solver() {
    // Independent code: the 2D advection and projection (their own loops,
    // face lists and matrices) against the 3D ones on a z-invariant state.
    let kinds = [
        Boundary::all(Side::Periodic),
        Boundary::CLOSED.with_lower(0, Side::Inflow(Profile::Uniform(0.4))).with_upper(0, Side::Outflow),
        Boundary::axes([Side::Periodic, Side::Closed]).with_lower(1, Side::Inflow(Profile::Uniform(0.5))).with_upper(1, Side::Outflow),
        Boundary::all(Side::Outflow),
    ];
    for b in kinds {
        let (cfg2, cfg3) = twins(7, 6, 4, b);
        let mut x2 = crate::checks::smoke_state(&cfg2, 11);
        {
            let ns = cfg2.n_s();
            smoke::enforce_boundary(&cfg2, &mut x2[ns..]);
        }
        let x3 = lift(&cfg2, &cfg3, &x2);
        let close = |a: &[f64], b: &[f64], what: &str| {
            let worst = a.iter().zip(b).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(worst < 1e-10, "{b:?}: {what} differs from 2D by {worst:e}");
        };
        for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: true }] {
            let mut y2 = vec![0.0; cfg2.n_state()];
            let mut scratch = vec![0.0; smoke::advect_scratch_len(&cfg2, scheme)];
            smoke::advect(&cfg2, scheme, cfg3.dt, true, true, &x2, &mut y2, &mut scratch);
            let y3 = Advect { cfg: cfg3, dt: cfg3.dt, scheme, smoke: true, velocity: true }.eval(&x3, &[]);
            close(&y3, &lift(&cfg2, &cfg3, &y2), &format!("{scheme:?} advection"));
        }
        let mut y2 = x2.clone();
        let mut solver = PressureSolver::general(cfg2.n[0], cfg2.n[1], b, 1e-13, 2000, None);
        smoke::project(&cfg2, &mut y2, &mut solver, &mut ProjectScratch::new(cfg2.n_s())).unwrap();
        for precond in [Preconditioner::Mic0, Preconditioner::None] {
            let y3 = Project3::new(cfg3, 1e-13, 2000, precond).eval(&x3, &[]);
            close(&y3, &lift(&cfg2, &cfg3, &y2), &format!("projection ({precond})"));
        }
    }
}

/// The largest divergence over the fluid cells of a packed state.
fn max_divergence(cfg: &MacGrid<3>, x: &[f64], solid: Option<&[bool]>) -> f64 {
    let (_, [u, v, w]) = cfg.split(x);
    let mut d = vec![0.0; cfg.n_s()];
    divergence(cfg, [u, v, w], &mut d);
    d.iter().enumerate().filter(|(c, _)| solid.is_none_or(|s| !s[*c])).map(|(_, d)| d.abs()).fold(0.0, f64::max)
}

#[test]
fn projection_under_every_kind_leaves_no_divergence_and_keeps_the_sides() {
    for b in boundaries() {
        let cfg = MacGrid::new([8, 7, 6]).with_dt(1.0).with_boundary(b);
        let x = state(&cfg, 7);
        let sphere = solid_cells(&cfg, &[Solid::Ball { center: [4.0, 3.5, 3.0], radius: 1.6 }]);
        for (solid, name) in [(None, "no obstacle"), (Some(&sphere[..]), "a sphere")] {
            let op = match solid {
                Some(s) => Project3::with_obstacles(cfg, 1e-12, 3000, Preconditioner::Mic0, s),
                None => Project3::new(cfg, 1e-12, 3000, Preconditioner::Mic0),
            };
            let y = op.eval(&x, &[]);
            let scale = y[cfg.n_s()..].iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let d = max_divergence(&cfg, &y, solid);
            assert!(d < 1e-9 * scale, "{b:?}, {name}: divergence {d:e}");
            // Projecting twice is projecting once.
            let z = op.eval(&y, &[]);
            let again = z.iter().zip(&y).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(again < 1e-9 * scale, "{b:?}, {name}: not idempotent ({again:e})");
            // Periodic copies hold their face 0; closed and inflow faces keep their value.
            for axis in 0..3 {
                let start = cfg.slab_starts(0).1[axis];
                for_each_face(cfg.n, &cfg.boundary, axis, |f| {
                    if let Some(k) = f.copy {
                        assert_eq!(y[start + k], y[start + f.index], "{b:?}: copy of face {}", f.index);
                    }
                    if !f.projected {
                        assert_eq!(y[start + f.index], x[start + f.index], "{b:?}: side face {} changed", f.index);
                    }
                });
            }
        }
    }
}

#[test]
fn a_uniform_through_flow_is_left_as_it_is_and_periodic_advection_shifts_exactly() {
    // Inflow on the left at 0.5, outflow on the right: u = 0.5 everywhere
    // is divergence-free and the projection keeps it (p = 0).
    let b = Boundary::<3>::CLOSED.with_lower(0, Side::Inflow(Profile::Uniform(0.5))).with_upper(0, Side::Outflow);
    let cfg = MacGrid::new([6, 5, 4]).with_dt(1.0).with_boundary(b);
    let mut x = vec![0.0; cfg.n_state()];
    let start = cfg.n_s();
    x[start..start + cfg.n_face(0)].fill(0.5);
    let y = Project3::new(cfg, 1e-13, 500, Preconditioner::None).eval(&x, &[]);
    let worst = y.iter().zip(&x).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-12, "uniform through-flow changed by {worst:e}");
    // Every axis periodic, velocity (1, 0, 0) and a unit step: each step
    // moves every field one cell along x exactly; Nx steps bring it back.
    let cfg = MacGrid::new([5, 4, 3]).with_dt(1.0).with_boundary(Boundary::<3>::all(Side::Periodic));
    let mut x = field(cfg.n_state(), 5);
    let [ns, nu] = [cfg.n_s(), cfg.n_face(0)];
    x[ns..ns + nu].fill(1.0);
    x[ns + nu..].fill(0.0);
    let op = Advect { cfg, dt: cfg.dt, scheme: Scheme::SemiLagrangian, smoke: true, velocity: true };
    let one = op.eval(&x, &[]);
    for (c, &v) in one.iter().enumerate().take(ns) {
        let (i, rest) = (c % 5, c - c % 5);
        assert_eq!(v, x[rest + (i + 4) % 5], "smoke cell {c} after one step");
    }
    let mut y = x.clone();
    for _ in 0..5 {
        y = op.eval(&y, &[]);
    }
    assert_eq!(y, x, "five steps around the period");
}

#[test]
fn every_3d_operator_passes_all_checks_under_every_boundary() {
    let opts = CheckParams::default();
    for b in boundaries() {
        let cfg = MacGrid::new([6, 5, 4]).with_dt(0.8).with_boundary(b);
        let x = state(&cfg, 31);
        let name = |op: &str| format!("{op} under {b:?}");
        // The operators written once for every dimension: boundaries.rs.
        let r = check_all(&Diffuse::in_box(cfg, true, true, DiffuseExplicit::on), &x, &[0.1], &opts);
        assert!(r.passed(), "{}:\n{r}", name("explicit diffusion"));
        let r = check_all(&Diffuse::in_box(cfg, true, true, |g| DiffuseImplicit::on(g, 1e-13, 500)), &x, &[0.7], &opts);
        assert!(r.passed(), "{}:\n{r}", name("implicit diffusion"));
        for precond in [Preconditioner::Mic0, Preconditioner::None] {
            let r = check_all(&Project3::new(cfg, 1e-13, 2000, precond), &x, &[], &opts);
            assert!(r.passed(), "{}:\n{r}", name(&format!("projection ({precond})")));
        }
        let solid = solid_cells(&cfg, &[Solid::Box { lower: [2.0, 1.0, 1.0], upper: [4.0, 3.0, 3.0] }]);
        let r = check_all(&Project3::with_obstacles(cfg, 1e-13, 2000, Preconditioner::Mic0, &solid), &x, &[], &opts);
        assert!(r.passed(), "{}:\n{r}", name("projection with a box"));
    }
}

#[test]
fn the_aggregation_multigrid_is_galerkin_and_preconditions_any_box_and_sides() {
    use diffsim_solvers::multigrid::{AggregateMultigrid, apply_weighted3};
    // Pᵀ·A·P (P copies each coarse value to its cells) is the seven-point
    // stencil of the same sides on the coarse box, each axis weighted by
    // the faces between two coarse cells: checked on a box halved along x
    // and z only (y odd) and along all three.
    for (fine, factor) in [([8, 9, 6], [2, 1, 2]), ([8, 6, 4], [2, 2, 2])] {
        let coarse = [0, 1, 2].map(|a| fine[a] / factor[a]);
        let w = [0, 1, 2].map(|a| (0..3).filter(|&o| o != a).map(|o| factor[o] as f64).product::<f64>());
        for b in boundaries() {
            let v = field(coarse.iter().product(), 3);
            let cells: usize = fine.iter().product();
            let parent = |c: usize| {
                let q = [c % fine[0], (c / fine[0]) % fine[1], c / (fine[0] * fine[1])];
                ((q[2] / factor[2]) * coarse[1] + q[1] / factor[1]) * coarse[0] + q[0] / factor[0]
            };
            let pv: Vec<f64> = (0..cells).map(|c| v[parent(c)]).collect();
            let mut apv = vec![0.0; cells];
            apply_weighted3(fine, &b, [1.0; 3], &pv, &mut apv);
            let mut galerkin = vec![0.0; v.len()];
            for (c, a) in apv.iter().enumerate() {
                galerkin[parent(c)] += a;
            }
            let mut direct = vec![0.0; v.len()];
            apply_weighted3(coarse, &b, w, &v, &mut direct);
            let worst = galerkin.iter().zip(&direct).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(worst < 1e-12, "{fine:?} under {b:?}: Pᵀ·A·P vs the weighted stencil: {worst:e}");
        }
    }
    // The V-cycle is symmetric and positive, and cuts the iterations of
    // every boundary (and of a closed box whose sides all differ).
    let mut kinds = boundaries();
    kinds.push(Boundary::<3>::CLOSED);
    let mut counts = Vec::new();
    for b in kinds {
        let dims = [24, 20, 16];
        let mut mg = AggregateMultigrid::new(dims, b);
        assert!(mg.depth() >= 3, "{b:?}: {} levels", mg.depth());
        crate::checks::assert_symmetric_positive(&format!("{b:?}"), dims.iter().product(), !b.has_outflow(), |r, z| mg.apply(r, z));
        let cfg = MacGrid::new([dims[0], dims[1], dims[2]]).with_dt(1.0).with_boundary(b);
        let x = state(&cfg, 91);
        let iterations = |precond| {
            let op = Project3::new(cfg, 1e-10, 3000, precond);
            op.eval(&x, &[]);
            assert!(op.take_error().is_none(), "{b:?}, {precond}");
            op.log.cg_forward.get()
        };
        let (with, without) = (iterations(Preconditioner::Multigrid), iterations(Preconditioner::None));
        counts.push(format!("{with} vs {without}"));
        assert!(3 * with < without, "{b:?}: multigrid {with} iterations, plain CG {without}");
    }
    eprintln!("CG iterations at 24×20×16, tolerance 1e-10, multigrid vs none: {}", counts.join(", "));
}

#[test]
fn a_region_that_an_inflow_feeds_and_obstacles_seal_is_found() {
    use diffsim_solvers::boundary::{SealedRegion, sealed_region};
    // Inflow on the back, outflow on the front: a wall across z at k = 3
    // seals the first three slabs; a hole in it opens them.
    let cfg = MacGrid::new([5, 4, 6]).with_dt(1.0);
    let b = Boundary::<3>::CLOSED.with_lower(2, Side::Inflow(Profile::Uniform(0.5))).with_upper(2, Side::Outflow);
    let wall = solid_cells(&cfg, &[Solid::Box { lower: [-1.0, -1.0, 3.0], upper: [9.0, 9.0, 4.0] }]);
    assert_eq!(sealed_region(cfg.n, &b, &wall), Some(SealedRegion { cells: 3 * 20, at: [0, 0, 0] }));
    let mut holed = wall.clone();
    holed[(3 * 4 + 2) * 5 + 2] = false;
    assert_eq!(sealed_region(cfg.n, &b, &holed), None);
    // A parabolic profile feeds the side's inner cells: still sealed.
    let bp = b.with_lower(2, Side::Inflow(Profile::Parabolic(0.5)));
    assert!(sealed_region(cfg.n, &bp, &wall).is_some());
}

#[test]
fn enzyme_advection_adjoint_matches_the_hand_written_one_under_every_boundary() {
    use diffsim::op::Vjp;
    use diffsim_solvers::smoke::advect_adjoint;
    for b in boundaries() {
        let cfg = MacGrid::new([7, 6, 5]).with_dt(0.9).with_boundary(b);
        let x = state(&cfg, 17);
        for (smoke, velocity) in [(true, true), (true, false), (false, true)] {
            let op = Advect { cfg, dt: cfg.dt, scheme: Scheme::SemiLagrangian, smoke, velocity };
            let g = field(cfg.n_state(), 23);
            let (mut dy, mut enzyme) = (g.clone(), vec![0.0; cfg.n_state()]);
            op.vjp(&x, &[], &mut dy, &mut enzyme, &mut []);
            let (mut gy, mut hand) = (g.clone(), vec![0.0; cfg.n_state()]);
            advect_adjoint(&cfg, cfg.dt, smoke, velocity, &x, &mut gy, &mut hand);
            let scale = hand.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let worst = enzyme.iter().zip(&hand).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(worst < 1e-12 * scale, "{b:?}, smoke {smoke}, velocity {velocity}: Enzyme vs hand {worst:e}");
        }
    }
}

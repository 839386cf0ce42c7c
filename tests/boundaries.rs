//! Boundary kinds of the fluid (closed, periodic, inflow with a profile,
//! outflow on any side), in 2D and 3D: validation, the exact behaviour each
//! promises, agreement of 3D with the 2D solver on flows that do not vary
//! along a periodic z, and the three gradient checks of every operator
//! under every kind, with and without an obstacle. Each test function is
//! written once and run for `D = 2` and `D = 3`.

use diffsim::fluids::{Advect, AdvectUpwind, Buoyancy, Diffuse, Force, Project};
use diffsim::op::{Forward, Jvp, OperatorExt, Vjp};
use diffsim::problems::smoke::{SmokeAdvect, SmokeAdvectHand, SmokeStep};
use diffsim_solvers::boundary::{Boundary, BoundaryError, Profile, Side, for_each_face};
use diffsim_solvers::smoke::{self, MacGrid, Preconditioner, PressureSolver, ProjectScratch, Scheme, Solid, divergence, solid_cells};

use crate::checks::assert_passes;
use crate::smoke::field;

/// One boundary of each kind, and mixtures, on a box of `D` axes: every
/// side periodic; x periodic; a channel along x; x periodic and a channel
/// along y; the top an outflow; the last axis fed from its upper side and
/// leaving through the top; every side an outflow.
pub(crate) fn boundaries<const D: usize>() -> Vec<Boundary<D>> {
    let closed = Boundary::<D>::CLOSED;
    let periodic_x = closed.with_lower(0, Side::Periodic).with_upper(0, Side::Periodic);
    vec![
        Boundary::all(Side::Periodic),
        periodic_x,
        closed.with_lower(0, Side::Inflow(Profile::Uniform(0.4))).with_upper(0, Side::Outflow),
        periodic_x.with_lower(1, Side::Inflow(Profile::Parabolic(0.5))).with_upper(1, Side::Outflow),
        closed.with_upper(1, Side::Outflow),
        periodic_x.with_upper(D - 1, Side::Inflow(Profile::Uniform(0.3))).with_upper(1, Side::Outflow).with_lower(1, Side::Outflow),
        Boundary::all(Side::Outflow),
    ]
}

/// A box of `n` cells with P2's buoyancy, time step `dt` and sides `b`.
fn boxed<const D: usize>(n: [usize; D], dt: f64, b: Boundary<D>) -> MacGrid<D> {
    MacGrid { buoyancy: 0.1, ..MacGrid::new(n) }.with_dt(dt).with_boundary(b)
}

/// A box whose last axis is periodic on one side only, or fed with no
/// outflow, is refused; every box of [`boundaries`] is accepted.
fn invalid_boundaries_are_refused<const D: usize>() {
    assert!(Boundary::<D>::CLOSED.validate().is_ok());
    let half = Boundary::<D>::CLOSED.with_upper(D - 1, Side::Periodic);
    assert_eq!(half.validate(), Err(BoundaryError::HalfPeriodic { axis: ["x", "y", "z"][D - 1] }));
    let inflow = Boundary::<D>::CLOSED.with_lower(D - 1, Side::Inflow(Profile::Uniform(1.0)));
    assert_eq!(inflow.validate(), Err(BoundaryError::InflowWithoutOutflow));
    assert!(inflow.validate().unwrap_err().to_string().contains("outflow"));
    for b in boundaries::<D>() {
        assert!(b.validate().is_ok(), "{b:?}");
    }
}

#[test]
fn invalid_boundaries_are_refused_with_the_reason() {
    invalid_boundaries_are_refused::<2>();
    invalid_boundaries_are_refused::<3>();
}

#[test]
fn faces_list_each_flux_once() {
    use diffsim_solvers::boundary::{Face, faces};
    let n = 3;
    let b = Boundary::axes([Side::Periodic, Side::Outflow]);
    let x: Vec<Face> = faces([n, n], &b, 0);
    assert_eq!(x.len(), n * n, "periodic x: N faces per row");
    assert_eq!((x[0].lower, x[0].upper, x[0].projected, x[0].copy), (Some(2), Some(0), true, Some(3)));
    let y: Vec<Face> = faces([n, n], &b, 1);
    assert_eq!(y.len(), n * (n + 1));
    assert_eq!((y[0].lower, y[0].upper, y[0].projected), (None, Some(0), true));
    assert_eq!((y[n * n].index, y[n * n].lower, y[n * n].upper), (n * n, Some(6), None));
    let closed: Vec<Face> = faces([n, n], &Boundary::CLOSED, 1);
    assert!(!closed[0].projected && !closed[1].projected && closed[n].projected);
    // 3D: a periodic z lists Nz face slabs; face (0, 0, 0) wraps from the
    // last slab's cell to the first's, its copy face (0, 0, 5).
    let cfg = MacGrid::new([3, 4, 5]).with_boundary(Boundary::axes([Side::Closed, Side::Outflow, Side::Periodic]));
    let z = faces(cfg.n, &cfg.boundary, 2);
    assert_eq!(z.len(), 3 * 4 * 5, "periodic z: Nz face slabs");
    assert_eq!((z[0].lower, z[0].upper, z[0].projected, z[0].copy), (Some(4 * 12), Some(0), true, Some(5 * 12)));
    let y = faces(cfg.n, &cfg.boundary, 1);
    assert_eq!(y.len(), 3 * 5 * 5);
    // The outflow bottom and top faces are projected with one cell each.
    assert_eq!((y[0].lower, y[0].upper, y[0].projected), (None, Some(0), true));
    assert_eq!((y[4 * 3].lower, y[4 * 3].upper, y[4 * 3].projected), (Some(9), None, true));
}

/// A seeded state of any box: smoke in [0, 2], each velocity component of
/// one sign (even axes positive, odd negative) with speeds in [0.15, 0.45]
/// cells per step, so that traced points stay away from the lattice planes
/// where multilinear sampling kinks.
pub(crate) fn signed_state<const D: usize>(cfg: &MacGrid<D>, seed: u64) -> Vec<f64> {
    let raw = field(cfg.n_state(), seed);
    let mut x: Vec<f64> = raw.iter().map(|v| 1.0 + v).collect();
    for a in 0..D {
        let r = cfg.face_range(a);
        let sign = if a % 2 == 0 { 1.0 } else { -1.0 };
        for k in cfg.n_s() + r.start..cfg.n_s() + r.end {
            x[k] = sign * (0.3 + 0.15 * raw[k]);
        }
    }
    x
}

/// The three checks of every operator written once for all dimensions, in
/// the box `cfg`: advection (semi-Lagrangian, MacCormack; the limited
/// MacCormack's kinks may spoil a rate but never fail a check), upwind,
/// buoyancy along every axis, a force, P2's and P4's explicit step (in 3D
/// the closed box's), and its hand-written adjoint against Enzyme's.
fn operators_written_once_pass_all_checks<const D: usize>(cfg: MacGrid<D>, seed: u64)
where
    Advect<D>: Vjp + Jvp,
    AdvectUpwind<D>: Vjp + Jvp,
    Buoyancy<D>: Vjp + Jvp,
    Force<D>: Vjp + Jvp,
    SmokeAdvect<D>: Vjp + Jvp,
{
    use diffsim::check::{CheckParams, Verdict, check_all, dot_product_between};
    let x = signed_state(&cfg, seed);
    let name = |op: &str| format!("{op} {:?} {:?}", cfg.n, cfg.boundary);
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        assert_passes(&name(&format!("{scheme:?} dt 0.7")), &Advect { dt: 0.7, ..Advect::new(cfg, scheme) }, &x, &[]);
    }
    let limited = check_all(&Advect::new(cfg, Scheme::MacCormack { limiter: true }), &x, &[], &CheckParams::default());
    for v in [&limited.fd.verdict, &limited.taylor.verdict, &limited.dot.verdict] {
        assert!(!matches!(v, Verdict::Fail(_)), "{}:\n{limited}", name("limited MacCormack"));
    }
    assert_passes(&name("upwind"), &AdvectUpwind { cfg, dt: 0.4 }, &x, &[]);
    for axis in 0..D {
        assert_passes(&name(&format!("buoyancy along {axis}")), &Buoyancy { cfg, dt: 0.5, axis }, &x, &[0.3]);
    }
    assert_passes(&name("force"), &Force { cfg, dt: 0.5 }, &x, &crate::checks::state(cfg.n_vel(), 7));
    // P2's and P4's explicit step (in 3D the closed box's).
    if D == 2 || cfg.is_closed() {
        assert_passes(&name("SmokeAdvect"), &SmokeAdvect(cfg), &x, &[]);
        let r = dot_product_between(&SmokeAdvect(cfg), &SmokeAdvectHand(cfg), &x, &[], &CheckParams { tol: 1e-12, ..Default::default() });
        assert!(r.verdict.passed(), "{}: {r}", name("hand adjoint against Enzyme's"));
    }
}

/// The three checks of the operators with a solve or a side condition,
/// in the box `cfg` with and without the solid `shape`: P2's and P4's
/// whole step, the projection under each preconditioner, explicit and
/// implicit diffusion and viscosity.
fn solved_operators_pass_all_checks<const D: usize>(cfg: MacGrid<D>, shape: Solid<D>, seed: u64)
where
    SmokeAdvect<D>: Vjp + Jvp,
    Diffuse<diffsim::fluids::DiffuseExplicit>: Vjp + Jvp,
    Diffuse<diffsim::fluids::DiffuseImplicit>: Vjp + Jvp,
{
    let x = signed_state(&cfg, seed);
    let name = |op: &str| format!("{op} {:?} {:?}", cfg.n, cfg.boundary);
    let solid = solid_cells(&cfg, &[shape]);
    assert!(solid.iter().any(|&s| s) && solid.iter().any(|&s| !s));
    // P2's step in any 2D box; P4's in the closed 3D box only (smoke.rs).
    if D == 2 {
        assert_passes(&name("SmokeStep"), &SmokeStep::new(cfg, 1e-13, 4000, Preconditioner::None), &x, &[]);
        assert_passes(&name("SmokeStep with obstacle"), &SmokeStep::new(cfg, 1e-13, 4000, Preconditioner::Mic0).with_obstacles(&solid), &x, &[]);
    }
    for precond in [Preconditioner::Mic0, Preconditioner::Multigrid, Preconditioner::None] {
        assert_passes(&name(&format!("projection ({precond})")), &Project::new(cfg, 1e-13, 4000, precond), &x, &[]);
        assert_passes(&name(&format!("projection with obstacle ({precond})")), &Project::with_obstacles(cfg, 1e-13, 4000, precond, &solid), &x, &[]);
    }
    assert_passes(&name("explicit diffusion and viscosity"), &Diffuse::explicit(cfg, true, true), &x, &[0.1]);
    assert_passes(&name("implicit viscosity"), &Diffuse::implicit(cfg, false, true, 1e-13, 2000), &x, &[1.5]);
    assert_passes(&name("implicit diffusion"), &Diffuse::implicit(cfg, true, false, 1e-13, 2000), &x, &[0.7]);
}

#[test]
fn operators_written_once_pass_all_checks_in_2d_and_3d() {
    for b in boundaries::<2>() {
        for n in [[5, 5], [8, 5]] {
            operators_written_once_pass_all_checks(boxed(n, 1.0, b), 90 + n[0] as u64);
        }
    }
    operators_written_once_pass_all_checks(MacGrid::p2(16), 3);
    for b in boundaries::<3>() {
        operators_written_once_pass_all_checks(boxed([6, 5, 4], 0.8, b), 31);
    }
    operators_written_once_pass_all_checks(MacGrid::p4(16), 5);
}

#[test]
fn every_operator_passes_all_checks_under_every_boundary() {
    for b in boundaries::<2>() {
        for n in [[5, 5], [8, 5]] {
            solved_operators_pass_all_checks(boxed(n, 1.0, b), Solid::Box { lower: [2.0, 2.0], upper: [4.0, 4.0] }, 90 + n[0] as u64);
        }
    }
    for b in boundaries::<3>() {
        solved_operators_pass_all_checks(boxed([6, 5, 4], 0.8, b), Solid::Box { lower: [2.0, 1.0, 1.0], upper: [4.0, 3.0, 3.0] }, 31);
    }
}

/// On a box periodic on every axis, a velocity of exactly one cell per
/// step along x moves every value one cell, the last onto the first, with
/// either traced scheme, and `n[0]` steps bring the state back; upwind
/// keeps the smoke's mass.
fn periodic_advection_wraps_exactly<const D: usize>(n: [usize; D])
where
    Advect<D>: Forward,
    AdvectUpwind<D>: Forward,
{
    let cfg = MacGrid::new(n).with_boundary(Boundary::all(Side::Periodic));
    let mut x = field(cfg.n_state(), 5);
    let (ns, nu) = (cfg.n_s(), cfg.n_face(0));
    x[ns..ns + nu].fill(1.0);
    x[ns + nu..].fill(0.0);
    let nx = n[0];
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: true }] {
        let op = Advect::new(cfg, scheme);
        let one = op.eval(&x, &[]);
        for (c, &v) in one.iter().enumerate().take(ns) {
            let (i, row) = (c % nx, c - c % nx);
            assert!((v - x[row + (i + nx - 1) % nx]).abs() < 1e-12, "{n:?} {scheme:?}: smoke cell {c} after one step");
        }
        let mut y = x.clone();
        for _ in 0..nx {
            y = op.eval(&y, &[]);
        }
        let worst = y.iter().zip(&x).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        assert!(worst < 1e-12, "{n:?} {scheme:?}: {nx} steps around the period ({worst:e})");
    }
    let y = AdvectUpwind { cfg, dt: 0.3 }.eval(&x, &[]);
    let mass = |v: &[f64]| v[..ns].iter().sum::<f64>();
    assert!((mass(&y) - mass(&x)).abs() < 1e-12 * mass(&x).abs().max(1.0));
}

#[test]
fn periodic_advection_wraps_exactly_in_2d_and_3d() {
    periodic_advection_wraps_exactly([6, 4]);
    periodic_advection_wraps_exactly([5, 4, 3]);
}

/// Uniform inflow on the left, outflow on the right, closed walls: the
/// only divergence-free field with these boundary values is the uniform
/// one, so one step from rest gives it everywhere, and the projection
/// leaves it as it is.
fn a_channel_carries_uniform_inflow<const D: usize>(n: [usize; D])
where
    SmokeAdvect<D>: Forward,
{
    let speed = 0.6;
    let b = Boundary::<D>::CLOSED.with_lower(0, Side::Inflow(Profile::Uniform(speed))).with_upper(0, Side::Outflow);
    let cfg = MacGrid::new(n).with_boundary(b);
    let y = SmokeStep::new(cfg, 1e-12, 2000, Preconditioner::Multigrid).eval(&vec![0.0; cfg.n_state()], &[]);
    let (_, vel) = cfg.split(&y);
    assert!(vel[0].iter().all(|&w| (w - speed).abs() < 1e-9), "{n:?} u: {:?}", &vel[0][..n[0] + 1]);
    assert!(vel[1..].iter().all(|v| v.iter().all(|&w| w.abs() < 1e-9)), "{n:?}: a cross-flow");
    let z = Project::new(cfg, 1e-13, 500, Preconditioner::None).eval(&y, &[]);
    let worst = z.iter().zip(&y).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-12, "{n:?}: uniform through-flow changed by {worst:e}");
}

#[test]
fn a_channel_with_uniform_inflow_carries_it_through_after_one_projection() {
    a_channel_carries_uniform_inflow([16, 6]);
    a_channel_carries_uniform_inflow([6, 5, 4]);
}

/// The largest divergence over the fluid cells of a packed state (NaN if
/// one is not a number, so that no bound holds).
pub(crate) fn max_divergence<const D: usize>(cfg: &MacGrid<D>, x: &[f64], solid: Option<&[bool]>) -> f64 {
    let (_, vel) = cfg.split(x);
    let mut d = vec![0.0; cfg.n_s()];
    divergence(cfg, vel, &mut d);
    let fluid = d.iter().enumerate().filter(|(c, _)| solid.is_none_or(|s| !s[*c])).map(|(_, d)| d.abs());
    fluid.fold(0.0, |m: f64, d| if d.is_nan() || m.is_nan() { f64::NAN } else { m.max(d) })
}

/// The projection of the box `cfg` under each preconditioner, without and
/// with the solid `shape`: no divergence left in the fluid, idempotent,
/// periodic copies holding their face 0, closed and inflow faces keeping
/// their values; and (2D: P2's step runs in any box) three whole steps
/// with the obstacle leave no divergence either.
fn projection_keeps_its_promises<const D: usize>(cfg: MacGrid<D>, shape: Solid<D>)
where
    SmokeAdvect<D>: Forward,
{
    // A velocity that meets the sides' conditions (the projection changes
    // the faces it solves for only).
    let mut x = signed_state(&cfg, 7);
    let ns = cfg.n_s();
    smoke::enforce_boundary(&cfg, &mut x[ns..]);
    let b = cfg.boundary;
    let obstacle = solid_cells(&cfg, &[shape]);
    for precond in [Preconditioner::Mic0, Preconditioner::Multigrid] {
        for solid in [None, Some(&obstacle[..])] {
            let name = format!("{:?} {b:?} {precond}, obstacle {}", cfg.n, solid.is_some());
            let op = match solid {
                Some(s) => Project::with_obstacles(cfg, 1e-12, 3000, precond, s),
                None => Project::new(cfg, 1e-12, 3000, precond),
            };
            let y = op.eval(&x, &[]);
            let scale = y[cfg.n_s()..].iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let d = max_divergence(&cfg, &y, solid);
            assert!(d < 1e-9 * scale, "{name}: divergence {d:e}");
            let z = op.eval(&y, &[]);
            let again = z.iter().zip(&y).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(again < 1e-9 * scale, "{name}: not idempotent ({again:e})");
            for axis in 0..D {
                let start = cfg.n_s() + cfg.face_range(axis).start;
                for_each_face(cfg.n, &cfg.boundary, axis, |f| {
                    if let Some(k) = f.copy {
                        assert_eq!(y[start + k], y[start + f.index], "{name}: copy of face {}", f.index);
                    }
                    if !f.projected && solid.is_none() {
                        assert_eq!(y[start + f.index], x[start + f.index], "{name}: side face {} changed", f.index);
                    }
                });
            }
        }
        if D == 2 {
            let step = SmokeStep::new(cfg, 1e-12, 4000, precond).with_obstacles(&obstacle);
            let mut y = x.clone();
            for _ in 0..3 {
                y = step.eval(&y, &[]);
            }
            let d = max_divergence(&cfg, &y, Some(&obstacle));
            assert!(d < 1e-9, "{:?} {b:?} {precond}: divergence {d:e} after three steps", cfg.n);
        }
    }
}

#[test]
fn projection_leaves_no_divergence_under_every_boundary() {
    for b in boundaries::<2>() {
        projection_keeps_its_promises(boxed([12, 9], 1.0, b), Solid::Box { lower: [4.0, 5.0], upper: [7.0, 7.0] });
    }
    for b in boundaries::<3>() {
        projection_keeps_its_promises(boxed([8, 7, 6], 1.0, b), Solid::Ball { center: [4.0, 3.5, 3.0], radius: 1.6 });
    }
}

/// Upwind flux out of the top (an outflow side) at speed 0.5 along y: the
/// mass drops by exactly what crossed it, one cell's worth per top face
/// times 0.5·dt; the closed bottom lets nothing in.
fn smoke_leaves_through_the_top<const D: usize>(n: [usize; D])
where
    AdvectUpwind<D>: Forward,
{
    let cfg = MacGrid::new(n).with_boundary(Boundary::CLOSED.with_upper(1, Side::Outflow));
    let mut x = vec![0.0; cfg.n_state()];
    x[..cfg.n_s()].fill(1.0);
    let v = cfg.n_s() + cfg.face_range(1).start;
    x[v..v + cfg.n_face(1)].fill(0.5);
    let y = AdvectUpwind { cfg, dt: 0.2 }.eval(&x, &[]);
    let mass = |v: &[f64]| v[..cfg.n_s()].iter().sum::<f64>();
    let top = (cfg.n_s() / n[1]) as f64;
    assert!((mass(&x) - mass(&y) - top * 0.1).abs() < 1e-12, "{n:?}: {} → {}", mass(&x), mass(&y));
}

#[test]
fn smoke_leaves_through_an_outflow_side() {
    smoke_leaves_through_the_top([6, 6]);
    smoke_leaves_through_the_top([5, 6, 4]);
}

/// Explicit and implicit diffusion of smoke and velocity on a box periodic
/// on every axis keep the smoke's mass and each component's momentum (the
/// sums over the faces, copies left out), shrink the smoke's spread, and
/// refresh the periodic copies.
fn periodic_diffusion_conserves<const D: usize>(n: [usize; D]) {
    let cfg = MacGrid::new(n).with_boundary(Boundary::all(Side::Periodic));
    let x = signed_state(&cfg, 17);
    let ns = cfg.n_s();
    let sums = |y: &[f64]| -> Vec<f64> {
        let (s, vel) = cfg.split(y);
        let mut sums = vec![s.iter().sum::<f64>()];
        for (a, u) in vel.into_iter().enumerate() {
            let mut sum = 0.0;
            for_each_face(cfg.n, &cfg.boundary, a, |f| sum += u[f.index]);
            sums.push(sum);
        }
        sums
    };
    let before = sums(&x);
    for y in [Diffuse::explicit(cfg, true, true).eval(&x, &[0.1]), Diffuse::implicit(cfg, true, true, 1e-13, 2000).eval(&x, &[3.0])] {
        for (a, b) in before.iter().zip(sums(&y)) {
            assert!((a - b).abs() < 1e-10, "{n:?}: {a} → {b}");
        }
        let spread = |v: &[f64]| v.iter().fold(f64::MIN, |m, &a| m.max(a)) - v.iter().fold(f64::MAX, |m, &a| m.min(a));
        assert!(spread(&y[..ns]) < spread(&x[..ns]));
        for axis in 0..D {
            let start = ns + cfg.face_range(axis).start;
            for_each_face(cfg.n, &cfg.boundary, axis, |f| {
                if let Some(k) = f.copy {
                    assert_eq!(y[start + k], y[start + f.index], "{n:?}: periodic copy refreshed");
                }
            });
        }
    }
}

#[test]
fn diffusion_on_a_periodic_box_conserves_mass_and_momentum() {
    periodic_diffusion_conserves([8, 8]);
    periodic_diffusion_conserves([6, 5, 4]);
}

#[test]
fn regions_cut_off_from_the_outflow_are_found() {
    use diffsim_solvers::boundary::{SealedRegion, sealed_region};
    let b = Boundary::CLOSED.with_lower(0, Side::Inflow(Profile::Uniform(1.0))).with_upper(0, Side::Outflow);
    let (nx, ny) = (6, 4);
    // A wall across the channel at column 2: columns 0-1 are fed and sealed.
    let wall: Vec<bool> = (0..nx * ny).map(|c| c % nx == 2).collect();
    assert_eq!(sealed_region([nx, ny], &b, &wall), Some(SealedRegion { cells: 8, at: [0, 0] }));
    // A gap in the wall drains it; a pocket with no inflow is no concern.
    let gap: Vec<bool> = (0..nx * ny).map(|c| c % nx == 2 && c / nx != 3).collect();
    assert_eq!(sealed_region([nx, ny], &b, &gap), None);
    let pocket: Vec<bool> = (0..nx * ny).map(|c| c % nx == 4).collect();
    assert_eq!(sealed_region([nx, ny], &b.with_lower(0, Side::Closed), &pocket), None);
    // Across a periodic axis the sealed part wraps: inflow at the bottom,
    // a full solid row 1, outflow at the top.
    let bt = Boundary::axes([Side::Periodic, Side::Closed]).with_lower(1, Side::Inflow(Profile::Uniform(0.1))).with_upper(1, Side::Outflow);
    let row: Vec<bool> = (0..nx * ny).map(|c| c / nx == 1).collect();
    assert_eq!(sealed_region([nx, ny], &bt, &row), Some(SealedRegion { cells: 6, at: [0, 0] }));
    // The projection of such a box cannot converge: that is why scenes refuse it.
    let cfg = MacGrid { n: [nx, ny], ..MacGrid::p2(nx).with_boundary(bt) };
    let op = Project::with_obstacles(cfg, 1e-10, 500, Preconditioner::Mic0, &row);
    let _ = op.eval(&crate::checks::smoke_state(&cfg, 1), &[]);
    assert!(op.take_error().is_some(), "a sealed fed region converged");
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
        let mut solver = PressureSolver::new(&cfg2, 1e-13, 2000, Preconditioner::Mic0);
        smoke::project(&cfg2, &mut y2, &mut solver, &mut ProjectScratch::new(cfg2.n_s())).unwrap();
        for precond in [Preconditioner::Mic0, Preconditioner::None] {
            let y3 = Project::new(cfg3, 1e-13, 2000, precond).eval(&x3, &[]);
            close(&y3, &lift(&cfg2, &cfg3, &y2), &format!("projection ({precond})"));
        }
    }
}

#[test]
fn the_aggregation_multigrid_is_galerkin_and_preconditions_any_box_and_sides() {
    use diffsim_solvers::multigrid::{AggregateMultigrid, apply_weighted};
    // Pᵀ·A·P (P copies each coarse value to its cells) is the seven-point
    // stencil of the same sides on the coarse box, each axis weighted by
    // the faces between two coarse cells: checked on a box halved along x
    // and z only (y odd) and along all three.
    for (fine, factor) in [([8, 9, 6], [2, 1, 2]), ([8, 6, 4], [2, 2, 2])] {
        let coarse = [0, 1, 2].map(|a| fine[a] / factor[a]);
        let w = [0, 1, 2].map(|a| (0..3).filter(|&o| o != a).map(|o| factor[o] as f64).product::<f64>());
        for b in boundaries::<3>() {
            let v = field(coarse.iter().product(), 3);
            let cells: usize = fine.iter().product();
            let parent = |c: usize| {
                let q = [c % fine[0], (c / fine[0]) % fine[1], c / (fine[0] * fine[1])];
                ((q[2] / factor[2]) * coarse[1] + q[1] / factor[1]) * coarse[0] + q[0] / factor[0]
            };
            let pv: Vec<f64> = (0..cells).map(|c| v[parent(c)]).collect();
            let mut apv = vec![0.0; cells];
            apply_weighted(fine, &b, [1.0; 3], &pv, &mut apv);
            let mut galerkin = vec![0.0; v.len()];
            for (c, a) in apv.iter().enumerate() {
                galerkin[parent(c)] += a;
            }
            let mut direct = vec![0.0; v.len()];
            apply_weighted(coarse, &b, w, &v, &mut direct);
            let worst = galerkin.iter().zip(&direct).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(worst < 1e-12, "{fine:?} under {b:?}: Pᵀ·A·P vs the weighted stencil: {worst:e}");
        }
    }
    // The V-cycle is symmetric and positive, and cuts the iterations of
    // every boundary (and of a closed box whose sides all differ).
    let mut kinds = boundaries::<3>();
    kinds.push(Boundary::<3>::CLOSED);
    let mut counts = Vec::new();
    for b in kinds {
        let dims = [24, 20, 16];
        let mut mg = AggregateMultigrid::new(dims, b);
        assert!(mg.depth() >= 3, "{b:?}: {} levels", mg.depth());
        crate::checks::assert_symmetric_positive(&format!("{b:?}"), dims.iter().product(), !b.has_outflow(), |r, z| mg.apply(r, z));
        let cfg = MacGrid::new([dims[0], dims[1], dims[2]]).with_dt(1.0).with_boundary(b);
        let x = signed_state(&cfg, 91);
        // The solver itself: `Project` takes the FFT on a box periodic on every axis.
        let iterations = |precond| {
            let mut solver = PressureSolver::new(&cfg, 1e-10, 3000, precond);
            smoke::project(&cfg, &mut x.clone(), &mut solver, &mut ProjectScratch::new(cfg.n_s())).unwrap_or_else(|e| panic!("{b:?}, {precond}: {e}"))
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

/// Enzyme's VJP of the semi-Lagrangian advection of each choice of fields
/// against the hand-written adjoint, in the box `cfg`.
fn enzyme_advection_adjoint_is_the_hand_one<const D: usize>(cfg: MacGrid<D>)
where
    Advect<D>: Vjp,
{
    let x = signed_state(&cfg, 17);
    for (smoke, velocity) in [(true, true), (true, false), (false, true)] {
        let op = Advect { cfg, dt: cfg.dt, scheme: Scheme::SemiLagrangian, smoke, velocity };
        let g = field(cfg.n_state(), 23);
        let (mut dy, mut enzyme) = (g.clone(), vec![0.0; cfg.n_state()]);
        op.vjp(&x, &[], &mut dy, &mut enzyme, &mut []);
        let (mut gy, mut hand) = (g.clone(), vec![0.0; cfg.n_state()]);
        smoke::advect_adjoint(&cfg, cfg.dt, smoke, velocity, &x, &mut gy, &mut hand);
        let scale = hand.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let worst = enzyme.iter().zip(&hand).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        assert!(worst < 1e-12 * scale, "{:?} {:?}, smoke {smoke}, velocity {velocity}: Enzyme vs hand {worst:e}", cfg.n, cfg.boundary);
    }
}

#[test]
fn enzyme_advection_adjoint_matches_the_hand_written_one_under_every_boundary() {
    for b in boundaries::<2>() {
        enzyme_advection_adjoint_is_the_hand_one(MacGrid::new([8, 6]).with_dt(0.9).with_boundary(b));
    }
    for b in boundaries::<3>() {
        enzyme_advection_adjoint_is_the_hand_one(MacGrid::new([7, 6, 5]).with_dt(0.9).with_boundary(b));
    }
}

/// On a box periodic on every axis the projection operator takes the FFT,
/// which equals the conjugate-gradient projection to its tolerance; with
/// an obstacle it solves by CG.
fn periodic_projection_is_the_fft<const D: usize>(n: [usize; D], shape: Solid<D>) {
    let cfg = MacGrid::new(n).with_boundary(Boundary::all(Side::Periodic));
    let x = signed_state(&cfg, 3);
    let op = Project::new(cfg, 1e-13, 2000, Preconditioner::Multigrid);
    assert!(op.by_fft(), "{n:?}");
    assert!(!Project::with_obstacles(cfg, 1e-13, 2000, Preconditioner::Multigrid, &solid_cells(&cfg, &[shape])).by_fft());
    let y = op.eval(&x, &[]);
    let mut z = x.clone();
    let mut solver = PressureSolver::new(&cfg, 1e-13, 2000, Preconditioner::Multigrid);
    smoke::project(&cfg, &mut z, &mut solver, &mut ProjectScratch::new(cfg.n_s())).unwrap();
    let scale = z.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let worst = y.iter().zip(&z).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-10 * scale, "{n:?}: FFT and CG projections differ by {worst:e}");
    assert_eq!(op.log.cg_forward.get(), 0);
}

#[test]
fn a_periodic_box_projects_by_fft() {
    periodic_projection_is_the_fft([12, 10], Solid::Ball { center: [5.0, 5.0], radius: 2.0 });
    periodic_projection_is_the_fft([6, 5, 4], Solid::Ball { center: [3.0, 2.5, 2.0], radius: 1.5 });
}

//! Boundary kinds of the fluid (closed, periodic, inflow with a profile,
//! outflow): validation, the exact behaviour each promises, and the three
//! gradient checks of every operator under every kind, with and without an
//! obstacle, on square and oblong boxes. The operators written once for
//! every dimension are checked here by one test function run for `D = 2`
//! and `D = 3` ([`operators_written_once_pass_all_checks`]); the 3D-only
//! parts are in `boundaries3d.rs`.

use diffsim::fluids::{Advect, AdvectUpwind, Buoyancy, Diffuse, Force, Project};
use diffsim::op::{Forward, Jvp, OperatorExt, Vjp};
use diffsim::problems::smoke::{SmokeAdvect, SmokeAdvectHand, SmokeStep};
use diffsim_solvers::boundary::{Boundary, BoundaryError, Profile, Side};
use diffsim_solvers::smoke::{MacGrid, Preconditioner, Scheme, divergence};

use crate::checks::{assert_passes, smoke_state};

/// P2's buoyant box of `nx × ny` cells with boundary `b`.
fn rect(nx: usize, ny: usize, b: Boundary) -> MacGrid<2> {
    MacGrid { n: [nx, ny], ..MacGrid::p2(nx).with_boundary(b) }
}

/// One boundary of each kind, and mixtures.
fn boundaries() -> Vec<Boundary> {
    vec![
        Boundary::all(Side::Periodic),
        Boundary::axes([Side::Periodic, Side::Closed]),
        Boundary::CLOSED.with_lower(0, Side::Inflow(Profile::Uniform(0.4))).with_upper(0, Side::Outflow),
        Boundary::axes([Side::Periodic, Side::Closed]).with_lower(1, Side::Inflow(Profile::Parabolic(0.5))).with_upper(1, Side::Outflow),
        Boundary::CLOSED.with_upper(1, Side::Outflow),
    ]
}

#[test]
fn invalid_boundaries_are_refused_with_the_reason() {
    assert!(Boundary::<2>::CLOSED.validate().is_ok());
    let half = Boundary::<2>::CLOSED.with_lower(0, Side::Periodic);
    assert_eq!(half.validate(), Err(BoundaryError::HalfPeriodic { axis: "x" }));
    let inflow = Boundary::<2>::CLOSED.with_lower(0, Side::Inflow(Profile::Uniform(1.0)));
    assert_eq!(inflow.validate(), Err(BoundaryError::InflowWithoutOutflow));
    assert!(inflow.validate().unwrap_err().to_string().contains("outflow"));
    for b in boundaries() {
        assert!(b.validate().is_ok(), "{b:?}");
    }
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
}

/// A seeded state of any box: smoke in [0, 2], each velocity component of
/// one sign (even axes positive, odd negative) with speeds in [0.15, 0.45]
/// cells per step, so that traced points stay away from the lattice planes
/// where multilinear sampling kinks.
fn signed_state<const D: usize>(cfg: &MacGrid<D>, seed: u64) -> Vec<f64> {
    let raw = crate::p4::field(cfg.n_state(), seed);
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

#[test]
fn operators_written_once_pass_all_checks_in_2d_and_3d() {
    for b in boundaries() {
        for (n, ny) in [(5, 5), (8, 5)] {
            operators_written_once_pass_all_checks(rect(n, ny, b), 90 + n as u64);
        }
    }
    operators_written_once_pass_all_checks(MacGrid::p2(16), 3);
    for b in crate::boundaries3d::boundaries() {
        operators_written_once_pass_all_checks(MacGrid { buoyancy: 0.1, ..MacGrid::new([6, 5, 4]) }.with_dt(0.8).with_boundary(b), 31);
    }
    operators_written_once_pass_all_checks(MacGrid::p4(16), 5);
}

#[test]
fn every_operator_passes_all_checks_under_every_boundary() {
    for b in boundaries() {
        for (n, ny) in [(5, 5), (8, 5)] {
            let cfg = rect(n, ny, b);
            let x = smoke_state(&cfg, 90 + n as u64);
            let name = |op: &str| format!("{op} {n}×{ny} {b:?}");
            assert_passes(&name("SmokeStep"), &SmokeStep::new(cfg, 1e-13, 4000, Preconditioner::None), &x, &[]);
            let solid: Vec<bool> = (0..n * ny).map(|c| (2..4).contains(&(c % n)) && (2..4).contains(&(c / n))).collect();
            assert_passes(&name("SmokeStep with obstacle"), &SmokeStep::with_obstacles(cfg, 1e-13, 4000, &solid), &x, &[]);
            assert_passes(&name("projection with obstacle"), &Project::with_obstacles(cfg, 1e-13, 4000, &solid), &x, &[]);
            assert_passes(&name("explicit diffusion and viscosity"), &Diffuse::explicit(cfg, true, true), &x, &[0.2]);
            assert_passes(&name("implicit viscosity"), &Diffuse::implicit(cfg, false, true, 1e-13, 2000), &x, &[1.5]);
        }
    }
}

#[test]
fn periodic_advection_wraps_exactly() {
    // A velocity of exactly one cell per step moves every value one cell,
    // the last onto the first.
    let (n, ny) = (6, 4);
    let cfg = rect(n, ny, Boundary::all(Side::Periodic));
    let mut x = vec![0.0; cfg.n_state()];
    for (k, s) in x[..cfg.n_s()].iter_mut().enumerate() {
        *s = k as f64;
    }
    let (us, vs) = (cfg.n_s(), cfg.n_s() + cfg.n_face(0));
    x[us..vs].fill(1.0);
    x[vs..].fill(-1.0);
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: true }] {
        let y = Advect { velocity: false, ..Advect::new(cfg, scheme) }.eval(&x, &[]);
        for j in 0..ny {
            for i in 0..n {
                let from = ((j + 1) % ny) * n + (i + n - 1) % n;
                assert!((y[j * n + i] - x[from]).abs() < 1e-12, "{scheme:?} ({i},{j}): {} vs {}", y[j * n + i], x[from]);
            }
        }
    }
    // Upwind conserves the mass through the periodic faces.
    let y = AdvectUpwind { cfg, dt: 0.3 }.eval(&x, &[]);
    let mass = |v: &[f64]| v[..cfg.n_s()].iter().sum::<f64>();
    assert!((mass(&y) - mass(&x)).abs() < 1e-12 * mass(&x));
}

#[test]
fn a_channel_with_uniform_inflow_carries_it_through_after_one_projection() {
    // Uniform inflow on the left, outflow on the right, closed walls: the
    // only divergence-free field with these boundary values is the uniform
    // one, so one step from rest gives it everywhere.
    let (n, speed) = (16, 0.6);
    let b = Boundary::CLOSED.with_lower(0, Side::Inflow(Profile::Uniform(speed))).with_upper(0, Side::Outflow);
    let cfg = MacGrid { buoyancy: 0.0, ..rect(n, 6, b) };
    let step = SmokeStep::new(cfg, 1e-12, 2000, Preconditioner::None);
    let y = step.eval(&vec![0.0; cfg.n_state()], &[]);
    let (_, [u, v]) = cfg.split(&y);
    assert!(u.iter().all(|&w| (w - speed).abs() < 1e-9), "u: {:?}", &u[..n + 1]);
    assert!(v.iter().all(|&w| w.abs() < 1e-9));
}

#[test]
fn projection_leaves_no_divergence_under_every_boundary() {
    for b in boundaries() {
        let (n, ny) = (12, 9);
        let cfg = rect(n, ny, b);
        let solid: Vec<bool> = (0..n * ny).map(|c| (4..7).contains(&(c % n)) && (5..7).contains(&(c / n))).collect();
        let step = SmokeStep::with_obstacles(cfg, 1e-12, 4000, &solid);
        let mut x = smoke_state(&cfg, 5);
        for _ in 0..3 {
            x = step.eval(&x, &[]);
        }
        let (_, [u, v]) = cfg.split(&x);
        let mut d = vec![0.0; n * ny];
        divergence(&cfg, [u, v], &mut d);
        let worst = d.iter().zip(&solid).filter(|(_, s)| !**s).map(|(d, _)| d.abs()).fold(0.0, f64::max);
        assert!(worst < 1e-9, "{b:?}: divergence {worst:e}");
        if b.periodic(0) {
            assert!((0..ny).all(|j| u[j * (n + 1)] == u[j * (n + 1) + n]), "periodic copy");
        }
    }
}

#[test]
fn smoke_leaves_through_an_outflow_side() {
    // Upwind flux out of the top: the mass drops by exactly what crossed it.
    let n = 6;
    let cfg = MacGrid::p2(n).with_boundary(Boundary::CLOSED.with_upper(1, Side::Outflow));
    let mut x = vec![0.0; cfg.n_state()];
    x[..cfg.n_s()].fill(1.0);
    let vs = cfg.n_s() + cfg.n_face(0);
    x[vs..].fill(0.5);
    let y = AdvectUpwind { cfg, dt: 0.2 }.eval(&x, &[]);
    let mass = |v: &[f64]| v[..cfg.n_s()].iter().sum::<f64>();
    // Through the bottom: closed; through the top: n faces × 0.5 × 0.2 × 1.
    assert!((mass(&x) - mass(&y) - n as f64 * 0.1).abs() < 1e-12, "{} → {}", mass(&x), mass(&y));
}

#[test]
fn diffusion_on_a_periodic_box_conserves_mass_and_momentum() {
    let n = 8;
    let cfg = MacGrid::p2(n).with_boundary(Boundary::all(Side::Periodic));
    let x = smoke_state(&cfg, 17);
    let ns = cfg.n_s();
    // Sums over the samples (a periodic axis's copy faces left out).
    let sums = |y: &[f64]| {
        let (s, [u, v]) = cfg.split(y);
        let su: f64 = (0..n).map(|j| u[j * (n + 1)..j * (n + 1) + n].iter().sum::<f64>()).sum();
        (s.iter().sum::<f64>(), su, v[..n * n].iter().sum::<f64>())
    };
    let before = sums(&x);
    for y in [Diffuse::explicit(cfg, true, true).eval(&x, &[0.2]), Diffuse::implicit(cfg, true, true, 1e-13, 2000).eval(&x, &[3.0])] {
        let after = sums(&y);
        for (a, b) in [(before.0, after.0), (before.1, after.1), (before.2, after.2)] {
            assert!((a - b).abs() < 1e-10, "{a} → {b}");
        }
        // It smooths: the smoke's spread shrinks.
        let spread = |v: &[f64]| v.iter().fold(0.0f64, |m, &a| m.max(a)) - v.iter().fold(1.0f64, |m, &a| m.min(a));
        assert!(spread(&y[..ns]) < spread(&x[..ns]));
        assert_eq!(y[ns + n], y[ns], "periodic copy refreshed");
    }
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
    let op = Project::with_obstacles(cfg, 1e-10, 500, &row);
    let _ = op.eval(&smoke_state(&cfg, 1), &[]);
    assert!(op.take_error().is_some(), "a sealed fed region converged");
}

//! Periodic Navier–Stokes as an operator (`src/navier_stokes.rs`), 2D and 3D
//! from one code: the three gradient checks with respect to the velocity,
//! the viscosity and the time step, with one sub-step and with several;
//! a call split into sub-steps is those sub-steps; a blown-up velocity or
//! a bad parameter is an error, not a result.

use diffsim::check::{CheckParams, check_all};
use diffsim::navier_stokes::{AdvectVelocity, PeriodicNavierStokes};
use diffsim::op::{Forward, OpError, OperatorExt};
use diffsim_solvers::exact::on_faces;
use diffsim_solvers::mac::periodic::Periodic;
use diffsim_solvers::smoke::Scheme;

/// A smooth periodic velocity (a few low modes, amplitude about `a`) on the
/// faces of the box, copies included.
fn velocity<const D: usize>(flow: &Periodic<D>, a: f64, seed: usize) -> Vec<f64> {
    on_faces(flow.n(), flow.h, |axis, p| {
        let phase = seed as f64 * 0.37 + axis as f64 + p.iter().enumerate().map(|(b, x)| (b + 1 + seed % 3) as f64 * x).sum::<f64>();
        a * (phase.sin() + 0.3 * (2.0 * phase + 1.0).cos() + 0.4)
    })
}

fn checks<const D: usize>(n: [usize; D])
where
    PeriodicNavierStokes<D>: diffsim::op::Vjp + diffsim::op::Jvp,
    AdvectVelocity<D>: diffsim::op::Vjp + diffsim::op::Jvp,
{
    let h = 2.0 * std::f64::consts::PI / n[0] as f64;
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        let flow = Periodic::new(n, h, 0.0, scheme);
        let op = PeriodicNavierStokes::new(flow);
        let x = velocity(&flow, 0.3, 1);
        // Its advection alone.
        let advect = AdvectVelocity { grid: flow.grid, h, scheme };
        let r = check_all(&advect, &x, &[0.2], &CheckParams::default());
        assert!(r.passed(), "advection, D = {D}, {scheme:?}:\n{r}");
        // One sub-step, then two (the viscous number above its limit).
        for p in [[0.05, 0.2], [0.9 * h * h, 0.3]] {
            let r = check_all(&op, &x, &p, &CheckParams::default());
            assert!(r.passed(), "D = {D}, {scheme:?}, p = {p:?}:\n{r}");
        }
    }
}

#[test]
fn the_periodic_step_passes_the_three_checks_in_2d_and_3d() {
    checks([8, 8]);
    checks([5, 5, 5]);
}

/// On a periodic box below a cell per sub-step the advection runs the
/// traces shorter than a cell (`diffsim_solvers::smoke::advect_velocity`):
/// Enzyme's VJP there equals the hand-written adjoint, with respect to the
/// velocity and the time step; past a cell (the general traces) the three
/// checks pass.
fn near_advection<const D: usize>(n: [usize; D])
where
    AdvectVelocity<D>: diffsim::op::Vjp + diffsim::op::Jvp,
{
    let h = 2.0 * std::f64::consts::PI / n[0] as f64;
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        let flow = Periodic::new(n, h, 0.0, scheme);
        let advect = AdvectVelocity { grid: flow.grid, h, scheme };
        let x = velocity(&flow, 0.3, 3);
        let w = velocity(&flow, 1.0, 5);
        let p = [0.2];
        let (gx, gp) = advect.vjp_new(&x, &p, &w);
        let mut hand = vec![0.0; x.len()];
        let gdt = diffsim_solvers::smoke::advect_velocity_near_adjoint(&flow.grid, scheme, p[0] / h, &x, &w, &mut hand) / h;
        let scale = gx.iter().fold(gp[0].abs(), |m, v| m.max(v.abs()));
        let diff = gx.iter().zip(&hand).fold((gp[0] - gdt).abs(), |m, (a, b)| m.max((a - b).abs()));
        assert!(diff <= 1e-13 * scale, "D = {D}, {scheme:?}: Enzyme and hand differ by {diff:e} (scale {scale:e})");
        let vmax = x.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let r = check_all(&advect, &x, &[1.6 * h / vmax], &CheckParams::default());
        assert!(r.passed(), "past a cell, D = {D}, {scheme:?}:\n{r}");
    }
}

#[test]
fn the_near_advection_adjoint_is_the_hand_one_and_past_a_cell_the_checks_pass() {
    near_advection([8, 8]);
    near_advection([5, 5, 5]);
}

#[test]
fn a_call_is_its_substeps_and_a_blown_up_velocity_is_refused() {
    let n = 8;
    let h = 2.0 * std::f64::consts::PI / n as f64;
    let flow = Periodic::new([n, n], h, 0.3, Scheme::MacCormack { limiter: true });
    let op = PeriodicNavierStokes::new(flow);
    let x = velocity(&flow, 1.0, 2);
    let dt = 3.0 * h;
    let k = flow.substeps(flow.viscosity, dt, &x);
    assert!(k > 3, "{k} sub-steps");
    let mut y = vec![0.0; x.len()];
    op.forward(&x, &[flow.viscosity, dt], &mut y);
    assert!(op.take_error().is_none());
    let (mut by_hand, mut work) = (x.clone(), flow.work());
    for _ in 0..k {
        flow.substep(dt / k as f64, &mut by_hand, &mut work);
    }
    let diff = y.iter().zip(&by_hand).fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    assert!(diff < 1e-13, "the operator and the solver's sub-steps differ by {diff:e}");
    let mut bad = x.clone();
    bad[5] = f64::INFINITY;
    op.forward(&bad, &[flow.viscosity, dt], &mut y);
    assert!(matches!(op.take_error(), Some(OpError::Unstable { .. })), "an infinite velocity must be refused");
    assert_eq!(y, bad, "the refused call leaves the velocity as it was");
    // A negative viscosity or a time step that is not finite: refused the same way.
    op.forward(&x, &[-0.1, dt], &mut y);
    let e = op.take_error();
    assert!(matches!(e, Some(OpError::Input(_))) && y == x, "a negative viscosity: {e:?}");
    op.forward(&x, &[flow.viscosity, f64::NAN], &mut y);
    let e = op.take_error();
    assert!(matches!(e, Some(OpError::Input(_))) && y == x, "a time step that is not a number: {e:?}");
}

#[test]
fn the_step_on_cell_centres_passes_the_three_checks_in_2d_and_3d() {
    use diffsim::navier_stokes::FacesToCentres;
    // The centred velocity of the same smooth field, through the step
    // wrapped in the spectral conversions.
    let flow2 = Periodic::new([8, 8], 2.0 * std::f64::consts::PI / 8.0, 0.0, Scheme::MacCormack { limiter: false });
    let x2 = FacesToCentres(flow2).eval(&velocity(&flow2, 0.3, 2), &[]);
    let r = check_all(&PeriodicNavierStokes::new(flow2).centred(), &x2, &[0.05, 0.2], &CheckParams::default());
    assert!(r.passed(), "2D:\n{r}");
    let flow3 = Periodic::new([5, 5, 5], 2.0 * std::f64::consts::PI / 5.0, 0.0, Scheme::SemiLagrangian);
    let x3 = FacesToCentres(flow3).eval(&velocity(&flow3, 0.3, 2), &[]);
    // Under a body force too (given on the faces).
    let mut p3 = vec![0.05, 0.2];
    p3.extend(velocity(&flow3, 0.5, 5));
    let r = check_all(&PeriodicNavierStokes::forced(flow3).centred(), &x3, &p3, &CheckParams::default());
    assert!(r.passed(), "3D:\n{r}");
}

#[test]
fn a_flow_at_rest_along_an_axis_has_the_gradient_central_differences_see() {
    use diffsim::op::Vjp;
    // The 3D Taylor–Green vortex has w = 0: every face's trace back lands
    // exactly on a lattice plane along z, where the multilinear sample has
    // a kink. The gradient takes the mean of its two slopes there, which is
    // what central differences measure (one-sided, it was off by about 2 %
    // in Mosaic's fd_check); MacCormack and semi-Lagrangian.
    let n = 8;
    let h = 2.0 * std::f64::consts::PI / n as f64;
    for scheme in [Scheme::MacCormack { limiter: false }, Scheme::SemiLagrangian] {
        let flow = Periodic::new([n, n, n], h, 0.0, scheme);
        let op = PeriodicNavierStokes::new(flow);
        let x = on_faces([n, n, n], h, |a, [x, y, z]| match a {
            0 => x.sin() * y.cos() * z.cos(),
            1 => -x.cos() * y.sin() * z.cos(),
            _ => 0.0,
        });
        let p = [0.001, 0.05];
        let m = x.len();
        let w: Vec<f64> = (0..m).map(|k| ((k as f64) * 0.731).sin()).collect();
        let d: Vec<f64> = (0..m).map(|k| ((k as f64) * 1.37 + 0.2).cos()).collect();
        let (mut dx, mut dp, mut dy) = (vec![0.0; m], vec![0.0; 2], w.clone());
        op.vjp(&x, &p, &mut dy, &mut dx, &mut dp);
        let along: f64 = dx.iter().zip(&d).map(|(a, b)| a * b).sum();
        let value = |t: f64| {
            let xt: Vec<f64> = x.iter().zip(&d).map(|(a, b)| a + t * b).collect();
            op.eval(&xt, &p).iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
        };
        // (Within 1e-4, not to rounding: where the averaged velocities
        // cancel to a rounding error instead of zero, the kink lies within
        // the differences' ±ε and they see both sides while the gradient
        // sees one; the exact zeros of w, which gave percents, are handled.)
        let eps = 1e-6;
        let fd = (value(eps) - value(-eps)) / (2.0 * eps);
        assert!((fd - along).abs() < 1e-4 * fd.abs(), "{scheme:?}: finite differences {fd} against the VJP's {along}");
    }
}

#[test]
fn a_rollout_on_cell_centres_converts_once_and_passes_the_three_checks() {
    use diffsim::navier_stokes::{Centred, FacesToCentres};
    use diffsim::rollout::Repeat;
    let flow = Periodic::new([8, 8], 2.0 * std::f64::consts::PI / 8.0, 0.0, Scheme::MacCormack { limiter: false });
    let x = FacesToCentres(flow).eval(&velocity(&flow, 0.3, 2), &[]);
    let p = [0.05, 0.2];
    let once = Centred::around(flow, Repeat::new(PeriodicNavierStokes::new(flow), 3).unwrap());
    let r = check_all(&once, &x, &p, &CheckParams::default());
    assert!(r.passed(), "{r}");
    // The same as converting at every step for a smooth field (a
    // Taylor–Green vortex moving through the box: nothing at the Nyquist
    // modes at first), to a small fraction of it.
    let tg = on_faces([8, 8], flow.h, |a, [x, y]| if a == 0 { x.sin() * y.cos() + 0.3 } else { -x.cos() * y.sin() + 0.2 });
    let x = FacesToCentres(flow).eval(&tg, &[]);
    let step = PeriodicNavierStokes::new(flow).centred();
    let chained = (0..3).fold(x.clone(), |v, _| step.eval(&v, &p));
    let y = once.eval(&x, &p);
    let (off, big) = y.iter().zip(&chained).fold((0.0f64, 0.0f64), |(o, b), (a, c)| (o.max((a - c).abs()), b.max(c.abs())));
    assert!(off < 1e-3 * big, "{off:.3e} of {big:.3e}");
}

#[test]
fn a_body_force_holds_the_taylor_green_vortex_steady_and_its_gradient_checks() {
    // f = 2ν·u₀ balances the viscous decay of the Taylor–Green vortex
    // (Δu₀ = −2u₀ on [0, 2π]²; its advection is a gradient): forced, the
    // vortex stays; unforced, it decays to e^{−2νt}.
    let (n, nu, dt) = (32, 0.5, 0.1);
    let h = 2.0 * std::f64::consts::PI / n as f64;
    let flow = Periodic::new([n, n], h, nu, Scheme::MacCormack { limiter: false });
    let u0 = on_faces([n, n], h, |a, [x, y]| if a == 0 { x.sin() * y.cos() } else { -x.cos() * y.sin() });
    let mut p = vec![nu, dt];
    p.extend(u0.iter().map(|u| 2.0 * nu * u));
    let (forced, free) = (PeriodicNavierStokes::forced(flow), PeriodicNavierStokes::new(flow));
    let (mut a, mut b) = (u0.clone(), u0.clone());
    for _ in 0..10 {
        a = forced.eval(&a, &p);
        b = free.eval(&b, &p[..2]);
    }
    let off = |v: &[f64], scale: f64| v.iter().zip(&u0).fold(0.0f64, |m, (x, u)| m.max((x - scale * u).abs()));
    assert!(off(&a, 1.0) < 0.02, "forced: {:.3e} from the initial vortex", off(&a, 1.0));
    assert!(off(&b, (-2.0 * nu).exp()) < 0.02 && off(&b, 1.0) > 0.5, "unforced: {:.3e} from the exact decay", off(&b, (-2.0 * nu).exp()));
    // The three checks with respect to the velocity, ν, dt and the force.
    let small = Periodic::new([8, 8], 2.0 * std::f64::consts::PI / 8.0, 0.0, Scheme::MacCormack { limiter: false });
    let op = PeriodicNavierStokes::forced(small);
    let x = velocity(&small, 0.3, 3);
    let mut q = vec![0.05, 0.2];
    q.extend(velocity(&small, 0.5, 4));
    let r = check_all(&op, &x, &q, &CheckParams::default());
    assert!(r.passed(), "forced step:\n{r}");
}

// ---- Any box: `NavierStokes<D>` (src/navier_stokes/step.rs) ----

use diffsim::navier_stokes::{NavierStokes, NavierStokesError, Viscosity};
use diffsim_solvers::boundary::{Boundary, Profile, Side};
use diffsim_solvers::smoke::{MacGrid, Preconditioner, Solid, solid_cells};

/// The box of `n` cells with `sides` (`[lower, upper]` per axis).
fn boxed<const D: usize>(n: [usize; D], sides: [[Side; 2]; D]) -> MacGrid<D> {
    MacGrid::new(n).with_boundary(Boundary { sides })
}

/// A smooth velocity (amplitude about `a`) on the faces of any box.
fn box_velocity<const D: usize>(n: [usize; D], h: f64, a: f64, seed: usize) -> Vec<f64> {
    on_faces(n, h, |axis, p| {
        let phase = seed as f64 * 0.37 + axis as f64 + p.iter().enumerate().map(|(b, x)| (b + 1 + seed % 3) as f64 * 2.1 * x).sum::<f64>();
        a * (phase.sin() + 0.3 * (2.0 * phase + 1.0).cos() + 0.4)
    })
}

/// The three checks of the step on `grid` at two time steps (one sub-step,
/// then several), with the velocity, ν, dt, the inflow profile and (when
/// `forced`) a body force all perturbed.
fn box_checks<const D: usize>(what: &str, grid: MacGrid<D>, viscosity: Viscosity, forced: bool, solid: Option<&[bool]>)
where
    NavierStokes<D>: diffsim::op::Vjp + diffsim::op::Jvp,
{
    let h = 1.0 / grid.n[0] as f64;
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        let mut op = NavierStokes::new(grid, h, scheme).unwrap().with_viscosity(viscosity).with_projection(1e-13, 4000, Preconditioner::Multigrid);
        if forced {
            op = op.forced();
        }
        if let Some(solid) = solid {
            op = op.with_obstacles(solid).unwrap();
        }
        let x = box_velocity(grid.n, h, 0.3, 1);
        let nu = 0.05;
        // One sub-step (κ = 0.16·h²/h², Courant about 0.3), then several.
        for dt in [0.16 * h * h / nu * 0.9, 2.5 * h * h / nu] {
            let mut p = op.params(nu, dt);
            if forced {
                let f = box_velocity(grid.n, h, 0.5, 4);
                let start = p.len() - f.len();
                p[start..].copy_from_slice(&f);
            }
            let r = check_all(&op, &x, &p, &CheckParams::default());
            assert!(r.passed(), "{what}, D = {D}, {scheme:?}, dt = {dt}:\n{r}");
        }
    }
}

#[test]
fn the_step_on_any_box_passes_the_three_checks_in_2d_and_3d() {
    use Side::*;
    let inflow = Inflow(Profile::Parabolic(0.5));
    let implicit = Viscosity::Implicit { tolerance: 1e-13, max_iterations: 500 };
    // Between no-slip walls, periodic along x, under a body force.
    box_checks("no-slip walls, forced", boxed([8, 6], [[Periodic, Periodic], [NoSlip, NoSlip]]), Viscosity::Explicit, true, None);
    // A channel: a parabolic inflow, an outflow, no-slip walls; implicit viscosity.
    box_checks("channel", boxed([8, 6], [[inflow, Outflow], [NoSlip, NoSlip]]), implicit, false, None);
    // A closed (free-slip) box with an obstacle.
    let closed = boxed([8, 8], [[Closed, Closed], [Closed, NoSlip]]);
    let solid = solid_cells(&closed, &[Solid::Box { lower: [3.0, 3.0], upper: [5.0, 5.0] }]);
    box_checks("closed box with an obstacle", closed, Viscosity::Explicit, false, Some(&solid));
    // 3D: a channel along x, no-slip along y, periodic along z, forced.
    box_checks("3D channel", boxed([5, 4, 4], [[inflow, Outflow], [NoSlip, NoSlip], [Periodic, Periodic]]), Viscosity::Explicit, true, None);
}

#[test]
fn on_a_periodic_box_the_step_is_the_solvers_periodic_step() {
    // The operator against the solvers crate's own forward code for the
    // periodic box (`Periodic::step`: its advection, its viscosity, the
    // FFT), in 2D and 3D, over several sub-steps.
    fn same<const D: usize>(n: [usize; D])
    where
        NavierStokes<D>: Forward,
    {
        let h = 2.0 * std::f64::consts::PI / n[0] as f64;
        let mut flow = Periodic::new(n, h, 0.0, Scheme::MacCormack { limiter: true });
        let x = velocity(&flow, 0.8, 3);
        // Several sub-steps: κ and the Courant number both above their limits.
        let p = [0.3 * h * h, 2.0 * h];
        flow.viscosity = p[0];
        let any = NavierStokes::new(flow.grid, h, flow.scheme).unwrap();
        let a = any.eval(&x, &p);
        let mut b = x.clone();
        let k = flow.step(p[1], &mut b, &mut flow.work());
        assert!(k > 1, "{k} sub-steps");
        let diff = a.iter().zip(&b).fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(diff < 1e-12, "D = {D}: the operator and the solver's step differ by {diff:e}");
    }
    same([8, 8]);
    same([5, 5, 5]);
}

/// Plane Poiseuille flow between no-slip walls at y = 0 and 1 (periodic on
/// the other axes), driven by a body force `g` along x: steady `u(y) =
/// g/(2ν)·y(1 − y)`. Returns the largest error of the steady state reached
/// from rest over `t = 2` (the slowest mode decays as `e^{−π²νt}`).
fn poiseuille<const D: usize>(n: [usize; D], viscosity: Viscosity, dt: f64) -> f64
where
    NavierStokes<D>: Forward,
{
    let mut sides = [[Side::Periodic; 2]; D];
    sides[1] = [Side::NoSlip; 2];
    let grid = boxed(n, sides);
    let (h, nu, g) = (1.0 / n[1] as f64, 1.0, 8.0);
    let op = NavierStokes::new(grid, h, Scheme::SemiLagrangian).unwrap().with_viscosity(viscosity).forced();
    let mut p = op.params(nu, dt);
    let u_faces = grid.face_range(0);
    for v in &mut p[2 + u_faces.start..2 + u_faces.end] {
        *v = g;
    }
    let mut x = vec![0.0; grid.n_vel()];
    for _ in 0..(2.0 / dt).round() as usize {
        x = op.eval(&x, &p);
    }
    let exact = on_faces(n, h, |axis, q| if axis == 0 { g / (2.0 * nu) * q[1] * (1.0 - q[1]) } else { 0.0 });
    x.iter().zip(&exact).fold(0.0f64, |m, (a, b)| m.max((a - b).abs()))
}

#[test]
fn poiseuille_flow_between_no_slip_walls_converges_at_second_order() {
    // Explicit viscosity (many sub-steps), then implicit (few, long ones):
    // the same steady state.
    let implicit = Viscosity::Implicit { tolerance: 1e-12, max_iterations: 500 };
    let e: Vec<f64> = [8, 16, 32].iter().map(|&n| poiseuille([4, n], Viscosity::Explicit, 0.1)).collect();
    let orders: Vec<f64> = e.windows(2).map(|w| (w[0] / w[1]).log2()).collect();
    assert!(orders.iter().all(|&o| (1.9..2.1).contains(&o)), "errors {e:?}, orders {orders:?}");
    // The error is the no-slip ghost value's: g·h²/(8ν) = h² here.
    assert!(e[2] < 1.05 / (32.0 * 32.0), "32 cells: error {:.3e}", e[2]);
    let ei = poiseuille([4, 16], implicit, 0.5);
    assert!((ei - e[1]).abs() < 1e-3 * e[1], "implicit viscosity: error {ei:.4e} against explicit {:.4e}", e[1]);
    // 3D, periodic along x and z: the same profile.
    let e3 = poiseuille([4, 16, 4], Viscosity::Explicit, 0.1);
    assert!((e3 - e[1]).abs() < 1e-3 * e[1], "3D: error {e3:.4e} against 2D {:.4e}", e[1]);
}

#[test]
fn a_channel_with_a_parabolic_inflow_keeps_its_poiseuille_profile() {
    // Inflow u = 4y(1 − y) on the left, outflow on the right, no-slip walls;
    // started from that profile everywhere, the flow stays on it (the
    // pressure gradient balancing the viscosity).
    let (nx, ny) = (32, 16);
    let h = 1.0 / ny as f64;
    let grid = boxed([nx, ny], [[Side::Inflow(Profile::Parabolic(1.0)), Side::Outflow], [Side::NoSlip, Side::NoSlip]]);
    let op = NavierStokes::new(grid, h, Scheme::MacCormack { limiter: true }).unwrap();
    let exact = on_faces([nx, ny], h, |axis, q| if axis == 0 { 4.0 * q[1] * (1.0 - q[1]) } else { 0.0 });
    let p = op.params(0.1, 0.1);
    let mut x = exact.clone();
    for _ in 0..20 {
        x = op.eval(&x, &p);
        assert!(op.take_error().is_none());
    }
    let off = x.iter().zip(&exact).fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    assert!(off < 0.02, "{off:.3e} from the Poiseuille profile after t = 2");
    // The profile is the parameters' (the faces of the left side).
    assert_eq!(op.inflow_faces().len(), ny);
    assert!(op.inflow_faces().iter().zip(&p[2..]).all(|(f, &q)| f.speed == q && f.sign == 1.0));
}

#[test]
fn a_bad_box_or_call_of_the_any_box_step_is_an_error() {
    let h = 0.1;
    let scheme = Scheme::SemiLagrangian;
    // Inflow without an outflow side; a cell size of zero; too few cells.
    let no_outflow = boxed([8, 8], [[Side::Inflow(Profile::Uniform(1.0)), Side::Closed], [Side::NoSlip, Side::NoSlip]]);
    let e = NavierStokes::new(no_outflow, h, scheme).unwrap_err();
    assert!(matches!(e, NavierStokesError::Sides(_)) && e.to_string().contains("outflow"), "{e}");
    assert!(matches!(NavierStokes::new(boxed([8, 8], [[Side::Closed; 2]; 2]), 0.0, scheme), Err(NavierStokesError::CellSize(_))));
    assert!(matches!(NavierStokes::new(boxed([1, 8], [[Side::Closed; 2]; 2]), h, scheme), Err(NavierStokesError::TooFewCells(_))));
    let grid = boxed([8, 8], [[Side::Closed; 2], [Side::NoSlip; 2]]);
    let op = NavierStokes::new(grid, h, scheme).unwrap();
    assert!(matches!(op.with_obstacles(&[true; 64]), Err(NavierStokesError::AllSolid)), "every cell solid");
    let op = NavierStokes::new(grid, h, scheme).unwrap();
    let x = box_velocity(grid.n, h, 0.3, 2);
    let mut y = vec![0.0; x.len()];
    op.forward(&x, &[-1.0, 0.1], &mut y);
    let e = op.take_error();
    assert!(matches!(e, Some(OpError::Input(_))) && y == x, "a negative viscosity: {e:?}");
    assert!(e.unwrap().to_string().contains("viscosity p[0] = -1"));
    let mut bad = x.clone();
    bad[3] = f64::NAN;
    op.forward(&bad, &[0.1, 0.1], &mut y);
    assert!(matches!(op.take_error(), Some(OpError::Unstable { .. })), "a velocity that is not a number");
}

// ---- The drag on obstacles (src/navier_stokes/drag.rs) ----

#[test]
fn the_drag_is_the_pressure_on_the_obstacle_summed_along_rows_and_its_gradient_checks() {
    use Side::*;
    use diffsim::navier_stokes::SurfaceDrag;
    // Mosaic's drag box: periodic along x, no-slip walls, a disc.
    let grid = boxed([12, 10], [[Periodic, Periodic], [NoSlip, NoSlip]]);
    let h = 1.0 / 12.0;
    let solid = solid_cells(&grid, &[Solid::Ball { center: [6.0, 5.0], radius: 2.2 }]);
    let drag = SurfaceDrag::new(&grid, h, &solid).unwrap();
    let scheme = Scheme::MacCormack { limiter: false };
    let op = NavierStokes::new(grid, h, scheme).unwrap().with_projection(1e-13, 4000, Preconditioner::Multigrid).with_obstacles(&solid).unwrap();
    // One projection of a rough velocity. Along a row through the disc the
    // pressure differences are the sums of the velocity change over the
    // row's faces between fluid cells (Δu = −s·∂p/∂x, around the periodic
    // side from the disc's back to its front), so the pressure term times
    // `s` is −h²·Σ Δu over every such x-face: a path other than the
    // weights' spanning tree.
    let before = box_velocity(grid.n, h, 0.7, 3);
    let mut after = before.clone();
    op.projection().apply_velocity(&mut after);
    let du: Vec<f64> = after.iter().zip(&before).map(|(a, b)| a - b).collect();
    let by_weights: f64 = drag.impulse.iter().zip(&du).map(|(w, d)| w * d).sum();
    let mut by_rows = 0.0;
    for f in diffsim_solvers::boundary::faces(grid.n, &grid.boundary, 0) {
        if let (Some(l), Some(u)) = (f.lower, f.upper)
            && !solid[l]
            && !solid[u]
        {
            by_rows -= h * h * du[f.index];
        }
    }
    assert!(by_rows.abs() > 1e-3, "a projection that changes nothing: {by_rows:e}");
    assert!((by_weights - by_rows).abs() < 1e-9 * by_rows.abs(), "weights {by_weights:e}, rows {by_rows:e}");
    // The shear sum: the disc's front cells count +ū, its back cells −ū.
    let uniform: Vec<f64> = (0..grid.n_vel()).map(|i| if i < grid.n_face(0) { 1.0 } else { 0.0 }).collect();
    let shear: f64 = drag.shear.iter().zip(&uniform).map(|(w, u)| w * u).sum();
    assert!(shear.abs() < 1e-12, "front and back cancel on a uniform flow: {shear:e}");

    // A uniform flow along +x pushes on the disc's front: the pressure
    // impulse of a step is positive (Mosaic's sign: + on the front).
    let op = op.with_drag().unwrap();
    let mut x = uniform.clone();
    x.extend([0.0, 0.0]);
    let y = op.eval(&x, &op.params(0.01, 0.05));
    assert!(op.take_error().is_none());
    assert!(y[grid.n_vel()] > 0.0, "impulse {:e}", y[grid.n_vel()]);

    // The three checks with the carried sums in the state, over one
    // sub-step and several, here and in a channel with an inflow.
    let mut x = box_velocity(grid.n, h, 0.3, 1);
    x.extend([0.3, -0.2]);
    for dt in [0.02, 0.3] {
        let r = check_all(&op, &x, &op.params(0.05, dt), &CheckParams::default());
        assert!(r.passed(), "periodic channel, dt = {dt}:\n{r}");
    }
    let channel = boxed([12, 10], [[Inflow(Profile::Parabolic(0.5)), Outflow], [NoSlip, NoSlip]]);
    let solid = solid_cells(&channel, &[Solid::Ball { center: [4.0, 5.0], radius: 2.0 }]);
    let op = NavierStokes::new(channel, h, scheme)
        .unwrap()
        .with_viscosity(Viscosity::Implicit { tolerance: 1e-13, max_iterations: 500 })
        .with_projection(1e-13, 4000, Preconditioner::Multigrid)
        .with_obstacles(&solid)
        .unwrap()
        .with_drag()
        .unwrap();
    let r = check_all(&op, &x, &op.params(0.05, 0.2), &CheckParams::default());
    assert!(r.passed(), "channel with an inflow:\n{r}");

    // Without obstacles, or with one against a closed side along x: errors.
    let closed = boxed([8, 8], [[Closed, Closed], [NoSlip, NoSlip]]);
    let e = NavierStokes::new(closed, h, scheme).unwrap().with_drag().unwrap_err();
    assert_eq!(e, NavierStokesError::NoObstacles);
    let against = solid_cells(&closed, &[Solid::Box { lower: [0.0, 3.0], upper: [2.0, 5.0] }]);
    let e = NavierStokes::new(closed, h, scheme).unwrap().with_obstacles(&against).unwrap().with_drag().unwrap_err();
    assert!(matches!(e, NavierStokesError::DragLevel { .. }), "{e}");
}

// ---- Central differences and RK3 (src/navier_stokes/central.rs) ----

use diffsim::navier_stokes::CentralNavierStokes;

/// The kinetic energy `Σ u²` over the faces that are not copies.
fn energy<const D: usize>(flow: &Periodic<D>, x: &[f64]) -> f64 {
    let mut own = vec![true; x.len()];
    for a in 0..D {
        let start = flow.grid.face_range(a).start;
        for f in diffsim_solvers::boundary::faces(flow.n(), &flow.grid.boundary, a) {
            if let Some(c) = f.copy {
                own[start + c] = false;
            }
        }
    }
    x.iter().zip(&own).filter(|(_, o)| **o).map(|(v, _)| v * v).sum()
}

fn central_checks<const D: usize>(n: [usize; D])
where
    CentralNavierStokes<D>: diffsim::op::Vjp + diffsim::op::Jvp,
{
    let h = 2.0 * std::f64::consts::PI / n[0] as f64;
    let flow = Periodic::new(n, h, 0.0, Scheme::SemiLagrangian);
    let op = CentralNavierStokes::new(flow);
    let mut x = velocity(&flow, 0.3, 1);
    // A divergence-free start: one step of nothing but the projection.
    x = op.eval(&x, &[0.0, 0.0]);
    // One sub-step, then several (the viscous and advective limits).
    for p in [[0.05, 0.2], [3.0 * h * h, 1.5]] {
        let r = check_all(&op, &x, &p, &CheckParams::default());
        assert!(r.passed(), "D = {D}, p = {p:?}:\n{r}");
    }
}

#[test]
fn the_central_step_passes_the_three_checks_in_2d_and_3d() {
    central_checks([8, 6]);
    central_checks([6, 4, 5]);
}

#[test]
fn the_central_step_keeps_its_energy_without_viscosity_and_decays_taylor_green_at_second_order() {
    // Inviscid: the flux conserves the energy, RK3 damps it slightly; it
    // never grows, over 200 steps at a Courant number near 1.
    let n = [24, 24];
    let h = 2.0 * std::f64::consts::PI / 24.0;
    let flow = Periodic::new(n, h, 0.0, Scheme::SemiLagrangian);
    let op = CentralNavierStokes::new(flow);
    let mut x = op.eval(&velocity(&flow, 1.0, 3), &[0.0, 0.0]);
    let e0 = energy(&flow, &x);
    let mut last = e0;
    for step in 0..200 {
        x = op.eval(&x, &[0.0, 0.2]);
        assert!(op.take_error().is_none());
        let e = energy(&flow, &x);
        assert!(e <= last * (1.0 + 1e-12), "step {step}: energy {e} after {last}");
        last = e;
    }
    assert!(last > 0.9 * e0, "energy {last} of {e0}: damped too much");
    // Both limits nearly reached in one sub-step (each on its own is the
    // rule): still no growth.
    let speeds: f64 = (0..2).map(|a| x[flow.grid.face_range(a)].iter().fold(0.0f64, |m, v| m.max(v.abs()))).sum();
    let dt = 1.45 * h / speeds;
    let nu = 2.25 * h * h / (8.0 * dt);
    for step in 0..100 {
        x = op.eval(&x, &[nu, dt]);
        let e = energy(&flow, &x);
        assert!(e <= last * (1.0 + 1e-12), "both limits, step {step}: energy {e} after {last}");
        last = e;
    }
    // The 2D Taylor–Green vortex against its exact decay e^{−2νt}.
    let err = |m: usize| {
        let h = 2.0 * std::f64::consts::PI / m as f64;
        let flow = Periodic::new([m, m], h, 0.0, Scheme::SemiLagrangian);
        let op = CentralNavierStokes::new(flow);
        let tg = |t: f64| on_faces([m, m], h, |a, p| (-2.0 * 0.1 * t).exp() * if a == 0 { p[0].sin() * p[1].cos() } else { -p[0].cos() * p[1].sin() });
        let mut x = tg(0.0);
        for _ in 0..10 {
            x = op.eval(&x, &[0.1, 0.1]);
        }
        x.iter().zip(&tg(1.0)).fold(0.0f64, |m, (a, b)| m.max((a - b).abs()))
    };
    let (coarse, fine) = (err(16), err(32));
    let order = (coarse / fine).log2();
    assert!((1.8..2.3).contains(&order), "Taylor–Green: {coarse:e} at 16, {fine:e} at 32, order {order:.2}");
}

#[test]
fn the_central_step_stays_bounded_where_unlimited_maccormack_blows_up() {
    // Mosaic's 3D horizon setting: the Taylor–Green vortex on 20³, ν =
    // 0.001, dt = 0.05. MacCormack without its limiter gains energy 92-fold
    // by 640 steps (docs/mosaic.md); the central step loses it.
    let m = 20;
    let h = 2.0 * std::f64::consts::PI / m as f64;
    let flow = Periodic::new([m, m, m], h, 0.0, Scheme::SemiLagrangian);
    let op = CentralNavierStokes::new(flow);
    let mut x = on_faces([m, m, m], h, |a, p| match a {
        0 => p[0].sin() * p[1].cos() * p[2].cos(),
        1 => -p[0].cos() * p[1].sin() * p[2].cos(),
        _ => 0.0,
    });
    let e0 = energy(&flow, &x);
    for step in 0..640 {
        x = op.eval(&x, &[0.001, 0.05]);
        assert!(op.take_error().is_none(), "step {step}");
    }
    let e = energy(&flow, &x);
    assert!(e.is_finite() && e < e0, "energy {e} of {e0} after 640 steps");
    // A bad parameter is refused, the velocity left as it was; so is a
    // step needing more sub-steps than allowed, naming the viscous number
    // when that is what asked for them.
    let y = op.eval(&x, &[-1.0, 0.05]);
    assert!(matches!(op.take_error(), Some(OpError::Input(_))) && y == x);
    let y = op.eval(&x, &[1e6, 0.05]);
    let e = op.take_error();
    assert!(matches!(e, Some(OpError::Unstable { value, .. }) if value > 1e6) && y == x, "{e:?}");
}

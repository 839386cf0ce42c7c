//! Periodic Navier–Stokes as an operator (`src/navier_stokes.rs`), 2D and 3D
//! from one code: the three gradient checks with respect to the velocity,
//! the viscosity and the time step, with one sub-step and with several;
//! a call split into sub-steps is those sub-steps; a blown-up velocity or
//! a bad parameter is an error, not a result.

use diffsim::check::{CheckParams, check_all};
use diffsim::navier_stokes::{PeriodicAdvect, PeriodicNavierStokes, PeriodicViscosity};
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
    PeriodicAdvect<D>: diffsim::op::Vjp + diffsim::op::Jvp,
    PeriodicViscosity<D>: diffsim::op::Vjp + diffsim::op::Jvp,
{
    let h = 2.0 * std::f64::consts::PI / n[0] as f64;
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        let flow = Periodic::new(n, h, 0.0, scheme);
        let op = PeriodicNavierStokes::new(flow);
        let x = velocity(&flow, 0.3, 1);
        // Its parts: the advection, the viscosity.
        let r = check_all(&PeriodicAdvect(flow), &x, &[0.2], &CheckParams::default());
        assert!(r.passed(), "advection, D = {D}, {scheme:?}:\n{r}");
        let r = check_all(&PeriodicViscosity(flow), &x, &[0.05, 0.2], &CheckParams::default());
        assert!(r.passed(), "viscosity, D = {D}, {scheme:?}:\n{r}");
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

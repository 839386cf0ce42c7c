//! The periodic Navier–Stokes step of `diffsim_solvers::mac::periodic`:
//! the 2D Taylor–Green vortex and the 3D ABC flow against their exact
//! decay (errors and observed orders), and the time of one step. The figures of docs/navier-stokes.md:
//!
//! ```sh
//! cargo run --release -p diffsim-solvers --example periodic_flow
//! ```

use std::f64::consts::PI;
use std::time::Instant;

use diffsim_solvers::exact::{Abc, on_faces};
use diffsim_solvers::mac::periodic::Periodic;
use diffsim_solvers::smoke::Scheme;

/// `u = sin x cos y·f`, `v = −cos x sin y·f` on the faces of `n²` cells of `[0, 2π]²`.
fn taylor_green(n: usize, f: f64) -> Vec<f64> {
    on_faces([n, n], 2.0 * PI / n as f64, |a, [x, y]| if a == 0 { x.sin() * y.cos() * f } else { -x.cos() * y.sin() * f })
}

/// The ABC flow (`A = B = C = 1`) at time `t` on the faces of `n³` cells of `[0, 2π]³`.
fn abc(n: usize, nu: f64, t: f64) -> Vec<f64> {
    let flow = Abc { coefficients: [1.0; 3], nu };
    on_faces([n, n, n], 2.0 * PI / n as f64, |a, p| flow.velocity(p, t)[a])
}

/// `(errors, observed orders)` as table cells.
fn row(errors: &[f64]) -> (String, String) {
    let orders: Vec<String> = errors.windows(2).map(|w| format!("{:.2}", (w[0] / w[1]).log2())).collect();
    let cells: Vec<String> = errors.iter().map(|e| format!("{e:.2e}")).collect();
    (cells.join(" | "), orders.join(", "))
}

/// The largest difference between two packed velocities.
fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).fold(0.0f64, |m, (a, b)| m.max((a - b).abs()))
}

/// The shortest of `runs` calls of `f`, in seconds.
fn best_of(runs: usize, mut f: impl FnMut()) -> f64 {
    (0..runs)
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

/// Runs `flow` from `start` to `t` with a time step of half a cell at unit
/// speed; the largest difference from `exact`.
fn run_error<const D: usize>(flow: Periodic<D>, start: Vec<f64>, t: f64, exact: &[f64]) -> f64 {
    let mut work = flow.work();
    let mut vel = start;
    let steps = (t / (0.5 * flow.h)).ceil() as usize;
    for _ in 0..steps {
        flow.step(t / steps as f64, &mut vel, &mut work);
    }
    max_diff(&vel, exact)
}

/// One table: a row per scheme of the errors at each size and the observed orders.
fn table(title: &str, sizes: &[usize], dims: &str, error: impl Fn(usize, Scheme) -> f64) {
    println!("{title}");
    let heads: Vec<String> = sizes.iter().map(|n| format!("{n}{dims}")).collect();
    println!("| scheme | {} | observed orders |", heads.join(" | "));
    println!("|---|{}---|", "---|".repeat(sizes.len()));
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        let errors: Vec<f64> = sizes.iter().map(|&n| error(n, scheme)).collect();
        let (cells, orders) = row(&errors);
        println!("| {scheme:?} | {cells} | {orders} |");
    }
}

fn main() {
    let (nu, t) = (0.05, 1.0);
    let title = format!("2D Taylor-Green vortex on [0, 2pi]^2, nu = {nu}, t = {t}, time step 0.5 h: largest error on the faces");
    table(&title, &[16, 32, 64, 128], "²", |n, scheme| {
        run_error(Periodic::new([n, n], 2.0 * PI / n as f64, nu, scheme), taylor_green(n, 1.0), t, &taylor_green(n, (-2.0 * nu * t).exp()))
    });
    println!();
    let title = format!("3D ABC flow (A = B = C = 1) on [0, 2pi]^3, nu = {nu}, t = {t}, time step 0.5 h: largest error on the faces");
    table(&title, &[8, 16, 32, 64], "³", |n, scheme| run_error(Periodic::new([n, n, n], 2.0 * PI / n as f64, nu, scheme), abc(n, nu, 0.0), t, &abc(n, nu, t)));
    println!();
    println!("One step (Courant 0.5, one sub-step), best of 20:");
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        for n in [64usize, 128] {
            let flow = Periodic::new([n, n], 2.0 * PI / n as f64, 0.01, scheme);
            let (mut work, mut vel) = (flow.work(), taylor_green(n, 1.0));
            let best = best_of(20, || {
                flow.step(0.5 * flow.h, &mut vel, &mut work);
            });
            println!("  2D {n}² {scheme:?}: {:.0} µs", best * 1e6);
        }
        let n = 32;
        let flow = Periodic::new([n, n, n], 2.0 * PI / n as f64, 0.01, scheme);
        let mut work = flow.work();
        let mut vel: Vec<f64> = (0..flow.n_vel()).map(|k| ((k as f64) * 0.618).fract() - 0.5).collect();
        let best = best_of(5, || {
            flow.step(0.5 * flow.h, &mut vel, &mut work);
        });
        println!("  3D {n}³ {scheme:?}: {:.0} µs", best * 1e6);
    }
    println!();
    println!("The projection of a periodic box: FFT against CG (tolerance 1e-8), best of 5:");
    projection_times();
}

/// The time of one projection of a velocity that is not divergence-free
/// on periodic boxes: the FFT, and the smoke solver's CG (2D: MIC(0), the
/// only preconditioner of a periodic 2D box; 3D: the aggregation multigrid
/// and MIC(0)).
fn projection_times() {
    use diffsim_solvers::boundary::{Boundary, Side};
    use diffsim_solvers::mac::fft::FftProjection;
    use diffsim_solvers::smoke::{MacGrid, Preconditioner, PressureSolver, ProjectScratch, project};
    use diffsim_solvers::smoke3d::{PressureSolver3, project as project3};
    let field = |len: usize| -> Vec<f64> { (0..len).map(|k| ((k as f64) * 0.618).fract() - 0.5).collect() };
    for n in [64usize, 128] {
        let cfg = MacGrid::new([n, n]).with_boundary(Boundary::all(Side::Periodic));
        let vel = field(cfg.n_vel());
        let mut fft = FftProjection::new([n, n]);
        let t_fft = best_of(5, || {
            let mut v = vel.clone();
            let (u, w) = v.split_at_mut(cfg.n_face(0));
            fft.project([u, w]);
        });
        let mut solver = PressureSolver::general(n, n, cfg.boundary, 1e-8, 10_000, None);
        let mut scratch = ProjectScratch::new(n * n);
        let mut iterations = 0;
        let t_cg = best_of(5, || {
            let mut state = vec![0.0; cfg.n_s()];
            state.extend_from_slice(&vel);
            iterations = project(&cfg, &mut state, &mut solver, &mut scratch).expect("the CG projection converges");
        });
        println!("  2D {n}²: FFT {:.0} µs, CG with MIC(0) {:.0} µs ({iterations} iterations)", t_fft * 1e6, t_cg * 1e6);
    }
    for n in [32usize, 64] {
        let cfg = MacGrid::new([n, n, n]).with_boundary(Boundary::all(Side::Periodic));
        let vel = field(cfg.n_vel());
        let mut fft = FftProjection::new([n, n, n]);
        let t_fft = best_of(5, || {
            let mut v = vel.clone();
            let (u, rest) = v.split_at_mut(cfg.n_face(0));
            let (w0, w1) = rest.split_at_mut(cfg.n_face(1));
            fft.project([u, w0, w1]);
        });
        let mut line = format!("  3D {n}³: FFT {:.0} µs", t_fft * 1e6);
        for (name, precond) in [("multigrid", Preconditioner::Multigrid), ("MIC(0)", Preconditioner::Mic0)] {
            let mut solver = PressureSolver3::new(&cfg, 1e-8, 10_000, precond);
            let mut scratch = ProjectScratch::new(cfg.n_s());
            let mut iterations = 0;
            let t = best_of(5, || {
                let mut state = vec![0.0; cfg.n_s()];
                state.extend_from_slice(&vel);
                iterations = project3(&cfg, &mut state, &mut solver, &mut scratch).expect("the CG projection converges");
            });
            line += &format!(", CG with {name} {:.0} µs ({iterations} iterations)", t * 1e6);
        }
        println!("{line}");
    }
}

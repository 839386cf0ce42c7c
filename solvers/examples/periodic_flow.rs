//! The periodic Navier–Stokes step of `diffsim_solvers::mac::periodic`:
//! the 2D Taylor–Green vortex and the 3D ABC flow against their exact
//! decay (errors and observed orders), and the time of one step. The figures of docs/navier-stokes.md:
//!
//! ```sh
//! cargo run --release -p diffsim-solvers --example periodic_flow
//! cargo run --release -p diffsim-solvers --example periodic_flow -- time   # the orders in time only
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
fn run_error<const D: usize>(flow: Periodic<D>, mut vel: Vec<f64>, t: f64, exact: &[f64]) -> f64 {
    flow.run(t, 0.5 * flow.h, &mut vel);
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
    // `-- time`: the orders in time only.
    if std::env::args().nth(1).as_deref() == Some("time") {
        return time_orders(nu, t);
    }
    let title = format!("2D Taylor-Green vortex on [0, 2pi]^2, nu = {nu}, t = {t}, time step 0.5 h: largest error on the faces");
    table(&title, &[16, 32, 64, 128], "²", |n, scheme| {
        run_error(Periodic::new([n, n], 2.0 * PI / n as f64, nu, scheme), taylor_green(n, 1.0), t, &taylor_green(n, (-2.0 * nu * t).exp()))
    });
    println!();
    let title = format!("3D ABC flow (A = B = C = 1) on [0, 2pi]^3, nu = {nu}, t = {t}, time step 0.5 h: largest error on the faces");
    table(&title, &[8, 16, 32, 64], "³", |n, scheme| run_error(Periodic::new([n, n, n], 2.0 * PI / n as f64, nu, scheme), abc(n, nu, 0.0), t, &abc(n, nu, t)));
    println!();
    time_orders(nu, t);
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
    round_trips();
    println!();
    println!("The projection of a periodic box: FFT against CG (tolerance 1e-8), best of 5:");
    projection_times();
}

/// Observed orders in time on a fixed grid: the 2D Taylor–Green vortex at
/// 64² and the ABC flow at 32³ run to `t` with steps of `dt`, `dt/2`, …;
/// the largest difference between the results of successive steps (the
/// time-stepping error alone: the grid's is the same in both) and its
/// observed order.
fn time_orders(nu: f64, t: f64) {
    let dts = [0.04, 0.02, 0.01, 0.005, 0.0025];
    println!("Orders in time on a fixed grid (nu = {nu}, t = {t}): |u(dt) − u(dt/2)|, largest on the faces, dt = {dts:?}");
    println!("| flow | scheme | differences | observed orders |");
    println!("|---|---|---|---|");
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        let runs2: Vec<Vec<f64>> = dts
            .iter()
            .map(|&dt| {
                let (n, mut vel) = (64, taylor_green(64, 1.0));
                Periodic::new([n, n], 2.0 * PI / n as f64, nu, scheme).run(t, dt, &mut vel);
                vel
            })
            .collect();
        let runs3: Vec<Vec<f64>> = dts
            .iter()
            .map(|&dt| {
                let (n, mut vel) = (32, abc(32, nu, 0.0));
                Periodic::new([n, n, n], 2.0 * PI / n as f64, nu, scheme).run(t, dt, &mut vel);
                vel
            })
            .collect();
        for (flow, runs) in [("Taylor–Green 64²", &runs2), ("ABC 32³", &runs3)] {
            let differences: Vec<f64> = runs.windows(2).map(|w| max_diff(&w[0], &w[1])).collect();
            let (cells, orders) = row(&differences);
            println!("| {flow} | {scheme:?} | {cells} | {orders} |");
        }
    }
}

/// The time of one projection of a velocity that is not divergence-free
/// on periodic boxes: the FFT, and the smoke solver's CG preconditioned by
/// the aggregation multigrid and by MIC(0).
fn projection_times() {
    for n in [64usize, 128] {
        projection_time([n, n]);
    }
    for n in [32usize, 64] {
        projection_time([n, n, n]);
    }
}

/// [`projection_times`] on a box of `n` cells.
fn projection_time<const D: usize>(n: [usize; D]) {
    use diffsim_solvers::boundary::{Boundary, Side};
    use diffsim_solvers::mac::fft::FftProjection;
    use diffsim_solvers::smoke::{MacGrid, Preconditioner, PressureSolver, ProjectScratch, project};
    let cfg = MacGrid::new(n).with_boundary(Boundary::all(Side::Periodic));
    let vel: Vec<f64> = (0..cfg.n_vel()).map(|k| ((k as f64) * 0.618).fract() - 0.5).collect();
    let mut fft = FftProjection::new(n);
    let t_fft = best_of(5, || {
        let mut v = vel.clone();
        fft.project(cfg.components_mut(&mut v));
    });
    let mut line = format!("  {D}D {}: FFT {:.0} µs", n.map(|k| k.to_string()).join("×"), t_fft * 1e6);
    for (name, precond) in [("multigrid", Preconditioner::Multigrid), ("MIC(0)", Preconditioner::Mic0)] {
        let mut solver = PressureSolver::new(&cfg, 1e-8, 10_000, precond);
        let mut scratch = ProjectScratch::new(cfg.n_s());
        let mut iterations = 0;
        let t = best_of(5, || {
            let mut state = vec![0.0; cfg.n_s()];
            state.extend_from_slice(&vel);
            iterations = project(&cfg, &mut state, &mut solver, &mut scratch).expect("the CG projection converges");
        });
        line += &format!(", CG with {name} {:.0} µs ({iterations} iterations)", t * 1e6);
    }
    println!("{line}");
}

/// Faces → centres → faces at 16²: the largest error of the spectral
/// half-cell shift and of linear averages, for one mode at a time and for
/// a field of random values.
fn round_trips() {
    let n = 16;
    let h = 2.0 * PI / n as f64;
    let flow = Periodic::new([n, n], h, 0.0, Scheme::SemiLagrangian);
    // Linear: each centre the mean of its two faces along the component's
    // axis, each face the mean of its two centres.
    let linear = |vel: &[f64]| -> Vec<f64> {
        let (u, v) = vel.split_at(n * (n + 1));
        let mut cu = vec![0.0; n * n];
        let mut cv = vec![0.0; n * n];
        for j in 0..n {
            for i in 0..n {
                cu[j * n + i] = 0.5 * (u[j * (n + 1) + i] + u[j * (n + 1) + i + 1]);
                cv[j * n + i] = 0.5 * (v[j * n + i] + v[(j + 1) * n + i]);
            }
        }
        let mut out = vec![0.0; vel.len()];
        let (ou, ov) = out.split_at_mut(n * (n + 1));
        for j in 0..n {
            for i in 0..=n {
                ou[j * (n + 1) + i] = 0.5 * (cu[j * n + (i + n - 1) % n] + cu[j * n + i % n]);
            }
        }
        for j in 0..=n {
            for i in 0..n {
                ov[j * n + i] = 0.5 * (cv[((j + n - 1) % n) * n + i] + cv[(j % n) * n + i]);
            }
        }
        out
    };
    println!("Faces -> centres -> faces at 16², largest error relative to the field's largest value:");
    println!("| field | spectral half-cell shift | linear averages |");
    println!("|---|---|---|");
    let mut fields: Vec<(String, Vec<f64>)> =
        [1usize, 4, 7].iter().map(|&k| (format!("mode {k}"), on_faces([n, n], h, |a, [x, y]| (k as f64 * (x + y) + a as f64).sin()))).collect();
    // Values of no pattern, the same on a face and its periodic copy: a
    // function of the position in half cells, wrapped.
    let noise = on_faces([n, n], h, |a, [x, y]| {
        let (i, j) = (((x / h * 2.0).round() as usize) % (2 * n), ((y / h * 2.0).round() as usize) % (2 * n));
        (((i * 2 * n + j) * 3 + a) as f64 * 0.618_033_988_7).fract() - 0.5
    });
    fields.push(("random values".into(), noise));
    for (name, vel) in fields {
        let peak = vel.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let spectral = max_diff(&flow.centres_to_faces(&flow.faces_to_centres(&vel)), &vel) / peak;
        let lin = max_diff(&linear(&vel), &vel) / peak;
        println!("| {name} | {spectral:.1e} | {lin:.1e} |");
    }
}

//! The periodic Navier–Stokes step of `diffsim_solvers::mac::periodic`:
//! the 2D Taylor–Green vortex against its exact decay (errors and observed
//! orders), and the time of one step. The figures of docs/navier-stokes.md:
//!
//! ```sh
//! cargo run --release -p diffsim-solvers --example periodic_flow
//! ```

use std::f64::consts::PI;
use std::time::Instant;

use diffsim_solvers::mac::periodic::Periodic;
use diffsim_solvers::smoke::Scheme;

/// `u = sin x cos y·f`, `v = −cos x sin y·f` on the faces of `n²` cells of `[0, 2π]²`.
fn taylor_green(n: usize, f: f64) -> Vec<Vec<f64>> {
    let h = 2.0 * PI / n as f64;
    let u = (0..n * (n + 1)).map(|c| ((c % (n + 1)) as f64 * h).sin() * (((c / (n + 1)) as f64 + 0.5) * h).cos() * f);
    let v = (0..(n + 1) * n).map(|c| -(((c % n) as f64 + 0.5) * h).cos() * ((c / n) as f64 * h).sin() * f);
    vec![u.collect(), v.collect()]
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

fn main() {
    let (nu, t) = (0.05, 1.0);
    println!("2D Taylor-Green vortex on [0, 2pi]^2, nu = {nu}, t = {t}, time step 0.5 h: largest error on the faces");
    println!("| scheme | 16² | 32² | 64² | 128² | observed orders |");
    println!("|---|---|---|---|---|---|");
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        let errors: Vec<f64> = [16, 32, 64, 128]
            .iter()
            .map(|&n| {
                let flow = Periodic { n: [n, n], h: 2.0 * PI / n as f64, viscosity: nu, scheme };
                let mut work = flow.work();
                let mut vel = taylor_green(n, 1.0).concat();
                let steps = (t / (0.5 * flow.h)).ceil() as usize;
                for _ in 0..steps {
                    flow.step(t / steps as f64, &mut vel, &mut work);
                }
                let exact = taylor_green(n, (-2.0 * nu * t).exp()).concat();
                vel.iter().zip(&exact).fold(0.0f64, |m, (a, b)| m.max((a - b).abs()))
            })
            .collect();
        let orders: Vec<String> = errors.windows(2).map(|w| format!("{:.2}", (w[0] / w[1]).log2())).collect();
        let cells: Vec<String> = errors.iter().map(|e| format!("{e:.2e}")).collect();
        println!("| {scheme:?} | {} | {} |", cells.join(" | "), orders.join(", "));
    }
    println!();
    println!("One step (Courant 0.5, one sub-step), best of 20:");
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        for n in [64usize, 128] {
            let flow = Periodic { n: [n, n], h: 2.0 * PI / n as f64, viscosity: 0.01, scheme };
            let (mut work, mut vel) = (flow.work(), taylor_green(n, 1.0).concat());
            let best = best_of(20, || {
                flow.step(0.5 * flow.h, &mut vel, &mut work);
            });
            println!("  2D {n}² {scheme:?}: {:.0} µs", best * 1e6);
        }
        let n = 32;
        let flow = Periodic { n: [n, n, n], h: 2.0 * PI / n as f64, viscosity: 0.01, scheme };
        let mut work = flow.work();
        let mut vel: Vec<f64> = (0..flow.n_vel()).map(|k| ((k as f64) * 0.618).fract() - 0.5).collect();
        let best = best_of(5, || {
            flow.step(0.5 * flow.h, &mut vel, &mut work);
        });
        println!("  3D {n}³ {scheme:?}: {:.0} µs", best * 1e6);
    }
}

//! Exact solutions to measure the schemes against: viscous Burgers by the
//! Cole–Hopf transform, the Taylor–Green vortex, the
//! Arnold–Beltrami–Childress flow, Fourier modes of the heat equation and
//! translation by constant advection.
//!
//! All are plain functions of position and time; sampling them on a grid
//! (cell centres, MAC faces) is the caller's business.

use std::f64::consts::PI;

/// Viscous Burgers `u_t + u·u_x = ν·u_xx` on the real line (so on any
/// period) from `u(x, 0) = sin(x)`, exact through the Cole–Hopf transform
/// `u = −2ν·φ_x/φ` with `φ` solving the heat equation:
///
/// ```text
/// u(x, t) = ∫ ((x − ξ)/t)·e^{−G/(2ν)} dξ / ∫ e^{−G/(2ν)} dξ,
/// G(ξ) = (1 − cos ξ) + (x − ξ)²/(2t)
/// ```
///
/// (`1 − cos ξ = ∫₀^ξ sin`). Both integrals are evaluated by the
/// trapezoidal rule on `x ± R` with `R` where the Gaussian factor has fallen
/// below `e^{−40}`, with the weights shifted by the smallest `G` (no
/// overflow for small ν, no cancellation: every weight is positive). The
/// integrand is smooth and negligible at the ends, so the rule converges
/// spectrally; `points` = 4000 agrees with the Fourier-series solution to
/// 1e-10 (tests, ν = 0.1, t ≤ 2).
#[derive(Clone, Copy, Debug)]
pub struct ColeHopf {
    /// Viscosity ν > 0.
    pub nu: f64,
    /// Quadrature points per evaluation.
    pub points: usize,
}

impl ColeHopf {
    /// The solution for viscosity `nu` with 4000 quadrature points.
    pub fn new(nu: f64) -> Self {
        Self { nu, points: 4000 }
    }

    /// `u(x, t)`; `sin(x)` at `t = 0`.
    pub fn at(&self, x: f64, t: f64) -> f64 {
        if t <= 0.0 {
            return x.sin();
        }
        let nu = self.nu;
        // (x − ξ)²/(2t)/(2ν) ≥ 40 beyond R.
        let r = (160.0 * nu * t).sqrt();
        let m = self.points;
        let h = 2.0 * r / m as f64;
        let g = |xi: f64| (1.0 - xi.cos()) + (x - xi) * (x - xi) / (2.0 * t);
        let gmin = (0..=m).map(|k| g(x - r + k as f64 * h)).fold(f64::INFINITY, f64::min);
        let (mut num, mut den) = (0.0, 0.0);
        for k in 0..=m {
            let xi = x - r + k as f64 * h;
            let w = if k == 0 || k == m { 0.5 } else { 1.0 } * (-(g(xi) - gmin) / (2.0 * nu)).exp();
            num += w * (x - xi) / t;
            den += w;
        }
        num / den
    }

    /// `u(x_i, t)` at the cells `x_i = i·2π/n` of a periodic grid of `n`.
    pub fn on_grid(&self, n: usize, t: f64) -> Vec<f64> {
        (0..n).map(|i| self.at(2.0 * PI * i as f64 / n as f64, t)).collect()
    }
}

/// The 2D Taylor–Green vortex on the periodic square `[0, L)²`, `k = 2π/L`:
///
/// ```text
/// u =  A·sin(k·x)·cos(k·y)·e^{−2νk²t}
/// v = −A·cos(k·x)·sin(k·y)·e^{−2νk²t}
/// ```
///
/// an exact solution of the incompressible Navier–Stokes equations (the
/// advection is balanced by the pressure `p = (A²/4)(cos 2kx + cos 2ky)·e^{−4νk²t}`, density 1);
/// steady for ν = 0.
#[derive(Clone, Copy, Debug)]
pub struct TaylorGreen {
    /// Side `L` of the periodic square.
    pub length: f64,
    /// Amplitude `A`.
    pub amplitude: f64,
    /// Viscosity ν.
    pub nu: f64,
}

impl TaylorGreen {
    /// The velocity `(u, v)` at `(x, y)` and time `t`.
    pub fn velocity(&self, x: f64, y: f64, t: f64) -> (f64, f64) {
        let k = 2.0 * PI / self.length;
        let a = self.amplitude * (-2.0 * self.nu * k * k * t).exp();
        (a * (k * x).sin() * (k * y).cos(), -a * (k * x).cos() * (k * y).sin())
    }

    /// The MAC velocity of an `n × n` periodic grid (cell width `h = L/n`) at
    /// time `t`, in the smoke solver's layout and units (cells per unit
    /// time, so divided by `h`): `u` at the x-faces `(i·h, (j+½)·h)`, `v` at
    /// the y-faces `((i+½)·h, j·h)`, face `n` the copy of face 0.
    pub fn mac(&self, n: usize, t: f64) -> (Vec<f64>, Vec<f64>) {
        let h = self.length / n as f64;
        let mut u = vec![0.0; n * (n + 1)];
        let mut v = vec![0.0; n * (n + 1)];
        for j in 0..n {
            for i in 0..=n {
                u[j * (n + 1) + i] = self.velocity(i as f64 * h, (j as f64 + 0.5) * h, t).0 / h;
            }
        }
        for j in 0..=n {
            for i in 0..n {
                v[j * n + i] = self.velocity((i as f64 + 0.5) * h, j as f64 * h, t).1 / h;
            }
        }
        (u, v)
    }
}

/// The Arnold–Beltrami–Childress flow on the periodic cube `[0, 2π)³`,
///
/// ```text
/// u = (A·sin z + C·cos y,  B·sin x + A·cos z,  C·sin y + B·cos x)·e^{−νt}
/// ```
///
/// a Beltrami field (its vorticity is itself, so `(u·∇)u = ∇|u|²/2`, which
/// the pressure balances) and an eigenfunction of the Laplacian
/// (`Δu = −u`): an exact solution of the 3D incompressible Navier–Stokes
/// equations that decays as `e^{−νt}` (steady under the forcing `ν·u₀`).
#[derive(Clone, Copy, Debug)]
pub struct Abc {
    /// The coefficients `A`, `B`, `C`.
    pub coefficients: [f64; 3],
    /// Viscosity ν.
    pub nu: f64,
}

impl Abc {
    /// The velocity at `p` and time `t`.
    pub fn velocity(&self, p: [f64; 3], t: f64) -> [f64; 3] {
        let ([a, b, c], f) = (self.coefficients, (-self.nu * t).exp());
        let [x, y, z] = p;
        [f * (a * z.sin() + c * y.cos()), f * (b * x.sin() + a * z.cos()), f * (c * y.sin() + b * x.cos())]
    }
}

/// A velocity field `f(axis, point)` sampled on the faces of a periodic
/// box of `n` cells of size `h` (in its own units, not divided by `h`):
/// the packed MAC layout of `mac::periodic::Periodic` (component `a` at the
/// faces normal to axis `a`, `x` fastest, face `n` along `a` the copy of
/// face 0).
pub fn on_faces<const D: usize>(n: [usize; D], h: f64, f: impl Fn(usize, [f64; D]) -> f64) -> Vec<f64> {
    let mut out = Vec::new();
    for axis in 0..D {
        let len = |b: usize| n[b] + usize::from(b == axis);
        let total: usize = (0..D).map(len).product();
        for c in 0..total {
            let mut p = [0.0; D];
            let mut rest = c;
            for (b, x) in p.iter_mut().enumerate() {
                let q = (rest % len(b)) as f64;
                rest /= len(b);
                *x = (q + if b == axis { 0.0 } else { 0.5 }) * h;
            }
            out.push(f(axis, p));
        }
    }
    out
}

/// A Fourier mode of the heat equation `s_t = ν·Δs` on the periodic square
/// `[0, L)²`: `s = sin(a·k·x + φ)·cos(b·k·y)·e^{−ν(a² + b²)k²t}`, `k = 2π/L`.
#[derive(Clone, Copy, Debug)]
pub struct HeatMode {
    /// Side `L`.
    pub length: f64,
    /// Wave numbers `(a, b)` in units of `k`.
    pub modes: (f64, f64),
    /// Phase φ along x.
    pub phase: f64,
    /// Diffusivity ν.
    pub nu: f64,
}

impl HeatMode {
    /// `s(x, y, t)`.
    pub fn at(&self, x: f64, y: f64, t: f64) -> f64 {
        let k = 2.0 * PI / self.length;
        let (a, b) = self.modes;
        (a * k * x + self.phase).sin() * (b * k * y).cos() * (-self.nu * (a * a + b * b) * k * k * t).exp()
    }

    /// Sampled at the cell centres `((i+½)·h, (j+½)·h)` of an `n × n` grid,
    /// index `j·n + i`.
    pub fn cells(&self, n: usize, t: f64) -> Vec<f64> {
        cells(n, self.length, |x, y| self.at(x, y, t))
    }
}

/// Translation by a constant velocity `c`: `s(x, t) = s₀(x − c·t)` for the
/// smooth periodic profile `s₀(x, y) = exp(sin(k·x))·cos(k·y)`, `k = 2π/L`.
#[derive(Clone, Copy, Debug)]
pub struct Translation {
    /// Side `L` of the periodic square.
    pub length: f64,
    /// Velocity `(c_x, c_y)` in length per unit time.
    pub velocity: (f64, f64),
}

impl Translation {
    /// `s(x, y, t)`.
    pub fn at(&self, x: f64, y: f64, t: f64) -> f64 {
        let k = 2.0 * PI / self.length;
        let (x0, y0) = (x - self.velocity.0 * t, y - self.velocity.1 * t);
        (k * x0).sin().exp() * (k * y0).cos()
    }

    /// Sampled at the cell centres of an `n × n` grid, index `j·n + i`.
    pub fn cells(&self, n: usize, t: f64) -> Vec<f64> {
        cells(n, self.length, |x, y| self.at(x, y, t))
    }
}

fn cells(n: usize, length: f64, f: impl Fn(f64, f64) -> f64) -> Vec<f64> {
    let h = length / n as f64;
    let mut s = vec![0.0; n * n];
    for j in 0..n {
        for i in 0..n {
            s[j * n + i] = f((i as f64 + 0.5) * h, (j as f64 + 0.5) * h);
        }
    }
    s
}

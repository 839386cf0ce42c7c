//! The heat equation `∂u/∂t = ν·∇²u` on a periodic 2D grid, solved exactly
//! in Fourier space, and its damped inverse (rustfft, behind plain
//! non-generic functions).
//!
//! Values are stored row by row, `u[j·nx + i]` (row `j` along y, column `i`
//! along x), cell size `dx` on both axes. The wavenumbers are those of
//! numpy's `fftfreq(n, dx)` times 2π, as in PhiFlow's `diffuse.fourier`.
//!
//! Diffusing to `ν·t` multiplies mode `k` by `f(k) = exp(−ν·t·|k|²)`. The
//! exact inverse `1/f` amplifies high modes beyond any precision, so
//! [`heat_inverse`] uses the Tikhonov (Wiener) filter `f/(f² + ε²)`: modes
//! with `f ≫ ε` are inverted, modes with `f ≪ ε` are left out, and no mode
//! is amplified by more than `1/(2ε)`.

use rustfft::FftPlanner;
use rustfft::num_complex::Complex;

/// A periodic grid and the amount of diffusion `ν·t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Heat2d {
    /// Cells along x.
    pub nx: usize,
    /// Cells along y.
    pub ny: usize,
    /// Cell size (both axes).
    pub dx: f64,
    /// Viscosity times time.
    pub nu_t: f64,
}

/// `2π·fftfreq(n, dx)[m]`.
fn wavenumber(m: usize, n: usize, dx: f64) -> f64 {
    let signed = if 2 * m < n { m as f64 } else { m as f64 - n as f64 };
    2.0 * std::f64::consts::PI * signed / (n as f64 * dx)
}

impl Heat2d {
    /// The factor `exp(−ν·t·|k|²)` of each mode, `[j·nx + i]`.
    pub fn decay(&self) -> Vec<f64> {
        let mut f = Vec::with_capacity(self.nx * self.ny);
        for j in 0..self.ny {
            let ky = wavenumber(j, self.ny, self.dx);
            for i in 0..self.nx {
                let kx = wavenumber(i, self.nx, self.dx);
                f.push((-self.nu_t * (kx * kx + ky * ky)).exp());
            }
        }
        f
    }

    /// The damped inverse factors `f/(f² + ε²)` of each mode.
    pub fn inverse_factors(&self, epsilon: f64) -> Vec<f64> {
        self.decay().into_iter().map(|f| f / (f * f + epsilon * epsilon)).collect()
    }
}

/// `y = F⁻¹(m ⊙ F(x))` for a real multiplier `m` that is even in each
/// wavenumber (so the result is real), on an `nx × ny` grid.
///
/// # Panics
/// If a slice does not hold `nx·ny` values.
pub fn spectral_multiply(nx: usize, ny: usize, multiplier: &[f64], x: &[f64], y: &mut [f64]) {
    let n = nx * ny;
    assert!(multiplier.len() == n && x.len() == n && y.len() == n, "spectral_multiply: slices must hold nx·ny values");
    let mut planner = FftPlanner::<f64>::new();
    let (fx, ifx) = (planner.plan_fft_forward(nx), planner.plan_fft_inverse(nx));
    let (fy, ify) = (planner.plan_fft_forward(ny), planner.plan_fft_inverse(ny));
    let mut rows: Vec<Complex<f64>> = x.iter().map(|&v| Complex::new(v, 0.0)).collect();
    fx.process(&mut rows); // every row along x
    let mut cols = transpose(nx, ny, &rows); // [i·ny + j]
    fy.process(&mut cols);
    for i in 0..nx {
        for j in 0..ny {
            cols[i * ny + j] *= multiplier[j * nx + i];
        }
    }
    ify.process(&mut cols);
    let mut rows = transpose(ny, nx, &cols);
    ifx.process(&mut rows);
    let scale = 1.0 / n as f64;
    for (out, c) in y.iter_mut().zip(&rows) {
        *out = c.re * scale;
    }
}

/// The transpose of the row-major `rows × cols` matrix `a`:
/// `a[r·cols + c]` → `out[c·rows + r]`.
fn transpose(cols: usize, rows: usize, a: &[Complex<f64>]) -> Vec<Complex<f64>> {
    let mut out = vec![Complex::new(0.0, 0.0); a.len()];
    for r in 0..rows {
        for c in 0..cols {
            out[c * rows + r] = a[r * cols + c];
        }
    }
    out
}

/// Diffuses `x` by `ν·t` exactly: `y = F⁻¹(exp(−ν·t·|k|²) ⊙ F(x))`. The map
/// is linear and symmetric, so it is its own adjoint.
pub fn heat(h: &Heat2d, x: &[f64], y: &mut [f64]) {
    spectral_multiply(h.nx, h.ny, &h.decay(), x, y);
}

/// The damped inverse of [`heat`]: `x = F⁻¹(f/(f² + ε²) ⊙ F(y))`.
pub fn heat_inverse(h: &Heat2d, epsilon: f64, y: &[f64], x: &mut [f64]) {
    spectral_multiply(h.nx, h.ny, &h.inverse_factors(epsilon), y, x);
}

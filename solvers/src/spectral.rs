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
//! is amplified by more than `1/(2ε)`. [`heat_inverse_bayesian`] is the
//! published alternative (Holl, Koltun & Thuerey, NeurIPS 2022, code
//! tum-pbs/SIP `heat/inv_diffuse.py`): per mode, the probability that its
//! amplitude is signal rather than noise decides how far it is inverted.

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
    let spectrum = forward(&mut planner, nx, ny, x);
    multiply_back(&mut planner, nx, ny, spectrum, multiplier, y);
}

/// The unnormalised 2D DFT of a real `nx × ny` field, column by column:
/// mode `(i, j)` (along x, along y) at `[i·ny + j]`.
fn forward(planner: &mut FftPlanner<f64>, nx: usize, ny: usize, x: &[f64]) -> Vec<Complex<f64>> {
    let mut rows: Vec<Complex<f64>> = x.iter().map(|&v| Complex::new(v, 0.0)).collect();
    planner.plan_fft_forward(nx).process(&mut rows); // every row along x
    let mut cols = transpose(nx, ny, &rows); // [i·ny + j]
    planner.plan_fft_forward(ny).process(&mut cols);
    cols
}

/// `y = F⁻¹(m ⊙ spectrum)` for a [`forward`] spectrum and a multiplier
/// `[j·nx + i]`; the real part.
fn multiply_back(planner: &mut FftPlanner<f64>, nx: usize, ny: usize, mut cols: Vec<Complex<f64>>, multiplier: &[f64], y: &mut [f64]) {
    for i in 0..nx {
        for j in 0..ny {
            cols[i * ny + j] *= multiplier[j * nx + i];
        }
    }
    planner.plan_fft_inverse(ny).process(&mut cols);
    let mut rows = transpose(ny, nx, &cols);
    planner.plan_fft_inverse(nx).process(&mut rows);
    let scale = 1.0 / (nx * ny) as f64;
    for (out, c) in y.iter_mut().zip(&rows) {
        *out = c.re * scale;
    }
}

/// The settings of [`heat_inverse_bayesian`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BayesianInverse {
    /// Prior probability that a mode carries signal (published: 0.5).
    pub signal_prior: f64,
    /// The noise level per cell relative to `|y|` (published: 1e-6, the
    /// uncertainty `1e-6·|y − y*|` of the physics step's target).
    pub noise: f64,
}

impl BayesianInverse {
    /// The published settings: signal prior 0.5, noise 1e-6.
    pub const PUBLISHED: Self = Self { signal_prior: 0.5, noise: 1e-6 };

    /// The multiplier of each mode `[j·nx + i]` for the amplitudes
    /// `amp(i, j)` of mode `(i, j)` (along x, along y; of the unnormalised
    /// DFT of the input, as numpy's `fft`).
    ///
    /// With `g = ν·t·|k|²` (so diffusion multiplies by `e^{−g}`), the
    /// expected signal amplitude `nx·e^{−g}` and the noise amplitude
    /// `σ = noise·‖y‖₂`: `P(signal) = L_s/(L_s + L_n)` with
    /// `L_s = prior·exp(−½(|amp|/(nx·e^{−g}))²)` and
    /// `L_n = (1 − prior)·exp(−½(|amp|/σ)²)`; the action `a = 2(P − ½)` where
    /// `P ≤ ½` or `P ≥ 0.68` (one sigma), else 0; the multiplier `e^{a·g}`
    /// (the exact inverse for `a = 1`, more diffusion for `a < 0`), its
    /// exponent capped at `⌊ln f32::MAX⌋ = 88` as published.
    pub fn multipliers(&self, h: &Heat2d, amp: impl Fn(usize, usize) -> f64, y_norm: f64) -> Vec<f64> {
        let sigma = self.noise * y_norm;
        let cap = f64::from(f32::MAX).ln().floor();
        let mut out = Vec::with_capacity(h.nx * h.ny);
        for j in 0..h.ny {
            let ky = wavenumber(j, h.ny, h.dx);
            for i in 0..h.nx {
                let kx = wavenumber(i, h.nx, h.dx);
                let g = h.nu_t * (kx * kx + ky * ky);
                let a = amp(i, j);
                let expected = h.nx as f64 * (-g).exp();
                let mut ls = (-0.5 * (a / expected).powi(2)).exp() * self.signal_prior;
                if !ls.is_finite() {
                    ls = 0.0;
                }
                let ln = (-0.5 * (a / sigma).powi(2)).exp() * (1.0 - self.signal_prior);
                let p = if ls + ln > 0.0 { ls / (ls + ln) } else { 0.0 };
                let action = if p <= 0.5 || p >= 0.68 { 2.0 * (p - 0.5) } else { 0.0 };
                // The published code caps g only in its unused raw kernel;
                // the applied one is exp(g·a), capped here so that no
                // mode overflows.
                out.push((g * action).min(cap).exp());
            }
        }
        out
    }
}

/// The published Bayesian damped inverse of [`heat`] applied to `y` (the
/// physics step's target change `y* − P(x)`): each mode multiplied by
/// [`BayesianInverse::multipliers`], with the noise scaled by `‖y‖₂`.
///
/// # Panics
/// If a slice does not hold `nx·ny` values.
pub fn heat_inverse_bayesian(h: &Heat2d, settings: &BayesianInverse, y: &[f64], x: &mut [f64]) {
    let (nx, ny) = (h.nx, h.ny);
    assert!(y.len() == nx * ny && x.len() == nx * ny, "heat_inverse_bayesian: slices must hold nx·ny values");
    let mut planner = FftPlanner::<f64>::new();
    let spectrum = forward(&mut planner, nx, ny, y);
    let norm = y.iter().map(|v| v * v).sum::<f64>().sqrt();
    let m = settings.multipliers(h, |i, j| spectrum[i * ny + j].norm(), norm);
    multiply_back(&mut planner, nx, ny, spectrum, &m, x);
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

#[cfg(test)]
mod tests {
    use super::*;

    /// One Fourier mode decays by exactly `exp(−ν·t·|k|²)`, and the damped
    /// inverse undoes it to the damping's order.
    #[test]
    fn a_fourier_mode_decays_by_its_factor_and_the_inverse_restores_it() {
        let h = Heat2d { nx: 16, ny: 8, dx: 0.5, nu_t: 0.3 };
        let (kx, ky) = (2.0 * std::f64::consts::PI * 3.0 / 8.0, 2.0 * std::f64::consts::PI * 1.0 / 4.0);
        let mode: Vec<f64> = (0..8 * 16).map(|c| (kx * (c % 16) as f64 * 0.5 + ky * (c / 16) as f64 * 0.5).cos()).collect();
        let mut y = vec![0.0; mode.len()];
        heat(&h, &mode, &mut y);
        let f = (-0.3 * (kx * kx + ky * ky)).exp();
        for (a, b) in y.iter().zip(&mode) {
            assert!((a - f * b).abs() < 1e-12, "{a} vs {}", f * b);
        }
        let mut x = vec![0.0; mode.len()];
        heat_inverse(&h, 1e-6, &y, &mut x);
        for (a, b) in x.iter().zip(&mode) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
    }
}

//! Benchmark P4 `smoke3d`: initial state, target and reference values (the loss is
//! `diffsim::problems::half_squared_error`, shared with P2)
//! (`docs/benchmarks.md`).

use super::*;

/// P4's initial state: zero velocity, smoke 1 in every cell whose centre
/// lies within `N/8` of `(N/2, N/4, N/2)`, packed as `[s, u, v, w]`.
pub fn p4_initial(cfg: &MacGrid<3>) -> Vec<f64> {
    let mut x = vec![0.0; cfg.n_state()];
    x[..cfg.n_s()].copy_from_slice(&ball(cfg.n[0], 0.25));
    x
}

/// P4's target smoke: the same ball centred at `(N/2, 3N/4, N/2)`.
pub fn p4_target(cfg: &MacGrid<3>) -> Vec<f64> {
    ball(cfg.n[0], 0.75)
}

fn ball(n: usize, cy: f64) -> Vec<f64> {
    let nf = n as f64;
    let r2 = (nf / 8.0) * (nf / 8.0);
    let mut s = vec![0.0; n * n * n];
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                let (dx, dy, dz) = (i as f64 + 0.5 - nf / 2.0, j as f64 + 0.5 - cy * nf, k as f64 + 0.5 - nf / 2.0);
                if dx * dx + dy * dy + dz * dz <= r2 {
                    s[(k * n + j) * n + i] = 1.0;
                }
            }
        }
    }
    s
}

/// The flat index of P4's `grad_mid`: the cell `(N/2, N/2, N/2)`.
pub fn p4_mid(n: usize) -> usize {
    (n / 2 * n + n / 2) * n + n / 2
}

/// Reference values of one P4 size (JAX, float64; `docs/benchmarks.md`).
#[derive(Clone, Copy, Debug)]
pub struct P4Reference {
    /// Cells per side.
    pub n: usize,
    /// Steps.
    pub steps: usize,
    /// Loss.
    pub loss: f64,
    /// ‖∇L‖₂.
    pub grad_l2: f64,
    /// ∂L/∂s at flat index 0.
    pub grad_0: f64,
    /// ∂L/∂s at [`p4_mid`].
    pub grad_mid: f64,
}

/// The two P4 sizes with their reference values.
pub const P4_SIZES: [P4Reference; 2] = [
    P4Reference { n: 32, steps: 10, loss: 232.5030476211, grad_l2: 20.162716923, grad_0: 3.75734486e-05, grad_mid: 3.80726477e-02 },
    P4Reference { n: 48, steps: 10, loss: 806.6299262654, grad_l2: 38.391392528, grad_0: 1.44703611e-05, grad_mid: 1.53380722e-02 },
];

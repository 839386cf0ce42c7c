//! Benchmark P2 `smoke2d`: initial state, target and reference values (the loss is
//! `diffsim::problems::half_squared_error`, shared with P4)
//! (`docs/benchmarks.md`).

use super::*;

/// P2's initial state: zero velocity, smoke 1 in every cell whose centre lies
/// within `N/8` of `(N/2, N/4)`, packed as `[s, u, v]`.
pub fn p2_initial(cfg: &MacGrid<2>) -> Vec<f64> {
    let mut x = vec![0.0; cfg.n_state()];
    x[..cfg.n_s()].copy_from_slice(&disc(cfg.n[0], 0.25));
    x
}

/// P2's target smoke: the same disc centred at `(N/2, 3N/4)`.
pub fn p2_target(cfg: &MacGrid<2>) -> Vec<f64> {
    disc(cfg.n[0], 0.75)
}

fn disc(n: usize, cy: f64) -> Vec<f64> {
    let nf = n as f64;
    let mut s = vec![0.0; n * n];
    for j in 0..n {
        for i in 0..n {
            let (dx, dy) = (i as f64 + 0.5 - nf / 2.0, j as f64 + 0.5 - cy * nf);
            if dx * dx + dy * dy <= (nf / 8.0) * (nf / 8.0) {
                s[j * n + i] = 1.0;
            }
        }
    }
    s
}

/// Reference values of one P2 size (JAX, float64; `docs/benchmarks.md`).
#[derive(Clone, Copy, Debug)]
pub struct P2Reference {
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
    /// ∂L/∂s at flat index N²/2.
    pub grad_n2: f64,
}

/// The two P2 sizes with their reference values.
pub const P2_SIZES: [P2Reference; 2] = [
    P2Reference { n: 64, steps: 20, loss: 183.8917448743, grad_l2: 18.18088488397, grad_0: 1.37382956e-4, grad_n2: -3.78117637e-3 },
    P2Reference { n: 128, steps: 20, loss: 768.1330262886, grad_l2: 38.36607301311, grad_0: 1.88809603e-5, grad_n2: -1.54349595e-3 },
];

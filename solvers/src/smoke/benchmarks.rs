//! Benchmarks P2 `smoke2d` and P4 `smoke3d` (`docs/benchmarks.md`): one
//! set-up in any dimension (a closed box, a blob of smoke rising towards a
//! target blob), and the reference values of each (the loss is
//! `diffsim::problems::half_squared_error`).

use super::*;

/// The initial state of P2 (`D = 2`) and P4 (`D = 3`): zero velocity,
/// smoke 1 in every cell whose centre lies within `N/8` of `(N/2, N/4)`
/// (`(N/2, N/4, N/2)` in 3D), packed as `[s, u₀, …]`.
pub fn initial<const D: usize>(cfg: &MacGrid<D>) -> Vec<f64> {
    let mut x = vec![0.0; cfg.n_state()];
    x[..cfg.n_s()].copy_from_slice(&blob::<D>(cfg.n[0], 0.25));
    x
}

/// The target smoke of P2 and P4: the same blob centred at height `3N/4`.
pub fn target<const D: usize>(cfg: &MacGrid<D>) -> Vec<f64> {
    blob::<D>(cfg.n[0], 0.75)
}

/// Smoke 1 in the cells of an `N`-cube whose centre lies within `N/8` of
/// the point at height `cy·N` in the middle of the other axes.
fn blob<const D: usize>(n: usize, cy: f64) -> Vec<f64> {
    let nf = n as f64;
    let r2 = (nf / 8.0) * (nf / 8.0);
    let cells = Mac::bounded([n; D]).lattice(At::Centre);
    let mut s = vec![0.0; cells.len];
    for q in cells.points() {
        let mut d2 = 0.0;
        for (a, &k) in q.iter().enumerate() {
            let c = if a == 1 { cy * nf } else { nf / 2.0 };
            let d = k as f64 + 0.5 - c;
            d2 += d * d;
        }
        if d2 <= r2 {
            s[cells.index(q)] = 1.0;
        }
    }
    s
}

/// Reference values of one size of P2 or P4 (JAX, float64;
/// `docs/benchmarks.md`).
#[derive(Clone, Copy, Debug)]
pub struct Reference {
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
    /// ∂L/∂s at the problem's probe cell ([`probe`]).
    pub grad_probe: f64,
}

/// The probe cell of P2 (`D = 2`: flat index `N²/2`, the reference's
/// `grad_n2`) and P4 (`D = 3`: the middle cell `(N/2, N/2, N/2)`, its
/// `grad_mid`).
pub const fn probe<const D: usize>(n: usize) -> usize {
    if D == 2 { n * n / 2 } else { (n / 2 * n + n / 2) * n + n / 2 }
}

/// The two P2 sizes with their reference values.
pub const P2_SIZES: [Reference; 2] = [
    Reference { n: 64, steps: 20, loss: 183.8917448743, grad_l2: 18.18088488397, grad_0: 1.37382956e-4, grad_probe: -3.78117637e-3 },
    Reference { n: 128, steps: 20, loss: 768.1330262886, grad_l2: 38.36607301311, grad_0: 1.88809603e-5, grad_probe: -1.54349595e-3 },
];

/// The two P4 sizes with their reference values.
pub const P4_SIZES: [Reference; 2] = [
    Reference { n: 32, steps: 10, loss: 232.5030476211, grad_l2: 20.162716923, grad_0: 3.75734486e-05, grad_probe: 3.80726477e-02 },
    Reference { n: 48, steps: 10, loss: 806.6299262654, grad_l2: 38.391392528, grad_0: 1.44703611e-05, grad_probe: 1.53380722e-02 },
];

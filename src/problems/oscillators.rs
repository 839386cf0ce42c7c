//! Two coupled oscillators with a control on the last one, integrated by
//! RK4 (the half-inverse-gradients problem of Schnell, Holl & Thuerey, ICLR
//! 2022, and the Physics-based Deep Learning book).
//!
//! State `s = (x₁, x₂, v₁, v₂)`:
//!
//! ```text
//! ẋᵢ = vᵢ
//! v̇₁ = −x₁ + c·(x₂ − x₁) − κ·(x₁ − x₂)³
//! v̇₂ = −x₂ + c·(x₁ − x₂) + κ·(x₁ − x₂)³ + a·u(t)
//! ```
//!
//! with `u` constant over each of the `steps` RK4 steps of `dt`. The
//! operator maps the initial state `x` (4 values) and the controls `p`
//! (`steps` values) to the final state. Linear problem: `c = 0.2`, `κ = 0`,
//! `a = 1`, 24 steps of 0.5; nonlinear: `c = 0`, `κ = 1` (the cubic force of
//! the quartic coupling energy), `a = 3`, 96 steps of 0.125 (the published
//! code's `Nonlinear_oscillators/ODEs_batch.py`). Derivatives by Enzyme
//! through nalgebra's fixed-size vectors.

use nalgebra::Vector4;

use crate::op::{LANES, Operator};

/// The oscillator rollout as one operator: `(x₀, u) ↦ s_T`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Oscillators {
    /// RK4 steps (= controls).
    pub steps: usize,
    /// Time step.
    pub dt: f64,
    /// Linear coupling `c`.
    pub linear: f64,
    /// Cubic coupling `κ`.
    pub cubic: f64,
    /// The control's coefficient `a` on the last oscillator.
    pub control: f64,
}

impl Oscillators {
    /// The linear problem: coupling 0.2, control coefficient 1, 24 steps of 0.5.
    pub fn linear() -> Self {
        Self { steps: 24, dt: 0.5, linear: 0.2, cubic: 0.0, control: 1.0 }
    }

    /// The nonlinear problem: cubic coupling 1.0, control coefficient 3, 96
    /// steps of 0.125.
    pub fn nonlinear() -> Self {
        Self { steps: 96, dt: 0.125, linear: 0.0, cubic: 1.0, control: 3.0 }
    }
}

impl Operator for Oscillators {
    fn n_in(&self) -> usize {
        4
    }
    fn n_out(&self) -> usize {
        4
    }
    fn n_params(&self) -> usize {
        self.steps
    }
}

#[inline(always)]
fn rhs(op: &Oscillators, s: &Vector4<f64>, u: f64) -> Vector4<f64> {
    let d = s[0] - s[1];
    let f = op.cubic * d * d * d;
    Vector4::new(s[2], s[3], -s[0] - op.linear * d - f, -s[1] + op.linear * d + f + op.control * u)
}

#[inline(always)]
fn rk4(op: &Oscillators, s: &Vector4<f64>, u: f64) -> Vector4<f64> {
    let h = op.dt;
    let k1 = rhs(op, s, u);
    let k2 = rhs(op, &(s + k1 * (0.5 * h)), u);
    let k3 = rhs(op, &(s + k2 * (0.5 * h)), u);
    let k4 = rhs(op, &(s + k3 * h), u);
    s + (k1 + k2 * 2.0 + k3 * 2.0 + k4) * (h / 6.0)
}

/// The plain rollout: `y = s_T` from `x = s₀` under the controls `p`.
pub fn oscillate(op: &Oscillators, x: &[f64], p: &[f64], y: &mut [f64]) {
    let mut s = Vector4::new(x[0], x[1], x[2], x[3]);
    for &u in &p[..op.steps] {
        s = rk4(op, &s, u);
    }
    y[..4].copy_from_slice(s.as_slice());
}

/// [`oscillate`] on [`LANES`] samples side by side (value `c` of sample `l`
/// at `c·LANES + l`, control `k` at `k·LANES + l`): the same RK4 step per
/// lane, so each lane gets its sample's [`oscillate`] bit for bit; batches
/// of samples run through it ([`Forward::forward_each`](crate::op::Forward::forward_each),
/// [`Vjp::vjp_each`](crate::op::Vjp::vjp_each)).
// Slices, not `as_chunks`' arrays, inside the differentiated function.
#[allow(clippy::chunks_exact_to_as_chunks)]
pub fn oscillate_lanes(op: &Oscillators, x: &[f64], p: &[f64], y: &mut [f64]) {
    // The state lives in `y`: Enzyme cannot type the zero fill or the
    // copies of a local array of lanes (`Cannot deduce type of memset /
    // copy`).
    y[..4 * LANES].copy_from_slice(&x[..4 * LANES]);
    for u in p[..op.steps * LANES].chunks_exact(LANES) {
        for (l, &u) in u.iter().enumerate() {
            let s = Vector4::new(y[l], y[LANES + l], y[2 * LANES + l], y[3 * LANES + l]);
            let next = rk4(op, &s, u);
            for c in 0..4 {
                y[c * LANES + l] = next[c];
            }
        }
    }
}

crate::differentiable!(Oscillators => oscillate, lanes = oscillate_lanes);

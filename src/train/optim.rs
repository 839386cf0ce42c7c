//! Optimizers on a flat parameter vector: SGD (with optional momentum) and
//! Adam (Kingma & Ba 2015, published defaults), and gradient clipping by
//! norm. The state is plain data, saved with the parameters to resume.

use serde::{Deserialize, Serialize};

use crate::op::Real;

/// An optimizer and its state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Optimizer {
    /// `v ← μ·v + g`, `p ← p − η·v` (plain SGD for μ = 0).
    Sgd {
        /// Learning rate η.
        lr: f64,
        /// Momentum μ.
        momentum: f64,
        /// Velocity (empty until the first step).
        velocity: Vec<f64>,
    },
    /// Adam: `m ← β₁m + (1−β₁)g`, `v ← β₂v + (1−β₂)g²`,
    /// `p ← p − η·m̂/(√v̂ + ε)` with bias-corrected `m̂`, `v̂`.
    Adam {
        /// Learning rate η.
        lr: f64,
        /// β₁.
        beta1: f64,
        /// β₂.
        beta2: f64,
        /// ε.
        eps: f64,
        /// First moments.
        m: Vec<f64>,
        /// Second moments.
        v: Vec<f64>,
        /// Steps taken.
        t: u64,
    },
}

impl Optimizer {
    /// Plain SGD.
    pub fn sgd(lr: f64) -> Self {
        Optimizer::Sgd { lr, momentum: 0.0, velocity: Vec::new() }
    }

    /// Adam with the published defaults β = (0.9, 0.999), ε = 1e-8.
    pub fn adam(lr: f64) -> Self {
        Optimizer::Adam { lr, beta1: 0.9, beta2: 0.999, eps: 1e-8, m: Vec::new(), v: Vec::new(), t: 0 }
    }

    /// Every number of its state (rates, moments, step count), for
    /// comparing two optimizers' states exactly.
    pub fn state(&self) -> Vec<f64> {
        match self {
            Optimizer::Sgd { lr, momentum, velocity } => [*lr, *momentum].into_iter().chain(velocity.iter().copied()).collect(),
            Optimizer::Adam { lr, beta1, beta2, eps, m, v, t } => {
                [*lr, *beta1, *beta2, *eps, *t as f64].into_iter().chain(m.iter().copied()).chain(v.iter().copied()).collect()
            }
        }
    }

    /// `"adam"` or `"sgd"`, as in a training configuration.
    pub fn kind(&self) -> &'static str {
        match self {
            Optimizer::Sgd { .. } => "sgd",
            Optimizer::Adam { .. } => "adam",
        }
    }

    /// Checks saved state against `n` parameters: settings in range, state
    /// empty (no step yet) or of length `n`, every value finite, Adam's
    /// step count consistent with its moments. For state read from a file.
    pub fn validate(&self, n: usize) -> Result<(), String> {
        let finite = |name: &str, v: &[f64]| match v.iter().position(|x| !x.is_finite()) {
            Some(i) => Err(format!("{} state `{name}`[{i}] is not finite", self.kind())),
            None => Ok(()),
        };
        let length = |name: &str, v: &[f64]| {
            if v.is_empty() || v.len() == n { Ok(()) } else { Err(format!("{} state `{name}` has {} values for {n} parameters", self.kind(), v.len())) }
        };
        let lr = self.lr();
        if !(lr.is_finite() && lr >= 0.0) {
            return Err(format!("learning rate {lr} is not a finite non-negative number"));
        }
        match self {
            Optimizer::Sgd { momentum, velocity, .. } => {
                if !(0.0..1.0).contains(momentum) {
                    return Err(format!("sgd momentum {momentum} is outside [0, 1)"));
                }
                length("velocity", velocity)?;
                finite("velocity", velocity)
            }
            Optimizer::Adam { beta1, beta2, eps, m, v, t, .. } => {
                if !((0.0..1.0).contains(beta1) && (0.0..1.0).contains(beta2) && eps.is_finite() && *eps > 0.0) {
                    return Err(format!("adam settings beta1 {beta1}, beta2 {beta2}, eps {eps} are out of range"));
                }
                length("m", m)?;
                length("v", v)?;
                if m.len() != v.len() {
                    return Err(format!("adam state `m` has {} values and `v` {}", m.len(), v.len()));
                }
                if (*t == 0) != m.is_empty() || *t > i32::MAX as u64 {
                    return Err(format!("adam step count {t} does not fit its moments ({} values)", m.len()));
                }
                finite("m", m)?;
                finite("v", v)?;
                match v.iter().position(|x| *x < 0.0) {
                    Some(i) => Err(format!("adam state `v`[{i}] is negative")),
                    None => Ok(()),
                }
            }
        }
    }

    /// The updates taken, where the rule counts them (Adam's bias
    /// correction does; plain SGD keeps no count).
    pub fn steps_taken(&self) -> Option<u64> {
        match self {
            Optimizer::Adam { t, .. } => Some(*t),
            Optimizer::Sgd { .. } => None,
        }
    }

    /// The learning rate.
    pub fn lr(&self) -> f64 {
        match self {
            Optimizer::Sgd { lr, .. } | Optimizer::Adam { lr, .. } => *lr,
        }
    }

    /// Sets the learning rate (for schedules).
    pub fn set_lr(&mut self, rate: f64) {
        match self {
            Optimizer::Sgd { lr, .. } | Optimizer::Adam { lr, .. } => *lr = rate,
        }
    }

    /// One update of `p` along the gradient `g`. For `f32` parameters the
    /// state (velocity, moments) and the update are computed in `f64` and
    /// the result rounded once.
    ///
    /// # Panics
    /// If `g` and `p` differ in length, or the state was made for another length.
    pub fn step<R: Real>(&mut self, p: &mut [R], g: &[R]) {
        assert_eq!(p.len(), g.len(), "optimizer: parameters and gradient differ in length");
        match self {
            Optimizer::Sgd { lr, momentum, velocity } => {
                if *momentum == 0.0 {
                    for (p, g) in p.iter_mut().zip(g) {
                        *p = R::of(p.as_f64() - *lr * g.as_f64());
                    }
                    return;
                }
                if velocity.is_empty() {
                    velocity.resize(p.len(), 0.0);
                }
                assert_eq!(velocity.len(), p.len(), "optimizer state is for another parameter count");
                for ((p, g), v) in p.iter_mut().zip(g).zip(velocity.iter_mut()) {
                    *v = *momentum * *v + g.as_f64();
                    *p = R::of(p.as_f64() - *lr * *v);
                }
            }
            Optimizer::Adam { lr, beta1, beta2, eps, m, v, t } => {
                if m.is_empty() {
                    m.resize(p.len(), 0.0);
                    v.resize(p.len(), 0.0);
                }
                assert_eq!(m.len(), p.len(), "optimizer state is for another parameter count");
                *t += 1;
                let c1 = 1.0 - beta1.powi(*t as i32);
                let c2 = 1.0 - beta2.powi(*t as i32);
                for (((p, g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                    let g = g.as_f64();
                    *m = *beta1 * *m + (1.0 - *beta1) * g;
                    *v = *beta2 * *v + (1.0 - *beta2) * g * g;
                    *p = R::of(p.as_f64() - *lr * (*m / c1) / ((*v / c2).sqrt() + *eps));
                }
            }
        }
    }
}

/// Scales `g` so that its Euclidean norm is at most `max`; returns the norm
/// before scaling.
pub fn clip_by_norm(g: &mut [f64], max: f64) -> f64 {
    let norm = g.iter().map(|a| a * a).sum::<f64>().sqrt();
    if norm > max && norm > 0.0 {
        let s = max / norm;
        for a in g.iter_mut() {
            *a *= s;
        }
    }
    norm
}

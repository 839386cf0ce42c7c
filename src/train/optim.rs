//! Gradient optimizers on a flat parameter vector: [`Sgd`] (with optional
//! momentum) and [`Adam`] (Kingma & Ba 2015, published defaults), each
//! with its `Params`; [`Optimizer`], the one a configuration names and a
//! checkpoint saves; and gradient clipping by norm. The state is plain
//! data, saved with the parameters to resume. The rules beyond plain
//! gradients (L-BFGS, HIG, Gauss–Newton, SIP) are in [`super::rule`].

use serde::{Deserialize, Serialize};

use crate::op::Real;

/// Settings of [`Sgd`]; `Default` is plain SGD at rate 0.01.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SgdParams {
    /// Learning rate η.
    pub lr: f64,
    /// Momentum μ (0: plain SGD).
    pub momentum: f64,
}

impl Default for SgdParams {
    fn default() -> Self {
        SgdParams { lr: 0.01, momentum: 0.0 }
    }
}

/// Stochastic gradient descent: `v ← μ·v + g`, `p ← p − η·v` (plain SGD
/// for μ = 0). Requires a gradient.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sgd {
    /// Settings.
    #[serde(flatten)]
    pub params: SgdParams,
    /// Velocity (empty until the first step with momentum).
    pub velocity: Vec<f64>,
}

/// Settings of [`Adam`]; `Default` is the published one (Kingma & Ba 2015:
/// η = 1e-3, β = (0.9, 0.999), ε = 1e-8).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamParams {
    /// Learning rate η.
    pub lr: f64,
    /// β₁.
    pub beta1: f64,
    /// β₂.
    pub beta2: f64,
    /// ε.
    pub eps: f64,
}

impl Default for AdamParams {
    fn default() -> Self {
        AdamParams { lr: 1e-3, beta1: 0.9, beta2: 0.999, eps: 1e-8 }
    }
}

/// Adam (Kingma & Ba 2015): `m ← β₁m + (1−β₁)g`, `v ← β₂v + (1−β₂)g²`,
/// `p ← p − η·m̂/(√v̂ + ε)` with bias-corrected `m̂`, `v̂`. Requires a
/// gradient.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Adam {
    /// Settings.
    #[serde(flatten)]
    pub params: AdamParams,
    /// First moments.
    pub m: Vec<f64>,
    /// Second moments.
    pub v: Vec<f64>,
    /// Steps taken.
    pub t: u64,
}

impl Sgd {
    /// Every number of its state: rate, momentum, velocity.
    pub fn state(&self) -> Vec<f64> {
        [self.params.lr, self.params.momentum].into_iter().chain(self.velocity.iter().copied()).collect()
    }

    /// SGD with `params`, no velocity yet.
    pub fn new(params: SgdParams) -> Self {
        Sgd { params, velocity: Vec::new() }
    }

    /// One update of `p` along the gradient `g` (the velocity in `f64`).
    ///
    /// # Panics
    /// If `g` and `p` differ in length, or the state was made for another length.
    pub fn update<R: Real>(&mut self, p: &mut [R], g: &[R]) {
        assert_eq!(p.len(), g.len(), "optimizer: parameters and gradient differ in length");
        let SgdParams { lr, momentum } = self.params;
        if momentum == 0.0 {
            for (p, g) in p.iter_mut().zip(g) {
                *p = R::of(p.as_f64() - lr * g.as_f64());
            }
            return;
        }
        if self.velocity.is_empty() {
            self.velocity.resize(p.len(), 0.0);
        }
        assert_eq!(self.velocity.len(), p.len(), "optimizer state is for another parameter count");
        for ((p, g), v) in p.iter_mut().zip(g).zip(self.velocity.iter_mut()) {
            *v = momentum * *v + g.as_f64();
            *p = R::of(p.as_f64() - lr * *v);
        }
    }
}

impl Adam {
    /// Every number of its state: settings, step count, moments.
    pub fn state(&self) -> Vec<f64> {
        let AdamParams { lr, beta1, beta2, eps } = self.params;
        [lr, beta1, beta2, eps, self.t as f64].into_iter().chain(self.m.iter().copied()).chain(self.v.iter().copied()).collect()
    }

    /// Adam with `params`, no moments yet.
    pub fn new(params: AdamParams) -> Self {
        Adam { params, m: Vec::new(), v: Vec::new(), t: 0 }
    }

    /// One update of `p` along the gradient `g` (moments in `f64`, the
    /// result rounded once for `f32` parameters).
    ///
    /// # Panics
    /// If `g` and `p` differ in length, or the state was made for another length.
    pub fn update<R: Real>(&mut self, p: &mut [R], g: &[R]) {
        assert_eq!(p.len(), g.len(), "optimizer: parameters and gradient differ in length");
        let AdamParams { lr, beta1, beta2, eps } = self.params;
        if self.m.is_empty() {
            self.m.resize(p.len(), 0.0);
            self.v.resize(p.len(), 0.0);
        }
        assert_eq!(self.m.len(), p.len(), "optimizer state is for another parameter count");
        self.t += 1;
        let c1 = 1.0 - beta1.powi(self.t as i32);
        let c2 = 1.0 - beta2.powi(self.t as i32);
        for (((p, g), m), v) in p.iter_mut().zip(g).zip(self.m.iter_mut()).zip(self.v.iter_mut()) {
            let g = g.as_f64();
            *m = beta1 * *m + (1.0 - beta1) * g;
            *v = beta2 * *v + (1.0 - beta2) * g * g;
            *p = R::of(p.as_f64() - lr * (*m / c1) / ((*v / c2).sqrt() + eps));
        }
    }
}

/// A gradient-based optimizer and its state, as a training configuration
/// names it and a checkpoint saves it (`{"adam": {"lr": …, "m": […], …}}`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Optimizer {
    /// [`Sgd`].
    Sgd(Sgd),
    /// [`Adam`].
    Adam(Adam),
}

impl Optimizer {
    /// Plain SGD.
    pub fn sgd(lr: f64) -> Self {
        Optimizer::Sgd(Sgd::new(SgdParams { lr, momentum: 0.0 }))
    }

    /// Adam with the published defaults β = (0.9, 0.999), ε = 1e-8.
    pub fn adam(lr: f64) -> Self {
        Optimizer::Adam(Adam::new(AdamParams { lr, ..AdamParams::default() }))
    }

    /// Every number of its state (rates, moments, step count), for
    /// comparing two optimizers' states exactly.
    pub fn state(&self) -> Vec<f64> {
        match self {
            Optimizer::Sgd(s) => s.state(),
            Optimizer::Adam(a) => a.state(),
        }
    }

    /// `"adam"` or `"sgd"`, as in a training configuration.
    pub fn kind(&self) -> &'static str {
        match self {
            Optimizer::Sgd(_) => "sgd",
            Optimizer::Adam(_) => "adam",
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
            Optimizer::Sgd(Sgd { params, velocity }) => {
                let momentum = params.momentum;
                if !(0.0..1.0).contains(&momentum) {
                    return Err(format!("sgd momentum {momentum} is outside [0, 1)"));
                }
                length("velocity", velocity)?;
                finite("velocity", velocity)
            }
            Optimizer::Adam(Adam { params, m, v, t }) => {
                let AdamParams { beta1, beta2, eps, .. } = *params;
                if !((0.0..1.0).contains(&beta1) && (0.0..1.0).contains(&beta2) && eps.is_finite() && eps > 0.0) {
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
            Optimizer::Adam(a) => Some(a.t),
            Optimizer::Sgd(_) => None,
        }
    }

    /// The learning rate.
    pub fn lr(&self) -> f64 {
        match self {
            Optimizer::Sgd(s) => s.params.lr,
            Optimizer::Adam(a) => a.params.lr,
        }
    }

    /// Sets the learning rate (for schedules).
    pub fn set_lr(&mut self, rate: f64) {
        match self {
            Optimizer::Sgd(s) => s.params.lr = rate,
            Optimizer::Adam(a) => a.params.lr = rate,
        }
    }

    /// One update of `p` along the gradient `g`. For `f32` parameters the
    /// state (velocity, moments) and the update are computed in `f64` and
    /// the result rounded once.
    ///
    /// # Panics
    /// If `g` and `p` differ in length, or the state was made for another length.
    pub fn step<R: Real>(&mut self, p: &mut [R], g: &[R]) {
        match self {
            Optimizer::Sgd(s) => s.update(p, g),
            Optimizer::Adam(a) => a.update(p, g),
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

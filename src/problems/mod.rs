//! The solvers of `diffsim-solvers` wrapped as operators: each problem's
//! step with its Enzyme-generated and hand-written derivatives side by side.

pub mod burgers;
pub mod drag;
pub mod heat;
pub mod implicit_heat;
pub mod oscillators;
pub mod ranges;
pub mod robertson;
pub mod smoke;

/// `L = ½·Σ (x_i − target_i)²` over the first `target.len()` entries of `x`
/// (a packed state's smoke part); writes `∂L/∂x` into `grad` (overwrites;
/// zero past the target).
pub fn half_squared_error(x: &[f64], target: &[f64], grad: &mut [f64]) -> f64 {
    grad.fill(0.0);
    let mut sum = 0.0;
    for ((g, &s), &t) in grad.iter_mut().zip(x).zip(target) {
        let d = s - t;
        sum += d * d;
        *g = d;
    }
    0.5 * sum
}

/// A smoke benchmark (P2, P4): a step operator rolled out `steps` steps
/// from the packed state `x0`, and the loss `L = ½·Σ (s_T − s*)²` on the
/// first `target.len()` entries of the final state (the smoke). The
/// problems' constructors are [`smoke::P2`]'s and [`smoke::P4`]'s.
#[derive(Debug)]
pub struct SmokeBenchmark<S> {
    /// The step operator (owns the solver and its iteration counters).
    pub step: S,
    /// Number of steps `T`.
    pub steps: usize,
    /// Packed initial state (smoke first, then the velocity).
    pub x0: Vec<f64>,
    /// Target smoke.
    pub target: Vec<f64>,
}

impl<S: crate::op::Vjp> SmokeBenchmark<S> {
    /// The loss and its gradient (zero on the velocity part).
    pub fn loss(&self) -> impl Fn(&[f64], &mut [f64]) -> f64 + '_ {
        |x, g| half_squared_error(x, &self.target, g)
    }

    /// `L` by the forward rollout alone.
    pub fn value(&self) -> Result<f64, crate::rollout::RolloutError> {
        crate::rollout::Rollout::new(&self.step, &[], self.steps)?.loss(&self.x0, &self.loss())
    }

    /// `L` and its gradient with respect to the packed initial state
    /// (Enzyme or the hand adjoint for the explicit part, the implicit
    /// adjoint for the solves).
    pub fn grad_in(
        &self,
        ws: &mut crate::rollout::Workspace,
        mode: crate::rollout::Checkpointing,
    ) -> Result<crate::rollout::Gradient, crate::rollout::RolloutError> {
        crate::rollout::Rollout::new(&self.step, &[], self.steps)?.value_and_grad_in(ws, &self.x0, &self.loss(), mode)
    }

    /// The gradient with respect to the initial smoke only.
    pub fn smoke_gradient<'g>(&self, g: &'g crate::rollout::Gradient) -> &'g [f64] {
        &g.dx0[..self.target.len()]
    }
}

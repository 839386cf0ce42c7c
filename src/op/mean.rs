//! An operator whose output is shifted to the input's mean.

use super::{Forward, Jvp, OpError, OpName, Operator, Vjp};

/// `y = O(x; p) + mean(x) − mean(O(x; p))`: the output of `O` with its mean
/// replaced by the input's. The published inverse-heat code (tum-pbs/SIP
/// `heat/train_heat.py`) shifts its network's prediction this way, since
/// diffusion keeps the mean: the mean of the observation is the true
/// state's, and the network need not learn it.
#[derive(Clone, Copy, Debug)]
pub struct MeanMatched<O>(pub O);

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

sizes_of_inner!([O: Operator] MeanMatched<O> => 0);

impl<O: Forward> Forward for MeanMatched<O> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        super::validate_forward(self, "MeanMatched", x, p, y);
        self.0.forward(x, p, y);
        let shift = mean(x) - mean(y);
        y.iter_mut().for_each(|v| *v += shift);
    }

    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        self.0.smooth_radius(x, p, dx, dp)
    }

    fn solve_tolerance(&self) -> f64 {
        self.0.solve_tolerance()
    }

    fn take_error(&self) -> Option<OpError> {
        self.0.take_error()
    }

    fn locate_non_finite(&self, x: &[f64], p: &[f64]) -> OpName {
        self.0.locate_non_finite(x, p)
    }
}

impl<O: Vjp> Vjp for MeanMatched<O> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        super::validate_vjp(self, "MeanMatched", x, p, dy, dx, dp);
        // ∂y/∂O = I − 1·1ᵀ/n_out; the input's mean adds Σdy/n_in to each dx.
        let total: f64 = dy.iter().sum();
        let g = total / dy.len().max(1) as f64;
        let direct = total / x.len().max(1) as f64;
        dy.iter_mut().for_each(|v| *v -= g);
        self.0.vjp(x, p, dy, dx, dp);
        dx.iter_mut().for_each(|v| *v += direct);
    }
}

impl<O: Jvp> Jvp for MeanMatched<O> {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        super::validate_jvp(self, "MeanMatched", x, p, tx, tp, y, ty);
        self.0.jvp(x, p, tx, tp, y, ty);
        let shift = mean(x) - mean(y);
        y.iter_mut().for_each(|v| *v += shift);
        let tshift = mean(tx) - mean(ty);
        ty.iter_mut().for_each(|v| *v += tshift);
    }
}

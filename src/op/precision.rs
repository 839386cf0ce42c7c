//! Mixed precision: an operator computed in `f32` behind the `f64`
//! interface.

use super::{Forward, Jvp, OpError, OpName, Operator, Vjp};

/// `O` evaluated in single precision inside a double-precision program:
/// inputs, parameters and seeds are rounded to `f32` on the way in, results
/// widened to `f64` on the way out, so the rest of the rollout (a solver in
/// `f64`, the optimizer's master weights) stays in double precision. This is
/// how the published physical-gradient code runs its networks; wrap a
/// [`crate::nn::Net`] as `Float32(net)` and couple it to an `f64` solver.
///
/// The conversions cost one pass over `x`, `p` and the seed per call
/// (for a conv net's few thousand weights, microseconds).
#[derive(Clone, Copy, Debug)]
pub struct Float32<O>(pub O);

fn narrow(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&a| a as f32).collect()
}

fn widen_into(v: &[f32], out: &mut [f64]) {
    for (o, &a) in out.iter_mut().zip(v) {
        *o = a as f64;
    }
}

fn add_widened(v: &[f32], out: &mut [f64]) {
    for (o, &a) in out.iter_mut().zip(v) {
        *o += a as f64;
    }
}

sizes_of_inner!([O: Operator] Float32<O> => 0);

impl<O: Forward<f32>> Forward for Float32<O> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        super::validate_forward(self, "Float32", x, p, y);
        let mut y32 = vec![0.0f32; y.len()];
        self.0.forward(&narrow(x), &narrow(p), &mut y32);
        widen_into(&y32, y);
    }

    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        self.0.smooth_radius(&narrow(x), &narrow(p), &narrow(dx), &narrow(dp))
    }

    fn take_error(&self) -> Option<OpError> {
        self.0.take_error()
    }

    fn locate_non_finite(&self, x: &[f64], p: &[f64]) -> OpName {
        self.0.locate_non_finite(&narrow(x), &narrow(p))
    }
}

impl<O: Vjp<f32>> Vjp for Float32<O> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        super::validate_vjp(self, "Float32", x, p, dy, dx, dp);
        let (mut dx32, mut dp32) = (vec![0.0f32; dx.len()], vec![0.0f32; dp.len()]);
        self.0.vjp(&narrow(x), &narrow(p), &mut narrow(dy), &mut dx32, &mut dp32);
        add_widened(&dx32, dx);
        add_widened(&dp32, dp);
        dy.fill(0.0);
    }
}

impl<O: Jvp<f32>> Jvp for Float32<O> {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        super::validate_jvp(self, "Float32", x, p, tx, tp, y, ty);
        let (mut y32, mut ty32) = (vec![0.0f32; y.len()], vec![0.0f32; ty.len()]);
        self.0.jvp(&narrow(x), &narrow(p), &narrow(tx), &narrow(tp), &mut y32, &mut ty32);
        widen_into(&y32, y);
        widen_into(&ty32, ty);
    }
}

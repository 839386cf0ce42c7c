//! Enzyme-generated derivatives of the dense and convolution layers, kept
//! to measure them against the hand-written ones that [`super::Layer`] uses
//! (criterion group `nn_layers`; docs/networks.md). Both are checked by
//! the gradient checks.

use diffsim_solvers::nn::{self as kernel, Conv1d};

use crate::op::Operator;

/// A dense layer `y = W·x + b`, `p = [W, b]`, derivatives by Enzyme.
#[derive(Clone, Copy, Debug)]
pub struct DenseEnzyme {
    /// Inputs.
    pub n_in: usize,
    /// Outputs.
    pub n_out: usize,
}

impl Operator for DenseEnzyme {
    fn n_in(&self) -> usize {
        self.n_in
    }
    fn n_out(&self) -> usize {
        self.n_out
    }
    fn n_params(&self) -> usize {
        self.n_out * (self.n_in + 1)
    }
}

fn dense(op: &DenseEnzyme, x: &[f64], p: &[f64], y: &mut [f64]) {
    let (w, b) = p.split_at(op.n_in * op.n_out);
    kernel::dense(op.n_in, w, b, x, y)
}

crate::differentiable!(DenseEnzyme => dense);

/// A 1D convolution, `p = [W, b]`, derivatives by Enzyme.
#[derive(Clone, Copy, Debug)]
pub struct Conv1dEnzyme(pub Conv1d);

impl Operator for Conv1dEnzyme {
    fn n_in(&self) -> usize {
        self.0.c_in * self.0.len
    }
    fn n_out(&self) -> usize {
        self.0.c_out * self.0.len
    }
    fn n_params(&self) -> usize {
        self.0.n_weights() + self.0.c_out
    }
}

fn conv1d(op: &Conv1dEnzyme, x: &[f64], p: &[f64], y: &mut [f64]) {
    let (w, b) = p.split_at(op.0.n_weights());
    kernel::conv1d_simple(&op.0, w, b, x, y)
}

crate::differentiable!(Conv1dEnzyme => conv1d);

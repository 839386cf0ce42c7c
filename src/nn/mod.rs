//! Neural networks as operators: the input is the operator's `x`, the
//! weights its parameters `p`, and forward, VJP and JVP are the framework's
//! (so the gradient checks, rollouts and optimizers apply unchanged).
//!
//! A [`Net`] is a sequence of [`Layer`]s: dense layers, 1D and 2D
//! convolutions with zero or periodic padding, activations, average
//! pooling and upsampling, and two wrappers that hold a whole inner net: a
//! residual block (`y = x + f(x)`) and a skip connection (`y = [x, f(x)]`,
//! channels concatenated) from which U-Nets are built ([`presets`]). The
//! derivatives are written by hand on top of the kernels of
//! [`diffsim_solvers::nn`]; [`enzyme`] holds the Enzyme-generated versions
//! of the dense and convolution layers they were measured against (docs/networks.md).
//!
//! Parameters live in one flat [`ParamStore`] with a name and shape per
//! tensor, saved to and loaded from JSON.

pub mod enzyme;
mod layer;
pub mod presets;
mod store;

pub use diffsim_solvers::nn::{Activation, Conv1d, Conv2d, Padding};
pub use layer::normal;
pub use layer::{Init, Layer, NET_PAR_MIN_WORK, Net, NetError};
pub use store::{ParamEntry, ParamStore, StoreError};

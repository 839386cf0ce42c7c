//! diffsim: differentiable physics in Rust.
#![feature(autodiff)]
#![deny(missing_docs)]

pub mod check;
pub mod cli;
pub mod op;
pub mod problems;
pub mod rollout;

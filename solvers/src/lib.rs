//! Plain forward solvers for diffsim.
//!
//! Every solver step here is an ordinary Rust function on slices: it reads
//! its inputs, overwrites its output, and knows nothing of differentiation or
//! of the diffsim framework. Beside each step sit its hand-written adjoint
//! (the reference for correctness and speed of the generated one), the
//! canonical problems built on it and, where one exists, an exact solution.
//!
//! This crate is compiled **without** `-Zautodiff=Enable`: Enzyme sees its
//! functions only at the fat-LTO link of the binaries that differentiate them.
//! Linear algebra (faer) lives here too ([`linalg`]), behind non-generic functions,
//! because faer crashes rustc when the autodiff flag is on.
#![deny(missing_docs)]
// Explicit 512-bit vectors in the network kernels (`nn`, `real`).
#![feature(portable_simd)]
// `chunks_exact(8)` keeps the eight-lane reductions readable on stable APIs.
#![allow(clippy::chunks_exact_to_as_chunks)]

pub mod boundary;
pub mod burgers;
pub mod cg;
pub mod diffusion;
pub mod exact;
pub mod flow;
pub mod grid;
pub mod krylov;
pub mod linalg;
pub mod mac;
pub mod multigrid;
pub mod nn;
pub mod nonsmooth;
pub mod optim;
pub mod par;
pub mod real;
pub mod simd;
pub mod smoke;
pub mod spectral;

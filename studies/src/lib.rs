//! # diffsim's studies
//!
//! Published setups reproduced through the `diffsim` library, one module
//! each; the command line (`diffsim experiment …`, `diffsim train`,
//! `diffsim pareto`, `diffsim stability`, `diffsim bench p3`) runs them and
//! writes their files. Nothing here is needed to use the library: a study
//! is an example of its parts at work, and its result is checked against a
//! published figure.
//!
//! - [`sol`]: solver-in-the-loop (Um et al. 2020) on Burgers ([`burgers`],
//!   configured by [`config`] for `diffsim train`) and on 2D flow past a
//!   disc ([`wake`]).
//! - [`oscillators`]: half-inverse gradients against Adam and Gauss–Newton
//!   on coupled oscillators (Schnell et al. 2022).
//! - [`heat`] and [`smoke`]: scale-invariant physics (SIP) updates against
//!   Adam (Holl et al. 2022).
//! - [`shape_net`]: a network from the Reynolds number to the minimum-drag
//!   shape, trained through the steady solver.
//! - [`p3`]: benchmark P3, one training iteration (docs/benchmarks.md).
//! - [`accuracy`]: the schemes against exact solutions, error against time
//!   and memory, and the hard cases that must stay stable.
#![deny(missing_docs)]

pub mod accuracy;
pub mod burgers;
pub mod config;
pub mod heat;
pub mod oscillators;
pub mod p3;
pub mod shape_net;
pub mod smoke;
pub mod sol;
pub mod wake;

//! The one integration-test binary (Enzyme runs at every test binary's
//! fat-LTO link, so there is exactly one). Each module covers one layer.
#![feature(autodiff)]

mod accuracy;
mod bad_inputs;
mod boundaries;
mod boundaries3d;
mod checks;
mod cli;
mod distributed;
mod doc_examples;
mod flow;
mod fluids;
mod fluids3d;
mod fuzz_replay;
mod inputs;
mod nn;
mod nonsmooth;
mod p1;
mod p2;
mod p4;
mod pg;
mod properties;
mod resume;
mod rollout;
mod rollout_wrt;
mod scenes;
mod shapes;
mod user_op;
mod wake;

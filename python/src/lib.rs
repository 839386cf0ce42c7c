//! The extension module `diffsim._diffsim`: the final link, where Enzyme
//! generates the gradients diffsim declares. Everything is in
//! `diffsim-bindings` (built without the autodiff flag); its `#[pymodule]`
//! exports `PyInit__diffsim` from here.

pub use diffsim_bindings::_diffsim;

// maturin finds the bindings through this dependency.
use pyo3 as _;

//! The solvers of `diffsim-solvers` wrapped as operators: each problem's
//! step with its Enzyme-generated and hand-written derivatives side by side.

pub mod burgers;
pub mod drag;
pub mod heat;
pub mod oscillators;
pub mod smoke;

//! The one integration-test binary (Enzyme runs at every test binary's
//! fat-LTO link, so there is exactly one). Each module covers one layer.
#![feature(autodiff)]

mod accuracy;
mod bad_inputs;
mod boundaries;
mod checks;
mod cli;
mod distributed;
mod doc_examples;
mod fixed_point;
mod flow;
mod fluids;
mod fuzz_replay;
mod implicit;
mod inputs;
mod integrators;
mod layout;
mod memory;
mod navier_stokes;
mod nn;
mod nonlinear;
mod nonsmooth;
mod obstacles;
mod p1;
mod pg;
mod properties;
mod resume;
mod rollout;
mod rollout_wrt;
mod rules;
mod scenes;
mod shapes;
mod smoke;
mod studies;
mod trainer;
mod user_op;
mod wake;
mod words;

/// The `diffsim` program the command-line tests run: `target/release/diffsim`. It belongs to another package (`bin/`), so
/// `cargo test` does not build it: `scripts/test.sh` (or
/// `scripts/cargo-enzyme build --release`) builds it first.
pub fn diffsim_bin() -> &'static str {
    static BIN: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    BIN.get_or_init(|| {
        // Cargo gives integration tests TARGET/tmp; the program is at
        // TARGET/release/diffsim (the suite runs in release only).
        let bin = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).parent().expect("the target folder").join("release").join("diffsim");
        assert!(bin.is_file(), "{} is missing: build it first (scripts/cargo-enzyme build --release)", bin.display());
        bin.to_str().expect("a UTF-8 path").to_string()
    })
}

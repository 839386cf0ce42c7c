//! Fuzz target: see `diffsim_cli::fuzz::params`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| diffsim_cli::fuzz::params(data));

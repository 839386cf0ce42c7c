//! Fuzz target: see `diffsim_cli::fuzz::config`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| diffsim_cli::fuzz::config(data));

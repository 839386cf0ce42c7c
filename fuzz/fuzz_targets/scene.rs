//! Fuzz target: see `diffsim_cli::fuzz::scene`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| diffsim_cli::fuzz::scene(data));

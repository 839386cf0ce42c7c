//! Fuzz target: see `diffsim_cli::fuzz::npy`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| diffsim_cli::fuzz::npy(data));

//! Fuzz target: see `diffsim::fuzz::npy`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| diffsim::fuzz::npy(data));

//! Fuzz target: see `diffsim::fuzz::params`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| diffsim::fuzz::params(data));

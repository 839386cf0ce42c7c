//! Fuzz target: see `diffsim::fuzz::config`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| diffsim::fuzz::config(data));

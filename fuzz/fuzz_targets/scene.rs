//! Fuzz target: see `diffsim::fuzz::scene`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| diffsim::fuzz::scene(data));

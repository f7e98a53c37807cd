#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| prac::fuzz::bundle_manifest(data));

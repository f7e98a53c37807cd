#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    prac::testing::fuzz::bundle_bytes(data);
});

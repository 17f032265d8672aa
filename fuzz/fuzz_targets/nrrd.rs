//! Fuzzes the NRRD reader (attached data, raw or gzip).

#![no_main]

use libfuzzer_sys::fuzz_target;
use lungmotion::formats::nrrd::parse_nrrd;

fuzz_target!(|data: &[u8]| {
    let _ = parse_nrrd(data, "fuzz.nrrd");
});

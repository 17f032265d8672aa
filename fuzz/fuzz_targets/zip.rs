//! Fuzzes the safe zip reader with the limits every upload gets.

#![no_main]

use libfuzzer_sys::fuzz_target;
use lungmotion::formats::archive::{read_zip_entries, ArchiveLimits};

fuzz_target!(|data: &[u8]| {
    let _ = read_zip_entries(
        std::io::Cursor::new(data),
        "fuzz.zip",
        &ArchiveLimits::default(),
    );
});

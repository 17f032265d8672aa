//! Fuzzes the breathing-trace CSV reader, with units from the header and from the options.

#![no_main]

use libfuzzer_sys::fuzz_target;
use lungmotion::breathing::{BreathingTrace, TraceFormat, TraceOptions, VolumeReference};

fuzz_target!(|data: &[u8]| {
    // The file reader refuses text that is not UTF-8 before parsing.
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let csv = TraceOptions {
        format: TraceFormat::Csv,
        ..TraceOptions::default()
    };
    let _ = BreathingTrace::parse(text, &csv);
    let absolute = TraceOptions {
        reference: VolumeReference::Absolute {
            scanned_volume_ml: 3000.0,
        },
        seconds_per_time_unit: Some(1e-3),
        ml_per_volume_unit: Some(1e3),
        ..csv
    };
    let _ = BreathingTrace::parse(text, &absolute);
});

//! Fuzzes the breathing-trace JSON reader.

#![no_main]

use libfuzzer_sys::fuzz_target;
use lungmotion::breathing::{BreathingTrace, TraceFormat, TraceOptions};

fuzz_target!(|data: &[u8]| {
    // The file reader refuses text that is not UTF-8 before parsing.
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let json = TraceOptions {
        format: TraceFormat::Json,
        ..TraceOptions::default()
    };
    let _ = BreathingTrace::parse(text, &json);
    // What the service and the CLI do: tell the format from the first character.
    let _ = BreathingTrace::parse(text, &TraceOptions::default());
});

//! Hostile breathing traces (CSV and JSON): NaN, non-monotonic time, wrong units, empty,
//! huge and malformed files.

use std::path::Path;

use lungmotion::breathing::{BreathingTrace, TraceOptions};

use super::{write, Case, Expect, Outcome};

/// Reads `text` written as `name` with the default options.
fn read(dir: &Path, name: &str, text: &[u8]) -> Outcome {
    let path = write(dir, name, text);
    BreathingTrace::read(&path, &TraceOptions::default())
        .map(|t| format!("{} samples over {} s", t.time_s.len(), t.duration_s()))
        .map_err(|e| e.to_string())
}

fn csv(name: &str, expect: Expect, text: impl Into<Vec<u8>>) -> Case {
    let text = text.into();
    Case::new(format!("CSV: {name}"), expect, move |dir| {
        read(dir, "trace.csv", &text)
    })
}

fn json(name: &str, expect: Expect, text: impl Into<Vec<u8>>) -> Case {
    let text = text.into();
    Case::new(format!("JSON: {name}"), expect, move |dir| {
        read(dir, "trace.json", &text)
    })
}

/// A breathing CSV of `n` samples at 10 Hz.
fn breaths(n: usize) -> String {
    let mut s = String::from("time_s,volume_ml\n");
    for i in 0..n {
        let t = i as f64 / 10.0;
        s.push_str(&format!(
            "{t},{}\n",
            250.0 * (1.0 - (t * std::f64::consts::PI / 2.0).cos())
        ));
    }
    s
}

/// The trace cases.
pub fn cases() -> Vec<Case> {
    use Expect::*;
    vec![
        csv(
            "valid",
            Accepted(&["3 samples"]),
            "time_s,volume_ml\n0,0\n1,250\n2,0\n",
        ),
        csv("empty file", Refused(&["empty"]), ""),
        csv(
            "only a BOM and blank lines",
            Refused(&["empty"]),
            "\u{feff}\n\n  \n",
        ),
        csv("header only", Refused(&["0 samples"]), "time_s,volume_ml\n"),
        csv(
            "one sample",
            Refused(&["1 samples"]),
            "time_s,volume_ml\n0,0\n",
        ),
        csv("unknown header", Refused(&["header"]), "t,v\n0,0\n1,1\n"),
        csv(
            "time in hours",
            Refused(&["header"]),
            "time_h,volume_ml\n0,0\n1,100\n",
        ),
        csv(
            "NaN volume",
            Refused(&["volume is NaN"]),
            "time_s,volume_ml\n0,0\n1,NaN\n",
        ),
        csv(
            "infinite time",
            Refused(&["time is inf"]),
            "time_s,volume_ml\n0,0\ninf,1\n",
        ),
        csv(
            "negative infinite volume",
            Refused(&["volume is -inf"]),
            "time_s,volume_ml\n0,0\n1,-inf\n",
        ),
        csv(
            "time going back",
            Refused(&["strictly increase"]),
            "time_s,volume_ml\n0,0\n2,5\n1,6\n",
        ),
        csv(
            "duplicate time",
            Refused(&["not after"]),
            "time_s,volume_ml\n0,0\n1,5\n1,6\n",
        ),
        csv(
            "volume in mL labelled L",
            Refused(&["implausible"]),
            "time_s,volume_l\n0,0\n2,500\n4,0\n",
        ),
        csv(
            "absolute volumes without the scanned volume",
            Refused(&["absolute lung volumes"]),
            "time_s,volume_ml\n0,5500\n2,6000\n4,5500\n",
        ),
        csv(
            "time in s labelled ms",
            Refused(&["flow", "wrong units"]),
            "time_ms,volume_ml\n0,0\n2,500\n4,0\n",
        ),
        csv(
            "9 L breath",
            Refused(&["implausible"]),
            "time_s,volume_ml\n0,0\n2,9000\n",
        ),
        csv(
            "a word in a number",
            Refused(&["line 3", "'abc'"]),
            "time_s,volume_ml\n0,0\n1,abc\n",
        ),
        csv(
            "3 columns under a 2-column header",
            Refused(&["3 columns"]),
            "time_s,volume_ml\n0,0,1\n",
        ),
        csv(
            "semicolons",
            Refused(&["header"]),
            "time_s;volume_ml\n0;0\n1;250\n",
        ),
        csv(
            "1e400",
            Refused(&["time is inf"]),
            "time_s,volume_ml\n0,0\n1e400,5\n",
        ),
        csv(
            "hex numbers",
            Refused(&["not a number"]),
            "time_s,volume_ml\n0,0\n0x10,5\n",
        ),
        csv("NUL bytes", Refused(&["header"]), "\0\0\0\0\0\0"),
        csv(
            "Latin-1 bytes (not UTF-8)",
            Refused(&["trace.csv"]),
            b"time_s,volume_ml\n0,0\n1,\xe9\n".to_vec(),
        ),
        csv(
            "a 20 MB header line",
            Refused(&["header 'xxxx", "(20971520 bytes)"]),
            "x".repeat(20 << 20),
        ),
        csv(
            "a 20 MB cell",
            Refused(&["not a number"]),
            format!("time_s,volume_ml\n0,0\n1,{}\n", "9".repeat(20 << 20) + "x"),
        ),
        csv(
            "100 000 samples",
            Accepted(&["100000 samples"]),
            breaths(100_000),
        ),
        csv(
            "a million comment lines",
            Refused(&["empty"]),
            "#\n".repeat(1_000_000),
        ),
        json(
            "valid",
            Accepted(&["3 samples"]),
            r#"{"time_s": [0, 1, 2], "volume_ml": [0, 250, 0]}"#,
        ),
        json(
            "null (NaN) volume",
            Refused(&["volume_ml[1] is null"]),
            r#"{"time_s": [0, 1], "volume_ml": [0, null]}"#,
        ),
        json(
            "NaN literal",
            Refused(&["not valid JSON"]),
            r#"{"time_s": [0, 1], "volume_ml": [0, NaN]}"#,
        ),
        json(
            "1e400",
            Refused(&["not valid JSON"]),
            r#"{"time_s": [0, 1e400], "volume_ml": [0, 1]}"#,
        ),
        json(
            "lengths differ",
            Refused(&["2 times but 3 volumes"]),
            r#"{"time_s": [0, 1], "volume_ml": [0, 1, 2]}"#,
        ),
        json(
            "no volumes",
            Refused(&["volume_ml"]),
            r#"{"time_s": [0, 1]}"#,
        ),
        json(
            "unknown field",
            Refused(&["unknown field"]),
            r#"{"time_s": [0, 1], "volume_ml": [0, 1], "units": "mL"}"#,
        ),
        json(
            "time_s and time_ms",
            Refused(&["time"]),
            r#"{"time_s": [0, 1], "time_ms": [0, 1000], "volume_ml": [0, 1]}"#,
        ),
        json(
            "strings for numbers",
            Refused(&["expected"]),
            r#"{"time_s": ["0", "1"], "volume_ml": [0, 1]}"#,
        ),
        json(
            "time going back",
            Refused(&["strictly increase"]),
            r#"{"time_s": [0, 2, 1], "volume_ml": [0, 1, 2]}"#,
        ),
        json(
            "time_ms and volume_l",
            Accepted(&["3 samples over 4 s"]),
            r#"{"time_ms": [0, 2000, 4000], "volume_l": [0, 0.5, 0]}"#,
        ),
        json(
            "top-level array",
            Refused(&["found a JSON array"]),
            "[[0, 0], [1, 250]]",
        ),
        json(
            "10 000 nested arrays",
            Refused(&["not valid JSON"]),
            format!("{{\"time_s\": {}{}", "[".repeat(10_000), "]".repeat(10_000)),
        ),
        json(
            "truncated",
            Refused(&["not valid JSON"]),
            r#"{"time_s": [0, 1], "volume_ml": [0,"#,
        ),
        json("empty object", Refused(&["time_s"]), "{}"),
        json(
            "a 20 MB string",
            Refused(&["expected"]),
            format!(
                "{{\"time_s\": \"{}\", \"volume_ml\": [0, 1]}}",
                "x".repeat(20 << 20)
            ),
        ),
    ]
}

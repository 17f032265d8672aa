//! Helpers shared by the command-line tests: the built binary, the bundled sample volumes and
//! per-process scratch directories.

use std::path::PathBuf;
use std::process::Command;

/// The `lungmotion` binary built for this test run.
pub fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_lungmotion"))
}

/// A file or directory of the bundled `sample-volumes/`.
pub fn sample(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("sample-volumes")
        .join(name)
}

/// `lm-cli-<name>-<pid>` in the temp directory, with anything left there by an earlier run
/// removed; the directory itself is not created, so a test can check that a command does.
pub fn absent_temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lm-cli-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

// Not every test binary that includes this module writes a trace.
#[allow(dead_code)]
/// Writes a `time_s,volume_ml` trace of sin² breaths of `tidal_ml`, 4 s each, sampled every
/// `step_s` for `duration_s`.
pub fn write_breaths(path: &std::path::Path, tidal_ml: f64, step_s: f64, duration_s: f64) {
    let mut csv = String::from("time_s,volume_ml\n");
    let samples = (duration_s / step_s).round() as usize;
    for i in 0..=samples {
        let t = i as f64 * step_s;
        let v = tidal_ml * (std::f64::consts::PI * t / 4.0).sin().powi(2);
        csv.push_str(&format!("{t:.1},{v:.3}\n"));
    }
    std::fs::write(path, csv).unwrap();
}

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

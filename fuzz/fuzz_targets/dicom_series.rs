//! Fuzzes the DICOM series reader through its public entry point: the input is one file of a
//! folder handed to `read_dicom_series`, as `lungmotion ingest --ct <folder>` would read it.

#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use lungmotion::formats::dicom::read_dicom_series;

/// A folder of this process (libFuzzer's `-fork`/`-jobs` run several) holding the one file.
fn series_dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let base = if std::path::Path::new("/dev/shm").is_dir() {
            PathBuf::from("/dev/shm")
        } else {
            std::env::temp_dir()
        };
        let dir = base.join(format!("lm-fuzz-dicom-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("create the fuzz folder");
        dir
    })
}

fuzz_target!(|data: &[u8]| {
    let dir = series_dir();
    std::fs::write(dir.join("slice.dcm"), data).expect("write the fuzz input");
    // Any Err is a refusal, which is what hostile input should get; panics and aborts are
    // the findings.
    let _ = read_dicom_series(dir);
});

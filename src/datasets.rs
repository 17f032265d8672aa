//! Where the third-party reference CTs live: `$LUNGMOTION_SHARED_DATA` if set, otherwise
//! `../shared/data` beside the checkout. Tests and benchmarks that need them report
//! themselves skipped when they are absent, so a fresh machine runs on the bundled phantom.

use std::path::PathBuf;

/// Environment variable that points at the reference data directory.
pub const SHARED_DATA_ENV: &str = "LUNGMOTION_SHARED_DATA";

/// The reference data directory, if it exists.
pub fn shared_data_dir() -> Option<PathBuf> {
    let dir = match std::env::var_os(SHARED_DATA_ENV) {
        Some(d) => PathBuf::from(d),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"),
    };
    dir.is_dir().then_some(dir)
}

/// The CIP chest CT case (`ct-64.nrrd`, `lm-64.nrrd`, `dicom/`), if present.
pub fn cip_chest_ct64() -> Option<PathBuf> {
    shared_data_dir()
        .map(|d| d.join("cip-chest-ct64"))
        .filter(|d| d.is_dir())
}

/// The TotalSegmentator abdomen case (JPEG 2000 DICOM and a RAS NIfTI), if present.
pub fn totalseg_abdomen_ct() -> Option<PathBuf> {
    shared_data_dir()
        .map(|d| d.join("totalseg-abdomen-ct"))
        .filter(|d| d.is_dir())
}

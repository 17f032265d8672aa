//! Fuzzes the MetaImage (`.mha`) reader through `read_mha`, from a file as the tools read it.

#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use lungmotion::formats::metaimage::read_mha;

/// A file of this process (libFuzzer's `-fork`/`-jobs` run several) the input is written to.
fn input_path() -> &'static PathBuf {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        let base = if std::path::Path::new("/dev/shm").is_dir() {
            PathBuf::from("/dev/shm")
        } else {
            std::env::temp_dir()
        };
        base.join(format!("lm-fuzz-{}.mha", std::process::id()))
    })
}

fuzz_target!(|data: &[u8]| {
    let path = input_path();
    std::fs::write(path, data).expect("write the fuzz input");
    let _ = read_mha(path);
});

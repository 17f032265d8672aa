//! Tells the tests whether the third-party reference CTs (`$LUNGMOTION_SHARED_DATA`, else
//! `../shared/data`) are present, as the `shared_data` cfg: tests that need them are then
//! reported as ignored with the reason, instead of passing without checking anything.
//!
//! Likewise `postgres_binaries` when PostgreSQL's server programs are installed
//! (`/usr/lib/postgresql/<version>/bin/initdb`, Debian's `postgresql`): the tests that start a
//! database of their own need them.
//!
//! Only a present folder is watched: watching a missing path would rerun this script and
//! rebuild the crate on every build. Data added later needs `touch build.rs` (README).

use std::path::PathBuf;

fn main() {
    println!("cargo:rustc-check-cfg=cfg(shared_data)");
    println!("cargo:rustc-check-cfg=cfg(postgres_binaries)");
    let postgres = std::path::Path::new("/usr/lib/postgresql");
    if let Ok(versions) = std::fs::read_dir(postgres) {
        println!("cargo:rerun-if-changed={}", postgres.display());
        if versions
            .flatten()
            .any(|v| v.path().join("bin/initdb").is_file())
        {
            println!("cargo:rustc-cfg=postgres_binaries");
        }
    }
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=LUNGMOTION_SHARED_DATA");
    let dir = match std::env::var_os("LUNGMOTION_SHARED_DATA") {
        Some(dir) => PathBuf::from(dir),
        None => PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("set by cargo"))
            .join("../shared/data"),
    };
    if dir.join("cip-chest-ct64").is_dir() {
        println!("cargo:rerun-if-changed={}", dir.display());
        println!("cargo:rustc-cfg=shared_data");
    }
}

//! The subcommands of `lungmotion`, one module each: its options as one `clap::Args` struct,
//! resolved once into the library's settings, and the call into the library. What they share
//! (logging, exit status, the output directory) is here and in [`exit`] and [`logging`].

pub mod bench;
pub mod exit;
pub mod ingest;
pub mod interrupt;
pub mod logging;
pub mod pacs;
pub mod phantom;
pub mod progress;
pub mod run;
pub mod serve;
pub mod validate;

/// Creates the report directory before any work, so a bad `--out` fails at once, by name
/// (refused, exit 2, as `run` refuses an output directory it cannot use).
pub fn prepare_out(out: &std::path::Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).map_err(|e| {
        lungmotion::Error::OutputDir {
            path: out.to_path_buf(),
            reason: format!("cannot create the output directory: {e}"),
        }
        .into()
    })
}

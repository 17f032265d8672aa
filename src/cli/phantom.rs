//! `lungmotion phantom`: the procedural thorax phantom written to disk.

use std::path::PathBuf;

use lungmotion::phantom::{write_phantom_files, PhantomSettings};

use super::prepare_out;

/// Options of `lungmotion phantom`.
#[derive(clap::Args)]
pub struct PhantomArgs {
    /// Directory for the phantom files.
    #[arg(long, default_value = "sample-volumes")]
    out: PathBuf,
    /// Random seed of the noise (same seed, same bytes).
    #[arg(long)]
    seed: Option<u64>,
    /// Leave the tumour out.
    #[arg(long)]
    no_tumour: bool,
}

impl PhantomArgs {
    /// Writes the phantom's files and names them on stderr.
    pub fn execute(self) -> anyhow::Result<()> {
        prepare_out(&self.out)?;
        let mut settings = PhantomSettings::default();
        if let Some(seed) = self.seed {
            settings.seed = seed;
        }
        if self.no_tumour {
            settings.tumour = None;
        }
        for p in write_phantom_files(&settings, &self.out)? {
            eprintln!("lungmotion: wrote {}", p.display());
        }
        Ok(())
    }
}

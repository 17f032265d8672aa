//! `lungmotion pacs`: pull a CT series from a DICOMweb server, push DICOM files to one.

use std::path::PathBuf;

use lungmotion::pacs::{pull_ct, push, DicomWebAddress};

/// Options of `lungmotion pacs`.
#[derive(clap::Args)]
pub struct PacsArgs {
    #[command(subcommand)]
    action: PacsAction,
}

#[derive(clap::Subcommand)]
enum PacsAction {
    /// Fetch a CT series (WADO-RS) into a directory. FROM is
    /// dicomweb://HOST:PORT/ROOT/studies/STUDY_UID[/series/SERIES_UID] (dicomwebs:// for
    /// HTTPS); without a series, the study's one CT series (found with QIDO-RS).
    Pull {
        /// The study (and series) to fetch.
        #[arg(long)]
        from: String,
        /// Directory to write the instances into (created if absent).
        #[arg(long)]
        out: PathBuf,
    },
    /// Store DICOM files (STOW-RS): every DICOM file under PATHS (directories searched),
    /// skipping the instances the server already holds, so a repeated push stores nothing
    /// twice. TO is dicomweb://HOST:PORT/ROOT.
    Push {
        /// The server's DICOMweb root.
        #[arg(long)]
        to: String,
        /// Files or directories (a run's output directory: its DICOM outputs).
        #[arg(required = true)]
        paths: Vec<PathBuf>,
    },
}

impl PacsArgs {
    /// Runs the action and prints what it did.
    pub fn execute(self) -> anyhow::Result<()> {
        match self.action {
            PacsAction::Pull { from, out } => {
                let address = DicomWebAddress::parse(&from)?;
                let files = pull_ct(&address, &out)?;
                println!("pulled {} instances into {}", files.len(), out.display());
            }
            PacsAction::Push { to, paths } => {
                let address = DicomWebAddress::parse(&to)?;
                let report = push(&address.root_url, &paths)?;
                println!(
                    "stored {} instances; {} already on the server; {} files were not DICOM",
                    report.stored, report.already_stored, report.not_dicom
                );
            }
        }
        Ok(())
    }
}

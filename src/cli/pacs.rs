//! `lungmotion pacs`: pull a CT series from a DICOMweb server, push DICOM files to one.

use std::path::{Path, PathBuf};

use lungmotion::pacs::{
    pull_series, push_with, ClientOptions, DicomWebAddress, DicomWebAuth, DicomWebClient,
    PushReport,
};

/// A client of `root_url` with the credentials of the environment, as the service reads
/// them: `LUNGMOTION_PACS_USERNAME` and `LUNGMOTION_PACS_PASSWORD` (HTTP Basic) or
/// `LUNGMOTION_PACS_TOKEN` (bearer); none when they are unset.
fn client(root_url: &str) -> anyhow::Result<DicomWebClient> {
    let var = |name: &str| std::env::var(name).ok().map(|v| v.trim().to_string());
    let auth = match (
        var("LUNGMOTION_PACS_USERNAME"),
        var("LUNGMOTION_PACS_PASSWORD"),
        var("LUNGMOTION_PACS_TOKEN"),
    ) {
        (None, None, None) => None,
        (Some(username), password, None) => Some(DicomWebAuth::Basic {
            username,
            password: password.unwrap_or_default(),
        }),
        (None, None, Some(token)) => Some(DicomWebAuth::Bearer(token)),
        _ => {
            return Err(lungmotion::Error::argument(
                "PACS credentials",
                "LUNGMOTION_PACS_USERNAME with LUNGMOTION_PACS_PASSWORD, or \
                 LUNGMOTION_PACS_TOKEN alone: the environment sets another combination",
            )
            .into())
        }
    };
    Ok(DicomWebClient::with_options(
        root_url,
        &ClientOptions {
            auth,
            ..ClientOptions::default()
        },
    )?)
}

/// Pulls the CT series `address` names into `dir` (see `pacs pull`); the files.
pub fn pull(address: &DicomWebAddress, dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let Some(study) = address.study_uid.as_deref() else {
        return Err(lungmotion::Error::argument(
            "DICOMweb address",
            format!(
                "{}: names no study to pull (add /studies/UID)",
                address.root_url
            ),
        )
        .into());
    };
    let client = client(&address.root_url)?;
    Ok(pull_series(&client, study, address.series_uid.as_deref(), dir)?.1)
}

/// Pushes the DICOM files under `paths` to the server at `root_url` (see `pacs push`).
pub fn push(root_url: &str, paths: &[PathBuf]) -> anyhow::Result<PushReport> {
    Ok(push_with(&client(root_url)?, paths)?)
}

/// Options of `lungmotion pacs`.
#[derive(clap::Args)]
pub struct PacsArgs {
    #[command(subcommand)]
    action: PacsAction,
}

#[derive(clap::Subcommand)]
enum PacsAction {
    /// Fetch a CT series (WADO-RS) into a directory. Credentials, when the server asks for
    /// them: LUNGMOTION_PACS_USERNAME and LUNGMOTION_PACS_PASSWORD, or LUNGMOTION_PACS_TOKEN.
    /// FROM is
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
                let files = pull(&address, &out)?;
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

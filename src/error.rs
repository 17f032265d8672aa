//! Errors of the crate: each names the offending input or the failing step, in fields a caller
//! can act on (the path and operation, the key, the sample, the point) as well as in its message.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use thiserror::Error;

/// Result type of the crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Everything lungmotion can refuse or detect.
///
/// Variants that carry an I/O error show its text in their message (`cannot read x.csv: No
/// such file or directory`) and keep it in a field rather than as [`std::error::Error::source`],
/// so a report that prints the chain (`{:#}` of anyhow) does not say it twice.
#[derive(Debug, Error)]
pub enum Error {
    /// A material parameter is outside its physical range.
    #[error("invalid material: {0}")]
    InvalidMaterial(String),

    /// An element shape cannot be represented by Baudet's element (some stiffness ≤ 0),
    /// or is degenerate.
    #[error("inadmissible element: {0}")]
    InadmissibleElement(String),

    /// The mesh, a constraint or a load refers to something that does not exist or is not finite.
    #[error("invalid model: {0}")]
    InvalidModel(String),

    /// The simulation produced a non-finite value or its energy grew without bound.
    #[error("numerical blow-up at step {step}: {cause}")]
    Diverged {
        /// Index of the time step or iteration where the blow-up was detected.
        step: usize,
        /// What was detected (non-finite position, energy growth, …), with the node where known.
        cause: String,
    },

    /// A solver ran out of iterations before meeting its tolerance.
    #[error("solver did not converge after {iterations} iterations: residual {residual:.3e} > tolerance {tolerance:.3e}")]
    NotConverged {
        /// Iterations performed.
        iterations: usize,
        /// Relative residual reached.
        residual: f64,
        /// Relative residual required.
        tolerance: f64,
    },

    /// The lungs cannot be brought to a volume the trace asks for: the solves stall or the mesh
    /// gives way first. Names where the mesh is most compressed and what to try.
    #[error("{0}")]
    VolumeUnreachable(Box<UnreachableVolume>),

    /// A run reached its time or equilibrium budget and was stopped (nothing was published).
    /// Names the budget, what was used, the stage and how far the solves got.
    #[error("{0}")]
    BudgetExceeded(Box<BudgetStop>),

    /// A scan (DICOM series, NIfTI, NRRD, zip) is unreadable, inconsistent or implausible.
    #[error("invalid scan: {}: {reason}", scan.display())]
    InvalidScan {
        /// The scan as the user named it: a file or directory, `archive.zip:entry`, or what a
        /// stage was handed (`CT for segmentation`).
        scan: PathBuf,
        /// What is wrong, naming the tag, field or value at fault.
        reason: String,
    },

    /// A setting is unusable: a key of the run or service configuration, a setting of a stage
    /// (segmentation, lung model, phantom, breathing model) or the output instants.
    #[error("invalid {settings}{}: {}{reason}", in_file(.file), key_prefix(.key))]
    Config {
        /// Which settings: `configuration`, `breathing model`, `phantom settings`,
        /// `output instants`, …
        settings: &'static str,
        /// The configuration file they were read from, if any.
        file: Option<PathBuf>,
        /// The key or setting to change (`element_size_mm`, `motion.driver.compliance_ml_per_pa`,
        /// `period_s`), when one is to blame.
        key: Option<String>,
        /// What is wrong, with the value found.
        reason: String,
    },

    /// A breathing trace is unusable.
    #[error("invalid breathing trace{}: {reason}", in_file(.path))]
    Trace {
        /// The file it was read from, if any.
        path: Option<PathBuf>,
        /// The 1-based sample (data row) at fault, where one is.
        row: Option<usize>,
        /// What is wrong, naming the line or sample as the user sees it.
        reason: String,
    },

    /// Tracked points are unusable (the points file or the points handed to a stage).
    #[error("invalid tracked points{}: {}{reason}", in_file(.file), point_prefix(.point))]
    Points {
        /// The points file they were read from, if any.
        file: Option<PathBuf>,
        /// The 1-based number of the point at fault in the list handed over, where one is.
        point: Option<usize>,
        /// What is wrong, naming the line of the file where there is one.
        reason: String,
    },

    /// A caller handed a stage data that does not fit: mismatched lengths or grids between
    /// stages, a slice outside the scan, frames out of order, a parameter out of range.
    #[error("invalid {what}: {reason}")]
    Argument {
        /// What was handed over (`quick-look slice`, `trajectory frame 3`, `volume target`, …).
        what: String,
        /// Why it does not fit.
        reason: String,
    },

    /// A file we read back (or write) is malformed: not a PNG, a damaged trajectories file, a
    /// record that cannot be encoded.
    #[error("{}: {reason}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong with its content.
        reason: String,
    },

    /// A record of the service's store is missing or corrupt.
    #[error("store {record}: {reason}")]
    Store {
        /// The record, relative to the store's data directory (`jobs/<id>/job.json`).
        record: String,
        /// What is wrong with it.
        reason: String,
    },

    /// The service's PostgreSQL database cannot be reached or used.
    #[error("database {server}: {reason}")]
    Database {
        /// The server as `user@host:port/dbname` (never the password).
        server: String,
        /// What went wrong, as the server or the client said it.
        reason: String,
    },

    /// The service's object store (scans' uploads, jobs' outputs) cannot be reached or used.
    #[error("object store {store}{}: {reason}", key_shown(key))]
    ObjectStore {
        /// The store as `s3://bucket/prefix at <endpoint>` (never a credential).
        store: String,
        /// The object's key inside the store's prefix, when one object was concerned.
        key: Option<String>,
        /// What went wrong, as the server or the client said it.
        reason: String,
    },

    /// The database's schema was written by a newer lungmotion than this one.
    #[error(
        "database {server}: its schema is version {found}, written by lungmotion {written_by}; \
         this lungmotion ({ours}) knows versions up to {known} and does not use it: upgrade \
         lungmotion, or give it another database"
    )]
    SchemaTooNew {
        /// The server as `user@host:port/dbname`.
        server: String,
        /// The schema version found.
        found: i32,
        /// The lungmotion version that wrote it.
        written_by: String,
        /// The newest version this lungmotion knows.
        known: i32,
        /// This lungmotion's version.
        ours: &'static str,
    },

    /// An output location cannot be used (not a directory, or a foreign non-empty one).
    #[error("output {}: {reason}", path.display())]
    OutputDir {
        /// The output directory asked for.
        path: PathBuf,
        /// Why it cannot be used.
        reason: String,
    },

    /// Data the crate ships or shares (the sample volumes, the CIP chest CT) is not there.
    #[error("{what} was not found{}; {hint}", looked_in(.path))]
    MissingData {
        /// What is missing.
        what: String,
        /// Where it was looked for, if in one place.
        path: Option<PathBuf>,
        /// How to get it.
        hint: String,
    },

    /// A file or directory operation failed.
    #[error("cannot {op} {}: {cause}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What was being done to it.
        op: IoOp,
        /// What the operating system said.
        cause: std::io::Error,
    },

    /// A server cannot listen on its address.
    #[error("cannot listen on {addr}: {cause}")]
    Listen {
        /// The address asked for.
        addr: SocketAddr,
        /// What the operating system said.
        cause: std::io::Error,
    },

    /// Lung segmentation or model building could not produce a usable result.
    #[error("ingest failed: {0}")]
    Ingest(String),

    /// An external tool (CalculiX) failed or its output could not be read.
    #[error("external tool: {0}")]
    External(String),

    /// The run was cancelled by its caller (nothing was published).
    #[error("cancelled: {0}")]
    Cancelled(String),

    /// A DICOMweb server (PACS) could not be reached, refused a request or answered with
    /// something unusable.
    #[error("PACS {url}{}: {reason}", status.map(|s| format!(" answered HTTP {s}")).unwrap_or_default())]
    Pacs {
        /// The request's URL.
        url: String,
        /// The HTTP status, when the server answered.
        status: Option<u16>,
        /// What went wrong.
        reason: String,
    },
}

/// What was being done to a file or directory when it failed; shown as a verb phrase
/// (`cannot read …`, `cannot create the directory …`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IoOp {
    /// Reading a file.
    Read,
    /// Writing to a file.
    Write,
    /// Creating a file.
    Create,
    /// Creating a directory (and its parents).
    CreateDir,
    /// Opening a file or directory.
    Open,
    /// Renaming a file or directory.
    Rename,
    /// Renaming something onto a path, replacing what was there (the commit of an atomic
    /// write or a published directory).
    Replace,
    /// Removing a file or directory.
    Remove,
    /// Listing a directory.
    List,
    /// Flushing a file or directory to disk.
    Sync,
    /// Reading a file's metadata (size, kind).
    Metadata,
    /// Starting a program or a thread.
    Spawn,
}

impl std::fmt::Display for IoOp {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            IoOp::Read => "read",
            IoOp::Write => "write",
            IoOp::Create => "create",
            IoOp::CreateDir => "create the directory",
            IoOp::Open => "open",
            IoOp::Rename => "rename",
            IoOp::Replace => "replace",
            IoOp::Remove => "remove",
            IoOp::List => "list the directory",
            IoOp::Sync => "sync",
            IoOp::Metadata => "inspect",
            IoOp::Spawn => "start",
        })
    }
}

/// Attaches the operation and the path to an I/O result, so a call site stays one line:
/// `std::fs::read(path).at(IoOp::Read, path)?`.
pub trait IoContext<T> {
    /// The value, or the error as [`Error::Io`] naming `op` on `path`.
    fn at(self, op: IoOp, path: impl AsRef<Path>) -> Result<T>;
}

impl<T> IoContext<T> for std::io::Result<T> {
    fn at(self, op: IoOp, path: impl AsRef<Path>) -> Result<T> {
        self.map_err(|cause| Error::io(op, path, cause))
    }
}

impl Error {
    /// Data handed to a stage that does not fit: `what` was handed over, `reason` says why.
    pub fn argument(what: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::Argument {
            what: what.into(),
            reason: reason.into(),
        }
    }

    /// Unusable `settings` (not read from a file, no single key to blame).
    pub fn settings(settings: &'static str, reason: impl Into<String>) -> Self {
        Error::Config {
            settings,
            file: None,
            key: None,
            reason: reason.into(),
        }
    }

    /// A scan that is unreadable, inconsistent or implausible; `scan` names it as the user did.
    pub fn scan(scan: impl AsRef<Path>, reason: impl Into<String>) -> Self {
        Error::InvalidScan {
            scan: scan.as_ref().to_path_buf(),
            reason: reason.into(),
        }
    }

    /// A file whose content is malformed or cannot be encoded.
    pub fn format(path: impl AsRef<Path>, reason: impl Into<String>) -> Self {
        Error::Format {
            path: path.as_ref().to_path_buf(),
            reason: reason.into(),
        }
    }

    /// An I/O failure of `op` on `path`.
    pub fn io(op: IoOp, path: impl AsRef<Path>, cause: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            op,
            cause,
        }
    }

    /// The file or directory this error names in a field, if any (errors that still carry a
    /// path only in their message text return `None`).
    pub fn path(&self) -> Option<&Path> {
        match self {
            Error::Io { path, .. }
            | Error::Format { path, .. }
            | Error::InvalidScan { scan: path, .. }
            | Error::OutputDir { path, .. } => Some(path),
            Error::Config { file: p, .. }
            | Error::Trace { path: p, .. }
            | Error::Points { file: p, .. }
            | Error::MissingData { path: p, .. } => p.as_deref(),
            _ => None,
        }
    }

    /// The same error with the path it names rewritten by `shown_as`: how a service shows an
    /// error to a client who must not learn the server's directories (a path relative to its
    /// data directory, or what the file is to the client).
    pub fn with_path_shown_as(mut self, shown_as: impl FnOnce(&Path) -> PathBuf) -> Self {
        let slot = match &mut self {
            Error::Io { path, .. }
            | Error::Format { path, .. }
            | Error::InvalidScan { scan: path, .. }
            | Error::OutputDir { path, .. } => Some(path),
            Error::Config { file: p, .. }
            | Error::Trace { path: p, .. }
            | Error::Points { file: p, .. }
            | Error::MissingData { path: p, .. } => p.as_mut(),
            _ => None,
        };
        if let Some(path) = slot {
            *path = shown_as(path);
        }
        self
    }
}

/// ` <path>` when there is one, for messages that name an optional file.
/// Where and why a breathing solve could not reach a volume (see [`Error::VolumeUnreachable`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "the lungs cannot reach {target_ml:+.0} mL: equilibrium was reached up to {reached_ml:+.0} mL \
     ({cause}); there the most compressed element is {element} at LPS ({:.0}, {:.0}, {:.0}) mm{}, \
     at {:.0} % of its rest volume. {remedy}",
    centre_lps_mm[0], centre_lps_mm[1], centre_lps_mm[2], group_suffix(.group), volume_ratio * 100.0
)]
pub struct UnreachableVolume {
    /// Volume change from the scanned state that was asked for, mL.
    pub target_ml: f64,
    /// Volume change of the last equilibrium reached on the way, mL.
    pub reached_ml: f64,
    /// Index of the most compressed element in that equilibrium.
    pub element: usize,
    /// Rest centre of that element, LPS millimetres.
    pub centre_lps_mm: [f64; 3],
    /// Its signed volume over its rest volume.
    pub volume_ratio: f64,
    /// Anatomical groups of its nodes, when the caller knows them.
    pub group: Option<String>,
    /// Why the last solve failed.
    pub cause: String,
    /// What to try.
    pub remedy: String,
}

/// Which budget of a run stopped it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum BudgetKind {
    /// Wall-clock time (`[budget] time_s`, `--time-budget`), counted in seconds.
    Time,
    /// Equilibrium solves (`[budget] max_equilibria`, `--max-equilibria`), counted in solves.
    Equilibria,
}

impl BudgetKind {
    /// The configuration key and the command-line flag that set it.
    pub fn setting(self) -> &'static str {
        match self {
            BudgetKind::Time => "`[budget] time_s` (--time-budget)",
            BudgetKind::Equilibria => "`[budget] max_equilibria` (--max-equilibria)",
        }
    }

    /// `60.2 s used of 60 s allowed`, `4 equilibrium solves used of 4 allowed`.
    fn usage(self, used: f64, limit: f64) -> String {
        match self {
            BudgetKind::Time => format!("{used:.1} s used of {limit} s allowed"),
            BudgetKind::Equilibria => {
                format!("{used:.0} equilibrium solves used of {limit:.0} allowed")
            }
        }
    }
}

/// How a run was stopped by its budget (see [`Error::BudgetExceeded`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "stopped by the {} budget: {}, while {stage}; {equilibria} equilibria reached{}; no output \
     was written. Try a larger element size, or raise {}",
    match budget { BudgetKind::Time => "time", BudgetKind::Equilibria => "equilibrium" },
    budget.usage(*used, *limit), volume_phrase(*volume_reached_ml, *target_ml),
    budget.setting()
)]
pub struct BudgetStop {
    /// The budget that stopped the run.
    pub budget: BudgetKind,
    /// Its limit (seconds, or equilibrium solves).
    pub limit: f64,
    /// What the run had used when it stopped (same unit).
    pub used: f64,
    /// The stage it was in (`solving the breathing cycle`, …).
    pub stage: String,
    /// Equilibria reached by the solves before the stop.
    pub equilibria: usize,
    /// Volume change from the scan of the last equilibrium reached, mL (none before the first).
    pub volume_reached_ml: Option<f64>,
    /// The volume change of the trace farthest from the scan, mL: where the solves were headed.
    pub target_ml: Option<f64>,
}

/// `, the last at +231 mL of the +500 mL the trace reaches` as far as known.
fn volume_phrase(reached: Option<f64>, target: Option<f64>) -> String {
    match (reached, target) {
        (Some(r), Some(t)) => {
            format!(", the last at {r:+.0} mL of the {t:+.0} mL the trace reaches")
        }
        (Some(r), None) => format!(", the last at {r:+.0} mL"),
        _ => String::new(),
    }
}

fn group_suffix(group: &Option<String>) -> String {
    group
        .as_ref()
        .map_or(String::new(), |g| format!(" (nodes: {g})"))
}

fn in_file(path: &Option<PathBuf>) -> String {
    path.as_ref()
        .map(|p| format!(" {}", p.display()))
        .unwrap_or_default()
}

/// ` at <path>` when there is one, for where missing data was looked for.
fn looked_in(path: &Option<PathBuf>) -> String {
    path.as_ref()
        .map(|p| format!(" at {}", p.display()))
        .unwrap_or_default()
}

/// `<key>: ` when a key is to blame.
fn key_prefix(key: &Option<String>) -> String {
    key.as_ref().map(|k| format!("{k}: ")).unwrap_or_default()
}

/// `point <n> ` when one point is to blame (the reason goes on: `point 3 is not finite`).
fn point_prefix(point: &Option<usize>) -> String {
    point.map(|n| format!("point {n} ")).unwrap_or_default()
}

/// `, key <key>` for an object store error about one object, else nothing.
fn key_shown(key: &Option<String>) -> String {
    key.as_ref()
        .map(|k| format!(", key {k}"))
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_name_the_operation_the_path_and_the_reason() {
        let e = std::fs::read("/no/such/dir/x.csv")
            .at(IoOp::Read, "/no/such/dir/x.csv")
            .unwrap_err();
        let text = e.to_string();
        assert!(
            text.starts_with("cannot read /no/such/dir/x.csv: "),
            "{text}"
        );
        assert!(std::error::Error::source(&e).is_none());
        let e = Error::Config {
            settings: "configuration",
            file: Some("run.toml".into()),
            key: Some("element_size_mm".into()),
            reason: "1 mm is outside 2–16 mm".into(),
        };
        assert_eq!(
            e.to_string(),
            "invalid configuration run.toml: element_size_mm: 1 mm is outside 2–16 mm"
        );
        let e = Error::MissingData {
            what: "the phantom description".into(),
            path: Some("s/phantom.json".into()),
            hint: "regenerate it".into(),
        };
        assert_eq!(
            e.to_string(),
            "the phantom description was not found at s/phantom.json; regenerate it"
        );
    }

    #[test]
    fn a_path_field_can_be_shown_as_something_else() {
        let e = Error::io(
            IoOp::Write,
            "/srv/data/jobs/1/job.json",
            std::io::Error::other("disk full"),
        )
        .with_path_shown_as(|p| p.strip_prefix("/srv/data").unwrap().to_path_buf());
        assert_eq!(e.path(), Some(Path::new("jobs/1/job.json")));
        assert_eq!(e.to_string(), "cannot write jobs/1/job.json: disk full");
        let e = Error::scan("/srv/data/tmp/upload-1.zip:IM0001", "no Rows (0028,0010)")
            .with_path_shown_as(|p| {
                p.to_string_lossy()
                    .replacen("/srv/data/tmp/upload-1.zip", "the upload", 1)
                    .into()
            });
        assert_eq!(e.path(), Some(Path::new("the upload:IM0001")));
        assert_eq!(
            e.to_string(),
            "invalid scan: the upload:IM0001: no Rows (0028,0010)"
        );
    }
}

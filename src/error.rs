//! Errors of the crate: each names the offending input or the failing step.

use thiserror::Error;

/// Result type of the crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Everything lungmotion can refuse or detect.
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

    /// A scan (DICOM series, NIfTI, NRRD, zip) is unreadable, inconsistent or implausible;
    /// the message names the file and the problem.
    #[error("invalid scan: {0}")]
    InvalidScan(String),

    /// A breathing trace, configuration or other user input is unusable; the message says why.
    #[error("invalid input: {0}")]
    InvalidInput(String),

    /// Lung segmentation or model building could not produce a usable result.
    #[error("ingest failed: {0}")]
    Ingest(String),

    /// An external tool (CalculiX) failed or its output could not be read.
    #[error("external tool: {0}")]
    External(String),

    /// The run was cancelled by its caller (nothing was published).
    #[error("cancelled: {0}")]
    Cancelled(String),

    /// File or process I/O failed.
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

//! The exit status of every subcommand: 0 success, 2 the usage or the input was refused,
//! 1 a failure while working, 3 stopped by its budget, 130 interrupted. The one place that
//! decides between them.

use std::process::ExitCode;

/// The exit status, as `lungmotion --help` documents it (also in the README).
pub const EXIT_STATUS_HELP: &str = "\
Exit status (the same for every subcommand):
  0  success
  1  a failure while working: the solver diverged or did not converge, writing an output
     failed, an external tool (CalculiX) failed
  2  the usage or the input was refused: an unknown or malformed option; an unreadable or
     unusable configuration, breathing trace, points file, scan, material or output
     directory; no usable lungs in the CT; service settings it cannot serve with (such as
     an address it cannot listen on)
  3  stopped by its budget: `run` or `demo` reached its time (--time-budget, [budget]
     time_s, default 1800 s) or equilibrium budget (--max-equilibria, [budget]
     max_equilibria); the message names which; the output directory is as it was
  130  interrupted: `run` or `demo` stopped by Ctrl-C, SIGTERM or SIGHUP; the output
     directory is as it was and the partial output was removed";

/// Exit status when the usage or the input was refused (as clap's own usage errors).
pub const REFUSED: u8 = 2;

/// Exit status of a failure while working.
pub const FAILED: u8 = 1;

/// Exit status of a run stopped by its time or equilibrium budget: neither refused (the input
/// was usable) nor failed (the solver did not give up): a larger element size or a larger
/// budget finishes it, which a script may want to tell apart.
pub const BUDGET: u8 = 3;

/// Exit status of a run stopped by Ctrl-C, SIGTERM or SIGHUP (128 + SIGINT, as shells report
/// Ctrl-C), whichever signal it was.
pub const INTERRUPTED: u8 = 130;

/// Whether the library refused what it was given (exit 2) rather than failing while working
/// on it (exit 1). Exhaustive, so a new error variant must be placed here; it mirrors the
/// service's 422 against 500 (`ApiError::from_input_error`).
pub fn is_refusal(error: &lungmotion::Error) -> bool {
    use lungmotion::{Error, IoOp};
    match error {
        Error::InvalidScan { .. }
        | Error::InvalidMaterial(_)
        | Error::Ingest(_)
        | Error::Config { .. }
        | Error::Trace { .. }
        | Error::Points { .. }
        | Error::Argument { .. }
        | Error::Format { .. }
        | Error::OutputDir { .. }
        | Error::MissingData { .. }
        | Error::Listen { .. }
        | Error::SchemaTooNew { .. } => true,
        // The PACS refused the request as asked (unknown study, no CT series): the input.
        Error::Pacs { status, .. } => status.is_some_and(|s| (400..500).contains(&s)),
        // An input that cannot be read is refused; an output that cannot be written failed.
        Error::Io { op, .. } => {
            matches!(op, IoOp::Read | IoOp::Open | IoOp::List | IoOp::Metadata)
        }
        Error::InadmissibleElement(_)
        | Error::InvalidModel(_)
        | Error::Diverged { .. }
        | Error::NotConverged { .. }
        | Error::VolumeUnreachable(_)
        | Error::External(_)
        | Error::Cancelled(_)
        | Error::BudgetExceeded(_)
        | Error::Store { .. }
        | Error::Database { .. }
        | Error::ObjectStore { .. } => false,
    }
}

/// The exit status of a library error. Only a signal cancels a command-line run.
pub fn exit_code(error: &lungmotion::Error) -> ExitCode {
    ExitCode::from(if matches!(error, lungmotion::Error::Cancelled(_)) {
        INTERRUPTED
    } else if matches!(error, lungmotion::Error::BudgetExceeded(_)) {
        BUDGET
    } else if is_refusal(error) {
        REFUSED
    } else {
        FAILED
    })
}

/// The exit status of a subcommand's error: decided by the outermost library error in its
/// chain; anything else failed while working.
pub fn exit_code_of_chain(error: &anyhow::Error) -> ExitCode {
    match error
        .chain()
        .find_map(|cause| cause.downcast_ref::<lungmotion::Error>())
    {
        Some(e) => exit_code(e),
        None => ExitCode::from(FAILED),
    }
}

/// Ends a subcommand: its error (if any) on stderr, and the documented exit status.
pub fn finish(result: anyhow::Result<()>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("lungmotion: error: {e:#}");
            exit_code_of_chain(&e)
        }
    }
}

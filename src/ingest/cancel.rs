//! Stopping an ingest that is under way: a job's `DELETE`, a server's shutdown or the CLI's
//! Ctrl-C raise the run's cancel flag, and the segmentation and the model builder look at it
//! between their steps and inside their long loops (once per slice, slab or pass: one atomic
//! load each, nothing next to the work of a slice), then unwind with [`Error::Cancelled`].

use std::sync::atomic::{AtomicBool, Ordering};

use crate::{Error, Result};

/// The flag that stops an ingest, or none (the ingest then runs to its end).
#[derive(Debug, Clone, Copy, Default)]
pub struct Cancel<'a>(Option<&'a AtomicBool>);

impl<'a> Cancel<'a> {
    /// An ingest nothing stops.
    pub const NEVER: Cancel<'static> = Cancel(None);

    /// Stops when `flag` is raised (never when `None`).
    pub fn new(flag: Option<&'a AtomicBool>) -> Self {
        Cancel(flag)
    }

    /// The flag itself, for a reader that takes one.
    pub fn flag(&self) -> Option<&'a AtomicBool> {
        self.0
    }

    /// Whether the flag is raised.
    pub fn raised(&self) -> bool {
        self.0.is_some_and(|f| f.load(Ordering::Relaxed))
    }

    /// [`Error::Cancelled`] naming the step `during` once the flag is raised.
    pub fn check(&self, during: &str) -> Result<()> {
        if self.raised() {
            return Err(Error::Cancelled(format!("stopped during {during}")));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_raised_flag_stops() {
        let flag = AtomicBool::new(false);
        let cancel = Cancel::new(Some(&flag));
        cancel.check("the body").unwrap();
        Cancel::NEVER.check("the body").unwrap();
        flag.store(true, Ordering::SeqCst);
        let e = cancel.check("the body").unwrap_err();
        assert!(
            matches!(&e, Error::Cancelled(m) if m.contains("the body")),
            "{e}"
        );
        Cancel::NEVER.check("the body").unwrap();
    }
}

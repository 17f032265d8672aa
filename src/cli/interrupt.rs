//! Ctrl-C, SIGTERM and SIGHUP during a run: the first raises the run's cancel flag, so the run
//! stops at its next check and unwinds, removing its staging directory; a second one ends the
//! process at once (its staging directory is then removed by the next run into the same place).

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;

use lungmotion::simulation::CancelFlag;

use super::exit::INTERRUPTED;

/// The signals that stop a run, with their names.
#[cfg(unix)]
const SIGNALS: [(i32, &str); 3] = [
    (signal_hook::consts::SIGINT, "SIGINT (Ctrl-C)"),
    (signal_hook::consts::SIGTERM, "SIGTERM"),
    (signal_hook::consts::SIGHUP, "SIGHUP"),
];
#[cfg(not(unix))]
const SIGNALS: [(i32, &str); 2] = [
    (signal_hook::consts::SIGINT, "Ctrl-C"),
    (signal_hook::consts::SIGTERM, "SIGTERM"),
];

/// The handlers of a run: the cancel flag they raise and the signal that raised it.
pub struct Interrupt {
    flag: CancelFlag,
    signal: Arc<AtomicUsize>,
}

impl Interrupt {
    /// Installs the handlers for the rest of the process.
    pub fn install() -> anyhow::Result<Self> {
        let flag: CancelFlag = Arc::new(AtomicBool::new(false));
        let signal = Arc::new(AtomicUsize::new(0));
        for (number, name) in SIGNALS {
            // Registered first, so it sees the flag as the previous signal left it: the
            // second signal ends the process, the first only asks the run to stop.
            signal_hook::flag::register_conditional_shutdown(
                number,
                i32::from(INTERRUPTED),
                flag.clone(),
            )
            .and_then(|_| {
                signal_hook::flag::register_usize(number, signal.clone(), number as usize)
            })
            .and_then(|_| signal_hook::flag::register(number, flag.clone()))
            .map_err(|e| anyhow::anyhow!("cannot install the {name} handler: {e}"))?;
        }
        Ok(Interrupt { flag, signal })
    }

    /// The flag a signal raises.
    pub fn flag(&self) -> CancelFlag {
        self.flag.clone()
    }

    /// The name of the signal that stopped the run, if one did.
    pub fn received(&self) -> Option<&'static str> {
        let number = self.signal.load(Ordering::SeqCst);
        SIGNALS
            .iter()
            .find(|(n, _)| *n as usize == number)
            .map(|(_, name)| *name)
    }
}

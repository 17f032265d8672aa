//! Enforcing a run's budgets ([`BudgetConfig`]): wall-clock time and equilibrium solves.
//!
//! It rides on the cancellation the solves already honour: the run's observer is wrapped in
//! a [`Budgeted`] one whose cancel flag is the flag every Newton, Krylov and relaxation
//! iteration checks. A watcher thread raises that flag at the deadline, recording why (and
//! forwards the caller's own flag, a signal or a client's cancellation, without a reason);
//! the progress sink counts equilibria and raises it when the last allowed one is reached,
//! so the next solve stops before it starts. The [`Error::Cancelled`] that unwinds the run
//! (through the staging directory, which removes the partial output) is then turned into
//! [`Error::BudgetExceeded`] naming the budget.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, AtomicUsize, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::config::BudgetConfig;
use super::{RunObserver, RunStage};
use crate::error::{BudgetKind, BudgetStop};
use crate::simulation::{CancelFlag, SolveProgress, SolveProgressSink};
use crate::Error;

/// How often the watcher looks at the clock and the caller's flag: a deadline or a signal
/// reaches the solver within this (plus the solver's own check interval).
const WATCH_INTERVAL: Duration = Duration::from_millis(50);

const TRIPPED_NONE: u8 = 0;
const TRIPPED_TIME: u8 = 1;
const TRIPPED_EQUILIBRIA: u8 = 2;
const NO_STAGE: u8 = u8::MAX;

/// The stages in the order of their codes in [`Shared::stage`].
const STAGES: [RunStage; 5] = [
    RunStage::LoadingScan,
    RunStage::Ingest,
    RunStage::Solving,
    RunStage::WritingFrames,
    RunStage::Finishing,
];

/// What the run, the watcher and the solving thread share.
struct Shared {
    limits: BudgetConfig,
    started: Instant,
    /// The flag the solves check.
    flag: CancelFlag,
    /// The caller's own flag, forwarded to `flag`.
    caller: Option<CancelFlag>,
    /// Which budget raised `flag`, if one did.
    tripped: AtomicU8,
    /// Equilibria reached.
    equilibria: AtomicUsize,
    /// Volume change of the last equilibrium, f64 bits (NaN before the first).
    volume_bits: AtomicU64,
    /// Code of the stage under way.
    stage: AtomicU8,
    /// The run has ended: the watcher stops.
    done: AtomicBool,
}

impl Shared {
    fn trip(&self, kind: u8) {
        // The first budget reached is the one reported.
        let _ =
            self.tripped
                .compare_exchange(TRIPPED_NONE, kind, Ordering::SeqCst, Ordering::SeqCst);
        self.flag.store(true, Ordering::SeqCst);
    }

    fn out_of_time(&self) -> bool {
        self.started.elapsed().as_secs_f64() >= self.limits.time_s
    }

    /// Looks at the clock and the caller's flag once.
    fn watch_once(&self) {
        if self.out_of_time() {
            self.trip(TRIPPED_TIME);
        }
        if self
            .caller
            .as_ref()
            .is_some_and(|c| c.load(Ordering::SeqCst))
        {
            self.flag.store(true, Ordering::SeqCst);
        }
    }
}

/// A run's observer with the run's budgets enforced on top of it.
pub(crate) struct Budgeted<'o> {
    inner: &'o mut dyn RunObserver,
    shared: Arc<Shared>,
    watcher: Option<JoinHandle<()>>,
    /// The trace's volume change farthest from the scan, mL, for the message.
    target_ml: Option<f64>,
}

impl<'o> Budgeted<'o> {
    /// Starts the clock of `limits` now, watching it (and `inner`'s cancel flag) on a thread.
    pub(crate) fn new(
        inner: &'o mut dyn RunObserver,
        limits: BudgetConfig,
        target_ml: Option<f64>,
    ) -> Self {
        let shared = Arc::new(Shared {
            limits,
            started: Instant::now(),
            flag: CancelFlag::default(),
            caller: inner.cancel_flag(),
            tripped: AtomicU8::new(TRIPPED_NONE),
            equilibria: AtomicUsize::new(0),
            volume_bits: AtomicU64::new(f64::NAN.to_bits()),
            stage: AtomicU8::new(NO_STAGE),
            done: AtomicBool::new(false),
        });
        let watched = shared.clone();
        // Without a watcher the deadline is still checked between stages and frames.
        let watcher = std::thread::Builder::new()
            .name("lungmotion-budget".into())
            .spawn(move || {
                while !watched.done.load(Ordering::SeqCst) {
                    watched.watch_once();
                    std::thread::park_timeout(WATCH_INTERVAL);
                }
            })
            .map_err(|e| tracing::warn!("cannot start the budget watcher: {e}"))
            .ok();
        Budgeted {
            inner,
            shared,
            watcher,
            target_ml,
        }
    }

    /// Seconds since the run started.
    pub(crate) fn elapsed_s(&self) -> f64 {
        self.shared.started.elapsed().as_secs_f64()
    }

    /// Equilibria reached so far.
    pub(crate) fn equilibria(&self) -> usize {
        self.shared.equilibria.load(Ordering::SeqCst)
    }

    /// The run's error as the budget explains it: a stop that a budget caused becomes
    /// [`Error::BudgetExceeded`]; anything else is returned as it is.
    pub(crate) fn explain(&self, error: Error) -> Error {
        let kind = match self.shared.tripped.load(Ordering::SeqCst) {
            TRIPPED_TIME => BudgetKind::Time,
            TRIPPED_EQUILIBRIA => BudgetKind::Equilibria,
            _ => return error,
        };
        // A solve cut short by the flag surfaces as a cancellation; a signal that came
        // after the budget does too, and the budget came first.
        let Error::Cancelled(_) = error else {
            return error;
        };
        let (limit, used) = match kind {
            BudgetKind::Time => (self.shared.limits.time_s, self.elapsed_s()),
            BudgetKind::Equilibria => (
                self.shared.limits.max_equilibria as f64,
                self.equilibria() as f64,
            ),
        };
        let stage = STAGES
            .get(usize::from(self.shared.stage.load(Ordering::SeqCst)))
            .map_or("starting", |s| s.label());
        let volume = f64::from_bits(self.shared.volume_bits.load(Ordering::SeqCst));
        Error::BudgetExceeded(Box::new(BudgetStop {
            budget: kind,
            limit,
            used,
            stage: stage.to_string(),
            equilibria: self.equilibria(),
            volume_reached_ml: volume.is_finite().then_some(volume),
            target_ml: self.target_ml,
        }))
    }
}

impl Drop for Budgeted<'_> {
    fn drop(&mut self) {
        self.shared.done.store(true, Ordering::SeqCst);
        if let Some(watcher) = self.watcher.take() {
            watcher.thread().unpark();
            let _ = watcher.join();
        }
    }
}

impl RunObserver for Budgeted<'_> {
    fn stage(&mut self, stage: RunStage) {
        let code = STAGES.iter().position(|s| *s == stage).unwrap_or(0);
        self.shared.stage.store(code as u8, Ordering::SeqCst);
        self.inner.stage(stage);
    }

    fn frame_written(&mut self, done: usize, total: usize) {
        self.inner.frame_written(done, total);
    }

    fn cancelled(&self) -> bool {
        if self.shared.out_of_time() {
            self.shared.trip(TRIPPED_TIME);
        }
        // The equilibrium budget only stops solves: frames of solves that stayed within it
        // are written.
        let stopped_by_time = self.shared.flag.load(Ordering::SeqCst)
            && self.shared.tripped.load(Ordering::SeqCst) != TRIPPED_EQUILIBRIA;
        self.inner.cancelled() || stopped_by_time
    }

    fn cancel_flag(&self) -> Option<CancelFlag> {
        Some(self.shared.flag.clone())
    }

    fn solve_progress(&self) -> Option<SolveProgressSink> {
        let shared = self.shared.clone();
        let inner = self.inner.solve_progress();
        Some(SolveProgressSink(Arc::new(move |p: SolveProgress| {
            let reached = shared.equilibria.fetch_add(1, Ordering::SeqCst) + 1;
            shared
                .volume_bits
                .store(p.volume_change_ml.to_bits(), Ordering::SeqCst);
            if reached as i64 >= shared.limits.max_equilibria {
                // The next solve, if the run needs one, stops before it starts.
                shared.trip(TRIPPED_EQUILIBRIA);
            }
            if let Some(sink) = &inner {
                (sink.0)(p);
            }
        })))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::SilentObserver;

    fn limits(time_s: f64, max_equilibria: i64) -> BudgetConfig {
        BudgetConfig {
            time_s,
            max_equilibria,
        }
    }

    #[test]
    fn reaching_the_last_equilibrium_raises_the_solver_flag_but_not_the_run_cancel() {
        let mut silent = SilentObserver;
        let b = Budgeted::new(&mut silent, limits(3600.0, 2), Some(500.0));
        let flag = b.cancel_flag().unwrap();
        let sink = b.solve_progress().unwrap();
        let at = |v| SolveProgress {
            equilibria: 0,
            volume_change_ml: v,
        };
        (sink.0)(at(100.0));
        assert!(!flag.load(Ordering::SeqCst));
        (sink.0)(at(210.0));
        assert!(flag.load(Ordering::SeqCst));
        assert!(
            !b.cancelled(),
            "frames of solves within the budget are written"
        );
        let Error::BudgetExceeded(stop) = b.explain(Error::Cancelled("stopped".into())) else {
            panic!("not a budget error");
        };
        assert_eq!(stop.budget, BudgetKind::Equilibria);
        assert_eq!((stop.limit, stop.used, stop.equilibria), (2.0, 2.0, 2));
        assert_eq!(stop.volume_reached_ml, Some(210.0));
        let text = stop.to_string();
        assert!(text.contains("max_equilibria"), "{text}");
        assert!(text.contains("+210 mL of the +500 mL"), "{text}");
        // Only a stop surfaces as the budget; other failures keep their own error.
        assert!(matches!(
            b.explain(Error::External("x".into())),
            Error::External(_)
        ));
    }

    #[test]
    fn a_passed_deadline_cancels_the_run_and_a_caller_flag_is_forwarded_without_a_reason() {
        let mut silent = SilentObserver;
        let b = Budgeted::new(&mut silent, limits(0.0, 10), None);
        assert!(b.cancelled());
        assert!(b.cancel_flag().unwrap().load(Ordering::SeqCst));
        let e = b.explain(Error::Cancelled("stopped before the solves".into()));
        assert!(
            matches!(&e, Error::BudgetExceeded(s) if s.budget == BudgetKind::Time),
            "{e:?}"
        );
        drop(b);

        struct Flagged(CancelFlag);
        impl RunObserver for Flagged {
            fn cancel_flag(&self) -> Option<CancelFlag> {
                Some(self.0.clone())
            }
        }
        let caller = CancelFlag::default();
        let mut observer = Flagged(caller.clone());
        let b = Budgeted::new(&mut observer, limits(3600.0, 10), None);
        let flag = b.cancel_flag().unwrap();
        caller.store(true, Ordering::SeqCst);
        // The watcher forwards it within its interval (no time asserted: waits as needed).
        while !flag.load(Ordering::SeqCst) {
            std::thread::sleep(WATCH_INTERVAL);
        }
        assert!(matches!(
            b.explain(Error::Cancelled("signal".into())),
            Error::Cancelled(_)
        ));
    }
}

//! A running job's progress, carried from the run's observer callbacks (stages, equilibria,
//! frames) into its record, with the time left estimated once frames are being written.
//!
//! The record is updated in memory at every callback (a `GET /v1/jobs/{id}` reads it there)
//! and written to the store at each stage, so a restart finds the stage a job had reached.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Instant;

use super::records::Records;
use super::store::JobRecord;
use crate::run::{RunObserver, RunStage};
use crate::simulation::{CancelFlag, SolveProgress, SolveProgressSink};

/// Equilibria after which the solving stage's fraction is half-way: the number of key
/// volumes is not known in advance (the solver refines until the interpolation is within
/// tolerance), so each equilibrium closes part of the remaining gap instead.
const HALF_WAY_EQUILIBRIA: f64 = 8.0;

/// Where each stage starts in the progress fraction (solving dominates).
pub(super) fn stage_start(stage: RunStage) -> f64 {
    match stage {
        RunStage::LoadingScan => 0.0,
        RunStage::Ingest => 0.05,
        RunStage::Solving => 0.15,
        RunStage::WritingFrames => 0.7,
        RunStage::Finishing => 0.95,
    }
}

/// The stage's name as the API gives it.
pub(super) fn stage_name(stage: RunStage) -> &'static str {
    match stage {
        RunStage::LoadingScan => "loading_scan",
        RunStage::Ingest => "ingest",
        RunStage::Solving => "solving",
        RunStage::WritingFrames => "writing_frames",
        RunStage::Finishing => "finishing",
    }
}

/// The solving stage's fraction after `equilibria`: rises toward the start of frame writing
/// and never reaches it.
fn solving_fraction(equilibria: usize) -> f64 {
    let n = equilibria as f64;
    let (a, b) = (
        stage_start(RunStage::Solving),
        stage_start(RunStage::WritingFrames),
    );
    a + (b - a) * n / (n + HALF_WAY_EQUILIBRIA)
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// Carries a run's progress into the job record and the job's stop flag into the run.
pub(super) struct JobObserver<'a> {
    store: &'a dyn Records,
    record: Arc<Mutex<JobRecord>>,
    stop: CancelFlag,
    started: Instant,
    frames_started: Option<Instant>,
}

impl<'a> JobObserver<'a> {
    /// An observer of the run of the job whose live record is `record`, stopped by `stop`.
    pub(super) fn new(
        store: &'a dyn Records,
        record: Arc<Mutex<JobRecord>>,
        stop: CancelFlag,
    ) -> Self {
        JobObserver {
            store,
            record,
            stop,
            started: Instant::now(),
            frames_started: None,
        }
    }
}

impl RunObserver for JobObserver<'_> {
    fn stage(&mut self, stage: RunStage) {
        if stage == RunStage::WritingFrames {
            self.frames_started = Some(Instant::now());
        }
        let mut record = lock(&self.record);
        let progress = &mut record.progress;
        progress.stage = Some(stage_name(stage).to_string());
        progress.stage_label = Some(stage.label().to_string());
        // Never backwards: with every frame solved, frames are written during the solves.
        progress.fraction = progress.fraction.max(stage_start(stage));
        progress.elapsed_s = Some(self.started.elapsed().as_secs_f64());
        if let Err(e) = self.store.save_job(&record) {
            tracing::warn!(job = %record.job_id, "cannot record progress: {e}");
        }
    }

    fn frame_written(&mut self, done: usize, total: usize) {
        let mut record = lock(&self.record);
        let progress = &mut record.progress;
        progress.frames_written = done;
        progress.frames_total = Some(total);
        let (a, b) = (
            stage_start(RunStage::WritingFrames),
            stage_start(RunStage::Finishing),
        );
        progress.fraction = progress
            .fraction
            .max(a + (b - a) * done as f64 / total.max(1) as f64);
        progress.elapsed_s = Some(self.started.elapsed().as_secs_f64());
        if let Some(since) = self.frames_started {
            let per_frame_s = since.elapsed().as_secs_f64() / done.max(1) as f64;
            progress.seconds_left = Some(per_frame_s * total.saturating_sub(done) as f64);
        }
    }

    fn cancelled(&self) -> bool {
        self.stop.load(std::sync::atomic::Ordering::SeqCst)
    }

    fn cancel_flag(&self) -> Option<CancelFlag> {
        Some(self.stop.clone())
    }

    fn solve_progress(&self) -> Option<SolveProgressSink> {
        let record = self.record.clone();
        let started = self.started;
        Some(SolveProgressSink(Arc::new(move |p: SolveProgress| {
            let mut record = lock(&record);
            let progress = &mut record.progress;
            progress.equilibria = p.equilibria;
            progress.volume_change_ml = Some(p.volume_change_ml);
            progress.elapsed_s = Some(started.elapsed().as_secs_f64());
            if progress.stage.as_deref() == Some(stage_name(RunStage::Solving)) {
                progress.fraction = progress.fraction.max(solving_fraction(p.equilibria));
            }
        })))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_solving_fraction_rises_with_each_equilibrium_and_stays_below_frame_writing() {
        let mut last = stage_start(RunStage::Solving);
        for n in 1..1000 {
            let f = solving_fraction(n);
            assert!(f > last, "equilibrium {n}: {f} after {last}");
            assert!(f < stage_start(RunStage::WritingFrames));
            last = f;
        }
        assert!((solving_fraction(8) - 0.425).abs() < 1e-12);
    }
}

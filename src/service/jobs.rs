//! Simulation jobs: a bounded queue in front of a fixed pool of worker threads, with every
//! change of state written to the store before it is acted on, so that a job survives a
//! crash or restart: queued jobs run after the restart, a job found `running` (the server
//! stopped during it) is re-run until `max_attempts` runs have started, then failed with
//! the reason.
//!
//! Workers are OS threads, not tokio tasks: a run is seconds of CPU work (itself parallel
//! with rayon) that must not stall the HTTP reactor. Cost model: one run at a time per
//! worker, memory per run as `lungmotion run` (≈ 60 MiB at 8 mm, ≈ 300 MiB at 4 mm).

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::callbacks::{CallbackDelivery, CallbackState};
use super::ids::{JobId, ScanId};
use super::ingest_cache::{IngestCache, IngestKey};
use super::pacs_jobs::PacsAccess;
use super::progress::JobObserver;
use super::records::Records;
use super::store::{
    now_rfc3339, JobProgress, JobRecord, JobRequest, JobState, PacsActivity, PacsSeries, Store,
};
use super::targets::{JobTarget, TargetChoice};
use crate::breathing::BreathingTrace;
use crate::run::{run_breathing_on, IngestedScan, RunInputs, RunObserver};
use crate::simulation::CancelFlag;
use crate::{Error, IoContext, IoOp, Result};

/// Why a submission was refused.
#[derive(Debug, Clone, PartialEq)]
pub enum SubmitRefusal {
    /// `queue_capacity` jobs are waiting; retry after about this many seconds.
    QueueFull {
        /// Jobs waiting.
        queued: usize,
        /// Suggested wait, s.
        retry_after_s: u64,
    },
    /// The server is shutting down.
    ShuttingDown,
    /// The scan was deleted (by a client or retention) since the request was read.
    ScanMissing,
}

/// What removing a scan that no live job uses came to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScanRemoval {
    /// It and its files are gone.
    Removed,
    /// A queued, running or cancelling job uses it; nothing was removed.
    InUse,
    /// There was no such scan.
    Missing,
}

/// Ids of jobs that ended with a completion callback to deliver (see [`super::callbacks`]).
pub type FinishedJobs = tokio::sync::mpsc::UnboundedSender<JobId>;

/// What a client's cancellation did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CancelOutcome {
    /// The job was waiting and is now cancelled.
    Cancelled,
    /// The job is running and is now `cancelling`: the solver stops at its next Newton or
    /// Krylov iteration (or the run at its next frame or stage), then it is `cancelled`.
    Requested,
    /// The job had already finished.
    AlreadyFinished,
}

/// Counts of jobs by state, and the queue, for readiness and metrics.
#[derive(Debug, Clone, Default)]
pub struct JobCounts {
    /// Jobs known, by state.
    pub by_state: [usize; 6],
    /// Jobs waiting for a worker.
    pub queued: usize,
    /// Jobs running.
    pub running: usize,
    /// With PostgreSQL, the worker processes that reported lately, with their counts.
    pub workers: Vec<super::postgres::WorkerStatus>,
}

/// Runs whose wall times estimate `Retry-After` (the latest; the server may run for months).
const RECENT_RUNS: usize = 64;

/// How long shutdown waits for cancelled runs to reach a stopping point.
const SHUTDOWN_JOIN_LIMIT: Duration = Duration::from_secs(60);

const CANCEL_NONE: u8 = 0;
const CANCEL_CLIENT: u8 = 1;
const CANCEL_SHUTDOWN: u8 = 2;
/// A PostgreSQL worker's lease was taken back: another worker runs the job now, so this run
/// stops and writes nothing.
const CANCEL_LEASE_LOST: u8 = 3;

/// A job the server knows of: its record (shared with the run's progress callbacks), and
/// while it runs the flag that stops it (seen by the run's stages, frames and the solver's
/// iterations) and why it was raised.
struct LiveJob {
    record: Arc<Mutex<JobRecord>>,
    stop: CancelFlag,
    cancel: AtomicU8,
}

impl LiveJob {
    fn new(record: JobRecord) -> Arc<Self> {
        Arc::new(LiveJob {
            record: Arc::new(Mutex::new(record)),
            stop: CancelFlag::default(),
            cancel: AtomicU8::new(CANCEL_NONE),
        })
    }

    fn request_stop(&self, reason: u8) {
        self.cancel.store(reason, Ordering::SeqCst);
        self.stop.store(true, Ordering::SeqCst);
    }
}

struct Board {
    jobs: HashMap<JobId, Arc<LiveJob>>,
    queue: VecDeque<JobId>,
    running: usize,
    shutting_down: bool,
    /// Wall times of the latest runs, s (at most `RECENT_RUNS`), for `Retry-After`.
    run_times_s: VecDeque<f64>,
}

pub(super) struct Shared {
    /// The data directory: uploads, targets and outputs.
    store: Store,
    /// The job and scan records.
    records: Arc<dyn Records>,
    board: Mutex<Board>,
    changed: Condvar,
    queue_capacity: usize,
    workers: usize,
    ingests: Arc<IngestCache>,
    /// Where ended jobs with a callback are announced; none in a PostgreSQL worker.
    finished: Option<FinishedJobs>,
    pacs: Option<PacsAccess>,
}

impl Shared {
    /// Hands a job whose callback became pending to the deliveries (after its record is saved).
    fn announce_finished(&self, id: JobId) {
        let Some(finished) = &self.finished else {
            // A PostgreSQL worker: the job's row says the callback is due.
            return;
        };
        if finished.send(id).is_err() {
            tracing::warn!(job = %id, "no callback delivery running; the callback is sent after the next start");
        }
    }
}

/// Moves a job's callback from `waiting` to `pending` as the job ends; whether it did (the
/// caller then announces it once the record is saved).
pub(super) fn begin_callback(record: &mut JobRecord) -> bool {
    match &mut record.callback {
        Some(c) if c.state == CallbackState::Waiting && record.state.is_terminal() => {
            c.state = CallbackState::Pending;
            true
        }
        _ => false,
    }
}

/// The job queue and its workers.
#[derive(Clone)]
pub struct JobManager {
    shared: Arc<Shared>,
}

/// The worker threads, to join at shutdown.
pub struct Workers {
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl JobManager {
    /// Recovers the jobs in `records` (their files in `store`; see the module doc) and starts `workers` threads, which
    /// keep the scans they ingest in `ingests` and reach the PACS through `pacs`; jobs with a
    /// callback to deliver (ended now or left pending by an earlier process) are announced on
    /// `finished`.
    pub fn start(
        (store, records): (Store, Arc<dyn Records>),
        workers: usize,
        queue_capacity: usize,
        max_attempts: u32,
        ingests: Arc<IngestCache>,
        finished: FinishedJobs,
        pacs: Option<PacsAccess>,
    ) -> Result<(Self, Workers)> {
        let (stored, problems) = records.list_jobs()?;
        for p in problems {
            tracing::warn!("store: {p}");
        }
        let mut board = Board {
            jobs: HashMap::new(),
            queue: VecDeque::new(),
            running: 0,
            shutting_down: false,
            run_times_s: VecDeque::new(),
        };
        for mut record in stored {
            // No run of this process has started yet, so every partial output directory is
            // a leftover of a process that was killed (its pid may even be ours again, as in
            // a container where the server is always the same pid).
            match store.clear_partial_outputs(record.job_id) {
                Ok(0) => {}
                Ok(n) => {
                    tracing::info!(job = %record.job_id, removed = n, "partial outputs of an interrupted run removed")
                }
                Err(e) => {
                    tracing::warn!(job = %record.job_id, "cannot remove partial outputs: {e}")
                }
            }
            match recover(&mut record, max_attempts, "the server") {
                Recovery::Unchanged if record.state == JobState::Queued => {
                    board.queue.push_back(record.job_id)
                }
                Recovery::Unchanged => {}
                Recovery::Failed => {
                    records.save_job(&record)?;
                    tracing::warn!(job = %record.job_id, "interrupted too often, failed");
                }
                Recovery::Cancelled => records.save_job(&record)?,
                Recovery::Queued => {
                    records.save_job(&record)?;
                    board.queue.push_back(record.job_id);
                    tracing::warn!(job = %record.job_id, "was running when the server stopped; re-queued");
                }
            }
            if begin_callback(&mut record) {
                records.save_job(&record)?;
            }
            if record
                .callback
                .as_ref()
                .is_some_and(|c| c.state == CallbackState::Pending)
            {
                let _ = finished.send(record.job_id);
            }
            board.jobs.insert(record.job_id, LiveJob::new(record));
        }
        if !board.queue.is_empty() {
            tracing::info!(queued = board.queue.len(), "jobs recovered from the store");
        }
        let shared = Arc::new(Shared {
            store,
            records,
            board: Mutex::new(board),
            changed: Condvar::new(),
            queue_capacity,
            workers,
            ingests,
            finished: Some(finished),
            pacs,
        });
        let threads = (0..workers)
            .map(|i| {
                let shared = shared.clone();
                let name = format!("lungmotion-worker-{i}");
                std::thread::Builder::new()
                    .name(name.clone())
                    .spawn(move || worker_loop(&shared))
                    .at(IoOp::Spawn, name)
            })
            .collect::<Result<Vec<_>>>()?;
        Ok((JobManager { shared }, Workers { threads }))
    }

    fn board(&self) -> MutexGuard<'_, Board> {
        self.shared
            .board
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// Stores and queues a job, or refuses it when the queue is full or the server stops. A
    /// job whose CT comes from the PACS gets `scan_id` for the scan its series becomes; a job
    /// following a target uploaded to the scan stores its own copy of the file `target`.
    pub fn submit(
        &self,
        scan_id: ScanId,
        request: &JobRequest,
        target: Option<&std::path::Path>,
    ) -> Result<std::result::Result<JobRecord, SubmitRefusal>> {
        let mut board = self.board();
        if board.shutting_down {
            return Ok(Err(SubmitRefusal::ShuttingDown));
        }
        if board.queue.len() >= self.shared.queue_capacity {
            let queued = board.queue.len();
            return Ok(Err(SubmitRefusal::QueueFull {
                queued,
                retry_after_s: self.retry_after_s(&board),
            }));
        }
        // Under the board's lock, as scans are removed, so a job never waits for a scan that
        // is already gone.
        if request.pacs_ct.is_none() && self.shared.records.scan(scan_id)?.is_none() {
            return Ok(Err(SubmitRefusal::ScanMissing));
        }
        let pacs_server = self
            .shared
            .pacs
            .as_ref()
            .map(|p| p.settings.root_url.as_str());
        let record = queued_record(scan_id, request, pacs_server);
        // On disk before it is acknowledged: an accepted job is never lost.
        self.shared.records.put_job(&record, request, target)?;
        board
            .jobs
            .insert(record.job_id, LiveJob::new(record.clone()));
        board.queue.push_back(record.job_id);
        drop(board);
        self.shared.changed.notify_all();
        Ok(Ok(record))
    }

    /// Seconds a refused client should wait: the median run time spread over the workers.
    fn retry_after_s(&self, board: &Board) -> u64 {
        let mut times: Vec<f64> = board.run_times_s.iter().copied().collect();
        times.sort_by(f64::total_cmp);
        let typical = times.get(times.len() / 2).copied().unwrap_or(10.0);
        (typical / self.shared.workers as f64)
            .ceil()
            .clamp(1.0, 600.0) as u64
    }

    /// A job's current record.
    pub fn status(&self, id: JobId) -> Option<JobRecord> {
        let live = self.board().jobs.get(&id).cloned()?;
        let record = lock(&live.record).clone();
        Some(record)
    }

    /// Cancels a queued or running job; `None` for an unknown job.
    pub fn cancel(&self, id: JobId) -> Result<Option<CancelOutcome>> {
        let mut board = self.board();
        let Some(live) = board.jobs.get(&id).cloned() else {
            return Ok(None);
        };
        let mut record = lock(&live.record);
        match record.state {
            JobState::Queued => {
                board.queue.retain(|q| *q != id);
                record.state = JobState::Cancelled;
                record.error = Some("cancelled by a client before it ran".into());
                record.finished_at = Some(now_rfc3339());
                let announce = begin_callback(&mut record);
                self.shared.records.save_job(&record)?;
                if announce {
                    self.shared.announce_finished(id);
                }
                Ok(Some(CancelOutcome::Cancelled))
            }
            JobState::Running => {
                // Visible (and on disk) before the flag is raised, so a client polling after
                // its DELETE sees `cancelling`, never `running`.
                record.state = JobState::Cancelling;
                self.shared.records.save_job(&record)?;
                live.request_stop(CANCEL_CLIENT);
                tracing::info!(job = %id, "cancellation requested; the run stops at its next check");
                Ok(Some(CancelOutcome::Requested))
            }
            JobState::Cancelling => Ok(Some(CancelOutcome::Requested)),
            _ => Ok(Some(CancelOutcome::AlreadyFinished)),
        }
    }

    /// Removes a finished job and its outputs; `Ok(false)` when it is not finished.
    pub fn remove(&self, id: JobId) -> Result<bool> {
        let mut board = self.board();
        let finished = board
            .jobs
            .get(&id)
            .is_some_and(|j| lock(&j.record).state.is_terminal());
        if !finished {
            return Ok(false);
        }
        board.jobs.remove(&id);
        self.shared.records.delete_job(id)?;
        Ok(true)
    }

    /// Every job's record now, for retention.
    pub fn records(&self) -> Vec<JobRecord> {
        let board = self.board();
        board
            .jobs
            .values()
            .map(|live| lock(&live.record).clone())
            .collect()
    }

    /// Removes a finished job for retention, unless a client or its callback still acts on it
    /// (not finished, or a callback `pending`); whether it was removed.
    pub fn remove_expired(&self, id: JobId) -> Result<bool> {
        let mut board = self.board();
        let removable = board.jobs.get(&id).is_some_and(|j| {
            let r = lock(&j.record);
            r.state.is_terminal()
                && !r
                    .callback
                    .as_ref()
                    .is_some_and(|c| c.state == CallbackState::Pending)
        });
        if !removable {
            return Ok(false);
        }
        board.jobs.remove(&id);
        self.shared.records.delete_job(id)?;
        Ok(true)
    }

    /// Removes a scan and its files unless a queued, running or cancelling job uses it,
    /// decided under the board's lock so no job is submitted for it meanwhile.
    pub fn remove_unused_scan(&self, scan_id: ScanId) -> Result<ScanRemoval> {
        let board = self.board();
        let in_use = board.jobs.values().any(|j| {
            let r = lock(&j.record);
            r.scan_id == scan_id && !r.state.is_terminal()
        });
        if in_use {
            return Ok(ScanRemoval::InUse);
        }
        if !self.shared.records.delete_scan(scan_id)? {
            return Ok(ScanRemoval::Missing);
        }
        drop(board);
        self.shared.ingests.forget_scan(scan_id);
        Ok(ScanRemoval::Removed)
    }

    /// Changes a job's callback record (on disk too); `false` when the job is gone.
    pub fn update_callback(
        &self,
        id: JobId,
        change: impl FnOnce(&mut CallbackDelivery),
    ) -> Result<bool> {
        let board = self.board();
        let Some(live) = board.jobs.get(&id).cloned() else {
            return Ok(false);
        };
        let mut record = lock(&live.record);
        let Some(callback) = record.callback.as_mut() else {
            return Ok(false);
        };
        change(callback);
        self.shared.records.save_job(&record)?;
        Ok(true)
    }

    /// Jobs by state and the queue.
    pub fn counts(&self) -> JobCounts {
        let board = self.board();
        let mut counts = JobCounts {
            queued: board.queue.len(),
            running: board.running,
            ..JobCounts::default()
        };
        for live in board.jobs.values() {
            let state = lock(&live.record).state;
            let i = JobState::ALL.iter().position(|s| *s == state).unwrap_or(0);
            counts.by_state[i] += 1;
        }
        counts
    }

    /// The scans jobs have read and ingested.
    pub fn ingest_cache(&self) -> &IngestCache {
        &self.shared.ingests
    }

    /// Whether shutdown has begun.
    pub fn shutting_down(&self) -> bool {
        self.board().shutting_down
    }

    /// Refuses new jobs from now on (running ones go on).
    pub fn begin_shutdown(&self) {
        self.board().shutting_down = true;
    }

    /// Stops taking jobs, waits up to `grace` for running ones, then stops them and puts them
    /// back in the queue on disk (they run after the next start), and joins the workers.
    pub fn shutdown(&self, workers: Workers, grace: Duration) {
        let mut board = self.board();
        board.shutting_down = true;
        self.shared.changed.notify_all();
        let board = wait_for_running_jobs(&self.shared, board, grace);
        if board.running > 0 {
            tracing::info!(
                running = board.running,
                "grace period over; stopping running jobs and re-queueing them"
            );
            for live in board.jobs.values() {
                if lock(&live.record).state == JobState::Running {
                    live.request_stop(CANCEL_SHUTDOWN);
                }
            }
        }
        drop(board);
        // A run checks for cancellation between stages and frames, before each DICOM slice,
        // between and inside the ingest's steps and in every Newton and Krylov iteration; a
        // worker still busy after this is left behind, and its job, still `running` on disk,
        // is re-run at the next start.
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for t in workers.threads {
                let _ = t.join();
            }
            let _ = done_tx.send(());
        });
        if done_rx.recv_timeout(SHUTDOWN_JOIN_LIMIT).is_err() {
            tracing::warn!("a worker did not stop in time; its job runs again after the restart");
        }
    }
}

/// What [`recover`] did to a job found unfinished by a new process (or with an expired lease).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Recovery {
    /// Nothing: it was queued or finished.
    Unchanged,
    /// It was running and goes back to the queue (the run counted as an attempt).
    Queued,
    /// It was running and had used its `max_attempts` runs.
    Failed,
    /// A client had asked for its cancellation.
    Cancelled,
}

/// Decides the fate of a job whose run was interrupted because `who` (`the server`, a worker)
/// stopped: run again until `max_attempts` runs have started, then failed; a `cancelling` job
/// is cancelled, since the client's wish stands.
pub(super) fn recover(record: &mut JobRecord, max_attempts: u32, who: &str) -> Recovery {
    let started = record
        .started_at
        .clone()
        .unwrap_or_else(|| "at an unknown time".into());
    match record.state {
        JobState::Running if record.attempts >= max_attempts => {
            record.state = JobState::Failed;
            record.error = Some(format!(
                "{who} stopped during each of this job's {} runs (last started {started}); not \
                 retried",
                record.attempts,
            ));
            record.finished_at = Some(now_rfc3339());
            Recovery::Failed
        }
        JobState::Cancelling => {
            record.state = JobState::Cancelled;
            record.error = Some(format!(
                "cancelled by a client while running ({who} stopped before the run did)"
            ));
            record.finished_at = Some(now_rfc3339());
            Recovery::Cancelled
        }
        JobState::Running => {
            record.state = JobState::Queued;
            record.progress = JobProgress::default();
            record.error = Some(format!(
                "{who} stopped during run {} (started {started}); queued to run again",
                record.attempts,
            ));
            Recovery::Queued
        }
        _ => Recovery::Unchanged,
    }
}

/// Marks a job taken by a worker: running, one attempt more, its progress reset.
pub(super) fn mark_running(record: &mut JobRecord) {
    record.state = JobState::Running;
    record.attempts += 1;
    record.started_at = Some(now_rfc3339());
    record.progress = JobProgress {
        frames_total: record.progress.frames_total,
        ..JobProgress::default()
    };
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

fn worker_loop(shared: &Shared) {
    loop {
        let live = {
            let mut board = lock(&shared.board);
            loop {
                if board.shutting_down {
                    return;
                }
                if let Some(id) = board.queue.pop_front() {
                    let Some(live) = board.jobs.get(&id).cloned() else {
                        continue;
                    };
                    // Marked running under the board's lock, so a cancellation sees either
                    // a queued job it can drop or a running one it must stop, never both.
                    let mut record = lock(&live.record);
                    if record.state != JobState::Queued {
                        continue;
                    }
                    mark_running(&mut record);
                    drop(record);
                    board.running += 1;
                    break live;
                }
                board = shared
                    .changed
                    .wait(board)
                    .unwrap_or_else(|p| p.into_inner());
            }
        };
        let started = Instant::now();
        run_job(shared, &live);
        let mut board = lock(&shared.board);
        board.running -= 1;
        if board.run_times_s.len() == RECENT_RUNS {
            board.run_times_s.pop_front();
        }
        board.run_times_s.push_back(started.elapsed().as_secs_f64());
        drop(board);
        shared.changed.notify_all();
    }
}

/// Runs one job, already marked running, to a final state (or back to `queued` when the
/// server stops).
fn run_job(shared: &Shared, live: &LiveJob) {
    let (id, scan_id) = {
        let record = lock(&live.record);
        if let Err(e) = shared.records.save_job(&record) {
            tracing::error!(job = %record.job_id, "cannot record the start: {e}");
        }
        (record.job_id, record.scan_id)
    };
    tracing::info!(job = %id, "run started");
    let started = Instant::now();
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        execute(shared, id, scan_id, live)
    }))
    .unwrap_or_else(|panic| {
        let what = panic
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "unknown panic".into());
        Err(Error::InvalidModel(format!("internal error: {what}")))
    });
    if live.cancel.load(Ordering::SeqCst) == CANCEL_LEASE_LOST {
        // Its files and record are another worker's now.
        tracing::warn!(job = %id, "lease lost during the run; stopped, nothing written");
        return;
    }
    let cancelled_by_client = live.cancel.load(Ordering::SeqCst) == CANCEL_CLIENT;
    let mut record = lock(&live.record);
    match outcome {
        Ok(()) if cancelled_by_client => {
            // The run published its outputs before it saw the flag; the client asked for
            // none, and a cancelled job has none.
            if let Err(e) = shared.store.remove_job_output(id) {
                tracing::warn!(job = %id, "cannot remove the outputs of a cancelled job: {e}");
            }
            record.state = JobState::Cancelled;
            record.error = Some(
                "cancelled by a client while running (the run had just finished; its outputs \
                 were removed)"
                    .into(),
            );
        }
        Ok(()) => {
            record.state = JobState::Done;
            record.error = None;
            record.progress.fraction = 1.0;
            record.progress.stage = None;
            record.progress.stage_label = None;
            record.progress.seconds_left = Some(0.0);
        }
        Err(_) if cancelled_by_client => {
            // Whatever the stop surfaced as (a cancellation, or a solve cut short), the
            // client asked for it.
            record.state = JobState::Cancelled;
            record.error = Some("cancelled by a client while running".into());
        }
        Err(Error::Cancelled(_)) if live.cancel.load(Ordering::SeqCst) == CANCEL_SHUTDOWN => {
            // Not the job's fault: it runs again after the restart, without using an attempt.
            record.state = JobState::Queued;
            record.attempts -= 1;
            record.progress = JobProgress::default();
            record.error = Some("the server shut down during the run; queued to run again".into());
            let _ = shared.store.clear_partial_outputs(id);
        }
        Err(Error::Cancelled(_)) => {
            record.state = JobState::Cancelled;
            record.error = Some("cancelled while running".into());
        }
        Err(e) => {
            record.state = JobState::Failed;
            tracing::warn!(job = %id, "run failed: {e}");
            record.error = Some(client_message(e, shared.store.root()));
        }
    }
    if matches!(record.state, JobState::Failed | JobState::Cancelled) {
        // The run's staging directory removes itself when dropped; this covers a removal
        // that failed there, so a finished job never keeps half its outputs.
        if let Err(e) = shared.store.clear_partial_outputs(id) {
            tracing::warn!(job = %id, "cannot remove partial outputs: {e}");
        }
    }
    if record.state.is_terminal() {
        record.finished_at = Some(now_rfc3339());
    }
    let announce = begin_callback(&mut record);
    live.cancel.store(CANCEL_NONE, Ordering::SeqCst);
    live.stop.store(false, Ordering::SeqCst);
    if let Err(e) = shared.records.save_job(&record) {
        tracing::error!(job = %id, "cannot record the end: {e}");
    }
    if announce {
        shared.announce_finished(id);
    }
    tracing::info!(
        job = %id,
        state = record.state.name(),
        seconds = started.elapsed().as_secs_f64(),
        "run ended"
    );
}

/// A failed run's error as clients read it: paths relative to the store, not the server's file
/// system (from the path field; errors that carry a path only in their text are cut there).
fn client_message(e: Error, root: &std::path::Path) -> String {
    let e = e.with_path_shown_as(|p| match p.strip_prefix(root) {
        Ok(relative) => relative.to_path_buf(),
        Err(_) => p.file_name().map(Into::into).unwrap_or_default(),
    });
    e.to_string().replace(&format!("{}/", root.display()), "")
}

/// The record of a job just submitted for `request` on `scan_id`: its PACS activity when it
/// pulls or pushes through `pacs_server`, the frames it will write, a callback waiting.
pub(super) fn queued_record(
    scan_id: ScanId,
    request: &JobRequest,
    pacs_server: Option<&str>,
) -> JobRecord {
    let mut record = JobRecord::queued(scan_id);
    if let (true, Some(server)) = (request.pacs_ct.is_some() || request.push, pacs_server) {
        record.pacs = Some(PacsActivity {
            server: server.to_string(),
            ct: request.pacs_ct.clone(),
            push: request.push,
            ..PacsActivity::default()
        });
    }
    record.progress.frames_total = frames_total(request);
    if request.callback_url.is_some() {
        record.callback = Some(CallbackDelivery::waiting());
    }
    record
}

/// Frames a job will write, from its trace and output instants (none when they are unusable:
/// the run then fails saying why).
pub(super) fn frames_total(request: &JobRequest) -> Option<usize> {
    let trace = BreathingTrace::new(request.time_s.clone(), request.volume_ml.clone()).ok()?;
    let times = request
        .config
        .motion_settings()
        .instants
        .times(&trace)
        .ok()?;
    Some(times.len())
}

fn execute(shared: &Shared, id: JobId, scan_id: ScanId, live: &LiveJob) -> Result<()> {
    let request = shared.records.job_request(id)?;
    if let Some(series) = &request.pacs_ct {
        // A re-run finds the series it pulled before.
        if shared.records.scan(scan_id)?.is_none() {
            pull_ct(shared, scan_id, series, &request.config, live)?;
        }
    }
    let push = request.push;
    let scan = shared.records.scan(scan_id)?.ok_or_else(|| Error::Store {
        record: format!("scans/{scan_id}"),
        reason: "the scan was deleted before the job ran".into(),
    })?;
    shared.store.clear_partial_outputs(id)?;
    // Jobs queued by an older server have no count yet.
    let frames = frames_total(&request);
    lock(&live.record).progress.frames_total = frames;
    let JobRequest {
        config,
        time_s,
        volume_ml,
        trace_source,
        points,
        callback_url: _,
        target,
        pacs_ct: _,
        push: _,
    } = request;
    // The series the scan was ingested from, whatever the server's default is now.
    let config = crate::run::RunConfig {
        series: scan.series_or(config.series),
        ..config
    };
    // A worker on another machine than the upload's API process fetches it first, and holds
    // the copy until the run ends so that no eviction removes it under the run.
    let _copy = shared.store.ensure_scan_local(&scan)?;
    let _target_copy = match &target {
        Some(JobTarget::Upload(TargetChoice {
            file: Some(file), ..
        })) => Some(shared.store.ensure_job_target_local(id, file)?),
        _ => None,
    };
    let inputs = RunInputs {
        ct_path: shared.store.scan_file(&scan),
        trace: BreathingTrace::new(time_s, volume_ml)?,
        trace_source,
        points: points.iter().map(Into::into).collect(),
        target: target
            .map(|t| t.spec(&shared.store.job_target_dir(id)))
            .transpose()?,
    };
    let mut observer = JobObserver::new(&*shared.records, live.record.clone(), live.stop.clone());
    let (ingested, read_timings) = ingested_scan(shared, scan_id, &inputs, &config, &mut observer)?;
    run_breathing_on(
        &inputs,
        &config,
        &shared.store.job_output_dir(id),
        crate::run::Overwrite::SameCtOnly,
        &mut observer,
        Some((&ingested, read_timings)),
    )?;
    // With an object store the outputs go there; the local copy stays for the push only.
    if let Err(e) = shared.store.put_job_output_blobs(id) {
        shared.store.drop_local_job_output(id);
        return Err(e);
    }
    let pushed = if push {
        push_outputs(shared, id, live)
    } else {
        Ok(())
    };
    shared.store.drop_local_job_output(id);
    pushed
}

/// The PACS of the service, or the error of a job that needs one on a server that has none
/// any more (it was configured when the job was submitted).
fn pacs_of(shared: &Shared) -> Result<&PacsAccess> {
    shared.pacs.as_ref().ok_or_else(|| {
        Error::settings(
            "service configuration",
            "this job uses the PACS, but the server now has none configured ([pacs] url)",
        )
    })
}

/// Shows a PACS step as the job's stage.
fn show_stage(live: &LiveJob, stage: &str, label: &str) {
    let mut record = lock(&live.record);
    record.progress.stage = Some(stage.into());
    record.progress.stage_label = Some(label.into());
}

/// Pulls the job's CT series from the PACS and stores it as scan `scan_id`, recording the
/// series UID found.
fn pull_ct(
    shared: &Shared,
    scan_id: ScanId,
    series: &PacsSeries,
    config: &crate::run::RunConfig,
    live: &LiveJob,
) -> Result<()> {
    let pacs = pacs_of(shared)?;
    show_stage(live, "pulling_ct", "pulling the CT series from the PACS");
    let series_uid =
        pacs.import_series(&shared.store, &*shared.records, scan_id, series, config)?;
    let mut record = lock(&live.record);
    if let Some(activity) = record.pacs.as_mut() {
        activity.ct = Some(PacsSeries {
            study: series.study.clone(),
            series: Some(series_uid),
        });
    }
    shared.records.save_job(&record)
}

/// Pushes the job's DICOM outputs to the PACS and records what it stored.
fn push_outputs(shared: &Shared, id: JobId, live: &LiveJob) -> Result<()> {
    let pacs = pacs_of(shared)?;
    show_stage(live, "pushing", "pushing the DICOM outputs to the PACS");
    let report = match pacs.push_outputs(shared.store.job_output_dir(id)) {
        Ok(report) => report,
        Err(e) => {
            // The outputs are published: record that only the push failed, so they stay
            // downloadable.
            let mut record = lock(&live.record);
            if let Some(activity) = record.pacs.as_mut() {
                let root = format!("{}/", shared.store.root().display());
                activity.push_error = Some(e.to_string().replace(&root, ""));
            }
            shared.records.save_job(&record)?;
            return Err(e);
        }
    };
    tracing::info!(job = %id, stored = report.stored, already = report.already_stored, "outputs pushed to the PACS");
    let mut record = lock(&live.record);
    if let Some(activity) = record.pacs.as_mut() {
        activity.stored = Some(report.stored);
        activity.already_stored = Some(report.already_stored);
    }
    shared.records.save_job(&record)
}

/// The job's scan read and ingested with its settings: from the cache when an earlier job
/// did it (no wall times then), else read now, its ingest taken from the file its upload
/// stored when that was made with these settings or computed, and kept in the cache.
fn ingested_scan(
    shared: &Shared,
    scan_id: ScanId,
    inputs: &RunInputs,
    config: &crate::run::RunConfig,
    observer: &mut dyn RunObserver,
) -> Result<(Arc<IngestedScan>, std::collections::BTreeMap<String, f64>)> {
    let key = IngestKey::new(scan_id, config);
    if let Some(ingested) = shared.ingests.get(&key) {
        tracing::info!(scan = %scan_id, "ingest reused: the scan was read and ingested with these settings before");
        return Ok((ingested, Default::default()));
    }
    let mut timings = Default::default();
    let stored = shared.store.stored_ingest_file(scan_id);
    let (ingested, used_stored) = IngestedScan::read_using(
        &inputs.ct_path,
        config,
        Some(&stored),
        observer,
        &mut timings,
    )?;
    let ingested = Arc::new(ingested);
    if used_stored {
        tracing::info!(scan = %scan_id, "ingest taken from the scan's stored ingest");
        shared.ingests.insert_from_stored(key, ingested.clone());
    } else {
        shared.ingests.insert_ingested(key, ingested.clone());
    }
    Ok((ingested, timings))
}

/// Counts of a PostgreSQL worker process's jobs, reported to the database for the metrics.
#[derive(Debug, Default)]
pub(super) struct LeasedStats {
    pub(super) running: std::sync::atomic::AtomicI64,
    pub(super) done: std::sync::atomic::AtomicI64,
    pub(super) failed: std::sync::atomic::AtomicI64,
    pub(super) cancelled: std::sync::atomic::AtomicI64,
}

/// The state a PostgreSQL worker process's threads share: the files, its leased records,
/// the ingest cache and the PACS; its board holds only the jobs it runs now.
pub(super) fn leased_shared(
    store: Store,
    records: Arc<dyn Records>,
    workers: usize,
    ingests: Arc<IngestCache>,
    pacs: Option<PacsAccess>,
) -> Arc<Shared> {
    // With PostgreSQL a job's end makes its callback due in its row (see
    // [`super::postgres::Postgres::claim_callback`]); the API processes deliver it, so
    // nothing is announced here.
    let finished = None;
    Arc::new(Shared {
        store,
        records,
        board: Mutex::new(Board {
            jobs: HashMap::new(),
            queue: VecDeque::new(),
            running: 0,
            shutting_down: false,
            run_times_s: VecDeque::new(),
        }),
        changed: Condvar::new(),
        queue_capacity: 0,
        workers,
        ingests,
        finished,
        pacs,
    })
}

/// How often a PostgreSQL worker renews the lease of the job it runs, which also tells it of
/// a client's cancellation: a third of the lease, at most a second, so a DELETE reaches the run
/// within about a second.
fn renewal_interval(lease: Duration) -> Duration {
    (lease / 3).min(Duration::from_secs(1))
}

/// One simulation thread of `lungmotion worker`: takes jobs from the PostgreSQL queue as
/// `worker`, runs each with its lease renewed, until the process shuts down.
pub(super) fn leased_worker_loop(
    shared: &Shared,
    pg: &super::postgres::Postgres,
    worker: &str,
    stats: &LeasedStats,
) {
    use super::postgres::{Lease, POLL_INTERVAL};
    loop {
        if lock(&shared.board).shutting_down {
            return;
        }
        let record = match pg.claim(worker) {
            Ok(Some(record)) => record,
            Ok(None) => {
                pg.wait_for_work(POLL_INTERVAL);
                continue;
            }
            Err(e) => {
                tracing::warn!("taking a job: {e}; trying again");
                std::thread::sleep(POLL_INTERVAL);
                continue;
            }
        };
        let id = record.job_id;
        let live = LiveJob::new(record);
        {
            let mut board = lock(&shared.board);
            board.jobs.insert(id, live.clone());
            board.running += 1;
        }
        stats.running.fetch_add(1, Ordering::SeqCst);
        let (done_tx, done_rx) = std::sync::mpsc::channel::<()>();
        let renewer = {
            let live = live.clone();
            let pg = pg.clone();
            let worker = worker.to_string();
            std::thread::Builder::new()
                .name(format!("lungmotion-lease-{id}"))
                .spawn(move || loop {
                    match done_rx.recv_timeout(renewal_interval(pg.lease())) {
                        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                        _ => return,
                    }
                    match pg.renew(id, &worker) {
                        Ok(Lease::Held) => {}
                        Ok(Lease::Cancelling) => {
                            if live.cancel.load(Ordering::SeqCst) == CANCEL_NONE {
                                tracing::info!(job = %id, "cancellation requested; the run stops at its next check");
                                live.request_stop(CANCEL_CLIENT);
                            }
                        }
                        Ok(Lease::Lost) => {
                            live.request_stop(CANCEL_LEASE_LOST);
                            return;
                        }
                        // The reaper takes the job back if this lasts a whole lease; until
                        // then the run goes on.
                        Err(e) => tracing::warn!(job = %id, "cannot renew the lease: {e}"),
                    }
                })
        };
        run_job(shared, &live);
        drop(done_tx);
        if let Ok(renewer) = renewer {
            let _ = renewer.join();
        }
        let state = lock(&live.record).state;
        let counter = match state {
            JobState::Done => Some(&stats.done),
            JobState::Failed => Some(&stats.failed),
            JobState::Cancelled => Some(&stats.cancelled),
            _ => None,
        };
        if let Some(counter) = counter {
            counter.fetch_add(1, Ordering::SeqCst);
        }
        stats.running.fetch_sub(1, Ordering::SeqCst);
        let mut board = lock(&shared.board);
        board.jobs.remove(&id);
        board.running -= 1;
        drop(board);
        shared.changed.notify_all();
    }
}

/// Waits up to `grace` for the running jobs on `board` to end; the board, locked again.
fn wait_for_running_jobs<'a>(
    shared: &'a Shared,
    mut board: MutexGuard<'a, Board>,
    grace: Duration,
) -> MutexGuard<'a, Board> {
    let deadline = Instant::now() + grace;
    while board.running > 0 {
        let now = Instant::now();
        if now >= deadline {
            break;
        }
        board = shared
            .changed
            .wait_timeout(board, deadline - now)
            .unwrap_or_else(|p| p.into_inner())
            .0;
    }
    board
}

/// Stops a PostgreSQL worker process's threads: no new jobs, `grace` for the running ones,
/// then they stop and go back to the queue without using an attempt.
pub(super) fn stop_leased_workers(shared: &Shared, grace: Duration) {
    let mut board = lock(&shared.board);
    board.shutting_down = true;
    let mut board = wait_for_running_jobs(shared, board, grace);
    if board.running > 0 {
        tracing::info!(
            running = board.running,
            "grace period over; stopping running jobs and re-queueing them"
        );
        for live in board.jobs.values() {
            live.request_stop(CANCEL_SHUTDOWN);
        }
    }
    let limit = Instant::now() + SHUTDOWN_JOIN_LIMIT;
    while board.running > 0 && Instant::now() < limit {
        board = shared
            .changed
            .wait_timeout(board, Duration::from_millis(200))
            .unwrap_or_else(|p| p.into_inner())
            .0;
    }
}

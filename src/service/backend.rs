//! The jobs as the HTTP side sees them, whichever backend holds them: the embedded queue and
//! worker threads of this process ([`JobManager`], the data directory's records), or the
//! PostgreSQL queue that `lungmotion worker` processes take from ([`PgJobs`]).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use super::callbacks::CallbackDelivery;
use super::ids::{JobId, ScanId};
use super::jobs::{
    queued_record, CancelOutcome, JobCounts, JobManager, ScanRemoval, SubmitRefusal, Workers,
};
use super::pacs_settings::PacsSettings;
use super::postgres::Postgres;
use super::store::{JobRecord, JobRequest, JobState};
use crate::Result;

/// The service's jobs: in this process, or in PostgreSQL.
#[derive(Clone)]
pub enum Jobs {
    /// The queue and worker threads of this process (no `[store] postgres_url`).
    Embedded(JobManager),
    /// The PostgreSQL queue; `lungmotion worker` processes run the jobs.
    Postgres(PgJobs),
}

/// The HTTP side of the PostgreSQL queue: every call is a statement, nothing is kept here, so
/// any number of API processes can serve one database.
#[derive(Clone)]
pub struct PgJobs {
    /// The database.
    pub pg: Postgres,
    /// Jobs that may wait before submissions are refused with 429.
    pub queue_capacity: usize,
    /// The server's PACS, recorded in the jobs that use it.
    pub pacs: Option<PacsSettings>,
    /// Raised when this process begins to shut down.
    pub shutting_down: Arc<AtomicBool>,
}

impl Jobs {
    /// Stores and queues a job, or says why not (see [`JobManager::submit`]).
    pub fn submit(
        &self,
        scan_id: ScanId,
        request: &JobRequest,
        target: Option<&std::path::Path>,
    ) -> Result<std::result::Result<JobRecord, SubmitRefusal>> {
        match self {
            Jobs::Embedded(m) => m.submit(scan_id, request, target),
            Jobs::Postgres(p) => {
                if p.shutting_down.load(Ordering::SeqCst) {
                    return Ok(Err(SubmitRefusal::ShuttingDown));
                }
                let pacs_server = p.pacs.as_ref().map(|s| s.root_url.as_str());
                let record = queued_record(scan_id, request, pacs_server);
                Ok(
                    match p.pg.submit(&record, request, target, p.queue_capacity)? {
                        Ok(true) => Ok(record),
                        Ok(false) => Err(SubmitRefusal::ScanMissing),
                        Err(queued) => Err(SubmitRefusal::QueueFull {
                            queued,
                            // No run times are kept across processes: a job on the bundled
                            // phantom takes seconds, a POPI-sized one minutes.
                            retry_after_s: 30,
                        }),
                    },
                )
            }
        }
    }

    /// A job's current record, `None` for an unknown job.
    pub fn status(&self, id: JobId) -> Result<Option<JobRecord>> {
        match self {
            Jobs::Embedded(m) => Ok(m.status(id)),
            Jobs::Postgres(p) => p.pg.status(id),
        }
    }

    /// Cancels a queued or running job; `None` for an unknown job. A running job's worker
    /// sees `cancelling` at its next lease renewal.
    pub fn cancel(&self, id: JobId) -> Result<Option<CancelOutcome>> {
        match self {
            Jobs::Embedded(m) => m.cancel(id),
            Jobs::Postgres(p) => p.pg.update(id, |record| match record.state {
                JobState::Queued => {
                    record.state = JobState::Cancelled;
                    record.error = Some("cancelled by a client before it ran".into());
                    record.finished_at = Some(super::store::now_rfc3339());
                    // Written with the record: its row's callback is due from now.
                    super::jobs::begin_callback(record);
                    (true, CancelOutcome::Cancelled)
                }
                JobState::Running => {
                    record.state = JobState::Cancelling;
                    (true, CancelOutcome::Requested)
                }
                JobState::Cancelling => (false, CancelOutcome::Requested),
                _ => (false, CancelOutcome::AlreadyFinished),
            }),
        }
    }

    /// Removes a finished job and its outputs; `Ok(false)` when it is not finished.
    pub fn remove(&self, id: JobId) -> Result<bool> {
        match self {
            Jobs::Embedded(m) => m.remove(id),
            Jobs::Postgres(p) => p.pg.remove_if(id, |r| r.state.is_terminal()),
        }
    }

    /// Every job's record now.
    pub fn records(&self) -> Result<Vec<JobRecord>> {
        match self {
            Jobs::Embedded(m) => Ok(m.records()),
            Jobs::Postgres(p) => p.pg.records(),
        }
    }

    /// Removes a finished job for retention unless its callback is still being delivered.
    pub fn remove_expired(&self, id: JobId) -> Result<bool> {
        match self {
            Jobs::Embedded(m) => m.remove_expired(id),
            Jobs::Postgres(p) => p.pg.remove_if(id, |r| {
                r.state.is_terminal()
                    && !r
                        .callback
                        .as_ref()
                        .is_some_and(|c| c.state == super::callbacks::CallbackState::Pending)
            }),
        }
    }

    /// Removes a scan unless a queued, running or cancelling job uses it.
    pub fn remove_unused_scan(&self, scan_id: ScanId) -> Result<ScanRemoval> {
        match self {
            Jobs::Embedded(m) => m.remove_unused_scan(scan_id),
            Jobs::Postgres(p) => p.pg.remove_unused_scan(scan_id),
        }
    }

    /// Changes a job's callback record; `false` when the job (or its callback) is gone.
    pub fn update_callback(
        &self,
        id: JobId,
        change: impl FnOnce(&mut CallbackDelivery) + Send + 'static,
    ) -> Result<bool> {
        match self {
            Jobs::Embedded(m) => m.update_callback(id, change),
            Jobs::Postgres(p) => Ok(p
                .pg
                .update(id, |record| match record.callback.as_mut() {
                    Some(c) => {
                        change(c);
                        (true, true)
                    }
                    None => (false, false),
                })?
                .unwrap_or(false)),
        }
    }

    /// Records a POST of a job's callback: `change` to its record, and with PostgreSQL when
    /// the next POST is due (`retry_in`; `None`: no more), so that any API process makes it,
    /// even after this one stopped. `false` when the job (or its callback) is gone.
    pub fn record_callback(
        &self,
        id: JobId,
        change: impl FnOnce(&mut CallbackDelivery) + Send + 'static,
        retry_in: Option<Duration>,
    ) -> Result<bool> {
        match self {
            Jobs::Embedded(m) => m.update_callback(id, change),
            Jobs::Postgres(p) => p.pg.record_callback(id, change, retry_in),
        }
    }

    /// Jobs by state and the queue (and with PostgreSQL the workers); empty when the
    /// database does not answer (`/readyz` says why).
    pub fn counts(&self) -> JobCounts {
        match self {
            Jobs::Embedded(m) => m.counts(),
            Jobs::Postgres(p) => p.pg.counts().unwrap_or_else(|e| {
                tracing::warn!("job counts: {e}");
                JobCounts::default()
            }),
        }
    }

    /// Whether the database answers: `None` without one, else why not.
    pub fn probe_database(&self) -> Option<std::result::Result<(), String>> {
        match self {
            Jobs::Embedded(_) => None,
            Jobs::Postgres(p) => Some(p.pg.probe()),
        }
    }

    /// Whether the records and the queue are in PostgreSQL.
    pub fn is_postgres(&self) -> bool {
        matches!(self, Jobs::Postgres(_))
    }

    /// Whether shutdown has begun.
    pub fn shutting_down(&self) -> bool {
        match self {
            Jobs::Embedded(m) => m.shutting_down(),
            Jobs::Postgres(p) => p.shutting_down.load(Ordering::SeqCst),
        }
    }

    /// Refuses new jobs from now on (running ones go on).
    pub fn begin_shutdown(&self) {
        match self {
            Jobs::Embedded(m) => m.begin_shutdown(),
            Jobs::Postgres(p) => p.shutting_down.store(true, Ordering::SeqCst),
        }
    }

    /// Stops this process's workers (see [`JobManager::shutdown`]); nothing runs in an API
    /// process on PostgreSQL.
    pub fn shutdown(&self, workers: Option<Workers>, grace: Duration) {
        match (self, workers) {
            (Jobs::Embedded(m), Some(w)) => m.shutdown(w, grace),
            _ => self.begin_shutdown(),
        }
    }
}

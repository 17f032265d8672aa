//! `lungmotion worker`: a process that takes simulation jobs from the PostgreSQL queue, runs
//! them on its own threads (as many as `workers`) and writes their outputs into the shared
//! data directory, beside any number of `lungmotion serve` API processes and other workers.
//! See [`super::postgres`] for the queue, its leases and how a dead worker's job comes back.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::config::ServiceConfig;
use super::ingest_cache::IngestCache;
use super::jobs::{leased_shared, leased_worker_loop, stop_leased_workers, LeasedStats};
use super::pacs_jobs::PacsAccess;
use super::postgres::{LeasedRecords, Postgres, WorkerStatus};
use super::store::Store;
use crate::error::{IoContext, IoOp};
use crate::{Error, Result};

/// What the worker prints on stdout once it takes jobs.
pub const READY_PREFIX: &str = "lungmotion worker: taking jobs as ";

/// This process's worker id: host, pid and 32 random bits, so a restarted process with the
/// same pid (a container) never holds its predecessor's leases.
fn worker_id() -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .unwrap_or_else(|_| "host".into());
    let random = uuid::Uuid::new_v4().simple().to_string();
    format!("{host}-{}-{}", std::process::id(), &random[..8])
}

/// Records in the database that this worker is alive, with its counts (for the metrics).
fn report(pg: &Postgres, stats: &LeasedStats, id: &str, threads: usize) {
    let status = WorkerStatus {
        worker_id: id.to_string(),
        threads: threads as i64,
        running: stats.running.load(Ordering::SeqCst),
        done: stats.done.load(Ordering::SeqCst),
        failed: stats.failed.load(Ordering::SeqCst),
        cancelled: stats.cancelled.load(Ordering::SeqCst),
        seen_s_ago: 0.0,
    };
    if let Err(e) = pg.report_worker(&status) {
        tracing::warn!("reporting this worker: {e}");
    }
}

/// A worker taking jobs: its simulation threads and its reaper, until [`RunningWorker::stop`].
pub struct RunningWorker {
    id: String,
    shared: Arc<super::jobs::Shared>,
    threads: Vec<std::thread::JoinHandle<()>>,
    stop_reaper: std::sync::mpsc::Sender<()>,
    reaper: std::thread::JoinHandle<()>,
    grace: Duration,
}

impl RunningWorker {
    /// Its worker id, the lease owner of the jobs it runs (`host-pid-random`).
    pub fn id(&self) -> &str {
        &self.id
    }

    /// Stops taking jobs, gives running ones `shutdown_grace_s`, then puts them back in the
    /// queue without using an attempt, and waits for its threads.
    pub fn stop(self) {
        stop_leased_workers(&self.shared, self.grace);
        for t in self.threads {
            let _ = t.join();
        }
        drop(self.stop_reaper);
        let _ = self.reaper.join();
    }
}

/// Starts a worker in this process: connects (see [`Postgres::connect`]), starts `workers`
/// simulation threads and a reaper that takes back jobs whose lease expired. `lungmotion
/// worker` runs one until a signal; the queue benchmark runs several side by side.
pub fn start_worker(config: &ServiceConfig) -> Result<RunningWorker> {
    config.validate()?;
    let settings = config.postgres.clone().ok_or_else(|| {
        Error::settings(
            "service configuration",
            "lungmotion worker takes its jobs from PostgreSQL: set [store] postgres_url or \
             LUNGMOTION_POSTGRES_URL (without one, lungmotion serve runs the jobs itself)",
        )
    })?;
    let store =
        Store::open_shared(&config.data_dir)?.with_blobs(super::server::open_blobs(config)?);
    let pg = Postgres::connect(&settings, store.clone())?;
    let id = worker_id();
    let ingests = Arc::new(IngestCache::new(config.ingest_cache_mib));
    let pacs = PacsAccess::of_service(config);
    let records = Arc::new(LeasedRecords {
        pg: pg.clone(),
        worker: id.clone(),
    });
    let shared = leased_shared(store, records, config.workers, ingests, pacs);
    let stats = Arc::new(LeasedStats::default());
    pg.listen_for_work();
    report(&pg, &stats, &id, config.workers);
    let threads = (0..config.workers)
        .map(|i| {
            let (shared, pg, id, stats) = (shared.clone(), pg.clone(), id.clone(), stats.clone());
            let name = format!("lungmotion-worker-{i}");
            std::thread::Builder::new()
                .name(name.clone())
                .spawn(move || leased_worker_loop(&shared, &pg, &id, &stats))
                .at(IoOp::Spawn, name)
        })
        .collect::<Result<Vec<_>>>()?;
    let (stop_tx, stop_rx) = std::sync::mpsc::channel::<()>();
    let reaper = {
        let (pg, stats, id) = (pg.clone(), stats.clone(), id.clone());
        let threads = config.workers;
        let max_attempts = config.max_attempts;
        let period = (pg.lease() / 3).max(Duration::from_millis(200));
        std::thread::Builder::new()
            .name("lungmotion-reaper".into())
            .spawn(move || loop {
                match pg.reap(max_attempts) {
                    Ok(0) => {}
                    Ok(n) => tracing::info!(jobs = n, "jobs of a stopped worker taken back"),
                    Err(e) => tracing::warn!("taking back expired leases: {e}"),
                }
                report(&pg, &stats, &id, threads);
                match stop_rx.recv_timeout(period) {
                    Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                    _ => return,
                }
            })
            .at(IoOp::Spawn, "the thread lungmotion-reaper")?
    };
    tracing::info!(worker = %id, server = %pg.server(), threads = config.workers, lease_s = pg.lease().as_secs_f64(), "taking jobs");
    Ok(RunningWorker {
        id,
        shared,
        threads,
        stop_reaper: stop_tx,
        reaper,
        grace: Duration::from_secs_f64(config.shutdown_grace_s),
    })
}

/// Runs a worker process until SIGTERM or Ctrl-C (see [`start_worker`]), then gives running
/// jobs `shutdown_grace_s` before re-queueing them.
pub fn work_blocking(config: ServiceConfig) -> Result<()> {
    let worker = start_worker(&config)?;
    {
        use std::io::Write;
        let server = config
            .postgres
            .as_ref()
            .map(|p| p.server())
            .unwrap_or_default();
        let mut out = std::io::stdout().lock();
        let _ = writeln!(out, "{READY_PREFIX}{} from {server}", worker.id());
        let _ = out.flush();
    }
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .at(IoOp::Spawn, "the signal handler's runtime")?;
    runtime.block_on(super::server::termination());
    tracing::info!("shutting down: no new jobs");
    worker.stop();
    tracing::info!("stopped");
    Ok(())
}

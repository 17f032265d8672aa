//! The PostgreSQL store of job and scan records and the queue, shared by `lungmotion serve`
//! processes (the API, stateless) and `lungmotion worker` processes (the simulations). The
//! files (uploads, targets, outputs) are in the object store when one is configured (see
//! [`super::blobs`]), else in the data directory, which every process of one deployment then
//! mounts.
//!
//! * Jobs and scans are rows (`lungmotion_jobs`, `lungmotion_scans`), each record as JSONB with
//!   its state beside it for the queries; the request is a column of the job's row.
//! * A worker takes the oldest queued job with `FOR UPDATE SKIP LOCKED` (so two workers never
//!   take one job and neither waits for the other), marks it `running` with its id as the lease
//!   owner and `lease_until` = now + `lease_s`, and renews the lease every third of it while
//!   the run goes on; the renewal also tells it that a client asked for cancellation.
//! * A job whose lease expired (its worker died or lost the database) is taken back by any
//!   worker's reaper as the embedded server does at a restart: queued again (the run counted
//!   as an attempt), failed once `max_attempts` runs have started, or cancelled when a client
//!   had asked. Every write of a worker names its lease, so a worker that lost its lease
//!   changes nothing any more.
//! * A job that ends with a completion callback waiting has its row's `callback_due` set;
//!   the API processes claim due callbacks ([`Postgres::claim_callback`]), POST them and write
//!   the outcome with the next due time ([`Postgres::record_callback`]).
//! * Idle workers sleep on `LISTEN lungmotion_queue`, which submissions and re-queues
//!   `NOTIFY`, and look at the queue every [`POLL_INTERVAL`] as well.
//! * The schema is created and upgraded by the service (`lungmotion_schema` holds its version
//!   and the lungmotion that wrote it), under an advisory lock so that processes starting
//!   together do it once; a schema newer than this lungmotion knows is refused by name.
//!
//! The client is `tokio-postgres` with a `deadpool-postgres` pool: pure Rust (no libpq), and
//! its own small runtime here, so the simulation workers (OS threads) and the HTTP handlers
//! call it alike through [`Postgres::run`].

use std::future::Future;
use std::path::Path;
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use deadpool_postgres::{Manager, ManagerConfig, Pool, RecyclingMethod};
use tokio_postgres::error::SqlState;
use tokio_postgres::{NoTls, Row};

use super::client_runtime::ClientRuntime;
use super::ids::{JobId, ScanId};
use super::jobs::{JobCounts, ScanRemoval};
use super::records::Records;
use super::store::{JobRecord, JobRequest, JobState, ScanRecord, Store, StoredScan};
use crate::{Error, Result};

/// The schema version this lungmotion writes; [`MIGRATIONS`]`[v]` upgrades version `v` to
/// `v + 1`.
pub const SCHEMA_VERSION: i32 = 2;

/// The statements that bring a schema from each version to the next (index 0: from none).
const MIGRATIONS: [&str; SCHEMA_VERSION as usize] = [
    r#"
CREATE TABLE lungmotion_scans (
    scan_id text PRIMARY KEY,
    created_at text NOT NULL,
    record jsonb NOT NULL
);
CREATE TABLE lungmotion_jobs (
    job_id text PRIMARY KEY,
    seq bigserial NOT NULL,
    scan_id text NOT NULL,
    state text NOT NULL,
    created_at text NOT NULL,
    record jsonb NOT NULL,
    request jsonb NOT NULL,
    lease_owner text,
    lease_until timestamptz
);
CREATE INDEX lungmotion_jobs_queue ON lungmotion_jobs (seq) WHERE state = 'queued';
CREATE INDEX lungmotion_jobs_leases ON lungmotion_jobs (lease_until)
    WHERE state IN ('running', 'cancelling');
CREATE INDEX lungmotion_jobs_scan ON lungmotion_jobs (scan_id);
CREATE TABLE lungmotion_workers (
    worker_id text PRIMARY KEY,
    host text NOT NULL,
    pid integer NOT NULL,
    threads integer NOT NULL,
    started_at timestamptz NOT NULL,
    last_seen timestamptz NOT NULL,
    running integer NOT NULL DEFAULT 0,
    jobs_done bigint NOT NULL DEFAULT 0,
    jobs_failed bigint NOT NULL DEFAULT 0,
    jobs_cancelled bigint NOT NULL DEFAULT 0
);
"#,
    r#"
ALTER TABLE lungmotion_jobs ADD COLUMN callback_due timestamptz;
CREATE INDEX lungmotion_jobs_callbacks ON lungmotion_jobs (callback_due)
    WHERE callback_due IS NOT NULL;
"#,
];

/// The `callback_due` of a job row whose record is written as `$json` (a SQL expression of
/// that parameter): due now (or when it already was) while the record's callback is
/// `pending`, none otherwise. Every write of a record goes through it, so a job that ends
/// with a callback waiting is delivered by whichever API process claims it next.
fn callback_due_of(json: &str) -> String {
    format!(
        "CASE WHEN ({json}::jsonb)->'callback'->>'state' = 'pending' \
         THEN COALESCE(callback_due, now()) ELSE NULL END"
    )
}

/// Key of the advisory lock held while the schema is created or upgraded.
const SCHEMA_LOCK: i64 = 0x6c75_6e67_6d6f_7401;
/// Key space of the advisory locks that order a submission and a scan's removal.
const SCAN_LOCK_SPACE: i32 = 0x6c6d_7363;
/// The channel idle workers listen on.
const QUEUE_CHANNEL: &str = "lungmotion_queue";
/// How often an idle worker looks at the queue even without a notification (one lost while
/// its listening connection was being re-made, a clock of the database far off).
pub const POLL_INTERVAL: Duration = Duration::from_secs(2);
/// Longest wait for one statement of a probe (`/readyz`).
const PROBE_TIMEOUT: Duration = Duration::from_secs(3);
/// Connections one process keeps.
const POOL_SIZE: usize = 8;
/// Default lease of a running job, s: renewed every third of it, so a worker must miss two
/// renewals in a row (a database failover, a stalled machine) before its job is taken back.
pub const DEFAULT_LEASE_S: f64 = 30.0;
/// Default time a process keeps trying to reach the database at start, s.
pub const DEFAULT_CONNECT_TIMEOUT_S: f64 = 60.0;

/// Where the records live when they are in PostgreSQL, and how leases work.
#[derive(Clone, PartialEq)]
pub struct PostgresSettings {
    /// The connection string (`postgres://user@host:port/db` or `host=… user=…`).
    pub url: String,
    /// The password, when it is not in the URL (`[store] postgres_password_file`).
    pub password: Option<String>,
    /// A running job's lease, s.
    pub lease_s: f64,
    /// How long to keep trying to reach the database at start, s (0: once).
    pub connect_timeout_s: f64,
}

impl std::fmt::Debug for PostgresSettings {
    // The URL may hold the password: only the server is shown.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PostgresSettings")
            .field("server", &self.server())
            .field("password", &self.password.as_ref().map(|_| "<set>"))
            .field("lease_s", &self.lease_s)
            .field("connect_timeout_s", &self.connect_timeout_s)
            .finish()
    }
}

impl PostgresSettings {
    /// Settings for `url` with the default lease and start timeout.
    pub fn new(url: impl Into<String>) -> Self {
        PostgresSettings {
            url: url.into(),
            password: None,
            lease_s: DEFAULT_LEASE_S,
            connect_timeout_s: DEFAULT_CONNECT_TIMEOUT_S,
        }
    }

    /// The parsed connection settings, with the password file's password.
    fn config(&self) -> std::result::Result<tokio_postgres::Config, String> {
        let mut config = tokio_postgres::Config::from_str(&self.url)
            .map_err(|e| format!("postgres_url is not a PostgreSQL connection string: {e}"))?;
        if let Some(password) = &self.password {
            config.password(password);
        }
        if config.get_connect_timeout().is_none() {
            config.connect_timeout(Duration::from_secs(5));
        }
        config.application_name("lungmotion");
        Ok(config)
    }

    /// The server as errors and logs name it: `user@host:port/dbname`, never the password.
    pub fn server(&self) -> String {
        match self.config() {
            Ok(c) => describe_server(&c),
            Err(_) => "(unparsable postgres_url)".into(),
        }
    }

    /// Refuses settings that cannot work, naming the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::settings("service configuration", m));
        if let Err(m) = self.config() {
            return bad(m);
        }
        if !(self.lease_s.is_finite() && (1.0..=3600.0).contains(&self.lease_s)) {
            return bad(format!(
                "[store] lease_s must be a number of seconds from 1 to 3600, not {}",
                self.lease_s
            ));
        }
        if !(self.connect_timeout_s.is_finite() && (0.0..=3600.0).contains(&self.connect_timeout_s))
        {
            return bad(format!(
                "[store] connect_timeout_s must be a number of seconds from 0 to 3600, not {}",
                self.connect_timeout_s
            ));
        }
        Ok(())
    }
}

/// `user@host:port/dbname` of a connection's settings.
fn describe_server(c: &tokio_postgres::Config) -> String {
    let host = c
        .get_hosts()
        .first()
        .map(|h| match h {
            tokio_postgres::config::Host::Tcp(name) => name.clone(),
            #[cfg(unix)]
            tokio_postgres::config::Host::Unix(path) => path.display().to_string(),
        })
        .unwrap_or_else(|| "localhost".into());
    let port = c.get_ports().first().copied().unwrap_or(5432);
    format!(
        "{}@{host}:{port}/{}",
        c.get_user().unwrap_or("(no user)"),
        c.get_dbname().unwrap_or(c.get_user().unwrap_or("postgres"))
    )
}

/// A PostgreSQL error as text: the server's message for its own errors, else the client's
/// with its cause (connection refused, timed out …).
fn describe(e: &tokio_postgres::Error) -> String {
    if let Some(db) = e.as_db_error() {
        return format!(
            "{}: {} (SQLSTATE {})",
            db.severity(),
            db.message(),
            db.code().code()
        );
    }
    let mut text = e.to_string();
    let mut source = std::error::Error::source(e);
    while let Some(cause) = source {
        let more = cause.to_string();
        if !text.contains(&more) {
            text.push_str(": ");
            text.push_str(&more);
        }
        source = cause.source();
    }
    text
}

/// Whether a failure to connect will not go away by trying again (credentials, an unknown
/// database or role: the settings are wrong).
fn is_permanent(e: &tokio_postgres::Error) -> bool {
    e.code().is_some_and(|c| {
        *c == SqlState::INVALID_PASSWORD
            || *c == SqlState::INVALID_AUTHORIZATION_SPECIFICATION
            || *c == SqlState::INVALID_CATALOG_NAME
    })
}

/// The PostgreSQL store: a pool on its own runtime, and the data directory for the files.
#[derive(Clone)]
pub struct Postgres {
    inner: Arc<Inner>,
}

struct Inner {
    pool: Pool,
    runtime: ClientRuntime,
    server: String,
    store: Store,
    lease: Duration,
    config: tokio_postgres::Config,
    /// Raised by notifications on [`QUEUE_CHANNEL`]; idle workers wait on it.
    wake: Arc<(Mutex<u64>, Condvar)>,
    listening: AtomicBool,
}

impl Inner {
    fn handle(&self) -> &tokio::runtime::Handle {
        self.runtime.handle()
    }
}

/// What a worker's renewal of its lease found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Lease {
    /// Still the worker's, the job running.
    Held,
    /// Still the worker's, and a client asked for cancellation.
    Cancelling,
    /// No longer the worker's (it expired and was taken back, or the job was removed).
    Lost,
}

/// A worker process as it reports itself (`lungmotion_workers`), for the metrics.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct WorkerStatus {
    /// Its id (`host-pid-random`).
    pub worker_id: String,
    /// Simulation threads.
    pub threads: i64,
    /// Jobs it runs now.
    pub running: i64,
    /// Jobs it finished `done`, `failed`, `cancelled`.
    pub done: i64,
    /// Jobs that ended failed.
    pub failed: i64,
    /// Jobs that ended cancelled.
    pub cancelled: i64,
    /// Seconds since it last reported.
    pub seen_s_ago: f64,
}

/// The error of a failed statement on `server`, naming the server and the database's words.
fn database_error(server: &str) -> impl Fn(tokio_postgres::Error) -> Error + Copy + '_ {
    move |e| Error::Database {
        server: server.to_string(),
        reason: describe(&e),
    }
}

/// A job's row, locked for the rest of the transaction `tx` (`None`: no such job).
async fn locked_job_row(
    tx: &tokio_postgres::Transaction<'_>,
    id: &str,
) -> std::result::Result<Option<Row>, tokio_postgres::Error> {
    tx.query_opt(
        "SELECT job_id, state, record FROM lungmotion_jobs WHERE job_id = $1 FOR UPDATE",
        &[&id],
    )
    .await
}

fn job_record(row: &Row) -> Result<JobRecord> {
    let value: serde_json::Value = row.get("record");
    let state: String = row.get("state");
    let mut record: JobRecord = serde_json::from_value(value).map_err(|e| Error::Store {
        record: format!("lungmotion_jobs {}", row.get::<_, String>("job_id")),
        reason: format!("corrupt record: {e}"),
    })?;
    // The column is what the queue acts on; the record's copy may trail it by a renewal.
    record.state = parse_state(&state).unwrap_or(record.state);
    Ok(record)
}

fn parse_state(text: &str) -> Option<JobState> {
    JobState::ALL.into_iter().find(|s| s.name() == text)
}

fn to_json<T: serde::Serialize>(value: &T) -> Result<serde_json::Value> {
    serde_json::to_value(value).map_err(|e| Error::Store {
        record: "lungmotion_jobs".into(),
        reason: format!("cannot serialise: {e}"),
    })
}

impl Postgres {
    /// Connects (trying again with a doubling wait, up to `connect_timeout_s`, while the server
    /// cannot be reached; at once for refused credentials), creates or upgrades the schema,
    /// and starts listening for queued work. Errors name the server.
    pub fn connect(settings: &PostgresSettings, store: Store) -> Result<Self> {
        settings.validate()?;
        let config = settings
            .config()
            .map_err(|m| Error::settings("service configuration", m))?;
        let server = describe_server(&config);
        let runtime = ClientRuntime::start("lungmotion-postgres").map_err(|e| Error::Database {
            server: server.clone(),
            reason: format!("cannot start the client's threads: {e}"),
        })?;
        let manager = Manager::from_config(
            config.clone(),
            NoTls,
            ManagerConfig {
                recycling_method: RecyclingMethod::Fast,
            },
        );
        let pool = Pool::builder(manager)
            .max_size(POOL_SIZE)
            .runtime(deadpool_postgres::Runtime::Tokio1)
            .wait_timeout(Some(Duration::from_secs(30)))
            .create_timeout(Some(Duration::from_secs(10)))
            .build()
            .map_err(|e| Error::Database {
                server: server.clone(),
                reason: format!("cannot make a connection pool: {e}"),
            })?;
        let pg = Postgres {
            inner: Arc::new(Inner {
                pool,
                runtime,
                server,
                store,
                lease: Duration::from_secs_f64(settings.lease_s),
                config,
                wake: Arc::new((Mutex::new(0), Condvar::new())),
                listening: AtomicBool::new(false),
            }),
        };
        pg.first_connection(Duration::from_secs_f64(settings.connect_timeout_s))?;
        pg.migrate()?;
        Ok(pg)
    }

    /// The server, as `user@host:port/dbname`.
    pub fn server(&self) -> &str {
        &self.inner.server
    }

    /// A running job's lease.
    pub fn lease(&self) -> Duration {
        self.inner.lease
    }

    /// The data directory of the files.
    pub fn files(&self) -> &Store {
        &self.inner.store
    }

    /// Runs `future` on the client's runtime and waits for it, from any thread (an HTTP
    /// handler's or a simulation worker's): a channel, not `block_on`, so no runtime context
    /// is entered twice.
    fn run<T: Send + 'static>(&self, future: impl Future<Output = T> + Send + 'static) -> T {
        self.inner.runtime.run(future)
    }

    fn error(&self, e: impl std::fmt::Display) -> Error {
        Error::Database {
            server: self.inner.server.clone(),
            reason: e.to_string(),
        }
    }

    /// A pooled connection, or the error naming the server.
    async fn client(
        pool: &Pool,
        server: &str,
    ) -> std::result::Result<deadpool_postgres::Object, Error> {
        pool.get().await.map_err(|e| Error::Database {
            server: server.to_string(),
            reason: match &e {
                deadpool_postgres::PoolError::Backend(pg) => describe(pg),
                other => other.to_string(),
            },
        })
    }

    /// Runs `work` with a pooled connection on the client's runtime.
    fn with_client<T, F, Fut>(&self, work: F) -> Result<T>
    where
        T: Send + 'static,
        F: FnOnce(deadpool_postgres::Object, String) -> Fut + Send + 'static,
        Fut: Future<Output = Result<T>> + Send,
    {
        let pool = self.inner.pool.clone();
        let server = self.inner.server.clone();
        self.run(async move {
            let client = Self::client(&pool, &server).await?;
            work(client, server).await
        })
    }

    /// Connects once, trying again while the server is unreachable until `limit` has passed.
    fn first_connection(&self, limit: Duration) -> Result<()> {
        let started = Instant::now();
        let mut wait = Duration::from_millis(250);
        let mut tries = 0u32;
        loop {
            tries += 1;
            let config = self.inner.config.clone();
            let outcome = self.run(async move {
                let (client, connection) = config.connect(NoTls).await?;
                drop(client);
                let _ = connection.await;
                Ok::<(), tokio_postgres::Error>(())
            });
            let e = match outcome {
                Ok(()) => return Ok(()),
                Err(e) => e,
            };
            let reason = describe(&e);
            if is_permanent(&e) {
                return Err(self.error(format!("the server refused this connection: {reason}")));
            }
            let elapsed = started.elapsed();
            if elapsed + wait > limit {
                return Err(self.error(format!(
                    "unreachable after {tries} attempts over {:.0} s ([store] \
                     connect_timeout_s): {reason}",
                    elapsed.as_secs_f64()
                )));
            }
            tracing::warn!(
                server = %self.inner.server,
                attempt = tries,
                retry_in_s = wait.as_secs_f64(),
                "database unreachable, trying again: {reason}"
            );
            std::thread::sleep(wait);
            wait = (wait * 2).min(Duration::from_secs(10));
        }
    }

    /// Creates the schema, or upgrades an older one, or refuses a newer one by name.
    fn migrate(&self) -> Result<()> {
        self.with_client(|mut client, server| async move {
            let fail = |e: tokio_postgres::Error| Error::Database {
                server: server.clone(),
                reason: format!("schema: {}", describe(&e)),
            };
            let tx = client.transaction().await.map_err(fail)?;
            tx.execute("SELECT pg_advisory_xact_lock($1)", &[&SCHEMA_LOCK])
                .await
                .map_err(fail)?;
            tx.batch_execute(
                "CREATE TABLE IF NOT EXISTS lungmotion_schema (
                     singleton boolean PRIMARY KEY DEFAULT true CHECK (singleton),
                     version integer NOT NULL,
                     written_by text NOT NULL
                 )",
            )
            .await
            .map_err(fail)?;
            let row = tx
                .query_opt("SELECT version, written_by FROM lungmotion_schema", &[])
                .await
                .map_err(fail)?;
            let (found, written_by) = row
                .map(|r| (r.get::<_, i32>(0), r.get::<_, String>(1)))
                .unwrap_or((0, String::new()));
            if found > SCHEMA_VERSION {
                return Err(Error::SchemaTooNew {
                    server: server.clone(),
                    found,
                    written_by,
                    known: SCHEMA_VERSION,
                    ours: env!("CARGO_PKG_VERSION"),
                });
            }
            for (v, statements) in MIGRATIONS.iter().enumerate().skip(found as usize) {
                tx.batch_execute(statements).await.map_err(|e| Error::Database {
                    server: server.clone(),
                    reason: format!("upgrading the schema to version {}: {}", v + 1, describe(&e)),
                })?;
            }
            tx.execute(
                "INSERT INTO lungmotion_schema (version, written_by) VALUES ($1, $2)
                 ON CONFLICT (singleton) DO UPDATE SET version = $1, written_by = $2",
                &[&SCHEMA_VERSION, &env!("CARGO_PKG_VERSION")],
            )
            .await
            .map_err(fail)?;
            tx.commit().await.map_err(fail)?;
            if found < SCHEMA_VERSION {
                tracing::info!(%server, from = found, to = SCHEMA_VERSION, "database schema created or upgraded");
            }
            Ok(())
        })
    }

    /// Whether the database answers now (for `/readyz`): `Err` says why not, naming the server.
    /// A schema that a newer lungmotion wrote meanwhile (a rolling upgrade that reached the
    /// database before this process) is refused by name, as at start.
    pub fn probe(&self) -> std::result::Result<(), String> {
        let outcome = self.with_client(|client, server| async move {
            let query = client.query_opt("SELECT version, written_by FROM lungmotion_schema", &[]);
            match tokio::time::timeout(PROBE_TIMEOUT, query).await {
                Ok(Ok(row)) => {
                    let (found, written_by) = row
                        .map(|r| (r.get::<_, i32>(0), r.get::<_, String>(1)))
                        .unwrap_or((SCHEMA_VERSION, String::new()));
                    if found > SCHEMA_VERSION {
                        return Err(Error::SchemaTooNew {
                            server,
                            found,
                            written_by,
                            known: SCHEMA_VERSION,
                            ours: env!("CARGO_PKG_VERSION"),
                        });
                    }
                    Ok(())
                }
                Ok(Err(e)) => Err(Error::Database {
                    server,
                    reason: describe(&e),
                }),
                Err(_) => Err(Error::Database {
                    server,
                    reason: format!("no answer within {} s", PROBE_TIMEOUT.as_secs()),
                }),
            }
        });
        outcome.map_err(|e| e.to_string())
    }

    /// Starts the connection that listens for queued work (a worker's), re-made when it drops.
    pub fn listen_for_work(&self) {
        if self.inner.listening.swap(true, Ordering::SeqCst) {
            return;
        }
        let config = self.inner.config.clone();
        let wake = self.inner.wake.clone();
        let server = self.inner.server.clone();
        self.inner.handle().spawn(async move {
            loop {
                if let Err(e) = listen_once(&config, &wake).await {
                    tracing::warn!(%server, "listening for queued jobs: {}; polling meanwhile", describe(&e));
                }
                tokio::time::sleep(POLL_INTERVAL).await;
            }
        });
    }

    /// Waits until a job may have been queued (a notification) or `timeout` has passed.
    pub fn wait_for_work(&self, timeout: Duration) {
        let (lock, cv) = &*self.inner.wake;
        let guard = lock.lock().unwrap_or_else(|p| p.into_inner());
        let seen = *guard;
        let _ = cv
            .wait_timeout_while(guard, timeout, |n| *n == seen)
            .unwrap_or_else(|p| p.into_inner());
    }

    /// Stores and queues a job unless `capacity` jobs are queued already or its scan is gone
    /// (checked under the scan's lock, as a scan's removal is); `Ok(Err(queued))` when full,
    /// `Ok(Ok(false))` when the scan is missing.
    pub fn submit(
        &self,
        record: &JobRecord,
        request: &JobRequest,
        target: Option<&Path>,
        capacity: usize,
    ) -> Result<std::result::Result<bool, usize>> {
        // The files first: a row whose directory is missing would be a job that cannot run.
        self.inner
            .store
            .put_job_files(record.job_id, target, None)?;
        let id = record.job_id.to_string();
        let scan_id = record.scan_id.to_string();
        let needs_scan = request.pacs_ct.is_none();
        let record_json = to_json(record)?;
        let request_json = to_json(request)?;
        let created = record.created_at.clone();
        let outcome = self.with_client(move |mut client, server| async move {
            let fail = database_error(&server);
            let tx = client.transaction().await.map_err(fail)?;
            tx.execute(
                "SELECT pg_advisory_xact_lock($1, hashtext($2))",
                &[&SCAN_LOCK_SPACE, &scan_id],
            )
            .await
            .map_err(fail)?;
            let queued: i64 = tx
                .query_one(
                    "SELECT count(*) FROM lungmotion_jobs WHERE state = 'queued'",
                    &[],
                )
                .await
                .map_err(fail)?
                .get(0);
            if queued as usize >= capacity {
                return Ok(Err(queued as usize));
            }
            if needs_scan {
                let scan = tx
                    .query_opt(
                        "SELECT 1 FROM lungmotion_scans WHERE scan_id = $1",
                        &[&scan_id],
                    )
                    .await
                    .map_err(fail)?;
                if scan.is_none() {
                    return Ok(Ok(false));
                }
            }
            tx.execute(
                "INSERT INTO lungmotion_jobs (job_id, scan_id, state, created_at, record, request)
                 VALUES ($1, $2, 'queued', $3, $4, $5)",
                &[&id, &scan_id, &created, &record_json, &request_json],
            )
            .await
            .map_err(fail)?;
            tx.execute("SELECT pg_notify($1, '')", &[&QUEUE_CHANNEL])
                .await
                .map_err(fail)?;
            tx.commit().await.map_err(fail)?;
            Ok(Ok(true))
        });
        if !matches!(outcome, Ok(Ok(true))) {
            let _ = self.inner.store.delete_job(record.job_id);
        }
        outcome
    }

    /// A job's record.
    pub fn status(&self, id: JobId) -> Result<Option<JobRecord>> {
        let id = id.to_string();
        self.with_client(move |client, server| async move {
            let row = client
                .query_opt(
                    "SELECT job_id, state, record FROM lungmotion_jobs WHERE job_id = $1",
                    &[&id],
                )
                .await
                .map_err(database_error(&server))?;
            row.as_ref().map(job_record).transpose()
        })
    }

    /// Every job's record, oldest first.
    pub fn records(&self) -> Result<Vec<JobRecord>> {
        self.with_client(move |client, server| async move {
            let rows = client
                .query(
                    "SELECT job_id, state, record FROM lungmotion_jobs ORDER BY seq",
                    &[],
                )
                .await
                .map_err(database_error(&server))?;
            let mut records = Vec::with_capacity(rows.len());
            for row in &rows {
                match job_record(row) {
                    Ok(r) => records.push(r),
                    Err(e) => tracing::warn!("{e}"),
                }
            }
            Ok(records)
        })
    }

    /// Changes a job's record under its row's lock: `change` gets the record as stored and
    /// says whether to write it back (its state too). `None`: no such job.
    pub fn update<T: Send + 'static>(
        &self,
        id: JobId,
        change: impl FnOnce(&mut JobRecord) -> (bool, T) + Send + 'static,
    ) -> Result<Option<T>> {
        let id = id.to_string();
        self.with_client(move |mut client, server| async move {
            let fail = database_error(&server);
            let tx = client.transaction().await.map_err(fail)?;
            let Some(row) = locked_job_row(&tx, &id).await.map_err(fail)? else {
                return Ok(None);
            };
            let mut record = job_record(&row)?;
            let (write, answer) = change(&mut record);
            if write {
                let json = to_json(&record)?;
                let releases =
                    record.state != JobState::Running && record.state != JobState::Cancelling;
                tx.execute(
                    &format!(
                        "UPDATE lungmotion_jobs SET state = $2, record = $3,
                             lease_owner = CASE WHEN $4 THEN NULL ELSE lease_owner END,
                             callback_due = {}
                         WHERE job_id = $1",
                        callback_due_of("$3")
                    ),
                    &[&id, &record.state.name(), &json, &releases],
                )
                .await
                .map_err(fail)?;
            }
            tx.commit().await.map_err(fail)?;
            Ok(Some(answer))
        })
    }

    /// Removes a job's row and files if `removable` says so of its record; whether it did.
    pub fn remove_if(
        &self,
        id: JobId,
        removable: impl FnOnce(&JobRecord) -> bool + Send + 'static,
    ) -> Result<bool> {
        let key = id.to_string();
        let removed = self.with_client(move |mut client, server| async move {
            let fail = database_error(&server);
            let tx = client.transaction().await.map_err(fail)?;
            let Some(row) = locked_job_row(&tx, &key).await.map_err(fail)? else {
                return Ok(false);
            };
            if !removable(&job_record(&row)?) {
                return Ok(false);
            }
            tx.execute("DELETE FROM lungmotion_jobs WHERE job_id = $1", &[&key])
                .await
                .map_err(fail)?;
            tx.commit().await.map_err(fail)?;
            Ok(true)
        })?;
        if removed {
            self.inner.store.delete_job(id)?;
        }
        Ok(removed)
    }

    /// Removes a scan unless a queued, running or cancelling job uses it, under the scan's
    /// lock so that no job is submitted on it meanwhile.
    pub fn remove_unused_scan(&self, id: ScanId) -> Result<ScanRemoval> {
        let key = id.to_string();
        let store = self.inner.store.clone();
        self.with_client(move |mut client, server| async move {
            let fail = database_error(&server);
            let tx = client.transaction().await.map_err(fail)?;
            tx.execute(
                "SELECT pg_advisory_xact_lock($1, hashtext($2))",
                &[&SCAN_LOCK_SPACE, &key],
            )
            .await
            .map_err(fail)?;
            let live = tx
                .query_opt(
                    "SELECT 1 FROM lungmotion_jobs WHERE scan_id = $1
                         AND state IN ('queued', 'running', 'cancelling') LIMIT 1",
                    &[&key],
                )
                .await
                .map_err(fail)?;
            if live.is_some() {
                return Ok(ScanRemoval::InUse);
            }
            let n = tx
                .execute("DELETE FROM lungmotion_scans WHERE scan_id = $1", &[&key])
                .await
                .map_err(fail)?;
            // The files go before the lock is released, so a new upload can never be
            // submitted on a scan whose directory is disappearing.
            let files_gone = tokio::task::spawn_blocking(move || store.delete_scan(id))
                .await
                .map_err(|e| Error::Database {
                    server: server.clone(),
                    reason: format!("removing the scan's files: {e}"),
                })??;
            tx.commit().await.map_err(fail)?;
            Ok(if n > 0 || files_gone {
                ScanRemoval::Removed
            } else {
                ScanRemoval::Missing
            })
        })
    }

    /// Jobs by state and the queue, and the workers that reported in the last ten leases.
    pub fn counts(&self) -> Result<JobCounts> {
        let stale = self.inner.lease.as_secs_f64() * 10.0;
        self.with_client(move |client, server| async move {
            let fail = database_error(&server);
            let rows = client
                .query(
                    "SELECT state, count(*) FROM lungmotion_jobs GROUP BY state",
                    &[],
                )
                .await
                .map_err(fail)?;
            let mut counts = JobCounts::default();
            for row in rows {
                let n = row.get::<_, i64>(1) as usize;
                if let Some(state) = parse_state(row.get(0)) {
                    let i = JobState::ALL.iter().position(|s| *s == state).unwrap_or(0);
                    counts.by_state[i] += n;
                    match state {
                        JobState::Queued => counts.queued += n,
                        JobState::Running | JobState::Cancelling => counts.running += n,
                        _ => {}
                    }
                }
            }
            let workers = client
                .query(
                    "SELECT worker_id, threads, running, jobs_done, jobs_failed, jobs_cancelled,
                         extract(epoch FROM now() - last_seen)::float8
                     FROM lungmotion_workers
                     WHERE last_seen > now() - make_interval(secs => $1)
                     ORDER BY worker_id",
                    &[&stale],
                )
                .await
                .map_err(fail)?;
            counts.workers = workers
                .iter()
                .map(|r| WorkerStatus {
                    worker_id: r.get(0),
                    threads: r.get::<_, i32>(1) as i64,
                    running: r.get::<_, i32>(2) as i64,
                    done: r.get(3),
                    failed: r.get(4),
                    cancelled: r.get(5),
                    seen_s_ago: r.get(6),
                })
                .collect();
            Ok(counts)
        })
    }

    /// Takes the oldest queued job for `worker`: marks it running (an attempt more), leased
    /// for [`Postgres::lease`]. `None` when the queue is empty.
    pub fn claim(&self, worker: &str) -> Result<Option<JobRecord>> {
        let worker = worker.to_string();
        let lease = self.inner.lease.as_secs_f64();
        self.with_client(move |mut client, server| async move {
            let fail = database_error(&server);
            let tx = client.transaction().await.map_err(fail)?;
            let Some(row) = tx
                .query_opt(
                    "SELECT job_id, state, record FROM lungmotion_jobs WHERE state = 'queued'
                     ORDER BY seq LIMIT 1 FOR UPDATE SKIP LOCKED",
                    &[],
                )
                .await
                .map_err(fail)?
            else {
                return Ok(None);
            };
            let mut record = job_record(&row)?;
            super::jobs::mark_running(&mut record);
            let json = to_json(&record)?;
            tx.execute(
                "UPDATE lungmotion_jobs SET state = 'running', record = $2, lease_owner = $3,
                     lease_until = now() + make_interval(secs => $4)
                 WHERE job_id = $1",
                &[&record.job_id.to_string(), &json, &worker, &lease],
            )
            .await
            .map_err(fail)?;
            tx.commit().await.map_err(fail)?;
            Ok(Some(record))
        })
    }

    /// Renews `worker`'s lease of job `id`.
    pub fn renew(&self, id: JobId, worker: &str) -> Result<Lease> {
        let id = id.to_string();
        let worker = worker.to_string();
        let lease = self.inner.lease.as_secs_f64();
        self.with_client(move |client, server| async move {
            let row = client
                .query_opt(
                    "UPDATE lungmotion_jobs SET lease_until = now() + make_interval(secs => $3)
                     WHERE job_id = $1 AND lease_owner = $2
                         AND state IN ('running', 'cancelling')
                     RETURNING state",
                    &[&id, &worker, &lease],
                )
                .await
                .map_err(database_error(&server))?;
            Ok(match row.map(|r| r.get::<_, String>(0)) {
                None => Lease::Lost,
                Some(s) if s == "cancelling" => Lease::Cancelling,
                Some(_) => Lease::Held,
            })
        })
    }

    /// Writes a leased job's record as its worker has it: progress while running (a client's
    /// `cancelling` is kept), its end (the lease released). Nothing is written once the lease
    /// is lost; whether it was written.
    pub fn save_leased(&self, record: &JobRecord, worker: &str) -> Result<bool> {
        let id = record.job_id.to_string();
        let worker = worker.to_string();
        let json = to_json(record)?;
        let state = record.state.name();
        let notify = record.state == JobState::Queued;
        self.with_client(move |client, server| async move {
            let fail = database_error(&server);
            let n = client
                .execute(
                    &format!(
                        "UPDATE lungmotion_jobs SET
                             state = CASE WHEN state = 'cancelling' AND $3::text = 'running'
                                          THEN 'cancelling' ELSE $3::text END,
                             record = jsonb_set($2::jsonb, '{{state}}', to_jsonb(
                                          CASE WHEN state = 'cancelling' AND $3::text = 'running'
                                          THEN 'cancelling'::text ELSE $3::text END)),
                             lease_owner = CASE WHEN $3::text IN ('running', 'cancelling')
                                           THEN lease_owner ELSE NULL END,
                             callback_due = {}
                         WHERE job_id = $1 AND lease_owner = $4::text",
                        callback_due_of("$2")
                    ),
                    &[&id, &json, &state, &worker],
                )
                .await
                .map_err(fail)?;
            if notify && n > 0 {
                client
                    .execute("SELECT pg_notify($1, '')", &[&QUEUE_CHANNEL])
                    .await
                    .map_err(fail)?;
            }
            Ok(n > 0)
        })
    }

    /// Takes back the jobs whose lease expired, as a restart of the embedded server does
    /// (see [`super::jobs::recover`]); how many.
    pub fn reap(&self, max_attempts: u32) -> Result<usize> {
        let taken = self.with_client(move |mut client, server| async move {
            let fail = database_error(&server);
            let tx = client.transaction().await.map_err(fail)?;
            let rows = tx
                .query(
                    "SELECT job_id, state, record, lease_owner FROM lungmotion_jobs
                     WHERE state IN ('running', 'cancelling') AND lease_until < now()
                     FOR UPDATE SKIP LOCKED",
                    &[],
                )
                .await
                .map_err(fail)?;
            let mut taken = Vec::new();
            for row in &rows {
                let mut record = job_record(row)?;
                let owner: Option<String> = row.get(3);
                let why = format!(
                    "its worker {} stopped renewing its lease",
                    owner.as_deref().unwrap_or("(unknown)")
                );
                super::jobs::recover(&mut record, max_attempts, &why);
                super::jobs::begin_callback(&mut record);
                let json = to_json(&record)?;
                tx.execute(
                    &format!(
                        "UPDATE lungmotion_jobs SET state = $2, record = $3, lease_owner = NULL,
                             lease_until = NULL, callback_due = {}
                         WHERE job_id = $1",
                        callback_due_of("$3")
                    ),
                    &[&record.job_id.to_string(), &record.state.name(), &json],
                )
                .await
                .map_err(fail)?;
                taken.push(record);
            }
            if !taken.is_empty() {
                tx.execute("SELECT pg_notify($1, '')", &[&QUEUE_CHANNEL])
                    .await
                    .map_err(fail)?;
            }
            tx.commit().await.map_err(fail)?;
            Ok(taken)
        })?;
        for record in &taken {
            tracing::warn!(job = %record.job_id, state = record.state.name(), "lease expired; job taken back");
            if record.state.is_terminal() {
                let _ = self.inner.store.clear_partial_outputs(record.job_id);
            }
        }
        Ok(taken.len())
    }

    /// Takes the completion callback that has waited longest past its due time for this
    /// process to POST, holding it for `hold` (no other process takes it meanwhile; one that
    /// died with it is taken over once `hold` has passed). `None` when none is due.
    pub fn claim_callback(&self, hold: Duration) -> Result<Option<JobId>> {
        let hold = hold.as_secs_f64();
        let id = self.with_client(move |client, server| async move {
            let row = client
                .query_opt(
                    "UPDATE lungmotion_jobs SET callback_due = now() + make_interval(secs => $1)
                     WHERE job_id = (SELECT job_id FROM lungmotion_jobs
                                     WHERE callback_due <= now()
                                     ORDER BY callback_due LIMIT 1 FOR UPDATE SKIP LOCKED)
                     RETURNING job_id",
                    &[&hold],
                )
                .await
                .map_err(database_error(&server))?;
            Ok(row.map(|r| r.get::<_, String>(0)))
        })?;
        Ok(id.and_then(|id| JobId::parse(&id)))
    }

    /// Changes a job's callback record after a POST (see [`Postgres::claim_callback`]) and
    /// when the next one is due: `retry_in` from now, or never (`None`: delivered or given
    /// up). `false` when the job (or its callback) is gone.
    pub fn record_callback(
        &self,
        id: JobId,
        change: impl FnOnce(&mut super::callbacks::CallbackDelivery) + Send + 'static,
        retry_in: Option<Duration>,
    ) -> Result<bool> {
        let key = id.to_string();
        let retry_s = retry_in.map(|d| d.as_secs_f64());
        self.with_client(move |mut client, server| async move {
            let fail = database_error(&server);
            let tx = client.transaction().await.map_err(fail)?;
            let Some(row) = locked_job_row(&tx, &key).await.map_err(fail)? else {
                return Ok(false);
            };
            let mut record = job_record(&row)?;
            let Some(callback) = record.callback.as_mut() else {
                return Ok(false);
            };
            change(callback);
            let json = to_json(&record)?;
            tx.execute(
                "UPDATE lungmotion_jobs SET record = jsonb_set($2::jsonb, '{state}',
                         to_jsonb(state)),
                     callback_due = CASE WHEN $3::float8 IS NULL THEN NULL
                                    ELSE now() + make_interval(secs => $3::float8) END
                 WHERE job_id = $1",
                &[&key, &json, &retry_s],
            )
            .await
            .map_err(fail)?;
            tx.commit().await.map_err(fail)?;
            Ok(true)
        })
    }

    /// Records that worker `status.worker_id` is alive, with its counts.
    pub fn report_worker(&self, status: &WorkerStatus) -> Result<()> {
        let s = status.clone();
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "unknown".into());
        let pid = std::process::id() as i32;
        self.with_client(move |client, server| async move {
            client
                .execute(
                    "INSERT INTO lungmotion_workers (worker_id, host, pid, threads, started_at,
                         last_seen, running, jobs_done, jobs_failed, jobs_cancelled)
                     VALUES ($1, $2, $3, $4, now(), now(), $5, $6, $7, $8)
                     ON CONFLICT (worker_id) DO UPDATE SET last_seen = now(), running = $5,
                         jobs_done = $6, jobs_failed = $7, jobs_cancelled = $8",
                    &[
                        &s.worker_id,
                        &host,
                        &pid,
                        &(s.threads as i32),
                        &(s.running as i32),
                        &s.done,
                        &s.failed,
                        &s.cancelled,
                    ],
                )
                .await
                .map_err(database_error(&server))?;
            Ok(())
        })
    }
}

/// Listens on [`QUEUE_CHANNEL`] until the connection ends, waking idle workers at each
/// notification.
async fn listen_once(
    config: &tokio_postgres::Config,
    wake: &Arc<(Mutex<u64>, Condvar)>,
) -> std::result::Result<(), tokio_postgres::Error> {
    use futures_util::StreamExt;
    let (client, mut connection) = config.connect(NoTls).await?;
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let driver = tokio::spawn(async move {
        let mut messages = futures_util::stream::poll_fn(move |cx| connection.poll_message(cx));
        while let Some(message) = messages.next().await {
            match message {
                Ok(tokio_postgres::AsyncMessage::Notification(_)) => {
                    let _ = tx.send(());
                }
                Ok(_) => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    });
    client
        .batch_execute(&format!("LISTEN {QUEUE_CHANNEL}"))
        .await?;
    while rx.recv().await.is_some() {
        let (lock, cv) = &**wake;
        *lock.lock().unwrap_or_else(|p| p.into_inner()) += 1;
        cv.notify_all();
    }
    drop(client);
    driver.await.unwrap_or(Ok(()))
}

/// The records of a [`Postgres`] store as [`Records`]; a worker's writes of the jobs it runs
/// go through [`Postgres::save_leased`] instead (see [`LeasedRecords`]).
impl Records for Postgres {
    fn put_scan(&self, record: &ScanRecord, upload: &Path) -> Result<()> {
        self.inner.store.put_scan_files(record, upload, false)?;
        let id = record.scan_id.to_string();
        let created = record.created_at.clone();
        let json = to_json(record)?;
        let stored = self.with_client(move |client, server| async move {
            client
                .execute(
                    "INSERT INTO lungmotion_scans (scan_id, created_at, record) VALUES ($1, $2, $3)",
                    &[&id, &created, &json],
                )
                .await
                .map_err(database_error(&server))?;
            Ok(())
        });
        if stored.is_err() {
            let _ = self.inner.store.delete_scan(record.scan_id);
        }
        stored
    }

    fn scan(&self, id: ScanId) -> Result<Option<ScanRecord>> {
        let key = id.to_string();
        self.with_client(move |client, server| async move {
            let row = client
                .query_opt(
                    "SELECT record FROM lungmotion_scans WHERE scan_id = $1",
                    &[&key],
                )
                .await
                .map_err(database_error(&server))?;
            row.map(|r| {
                serde_json::from_value(r.get(0)).map_err(|e| Error::Store {
                    record: format!("lungmotion_scans {key}"),
                    reason: format!("corrupt record: {e}"),
                })
            })
            .transpose()
        })
    }

    fn delete_scan(&self, id: ScanId) -> Result<bool> {
        let key = id.to_string();
        let n = self.with_client(move |client, server| async move {
            client
                .execute("DELETE FROM lungmotion_scans WHERE scan_id = $1", &[&key])
                .await
                .map_err(database_error(&server))
        })?;
        let files = self.inner.store.delete_scan(id)?;
        Ok(n > 0 || files)
    }

    fn list_scans(&self) -> Result<(Vec<StoredScan>, Vec<String>)> {
        let rows = self.with_client(move |client, server| async move {
            let rows = client
                .query(
                    "SELECT scan_id, record FROM lungmotion_scans ORDER BY created_at",
                    &[],
                )
                .await
                .map_err(database_error(&server))?;
            Ok(rows
                .iter()
                .map(|r| (r.get::<_, String>(0), r.get::<_, serde_json::Value>(1)))
                .collect::<Vec<_>>())
        })?;
        let mut scans = Vec::new();
        let mut problems = Vec::new();
        for (id, value) in rows {
            match serde_json::from_value::<ScanRecord>(value) {
                Ok(record) => {
                    let bytes = self.inner.store.local_scan_bytes(record.scan_id);
                    scans.push((record, bytes));
                }
                Err(e) => problems.push(format!("lungmotion_scans {id}: corrupt record: {e}")),
            }
        }
        Ok((scans, problems))
    }

    fn put_job(
        &self,
        record: &JobRecord,
        request: &JobRequest,
        target: Option<&Path>,
    ) -> Result<()> {
        match self.submit(record, request, target, usize::MAX)? {
            Ok(true) => Ok(()),
            _ => Err(Error::Store {
                record: format!("lungmotion_jobs {}", record.job_id),
                reason: "its scan is gone".into(),
            }),
        }
    }

    fn save_job(&self, record: &JobRecord) -> Result<()> {
        let record = record.clone();
        self.update(record.job_id, move |stored| {
            *stored = record;
            (true, ())
        })?;
        Ok(())
    }

    fn job(&self, id: JobId) -> Result<Option<JobRecord>> {
        self.status(id)
    }

    fn job_request(&self, id: JobId) -> Result<JobRequest> {
        let key = id.to_string();
        self.with_client(move |client, server| async move {
            let row = client
                .query_opt(
                    "SELECT request FROM lungmotion_jobs WHERE job_id = $1",
                    &[&key],
                )
                .await
                .map_err(database_error(&server))?;
            let not = |reason: String| Error::Store {
                record: format!("lungmotion_jobs {key} request"),
                reason,
            };
            let value = row.ok_or_else(|| not("missing".into()))?.get(0);
            serde_json::from_value(value).map_err(|e| not(format!("corrupt record: {e}")))
        })
    }

    fn delete_job(&self, id: JobId) -> Result<bool> {
        self.remove_if(id, |_| true)
    }

    fn list_jobs(&self) -> Result<(Vec<JobRecord>, Vec<String>)> {
        Ok((self.records()?, Vec::new()))
    }
}

/// The records as a worker process writes them: a job's record only while this worker holds
/// its lease ([`Postgres::save_leased`]), everything else as [`Postgres`].
pub struct LeasedRecords {
    /// The store.
    pub pg: Postgres,
    /// This worker's id, the lease owner of the jobs it runs.
    pub worker: String,
}

impl Records for LeasedRecords {
    fn put_scan(&self, record: &ScanRecord, upload: &Path) -> Result<()> {
        self.pg.put_scan(record, upload)
    }
    fn scan(&self, id: ScanId) -> Result<Option<ScanRecord>> {
        self.pg.scan(id)
    }
    fn delete_scan(&self, id: ScanId) -> Result<bool> {
        Records::delete_scan(&self.pg, id)
    }
    fn list_scans(&self) -> Result<(Vec<StoredScan>, Vec<String>)> {
        self.pg.list_scans()
    }
    fn put_job(
        &self,
        record: &JobRecord,
        request: &JobRequest,
        target: Option<&Path>,
    ) -> Result<()> {
        Records::put_job(&self.pg, record, request, target)
    }
    fn save_job(&self, record: &JobRecord) -> Result<()> {
        if !self.pg.save_leased(record, &self.worker)? {
            tracing::warn!(job = %record.job_id, "lease lost: this worker's record of the job was not written");
        }
        Ok(())
    }
    fn job(&self, id: JobId) -> Result<Option<JobRecord>> {
        self.pg.status(id)
    }
    fn job_request(&self, id: JobId) -> Result<JobRequest> {
        self.pg.job_request(id)
    }
    fn delete_job(&self, id: JobId) -> Result<bool> {
        Records::delete_job(&self.pg, id)
    }
    fn list_jobs(&self) -> Result<(Vec<JobRecord>, Vec<String>)> {
        self.pg.list_jobs()
    }
}

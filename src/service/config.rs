//! How the service is set up: a TOML file, then the environment, then the command line, each
//! overriding the one before, merged in one place ([`ServiceConfig::resolve`]). Every key is
//! optional; unknown keys are refused by name.
//!
//! ```toml
//! listen = "127.0.0.1:8080"
//! data_dir = "lungmotion-data"
//! workers = 2                 # simulations at once; default one per core
//! queue_capacity = 16         # simulations waiting; beyond it, 429
//! max_upload_mib = 2048       # scan uploads
//! max_request_kib = 16384     # JSON and CSV bodies
//! api_token_file = "/etc/lungmotion/token"
//! shutdown_grace_s = 30
//! max_attempts = 2            # runs of one job across server restarts
//! max_connections = 256       # open at once; beyond, new ones wait to be accepted
//! header_read_timeout_s = 10  # a request's headers, whole
//! body_read_timeout_s = 30    # the longest pause inside a request body
//! ingest_timeout_s = 600      # reading and meshing one uploaded scan
//! ingest_memory_mib = 8192    # address space of the child reading one upload; 0: no limit
//! ingest_cache_mib = 1024     # scans kept read and ingested for the next job; 0: none
//! retention_max_age_days = 30 # finished jobs and unused scans older than this go; 0: kept
//! retention_max_store_gib = 100 # then oldest first while the store is larger; 0: no bound
//! retention_interval_s = 600  # how often retention runs (also once at start)
//! callback_secret_file = "/etc/lungmotion/callback-secret"  # signs completion callbacks
//! callback_max_attempts = 8   # POSTs of one callback before it is given up
//! callback_retry_base_s = 2   # wait after the first failed POST, doubling after each
//! callback_timeout_s = 10     # one POST, connection to answer
//! callback_allow_plain_http = false  # http:// callbacks beyond loopback
//! [run]                       # defaults of every simulation, as `lungmotion run --config`
//! element_size_mm = 6
//! [pacs]                      # the DICOMweb server of jobs' CTs and pushes (see pacs_settings)
//! url = "dicomweb://127.0.0.1:8042/dicom-web"
//! [store]                     # job and scan records in PostgreSQL (see postgres); default: data_dir
//! postgres_url = "postgres://lungmotion@db.example:5432/lungmotion"
//! postgres_password_file = "/etc/lungmotion/db-password"
//! lease_s = 30                # a running job's lease, renewed while it runs
//! connect_timeout_s = 60      # how long to keep trying to reach the database at start
//! object_store_url = "s3://lungmotion/site-a"  # uploads and outputs there (see blobs)
//! object_store_endpoint = "http://s3.example:9000"
//! object_store_region = "us-east-1"
//! object_store_access_key_id = "lungmotion"
//! object_store_secret_access_key_file = "/etc/lungmotion/s3-secret"
//! presigned_get = false       # outputs answered with 307 to a presigned URL
//! presigned_ttl_s = 300
//! object_store_multipart_part_mib = 16
//! fetched_scans_mib = 10240   # local copies of scans (uploads, fetches), LRU
//! ```

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::blobs::BlobSettings;
use super::pacs_settings::{self, PacsFile, PacsSettings, PACS_ENV_VARS};
use super::postgres::PostgresSettings;
use crate::error::{IoContext, IoOp};
use crate::run::RunConfig;
use crate::{Error, Result};

/// Largest service configuration file read, bytes.
const MAX_CONFIG_BYTES: u64 = 1 << 20;
/// Default address space of the ingest child, MiB: a 512 × 512 × 141 chest CT (POPI) is read
/// and meshed under `ulimit -v` 1.2 GiB (844 MB peak), so 8 GiB leaves room for 500-slice
/// scans while a hostile file's runaway allocation stops there.
pub const DEFAULT_INGEST_MEMORY_MIB: u64 = 8192;
/// Default memory for scans kept read and ingested between jobs, MiB: one POPI-sized chest
/// CT with its ingest (about 0.6 GB).
pub const DEFAULT_INGEST_CACHE_MIB: u64 = 1024;
/// Smallest ingest child limit accepted, MiB.
const MIN_INGEST_MEMORY_MIB: u64 = 256;
/// Default age after which finished jobs and unused scans are removed, days: a month covers
/// planning, review and the first treatment fractions, after which the planning system holds
/// the fields it imported.
pub const DEFAULT_RETENTION_MAX_AGE_DAYS: f64 = 30.0;
/// Default bound on the store's size, GiB: about 245 POPI-sized jobs with their scans (357 MB
/// and 81 MB), eight a day for the 30 days kept, so the age bound is what acts on a typical
/// department's load and this one stops a busy month from filling the disk.
pub const DEFAULT_RETENTION_MAX_STORE_GIB: f64 = 100.0;
/// Default time between two retention sweeps, s.
pub const DEFAULT_RETENTION_INTERVAL_S: f64 = 600.0;
/// Shortest callback secret accepted, characters.
const MIN_CALLBACK_SECRET_CHARS: usize = 16;

/// Everything the service can be told.
#[derive(Debug, Clone)]
pub struct ServiceConfig {
    /// Address and port to listen on (port 0 picks a free one).
    pub listen: SocketAddr,
    /// Root of the on-disk store (scans, jobs, uploads in progress).
    pub data_dir: PathBuf,
    /// Simulations run at once.
    pub workers: usize,
    /// Simulations waiting for a worker before new ones are refused with 429.
    pub queue_capacity: usize,
    /// Largest scan upload, bytes.
    pub max_upload_bytes: u64,
    /// Largest JSON or CSV request body, bytes.
    pub max_request_bytes: u64,
    /// Bearer token every `/v1` request must carry; required beyond loopback.
    pub api_token: Option<String>,
    /// How long a shutdown waits for running jobs before re-queueing them, seconds.
    pub shutdown_grace_s: f64,
    /// Runs of one job (the first and re-runs after a server stopped during it).
    pub max_attempts: u32,
    /// Connections served at once; further ones wait in the listen backlog.
    pub max_connections: usize,
    /// Longest time a client may take to send a request's headers, s.
    pub header_read_timeout_s: f64,
    /// Longest pause between two pieces of a request body, s.
    pub body_read_timeout_s: f64,
    /// Longest time the ingest of one upload may take before it is stopped, s.
    pub ingest_timeout_s: f64,
    /// Address space the ingest child may reserve, MiB (0: no limit; a thread is never limited).
    pub ingest_memory_mib: u64,
    /// Memory for scans kept read and ingested for the next job on them, MiB (0: none).
    pub ingest_cache_mib: u64,
    /// Where an upload's ingest runs (set by the program embedding the service, not by files).
    pub ingest_isolation: IngestIsolation,
    /// How long finished jobs and unused scans are kept.
    pub retention: RetentionSettings,
    /// How completion callbacks are signed and retried.
    pub callbacks: CallbackSettings,
    /// Defaults of every simulation; a request's options are merged over them.
    pub run: RunConfig,
    /// The DICOMweb server jobs take their CT from and push their outputs to, if any.
    pub pacs: Option<PacsSettings>,
    /// Where the job and scan records and the queue are when not in `data_dir`: PostgreSQL,
    /// shared by `lungmotion serve` (API) and `lungmotion worker` processes.
    pub postgres: Option<PostgresSettings>,
    /// Where scans' uploads and jobs' outputs are kept when not only in `data_dir`: an
    /// object store (`[store] object_store_url`).
    pub object_store: Option<BlobSettings>,
}

/// How long finished jobs and unused scans are kept (see [`super::retention`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RetentionSettings {
    /// Finished jobs and scans no live job uses are removed this long after they finished
    /// or were last used, days (0: no age limit).
    pub max_age_days: f64,
    /// Beyond this size of the store, the oldest of them are removed first, GiB (0: no limit).
    pub max_store_gib: f64,
    /// Time between two sweeps, s (the first runs at start).
    pub interval_s: f64,
}

impl Default for RetentionSettings {
    fn default() -> Self {
        RetentionSettings {
            max_age_days: DEFAULT_RETENTION_MAX_AGE_DAYS,
            max_store_gib: DEFAULT_RETENTION_MAX_STORE_GIB,
            interval_s: DEFAULT_RETENTION_INTERVAL_S,
        }
    }
}

/// How completion callbacks are signed and retried (see [`super::callbacks`]).
#[derive(Clone, PartialEq)]
pub struct CallbackSettings {
    /// The HMAC-SHA256 key of the signature; without one, callbacks are refused.
    pub secret: Option<String>,
    /// POSTs of one callback before it is given up.
    pub max_attempts: u32,
    /// Wait after the first failed POST, s; doubled after each further one (at most 5 min).
    pub retry_base_s: f64,
    /// Longest time for one POST, from connecting to the answer's headers, s.
    pub timeout_s: f64,
    /// Whether `http://` callbacks may go beyond loopback (unencrypted on the network).
    pub allow_plain_http: bool,
}

impl Default for CallbackSettings {
    fn default() -> Self {
        CallbackSettings {
            secret: None,
            max_attempts: 8,
            retry_base_s: 2.0,
            timeout_s: 10.0,
            allow_plain_http: false,
        }
    }
}

impl std::fmt::Debug for CallbackSettings {
    // The secret never reaches a log.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CallbackSettings")
            .field("secret", &self.secret.as_ref().map(|_| "<set>"))
            .field("max_attempts", &self.max_attempts)
            .field("retry_base_s", &self.retry_base_s)
            .field("timeout_s", &self.timeout_s)
            .field("allow_plain_http", &self.allow_plain_http)
            .finish()
    }
}

/// Where the ingest of an uploaded scan runs.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub enum IngestIsolation {
    /// On the server's blocking threads: a panic is contained, a reader that overflows its
    /// stack aborts the whole process (Rust cannot unwind a stack overflow).
    #[default]
    Thread,
    /// In a child process running `program serve --ingest-child` (the `lungmotion` binary),
    /// so that a reader crashing on a hostile file ends only the child.
    ChildProcess {
        /// The `lungmotion` executable.
        program: PathBuf,
    },
}

impl Default for ServiceConfig {
    fn default() -> Self {
        ServiceConfig {
            listen: SocketAddr::from(([127, 0, 0, 1], 8080)),
            data_dir: PathBuf::from("lungmotion-data"),
            workers: std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1),
            queue_capacity: 16,
            max_upload_bytes: 2048 << 20,
            max_request_bytes: 16 << 20,
            api_token: None,
            shutdown_grace_s: 30.0,
            max_attempts: 2,
            max_connections: 256,
            header_read_timeout_s: 10.0,
            body_read_timeout_s: 30.0,
            ingest_timeout_s: 600.0,
            ingest_memory_mib: DEFAULT_INGEST_MEMORY_MIB,
            ingest_cache_mib: DEFAULT_INGEST_CACHE_MIB,
            ingest_isolation: IngestIsolation::default(),
            retention: RetentionSettings::default(),
            callbacks: CallbackSettings::default(),
            run: RunConfig::default(),
            pacs: None,
            postgres: None,
            object_store: None,
        }
    }
}

/// The TOML file's shape: every key optional.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ServiceFile {
    listen: Option<String>,
    data_dir: Option<PathBuf>,
    workers: Option<usize>,
    queue_capacity: Option<usize>,
    max_upload_mib: Option<u64>,
    max_request_kib: Option<u64>,
    api_token_file: Option<PathBuf>,
    shutdown_grace_s: Option<f64>,
    max_attempts: Option<u32>,
    max_connections: Option<usize>,
    header_read_timeout_s: Option<f64>,
    body_read_timeout_s: Option<f64>,
    ingest_timeout_s: Option<f64>,
    ingest_memory_mib: Option<u64>,
    ingest_cache_mib: Option<u64>,
    retention_max_age_days: Option<f64>,
    retention_max_store_gib: Option<f64>,
    retention_interval_s: Option<f64>,
    callback_secret_file: Option<PathBuf>,
    callback_max_attempts: Option<u32>,
    callback_retry_base_s: Option<f64>,
    callback_timeout_s: Option<f64>,
    callback_allow_plain_http: Option<bool>,
    run: Option<toml::Value>,
    pacs: Option<PacsFile>,
    store: Option<StoreFile>,
}

/// The `[store]` table: where the records are when not in the data directory.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct StoreFile {
    postgres_url: Option<String>,
    postgres_password_file: Option<PathBuf>,
    lease_s: Option<f64>,
    connect_timeout_s: Option<f64>,
    object_store_url: Option<String>,
    object_store_endpoint: Option<String>,
    object_store_region: Option<String>,
    object_store_access_key_id: Option<String>,
    object_store_secret_access_key_file: Option<PathBuf>,
    presigned_get: Option<bool>,
    presigned_ttl_s: Option<f64>,
    object_store_multipart_part_mib: Option<u64>,
    fetched_scans_mib: Option<u64>,
}

/// What the command line (`lungmotion serve`) may override, each over the file and the
/// environment; `None` leaves the setting as they made it.
#[derive(Debug, Clone, Default)]
pub struct ServeOverrides {
    /// `--listen`: address and port, as text (checked when merged).
    pub listen: Option<String>,
    /// `--data-dir`: root of the on-disk store.
    pub data_dir: Option<PathBuf>,
    /// `--workers`: simulations at once.
    pub workers: Option<usize>,
    /// `--queue-capacity`: simulations that may wait.
    pub queue_capacity: Option<usize>,
    /// `--max-connections`: connections served at once.
    pub max_connections: Option<usize>,
    /// `--header-read-timeout-s`: longest time for a request's headers.
    pub header_read_timeout_s: Option<f64>,
    /// `--body-read-timeout-s`: longest pause inside a request body.
    pub body_read_timeout_s: Option<f64>,
}

/// Environment variables the service reads (each overrides the file's key).
pub const ENV_VARS: [&str; 34 + PACS_ENV_VARS.len()] = [
    "LUNGMOTION_LISTEN",
    "LUNGMOTION_DATA_DIR",
    "LUNGMOTION_WORKERS",
    "LUNGMOTION_QUEUE_CAPACITY",
    "LUNGMOTION_MAX_UPLOAD_MIB",
    "LUNGMOTION_API_TOKEN",
    "LUNGMOTION_API_TOKEN_FILE",
    "LUNGMOTION_MAX_CONNECTIONS",
    "LUNGMOTION_HEADER_READ_TIMEOUT_S",
    "LUNGMOTION_BODY_READ_TIMEOUT_S",
    "LUNGMOTION_INGEST_TIMEOUT_S",
    "LUNGMOTION_INGEST_MEMORY_MIB",
    "LUNGMOTION_INGEST_CACHE_MIB",
    "LUNGMOTION_RETENTION_MAX_AGE_DAYS",
    "LUNGMOTION_RETENTION_MAX_STORE_GIB",
    "LUNGMOTION_RETENTION_INTERVAL_S",
    "LUNGMOTION_CALLBACK_SECRET",
    "LUNGMOTION_CALLBACK_SECRET_FILE",
    "LUNGMOTION_CALLBACK_MAX_ATTEMPTS",
    "LUNGMOTION_CALLBACK_RETRY_BASE_S",
    "LUNGMOTION_CALLBACK_TIMEOUT_S",
    "LUNGMOTION_CALLBACK_ALLOW_PLAIN_HTTP",
    "LUNGMOTION_POSTGRES_URL",
    "LUNGMOTION_POSTGRES_PASSWORD_FILE",
    "LUNGMOTION_LEASE_S",
    "LUNGMOTION_POSTGRES_CONNECT_TIMEOUT_S",
    "LUNGMOTION_OBJECT_STORE_URL",
    "LUNGMOTION_S3_ENDPOINT",
    "LUNGMOTION_S3_REGION",
    "AWS_ACCESS_KEY_ID",
    "AWS_SECRET_ACCESS_KEY",
    "AWS_SECRET_ACCESS_KEY_FILE",
    "LUNGMOTION_PRESIGNED_GET",
    "LUNGMOTION_FETCHED_SCANS_MIB",
    PACS_ENV_VARS[0],
    PACS_ENV_VARS[1],
    PACS_ENV_VARS[2],
    PACS_ENV_VARS[3],
    PACS_ENV_VARS[4],
    PACS_ENV_VARS[5],
    PACS_ENV_VARS[6],
    PACS_ENV_VARS[7],
    PACS_ENV_VARS[8],
];

impl ServiceConfig {
    /// Reads the optional TOML file, then applies `env` (name → value, as from the process
    /// environment) and validates; the error names the file or variable and the key.
    pub fn load(file: Option<&Path>, env: &dyn Fn(&str) -> Option<String>) -> Result<Self> {
        let config = Self::from_sources(file, env)?;
        config.validate()?;
        Ok(config)
    }

    /// The service's settings from all three sources: the optional TOML `file`, then `env`
    /// (name → value, as from the process environment), then the command line's
    /// `overrides`; the result is validated once. Errors name the source and the key.
    pub fn resolve(
        file: Option<&Path>,
        env: &dyn Fn(&str) -> Option<String>,
        overrides: &ServeOverrides,
    ) -> Result<Self> {
        let mut config = Self::from_sources(file, env)?;
        config.apply_overrides(overrides)?;
        config.validate()?;
        Ok(config)
    }

    /// As [`ServiceConfig::load`] without the final validation, for callers that override
    /// more and validate the result once (as [`ServiceConfig::resolve`] does).
    pub fn from_sources(file: Option<&Path>, env: &dyn Fn(&str) -> Option<String>) -> Result<Self> {
        let mut config = ServiceConfig::default();
        if let Some(path) = file {
            config.apply_file(path)?;
        }
        config.apply_env(env)?;
        Ok(config)
    }

    fn apply_file(&mut self, path: &Path) -> Result<()> {
        let bad = |m: String| Error::Config {
            settings: "configuration",
            file: Some(path.to_path_buf()),
            key: None,
            reason: m,
        };
        let meta = std::fs::metadata(path).at(IoOp::Read, path)?;
        if meta.len() > MAX_CONFIG_BYTES {
            return Err(bad(format!(
                "{} bytes is not a configuration file",
                meta.len()
            )));
        }
        let text = std::fs::read_to_string(path).at(IoOp::Read, path)?;
        let file: ServiceFile = toml::from_str(&text).map_err(|e| {
            let (key, reason) = crate::run::toml_key::describe(&text, &e);
            Error::Config {
                settings: "configuration",
                file: Some(path.to_path_buf()),
                key,
                reason,
            }
        })?;
        if let Some(listen) = file.listen {
            self.listen = parse_listen(&listen).map_err(|m| bad(format!("listen: {m}")))?;
        }
        if let Some(dir) = file.data_dir {
            // Relative to the configuration file, as a hospital's deployment expects.
            self.data_dir = match path.parent() {
                Some(parent) if dir.is_relative() => parent.join(dir),
                _ => dir,
            };
        }
        set(&mut self.workers, file.workers);
        set(&mut self.queue_capacity, file.queue_capacity);
        if let Some(mib) = file.max_upload_mib {
            self.max_upload_bytes = mib.saturating_mul(1 << 20);
        }
        if let Some(kib) = file.max_request_kib {
            self.max_request_bytes = kib.saturating_mul(1 << 10);
        }
        if let Some(token_file) = file.api_token_file {
            self.api_token = Some(read_token_file(&token_file)?);
        }
        set(&mut self.shutdown_grace_s, file.shutdown_grace_s);
        set(&mut self.max_attempts, file.max_attempts);
        set(&mut self.max_connections, file.max_connections);
        set(&mut self.header_read_timeout_s, file.header_read_timeout_s);
        set(&mut self.body_read_timeout_s, file.body_read_timeout_s);
        set(&mut self.ingest_timeout_s, file.ingest_timeout_s);
        set(&mut self.ingest_memory_mib, file.ingest_memory_mib);
        set(&mut self.ingest_cache_mib, file.ingest_cache_mib);
        set(
            &mut self.retention.max_age_days,
            file.retention_max_age_days,
        );
        set(
            &mut self.retention.max_store_gib,
            file.retention_max_store_gib,
        );
        set(&mut self.retention.interval_s, file.retention_interval_s);
        if let Some(secret_file) = file.callback_secret_file {
            self.callbacks.secret = Some(read_token_file(&secret_file)?);
        }
        set(&mut self.callbacks.max_attempts, file.callback_max_attempts);
        set(&mut self.callbacks.retry_base_s, file.callback_retry_base_s);
        set(&mut self.callbacks.timeout_s, file.callback_timeout_s);
        set(
            &mut self.callbacks.allow_plain_http,
            file.callback_allow_plain_http,
        );
        if let Some(pacs) = file.pacs {
            pacs_settings::apply_file(&mut self.pacs, pacs).map_err(|e| bad(e.to_string()))?;
        }
        if let Some(store) = file.store {
            self.apply_store_file(store)?;
        }
        if let Some(run) = file.run {
            let text = toml::to_string(&run).map_err(|e| bad(format!("[run]: {e}")))?;
            self.run = RunConfig::from_toml(&text).map_err(|e| bad(format!("[run]: {e}")))?;
        }
        Ok(())
    }

    fn apply_env(&mut self, env: &dyn Fn(&str) -> Option<String>) -> Result<()> {
        fn parsed<T: std::str::FromStr>(name: &str, value: &str) -> Result<T> {
            value.trim().parse().map_err(|_| {
                Error::settings(
                    "service configuration",
                    format!("environment {name}={value:?} is not a valid number"),
                )
            })
        }
        if let Some(v) = env("LUNGMOTION_LISTEN") {
            self.listen = parse_listen(&v).map_err(|m| {
                Error::settings(
                    "service configuration",
                    format!("environment LUNGMOTION_LISTEN: {m}"),
                )
            })?;
        }
        if let Some(v) = env("LUNGMOTION_DATA_DIR") {
            self.data_dir = PathBuf::from(v);
        }
        if let Some(v) = env("LUNGMOTION_WORKERS") {
            self.workers = parsed("LUNGMOTION_WORKERS", &v)?;
        }
        if let Some(v) = env("LUNGMOTION_QUEUE_CAPACITY") {
            self.queue_capacity = parsed("LUNGMOTION_QUEUE_CAPACITY", &v)?;
        }
        if let Some(v) = env("LUNGMOTION_MAX_UPLOAD_MIB") {
            let mib: u64 = parsed("LUNGMOTION_MAX_UPLOAD_MIB", &v)?;
            self.max_upload_bytes = mib.saturating_mul(1 << 20);
        }
        if let Some(v) = env("LUNGMOTION_MAX_CONNECTIONS") {
            self.max_connections = parsed("LUNGMOTION_MAX_CONNECTIONS", &v)?;
        }
        if let Some(v) = env("LUNGMOTION_HEADER_READ_TIMEOUT_S") {
            self.header_read_timeout_s = parsed("LUNGMOTION_HEADER_READ_TIMEOUT_S", &v)?;
        }
        if let Some(v) = env("LUNGMOTION_BODY_READ_TIMEOUT_S") {
            self.body_read_timeout_s = parsed("LUNGMOTION_BODY_READ_TIMEOUT_S", &v)?;
        }
        if let Some(v) = env("LUNGMOTION_INGEST_TIMEOUT_S") {
            self.ingest_timeout_s = parsed("LUNGMOTION_INGEST_TIMEOUT_S", &v)?;
        }
        if let Some(v) = env("LUNGMOTION_INGEST_MEMORY_MIB") {
            self.ingest_memory_mib = parsed("LUNGMOTION_INGEST_MEMORY_MIB", &v)?;
        }
        if let Some(v) = env("LUNGMOTION_INGEST_CACHE_MIB") {
            self.ingest_cache_mib = parsed("LUNGMOTION_INGEST_CACHE_MIB", &v)?;
        }
        self.apply_retention_and_callback_env(env)?;
        self.apply_store_env(env)?;
        pacs_settings::apply_env(&mut self.pacs, env)?;
        if let Some(v) = env("LUNGMOTION_API_TOKEN_FILE") {
            self.api_token = Some(read_token_file(Path::new(&v))?);
        }
        if let Some(v) = env("LUNGMOTION_API_TOKEN") {
            self.api_token = Some(v.trim().to_string());
        }
        Ok(())
    }

    fn apply_retention_and_callback_env(
        &mut self,
        env: &dyn Fn(&str) -> Option<String>,
    ) -> Result<()> {
        fn parsed<T: std::str::FromStr>(name: &str, value: &str, what: &str) -> Result<T> {
            value.trim().parse().map_err(|_| {
                Error::settings(
                    "service configuration",
                    format!("environment {name}={value:?} is not {what}"),
                )
            })
        }
        let number = "a valid number";
        for (name, slot) in [
            (
                "LUNGMOTION_RETENTION_MAX_AGE_DAYS",
                &mut self.retention.max_age_days,
            ),
            (
                "LUNGMOTION_RETENTION_MAX_STORE_GIB",
                &mut self.retention.max_store_gib,
            ),
            (
                "LUNGMOTION_RETENTION_INTERVAL_S",
                &mut self.retention.interval_s,
            ),
            (
                "LUNGMOTION_CALLBACK_RETRY_BASE_S",
                &mut self.callbacks.retry_base_s,
            ),
            (
                "LUNGMOTION_CALLBACK_TIMEOUT_S",
                &mut self.callbacks.timeout_s,
            ),
        ] {
            if let Some(v) = env(name) {
                *slot = parsed(name, &v, number)?;
            }
        }
        if let Some(v) = env("LUNGMOTION_CALLBACK_MAX_ATTEMPTS") {
            self.callbacks.max_attempts = parsed("LUNGMOTION_CALLBACK_MAX_ATTEMPTS", &v, number)?;
        }
        if let Some(v) = env("LUNGMOTION_CALLBACK_ALLOW_PLAIN_HTTP") {
            self.callbacks.allow_plain_http =
                parsed("LUNGMOTION_CALLBACK_ALLOW_PLAIN_HTTP", &v, "true or false")?;
        }
        if let Some(v) = env("LUNGMOTION_CALLBACK_SECRET_FILE") {
            self.callbacks.secret = Some(read_token_file(Path::new(&v))?);
        }
        if let Some(v) = env("LUNGMOTION_CALLBACK_SECRET") {
            self.callbacks.secret = Some(v.trim().to_string());
        }
        Ok(())
    }

    /// Applies the command line's values over the file's and the environment's.
    fn apply_overrides(&mut self, overrides: &ServeOverrides) -> Result<()> {
        if let Some(listen) = &overrides.listen {
            self.listen = parse_listen(listen)
                .map_err(|m| Error::settings("service configuration", format!("--listen {m}")))?;
        }
        if let Some(dir) = &overrides.data_dir {
            self.data_dir = dir.clone();
        }
        set(&mut self.workers, overrides.workers);
        set(&mut self.queue_capacity, overrides.queue_capacity);
        set(&mut self.max_connections, overrides.max_connections);
        set(
            &mut self.header_read_timeout_s,
            overrides.header_read_timeout_s,
        );
        set(&mut self.body_read_timeout_s, overrides.body_read_timeout_s);
        Ok(())
    }

    /// Refuses settings the service cannot run with, naming the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: &str| Err(Error::settings("service configuration", m));
        if self.workers == 0 || self.workers > 256 {
            return bad("workers must be 1–256");
        }
        if self.queue_capacity == 0 || self.queue_capacity > 100_000 {
            return bad("queue_capacity must be 1–100000");
        }
        if self.max_upload_bytes < 1 << 10 {
            return bad("max_upload_mib must be at least 1");
        }
        if self.max_request_bytes < 1 << 10 {
            return bad("max_request_kib must be at least 1");
        }
        if !(self.shutdown_grace_s.is_finite() && self.shutdown_grace_s >= 0.0) {
            return bad("shutdown_grace_s must be a non-negative number of seconds");
        }
        if self.max_attempts == 0 {
            return bad("max_attempts must be at least 1");
        }
        if self.max_connections == 0 || self.max_connections > 100_000 {
            return bad(&format!(
                "max_connections must be 1–100000, not {}",
                self.max_connections
            ));
        }
        for (key, seconds) in [
            ("header_read_timeout_s", self.header_read_timeout_s),
            ("body_read_timeout_s", self.body_read_timeout_s),
            ("ingest_timeout_s", self.ingest_timeout_s),
        ] {
            // Zero or endless would hand every connection or ingest to whoever holds it.
            if !(seconds.is_finite() && seconds > 0.0 && seconds <= 86_400.0) {
                return bad(&format!(
                    "{key} must be a number of seconds above 0 and at most 86400, not {seconds}"
                ));
            }
        }
        // Below this the child's own threads and allocator arenas fail before any reader runs,
        // which would refuse every upload for a reason that is not the upload's.
        if self.ingest_memory_mib != 0 && self.ingest_memory_mib < MIN_INGEST_MEMORY_MIB {
            return bad(&format!(
                "ingest_memory_mib must be 0 (no limit) or at least {MIN_INGEST_MEMORY_MIB}, not {}",
                self.ingest_memory_mib
            ));
        }
        self.validate_retention_and_callbacks()?;
        if let Some(postgres) = &self.postgres {
            postgres.validate()?;
        }
        if let Some(blobs) = &self.object_store {
            blobs.validate()?;
        }
        if let Some(pacs) = &self.pacs {
            pacs.validate()?;
        }
        if let Some(token) = &self.api_token {
            if token.len() < 8 || token.chars().any(|c| c.is_whitespace() || c.is_control()) {
                return bad("the API token must be at least 8 characters without spaces");
            }
        }
        if !self.listen.ip().is_loopback() && self.api_token.is_none() {
            return bad(&format!(
                "listening on {} (beyond loopback) needs a bearer token: set LUNGMOTION_API_TOKEN \
                 or LUNGMOTION_API_TOKEN_FILE, or api_token_file in the configuration",
                self.listen
            ));
        }
        self.run.validate()
    }
}

impl ServiceConfig {
    /// Refuses retention and callback settings that cannot work, naming the key and value.
    fn validate_retention_and_callbacks(&self) -> Result<()> {
        let bad = |m: String| Err(Error::settings("service configuration", m));
        let RetentionSettings {
            max_age_days,
            max_store_gib,
            interval_s,
        } = self.retention;
        if !(max_age_days.is_finite() && (0.0..=36_500.0).contains(&max_age_days)) {
            return bad(format!(
                "retention_max_age_days must be 0 (no age limit) or a number of days up to \
                 36500, not {max_age_days}"
            ));
        }
        if !(max_store_gib.is_finite() && max_store_gib >= 0.0) {
            return bad(format!(
                "retention_max_store_gib must be 0 (no size limit) or a positive number of \
                 GiB, not {max_store_gib}"
            ));
        }
        if !(interval_s.is_finite() && (0.1..=86_400.0).contains(&interval_s)) {
            return bad(format!(
                "retention_interval_s must be a number of seconds from 0.1 to 86400, not \
                 {interval_s}"
            ));
        }
        let c = &self.callbacks;
        if !(1..=20).contains(&c.max_attempts) {
            return bad(format!(
                "callback_max_attempts must be 1–20, not {}",
                c.max_attempts
            ));
        }
        for (key, seconds, most) in [
            ("callback_retry_base_s", c.retry_base_s, 3_600.0),
            ("callback_timeout_s", c.timeout_s, 300.0),
        ] {
            if !(seconds.is_finite() && seconds > 0.0 && seconds <= most) {
                return bad(format!(
                    "{key} must be a number of seconds above 0 and at most {most}, not {seconds}"
                ));
            }
        }
        if let Some(secret) = &c.secret {
            if secret.chars().count() < MIN_CALLBACK_SECRET_CHARS
                || secret
                    .chars()
                    .any(|ch| ch.is_whitespace() || ch.is_control())
            {
                return bad(format!(
                    "the callback secret (callback_secret_file, LUNGMOTION_CALLBACK_SECRET or \
                     _FILE) must be at least {MIN_CALLBACK_SECRET_CHARS} characters without \
                     spaces; it has {}",
                    secret.chars().count()
                ));
            }
        }
        Ok(())
    }
}

impl ServiceConfig {
    /// The `[store]` table over the defaults: lease and timeouts apply once a URL is set
    /// (here or in the environment).
    fn apply_store_file(&mut self, file: StoreFile) -> Result<()> {
        let blobs = self
            .object_store
            .get_or_insert_with(|| BlobSettings::new(String::new()));
        set(&mut blobs.url, file.object_store_url);
        blobs.endpoint = file.object_store_endpoint.or(blobs.endpoint.take());
        blobs.region = file.object_store_region.or(blobs.region.take());
        blobs.access_key_id = file
            .object_store_access_key_id
            .or(blobs.access_key_id.take());
        if let Some(path) = file.object_store_secret_access_key_file {
            blobs.secret_access_key = Some(read_token_file(&path)?);
        }
        set(&mut blobs.presigned_get, file.presigned_get);
        set(&mut blobs.presigned_ttl_s, file.presigned_ttl_s);
        set(
            &mut blobs.multipart_part_mib,
            file.object_store_multipart_part_mib,
        );
        set(&mut blobs.fetched_scans_mib, file.fetched_scans_mib);
        let postgres = self
            .postgres
            .get_or_insert_with(|| PostgresSettings::new(String::new()));
        set(&mut postgres.url, file.postgres_url);
        if let Some(path) = file.postgres_password_file {
            postgres.password = Some(read_token_file(&path)?);
        }
        set(&mut postgres.lease_s, file.lease_s);
        set(&mut postgres.connect_timeout_s, file.connect_timeout_s);
        // Kept even without a URL here: `LUNGMOTION_POSTGRES_URL` may give it (a Secret
        // in a container), and the file's tuning must then apply, not be dropped.
        Ok(())
    }

    /// `LUNGMOTION_POSTGRES_URL`, `_PASSWORD_FILE`, `LUNGMOTION_LEASE_S` and
    /// `LUNGMOTION_POSTGRES_CONNECT_TIMEOUT_S` over the file's `[store]`.
    fn apply_store_env(&mut self, env: &dyn Fn(&str) -> Option<String>) -> Result<()> {
        self.apply_object_store_env(env)?;
        if let Some(url) = env("LUNGMOTION_POSTGRES_URL") {
            let url = url.trim().to_string();
            match &mut self.postgres {
                Some(p) => p.url = url,
                None => self.postgres = Some(PostgresSettings::new(url)),
            }
        }
        if self.postgres.as_ref().is_some_and(|p| p.url.is_empty()) {
            // Only tuning and no database anywhere: the directory store, as before.
            self.postgres = None;
        }
        let Some(postgres) = self.postgres.as_mut() else {
            return Ok(());
        };
        if let Some(path) = env("LUNGMOTION_POSTGRES_PASSWORD_FILE") {
            postgres.password = Some(read_token_file(Path::new(&path))?);
        }
        for (name, slot) in [
            ("LUNGMOTION_LEASE_S", &mut postgres.lease_s),
            (
                "LUNGMOTION_POSTGRES_CONNECT_TIMEOUT_S",
                &mut postgres.connect_timeout_s,
            ),
        ] {
            if let Some(v) = env(name) {
                *slot = v.trim().parse().map_err(|_| {
                    Error::settings(
                        "service configuration",
                        format!("environment {name}={v:?} is not a valid number"),
                    )
                })?;
            }
        }
        Ok(())
    }
}

impl ServiceConfig {
    /// `LUNGMOTION_OBJECT_STORE_URL`, `LUNGMOTION_S3_ENDPOINT`, `LUNGMOTION_S3_REGION`,
    /// `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY` (or `_FILE`) and `LUNGMOTION_PRESIGNED_GET`
    /// over the file's `[store]`; settings without a URL leave the data directory the store.
    fn apply_object_store_env(&mut self, env: &dyn Fn(&str) -> Option<String>) -> Result<()> {
        let blobs = self
            .object_store
            .get_or_insert_with(|| BlobSettings::new(String::new()));
        if let Some(url) = env("LUNGMOTION_OBJECT_STORE_URL") {
            blobs.url = url.trim().to_string();
        }
        if blobs.url.is_empty() {
            // Only tuning, or nothing: the directory store, as before.
            self.object_store = None;
            return Ok(());
        }
        if let Some(v) = env("LUNGMOTION_S3_ENDPOINT") {
            blobs.endpoint = Some(v.trim().to_string());
        }
        if let Some(v) = env("LUNGMOTION_S3_REGION") {
            blobs.region = Some(v.trim().to_string());
        }
        if let Some(v) = env("AWS_ACCESS_KEY_ID") {
            blobs.access_key_id = Some(v.trim().to_string());
        }
        if let Some(v) = env("AWS_SECRET_ACCESS_KEY") {
            blobs.secret_access_key = Some(v.trim().to_string());
        }
        if let Some(path) = env("AWS_SECRET_ACCESS_KEY_FILE") {
            blobs.secret_access_key = Some(read_token_file(Path::new(&path))?);
        }
        if let Some(v) = env("LUNGMOTION_FETCHED_SCANS_MIB") {
            blobs.fetched_scans_mib = v.trim().parse().map_err(|_| {
                Error::settings(
                    "service configuration",
                    format!(
                        "environment LUNGMOTION_FETCHED_SCANS_MIB={v:?} is not a whole number \
                         of MiB"
                    ),
                )
            })?;
        }
        if let Some(v) = env("LUNGMOTION_PRESIGNED_GET") {
            blobs.presigned_get = match v.trim() {
                "1" | "true" | "yes" => true,
                "0" | "false" | "no" => false,
                other => {
                    return Err(Error::settings(
                        "service configuration",
                        format!(
                            "environment LUNGMOTION_PRESIGNED_GET={other:?} is not true or false"
                        ),
                    ))
                }
            };
        }
        Ok(())
    }
}

fn set<T>(slot: &mut T, value: Option<T>) {
    if let Some(v) = value {
        *slot = v;
    }
}

/// Parses a listening address; the error says what was expected.
pub fn parse_listen(text: &str) -> std::result::Result<SocketAddr, String> {
    text.trim()
        .parse()
        .map_err(|_| format!("{text:?} is not an address:port such as 127.0.0.1:8080"))
}

fn read_token_file(path: &Path) -> Result<String> {
    let text = std::fs::read_to_string(path).at(IoOp::Read, path)?;
    Ok(text.trim().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn no_env(_: &str) -> Option<String> {
        None
    }

    #[test]
    fn file_then_environment_override_defaults() {
        let dir = std::env::temp_dir().join(format!("lm-svc-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("service.toml");
        std::fs::write(
            &path,
            "listen = \"127.0.0.1:9000\"\ndata_dir = \"store\"\nworkers = 3\nqueue_capacity = 5\n\
             [run]\nelement_size_mm = 10\n",
        )
        .unwrap();
        let c = ServiceConfig::load(Some(&path), &no_env).unwrap();
        assert_eq!(c.listen.port(), 9000);
        assert_eq!(c.data_dir, dir.join("store"));
        assert_eq!((c.workers, c.queue_capacity), (3, 5));
        assert_eq!(c.run.element_size_mm, 10.0);
        let env = |k: &str| match k {
            "LUNGMOTION_WORKERS" => Some("1".to_string()),
            "LUNGMOTION_MAX_UPLOAD_MIB" => Some("7".to_string()),
            _ => None,
        };
        let c = ServiceConfig::load(Some(&path), &env).unwrap();
        assert_eq!((c.workers, c.max_upload_bytes), (1, 7 << 20));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_files_store_tuning_applies_when_the_database_url_comes_from_the_environment() {
        let dir = std::env::temp_dir().join(format!("lm-svc-config-store-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("service.toml");
        let url = |k: &str| {
            (k == "LUNGMOTION_POSTGRES_URL").then(|| "postgres://lm@db:5432/lm".to_string())
        };
        std::fs::write(
            &path,
            "[store]
lease_s = 12
connect_timeout_s = 5
",
        )
        .unwrap();
        let c = ServiceConfig::load(Some(&path), &url).unwrap();
        let p = c.postgres.expect("the environment's database");
        assert_eq!(
            (p.url.as_str(), p.lease_s, p.connect_timeout_s),
            ("postgres://lm@db:5432/lm", 12.0, 5.0)
        );
        // Without a URL anywhere the tuning is moot: the directory store.
        assert!(ServiceConfig::load(Some(&path), &no_env)
            .unwrap()
            .postgres
            .is_none());
        // A bad value in the file is refused once a database is in use.
        std::fs::write(
            &path,
            "[store]
lease_s = 0.5
",
        )
        .unwrap();
        let e = ServiceConfig::load(Some(&path), &url)
            .unwrap_err()
            .to_string();
        assert!(e.contains("lease_s"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn connection_limits_come_from_file_environment_and_flags_and_are_checked() {
        let dir = std::env::temp_dir().join(format!("lm-svc-config-conn-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("service.toml");
        std::fs::write(
            &path,
            "max_connections = 40\nheader_read_timeout_s = 2.5\nbody_read_timeout_s = 7\n\
             ingest_timeout_s = 90\ningest_memory_mib = 3000\n",
        )
        .unwrap();
        let c = ServiceConfig::load(Some(&path), &no_env).unwrap();
        assert_eq!((c.max_connections, c.ingest_memory_mib), (40, 3000));
        let env = |k: &str| (k == "LUNGMOTION_INGEST_MEMORY_MIB").then(|| "100".to_string());
        let e = ServiceConfig::load(Some(&path), &env).unwrap_err();
        assert!(e.to_string().contains("ingest_memory_mib"), "{e}");
        assert_eq!(
            (
                c.header_read_timeout_s,
                c.body_read_timeout_s,
                c.ingest_timeout_s
            ),
            (2.5, 7.0, 90.0)
        );
        let env = |k: &str| match k {
            "LUNGMOTION_MAX_CONNECTIONS" => Some("30".to_string()),
            "LUNGMOTION_BODY_READ_TIMEOUT_S" => Some("3".to_string()),
            _ => None,
        };
        let flags = ServeOverrides {
            max_connections: Some(20),
            header_read_timeout_s: Some(1.0),
            ..ServeOverrides::default()
        };
        let c = ServiceConfig::resolve(Some(&path), &env, &flags).unwrap();
        assert_eq!(c.max_connections, 20);
        assert_eq!((c.header_read_timeout_s, c.body_read_timeout_s), (1.0, 3.0));
        for (flags, named) in [
            (
                ServeOverrides {
                    header_read_timeout_s: Some(0.0),
                    ..ServeOverrides::default()
                },
                "header_read_timeout_s",
            ),
            (
                ServeOverrides {
                    body_read_timeout_s: Some(f64::INFINITY),
                    ..ServeOverrides::default()
                },
                "body_read_timeout_s",
            ),
            (
                ServeOverrides {
                    max_connections: Some(0),
                    ..ServeOverrides::default()
                },
                "max_connections",
            ),
        ] {
            let e = ServiceConfig::resolve(None, &no_env, &flags).unwrap_err();
            assert!(e.to_string().contains(named), "{e}");
        }
        let env = |k: &str| (k == "LUNGMOTION_INGEST_TIMEOUT_S").then(|| "soon".to_string());
        let e = ServiceConfig::load(None, &env).unwrap_err();
        assert!(e.to_string().contains("LUNGMOTION_INGEST_TIMEOUT_S"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn retention_and_callback_settings_come_from_file_and_environment_and_are_checked() {
        let c = ServiceConfig::load(None, &no_env).unwrap();
        assert_eq!(c.retention, RetentionSettings::default());
        assert_eq!(
            (c.retention.max_age_days, c.retention.max_store_gib),
            (30.0, 100.0)
        );
        assert_eq!(
            (c.callbacks.secret.as_deref(), c.callbacks.max_attempts),
            (None, 8)
        );
        let dir = std::env::temp_dir().join(format!("lm-svc-config-ret-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let secret_path = dir.join("callback-secret");
        std::fs::write(&secret_path, "from-the-file-0123456789\n").unwrap();
        let path = dir.join("service.toml");
        std::fs::write(
            &path,
            format!(
                "retention_max_age_days = 7\nretention_max_store_gib = 20.5\n\
                 retention_interval_s = 60\ncallback_secret_file = {:?}\n\
                 callback_max_attempts = 3\ncallback_allow_plain_http = true\n",
                secret_path.display().to_string()
            ),
        )
        .unwrap();
        let c = ServiceConfig::load(Some(&path), &no_env).unwrap();
        assert_eq!(
            c.retention,
            RetentionSettings {
                max_age_days: 7.0,
                max_store_gib: 20.5,
                interval_s: 60.0
            }
        );
        assert_eq!(
            c.callbacks.secret.as_deref(),
            Some("from-the-file-0123456789")
        );
        assert!(c.callbacks.allow_plain_http);
        assert_eq!(c.callbacks.max_attempts, 3);
        // The secret never reaches a log through the settings' debug form.
        assert!(!format!("{c:?}").contains("from-the-file"), "{c:?}");
        let env = |k: &str| match k {
            "LUNGMOTION_RETENTION_MAX_AGE_DAYS" => Some("0.5".to_string()),
            "LUNGMOTION_CALLBACK_SECRET" => Some("from-the-environment-01".to_string()),
            "LUNGMOTION_CALLBACK_RETRY_BASE_S" => Some("0.25".to_string()),
            _ => None,
        };
        let c = ServiceConfig::load(Some(&path), &env).unwrap();
        assert_eq!(c.retention.max_age_days, 0.5);
        assert_eq!(c.callbacks.retry_base_s, 0.25);
        assert_eq!(
            c.callbacks.secret.as_deref(),
            Some("from-the-environment-01")
        );
        for (name, value, named) in [
            (
                "LUNGMOTION_RETENTION_MAX_AGE_DAYS",
                "-1",
                "retention_max_age_days must",
            ),
            (
                "LUNGMOTION_RETENTION_MAX_AGE_DAYS",
                "a month",
                "LUNGMOTION_RETENTION_MAX_AGE_DAYS",
            ),
            (
                "LUNGMOTION_RETENTION_MAX_STORE_GIB",
                "inf",
                "retention_max_store_gib",
            ),
            (
                "LUNGMOTION_RETENTION_INTERVAL_S",
                "0",
                "retention_interval_s",
            ),
            (
                "LUNGMOTION_CALLBACK_MAX_ATTEMPTS",
                "0",
                "callback_max_attempts must be 1–20, not 0",
            ),
            ("LUNGMOTION_CALLBACK_TIMEOUT_S", "900", "callback_timeout_s"),
            (
                "LUNGMOTION_CALLBACK_ALLOW_PLAIN_HTTP",
                "yes",
                "true or false",
            ),
            (
                "LUNGMOTION_CALLBACK_SECRET",
                "short",
                "at least 16 characters",
            ),
        ] {
            let env = |k: &str| (k == name).then(|| value.to_string());
            let e = ServiceConfig::load(None, &env).unwrap_err().to_string();
            // A secret is never echoed; every other value is.
            let secret = name == "LUNGMOTION_CALLBACK_SECRET";
            assert!(
                e.contains(named) && e.contains(value) != secret,
                "{name}={value}: {e}"
            );
        }
        std::fs::write(&path, "retention_max_age_days = -3\n").unwrap();
        let e = ServiceConfig::load(Some(&path), &no_env)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("retention_max_age_days") && e.contains("-3"),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_pacs_comes_from_the_files_table_and_the_environment() {
        let dir = std::env::temp_dir().join(format!("lm-svc-config-pacs-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("service.toml");
        std::fs::write(
            &path,
            "[pacs]\nurl = \"dicomweb://127.0.0.1:8042/dicom-web\"\npush = true\n",
        )
        .unwrap();
        let c = ServiceConfig::load(Some(&path), &no_env).unwrap();
        let pacs = c.pacs.unwrap();
        assert_eq!(pacs.root_url, "http://127.0.0.1:8042/dicom-web");
        assert!(pacs.push_by_default && pacs.auth().is_none());
        let env = |k: &str| (k == "LUNGMOTION_PACS_TOKEN").then(|| "a-bearer-token".to_string());
        let c = ServiceConfig::load(Some(&path), &env).unwrap();
        assert_eq!(
            c.pacs.unwrap().auth(),
            Some(crate::pacs::DicomWebAuth::Bearer("a-bearer-token".into()))
        );
        assert!(ServiceConfig::load(None, &no_env).unwrap().pacs.is_none());
        std::fs::write(
            &path,
            "[pacs]\nurl = \"dicomweb://h/dw\"\nusernme = \"x\"\n",
        )
        .unwrap();
        let e = ServiceConfig::load(Some(&path), &no_env).unwrap_err();
        assert!(e.to_string().contains("usernme"), "{e}");
        std::fs::write(&path, "[pacs]\nurl = \"dicomweb://h/dw\"\ntimeout_s = -1\n").unwrap();
        let e = ServiceConfig::load(Some(&path), &no_env).unwrap_err();
        assert!(e.to_string().contains("timeout_s"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn refuses_unknown_keys_bad_numbers_and_open_listening_without_token() {
        let dir = std::env::temp_dir().join(format!("lm-svc-config-bad-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("service.toml");
        std::fs::write(&path, "wokers = 3\n").unwrap();
        let e = ServiceConfig::load(Some(&path), &no_env).unwrap_err();
        assert!(e.to_string().contains("wokers"), "{e}");
        std::fs::write(&path, "[run]\nelement_sise_mm = 3\n").unwrap();
        let e = ServiceConfig::load(Some(&path), &no_env).unwrap_err();
        assert!(e.to_string().contains("element_sise_mm"), "{e}");
        let env = |k: &str| (k == "LUNGMOTION_WORKERS").then(|| "many".to_string());
        let e = ServiceConfig::load(None, &env).unwrap_err();
        assert!(e.to_string().contains("LUNGMOTION_WORKERS"), "{e}");
        let env = |k: &str| (k == "LUNGMOTION_LISTEN").then(|| "0.0.0.0:8080".to_string());
        let e = ServiceConfig::load(None, &env).unwrap_err();
        assert!(e.to_string().contains("LUNGMOTION_API_TOKEN"), "{e}");
        let env = |k: &str| match k {
            "LUNGMOTION_LISTEN" => Some("0.0.0.0:8080".to_string()),
            "LUNGMOTION_API_TOKEN" => Some("a-long-secret".to_string()),
            _ => None,
        };
        assert!(ServiceConfig::load(None, &env).is_ok());
        // Unvalidated, so that a later override (the command line) can still make it valid.
        let env = |k: &str| (k == "LUNGMOTION_LISTEN").then(|| "0.0.0.0:8080".to_string());
        let mut c = ServiceConfig::from_sources(None, &env).unwrap();
        assert!(c.validate().is_err());
        c.listen = parse_listen("127.0.0.1:8080").unwrap();
        assert!(c.validate().is_ok());
        // The command line's overrides win over the environment, then the whole is validated.
        let loopback = ServeOverrides {
            listen: Some("127.0.0.1:0".into()),
            workers: Some(2),
            ..ServeOverrides::default()
        };
        let c = ServiceConfig::resolve(None, &env, &loopback).unwrap();
        assert_eq!((c.listen.port(), c.workers), (0, 2));
        let e = ServiceConfig::resolve(None, &env, &ServeOverrides::default()).unwrap_err();
        assert!(e.to_string().contains("LUNGMOTION_API_TOKEN"), "{e}");
        let typo = ServeOverrides {
            listen: Some("localhost".into()),
            ..ServeOverrides::default()
        };
        let e = ServiceConfig::resolve(None, &no_env, &typo).unwrap_err();
        assert!(e.to_string().contains("--listen"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}

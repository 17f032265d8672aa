//! The HTTP service (`lungmotion serve`): the breathing pipeline offered to planning systems
//! and scripts. A thin shell over [`crate::run::run_breathing`] and the ingest stage:
//!
//! * [`config`]: file, environment and command-line settings, merged in one place;
//!   [`pacs_settings`]: the DICOMweb server jobs pull their CT from and push to;
//!   [`pacs_jobs`]: a job's CT pulled and stored as a scan, its DICOM outputs pushed;
//! * [`ids`]: unguessable scan and job ids; [`ingest_cache`]: scans ingested for jobs, by settings;
//! * [`store`]: the on-disk store with atomic records; [`records`]: the job and scan records
//!   behind one interface (that store, or PostgreSQL); [`blobs`]: uploads and outputs in an
//!   object store (S3 or a directory) when configured;
//! * [`jobs`]: the bounded queue and worker pool, recovery after a restart, cancellation;
//!   [`backend`]: the jobs as the HTTP side sees them, in this process or in PostgreSQL;
//!   [`postgres`]: the records and the queue in PostgreSQL, leases; [`worker`]: the
//!   `lungmotion worker` process that runs them;
//!   [`progress`]: a running job's progress and time left;
//! * [`upload`]: streaming, size-limited scan uploads told apart by content;
//! * [`request`]: a simulation request (JSON or CSV) merged over the run defaults and checked;
//!   [`targets`]: treatment targets (masks, RTSTRUCTs) uploaded to a scan and named by requests;
//! * [`routes`]: the endpoints, one file per resource; [`openapi`]: their description;
//!   [`problem`]: error bodies;
//! * [`retention`]: finished jobs and unused scans removed by age and store size;
//!   [`callbacks`]: signed completion callbacks, retried;
//! * [`metrics`]: Prometheus series; [`server`]: middleware, listening, graceful shutdown;
//!   [`connections`]: the connection cap and header timeout; [`body_timeout`]: the body's;
//! * [`isolation`]: an upload's ingest in a child process, so a crashing reader ends only it.
//!
//! The contract (endpoints, statuses, store layout) is in the README's "HTTP service" section.

pub mod backend;
pub mod blobs;
pub mod body_timeout;
pub mod callbacks;
mod client_runtime;
pub mod config;
pub mod connections;
pub mod ids;
pub mod ingest_cache;
pub mod isolation;
pub mod jobs;
pub mod metrics;
pub mod openapi;
pub mod pacs_jobs;
pub mod pacs_settings;
pub mod postgres;
pub mod problem;
mod progress;
pub mod records;
pub mod request;
pub mod retention;
pub mod routes;
pub mod server;
pub mod store;
pub mod targets;
pub mod upload;
pub mod worker;

pub use config::{IngestIsolation, ServeOverrides, ServiceConfig};
pub use server::{router, serve_blocking, start, ServerHandle};

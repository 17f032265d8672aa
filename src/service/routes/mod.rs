//! The HTTP endpoints: thin handlers that check the request, call the store or the job
//! manager, and answer JSON, files or a problem. Every handler is also described for
//! `/openapi.json` by its `utoipa::path` attribute, so the document cannot drift from the code.
//!
//! One file per resource: [`scans`], [`targets`] (a scan's uploaded treatment targets),
//! [`simulations`] (jobs), [`results`] (summary, frames,
//! fields, trajectories), [`files`] (every output file), [`listing`] (pages of scans and jobs) and [`operations`] (probes, metrics, unknown routes); the router
//! that puts them on paths is [`super::server::router`]. What they share is here.

use std::sync::Arc;

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Serialize;

use super::backend::Jobs;
use super::config::ServiceConfig;
use super::ids::{JobId, ScanId};
use super::metrics::ServiceMetrics;
use super::problem::{ApiError, ApiResult};
use super::records::Records;
use super::store::{JobRecord, ScanRecord, Store};

pub mod files;
pub mod listing;
pub mod operations;
pub mod results;
pub mod scans;
pub mod simulations;
pub mod targets;

// Globs, so that each handler's `utoipa` path description (`__path_<handler>`) comes along
// with it for `openapi.rs`.
pub use super::request::{SimulationRequest, TraceBody};
pub use files::*;
pub use listing::*;
pub use operations::*;
pub use results::*;
pub use scans::*;
pub use simulations::*;
pub use targets::*;

/// What every handler shares.
pub struct AppState {
    /// The service's settings.
    pub config: ServiceConfig,
    /// The data directory: uploads, targets and outputs.
    pub store: Store,
    /// The job and scan records.
    pub records: Arc<dyn Records>,
    /// Queue and workers.
    pub jobs: Jobs,
    /// Prometheus series.
    pub metrics: ServiceMetrics,
    /// Ingests at once (CPU-bound, beside the simulation workers).
    pub ingest_slots: tokio::sync::Semaphore,
}

/// Handler state.
pub type SharedState = Arc<AppState>;

/// A scan id from the path; a malformed one is simply not found.
fn scan_id(text: &str) -> ApiResult<ScanId> {
    ScanId::parse(text).ok_or_else(|| ApiError::not_found(format!("no scan {text:?}")))
}

/// A job id from the path; a malformed one is simply not found.
fn job_id(text: &str) -> ApiResult<JobId> {
    JobId::parse(text).ok_or_else(|| ApiError::not_found(format!("no job {text:?}")))
}

/// A store failure is the server's, never the client's.
fn store_error(e: crate::Error) -> ApiError {
    ApiError::internal(format!("store: {e}"))
}

/// Runs file-system work off the async threads.
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> ApiResult<T> + Send + 'static,
) -> ApiResult<T> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| ApiError::internal(format!("worker task failed: {e}")))?
}

/// The scan's record, or 404.
fn load_scan(state: &AppState, id: ScanId) -> ApiResult<ScanRecord> {
    state
        .records
        .scan(id)
        .map_err(store_error)?
        .ok_or_else(|| ApiError::not_found(format!("no scan {id}")))
}

/// The job's record, or 404.
fn load_job(state: &AppState, id: JobId) -> ApiResult<JobRecord> {
    state
        .jobs
        .status(id)
        .map_err(store_error)?
        .ok_or_else(|| ApiError::not_found(format!("no job {id}")))
}

/// The job's record if it is done, else 409 saying what it is.
fn finished_job(state: &AppState, id: JobId) -> ApiResult<JobRecord> {
    let job = load_job(state, id)?;
    if !job.outputs_complete() {
        return Err(ApiError::conflict(
            "job-not-done",
            format!(
                "job {id} is {}{}; its outputs exist once it is done",
                job.state.name(),
                job.error
                    .as_deref()
                    .map(|e| format!(" ({e})"))
                    .unwrap_or_default()
            ),
        ));
    }
    Ok(job)
}

/// A JSON answer with `status` and a `Location` header.
fn created<T: Serialize>(location: String, body: T, status: StatusCode) -> Response {
    let mut response = (status, Json(body)).into_response();
    if let Ok(v) = HeaderValue::from_str(&location) {
        response.headers_mut().insert(header::LOCATION, v);
    }
    response
}

/// The 503 new work gets once a shutdown has begun.
fn shutting_down() -> ApiError {
    ApiError::new(
        StatusCode::SERVICE_UNAVAILABLE,
        "shutting-down",
        "the server is shutting down; retry shortly",
    )
    .retry_after(10)
}

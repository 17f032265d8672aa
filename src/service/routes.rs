//! The HTTP endpoints: thin handlers that check the request, call the store or the job
//! manager, and answer JSON, files or a problem. Every handler is also described for
//! `/openapi.json` by its `utoipa::path` attribute, so the document cannot drift from the code.

use std::path::PathBuf;
use std::sync::Arc;

use axum::body::{Body, Bytes};
use axum::extract::{Path, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use utoipa::ToSchema;

use super::config::ServiceConfig;
use super::ids::{JobId, ScanId};
use super::jobs::{CancelOutcome, JobManager, SubmitRefusal};
use super::metrics::ServiceMetrics;
use super::problem::{ApiError, ApiResult, Problem};
use super::store::{now_rfc3339, JobRecord, JobRequest, JobState, ScanRecord, Store, StoredPoint};
use super::upload::{receive_scan, TempFileGuard};
use crate::breathing::BreathingTrace;
use crate::ingest::pipeline::ingest_scan;
use crate::ingest::scan::load_ct;
use crate::run::RunConfig;

/// What every handler shares.
pub struct AppState {
    /// The service's settings.
    pub config: ServiceConfig,
    /// The data directory.
    pub store: Store,
    /// Queue and workers.
    pub jobs: JobManager,
    /// Prometheus series.
    pub metrics: ServiceMetrics,
    /// Ingests at once (CPU-bound, beside the simulation workers).
    pub ingest_slots: tokio::sync::Semaphore,
}

/// Handler state.
pub type SharedState = Arc<AppState>;

/// Links of a scan.
#[derive(Debug, Serialize, ToSchema)]
pub struct ScanLinks {
    /// This scan.
    #[serde(rename = "self")]
    pub self_: String,
    /// Where to POST simulations of it.
    pub simulations: String,
}

/// A stored scan as the API shows it.
#[derive(Debug, Serialize, ToSchema)]
pub struct ScanView {
    /// The record.
    #[serde(flatten)]
    pub record: ScanRecord,
    /// Related resources.
    pub links: ScanLinks,
}

impl From<ScanRecord> for ScanView {
    fn from(record: ScanRecord) -> Self {
        let base = format!("/v1/scans/{}", record.scan_id);
        ScanView {
            links: ScanLinks {
                simulations: format!("{base}/simulations"),
                self_: base,
            },
            record,
        }
    }
}

/// Links of a job.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobLinks {
    /// This job.
    #[serde(rename = "self")]
    pub self_: String,
    /// The run's summary.json (when done).
    pub summary: String,
    /// The frame list (when done).
    pub frames: String,
    /// Tracked points per frame, CSV (when done and points were given).
    pub trajectories: String,
    /// The scan.
    pub scan: String,
}

/// A job as the API shows it.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobStatus {
    /// The record (`state`, `progress`, `error`, `attempts`, times).
    #[serde(flatten)]
    pub record: JobRecord,
    /// Related resources.
    pub links: JobLinks,
}

impl From<JobRecord> for JobStatus {
    fn from(record: JobRecord) -> Self {
        let base = format!("/v1/jobs/{}", record.job_id);
        JobStatus {
            links: JobLinks {
                summary: format!("{base}/summary"),
                frames: format!("{base}/frames"),
                trajectories: format!("{base}/trajectories"),
                scan: format!("/v1/scans/{}", record.scan_id),
                self_: base,
            },
            record,
        }
    }
}

/// A breathing trace in a JSON request.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TraceBody {
    /// Sample times, s, strictly increasing.
    pub time_s: Vec<f64>,
    /// Lung volume change from the scanned state, mL.
    pub volume_ml: Vec<f64>,
}

/// A simulation request: the trace, points to track, and any `lungmotion run` option.
#[derive(Debug, Deserialize, ToSchema)]
pub struct SimulationRequest {
    /// The breathing trace.
    pub trace: TraceBody,
    /// Points to track (LPS mm, at the scanned state).
    #[serde(default)]
    pub points: Vec<StoredPoint>,
    /// Any key of the CLI's configuration (`element_size_mm`, `material`, `diaphragm`,
    /// `trace`, `motion`, `outputs`), merged over the server's defaults.
    #[serde(flatten)]
    #[schema(value_type = Object)]
    pub options: serde_json::Map<String, Value>,
}

/// A frame in the frame list: the fields of its record in `summary.json`, and its link.
#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct FrameEntry {
    /// Frame number.
    pub index: usize,
    /// Time in the trace, s.
    pub time_s: f64,
    /// Volume change asked for, mL.
    pub target_volume_ml: f64,
    /// Volume change reached, mL.
    pub simulated_volume_ml: f64,
    /// Surface pressure, Pa.
    pub pressure_pa: f64,
    /// Largest node displacement, mm.
    pub max_displacement_mm: f64,
    /// Where to fetch its displacement field.
    #[serde(default)]
    pub displacement: String,
}

/// The frame list of a finished job.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameList {
    /// The frames in time order.
    pub frames: Vec<FrameEntry>,
}

/// Liveness or readiness.
#[derive(Debug, Serialize, ToSchema)]
pub struct Health {
    /// `ok`, `ready` or why not.
    pub status: String,
    /// Worker threads.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub workers: Option<usize>,
    /// Jobs waiting.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub queued: Option<usize>,
    /// Jobs running.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub running: Option<usize>,
}

/// How a displacement field is delivered.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
pub struct FieldFormat {
    /// `nifti` (default, `.nii.gz`) or `mha` (MetaImage).
    pub format: Option<String>,
}

fn scan_id(text: &str) -> ApiResult<ScanId> {
    ScanId::parse(text).ok_or_else(|| ApiError::not_found(format!("no scan {text:?}")))
}

fn job_id(text: &str) -> ApiResult<JobId> {
    JobId::parse(text).ok_or_else(|| ApiError::not_found(format!("no job {text:?}")))
}

fn store_error(e: crate::Error) -> ApiError {
    ApiError::internal(format!("store: {e}"))
}

async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> ApiResult<T> + Send + 'static,
) -> ApiResult<T> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| ApiError::internal(format!("worker task failed: {e}")))?
}

fn load_scan(state: &AppState, id: ScanId) -> ApiResult<ScanRecord> {
    state
        .store
        .scan(id)
        .map_err(store_error)?
        .ok_or_else(|| ApiError::not_found(format!("no scan {id}")))
}

fn load_job(state: &AppState, id: JobId) -> ApiResult<JobRecord> {
    state
        .jobs
        .status(id)
        .ok_or_else(|| ApiError::not_found(format!("no job {id}")))
}

fn finished_job(state: &AppState, id: JobId) -> ApiResult<JobRecord> {
    let job = load_job(state, id)?;
    if job.state != JobState::Done {
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

/// Upload a scan and ingest it.
#[utoipa::path(
    post, path = "/v1/scans", tag = "scans",
    request_body(description = "A NIfTI file (.nii, .nii.gz) or a zip of one DICOM series, raw \
        or as the part `file` of a multipart form; told apart by content",
        content(("application/octet-stream"), ("application/zip"), ("application/gzip"),
                ("multipart/form-data"))),
    responses(
        (status = 201, description = "Stored and ingested", body = ScanView,
         headers(("location" = String, description = "The scan's URL"))),
        (status = 400, description = "Empty or broken upload", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Over max_upload_mib", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "JSON or text instead of a scan", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Not a CT, truncated, unsafe zip, or no lungs found", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn upload_scan(
    State(state): State<SharedState>,
    request: Request,
) -> ApiResult<Response> {
    if state.jobs.shutting_down() {
        return Err(shutting_down());
    }
    let dest = state.store.tmp_path("upload");
    let mut guard = TempFileGuard(Some(dest.clone()));
    let received = receive_scan(request, &dest, state.config.max_upload_bytes).await?;
    let (file_name, format_name) = received.stored_name();
    // The readers tell .nii from .nii.gz by name, so the file gets its proper one.
    let named = PathBuf::from(format!("{}-{file_name}", dest.display()));
    std::fs::rename(&dest, &named)
        .map_err(|e| ApiError::internal(format!("cannot move the upload: {e}")))?;
    guard.0 = Some(named.clone());
    let _slot = state
        .ingest_slots
        .acquire()
        .await
        .map_err(|_| shutting_down())?;
    let bytes = received.bytes;
    let settings = state.config.run.ingest_settings();
    let worker_state = state.clone();
    let record = blocking(move || {
        let refused = |e| ApiError::from_input_error(e).redact_path(&named, "the upload");
        let scan = load_ct(&named).map_err(refused)?;
        let outcome = ingest_scan(&scan, &settings).map_err(refused)?;
        let record = ScanRecord {
            scan_id: ScanId::random(),
            created_at: now_rfc3339(),
            format: format_name.to_string(),
            upload_bytes: bytes,
            file_name: file_name.to_string(),
            ingest: serde_json::to_value(&outcome.summary)
                .map_err(|e| ApiError::internal(format!("ingest summary: {e}")))?,
        };
        worker_state
            .store
            .put_scan(&record, &named)
            .map_err(store_error)?;
        Ok(record)
    })
    .await?;
    guard.0 = None;
    state.metrics.observe_upload(bytes);
    tracing::info!(
        scan = %record.scan_id,
        format = format_name,
        bytes,
        elements = record.ingest["elements"].as_u64().unwrap_or(0),
        "scan stored"
    );
    let location = format!("/v1/scans/{}", record.scan_id);
    Ok(created(
        location,
        ScanView::from(record),
        StatusCode::CREATED,
    ))
}

fn created<T: Serialize>(location: String, body: T, status: StatusCode) -> Response {
    let mut response = (status, Json(body)).into_response();
    if let Ok(v) = HeaderValue::from_str(&location) {
        response.headers_mut().insert(header::LOCATION, v);
    }
    response
}

fn shutting_down() -> ApiError {
    ApiError::new(
        StatusCode::SERVICE_UNAVAILABLE,
        "shutting-down",
        "the server is shutting down; retry shortly",
    )
    .retry_after(10)
}

/// A stored scan and its ingest summary.
#[utoipa::path(
    get, path = "/v1/scans/{id}", tag = "scans",
    params(("id" = String, Path, description = "Scan id (32 hex digits)")),
    responses(
        (status = 200, description = "The scan", body = ScanView),
        (status = 404, description = "No such scan", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn get_scan(
    State(state): State<SharedState>,
    Path(id): Path<String>,
) -> ApiResult<Json<ScanView>> {
    let id = scan_id(&id)?;
    let record = blocking(move || load_scan(&state, id)).await?;
    Ok(Json(record.into()))
}

/// Delete a scan (its finished jobs keep their outputs).
#[utoipa::path(
    delete, path = "/v1/scans/{id}", tag = "scans",
    params(("id" = String, Path, description = "Scan id")),
    responses(
        (status = 204, description = "Deleted"),
        (status = 404, description = "No such scan", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "A job of this scan is queued or running", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn delete_scan(
    State(state): State<SharedState>,
    Path(id): Path<String>,
) -> ApiResult<StatusCode> {
    let id = scan_id(&id)?;
    blocking(move || {
        if state.jobs.scan_in_use(id) {
            return Err(ApiError::conflict(
                "scan-in-use",
                format!("scan {id} has queued or running jobs; cancel them first"),
            ));
        }
        if !state.store.delete_scan(id).map_err(store_error)? {
            return Err(ApiError::not_found(format!("no scan {id}")));
        }
        tracing::info!(scan = %id, "scan deleted");
        Ok(StatusCode::NO_CONTENT)
    })
    .await
}

/// Merges request options over the server's defaults: objects key by key, except tagged
/// choices (`{"kind": ...}`), which replace the default whole.
fn merge_options(base: &mut Value, overrides: &serde_json::Map<String, Value>) {
    let Value::Object(base) = base else { return };
    for (key, value) in overrides {
        match (base.get_mut(key), value) {
            (Some(existing @ Value::Object(_)), Value::Object(o)) if !o.contains_key("kind") => {
                merge_options(existing, o)
            }
            _ => {
                base.insert(key.clone(), value.clone());
            }
        }
    }
}

/// The job request from a JSON or CSV body, checked as far as it can be without running.
fn parse_simulation(
    defaults: &RunConfig,
    content_type: &str,
    body: &[u8],
) -> ApiResult<JobRequest> {
    let invalid = |m: String| ApiError::unprocessable("invalid-simulation", m);
    let (config, trace, points, source) =
        if content_type.starts_with("application/json") || content_type.ends_with("+json") {
            let value: Value = serde_json::from_slice(body).map_err(|e| {
                ApiError::bad_request("malformed-json", format!("the body is not valid JSON: {e}"))
            })?;
            if !value.is_object() {
                return Err(invalid(
                    "the body must be a JSON object with a \"trace\"".into(),
                ));
            }
            let request: SimulationRequest = serde_json::from_value(value)
                .map_err(|e| invalid(format!("simulation request: {e}")))?;
            let mut merged = serde_json::to_value(defaults)
                .map_err(|e| ApiError::internal(format!("default options: {e}")))?;
            merge_options(&mut merged, &request.options);
            let config: RunConfig =
                serde_json::from_value(merged).map_err(|e| invalid(format!("options: {e}")))?;
            let trace = BreathingTrace::new(request.trace.time_s, request.trace.volume_ml)
                .map_err(|e| invalid(e.to_string()))?;
            (config, trace, request.points, "HTTP request (JSON)")
        } else if content_type.starts_with("text/csv") || content_type.starts_with("text/plain") {
            let text = std::str::from_utf8(body)
                .map_err(|_| ApiError::bad_request("malformed-csv", "the CSV body is not UTF-8"))?;
            let trace = BreathingTrace::parse(text, &defaults.trace)
                .map_err(|e| invalid(format!("breathing trace: {e}")))?;
            (defaults.clone(), trace, Vec::new(), "HTTP request (CSV)")
        } else {
            return Err(ApiError::new(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "unsupported-media-type",
                format!(
                    "a simulation request is application/json ({{\"trace\": {{\"time_s\": [...], \
                 \"volume_ml\": [...]}}, ...options}}) or text/csv (time_s,volume_ml), not {:?}",
                    if content_type.is_empty() {
                        "no content type"
                    } else {
                        content_type
                    }
                ),
            ));
        };
    config.validate().map_err(|e| invalid(e.to_string()))?;
    trace.validate().map_err(|e| invalid(e.to_string()))?;
    config
        .motion_settings()
        .instants
        .times(&trace)
        .map_err(|e| invalid(e.to_string()))?;
    for (i, p) in points.iter().enumerate() {
        if p.name.trim().is_empty() || p.name.contains([',', '\n', '\r']) {
            return Err(invalid(format!(
                "points[{i}]: a name without commas or line breaks is needed"
            )));
        }
        if !p.lps_mm.iter().all(|c| c.is_finite()) {
            return Err(invalid(format!(
                "points[{i}] ({}): non-finite coordinate",
                p.name
            )));
        }
    }
    Ok(JobRequest {
        config,
        time_s: trace.time_s,
        volume_ml: trace.volume_change_ml,
        trace_source: source.to_string(),
        points,
    })
}

/// Submit a simulation of a scan over a breathing trace.
#[utoipa::path(
    post, path = "/v1/scans/{id}/simulations", tag = "jobs",
    params(("id" = String, Path, description = "Scan id")),
    request_body(description = "JSON (trace, points and any `lungmotion run` option) or the \
        CLI's CSV trace (time_s,volume_ml; volume as change from the scanned state)",
        content((SimulationRequest = "application/json"), (String = "text/csv"))),
    responses(
        (status = 202, description = "Queued", body = JobStatus,
         headers(("location" = String, description = "The job's URL"))),
        (status = 400, description = "Malformed JSON", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such scan", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Body over max_request_kib", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Neither JSON nor CSV", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Unusable trace or option", body = Problem, content_type = "application/problem+json"),
        (status = 429, description = "Queue full (see Retry-After)", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "Shutting down (see Retry-After)", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn create_simulation(
    State(state): State<SharedState>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult<Response> {
    let scan = scan_id(&id)?;
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_ascii_lowercase();
    let worker_state = state.clone();
    let record = blocking(move || {
        load_scan(&worker_state, scan)?;
        let request = parse_simulation(&worker_state.config.run, &content_type, &body)?;
        match worker_state
            .jobs
            .submit(scan, &request)
            .map_err(store_error)?
        {
            Ok(record) => Ok(record),
            Err(SubmitRefusal::ShuttingDown) => Err(shutting_down()),
            Err(SubmitRefusal::QueueFull {
                queued,
                retry_after_s,
            }) => Err(ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                "queue-full",
                format!("{queued} simulations are already waiting; retry later"),
            )
            .retry_after(retry_after_s)),
        }
    })
    .await?;
    tracing::info!(job = %record.job_id, scan = %scan, "job queued");
    let location = format!("/v1/jobs/{}", record.job_id);
    Ok(created(
        location,
        JobStatus::from(record),
        StatusCode::ACCEPTED,
    ))
}

/// A job's state and progress.
#[utoipa::path(
    get, path = "/v1/jobs/{id}", tag = "jobs",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, description = "The job", body = JobStatus),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn get_job(
    State(state): State<SharedState>,
    Path(id): Path<String>,
) -> ApiResult<Json<JobStatus>> {
    let id = job_id(&id)?;
    Ok(Json(load_job(&state, id)?.into()))
}

/// Cancel a queued or running job, or delete a finished one with its outputs.
#[utoipa::path(
    delete, path = "/v1/jobs/{id}", tag = "jobs",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 202, description = "Cancelled (queued) or cancellation requested (running)", body = JobStatus),
        (status = 204, description = "A finished job and its outputs were deleted"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn delete_job(
    State(state): State<SharedState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    blocking(move || {
        let outcome = state
            .jobs
            .cancel(id)
            .map_err(store_error)?
            .ok_or_else(|| ApiError::not_found(format!("no job {id}")))?;
        match outcome {
            CancelOutcome::Cancelled | CancelOutcome::Requested => {
                tracing::info!(job = %id, ?outcome, "job cancelled by a client");
                let status = JobStatus::from(load_job(&state, id)?);
                Ok((StatusCode::ACCEPTED, Json(status)).into_response())
            }
            CancelOutcome::AlreadyFinished => {
                if !state.jobs.remove(id).map_err(store_error)? {
                    return Err(ApiError::conflict(
                        "job-busy",
                        format!("job {id} changed state; retry"),
                    ));
                }
                tracing::info!(job = %id, "job deleted");
                Ok(StatusCode::NO_CONTENT.into_response())
            }
        }
    })
    .await
}

async fn file_response(
    path: PathBuf,
    content_type: &'static str,
    filename: String,
) -> ApiResult<Response> {
    let file = tokio::fs::File::open(&path).await.map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            ApiError::not_found(format!("{filename} is missing from the job's outputs"))
        } else {
            ApiError::internal(format!("cannot read {}: {e}", path.display()))
        }
    })?;
    let len = file.metadata().await.map(|m| m.len()).ok();
    let body = Body::from_stream(tokio_util::io::ReaderStream::with_capacity(file, 256 << 10));
    let mut response = Response::new(body);
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    if let Some(len) = len {
        headers.insert(header::CONTENT_LENGTH, HeaderValue::from(len));
    }
    if let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"{filename}\"")) {
        headers.insert(header::CONTENT_DISPOSITION, v);
    }
    Ok(response)
}

/// The run's summary.json.
#[utoipa::path(
    get, path = "/v1/jobs/{id}/summary", tag = "results",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, description = "summary.json of the run (as `lungmotion run` writes it)", body = Object),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not done", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn job_summary(
    State(state): State<SharedState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    finished_job(&state, id)?;
    let path = state.store.job_output_dir(id).join("summary.json");
    file_response(path, "application/json", format!("{id}-summary.json")).await
}

/// The frames of a finished job, read from its `summary.json`, each with its field's link.
fn read_frames(state: &AppState, id: JobId) -> ApiResult<Vec<FrameEntry>> {
    let path = state.store.job_output_dir(id).join("summary.json");
    let corrupt = |e: String| ApiError::internal(format!("job {id}: summary: {e}"));
    let bytes = std::fs::read(&path).map_err(|e| corrupt(e.to_string()))?;
    let summary: Value = serde_json::from_slice(&bytes).map_err(|e| corrupt(e.to_string()))?;
    let mut frames: Vec<FrameEntry> =
        serde_json::from_value(summary["frames"].clone()).map_err(|e| corrupt(e.to_string()))?;
    for f in &mut frames {
        f.displacement = format!("/v1/jobs/{id}/frames/{}/displacement", f.index);
    }
    Ok(frames)
}

/// The frames of a finished job.
#[utoipa::path(
    get, path = "/v1/jobs/{id}/frames", tag = "results",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, description = "The frames", body = FrameList),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not done", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn job_frames(
    State(state): State<SharedState>,
    Path(id): Path<String>,
) -> ApiResult<Json<FrameList>> {
    let id = job_id(&id)?;
    blocking(move || {
        finished_job(&state, id)?;
        let frames = read_frames(&state, id)?;
        Ok(Json(FrameList { frames }))
    })
    .await
}

/// One frame's displacement field.
#[utoipa::path(
    get, path = "/v1/jobs/{id}/frames/{k}/displacement", tag = "results",
    params(("id" = String, Path, description = "Job id"),
           ("k" = usize, Path, description = "Frame index"), FieldFormat),
    responses(
        (status = 200, description = "NIfTI-1 vector field (gzip; 3 float32 components in LPS \
            millimetres, on the CT's grid and affine, zero outside the lungs) or, with \
            `format=mha`, the same as MetaImage",
         content(("application/gzip"), ("application/octet-stream"))),
        (status = 404, description = "No such job or frame", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not done", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn frame_displacement(
    State(state): State<SharedState>,
    Path((id, k)): Path<(String, String)>,
    Query(format): Query<FieldFormat>,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    finished_job(&state, id)?;
    let k: usize = k
        .parse()
        .map_err(|_| ApiError::not_found(format!("no frame {k:?} (a frame is a number)")))?;
    let frame_dir = state
        .store
        .job_output_dir(id)
        .join("frames")
        .join(k.to_string());
    if !frame_dir.is_dir() {
        let worker_state = state.clone();
        let count = blocking(move || Ok(read_frames(&worker_state, id)?.len())).await?;
        return Err(ApiError::not_found(format!(
            "job {id} has {count} frames (0–{}); there is no frame {k}",
            count.saturating_sub(1)
        )));
    }
    match format.format.as_deref().unwrap_or("nifti") {
        "nifti" | "nii" | "nii.gz" => {
            file_response(
                frame_dir.join("displacement.nii.gz"),
                "application/gzip",
                format!("{id}-frame-{k}.nii.gz"),
            )
            .await
        }
        "mha" | "metaimage" => {
            let written = frame_dir.join("displacement.mha");
            let path = if written.is_file() {
                written
            } else {
                let worker_state = state.clone();
                blocking(move || metaimage_copy(&worker_state, id, k)).await?
            };
            file_response(
                path,
                "application/octet-stream",
                format!("{id}-frame-{k}.mha"),
            )
            .await
        }
        other => Err(ApiError::bad_request(
            "unknown-format",
            format!("format={other:?}: use nifti (default) or mha"),
        )),
    }
}

/// Converts a frame's NIfTI field to MetaImage once, into the job's cache.
fn metaimage_copy(state: &AppState, id: JobId, k: usize) -> ApiResult<PathBuf> {
    let cache = state.store.job_dir(id).join("cache");
    let path = cache.join(format!("frame-{k}.mha"));
    if path.is_file() {
        return Ok(path);
    }
    let nifti = state
        .store
        .job_output_dir(id)
        .join("frames")
        .join(k.to_string())
        .join("displacement.nii.gz");
    let (geometry, field) = crate::formats::nifti::read_nifti_vector_field(&nifti)
        .map_err(|e| ApiError::internal(format!("job {id} frame {k}: {e}")))?;
    let flat: Vec<f32> = field.iter().flatten().copied().collect();
    std::fs::create_dir_all(&cache)
        .map_err(|e| ApiError::internal(format!("cannot create {}: {e}", cache.display())))?;
    crate::formats::metaimage::write_mha(
        &path,
        &geometry,
        3,
        &flat,
        "lungmotion displacement, LPS millimetres",
    )
    .map_err(|e| ApiError::internal(format!("job {id} frame {k}: {e}")))?;
    Ok(path)
}

/// Tracked points per frame.
#[utoipa::path(
    get, path = "/v1/jobs/{id}/trajectories", tag = "results",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, description = "trajectories.csv: frame, time, point, rest and displaced \
            position and displacement in LPS mm", content_type = "text/csv", body = String),
        (status = 404, description = "No such job, or it tracked no points", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not done", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn job_trajectories(
    State(state): State<SharedState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    finished_job(&state, id)?;
    let path = state.store.job_output_dir(id).join("trajectories.csv");
    if !path.is_file() {
        return Err(ApiError::not_found(format!(
            "job {id} tracked no points (give \"points\" in the simulation request)"
        )));
    }
    file_response(path, "text/csv", format!("{id}-trajectories.csv")).await
}

/// Liveness: the process answers.
#[utoipa::path(get, path = "/healthz", tag = "operations",
    responses((status = 200, description = "Alive", body = Health)))]
pub async fn healthz() -> Json<Health> {
    Json(Health {
        status: "ok".into(),
        workers: None,
        queued: None,
        running: None,
    })
}

/// Readiness: the store is writable and the server is not shutting down.
#[utoipa::path(get, path = "/readyz", tag = "operations",
    responses((status = 200, description = "Ready", body = Health),
              (status = 503, description = "Shutting down or store not writable", body = Health)))]
pub async fn readyz(State(state): State<SharedState>) -> Response {
    let counts = state.jobs.counts();
    let worker_state = state.clone();
    let writable = tokio::task::spawn_blocking(move || worker_state.store.is_writable())
        .await
        .unwrap_or(false);
    let status = if state.jobs.shutting_down() {
        "shutting down"
    } else if !writable {
        "store not writable"
    } else {
        "ready"
    };
    let code = if status == "ready" {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    let body = Health {
        status: status.into(),
        workers: Some(state.config.workers),
        queued: Some(counts.queued),
        running: Some(counts.running),
    };
    (code, Json(body)).into_response()
}

/// Prometheus metrics.
#[utoipa::path(get, path = "/metrics", tag = "operations",
    responses((status = 200, description = "OpenMetrics text", content_type = "application/openmetrics-text", body = String)))]
pub async fn metrics(State(state): State<SharedState>) -> Response {
    let text = state.metrics.render(&state.jobs.counts());
    (
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        text,
    )
        .into_response()
}

/// Unknown routes.
pub async fn not_found(request: Request) -> ApiError {
    ApiError::not_found(format!(
        "no route {} {}; see /openapi.json",
        request.method(),
        request.uri().path()
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_breaths() -> (Vec<f64>, Vec<f64>) {
        let t: Vec<f64> = (0..=80).map(|i| i as f64 * 0.1).collect();
        let v = t
            .iter()
            .map(|t| 250.0 * (1.0 - (std::f64::consts::TAU * t / 4.0).cos()))
            .collect();
        (t, v)
    }

    #[test]
    fn json_options_merge_over_the_server_defaults() {
        let mut defaults = RunConfig::default();
        defaults.material.poisson_ratio = 0.3;
        let (t, v) = two_breaths();
        let body = serde_json::json!({
            "trace": {"time_s": t, "volume_ml": v},
            "element_size_mm": 10,
            "material": {"youngs_modulus_pa": 800.0},
            "motion": {"instants": {"kind": "every_kth", "k": 20}},
            "points": [{"name": "tumour", "lps_mm": [1.0, 2.0, 3.0]}],
        });
        let request =
            parse_simulation(&defaults, "application/json", body.to_string().as_bytes()).unwrap();
        assert_eq!(request.config.element_size_mm, 10.0);
        assert_eq!(request.config.material.youngs_modulus_pa, 800.0);
        // Keys the request leaves out keep the server's value, even inside a table.
        assert_eq!(request.config.material.poisson_ratio, 0.3);
        assert_eq!(
            request.config.motion.instants,
            crate::breathing::OutputInstants::EveryKth { k: 20 }
        );
        assert_eq!(request.points[0].name, "tumour");
        assert_eq!(request.time_s.len(), 81);
    }

    #[test]
    fn bad_requests_are_refused_with_the_right_status_and_a_named_cause() {
        let defaults = RunConfig::default();
        let (t, v) = two_breaths();
        let status = |ct: &str, body: &str| {
            let e = parse_simulation(&defaults, ct, body.as_bytes()).unwrap_err();
            (e.status.as_u16(), e.detail)
        };
        let (s, d) = status("application/json", "{\"trace\": ");
        assert_eq!(s, 400, "{d}");
        let (s, d) = status("application/json", "[1, 2]");
        assert_eq!(s, 422, "{d}");
        let body =
            serde_json::json!({"trace": {"time_s": t, "volume_ml": v}, "element_sise_mm": 8});
        let (s, d) = status("application/json", &body.to_string());
        assert!(s == 422 && d.contains("element_sise_mm"), "{s} {d}");
        let body = serde_json::json!({"trace": {"time_s": [0, 1], "volume_ml": ["a", 1]}});
        let (s, d) = status("application/json", &body.to_string());
        assert_eq!(s, 422, "{d}");
        let (s, d) = status("text/csv", "time_s,volume_ml\n0,0\n1,NaN\n2,3\n");
        assert!(s == 422 && d.contains("NaN"), "{s} {d}");
        let (s, d) = status("text/csv", "time_s,volume_ml\n0,0\n2,1\n1,3\n");
        assert_eq!(s, 422, "{d}");
        let (s, d) = status("application/xml", "<trace/>");
        assert!(s == 415 && d.contains("application/json"), "{s} {d}");
        let body = serde_json::json!({"trace": {"time_s": t, "volume_ml": v},
            "points": [{"name": "a,b", "lps_mm": [0, 0, 0]}]});
        let (s, d) = status("application/json", &body.to_string());
        assert!(s == 422 && d.contains("points[0]"), "{s} {d}");
    }
}

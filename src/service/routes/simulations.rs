//! Simulations and their jobs: submit one for a scan, follow it, cancel or delete it.

use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Serialize;
use utoipa::ToSchema;

use super::{
    blocking, created, job_id, load_job, load_scan, scan_id, shutting_down, store_error,
    SharedState,
};
use crate::service::callbacks::check_callback_url;
use crate::service::ids::ScanId;
use crate::service::jobs::{CancelOutcome, SubmitRefusal};
use crate::service::problem::{ApiError, ApiResult, Problem};
use crate::service::request::{parse_simulation, SimulationRequest};
use crate::service::store::{JobRecord, JobRequest, LocalTargetFile};
use crate::service::targets::{choose, JobTarget};

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
    /// Every file the run wrote, with its link and content type (when done).
    pub files: String,
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
                files: format!("{base}/files"),
                scan: format!("/v1/scans/{}", record.scan_id),
                self_: base,
            },
            record,
        }
    }
}

/// Submit a simulation of a scan over a breathing trace.
#[utoipa::path(
    post, path = "/v1/scans/{id}/simulations", tag = "jobs",
    params(("id" = String, Path, description = "Scan id")),
    request_body(description = "JSON (trace, points, target and any `lungmotion run` option) \
        or the CLI's CSV trace (time_s,volume_ml; volume as change from the scanned state)",
        content((SimulationRequest = "application/json"), (String = "text/csv"))),
    responses(
        (status = 202, description = "Queued", body = JobStatus,
         headers(("location" = String, description = "The job's URL"))),
        (status = 400, description = "Malformed JSON", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such scan (also one removed meanwhile by a client or retention)", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "The uploaded target the request follows was replaced or deleted while the request was being submitted (target-changed); submit again", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Body over max_request_kib", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Neither JSON nor CSV", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Unusable trace or option (invalid-simulation; also a `ct`, which belongs to POST /v1/simulations; a target that is a path, or an uploaded target the scan does not have, a label not in its mask, an ROI missing from its RTSTRUCT or unusable on the CT, each named), a callback_url refused (invalid-callback: scheme, plain http beyond loopback, credentials, length, or no callback secret on the server), or `\"push\": true` on a server without a PACS (no-pacs)", body = Problem, content_type = "application/problem+json"),
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
    let content_type = content_type_of(&headers);
    let worker_state = state.clone();
    let record = blocking(move || {
        load_scan(&worker_state, scan)?;
        let request = parse_simulation(
            &worker_state.config.run,
            worker_state.config.pacs.as_ref(),
            &content_type,
            &body,
        )?;
        if request.pacs_ct.is_some() {
            return Err(ApiError::unprocessable(
                "invalid-simulation",
                format!(
                    "\"ct\": scan {scan} is this simulation's CT; a simulation of a CT on the \
                     PACS is submitted to POST /v1/simulations"
                ),
            ));
        }
        let mut request = request;
        let target_file = uploaded_target(&worker_state, scan, &mut request)?;
        submit(
            &worker_state,
            scan,
            &request,
            target_file.as_ref().map(|f| f.path.as_path()),
        )
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

/// Submit a simulation of a CT series on the service's PACS.
#[utoipa::path(
    post, path = "/v1/simulations", tag = "jobs",
    request_body(description = "JSON as for a scan's simulations, with `ct` naming the series \
        on the server's PACS: `{\"ct\": {\"dicomweb\": {\"study\": UID, \"series\": UID}}, \
        \"trace\": {...}, \"push\": true, ...options}`. The job pulls the series (QIDO-RS, \
        WADO-RS), stores it as a scan (its `scan_id`, readable once pulled), runs, and with \
        `push` stores its DICOM outputs back (STOW-RS), skipping what the PACS already holds. \
        A PACS that is down or refuses fails the job, naming the server and its answer.",
        content((SimulationRequest = "application/json"))),
    responses(
        (status = 202, description = "Queued", body = JobStatus,
         headers(("location" = String, description = "The job's URL"))),
        (status = 400, description = "Malformed JSON", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Body over max_request_kib", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Not JSON", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "No `ct`, a UID that is not one, an unusable trace or option, an uploaded target (it belongs to a stored scan; invalid-simulation), no PACS configured (no-pacs), or a callback_url refused (invalid-callback)", body = Problem, content_type = "application/problem+json"),
        (status = 429, description = "Queue full (see Retry-After)", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "Shutting down (see Retry-After)", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn create_pacs_simulation(
    State(state): State<SharedState>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult<Response> {
    let content_type = content_type_of(&headers);
    if !(content_type.starts_with("application/json") || content_type.ends_with("+json")) {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            format!(
                "a simulation of a CT on the PACS is application/json ({{\"ct\": {{\"dicomweb\": \
                 {{\"study\": ...}}}}, \"trace\": {{...}}}}), not {content_type:?}"
            ),
        ));
    }
    let worker_state = state.clone();
    let record = blocking(move || {
        let request = parse_simulation(
            &worker_state.config.run,
            worker_state.config.pacs.as_ref(),
            &content_type,
            &body,
        )?;
        if request.pacs_ct.is_none() {
            return Err(ApiError::unprocessable(
                "invalid-simulation",
                "no \"ct\": POST /v1/simulations runs on a series of the PACS, \
                 {\"ct\": {\"dicomweb\": {\"study\": UID, \"series\": UID}}}; a stored scan's \
                 simulations go to POST /v1/scans/{id}/simulations",
            ));
        }
        if let Some(JobTarget::Upload(choice)) = &request.target {
            // An upload is checked against its scan's CT; this CT is not pulled yet.
            return Err(ApiError::unprocessable(
                "invalid-simulation",
                format!(
                    "target {{\"upload\": {:?}}}: uploaded targets belong to a stored scan and \
                     are checked against its CT, which a CT still on the PACS is not yet; run \
                     this series once (its job's scan_id is the stored scan), upload the target \
                     to PUT /v1/scans/{{scan_id}}/targets/{{name}} and submit to POST \
                     /v1/scans/{{scan_id}}/simulations, or give a point target here",
                    choice.upload
                ),
            ));
        }
        // The scan the series becomes once the job has pulled it.
        submit(&worker_state, ScanId::random(), &request, None)
    })
    .await?;
    tracing::info!(job = %record.job_id, scan = %record.scan_id, "job on a PACS series queued");
    let location = format!("/v1/jobs/{}", record.job_id);
    Ok(created(
        location,
        JobStatus::from(record),
        StatusCode::ACCEPTED,
    ))
}

/// The request's content type, lower case ("" when absent).
fn content_type_of(headers: &HeaderMap) -> String {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_ascii_lowercase()
}

/// The scan's stored file of the target the request names as an upload, checked against its
/// record (label or ROI present and usable); the request then names the job's copy. With an
/// object store the file is a copy fetched for the submission, removed when it is dropped.
fn uploaded_target(
    state: &SharedState,
    scan: ScanId,
    request: &mut JobRequest,
) -> ApiResult<Option<LocalTargetFile>> {
    let Some(JobTarget::Upload(choice)) = &mut request.target else {
        return Ok(None);
    };
    let record = state
        .store
        .target(scan, &choice.upload)
        .map_err(store_error)?;
    let uploaded: Vec<String> = match record {
        Some(_) => Vec::new(),
        None => state
            .store
            .list_targets(scan)
            .map_err(store_error)?
            .into_iter()
            .map(|r| r.name)
            .collect(),
    };
    choose(choice, record.as_ref(), &uploaded)?;
    let record = record.ok_or_else(|| ApiError::internal("choose let a missing upload through"))?;
    choice.file = Some(record.file_name.clone());
    match state
        .store
        .target_file_for_job(scan, &record)
        .map_err(store_error)?
    {
        Some(file) => Ok(Some(file)),
        None => Err(ApiError::conflict(
            "target-changed",
            format!(
                "target {:?} of scan {scan} was replaced or deleted while this simulation was \
                 being submitted; submit again",
                record.name
            ),
        )),
    }
}

/// Checks the callback and queues the job (with its copy of the uploaded target file
/// `target`), or says why not.
fn submit(
    state: &SharedState,
    scan: ScanId,
    request: &JobRequest,
    target: Option<&std::path::Path>,
) -> ApiResult<JobRecord> {
    if let Some(url) = &request.callback_url {
        check_callback_url(url, &state.config.callbacks)
            .map_err(|m| ApiError::unprocessable("invalid-callback", m))?;
    }
    match state
        .jobs
        .submit(scan, request, target)
        .map_err(store_error)?
    {
        Ok(record) => Ok(record),
        Err(SubmitRefusal::ShuttingDown) => Err(shutting_down()),
        Err(SubmitRefusal::ScanMissing) => Err(ApiError::not_found(format!("no scan {scan}"))),
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

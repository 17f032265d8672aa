//! Scans: upload (stored and ingested at once), fetch and delete.

use std::path::PathBuf;
use std::time::Duration;

use axum::extract::{Path, Query, Request, State};
use axum::http::StatusCode;
use axum::response::Response;
use axum::Json;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::{blocking, created, load_scan, scan_id, shutting_down, store_error, SharedState};
use crate::formats::dicom::SeriesChoice;
use crate::service::ids::ScanId;
use crate::service::isolation::{adopt_stored_ingest, ingest_isolated, IngestLimits, THE_UPLOAD};
use crate::service::jobs::ScanRemoval;
use crate::service::problem::{ApiError, ApiResult, Problem};
use crate::service::store::{now_rfc3339, ScanRecord};
use crate::service::upload::{receive_scan, TempFileGuard};

/// Links of a scan.
#[derive(Debug, Serialize, ToSchema)]
pub struct ScanLinks {
    /// This scan.
    #[serde(rename = "self")]
    pub self_: String,
    /// Where to POST simulations of it.
    pub simulations: String,
    /// Its uploaded treatment targets (`PUT .../targets/{name}` adds one).
    pub targets: String,
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
                targets: format!("{base}/targets"),
                self_: base,
            },
            record,
        }
    }
}

/// Options of an upload, in its query string.
#[derive(Debug, Default, Deserialize)]
pub struct UploadOptions {
    /// The DICOM series to read when the zip holds several (`uid:<UID>`, `number:<N>`,
    /// `description:<text>` or the bare value); else the service's `[run] series`.
    pub series: Option<String>,
}

/// Upload a scan and ingest it.
#[utoipa::path(
    post, path = "/v1/scans", tag = "scans",
    params(("series" = Option<String>, Query, description = "The DICOM series to read when \
        the zip holds several: `uid:<UID>`, `number:<N>`, `description:<text>`, or the bare \
        value (default: the service's `[run] series`, else the only CT series that is not a \
        scout)")),
    request_body(description = "A NIfTI-1 or NIfTI-2 file (.nii, .nii.gz), an NRRD file with \
        attached data (.nrrd, raw or gzip encoding inside) or a zip of one DICOM series, raw or \
        as the part `file` of a multipart form; told apart by content, whatever the content \
        type says. MetaImage, a single DICOM file and a zip of NIfTI files are refused (422).",
        content(("application/octet-stream"), ("application/zip"), ("application/gzip"),
                ("application/x-nrrd"), ("multipart/form-data"))),
    responses(
        (status = 201, description = "Stored and ingested", body = ScanView,
         headers(("location" = String, description = "The scan's URL"))),
        (status = 400, description = "Empty or broken upload", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Over max_upload_mib", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "JSON or text instead of a scan", body = Problem, content_type = "application/problem+json"),
        (status = 408, description = "The body stopped arriving for body_read_timeout_s", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Not a CT, truncated, unsafe zip, no lungs found, a reader that crashed on the file (scan-reader-crashed) an ingest over ingest_timeout_s or over ingest_memory_mib (ingest-out-of-memory)", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn upload_scan(
    State(state): State<SharedState>,
    Query(options): Query<UploadOptions>,
    request: Request,
) -> ApiResult<Response> {
    if state.jobs.shutting_down() {
        return Err(shutting_down());
    }
    let series = match &options.series {
        Some(text) => Some(text.parse::<SeriesChoice>().map_err(|e| {
            ApiError::bad_request("invalid-series", format!("query parameter series: {e}"))
        })?),
        None => state.config.run.series.clone(),
    };
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
    // The ingest's file form is left beside the upload and moves into the scan with it.
    let stored_ingest = PathBuf::from(format!("{}.ingest", dest.display()));
    let _stored_guard = TempFileGuard(Some(stored_ingest.clone()));
    let worker_state = state.clone();
    let record = blocking(move || {
        let config = &worker_state.config;
        // The upload's series choice overrides the server's default for this scan only.
        let run = crate::run::RunConfig {
            series: series.clone(),
            ..config.run.clone()
        };
        // Isolated: a reader crashing on a hostile file must not take the server down.
        let ingest = ingest_isolated(
            &config.ingest_isolation,
            &named,
            &run,
            IngestLimits {
                timeout: Duration::from_secs_f64(config.ingest_timeout_s),
                memory_mib: config.ingest_memory_mib,
            },
            THE_UPLOAD,
            Some(&stored_ingest),
        )?;
        let record = ScanRecord {
            scan_id: ScanId::random(),
            created_at: now_rfc3339(),
            format: format_name.to_string(),
            upload_bytes: bytes,
            file_name: file_name.to_string(),
            ingest,
            series,
        };
        // In the object store (when there is one) before the record makes it visible.
        worker_state
            .store
            .put_scan_blobs(&record, &named, Some(&stored_ingest))
            .map_err(store_error)?;
        if let Err(e) = worker_state.records.put_scan(&record, &named) {
            let _ = worker_state.store.delete_scan(record.scan_id);
            return Err(store_error(e));
        }
        adopt_stored_ingest(&worker_state.store, record.scan_id, &stored_ingest);
        // With an object store this copy is a cache: keep the data directory's copies bounded.
        worker_state.store.evict_after_store();
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
    blocking(
        move || match state.jobs.remove_unused_scan(id).map_err(store_error)? {
            ScanRemoval::InUse => Err(ApiError::conflict(
                "scan-in-use",
                format!("scan {id} has queued or running jobs; cancel them first"),
            )),
            ScanRemoval::Missing => Err(ApiError::not_found(format!("no scan {id}"))),
            ScanRemoval::Removed => {
                tracing::info!(scan = %id, "scan deleted");
                Ok(StatusCode::NO_CONTENT)
            }
        },
    )
    .await
}

//! A scan's treatment targets: upload (checked against the scan's CT at once), list, fetch
//! and delete. See [`crate::service::targets`].

use std::path::{Path as FsPath, PathBuf};

use axum::extract::{Path, Request, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Serialize;
use utoipa::ToSchema;

use super::{blocking, created, load_scan, scan_id, shutting_down, store_error, SharedState};
use crate::formats::dicom::DicomStudyContext;
use crate::ingest::scan::{load_ct_with, ScanFormat};
use crate::service::ids::ScanId;
use crate::service::problem::{ApiError, ApiResult, Problem};
use crate::service::store::{now_rfc3339, ScanRecord, TargetStored};
use crate::service::targets::{check_target_name, examine, TargetKind, TargetRecord};
use crate::service::upload::{receive_target, TempFileGuard};
use crate::volume::VolumeGeometry;
use crate::Error;

/// Links of a target.
#[derive(Debug, Serialize, ToSchema)]
pub struct TargetLinks {
    /// This target.
    #[serde(rename = "self")]
    pub self_: String,
    /// Its scan.
    pub scan: String,
}

/// An uploaded target as the API shows it.
#[derive(Debug, Serialize, ToSchema)]
pub struct TargetView {
    /// The record: kind, labels or ROIs found on the scan's CT, notes.
    #[serde(flatten)]
    pub record: TargetRecord,
    /// Related resources.
    pub links: TargetLinks,
}

impl TargetView {
    fn of(scan: ScanId, record: TargetRecord) -> Self {
        let base = format!("/v1/scans/{scan}/targets/{}", record.name);
        TargetView {
            links: TargetLinks {
                self_: base,
                scan: format!("/v1/scans/{scan}"),
            },
            record,
        }
    }
}

/// A scan's targets.
#[derive(Debug, Serialize, ToSchema)]
pub struct TargetList {
    /// By name.
    pub items: Vec<TargetView>,
}

/// The target name from the path, or 400 saying what is wrong with it.
fn target_name(name: &str) -> ApiResult<()> {
    check_target_name(name).map_err(|m| ApiError::bad_request("invalid-target-name", m))
}

/// Upload a treatment target (mask or RTSTRUCT) for a scan.
#[utoipa::path(
    put, path = "/v1/scans/{id}/targets/{name}", tag = "scans",
    params(
        ("id" = String, Path, description = "Scan id"),
        ("name" = String, Path, description = "The target's name: 1–64 letters, digits, \
            `.`, `_`, `-`, starting with a letter or digit; a simulation names it as \
            `{\"upload\": name}`"),
    ),
    request_body(description = "The file itself, raw or as the part `file` of a multipart \
        form, told apart by content: a NIfTI (.nii, .nii.gz) or NRRD label map on the scan's \
        CT grid (same dimensions, origin, spacing and direction within 0.01 mm), or one DICOM \
        RT Structure Set whose ROIs lie in the CT's frame of reference and on its slices. \
        Checked against the scan's CT at once, with the checks and messages of `lungmotion \
        run --target`; a file of that name is replaced whole, or kept when the new one is \
        refused. Jobs already submitted keep the file they were submitted with.",
        content(("application/octet-stream"), ("application/gzip"), ("application/dicom"),
                ("multipart/form-data"))),
    responses(
        (status = 201, description = "Stored: its labels (mask) or ROIs (RTSTRUCT) on the \
            scan's CT", body = TargetView,
         headers(("location" = String, description = "The target's URL"))),
        (status = 200, description = "Replaced the target of that name", body = TargetView),
        (status = 400, description = "A name that is not plain (invalid-target-name), an empty or broken upload", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such scan", body = Problem, content_type = "application/problem+json"),
        (status = 408, description = "The body stopped arriving for body_read_timeout_s", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Over max_upload_mib", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "JSON or text instead of a file", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Neither NIfTI, NRRD nor DICOM (unknown-target-format), or refused against the scan's CT (invalid-target): a mask on another grid or with no label, a DICOM file that is no RT Structure Set, an RTSTRUCT with no ROI usable on this CT (another frame of reference, contours off the CT's slices), each named", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "Shutting down (see Retry-After)", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn put_target(
    State(state): State<SharedState>,
    Path((id, name)): Path<(String, String)>,
    request: Request,
) -> ApiResult<Response> {
    if state.jobs.shutting_down() {
        return Err(shutting_down());
    }
    let scan = scan_id(&id)?;
    target_name(&name)?;
    let lookup = state.clone();
    let scan_record = blocking(move || load_scan(&lookup, scan)).await?;
    let dest = state.store.tmp_path("target-upload");
    let mut guard = TempFileGuard(Some(dest.clone()));
    let received = receive_target(request, &dest, state.config.max_upload_bytes).await?;
    let kind = TargetKind::of_format(received.format)
        .ok_or_else(|| ApiError::internal("receive_target let a zip through"))?;
    let (extension, format) = match received.format {
        ScanFormat::Nrrd => ("nrrd", "nrrd"),
        ScanFormat::DicomFile => ("dcm", "dicom"),
        _ if received.gzip => ("nii.gz", "nifti"),
        _ => ("nii", "nifti"),
    };
    let file_name = format!("{name}.{extension}");
    // The readers tell .nii from .nii.gz by name, so the file gets its proper one.
    let named = PathBuf::from(format!("{}-{file_name}", dest.display()));
    std::fs::rename(&dest, &named)
        .map_err(|e| ApiError::internal(format!("cannot move the upload: {e}")))?;
    guard.0 = Some(named.clone());
    // Reading the CT again is an ingest's worth of memory: it takes an ingest's slot.
    let _slot = state
        .ingest_slots
        .acquire()
        .await
        .map_err(|_| shutting_down())?;
    let bytes = received.bytes;
    let worker_state = state.clone();
    let (record, stored) = blocking(move || {
        let (ct, study) = scan_ct(&worker_state, &scan_record)?;
        let shown = format!("the target upload `{name}`");
        let contents = examine(&named, kind, &ct, study.as_ref(), &shown)
            .map_err(|e| refused(e, &named, &shown))?;
        let record = TargetRecord {
            name,
            kind,
            format: format.into(),
            upload_bytes: bytes,
            created_at: now_rfc3339(),
            file_name,
            labels: contents.labels,
            rois: contents.rois,
            notes: contents.notes,
        };
        let mut stored = worker_state
            .store
            .put_target(scan, &record, &named)
            .map_err(store_error)?;
        // With an object store the store cannot tell a scan deleted meanwhile (its record
        // may be in PostgreSQL): asked again now, and the target removed with it gone.
        if stored != TargetStored::ScanMissing
            && worker_state
                .records
                .scan(scan)
                .map_err(store_error)?
                .is_none()
        {
            worker_state
                .store
                .delete_target(scan, &record.name)
                .map_err(store_error)?;
            stored = TargetStored::ScanMissing;
        }
        Ok((record, stored))
    })
    .await?;
    guard.0 = None;
    // The name is the client's and is not logged (it may hold a patient's initials).
    tracing::info!(scan = %scan, kind = ?record.kind, bytes, ?stored, "target stored");
    let view = TargetView::of(scan, record);
    match stored {
        TargetStored::Created => Ok(created(view.links.self_.clone(), view, StatusCode::CREATED)),
        TargetStored::Replaced => Ok((StatusCode::OK, Json(view)).into_response()),
        TargetStored::ScanMissing => Err(ApiError::not_found(format!("no scan {scan}"))),
    }
}

/// The scan's CT grid and DICOM study, read as a job reads them (the server's `[run]`
/// series choice and DICOM options).
fn scan_ct(
    state: &SharedState,
    scan: &ScanRecord,
) -> ApiResult<(VolumeGeometry, Option<DicomStudyContext>)> {
    // Another API process may have received the upload: fetched (and held) when this one
    // has no copy.
    let _copy = state.store.ensure_scan_local(scan).map_err(store_error)?;
    let path = state.store.scan_file(scan);
    let mut options = state.config.run.dicom_read_options();
    options.series = scan.series_or(options.series);
    let loaded = load_ct_with(&path, &options).map_err(|e| {
        ApiError::internal(format!(
            "scan {} cannot be read again for a target check: {e}",
            scan.scan_id
        ))
    })?;
    Ok((loaded.ct.geometry, loaded.study))
}

/// A target refused against the CT: the client's (422) unless the disk failed; the server's
/// path shown as `shown`.
fn refused(e: Error, path: &FsPath, shown: &str) -> ApiError {
    if matches!(e, Error::Io { .. } | Error::Store { .. }) {
        return ApiError::internal(e.to_string());
    }
    let detail = e
        .with_path_shown_as(|_| PathBuf::from(shown))
        .to_string()
        .replace(&path.display().to_string(), shown);
    ApiError::unprocessable("invalid-target", detail)
}

/// A scan's uploaded targets.
#[utoipa::path(
    get, path = "/v1/scans/{id}/targets", tag = "scans",
    params(("id" = String, Path, description = "Scan id")),
    responses(
        (status = 200, description = "Its targets by name, each with its labels or ROIs", body = TargetList),
        (status = 404, description = "No such scan", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn list_targets(
    State(state): State<SharedState>,
    Path(id): Path<String>,
) -> ApiResult<Json<TargetList>> {
    let scan = scan_id(&id)?;
    let records = blocking(move || {
        load_scan(&state, scan)?;
        state.store.list_targets(scan).map_err(store_error)
    })
    .await?;
    Ok(Json(TargetList {
        items: records
            .into_iter()
            .map(|r| TargetView::of(scan, r))
            .collect(),
    }))
}

/// One uploaded target.
#[utoipa::path(
    get, path = "/v1/scans/{id}/targets/{name}", tag = "scans",
    params(("id" = String, Path, description = "Scan id"),
           ("name" = String, Path, description = "Target name")),
    responses(
        (status = 200, description = "The target", body = TargetView),
        (status = 404, description = "No such scan or target", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn get_target(
    State(state): State<SharedState>,
    Path((id, name)): Path<(String, String)>,
) -> ApiResult<Json<TargetView>> {
    let scan = scan_id(&id)?;
    let record = blocking(move || {
        load_scan(&state, scan)?;
        state
            .store
            .target(scan, &name)
            .map_err(store_error)?
            .ok_or_else(|| ApiError::not_found(format!("scan {scan} has no target {name:?}")))
    })
    .await?;
    Ok(Json(TargetView::of(scan, record)))
}

/// Delete an uploaded target (jobs submitted with it keep their copy).
#[utoipa::path(
    delete, path = "/v1/scans/{id}/targets/{name}", tag = "scans",
    params(("id" = String, Path, description = "Scan id"),
           ("name" = String, Path, description = "Target name")),
    responses(
        (status = 204, description = "Deleted"),
        (status = 404, description = "No such scan or target", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn delete_target(
    State(state): State<SharedState>,
    Path((id, name)): Path<(String, String)>,
) -> ApiResult<StatusCode> {
    let scan = scan_id(&id)?;
    blocking(move || {
        if state
            .store
            .delete_target(scan, &name)
            .map_err(store_error)?
        {
            Ok(StatusCode::NO_CONTENT)
        } else {
            Err(ApiError::not_found(format!(
                "scan {scan} has no target {name:?}"
            )))
        }
    })
    .await
}

//! A finished job's outputs: its summary, frame list, displacement fields (NIfTI, or
//! MetaImage converted once and cached) and tracked-point trajectories.

use std::path::PathBuf;

use axum::body::Body;
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderValue};
use axum::response::Response;
use axum::Json;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use utoipa::ToSchema;

use super::{blocking, finished_job, job_id, AppState, SharedState};
use crate::service::ids::JobId;
use crate::service::problem::{ApiError, ApiResult, Problem};

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

/// How a displacement field is delivered.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
pub struct FieldFormat {
    /// `nifti` (default, `.nii.gz`) or `mha` (MetaImage).
    pub format: Option<String>,
}

/// Streams one of the job's files as an attachment.
pub(super) async fn file_response(
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
            millimetres, on the CT's voxels around the lungs (its spacing and direction, origin \
            at the box's first voxel; the whole grid with outputs.field_grid = ct), zero \
            outside the lungs) or, with \
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

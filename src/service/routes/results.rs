//! A finished job's outputs: its summary, frame list, displacement fields (NIfTI, or
//! MetaImage converted once and cached) and tracked-point trajectories.

use std::path::PathBuf;

use axum::body::Body;
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, HeaderValue};
use axum::response::{IntoResponse, Response};
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

/// What a request's `Range` header asks of a file of `len` bytes (RFC 9110, section 14).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum ByteRange {
    /// No usable `Range` (none, another unit, several ranges, or one that does not parse, which
    /// the RFC lets a server ignore): the whole file, `200`.
    Whole,
    /// One satisfiable range, bytes `start..end` (end exclusive, clipped to the file): `206`.
    Part(std::ops::Range<u64>),
    /// A range starting at or past the end, or a zero-length suffix: `416`.
    Unsatisfiable,
}

/// Reads a `Range` header against a file of `len` bytes: `bytes=a-b`, `bytes=a-` and
/// `bytes=-n` (the last `n` bytes) are served; several ranges get the whole file, since one
/// `multipart/byteranges` answer would cost more code than clients of these files need.
pub(super) fn byte_range(header: Option<&HeaderValue>, len: u64) -> ByteRange {
    let Some(text) = header.and_then(|h| h.to_str().ok()) else {
        return ByteRange::Whole;
    };
    let Some((unit, spec)) = text.trim().split_once('=') else {
        return ByteRange::Whole;
    };
    if !unit.trim().eq_ignore_ascii_case("bytes") || spec.contains(',') {
        return ByteRange::Whole;
    }
    let Some((first, last)) = spec.trim().split_once('-') else {
        return ByteRange::Whole;
    };
    let number = |s: &str| -> Option<u64> {
        (!s.is_empty() && s.bytes().all(|b| b.is_ascii_digit()))
            .then(|| s.parse().ok())
            .flatten()
    };
    match (first.trim(), last.trim()) {
        ("", suffix) => match number(suffix) {
            None => ByteRange::Whole,
            Some(0) => ByteRange::Unsatisfiable,
            Some(_) if len == 0 => ByteRange::Unsatisfiable,
            Some(n) => ByteRange::Part(len.saturating_sub(n)..len),
        },
        (start, "") => match number(start) {
            None => ByteRange::Whole,
            Some(a) if a >= len => ByteRange::Unsatisfiable,
            Some(a) => ByteRange::Part(a..len),
        },
        (start, end) => match (number(start), number(end)) {
            (Some(a), Some(b)) if a <= b => {
                if a >= len {
                    ByteRange::Unsatisfiable
                } else {
                    ByteRange::Part(a..b.min(len - 1) + 1)
                }
            }
            // `b < a` or not numbers: invalid, so ignored.
            _ => ByteRange::Whole,
        },
    }
}

/// `416` for a file of `len` bytes, with `Content-Range: bytes */len` as the RFC asks.
fn range_not_satisfiable(filename: &str, len: u64) -> Response {
    let mut response = ApiError::new(
        axum::http::StatusCode::RANGE_NOT_SATISFIABLE,
        "range-not-satisfiable",
        format!("{filename} has {len} bytes; the range asked for starts past its end"),
    )
    .into_response();
    if let Ok(v) = HeaderValue::from_str(&format!("bytes */{len}")) {
        response.headers_mut().insert(header::CONTENT_RANGE, v);
    }
    response
}

/// A file's answer: `200` with the whole `len` bytes, or `206` with the bytes `part` of them
/// (`Content-Range`); both say that ranges are served.
fn file_answer(
    body: Body,
    content_type: &'static str,
    filename: &str,
    len: u64,
    part: Option<std::ops::Range<u64>>,
) -> Response {
    let mut response = Response::new(body);
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    headers.insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    match &part {
        Some(r) => {
            headers.insert(header::CONTENT_LENGTH, HeaderValue::from(r.end - r.start));
            if let Ok(v) = HeaderValue::from_str(&format!("bytes {}-{}/{len}", r.start, r.end - 1))
            {
                headers.insert(header::CONTENT_RANGE, v);
            }
        }
        None => {
            headers.insert(header::CONTENT_LENGTH, HeaderValue::from(len));
        }
    }
    if let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"{filename}\"")) {
        headers.insert(header::CONTENT_DISPOSITION, v);
    }
    if part.is_some() {
        *response.status_mut() = axum::http::StatusCode::PARTIAL_CONTENT;
    }
    response
}

/// Streams one of the job's files as an attachment, or the one range of it that `range` (the
/// request's `Range` header) asks for.
pub(super) async fn file_response(
    path: PathBuf,
    content_type: &'static str,
    filename: String,
    range: Option<&HeaderValue>,
) -> ApiResult<Response> {
    use tokio::io::{AsyncReadExt, AsyncSeekExt};
    let unreadable = |e: std::io::Error| {
        if e.kind() == std::io::ErrorKind::NotFound {
            ApiError::not_found(format!("{filename} is missing from the job's outputs"))
        } else {
            ApiError::internal(format!("cannot read {}: {e}", path.display()))
        }
    };
    let mut file = tokio::fs::File::open(&path).await.map_err(unreadable)?;
    let len = file.metadata().await.map_err(unreadable)?.len();
    Ok(match byte_range(range, len) {
        ByteRange::Whole => {
            let body =
                Body::from_stream(tokio_util::io::ReaderStream::with_capacity(file, 256 << 10));
            file_answer(body, content_type, &filename, len, None)
        }
        ByteRange::Part(r) => {
            file.seek(std::io::SeekFrom::Start(r.start))
                .await
                .map_err(unreadable)?;
            let part = file.take(r.end - r.start);
            let body =
                Body::from_stream(tokio_util::io::ReaderStream::with_capacity(part, 256 << 10));
            file_answer(body, content_type, &filename, len, Some(r))
        }
        ByteRange::Unsatisfiable => range_not_satisfiable(&filename, len),
    })
}

/// Serves the output file `relative` (a path in the run's output directory) of job `id`: from
/// the data directory, or from the object store when there is one (streamed, or a `307` to a
/// presigned URL with `presigned_get`, where the client sends its `Range` to the store). 404
/// naming `filename` when it is not there. One range (`range`, the request's `Range` header)
/// is served as `206` from either store; from the object store with a ranged GET, after a HEAD
/// for the object's size, so only those bytes leave the store.
pub(super) async fn output_response(
    state: &AppState,
    id: JobId,
    relative: &str,
    content_type: &'static str,
    filename: String,
    range: Option<&HeaderValue>,
) -> ApiResult<Response> {
    let Some(blobs) = state.store.blobs() else {
        let path = state.store.job_output_dir(id).join(relative);
        return file_response(path, content_type, filename, range).await;
    };
    let key = format!("jobs/{id}/{}/{relative}", crate::service::store::JOB_OUTPUT);
    let missing = || ApiError::not_found(format!("{filename} is missing from the job's outputs"));
    let failed = |e: crate::Error| ApiError::internal(e.to_string());
    if blobs.presigns() {
        let url = blobs
            .presigned_get(&key)
            .await
            .map_err(failed)?
            .ok_or_else(missing)?;
        let mut response = Response::new(Body::empty());
        *response.status_mut() = axum::http::StatusCode::TEMPORARY_REDIRECT;
        let location = HeaderValue::from_str(&url)
            .map_err(|e| ApiError::internal(format!("presigned URL of {key}: {e}")))?;
        response.headers_mut().insert(header::LOCATION, location);
        return Ok(response);
    }
    if range.is_some() {
        let len = blobs
            .head(&key)
            .await
            .map_err(failed)?
            .ok_or_else(missing)?;
        match byte_range(range, len) {
            ByteRange::Whole => {}
            ByteRange::Part(r) => {
                let stream = blobs
                    .get_range_stream(&key, r.clone())
                    .await
                    .map_err(failed)?
                    .ok_or_else(missing)?;
                let body = Body::from_stream(stream);
                return Ok(file_answer(body, content_type, &filename, len, Some(r)));
            }
            ByteRange::Unsatisfiable => return Ok(range_not_satisfiable(&filename, len)),
        }
    }
    let (len, stream) = blobs
        .get_stream(&key)
        .await
        .map_err(failed)?
        .ok_or_else(missing)?;
    Ok(file_answer(
        Body::from_stream(stream),
        content_type,
        &filename,
        len,
        None,
    ))
}

/// Whether the job's output file `relative` exists (locally or in the object store).
pub(super) fn output_exists(state: &AppState, id: JobId, relative: &str) -> ApiResult<bool> {
    match state.store.blobs() {
        None => Ok(state.store.job_output_dir(id).join(relative).is_file()),
        Some(blobs) => blobs
            .size(&format!(
                "jobs/{id}/{}/{relative}",
                crate::service::store::JOB_OUTPUT
            ))
            .map(|size| size.is_some())
            .map_err(|e| ApiError::internal(e.to_string())),
    }
}

/// Whether the job wrote frame `k` (its directory, or objects under it in the object store).
fn frame_exists(state: &AppState, id: JobId, k: usize) -> ApiResult<bool> {
    match state.store.blobs() {
        None => Ok(state
            .store
            .job_output_dir(id)
            .join("frames")
            .join(k.to_string())
            .is_dir()),
        Some(blobs) => blobs
            .list(&format!(
                "jobs/{id}/{}/frames/{k}",
                crate::service::store::JOB_OUTPUT
            ))
            .map(|listed| !listed.is_empty())
            .map_err(|e| ApiError::internal(e.to_string())),
    }
}

/// The bytes of the job's output file `relative` (small files: `summary.json`), `None` when
/// it is not there.
pub(super) fn read_output(
    state: &AppState,
    id: JobId,
    relative: &str,
) -> ApiResult<Option<Vec<u8>>> {
    match state.store.blobs() {
        None => match std::fs::read(state.store.job_output_dir(id).join(relative)) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(ApiError::internal(format!("job {id}: {relative}: {e}"))),
        },
        Some(blobs) => blobs
            .read(&format!(
                "jobs/{id}/{}/{relative}",
                crate::service::store::JOB_OUTPUT
            ))
            .map(|b| b.map(|b| b.to_vec()))
            .map_err(|e| ApiError::internal(e.to_string())),
    }
}

/// The run's summary.json.
#[utoipa::path(
    get, path = "/v1/jobs/{id}/summary", tag = "results",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, description = "summary.json of the run (as `lungmotion run` writes it)", body = Object),
        (status = 307, description = "With an S3 object store and `presigned_get`: the \
            object's presigned URL in `Location`"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not done", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn job_summary(
    State(state): State<SharedState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    finished_job(&state, id)?;
    output_response(
        &state,
        id,
        "summary.json",
        "application/json",
        format!("{id}-summary.json"),
        headers.get(header::RANGE),
    )
    .await
}

/// The frames of a finished job, read from its `summary.json`, each with its field's link.
fn read_frames(state: &AppState, id: JobId) -> ApiResult<Vec<FrameEntry>> {
    let corrupt = |e: String| ApiError::internal(format!("job {id}: summary: {e}"));
    let bytes = read_output(state, id, "summary.json")?.ok_or_else(|| corrupt("missing".into()))?;
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
        (status = 206, description = "One range of the file (`Range: bytes=a-b`, `a-` or \
            `-n`) with `Content-Range`; several ranges are answered 200 with the whole file"),
        (status = 416, description = "The range starts past the file's end; `Content-Range: \
            bytes */<length>`", body = Problem, content_type = "application/problem+json"),
        (status = 307, description = "With an S3 object store and `presigned_get`: the \
            object's presigned URL in `Location`"),
        (status = 404, description = "No such job or frame", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not done", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn frame_displacement(
    State(state): State<SharedState>,
    Path((id, k)): Path<(String, String)>,
    Query(format): Query<FieldFormat>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let range = headers.get(header::RANGE);
    let id = job_id(&id)?;
    finished_job(&state, id)?;
    let k: usize = k
        .parse()
        .map_err(|_| ApiError::not_found(format!("no frame {k:?} (a frame is a number)")))?;
    let field = format!("frames/{k}/displacement.nii.gz");
    let probe_state = state.clone();
    if !blocking(move || frame_exists(&probe_state, id, k)).await? {
        let worker_state = state.clone();
        let count = blocking(move || Ok(read_frames(&worker_state, id)?.len())).await?;
        return Err(ApiError::not_found(format!(
            "job {id} has {count} frames (0–{}); there is no frame {k}",
            count.saturating_sub(1)
        )));
    }
    match format.format.as_deref().unwrap_or("nifti") {
        "nifti" | "nii" | "nii.gz" => {
            output_response(
                &state,
                id,
                &field,
                "application/gzip",
                format!("{id}-frame-{k}.nii.gz"),
                range,
            )
            .await
        }
        "mha" | "metaimage" => {
            let written = format!("frames/{k}/displacement.mha");
            let probe_state = state.clone();
            let was_written = {
                let written = written.clone();
                blocking(move || output_exists(&probe_state, id, &written)).await?
            };
            if was_written {
                return output_response(
                    &state,
                    id,
                    &written,
                    "application/octet-stream",
                    format!("{id}-frame-{k}.mha"),
                    range,
                )
                .await;
            }
            let path = {
                let worker_state = state.clone();
                blocking(move || metaimage_copy(&worker_state, id, k)).await?
            };
            file_response(
                path,
                "application/octet-stream",
                format!("{id}-frame-{k}.mha"),
                range,
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
    std::fs::create_dir_all(&cache)
        .map_err(|e| ApiError::internal(format!("cannot create {}: {e}", cache.display())))?;
    let relative = format!("frames/{k}/displacement.nii.gz");
    // From the object store, the field is fetched into the cache for the conversion.
    let (nifti, fetched) = match state.store.blobs() {
        None => (state.store.job_output_dir(id).join(&relative), false),
        Some(blobs) => {
            let local = cache.join(format!("frame-{k}.nii.gz"));
            let key = format!("jobs/{id}/{}/{relative}", crate::service::store::JOB_OUTPUT);
            if !blobs
                .fetch_file(&key, &local)
                .map_err(|e| ApiError::internal(e.to_string()))?
            {
                return Err(ApiError::not_found(format!("job {id} has no frame {k}")));
            }
            (local, true)
        }
    };
    let read = crate::formats::nifti::read_nifti_vector_field(&nifti);
    if fetched {
        let _ = std::fs::remove_file(&nifti);
    }
    let (geometry, field) =
        read.map_err(|e| ApiError::internal(format!("job {id} frame {k}: {e}")))?;
    let flat: Vec<f32> = field.iter().flatten().copied().collect();
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
        (status = 307, description = "With an S3 object store and `presigned_get`: the \
            object's presigned URL in `Location`"),
        (status = 404, description = "No such job, or it tracked no points", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not done", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn job_trajectories(
    State(state): State<SharedState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    finished_job(&state, id)?;
    let probe_state = state.clone();
    if !blocking(move || output_exists(&probe_state, id, "trajectories.csv")).await? {
        return Err(ApiError::not_found(format!(
            "job {id} tracked no points (give \"points\" in the simulation request)"
        )));
    }
    output_response(
        &state,
        id,
        "trajectories.csv",
        "text/csv",
        format!("{id}-trajectories.csv"),
        headers.get(header::RANGE),
    )
    .await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_byte_range_is_served_and_the_rest_is_whole_or_unsatisfiable() {
        let ask =
            |text: &str, len: u64| byte_range(Some(&HeaderValue::from_str(text).unwrap()), len);
        assert_eq!(byte_range(None, 10), ByteRange::Whole);
        assert_eq!(ask("bytes=0-3", 10), ByteRange::Part(0..4));
        assert_eq!(ask("bytes=4-", 10), ByteRange::Part(4..10));
        assert_eq!(ask("bytes=-3", 10), ByteRange::Part(7..10));
        // Past the end: clipped; a suffix longer than the file is the whole file as a range.
        assert_eq!(ask("bytes=8-100", 10), ByteRange::Part(8..10));
        assert_eq!(ask("bytes=-100", 10), ByteRange::Part(0..10));
        assert_eq!(ask("Bytes = 2-2", 10), ByteRange::Part(2..3));
        for unsatisfiable in ["bytes=10-", "bytes=10-12", "bytes=-0"] {
            assert_eq!(
                ask(unsatisfiable, 10),
                ByteRange::Unsatisfiable,
                "{unsatisfiable}"
            );
        }
        assert_eq!(ask("bytes=-1", 0), ByteRange::Unsatisfiable);
        // Ignored, as the RFC allows: several ranges, another unit, nonsense, b < a.
        for whole in [
            "bytes=0-1,4-5",
            "items=0-1",
            "bytes=a-b",
            "bytes=5-2",
            "bytes=",
            "0-1",
        ] {
            assert_eq!(ask(whole, 10), ByteRange::Whole, "{whole}");
        }
    }
}

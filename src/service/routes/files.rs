//! Every file a finished job's run wrote (frames, meshes, quick looks, the lung mask and
//! groups, `ingest.json`, the summary …): listed with their links and served with their
//! content types, so nothing `lungmotion run` writes is out of a client's reach.

use std::path::{Component, Path as FsPath, PathBuf};

use axum::extract::{Path, State};
use axum::response::Response;
use axum::Json;
use serde::Serialize;
use utoipa::ToSchema;

use super::results::output_response;
use super::{blocking, finished_job, job_id, SharedState};
use crate::service::problem::{ApiError, ApiResult, Problem};
use crate::service::store::JOB_OUTPUT;

/// Deepest directory nesting listed (the run writes `frames/<k>/` and `ingest/`).
const MAX_DEPTH: usize = 4;

/// One output file of a job.
#[derive(Debug, Serialize, ToSchema)]
pub struct OutputFile {
    /// Its path in the run's output directory (`frames/0/displacement.nii.gz`).
    pub path: String,
    /// Its size, bytes.
    pub bytes: u64,
    /// The content type it is served with.
    pub content_type: String,
    /// Where to fetch it.
    pub href: String,
}

/// The output files of a finished job.
#[derive(Debug, Serialize, ToSchema)]
pub struct OutputFileList {
    /// Every file, sorted by path.
    pub files: Vec<OutputFile>,
}

/// The content type of an output file, from its name.
pub fn content_type_of(name: &str) -> &'static str {
    let lower = name.to_ascii_lowercase();
    let by_suffix = [
        (".nii.gz", "application/gzip"),
        (".dcm", "application/dicom"),
        (".gz", "application/gzip"),
        (".json", "application/json"),
        (".csv", "text/csv"),
        (".png", "image/png"),
        // VTK's XML formats (unstructured grid, poly data, image data).
        (".vtu", "application/xml"),
        (".vtp", "application/xml"),
        (".vti", "application/xml"),
        (".md", "text/markdown"),
        (".txt", "text/plain"),
    ];
    by_suffix
        .iter()
        .find(|(suffix, _)| lower.ends_with(suffix))
        .map_or("application/octet-stream", |(_, t)| t)
}

/// The files under `out`, as paths relative to it with `/` separators; hidden names, symbolic
/// links and anything deeper than [`MAX_DEPTH`] are left out (the run writes none of them).
fn output_files(out: &FsPath) -> std::io::Result<Vec<(String, u64)>> {
    let mut found = Vec::new();
    let mut stack = vec![(out.to_path_buf(), 0usize)];
    while let Some((dir, depth)) = stack.pop() {
        for entry in std::fs::read_dir(&dir)? {
            let entry = entry?;
            if entry.file_name().to_string_lossy().starts_with('.') {
                continue;
            }
            let kind = entry.file_type()?;
            let path = entry.path();
            if kind.is_dir() && depth < MAX_DEPTH {
                stack.push((path, depth + 1));
            } else if kind.is_file() {
                let relative = path.strip_prefix(out).unwrap_or(&path);
                let name: Vec<String> = relative
                    .components()
                    .map(|c| c.as_os_str().to_string_lossy().into_owned())
                    .collect();
                found.push((name.join("/"), entry.metadata()?.len()));
            }
        }
    }
    found.sort();
    Ok(found)
}

/// Whether `relative` is a plain path: `/`-separated names, none empty or hidden, no `..`, no
/// absolute path, no backslash or NUL, at most 1 024 bytes.
fn is_plain(relative: &str) -> bool {
    !relative.is_empty()
        && relative.len() <= 1024
        && !relative.contains('\\')
        && !relative.contains('\0')
        && relative
            .split('/')
            .all(|part| !part.is_empty() && !part.starts_with('.'))
        && FsPath::new(relative)
            .components()
            .all(|c| matches!(c, Component::Normal(_)))
}

/// The output files of job `id` in the object store, as [`output_files`] lists a directory:
/// hidden names and anything deeper than [`MAX_DEPTH`] left out.
fn stored_output_files(
    blobs: &crate::service::blobs::BlobStore,
    id: crate::service::ids::JobId,
    under: &str,
) -> ApiResult<Vec<(String, u64)>> {
    let dir = if under.is_empty() {
        format!("jobs/{id}/{JOB_OUTPUT}")
    } else {
        format!("jobs/{id}/{JOB_OUTPUT}/{under}")
    };
    let listed = blobs
        .list(&dir)
        .map_err(|e| ApiError::internal(format!("job {id}: cannot list its outputs: {e}")))?;
    Ok(listed
        .into_iter()
        .filter(|(name, _)| is_plain(name) && name.split('/').count() <= MAX_DEPTH + 1)
        .collect())
}

/// The file `relative` names inside `out`, or 404: plain names only (no `..`, no absolute
/// path, no hidden file), and it must be a regular file inside `out` once links are resolved.
fn resolve_output(out: &FsPath, relative: &str) -> ApiResult<PathBuf> {
    resolve_output_entry(out, relative, false)
}

/// The file (or, with `directory`, the directory) `relative` names inside `out`, or 404, as
/// [`resolve_output`] checks it.
fn resolve_output_entry(out: &FsPath, relative: &str, directory: bool) -> ApiResult<PathBuf> {
    let what = if directory { "directory" } else { "file" };
    let missing = || ApiError::not_found(format!("the job wrote no {what} {relative:?}"));
    if !is_plain(relative) {
        return Err(missing());
    }
    let path = out.join(relative);
    let (Ok(root), Ok(real)) = (out.canonicalize(), path.canonicalize()) else {
        return Err(missing());
    };
    let right_kind = if directory {
        real.is_dir()
    } else {
        real.is_file()
    };
    if !real.starts_with(&root) || !right_kind {
        return Err(missing());
    }
    Ok(real)
}

/// Most bytes of files one archive may hold (a 512 × 512 × 500 DICOM series is ≈ 260 MB).
const MAX_ARCHIVE_BYTES: u64 = 2 << 30;

/// A zip (stored, not deflated: DICOM and gzip gain nothing) of the files under `dir`, with
/// paths relative to it.
fn zip_directory(dir: &FsPath, shown: &str) -> ApiResult<Vec<u8>> {
    let files =
        output_files(dir).map_err(|e| ApiError::internal(format!("cannot list {shown}: {e}")))?;
    zip_files(&files, shown, |name| {
        std::fs::read(dir.join(name)).map_err(|e| e.to_string())
    })
}

/// A stored zip of `files` (name relative to the directory `shown`, bytes), each read by
/// `read`; refused when they hold more than [`MAX_ARCHIVE_BYTES`].
fn zip_files<B: AsRef<[u8]>>(
    files: &[(String, u64)],
    shown: &str,
    read: impl Fn(&str) -> Result<B, String>,
) -> ApiResult<Vec<u8>> {
    let total: u64 = files.iter().map(|(_, bytes)| bytes).sum();
    if total > MAX_ARCHIVE_BYTES {
        return Err(ApiError::new(
            axum::http::StatusCode::PAYLOAD_TOO_LARGE,
            "archive-too-large",
            format!(
                "{shown} holds {total} bytes, more than the {MAX_ARCHIVE_BYTES} one archive may; \
                 fetch its files one by one"
            ),
        ));
    }
    let failed = |e: &dyn std::fmt::Display| ApiError::internal(format!("zip of {shown}: {e}"));
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::with_capacity(
        total as usize + files.len() * 128,
    )));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Stored)
        .large_file(total > u64::from(u32::MAX));
    for (name, _) in files {
        let bytes = read(name).map_err(|e| failed(&e))?;
        zip.start_file(name.as_str(), options)
            .map_err(|e| failed(&e))?;
        std::io::Write::write_all(&mut zip, bytes.as_ref()).map_err(|e| failed(&e))?;
    }
    Ok(zip.finish().map_err(|e| failed(&e))?.into_inner())
}

/// As [`zip_directory`], of the directory `shown` of job `id`'s outputs in the object store.
fn zip_stored_directory(
    blobs: &crate::service::blobs::BlobStore,
    id: crate::service::ids::JobId,
    shown: &str,
) -> ApiResult<Vec<u8>> {
    if !is_plain(shown) {
        return Err(ApiError::not_found(format!(
            "the job wrote no directory {shown:?}"
        )));
    }
    let files = stored_output_files(blobs, id, shown)?;
    if files.is_empty() {
        return Err(ApiError::not_found(format!(
            "the job wrote no directory {shown:?}"
        )));
    }
    zip_files(&files, shown, |name| {
        let key = format!("jobs/{id}/{JOB_OUTPUT}/{shown}/{name}");
        blobs
            .read(&key)
            .map_err(|e| e.to_string())?
            .ok_or_else(|| format!("{key} vanished"))
    })
}

/// One directory of a finished job's outputs as a zip: a virtual 4D-CT phase's DICOM series
/// (`frames/3/virtual-ct-dicom`), a frame's whole folder, `ingest` …
#[utoipa::path(
    get, path = "/v1/jobs/{id}/archives/{path}", tag = "results",
    params(("id" = String, Path, description = "Job id"),
           ("path" = String, Path, description = "A directory of the file list's paths \
            (`frames/3/virtual-ct-dicom`, `frames/3`, `ingest`)")),
    responses(
        (status = 200, description = "A zip of the directory's files (stored, paths relative \
            to it)", content_type = "application/zip"),
        (status = 404, description = "No such job or directory", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not done", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "More than 2 GiB of files", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn job_archive(
    State(state): State<SharedState>,
    Path((id, relative)): Path<(String, String)>,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    let shown = relative.trim_end_matches('/').to_string();
    let name = shown.clone();
    let bytes = blocking(move || {
        finished_job(&state, id)?;
        if let Some(blobs) = state.store.blobs() {
            return zip_stored_directory(blobs, id, &name);
        }
        let dir = resolve_output_entry(&state.store.job_output_dir(id), &name, true)?;
        zip_directory(&dir, &name)
    })
    .await?;
    let filename = format!("{id}-{}.zip", shown.replace('/', "-"));
    let mut response = Response::new(axum::body::Body::from(bytes));
    let headers = response.headers_mut();
    headers.insert(
        axum::http::header::CONTENT_TYPE,
        axum::http::HeaderValue::from_static("application/zip"),
    );
    if let Ok(v) =
        axum::http::HeaderValue::from_str(&format!("attachment; filename=\"{filename}\""))
    {
        headers.insert(axum::http::header::CONTENT_DISPOSITION, v);
    }
    Ok(response)
}

/// Every file of a finished job, with its link and content type.
#[utoipa::path(
    get, path = "/v1/jobs/{id}/files", tag = "results",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, description = "Every file the run wrote: the frames' fields (and \
            MetaImage and meshes when asked for), summary.json, trajectories.csv, the quick \
            looks, and under ingest/ the lung mask, the groups, the meshes and ingest.json",
         body = OutputFileList),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not done", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn job_files(
    State(state): State<SharedState>,
    Path(id): Path<String>,
) -> ApiResult<Json<OutputFileList>> {
    let id = job_id(&id)?;
    blocking(move || {
        finished_job(&state, id)?;
        let listed = match state.store.blobs() {
            Some(blobs) => stored_output_files(blobs, id, "")?,
            None => output_files(&state.store.job_output_dir(id)).map_err(|e| {
                ApiError::internal(format!("job {id}: cannot list its outputs: {e}"))
            })?,
        };
        let files = listed
            .into_iter()
            .map(|(path, bytes)| OutputFile {
                content_type: content_type_of(&path).to_string(),
                href: format!("/v1/jobs/{id}/files/{path}"),
                path,
                bytes,
            })
            .collect();
        Ok(Json(OutputFileList { files }))
    })
    .await
}

/// One file of a finished job, by its path in the run's output directory.
#[utoipa::path(
    get, path = "/v1/jobs/{id}/files/{path}", tag = "results",
    params(("id" = String, Path, description = "Job id"),
           ("path" = String, Path, description = "The file's path as the file list gives it \
            (`ingest/lung-mask.nii.gz`, `frames/3/displacement.nii.gz`, `breathing.png` …)")),
    responses(
        (status = 200, description = "The file, with the content type the file list gives \
            (application/gzip, application/json, text/csv, image/png, application/xml for VTK \
            XML meshes, else application/octet-stream)",
         content(("application/gzip"), ("application/json"), ("text/csv"), ("image/png"),
                 ("application/xml"), ("application/octet-stream"))),
        (status = 206, description = "One range of the file (`Range: bytes=a-b`, `a-` or \
            `-n`) with `Content-Range`; several ranges are answered 200 with the whole file"),
        (status = 416, description = "The range starts past the file's end; `Content-Range: \
            bytes */<length>`", body = Problem, content_type = "application/problem+json"),
        (status = 307, description = "With an S3 object store and `presigned_get`: the \
            object's presigned URL in `Location`"),
        (status = 404, description = "No such job or file", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not done", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn job_file(
    State(state): State<SharedState>,
    Path((id, relative)): Path<(String, String)>,
    headers: axum::http::HeaderMap,
) -> ApiResult<Response> {
    let range = headers.get(axum::http::header::RANGE);
    let id = job_id(&id)?;
    let worker_state = state.clone();
    let shown = relative.clone();
    let filename = format!("{id}-{}", shown.replace('/', "-"));
    if state.store.blobs().is_some() {
        finished_job(&state, id)?;
        if !is_plain(&relative) {
            return Err(ApiError::not_found(format!(
                "the job wrote no file {relative:?}"
            )));
        }
        return output_response(
            &state,
            id,
            &relative,
            content_type_of(&shown),
            filename,
            range,
        )
        .await
        .map_err(|e| {
            if e.status == axum::http::StatusCode::NOT_FOUND {
                ApiError::not_found(format!("the job wrote no file {relative:?}"))
            } else {
                e
            }
        });
    }
    let path = blocking(move || {
        finished_job(&worker_state, id)?;
        resolve_output(&worker_state.store.job_output_dir(id), &relative)
    })
    .await?;
    super::results::file_response(path, content_type_of(&shown), filename, range).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn content_types_follow_the_file_names() {
        assert_eq!(
            content_type_of("frames/0/displacement.nii.gz"),
            "application/gzip"
        );
        assert_eq!(content_type_of("ingest/ingest.json"), "application/json");
        assert_eq!(content_type_of("ingest/mesh.vtu"), "application/xml");
        assert_eq!(content_type_of("breathing.png"), "image/png");
        assert_eq!(content_type_of("trajectories.csv"), "text/csv");
        assert_eq!(
            content_type_of("frames/0/displacement.mha"),
            "application/octet-stream"
        );
    }

    #[test]
    fn only_plain_paths_inside_the_outputs_resolve() {
        let dir = std::env::temp_dir().join(format!("lm-files-{}", std::process::id()));
        let out = dir.join("out");
        std::fs::create_dir_all(out.join("ingest")).unwrap();
        std::fs::write(out.join("ingest/ingest.json"), b"{}").unwrap();
        std::fs::write(dir.join("job.json"), b"{}").unwrap();
        std::fs::write(out.join(".hidden"), b"x").unwrap();
        assert!(resolve_output(&out, "ingest/ingest.json").is_ok());
        for bad in [
            "../job.json",
            "ingest/../../job.json",
            "/etc/passwd",
            ".hidden",
            "ingest//ingest.json",
            "ingest",
            "",
            "ingest\\ingest.json",
        ] {
            let e = resolve_output(&out, bad).unwrap_err();
            assert_eq!(e.status.as_u16(), 404, "{bad}");
            assert!(e.detail.contains("wrote no file"), "{bad}: {}", e.detail);
        }
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink(dir.join("job.json"), out.join("link.json")).unwrap();
            assert!(resolve_output(&out, "link.json").is_err());
        }
        let zipped = zip_directory(&out.join("ingest"), "ingest").unwrap();
        let mut read = zip::ZipArchive::new(std::io::Cursor::new(zipped)).unwrap();
        assert_eq!(read.len(), 1);
        assert_eq!(read.by_index(0).unwrap().name().unwrap(), "ingest.json");
        assert!(resolve_output_entry(&out, "ingest", true).is_ok());
        assert!(resolve_output_entry(&out, "ingest/ingest.json", true).is_err());
        assert!(resolve_output_entry(&out, "../out", true).is_err());
        let listed = output_files(&out).unwrap();
        assert_eq!(
            listed.iter().map(|(p, _)| p.as_str()).collect::<Vec<_>>(),
            vec!["ingest/ingest.json"]
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}

//! Receiving a scan or target upload: the body (raw, or the `file` part of a multipart form)
//! is streamed to a file in the store's `tmp/` while its size is counted, so an oversized
//! upload is cut off at the limit rather than buffered; then its format is told from its
//! first bytes, never from a name or content type the client chose.

use std::path::{Path, PathBuf};

use axum::body::Body;
use axum::extract::{FromRequest, Multipart, Request};
use axum::http::{header, StatusCode};
use futures_util::{Stream, StreamExt};
use tokio::io::AsyncWriteExt;

use super::problem::ApiError;
use crate::ingest::scan::{classify_header, ScanFormat};

/// A received upload in `tmp/`.
#[derive(Debug)]
pub struct ReceivedUpload {
    /// Where it was written.
    pub path: PathBuf,
    /// Bytes received.
    pub bytes: u64,
    /// What its content is.
    pub format: ScanFormat,
    /// Whether it is gzip-compressed (a `.nii.gz`).
    pub gzip: bool,
}

impl ReceivedUpload {
    /// The name the scan's file gets in the store, and the format's API name.
    pub fn stored_name(&self) -> (&'static str, &'static str) {
        match self.format {
            ScanFormat::DicomZip => ("scan.zip", "dicom-zip"),
            ScanFormat::Nrrd => ("scan.nrrd", "nrrd"),
            _ if self.gzip => ("scan.nii.gz", "nifti"),
            _ => ("scan.nii", "nifti"),
        }
    }
}

/// Removes the temporary file unless it was moved into the store.
pub struct TempFileGuard(pub Option<PathBuf>);

impl Drop for TempFileGuard {
    fn drop(&mut self) {
        if let Some(p) = self.0.take() {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// What an upload is, in the answers' words.
#[derive(Debug, Clone, Copy)]
struct Expected {
    /// What the server accepts up to the limit (`scans`).
    plural: &'static str,
    /// The bytes to send (`the bytes of a NIfTI file or a zip of a DICOM series`).
    bytes: &'static str,
}

const SCAN: Expected = Expected {
    plural: "scans",
    bytes: "the bytes of a NIfTI or NRRD file or a zip of a DICOM series",
};

const TARGET: Expected = Expected {
    plural: "target files",
    bytes: "the bytes of a NIfTI or NRRD label map (gzip or not) or of one DICOM RTSTRUCT file",
};

/// Streams the request's scan to `dest` within `limit` bytes and identifies it.
pub async fn receive_scan(
    request: Request,
    dest: &Path,
    limit: u64,
) -> Result<ReceivedUpload, ApiError> {
    let (bytes, head) = receive_body(request, dest, limit, SCAN).await?;
    let format = classify_header(&head).ok_or_else(|| {
        ApiError::unprocessable(
            "unknown-scan-format",
            format!(
                "the upload ({bytes} bytes, starting {:02x?}) is neither a NIfTI file \
                 (.nii or .nii.gz), an NRRD file nor a zip of a DICOM series",
                &head[..head.len().min(8)]
            ),
        )
    })?;
    if format == ScanFormat::DicomFile {
        return Err(ApiError::unprocessable(
            "single-dicom-file",
            "the upload is a single DICOM file; upload the whole series as one zip",
        ));
    }
    Ok(ReceivedUpload {
        path: dest.to_path_buf(),
        bytes,
        format,
        gzip: head.starts_with(&[0x1f, 0x8b]),
    })
}

/// Streams the request's target file to `dest` within `limit` bytes and identifies it: a
/// NIfTI or NRRD label map, or a single DICOM file (an RTSTRUCT, checked when read).
pub async fn receive_target(
    request: Request,
    dest: &Path,
    limit: u64,
) -> Result<ReceivedUpload, ApiError> {
    let (bytes, head) = receive_body(request, dest, limit, TARGET).await?;
    let format = classify_header(&head)
        .filter(|f| !matches!(f, ScanFormat::DicomZip | ScanFormat::DicomDirectory))
        .ok_or_else(|| {
            ApiError::unprocessable(
                "unknown-target-format",
                format!(
                    "the target upload ({bytes} bytes, starting {:02x?}) is neither a NIfTI \
                     file (.nii or .nii.gz), an NRRD file nor a DICOM file (an RTSTRUCT); a \
                     zip is not accepted: send the one file",
                    &head[..head.len().min(8)]
                ),
            )
        })?;
    Ok(ReceivedUpload {
        path: dest.to_path_buf(),
        bytes,
        format,
        gzip: head.starts_with(&[0x1f, 0x8b]),
    })
}

/// Streams the body (raw, or the multipart part `file`) to `dest` within `limit` bytes;
/// its length and first bytes.
async fn receive_body(
    request: Request,
    dest: &Path,
    limit: u64,
    expected: Expected,
) -> Result<(u64, Vec<u8>), ApiError> {
    let content_type = request
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_ascii_lowercase();
    let too_large = |n: u64| {
        ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "upload-too-large",
            format!(
                "the upload is {n} bytes or more; this server accepts {} up to {limit} bytes \
                 ({} MiB, max_upload_mib)",
                expected.plural,
                limit >> 20
            ),
        )
    };
    if let Some(declared) = request
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok())
    {
        if declared > limit {
            return Err(too_large(declared));
        }
    }
    if content_type.starts_with("application/json") || content_type.starts_with("text/") {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            format!(
                "an upload of {} is {} (application/octet-stream, application/zip, \
                 application/gzip, application/dicom or multipart/form-data with a part \
                 named \"file\"), not {content_type}",
                expected.plural, expected.bytes
            ),
        ));
    }
    let bytes = if content_type.starts_with("multipart/form-data") {
        let mut form = Multipart::from_request(request, &()).await.map_err(|e| {
            ApiError::bad_request("bad-multipart", format!("multipart upload: {e}"))
        })?;
        loop {
            let field = form.next_field().await.map_err(|e| {
                ApiError::bad_request("bad-multipart", format!("multipart upload: {e}"))
            })?;
            let Some(field) = field else {
                return Err(ApiError::bad_request(
                    "bad-multipart",
                    "multipart upload has no part named \"file\" holding the file",
                ));
            };
            if field.name() == Some("file") {
                break write_stream(field, dest, limit).await?;
            }
        }
    } else {
        write_stream(Body::into_data_stream(request.into_body()), dest, limit).await?
    };
    let Some(bytes) = bytes else {
        return Err(too_large(limit + 1));
    };
    if bytes == 0 {
        return Err(ApiError::bad_request(
            "empty-upload",
            format!("the upload is empty; send {}", expected.bytes),
        ));
    }
    Ok((bytes, read_head(dest).await?))
}

/// Writes a body stream to `dest`; `None` when it passed `limit` (the file is then removed).
async fn write_stream<S, B, E>(
    mut stream: S,
    dest: &Path,
    limit: u64,
) -> Result<Option<u64>, ApiError>
where
    S: Stream<Item = Result<B, E>> + Unpin,
    B: AsRef<[u8]>,
    E: std::fmt::Display,
{
    let store_error =
        |e: std::io::Error| ApiError::internal(format!("cannot write the upload: {e}"));
    let mut file = tokio::fs::File::create(dest).await.map_err(store_error)?;
    let mut written = 0u64;
    while let Some(chunk) = stream.next().await {
        let chunk = match chunk {
            Ok(c) => c,
            Err(e) => {
                drop(file);
                let _ = tokio::fs::remove_file(dest).await;
                return Err(ApiError::bad_request(
                    "upload-interrupted",
                    format!("the upload broke off after {written} bytes: {e}"),
                ));
            }
        };
        let chunk = chunk.as_ref();
        written += chunk.len() as u64;
        if written > limit {
            drop(file);
            let _ = tokio::fs::remove_file(dest).await;
            return Ok(None);
        }
        file.write_all(chunk).await.map_err(store_error)?;
    }
    file.flush().await.map_err(store_error)?;
    file.sync_all().await.map_err(store_error)?;
    Ok(Some(written))
}

async fn read_head(path: &Path) -> Result<Vec<u8>, ApiError> {
    use tokio::io::AsyncReadExt;
    let mut head = Vec::with_capacity(544);
    let file = tokio::fs::File::open(path)
        .await
        .map_err(|e| ApiError::internal(format!("cannot reopen the upload: {e}")))?;
    file.take(544)
        .read_to_end(&mut head)
        .await
        .map_err(|e| ApiError::internal(format!("cannot reopen the upload: {e}")))?;
    Ok(head)
}

//! Errors as the client sees them: RFC 9457 `application/problem+json`, one slug per kind of
//! problem, a detail that names what was wrong, and the request id to quote to support.

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use std::path::{Path, PathBuf};

use crate::Error;

/// Media type of every error body.
pub const PROBLEM_JSON: &str = "application/problem+json";

/// An error answer: status, a stable slug, and a detail for humans.
#[derive(Debug, Clone)]
pub struct ApiError {
    /// HTTP status.
    pub status: StatusCode,
    /// Stable machine-readable kind (`invalid-trace`, `queue-full`, …).
    pub slug: &'static str,
    /// What was wrong, naming the input.
    pub detail: String,
    /// Seconds the client should wait before retrying (429, 503).
    pub retry_after_s: Option<u64>,
}

/// The JSON body of an error.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct Problem {
    /// `urn:lungmotion:problem:<slug>`.
    #[serde(rename = "type")]
    pub type_uri: String,
    /// Short summary of the kind of problem.
    pub title: String,
    /// HTTP status.
    pub status: u16,
    /// What was wrong with this request.
    pub detail: String,
    /// The request path.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
    /// The request id (also in the `x-request-id` header).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub request_id: Option<String>,
}

impl ApiError {
    /// An error with a status, slug and detail.
    pub fn new(status: StatusCode, slug: &'static str, detail: impl Into<String>) -> Self {
        ApiError {
            status,
            slug,
            detail: detail.into(),
            retry_after_s: None,
        }
    }

    /// 400: the body is not what the content type promises.
    pub fn bad_request(slug: &'static str, detail: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, slug, detail)
    }

    /// 404: no such scan, job, frame or route.
    pub fn not_found(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, "not-found", detail)
    }

    /// 409: the resource is not in a state that allows this.
    pub fn conflict(slug: &'static str, detail: impl Into<String>) -> Self {
        Self::new(StatusCode::CONFLICT, slug, detail)
    }

    /// 422: well-formed but unusable content.
    pub fn unprocessable(slug: &'static str, detail: impl Into<String>) -> Self {
        Self::new(StatusCode::UNPROCESSABLE_ENTITY, slug, detail)
    }

    /// 500: our fault; the detail is logged, the client gets the request id.
    pub fn internal(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", detail)
    }

    /// Adds a `Retry-After`.
    pub fn retry_after(mut self, seconds: u64) -> Self {
        self.retry_after_s = Some(seconds);
        self
    }

    /// Maps a library error met while handling the client's input to its answer; a path the
    /// error names in a field is shown by its file name only (see
    /// [`ApiError::from_input_error_showing`]).
    pub fn from_input_error(error: Error) -> Self {
        Self::from_input_error_showing(error, |path| {
            path.file_name().map(PathBuf::from).unwrap_or_default()
        })
    }

    /// [`ApiError::from_input_error`], the path the error names in a field shown as what it is
    /// to the client (`the upload`, a name relative to the store), never as the server's path.
    pub fn from_input_error_showing(error: Error, shown_as: impl FnOnce(&Path) -> PathBuf) -> Self {
        let error = error.with_path_shown_as(shown_as);
        let detail = error.to_string();
        match error {
            Error::InvalidScan { .. } => Self::unprocessable("invalid-scan", detail),
            Error::Ingest(_) => Self::unprocessable("ingest-failed", detail),
            Error::InvalidMaterial(_)
            | Error::Config { .. }
            | Error::Trace { .. }
            | Error::Points { .. }
            | Error::Argument { .. } => Self::unprocessable("invalid-input", detail),
            // I/O, store and format failures are ours: 500, detail kept for the log only.
            _ => Self::internal(detail),
        }
    }

    /// Replaces a server path in the detail text with what it is to the client, for paths
    /// inside an error's reason (a DICOM series lists the files it skipped).
    pub fn redact_path(mut self, path: &Path, shown_as: &str) -> Self {
        self.detail = self.detail.replace(&path.display().to_string(), shown_as);
        self
    }

    fn title(&self) -> &'static str {
        self.status.canonical_reason().unwrap_or("Error")
    }

    /// The body, with the request's path and id when known.
    pub fn to_problem(&self, instance: Option<String>, request_id: Option<String>) -> Problem {
        Problem {
            type_uri: format!("urn:lungmotion:problem:{}", self.slug),
            title: self.title().to_string(),
            status: self.status.as_u16(),
            // Our own failures name server paths and internals: those stay in the log,
            // which the request id leads to.
            detail: if self.status == StatusCode::INTERNAL_SERVER_ERROR {
                "an internal error occurred; the server log has the details under this \
                 request id"
                    .to_string()
            } else {
                self.detail.clone()
            },
            instance,
            request_id,
        }
    }
}

impl std::fmt::Display for ApiError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} {}: {}", self.status.as_u16(), self.slug, self.detail)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        if self.status.is_server_error() && self.retry_after_s.is_none() {
            tracing::error!(slug = self.slug, detail = %self.detail, "request failed");
        }
        // The path and request id are filled in by the problem middleware, which sees the
        // request; the error itself travels in the response extensions.
        let body = serde_json::to_vec(&self.to_problem(None, None)).unwrap_or_default();
        let mut response = (self.status, body).into_response();
        let headers = response.headers_mut();
        headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
        if let Some(s) = self.retry_after_s {
            headers.insert(header::RETRY_AFTER, HeaderValue::from(s));
        }
        if self.status == StatusCode::UNAUTHORIZED {
            headers.insert(
                header::WWW_AUTHENTICATE,
                HeaderValue::from_static("Bearer realm=\"lungmotion\""),
            );
        }
        response.extensions_mut().insert(self);
        response
    }
}

/// Handler result.
pub type ApiResult<T> = std::result::Result<T, ApiError>;

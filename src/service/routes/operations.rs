//! Operations: liveness and readiness probes, Prometheus metrics, and the answer to unknown
//! routes.

use axum::extract::{Request, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Serialize;
use utoipa::ToSchema;

use super::SharedState;
use crate::service::problem::ApiError;

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
    /// With PostgreSQL (`/readyz`): `ok`, or why the database does not answer, naming it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub database: Option<String>,
    /// With an object store (`/readyz`): `ok`, or why it does not answer, naming the bucket
    /// and the endpoint (a missing bucket, refused credentials).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub object_store: Option<String>,
}

/// A probe's outcome as `/readyz` reports it: `ok` or why not.
fn probed(outcome: &Option<std::result::Result<(), String>>) -> Option<String> {
    outcome.as_ref().map(|result| match result {
        Ok(()) => "ok".to_string(),
        Err(why) => why.clone(),
    })
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
        database: None,
        object_store: None,
    })
}

/// Readiness: the store is writable (and the database and the object store answer, when
/// configured) and the server is not shutting down. The answer reports the database and the
/// object store each (`ok` or why not) when they are configured.
#[utoipa::path(get, path = "/readyz", tag = "operations",
    responses((status = 200, description = "Ready", body = Health),
              (status = 503, description = "Shutting down, store not writable, or the database or the object store not answering (each named in its field)", body = Health)))]
pub async fn readyz(State(state): State<SharedState>) -> Response {
    let counts = state.jobs.counts();
    let worker_state = state.clone();
    let (writable, database, objects) = tokio::task::spawn_blocking(move || {
        (
            worker_state.store.is_writable(),
            worker_state.jobs.probe_database(),
            worker_state
                .store
                .blobs()
                .map(|b| b.probe().map_err(|why| format!("{}: {why}", b.shown()))),
        )
    })
    .await
    .unwrap_or((false, None, None));
    let status = if state.jobs.shutting_down() {
        "shutting down".to_string()
    } else if !writable {
        "store not writable".to_string()
    } else if let Some(Err(why)) = &database {
        // Names the server and what it said (unreachable, credentials refused …).
        format!("database unavailable: {why}")
    } else if let Some(Err(why)) = &objects {
        // Names the bucket and endpoint, and a missing bucket or refused credentials.
        format!("object store unavailable: {why}")
    } else {
        "ready".to_string()
    };
    let code = if status == "ready" {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    let body = Health {
        status,
        workers: Some(state.config.workers),
        queued: Some(counts.queued),
        running: Some(counts.running),
        database: probed(&database),
        object_store: probed(&objects),
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

//! Assembling and running the server: routes, the middleware every request passes through
//! (request id, tracing span, metrics, problem bodies, bearer authentication, body read
//! timeout), listening (through [`super::connections`]), and a graceful shutdown that stops taking work, drains requests and gives running jobs
//! `shutdown_grace_s` before putting them back in the queue.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::{header, HeaderName, HeaderValue, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, put};
use axum::{Json, Router};
use subtle::ConstantTimeEq;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::TraceLayer;

use super::backend::{Jobs, PgJobs};
use super::body_timeout::limit_body_pauses;
use super::callbacks::spawn_deliveries;
use super::config::ServiceConfig;
use super::connections::{serve_connections, ConnectionLimits};
use super::ingest_cache::IngestCache;
use super::jobs::{JobManager, Workers};
use super::metrics::ServiceMetrics;
use super::openapi::openapi_document;
use super::pacs_jobs::PacsAccess;
use super::postgres::Postgres;
use super::problem::{ApiError, PROBLEM_JSON};
use super::records::Records;
use super::retention::spawn_retention;
use super::routes::{self, AppState, SharedState};
use super::store::Store;
use crate::error::{IoContext, IoOp};
use crate::{Error, Result};

const REQUEST_ID: HeaderName = HeaderName::from_static("x-request-id");

/// Longest request id kept from a client.
pub const MAX_REQUEST_ID_CHARS: usize = 64;

/// Whether a client's request id may be kept, logged and echoed: 1–64 characters of
/// `[A-Za-z0-9._-]`, so it can carry no markup, control or non-ASCII byte into a log or a page.
pub fn is_safe_request_id(id: &[u8]) -> bool {
    (1..=MAX_REQUEST_ID_CHARS).contains(&id.len())
        && id
            .iter()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

/// Drops a client's request id that is not safe (or given more than once); the request then
/// gets a fresh UUID, as one that came without.
async fn sanitize_request_id(mut request: Request) -> Request {
    let given = request.headers().get_all(&REQUEST_ID);
    let mut values = given.iter();
    let keep = match (values.next(), values.next()) {
        (None, _) => return request,
        (Some(v), None) => is_safe_request_id(v.as_bytes()),
        (Some(_), Some(_)) => false,
    };
    if !keep {
        tracing::debug!("unsafe x-request-id from the client replaced");
        request.headers_mut().remove(&REQUEST_ID);
    }
    request
}

/// Builds the router over `state`.
pub fn router(state: SharedState) -> Router {
    let request_limit = state.config.max_request_bytes as usize;
    let v1 = Router::new()
        .route(
            "/v1/scans",
            // Uploads are limited while streaming, by max_upload_bytes.
            post(routes::upload_scan)
                .layer(DefaultBodyLimit::disable())
                .get(routes::list_scans),
        )
        .route(
            "/v1/scans/{id}",
            get(routes::get_scan).delete(routes::delete_scan),
        )
        .route("/v1/scans/{id}/targets", get(routes::list_targets))
        .route(
            "/v1/scans/{id}/targets/{name}",
            // Uploads are limited while streaming, by max_upload_bytes.
            put(routes::put_target)
                .layer(DefaultBodyLimit::disable())
                .get(routes::get_target)
                .delete(routes::delete_target),
        )
        .route(
            "/v1/scans/{id}/simulations",
            post(routes::create_simulation).layer(DefaultBodyLimit::max(request_limit)),
        )
        .route(
            "/v1/simulations",
            post(routes::create_pacs_simulation).layer(DefaultBodyLimit::max(request_limit)),
        )
        .route("/v1/jobs", get(routes::list_jobs))
        .route(
            "/v1/jobs/{id}",
            get(routes::get_job).delete(routes::delete_job),
        )
        .route("/v1/jobs/{id}/summary", get(routes::job_summary))
        .route("/v1/jobs/{id}/frames", get(routes::job_frames))
        .route(
            "/v1/jobs/{id}/frames/{k}/displacement",
            get(routes::frame_displacement),
        )
        .route("/v1/jobs/{id}/trajectories", get(routes::job_trajectories))
        .route("/v1/jobs/{id}/files", get(routes::job_files))
        .route("/v1/jobs/{id}/files/{*path}", get(routes::job_file))
        .route("/v1/jobs/{id}/archives/{*path}", get(routes::job_archive))
        .route_layer(middleware::from_fn_with_state(state.clone(), authenticate));
    Router::new()
        .merge(v1)
        .route("/healthz", get(routes::healthz))
        .route("/readyz", get(routes::readyz))
        // Counts and route templates only, no ids or patient data: open like the probes.
        .route("/metrics", get(routes::metrics))
        .route("/openapi.json", get(|| async { Json(openapi_document()) }))
        .fallback(routes::not_found)
        .with_state(state.clone())
        .layer(middleware::from_fn_with_state(
            Duration::from_secs_f64(state.config.body_read_timeout_s),
            limit_body_pauses,
        ))
        .layer(middleware::from_fn_with_state(state, observe))
        .layer(PropagateRequestIdLayer::new(REQUEST_ID))
        .layer(
            TraceLayer::new_for_http().make_span_with(|request: &Request| {
                let id = request
                    .headers()
                    .get(&REQUEST_ID)
                    .and_then(|v| v.to_str().ok())
                    .unwrap_or("-");
                // Paths hold only random ids, never patient data, so they may be logged; a
                // target's name is the client's, so it is not.
                tracing::info_span!(
                    "request",
                    request_id = %id,
                    method = %request.method(),
                    path = %loggable_path(request.uri().path()),
                )
            }),
        )
        .layer(SetRequestIdLayer::new(REQUEST_ID, MakeRequestUuid))
        .layer(middleware::map_request(sanitize_request_id))
}

/// A request path as it may be logged: a target's name (chosen by the client, so possibly a
/// patient's initials) replaced by `{name}`.
fn loggable_path(path: &str) -> std::borrow::Cow<'_, str> {
    match path.split_once("/targets/") {
        Some((scan, _)) => format!("{scan}/targets/{{name}}").into(),
        None => path.into(),
    }
}

/// Requires the bearer token when one is configured.
async fn authenticate(State(state): State<SharedState>, request: Request, next: Next) -> Response {
    let Some(expected) = state.config.api_token.as_deref() else {
        return next.run(request).await;
    };
    let given = request
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| {
            v.strip_prefix("Bearer ")
                .or_else(|| v.strip_prefix("bearer "))
        })
        .map(str::trim);
    match given {
        Some(token) if bool::from(token.as_bytes().ct_eq(expected.as_bytes())) => {
            next.run(request).await
        }
        Some(_) => ApiError::new(
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "the bearer token is not valid for this server",
        )
        .into_response(),
        None => ApiError::new(
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "this server needs an `Authorization: Bearer <token>` header",
        )
        .into_response(),
    }
}

/// Records metrics and turns every error answer into a complete problem document (with the
/// request's path and id), including the framework's own (405, 413 from the body limit …).
async fn observe(State(state): State<SharedState>, request: Request, next: Next) -> Response {
    let started = Instant::now();
    let method = request.method().to_string();
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_string())
        .unwrap_or_else(|| "unmatched".to_string());
    let path = request.uri().path().to_string();
    let request_id = request
        .headers()
        .get(&REQUEST_ID)
        .and_then(|v| v.to_str().ok())
        .map(str::to_string);
    let response = next.run(request).await;
    let status = response.status();
    let response = if status.is_client_error() || status.is_server_error() {
        complete_problem(response, path, request_id).await
    } else {
        response
    };
    state.metrics.observe_request(
        &method,
        &route,
        status.as_u16(),
        started.elapsed().as_secs_f64(),
    );
    response
}

async fn complete_problem(
    response: Response,
    instance: String,
    request_id: Option<String>,
) -> Response {
    let (mut parts, body) = response.into_parts();
    let error = match parts.extensions.remove::<ApiError>() {
        Some(e) => e,
        None => {
            let is_problem = parts
                .headers
                .get(header::CONTENT_TYPE)
                .is_some_and(|v| v.as_bytes().starts_with(PROBLEM_JSON.as_bytes()));
            if is_problem {
                return Response::from_parts(parts, body);
            }
            // The framework's own answer (a rejection); its text becomes the detail.
            let text = axum::body::to_bytes(body, 64 << 10)
                .await
                .map(|b| String::from_utf8_lossy(&b).into_owned())
                .unwrap_or_default();
            let slug = match parts.status {
                StatusCode::PAYLOAD_TOO_LARGE => "body-too-large",
                StatusCode::METHOD_NOT_ALLOWED => "method-not-allowed",
                StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported-media-type",
                _ => "bad-request",
            };
            let detail = if text.trim().is_empty() {
                parts
                    .status
                    .canonical_reason()
                    .unwrap_or("error")
                    .to_string()
            } else {
                text.trim().to_string()
            };
            ApiError::new(parts.status, slug, detail)
        }
    };
    let body =
        serde_json::to_vec(&error.to_problem(Some(instance), request_id)).unwrap_or_default();
    parts
        .headers
        .insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
    parts.headers.remove(header::CONTENT_LENGTH);
    Response::from_parts(parts, axum::body::Body::from(body))
}

/// A server running on its own threads (for benchmarks and embedding).
pub struct ServerHandle {
    /// The address it listens on.
    pub addr: SocketAddr,
    /// `http://<addr>`.
    pub base_url: String,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<Result<()>>>,
}

impl ServerHandle {
    /// Shuts the server down gracefully and waits for it.
    pub fn shutdown(mut self) -> Result<()> {
        self.stop_and_join()
    }

    fn stop_and_join(&mut self) -> Result<()> {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        match self.thread.take() {
            Some(t) => t
                .join()
                .map_err(|_| Error::InvalidModel("the server thread panicked".into()))?,
            None => Ok(()),
        }
    }
}

impl Drop for ServerHandle {
    fn drop(&mut self) {
        let _ = self.stop_and_join();
    }
}

/// The background work of a server besides its workers, started with the HTTP runtime.
struct Background {
    /// The embedded worker threads; none in an API process on PostgreSQL.
    workers: Option<Workers>,
    finished: tokio::sync::mpsc::UnboundedReceiver<crate::service::ids::JobId>,
}

/// Opens the store, recovers its jobs, starts the workers and the HTTP state.
fn prepare(config: ServiceConfig) -> Result<(SharedState, Background)> {
    config.validate()?;
    // Other API and worker processes use a store shared through PostgreSQL at the same time.
    let store = match config.postgres {
        None => Store::open(&config.data_dir)?,
        Some(_) => Store::open_shared(&config.data_dir)?,
    };
    let store = store.with_blobs(open_blobs(&config)?);
    let records: Arc<dyn Records> = Arc::new(store.clone());
    let ingests = Arc::new(IngestCache::new(config.ingest_cache_mib));
    let metrics = ServiceMetrics::default();
    metrics.register_ingest_cache(&ingests);
    let (finished_tx, finished) = tokio::sync::mpsc::unbounded_channel();
    let pacs = PacsAccess::of_service(&config);
    let (jobs, workers, records) = match &config.postgres {
        None => {
            let (manager, workers) = JobManager::start(
                (store.clone(), records.clone()),
                config.workers,
                config.queue_capacity,
                config.max_attempts,
                ingests,
                finished_tx,
                pacs,
            )?;
            (Jobs::Embedded(manager), Some(workers), records)
        }
        Some(settings) => {
            // API only: the jobs run in `lungmotion worker` processes.
            drop((ingests, finished_tx, pacs));
            let pg = Postgres::connect(settings, store.clone())?;
            tracing::info!(server = %pg.server(), "job and scan records in PostgreSQL; lungmotion worker processes run the jobs");
            let records: Arc<dyn Records> = Arc::new(pg.clone());
            let jobs = Jobs::Postgres(PgJobs {
                pg,
                queue_capacity: config.queue_capacity,
                pacs: config.pacs.clone(),
                shutting_down: Arc::default(),
            });
            (jobs, None, records)
        }
    };
    let state = Arc::new(AppState {
        ingest_slots: tokio::sync::Semaphore::new(config.workers),
        metrics,
        store,
        records,
        jobs,
        config,
    });
    Ok((state, Background { workers, finished }))
}

/// The object store of uploads and outputs when `[store] object_store_url` names one, checked
/// to answer (the bucket exists, the credentials are accepted); the error names it.
pub(crate) fn open_blobs(config: &ServiceConfig) -> Result<Option<super::blobs::BlobStore>> {
    let Some(settings) = &config.object_store else {
        return Ok(None);
    };
    let blobs = super::blobs::BlobStore::open(settings)?;
    tracing::info!(
        store = blobs.shown(),
        presigned_get = blobs.presigns(),
        "uploads and outputs in the object store"
    );
    Ok(Some(blobs))
}

/// Serves on `listener` until `stop` resolves, then shuts down gracefully.
async fn serve_on(
    listener: tokio::net::TcpListener,
    state: SharedState,
    background: Background,
    stop: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<()> {
    let Background { workers, finished } = background;
    spawn_retention(state.clone());
    spawn_deliveries(state.clone(), finished);
    let jobs = state.jobs.clone();
    let grace = Duration::from_secs_f64(state.config.shutdown_grace_s);
    let limits = ConnectionLimits {
        max_connections: state.config.max_connections,
        header_read_timeout: Duration::from_secs_f64(state.config.header_read_timeout_s),
    };
    let app = router(state);
    let (begin_tx, begin_rx) = tokio::sync::oneshot::channel::<()>();
    let jobs_for_signal = jobs.clone();
    let shutdown_signal = async move {
        stop.await;
        tracing::info!("shutting down: no new work; draining requests");
        // New submissions get 503 from here on, while requests in flight finish.
        jobs_for_signal.begin_shutdown();
        let _ = begin_tx.send(());
    };
    serve_connections(listener, app, limits, shutdown_signal).await;
    let _ = begin_rx.await;
    tokio::task::spawn_blocking(move || jobs.shutdown(workers, grace))
        .await
        .map_err(|e| Error::InvalidModel(format!("shutdown: {e}")))?;
    tracing::info!("stopped");
    Ok(())
}

/// Starts a server on its own runtime thread; returns once it listens.
pub fn start(config: ServiceConfig) -> Result<ServerHandle> {
    let (state, background) = prepare(config)?;
    let runtime = http_runtime()?;
    let listener = runtime
        .block_on(tokio::net::TcpListener::bind(state.config.listen))
        .map_err(|e| bind_error(state.config.listen, e))?;
    let addr = listener.local_addr().map_err(|cause| Error::Listen {
        addr: state.config.listen,
        cause,
    })?;
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let thread = std::thread::Builder::new()
        .name("lungmotion-server".into())
        .spawn(move || {
            runtime.block_on(serve_on(listener, state, background, async move {
                let _ = stop_rx.await;
            }))
        })
        .at(IoOp::Spawn, "the thread lungmotion-server")?;
    Ok(ServerHandle {
        addr,
        base_url: format!("http://{addr}"),
        stop: Some(stop_tx),
        thread: Some(thread),
    })
}

/// The runtime of the HTTP side (the simulations run on the job workers' own threads).
fn http_runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("lungmotion-http")
        .build()
        .at(IoOp::Spawn, "the threads lungmotion-http")
}

fn bind_error(addr: SocketAddr, e: std::io::Error) -> Error {
    Error::Listen { addr, cause: e }
}

/// Runs the server in the foreground until SIGTERM or Ctrl-C (the CLI's `serve`); prints the
/// address it listens on to stdout once it does.
pub fn serve_blocking(config: ServiceConfig) -> Result<()> {
    let runtime = http_runtime()?;
    runtime.block_on(async move {
        let listener = tokio::net::TcpListener::bind(config.listen)
            .await
            .map_err(|e| bind_error(config.listen, e))?;
        let addr = listener.local_addr().map_err(|cause| Error::Listen {
            addr: config.listen,
            cause,
        })?;
        let (state, background) = tokio::task::block_in_place(|| prepare(config))?;
        tracing::info!(
            %addr,
            data_dir = %state.config.data_dir.display(),
            workers = state.config.workers,
            queue_capacity = state.config.queue_capacity,
            authentication = state.config.api_token.is_some(),
            "listening"
        );
        {
            use std::io::Write;
            let mut out = std::io::stdout().lock();
            let _ = writeln!(out, "lungmotion serve: listening on http://{addr}");
            let _ = out.flush();
        }
        serve_on(listener, state, background, termination()).await
    })
}

/// Resolves on SIGTERM or Ctrl-C.
pub(super) async fn termination() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}

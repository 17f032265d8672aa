//! The body read timeout: a request body that pauses longer than `body_read_timeout_s`
//! between two pieces (a client that declared more bytes than it sends, or stopped sending)
//! is cut off and the request answered `408 Request Timeout`, whatever the handler made of
//! the broken body. A pause, not a total: a 2 GiB upload over a slow link may take long.

use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::{Request, State};
use axum::http::StatusCode;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use http_body::{Body as HttpBody, Frame, SizeHint};
use tower_http::timeout::{TimeoutBody, TimeoutError};

use super::problem::ApiError;

/// The request body with the pause limit, noting in `timed_out` when it struck.
struct WatchedBody {
    inner: Pin<Box<TimeoutBody<Body>>>,
    timed_out: Arc<AtomicBool>,
}

impl HttpBody for WatchedBody {
    type Data = Bytes;
    type Error = axum::BoxError;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
        let polled = self.inner.as_mut().poll_frame(cx);
        if let Poll::Ready(Some(Err(e))) = &polled {
            if e.is::<TimeoutError>() {
                self.timed_out.store(true, Ordering::SeqCst);
            }
        }
        polled
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// Middleware: applies the pause limit to the body and answers 408 when it struck.
pub async fn limit_body_pauses(
    State(pause): State<Duration>,
    request: Request,
    next: Next,
) -> Response {
    let timed_out = Arc::new(AtomicBool::new(false));
    let request = request.map(|body| {
        Body::new(WatchedBody {
            inner: Box::pin(TimeoutBody::new(pause, body)),
            timed_out: timed_out.clone(),
        })
    });
    let response = next.run(request).await;
    if !timed_out.load(Ordering::SeqCst) {
        return response;
    }
    tracing::info!(
        seconds = pause.as_secs_f64(),
        "request body paused too long; cut off"
    );
    let mut answer = ApiError::new(
        StatusCode::REQUEST_TIMEOUT,
        "body-timeout",
        format!(
            "the request body stopped arriving: nothing for {} s (body_read_timeout_s) before \
             the length it announced was reached",
            pause.as_secs_f64()
        ),
    )
    .into_response();
    // The rest of the body will never be read, so the connection cannot carry another request.
    answer.headers_mut().insert(
        axum::http::header::CONNECTION,
        axum::http::HeaderValue::from_static("close"),
    );
    answer
}

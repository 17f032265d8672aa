//! Completion callbacks: when a job whose request named a `callback_url` ends (done, failed
//! or cancelled), a signed JSON POST to that URL on the HTTP runtime (never on a simulation
//! worker), retried with exponential backoff, its outcome kept in the job's record.
//!
//! The signature is HMAC-SHA256, keyed by the server's callback secret, over the bytes
//! `<timestamp>.<body>`, sent as `X-Lungmotion-Signature: sha256=<hex>` beside
//! `X-Lungmotion-Timestamp: <Unix seconds>`; a receiver recomputes it over the raw body and
//! refuses old timestamps, so a captured call cannot be replayed later. Delivery is at least
//! once: a receiver that answered after the timeout sees the call again.

use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use hmac::{Hmac, KeyInit, Mac};
use serde::{Deserialize, Serialize};
use sha2::Sha256;
use utoipa::ToSchema;

use super::backend::Jobs;
use super::config::CallbackSettings;
use super::ids::JobId;
use super::routes::{JobLinks, JobStatus, SharedState};
use super::store::{now_rfc3339, JobRecord, JobState};

/// The header carrying the body's signature, `sha256=<64 hex digits>`.
pub const SIGNATURE_HEADER: &str = "x-lungmotion-signature";
/// The header carrying the signing time, Unix seconds, part of the signed bytes.
pub const TIMESTAMP_HEADER: &str = "x-lungmotion-timestamp";
/// Longest callback URL accepted, characters.
pub const MAX_CALLBACK_URL_CHARS: usize = 2048;
/// The `event` of every callback body.
pub const JOB_FINISHED_EVENT: &str = "job.finished";
/// Longest wait between two POSTs of one callback.
const MAX_RETRY_WAIT: Duration = Duration::from_secs(300);
/// Callbacks being delivered at once; more wait their turn.
const MAX_CONCURRENT_DELIVERIES: usize = 32;
/// Longest error kept in a job's record.
const MAX_ERROR_CHARS: usize = 300;

/// Where a job's completion callback is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum CallbackState {
    /// The job has not ended yet.
    Waiting,
    /// The job ended; the POST is being made or retried.
    Pending,
    /// A POST was answered with a 2xx status.
    Delivered,
    /// Every attempt failed, or the receiver refused it (a 4xx other than 408 and 429).
    Failed,
}

/// A job's completion callback as its record shows it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct CallbackDelivery {
    /// Where it is.
    pub state: CallbackState,
    /// POSTs made so far.
    pub attempts: u32,
    /// The HTTP status of the latest answer, none when there was no answer.
    pub last_status: Option<u16>,
    /// Why the latest POST did not deliver it (no answer, a status, a refusal).
    pub last_error: Option<String>,
    /// When the latest POST was made (RFC 3339, UTC).
    pub last_attempt_at: Option<String>,
}

impl CallbackDelivery {
    /// A callback waiting for its job to end.
    pub fn waiting() -> Self {
        CallbackDelivery {
            state: CallbackState::Waiting,
            attempts: 0,
            last_status: None,
            last_error: None,
            last_attempt_at: None,
        }
    }
}

/// The JSON body POSTed to a job's `callback_url`.
#[derive(Debug, Serialize, ToSchema)]
pub struct CallbackBody {
    /// Always `job.finished`.
    pub event: String,
    /// The job.
    #[schema(value_type = String)]
    pub job_id: JobId,
    /// Its scan.
    pub scan_id: String,
    /// `done`, `failed` or `cancelled`.
    pub state: JobState,
    /// Why it failed or was cancelled; none when done.
    pub error: Option<String>,
    /// When it ended (RFC 3339, UTC).
    pub finished_at: Option<String>,
    /// The job's resources, relative to the server's address.
    pub links: JobLinks,
}

impl From<JobRecord> for CallbackBody {
    fn from(record: JobRecord) -> Self {
        let status = JobStatus::from(record);
        let record = status.record;
        CallbackBody {
            event: JOB_FINISHED_EVENT.into(),
            job_id: record.job_id,
            scan_id: record.scan_id.to_string(),
            state: record.state,
            error: record.error,
            finished_at: record.finished_at,
            links: status.links,
        }
    }
}

/// Checks a request's `callback_url` against the server's settings; the message names what
/// is wrong.
pub fn check_callback_url(
    text: &str,
    settings: &CallbackSettings,
) -> std::result::Result<reqwest::Url, String> {
    if settings.secret.is_none() {
        return Err(
            "callback_url: this server has no callback secret to sign callbacks with \
             (callback_secret_file, LUNGMOTION_CALLBACK_SECRET or _FILE), so it accepts none"
                .into(),
        );
    }
    let chars = text.chars().count();
    if chars > MAX_CALLBACK_URL_CHARS {
        return Err(format!(
            "callback_url: {chars} characters, more than the {MAX_CALLBACK_URL_CHARS} accepted"
        ));
    }
    let url = reqwest::Url::parse(text.trim())
        .map_err(|e| format!("callback_url {text:?} is not an absolute URL: {e}"))?;
    let host = url
        .host_str()
        .ok_or_else(|| format!("callback_url {text:?} names no host"))?;
    if !url.username().is_empty() || url.password().is_some() {
        return Err(format!(
            "callback_url: credentials in the URL (user@{host}) are refused; the signature \
             header authenticates the call"
        ));
    }
    match url.scheme() {
        "https" => Ok(url),
        "http" if settings.allow_plain_http || is_loopback_host(&url) => Ok(url),
        "http" => Err(format!(
            "callback_url: plain http to {host} (beyond loopback) is refused; use https, or \
             set callback_allow_plain_http on the server"
        )),
        other => Err(format!(
            "callback_url: scheme {other:?} is not http or https"
        )),
    }
}

/// Whether the URL's host is this machine: `localhost` or a loopback address.
fn is_loopback_host(url: &reqwest::Url) -> bool {
    let Some(host) = url.host_str() else {
        return false;
    };
    let bare = host.trim_start_matches('[').trim_end_matches(']');
    host.eq_ignore_ascii_case("localhost")
        || bare
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// The signature header's value for `body` signed at `timestamp_s`: `sha256=<hex>` of
/// HMAC-SHA256(`secret`, `"<timestamp_s>.<body>"`).
pub fn sign(secret: &[u8], timestamp_s: u64, body: &[u8]) -> String {
    // HMAC takes keys of any length, so this cannot fail.
    let mut mac = <Hmac<Sha256> as KeyInit>::new_from_slice(secret)
        .unwrap_or_else(|_| unreachable!("HMAC accepts every key length"));
    mac.update(timestamp_s.to_string().as_bytes());
    mac.update(b".");
    mac.update(body);
    let digest = mac.finalize().into_bytes();
    let mut hex = String::with_capacity(7 + 2 * digest.len());
    hex.push_str("sha256=");
    for byte in digest {
        hex.push_str(&format!("{byte:02x}"));
    }
    hex
}

/// The wait after the `attempt`-th failed POST: `base` doubled per attempt, at most 5 min.
pub fn retry_wait(base_s: f64, attempt: u32) -> Duration {
    let factor = 2f64.powi(attempt.saturating_sub(1).min(30) as i32);
    Duration::from_secs_f64(base_s * factor).min(MAX_RETRY_WAIT)
}

/// How often an API process on PostgreSQL looks for a callback that is due.
const DUE_POLL_INTERVAL: Duration = Duration::from_millis(250);

/// The HTTP client that POSTs callbacks: no redirects, `callback_timeout_s`.
fn callback_client(settings: &CallbackSettings) -> Option<reqwest::Client> {
    let client = reqwest::Client::builder()
        // A redirect would re-send the signed body somewhere the request did not name.
        .redirect(reqwest::redirect::Policy::none())
        .timeout(Duration::from_secs_f64(settings.timeout_s))
        .user_agent(concat!("lungmotion/", env!("CARGO_PKG_VERSION")))
        .build();
    match client {
        Ok(c) => Some(c),
        Err(e) => {
            tracing::error!("completion callbacks disabled: cannot build the HTTP client: {e}");
            None
        }
    }
}

/// Delivers the callback of every job id received, each on its own task, at most
/// [`MAX_CONCURRENT_DELIVERIES`] at once; ends when the job manager is dropped. With the
/// jobs in PostgreSQL the ids come from the database instead (see [`spawn_due_deliveries`]).
pub fn spawn_deliveries(
    state: SharedState,
    mut finished: tokio::sync::mpsc::UnboundedReceiver<JobId>,
) {
    if state.jobs.is_postgres() {
        spawn_due_deliveries(state);
        return;
    }
    let Some(client) = callback_client(&state.config.callbacks) else {
        return;
    };
    tokio::spawn(async move {
        let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CONCURRENT_DELIVERIES));
        while let Some(id) = finished.recv().await {
            let Ok(slot) = slots.clone().acquire_owned().await else {
                return;
            };
            let (state, client) = (state.clone(), client.clone());
            tokio::spawn(async move {
                while let Some(wait) = deliver_once(&state, &client, id).await {
                    tokio::time::sleep(wait).await;
                }
                drop(slot);
            });
        }
    });
}

/// With the jobs in PostgreSQL: takes the callbacks that are due from the database (a job
/// that ended on any worker, a retry whose wait is over, one whose API process died while
/// POSTing it) and makes one POST of each, recording when the next is due; every API process
/// does so, and a claim keeps two from POSTing one callback at once. Without a callback
/// secret nothing can be signed, so nothing is taken (another API process may have one).
fn spawn_due_deliveries(state: SharedState) {
    let Jobs::Postgres(pg) = &state.jobs else {
        return;
    };
    if state.config.callbacks.secret.is_none() {
        return;
    }
    let Some(client) = callback_client(&state.config.callbacks) else {
        return;
    };
    let pg = pg.pg.clone();
    // Longer than one POST may take, so a claim outlives the POST it is held for.
    let hold = Duration::from_secs_f64(state.config.callbacks.timeout_s) + Duration::from_secs(30);
    tokio::spawn(async move {
        let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CONCURRENT_DELIVERIES));
        loop {
            if state.jobs.shutting_down() {
                return;
            }
            let Ok(slot) = slots.clone().acquire_owned().await else {
                return;
            };
            let claimer = pg.clone();
            let claimed = tokio::task::spawn_blocking(move || claimer.claim_callback(hold)).await;
            let id = match claimed {
                Ok(Ok(Some(id))) => id,
                Ok(Ok(None)) => {
                    drop(slot);
                    tokio::time::sleep(DUE_POLL_INTERVAL).await;
                    continue;
                }
                Ok(Err(e)) => {
                    tracing::warn!("looking for due completion callbacks: {e}");
                    drop(slot);
                    tokio::time::sleep(DUE_POLL_INTERVAL * 4).await;
                    continue;
                }
                Err(e) => {
                    tracing::error!("completion callback claim task failed: {e}");
                    return;
                }
            };
            let (state, client) = (state.clone(), client.clone());
            tokio::spawn(async move {
                // The next POST, if any, is due in the job's row; whoever claims it makes it.
                let _ = deliver_once(&state, &client, id).await;
                drop(slot);
            });
        }
    });
}

/// What one POST came to.
struct Attempt {
    status: Option<u16>,
    error: Option<String>,
    /// Whether another POST could succeed (no answer, a 5xx, 408 or 429).
    retry: bool,
}

/// Makes one POST of a job's callback and records it; the wait before the next POST when
/// one is due (`None`: delivered, refused, given up, or the job deleted).
async fn deliver_once(
    state: &SharedState,
    client: &reqwest::Client,
    id: JobId,
) -> Option<Duration> {
    let settings = &state.config.callbacks;
    let jobs = state.jobs.clone();
    let record = tokio::task::spawn_blocking(move || jobs.status(id))
        .await
        .ok()?
        .ok()??;
    let delivery = record.callback.clone()?;
    if delivery.state != CallbackState::Pending {
        // Delivered or given up meanwhile (by another process): nothing is due any more.
        update(state, id, |_| {}, None).await;
        return None;
    }
    let Some(secret) = settings.secret.clone() else {
        finish(state, id, "this server has no callback secret any more").await;
        return None;
    };
    if delivery.attempts >= settings.max_attempts {
        finish(
            state,
            id,
            &format!(
                "{} POSTs made, callback_max_attempts is {}",
                delivery.attempts, settings.max_attempts
            ),
        )
        .await;
        return None;
    }
    let records = state.records.clone();
    let url = tokio::task::spawn_blocking(move || records.job_request(id))
        .await
        .ok()
        .and_then(|r| r.ok())
        .and_then(|request| request.callback_url);
    let Some(url) = url else {
        finish(state, id, "the job's request.json holds no callback_url").await;
        return None;
    };
    let body = match serde_json::to_vec(&CallbackBody::from(record)) {
        Ok(b) => b,
        Err(e) => {
            finish(state, id, &format!("cannot serialise the body: {e}")).await;
            return None;
        }
    };
    let attempts = delivery.attempts + 1;
    let outcome = post_once(client, &url, secret.as_bytes(), &body).await;
    let delivered = outcome.error.is_none();
    let give_up = !delivered && (!outcome.retry || attempts >= settings.max_attempts);
    let next = match (delivered, give_up) {
        (true, _) => CallbackState::Delivered,
        (false, true) => CallbackState::Failed,
        (false, false) => CallbackState::Pending,
    };
    tracing::info!(job = %id, attempt = attempts, status = ?outcome.status,
        error = outcome.error.as_deref().unwrap_or(""), state = ?next, "completion callback");
    state.metrics.observe_callback_attempt(delivered);
    let wait =
        (next == CallbackState::Pending).then(|| retry_wait(settings.retry_base_s, attempts));
    let still_there = update(
        state,
        id,
        move |c| {
            c.state = next;
            c.attempts = attempts;
            c.last_status = outcome.status;
            c.last_error = outcome.error;
            c.last_attempt_at = Some(now_rfc3339());
        },
        wait,
    )
    .await;
    if still_there {
        wait
    } else {
        None
    }
}

/// One signed POST of `body` to `url`.
async fn post_once(client: &reqwest::Client, url: &str, secret: &[u8], body: &[u8]) -> Attempt {
    let timestamp_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    let sent = client
        .post(url)
        .header(reqwest::header::CONTENT_TYPE, "application/json")
        .header(TIMESTAMP_HEADER, timestamp_s.to_string())
        .header(SIGNATURE_HEADER, sign(secret, timestamp_s, body))
        .body(body.to_vec())
        .send()
        .await;
    match sent {
        Ok(answer) => {
            let status = answer.status();
            let code = status.as_u16();
            if status.is_success() {
                return Attempt {
                    status: Some(code),
                    error: None,
                    retry: false,
                };
            }
            let retry = status.is_server_error() || code == 408 || code == 429;
            let why = if status.is_redirection() {
                " (redirects are not followed)"
            } else {
                ""
            };
            Attempt {
                status: Some(code),
                error: Some(format!("the receiver answered {status}{why}")),
                retry,
            }
        }
        Err(e) => Attempt {
            status: None,
            error: Some(describe_send_error(e)),
            retry: true,
        },
    }
}

/// A failed send in plain words with its causes, without the URL (its query may hold the
/// receiver's token).
fn describe_send_error(e: reqwest::Error) -> String {
    let what = if e.is_timeout() {
        "no answer within callback_timeout_s"
    } else if e.is_connect() {
        "cannot connect"
    } else {
        "the POST failed"
    };
    let e = e.without_url();
    let mut text = format!("{what}: {e}");
    let mut cause = std::error::Error::source(&e);
    while let Some(c) = cause {
        text.push_str(&format!(": {c}"));
        cause = c.source();
    }
    if text.chars().count() > MAX_ERROR_CHARS {
        text = text.chars().take(MAX_ERROR_CHARS).collect::<String>() + "…";
    }
    text
}

/// Applies `change` to the job's callback record (on disk or in its row too), with when the
/// next POST is due (`retry_in`); `false` when the job is gone.
async fn update(
    state: &SharedState,
    id: JobId,
    change: impl FnOnce(&mut CallbackDelivery) + Send + 'static,
    retry_in: Option<Duration>,
) -> bool {
    let jobs = state.jobs.clone();
    match tokio::task::spawn_blocking(move || jobs.record_callback(id, change, retry_in)).await {
        Ok(Ok(still_there)) => still_there,
        Ok(Err(e)) => {
            tracing::error!(job = %id, "cannot record the callback's delivery: {e}");
            true
        }
        Err(e) => {
            tracing::error!(job = %id, "callback record task failed: {e}");
            true
        }
    }
}

/// Marks the job's callback failed without a POST, for `reason`.
async fn finish(state: &SharedState, id: JobId, reason: &str) {
    tracing::warn!(job = %id, "completion callback not sent: {reason}");
    let reason = reason.to_string();
    update(
        state,
        id,
        move |c| {
            c.state = CallbackState::Failed;
            c.last_error = Some(reason);
        },
        None,
    )
    .await;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_secret() -> CallbackSettings {
        CallbackSettings {
            secret: Some("a-shared-secret-of-32-characters".into()),
            ..CallbackSettings::default()
        }
    }

    #[test]
    fn the_signature_is_hmac_sha256_of_timestamp_dot_body() {
        // Reference from Python's standard library, not this crate's dependencies:
        // hmac.new(b"a-shared-secret-of-32-characters", b'1700000000.{"event":"job.finished"}',
        //          hashlib.sha256).hexdigest()
        let expected = "sha256=8add045ca04fc9a9c3534152bd34372d4e6e47e9de9e4b4d89e4ede72433add8";
        let got = sign(
            b"a-shared-secret-of-32-characters",
            1_700_000_000,
            br#"{"event":"job.finished"}"#,
        );
        assert_eq!(got, expected);
        // The timestamp is signed: the same body at another time has another signature.
        assert_ne!(
            sign(
                b"a-shared-secret-of-32-characters",
                1_700_000_001,
                br#"{"event":"job.finished"}"#
            ),
            expected
        );
    }

    #[test]
    fn callback_urls_are_checked_by_scheme_host_length_and_secret() {
        let settings = with_secret();
        for ok in [
            "https://planning.example.org/hooks/lungmotion?token=abc",
            "http://127.0.0.1:9000/done",
            "http://localhost/done",
            "http://[::1]:8080/done",
        ] {
            assert!(check_callback_url(ok, &settings).is_ok(), "{ok}");
        }
        for (bad, named) in [
            ("ftp://host/x", "\"ftp\""),
            ("file:///etc/passwd", "file"),
            ("http://planning.example.org/x", "callback_allow_plain_http"),
            ("https://user:pw@host.example/x", "credentials"),
            ("not a url", "not an absolute URL"),
        ] {
            let e = check_callback_url(bad, &settings).unwrap_err();
            assert!(e.contains(named), "{bad}: {e}");
        }
        let long = format!(
            "https://host.example/{}",
            "a".repeat(MAX_CALLBACK_URL_CHARS)
        );
        let e = check_callback_url(&long, &settings).unwrap_err();
        assert!(e.contains("2048"), "{e}");
        let plain = CallbackSettings {
            allow_plain_http: true,
            ..with_secret()
        };
        assert!(check_callback_url("http://planning.example.org/x", &plain).is_ok());
        let e =
            check_callback_url("https://host.example/x", &CallbackSettings::default()).unwrap_err();
        assert!(e.contains("callback secret"), "{e}");
    }

    #[test]
    fn retries_wait_longer_each_time_up_to_five_minutes() {
        assert_eq!(retry_wait(2.0, 1), Duration::from_secs(2));
        assert_eq!(retry_wait(2.0, 2), Duration::from_secs(4));
        assert_eq!(retry_wait(2.0, 4), Duration::from_secs(16));
        assert_eq!(retry_wait(2.0, 20), MAX_RETRY_WAIT);
    }
}

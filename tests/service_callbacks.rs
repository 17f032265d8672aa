//! Completion callbacks over real sockets: a receiver on loopback (axum, in the test) gets a
//! signed POST when a job ends, verifies its HMAC-SHA256 with the shared secret, sees three
//! attempts when it answers 500 twice then 200 and one when it answers 410; the job's record
//! shows the delivery; bad callback URLs, and any callback on a server without a secret, are
//! refused with 422 naming why.
//!
//! Both backends: with `LUNGMOTION_TEST_BACKEND=postgres` the jobs run in a worker process and
//! the API process delivers the callbacks it finds due in the database (`.ci/run` runs this
//! file so, with the blobs in S3).
#![cfg(feature = "cli")]

mod service_support;

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use hmac::{Hmac, KeyInit, Mac};
use serde_json::{json, Value};
use service_support::*;
use sha2::Sha256;

/// The secret the server signs with and the receiver checks with.
const SECRET: &str = "test-callback-secret-0123456789";
/// Longest wait for a job or a delivery (the machine is shared).
const TIMEOUT: Duration = Duration::from_secs(600);

/// One POST the receiver got.
#[derive(Debug, Clone)]
struct Call {
    headers: HeaderMap,
    body: Bytes,
    at: Instant,
}

/// Per hook: the statuses still to answer (then 200), and the calls received.
type Hooks = Arc<Mutex<HashMap<String, (VecDeque<u16>, Vec<Call>)>>>;

/// An HTTP receiver on a loopback port, answering each hook's scripted statuses.
struct Receiver {
    hooks: Hooks,
    base_url: String,
    _runtime: tokio::runtime::Runtime,
}

async fn receive(
    State(hooks): State<Hooks>,
    Path(hook): Path<String>,
    headers: HeaderMap,
    body: Bytes,
) -> StatusCode {
    let mut hooks = hooks.lock().unwrap();
    let (script, calls) = hooks.entry(hook).or_default();
    calls.push(Call {
        headers,
        body,
        at: Instant::now(),
    });
    StatusCode::from_u16(script.pop_front().unwrap_or(200)).unwrap()
}

impl Receiver {
    fn start() -> Receiver {
        let runtime = tokio::runtime::Runtime::new().unwrap();
        let hooks: Hooks = Arc::default();
        let listener = runtime
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .unwrap();
        let base_url = format!("http://{}", listener.local_addr().unwrap());
        let app = axum::Router::new()
            .route("/{hook}", axum::routing::post(receive))
            .with_state(hooks.clone());
        runtime.spawn(async move { axum::serve(listener, app).await });
        Receiver {
            hooks,
            base_url,
            _runtime: runtime,
        }
    }

    /// The URL of `hook`, which answers `statuses` first, then 200.
    fn hook(&self, hook: &str, statuses: &[u16]) -> String {
        self.hooks.lock().unwrap().insert(
            hook.to_string(),
            (statuses.iter().copied().collect(), Vec::new()),
        );
        format!("{}/{hook}", self.base_url)
    }

    fn calls(&self, hook: &str) -> Vec<Call> {
        self.hooks
            .lock()
            .unwrap()
            .get(hook)
            .map(|(_, calls)| calls.clone())
            .unwrap_or_default()
    }
}

/// Whether `call` carries a valid signature of its body by `secret`, with a fresh timestamp.
fn signed_by(call: &Call, secret: &str) -> bool {
    let header = |name: &str| {
        call.headers
            .get(name)
            .unwrap()
            .to_str()
            .unwrap()
            .to_string()
    };
    let timestamp = header("x-lungmotion-timestamp");
    let sent_s: u64 = timestamp.parse().unwrap();
    let now_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_secs();
    assert!(
        now_s.abs_diff(sent_s) < 300,
        "timestamp {sent_s}, now {now_s}"
    );
    let signature = header("x-lungmotion-signature");
    let hex = signature.strip_prefix("sha256=").expect("sha256= prefix");
    assert_eq!(hex.len(), 64, "{signature}");
    let digest: Vec<u8> = (0..32)
        .map(|i| u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).unwrap())
        .collect();
    let mut mac = Hmac::<Sha256>::new_from_slice(secret.as_bytes()).unwrap();
    mac.update(timestamp.as_bytes());
    mac.update(b".");
    mac.update(&call.body);
    mac.verify_slice(&digest).is_ok()
}

/// Polls the job until its callback is no longer `waiting` or `pending`; the job's status.
fn wait_for_callback(server: &ServerProcess, job: &str) -> Value {
    let deadline = Instant::now() + TIMEOUT;
    loop {
        let status = server.get_json(&format!("/v1/jobs/{job}"));
        let state = status["callback"]["state"].as_str().unwrap_or("?");
        if state == "delivered" || state == "failed" {
            return status;
        }
        assert!(
            Instant::now() < deadline,
            "callback still {state}: {status}\n{}",
            tail(&server.log(), 30)
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn delete(server: &ServerProcess, job: &str) -> u16 {
    server.delete(&format!("/v1/jobs/{job}")).status().as_u16()
}

/// `request` with a `callback_url`.
fn with_callback(mut request: Value, url: &str) -> Value {
    request["callback_url"] = json!(url);
    request
}

#[test]
fn a_finished_job_calls_back_signed_and_retries_until_answered() {
    let receiver = Receiver::start();
    let scratch = Scratch::new("callbacks");
    let server = ServerProcess::start_with_env(
        &scratch.join("data"),
        &["--workers", "1"],
        &[
            ("LUNGMOTION_CALLBACK_SECRET", SECRET),
            ("LUNGMOTION_CALLBACK_RETRY_BASE_S", "0.2"),
        ],
    );
    let scan = server.upload_scan(&sample("phantom-ct.nii.gz"));

    // A long job holds the only worker, so the next two wait in the queue and are cancelled.
    let long = server.submit(&scan, &simulation_request(4, &[], 4.0, 20));
    let flaky = receiver.hook("flaky", &[500, 500]);
    let retried = server.submit(&scan, &with_callback(tiny_request(2), &flaky));
    let queued = server.get_json(&format!("/v1/jobs/{retried}"));
    assert_eq!(queued["callback"]["state"], "waiting", "{queued}");
    let gone = receiver.hook("gone", &[410]);
    let refused = server.submit(&scan, &with_callback(tiny_request(2), &gone));
    assert_eq!(delete(&server, &retried), 202);
    assert_eq!(delete(&server, &refused), 202);

    let status = wait_for_callback(&server, &retried);
    let calls = receiver.calls("flaky");
    assert_eq!(calls.len(), 3, "{status}");
    assert_eq!(status["callback"]["state"], "delivered", "{status}");
    assert_eq!(status["callback"]["attempts"], 3);
    assert_eq!(status["callback"]["last_status"], 200);
    for call in &calls {
        assert!(signed_by(call, SECRET));
    }
    // Each retry waits longer than the one before (0.2 s, then 0.4 s).
    let gaps: Vec<f64> = calls
        .windows(2)
        .map(|w| (w[1].at - w[0].at).as_secs_f64())
        .collect();
    assert!(gaps[0] >= 0.2 && gaps[1] >= 0.4, "{gaps:?}");
    let body: Value = serde_json::from_slice(&calls[2].body).unwrap();
    assert_eq!(body["event"], "job.finished");
    assert_eq!(body["job_id"], retried.as_str());
    assert_eq!(body["state"], "cancelled");
    assert!(
        body["error"].as_str().unwrap().contains("cancelled"),
        "{body}"
    );

    // A 4xx other than 408 and 429 is an answer: no retry.
    let status = wait_for_callback(&server, &refused);
    assert_eq!(receiver.calls("gone").len(), 1);
    assert_eq!(status["callback"]["state"], "failed", "{status}");
    assert_eq!(status["callback"]["last_status"], 410);
    assert!(
        status["callback"]["last_error"]
            .as_str()
            .unwrap()
            .contains("410"),
        "{status}"
    );
    assert_eq!(delete(&server, &long), 202);

    // A job that runs to the end: one POST, signed with the shared secret and no other.
    let hook = receiver.hook("done", &[]);
    let job = server.submit(&scan, &with_callback(tiny_request(2), &hook));
    server.wait_for_state(&job, &["done"], TIMEOUT);
    let status = wait_for_callback(&server, &job);
    let calls = receiver.calls("done");
    assert_eq!(calls.len(), 1, "{status}");
    assert_eq!(status["callback"]["state"], "delivered");
    assert_eq!(status["callback"]["attempts"], 1);
    let call = &calls[0];
    assert!(signed_by(call, SECRET));
    assert!(!signed_by(call, "another-secret-of-enough-length"));
    assert_eq!(call.headers["content-type"], "application/json");
    let body: Value = serde_json::from_slice(&call.body).unwrap();
    assert_eq!(body["state"], "done", "{body}");
    assert_eq!(body["error"], Value::Null);
    assert_eq!(body["links"]["self"], format!("/v1/jobs/{job}"));
    assert_eq!(body["links"]["files"], format!("/v1/jobs/{job}/files"));
    // What the links name is there.
    server.get_json(body["links"]["summary"].as_str().unwrap());

    // Refused before queueing, each naming why.
    for (url, named) in [
        ("ftp://127.0.0.1/x", "scheme"),
        (
            "http://planning.example.org/done",
            "callback_allow_plain_http",
        ),
        (
            "https://user:secret@planning.example.org/done",
            "credentials",
        ),
    ] {
        let resp = server.post_simulation(&scan, &with_callback(tiny_request(2), url));
        assert_problem(resp, 422, &["callback_url", named]);
    }
    let long_url = format!("https://planning.example.org/{}", "a".repeat(2100));
    let resp = server.post_simulation(&scan, &with_callback(tiny_request(2), &long_url));
    assert_problem(resp, 422, &["2048"]);
}

#[test]
fn a_server_without_a_callback_secret_refuses_callbacks() {
    let scratch = Scratch::new("callbacks-unsigned");
    let server = ServerProcess::start(&scratch.join("data"), &[]);
    let scan = server.upload_scan(&sample("phantom-ct.nii.gz"));
    let resp = server.post_simulation(
        &scan,
        &with_callback(tiny_request(2), "http://127.0.0.1:9/done"),
    );
    assert_problem(
        resp,
        422,
        &["callback secret", "LUNGMOTION_CALLBACK_SECRET"],
    );
    // Without one, the job goes ahead with no callback at all.
    let job = server.submit(&scan, &tiny_request(2));
    assert_eq!(
        server.get_json(&format!("/v1/jobs/{job}"))["callback"],
        Value::Null
    );
}

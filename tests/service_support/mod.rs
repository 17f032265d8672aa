//! Helpers of the service tests: a `lungmotion serve` child process on a free loopback port,
//! a blocking HTTP client, the bundled inputs (phantom CT, DICOM series zipped on the fly,
//! a small two-breath trace, tracked points inside the lungs) and the problem+json check.
//!
//! Every server gets its own data directory; its stderr goes to `server.log` beside that
//! directory so a failing test can print what the server said.
//!
//! With `LUNGMOTION_TEST_BACKEND=postgres`, each server gets a PostgreSQL server of its own
//! and a `lungmotion worker` process beside it (see [`postgres`]), so that a journey test runs
//! against that backend unchanged (`.ci/run` does it for the tests where it applies).
//!
//! With `LUNGMOTION_TEST_OBJECT_STORE=s3`, each server also gets an S3 server of its own
//! (moto's, see [`s3`]) and keeps its uploads and outputs there (`[store] object_store_url`).
//! A server started again on the same data directory (after a kill or a stop) gets the same
//! S3 server, as a restarted process of a deployment finds its bucket: it lives until the
//! test's [`Scratch`] is dropped. [`job_outputs`] and [`objects_under`] read a job's outputs
//! and a store's objects wherever they are.

#![allow(dead_code)]

pub mod postgres;
pub mod s3;

use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use reqwest::blocking::{Client, Response};
use serde_json::{json, Value};

/// What the server prints on stdout once it accepts connections.
const LISTENING_PREFIX: &str = "lungmotion serve: listening on ";
/// Longest wait for the listening line (a cold start on a busy 2-core machine).
const START_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest wait for a stopped server to exit.
const EXIT_TIMEOUT: Duration = Duration::from_secs(90);

/// A file or directory of the bundled `sample-volumes/`.
pub fn sample(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("sample-volumes")
        .join(name)
}

/// A scratch directory for one test, emptied first and removed when the test passes (kept
/// for a look when it fails).
pub struct Scratch {
    /// Its path.
    pub path: PathBuf,
}

impl Scratch {
    /// `lm-svc-<name>-<pid>` in the temp directory, created empty.
    pub fn new(name: &str) -> Scratch {
        let path = std::env::temp_dir().join(format!("lm-svc-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).unwrap();
        Scratch { path }
    }

    /// `path/name`.
    pub fn join(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        // The S3 servers of its data directories stop (once no server holds them).
        lock_s3_servers().retain(|(dir, _)| !dir.starts_with(&self.path));
        // And its PostgreSQL servers.
        lock_pg_servers().retain(|(dir, _)| !dir.starts_with(&self.path));
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.path);
        }
    }
}

/// A `lungmotion serve` child process.
pub struct ServerProcess {
    child: Child,
    base_url: String,
    data_dir: PathBuf,
    log_path: PathBuf,
    client: Client,
    /// With `LUNGMOTION_TEST_BACKEND=postgres`: the worker that runs the jobs, then the
    /// database (dropped in this order, after the server).
    worker: Option<postgres::WorkerProcess>,
    database: Option<Arc<postgres::PgServer>>,
    /// With `LUNGMOTION_TEST_OBJECT_STORE=s3`: the S3 server of its blobs (shared with the
    /// servers started again on its data directory).
    objects: Option<Arc<s3::S3Server>>,
}

/// The S3 servers of `LUNGMOTION_TEST_OBJECT_STORE=s3` by the data directory they serve,
/// until the [`Scratch`] holding that directory is dropped.
static S3_SERVERS: Mutex<Vec<(PathBuf, Arc<s3::S3Server>)>> = Mutex::new(Vec::new());

fn lock_s3_servers() -> std::sync::MutexGuard<'static, Vec<(PathBuf, Arc<s3::S3Server>)>> {
    S3_SERVERS.lock().unwrap_or_else(|p| p.into_inner())
}

/// The S3 server (with the tests' bucket) of the servers on `data_dir`: the one a server on
/// it started earlier in this test, else a new one.
fn s3_server_of(data_dir: &Path) -> Arc<s3::S3Server> {
    let mut servers = lock_s3_servers();
    if let Some((_, server)) = servers.iter().find(|(dir, _)| dir == data_dir) {
        return server.clone();
    }
    let name = data_dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let s3 = s3::S3Server::start(&data_dir.parent().unwrap().join(format!("moto-{name}")));
    s3.create_bucket(TEST_BUCKET);
    let s3 = Arc::new(s3);
    servers.push((data_dir.to_path_buf(), s3.clone()));
    s3
}

/// The PostgreSQL servers of `LUNGMOTION_TEST_BACKEND=postgres` by the data directory they
/// serve, until the [`Scratch`] holding that directory is dropped: a server started again on
/// its data directory (a restart) finds its records, as a restarted process of a deployment
/// finds its database.
static PG_SERVERS: Mutex<Vec<(PathBuf, Arc<postgres::PgServer>)>> = Mutex::new(Vec::new());

fn lock_pg_servers() -> std::sync::MutexGuard<'static, Vec<(PathBuf, Arc<postgres::PgServer>)>> {
    PG_SERVERS.lock().unwrap_or_else(|p| p.into_inner())
}

/// The PostgreSQL server of the servers on `data_dir`: the one a server on it started earlier
/// in this test, else a new one beside it (`postgres-<data dir's name>`).
fn pg_server_of(data_dir: &Path) -> Arc<postgres::PgServer> {
    let mut servers = lock_pg_servers();
    if let Some((_, server)) = servers.iter().find(|(dir, _)| dir == data_dir) {
        return server.clone();
    }
    let name = data_dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let db = Arc::new(postgres::PgServer::start(
        &data_dir.parent().unwrap().join(format!("postgres-{name}")),
    ));
    servers.push((data_dir.to_path_buf(), db.clone()));
    db
}

/// Whether the tests' servers keep their blobs in an S3 server of their own
/// (`LUNGMOTION_TEST_OBJECT_STORE=s3`).
pub fn object_store_backend() -> bool {
    std::env::var("LUNGMOTION_TEST_OBJECT_STORE").is_ok_and(|b| b == "s3")
}

/// The bucket of the servers' blobs with `LUNGMOTION_TEST_OBJECT_STORE=s3`.
pub const TEST_BUCKET: &str = "lungmotion-test";

/// Whether the tests' servers keep their jobs in PostgreSQL (`LUNGMOTION_TEST_BACKEND`).
pub fn postgres_backend() -> bool {
    std::env::var("LUNGMOTION_TEST_BACKEND").is_ok_and(|b| b == "postgres")
}

/// The HTTP client of the tests: generous timeouts, since the machine is shared.
pub fn client() -> Client {
    Client::builder()
        .connect_timeout(Duration::from_secs(10))
        .timeout(Duration::from_secs(300))
        .build()
        .unwrap()
}

/// The server command with no service variable inherited from the test's environment.
pub fn serve_command(data_dir: &Path, extra_args: &[&str], env: &[(&str, &str)]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_lungmotion"));
    cmd.arg("serve")
        .arg("--data-dir")
        .arg(data_dir)
        .args(extra_args);
    for name in lungmotion::service::config::ENV_VARS {
        cmd.env_remove(name);
    }
    for (k, v) in env {
        cmd.env(k, v);
    }
    cmd
}

impl ServerProcess {
    /// Starts `lungmotion serve --listen 127.0.0.1:0 --data-dir <data_dir> <extra_args>` and
    /// waits for its listening line.
    pub fn start(data_dir: &Path, extra_args: &[&str]) -> ServerProcess {
        Self::start_with_env(data_dir, extra_args, &[])
    }

    /// As [`ServerProcess::start`] with extra environment variables.
    pub fn start_with_env(
        data_dir: &Path,
        extra_args: &[&str],
        env: &[(&str, &str)],
    ) -> ServerProcess {
        Self::start_inner(data_dir, extra_args, env, true)
    }

    /// As [`ServerProcess::start_with_env`] with no database, worker or S3 server of its own
    /// whatever `LUNGMOTION_TEST_BACKEND` and `LUNGMOTION_TEST_OBJECT_STORE` say: for a test
    /// whose processes share the ones it started (named in `env`).
    pub fn start_sharing(
        data_dir: &Path,
        extra_args: &[&str],
        env: &[(&str, &str)],
    ) -> ServerProcess {
        Self::start_inner(data_dir, extra_args, env, false)
    }

    fn start_inner(
        data_dir: &Path,
        extra_args: &[&str],
        env: &[(&str, &str)],
        own_backends: bool,
    ) -> ServerProcess {
        let log_path = data_dir
            .parent()
            .expect("the data dir has a parent")
            .join("server.log");
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .unwrap();
        let mut args = vec!["--listen", "127.0.0.1:0"];
        args.extend_from_slice(extra_args);
        let database = (own_backends && postgres_backend()).then(|| pg_server_of(data_dir));
        let url = database.as_ref().map(|d| d.url());
        let mut env: Vec<(&str, &str)> = env.to_vec();
        if let Some(url) = &url {
            env.push(("LUNGMOTION_POSTGRES_URL", url));
        }
        let objects = (own_backends && object_store_backend()).then(|| s3_server_of(data_dir));
        let objects_env = objects
            .as_ref()
            .map(|s3| s3.service_env(TEST_BUCKET, "lm"))
            .unwrap_or_default();
        // First, so that a test's own object store settings win.
        env.splice(
            0..0,
            objects_env.iter().map(|(k, v)| (k.as_str(), v.as_str())),
        );
        let env = &env[..];
        let mut child = serve_command(data_dir, &args, env)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::from(log))
            .spawn()
            .expect("spawn lungmotion serve");
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        // Keeps draining stdout after the listening line so the pipe never fills.
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    // The test stopped listening; keep reading so the server never blocks.
                }
            }
        });
        let deadline = Instant::now() + START_TIMEOUT;
        let base_url = loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left.max(Duration::from_millis(1))) {
                Ok(line) => {
                    if let Some(url) = line.strip_prefix(LISTENING_PREFIX) {
                        break url.trim().to_string();
                    }
                }
                Err(_) => {
                    let status = child.try_wait().ok().flatten();
                    let _ = child.kill();
                    let _ = child.wait();
                    panic!(
                        "the server did not print its listening line within {:?} (exit: \
                         {status:?}); its log:\n{}",
                        START_TIMEOUT,
                        std::fs::read_to_string(&log_path).unwrap_or_default()
                    );
                }
            }
            if Instant::now() > deadline {
                panic!("no listening line within {START_TIMEOUT:?}");
            }
        };
        assert!(
            base_url.starts_with("http://127.0.0.1:"),
            "listening line names {base_url}"
        );
        let worker = database.as_ref().map(|_| {
            // The server's settings, workers among them, and its data directory.
            let worker_log = log_path.with_file_name("worker.log");
            let shared: Vec<&str> = extra_args
                .windows(2)
                .filter(|w| w[0] == "--workers" || w[0] == "--config")
                .flatten()
                .copied()
                .collect();
            postgres::WorkerProcess::start(data_dir, &worker_log, &shared, env)
        });
        ServerProcess {
            child,
            base_url,
            data_dir: data_dir.to_path_buf(),
            log_path,
            client: client(),
            worker,
            database,
            objects,
        }
    }

    /// `http://127.0.0.1:PORT`.
    pub fn base_url(&self) -> &str {
        &self.base_url
    }

    /// The absolute URL of `path` (which starts with `/`).
    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base_url)
    }

    /// The data directory.
    pub fn data_dir(&self) -> &Path {
        &self.data_dir
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Everything the server (and earlier servers of this data dir's parent) wrote on stderr,
    /// and with PostgreSQL its worker.
    pub fn log(&self) -> String {
        let mut log = std::fs::read_to_string(&self.log_path).unwrap_or_default();
        if let Some(worker) = &self.worker {
            log.push_str("\n--- worker ---\n");
            log.push_str(&worker.log());
        }
        log
    }

    /// The S3 server of its blobs (`LUNGMOTION_TEST_OBJECT_STORE=s3`).
    pub fn objects(&self) -> Option<&s3::S3Server> {
        self.objects.as_deref()
    }

    /// The object store settings it was started with by `LUNGMOTION_TEST_OBJECT_STORE=s3`
    /// (none otherwise), for the other processes a test starts on its store: a worker given
    /// none would keep its outputs where this server never looks.
    pub fn object_store_env(&self) -> Vec<(String, String)> {
        self.objects
            .as_ref()
            .map(|s3| s3.service_env(TEST_BUCKET, "lm"))
            .unwrap_or_default()
    }

    /// The shared client.
    pub fn client(&self) -> &Client {
        &self.client
    }

    /// SIGKILL, then reap.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// SIGTERM, then waits (bounded) for the exit status.
    pub fn terminate(&mut self) -> ExitStatus {
        let status = Command::new("kill")
            .arg("-TERM")
            .arg(self.child.id().to_string())
            .status()
            .expect("run kill -TERM");
        assert!(status.success(), "kill -TERM failed: {status}");
        self.wait_exit()
    }

    /// Waits (bounded) for the process to exit by itself.
    pub fn wait_exit(&mut self) -> ExitStatus {
        let deadline = Instant::now() + EXIT_TIMEOUT;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            if Instant::now() > deadline {
                self.kill();
                panic!(
                    "the server did not exit within {EXIT_TIMEOUT:?}; its log:\n{}",
                    self.log()
                );
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// GET `path`.
    pub fn get(&self, path: &str) -> Response {
        self.client.get(self.url(path)).send().unwrap()
    }

    /// DELETE `path`.
    pub fn delete(&self, path: &str) -> Response {
        self.client.delete(self.url(path)).send().unwrap()
    }

    /// GET `path`, expecting 200 and JSON.
    pub fn get_json(&self, path: &str) -> Value {
        let resp = self.get(path);
        let status = resp.status();
        let text = resp.text().unwrap();
        assert_eq!(status, 200, "GET {path}: {text}");
        serde_json::from_str(&text).unwrap_or_else(|e| panic!("GET {path}: {e}: {text}"))
    }

    /// POSTs raw bytes to `/v1/scans` with `content_type`.
    pub fn post_scan_bytes(&self, bytes: Vec<u8>, content_type: &str) -> Response {
        self.client
            .post(self.url("/v1/scans"))
            .header("content-type", content_type)
            .body(bytes)
            .send()
            .unwrap()
    }

    /// Uploads the scan file at `path` as `application/octet-stream`, expecting 201; the
    /// scan's id.
    pub fn upload_scan(&self, path: &Path) -> String {
        let body = self.upload_scan_json(path);
        body["scan_id"].as_str().unwrap().to_string()
    }

    /// As [`ServerProcess::upload_scan`], giving the whole 201 body.
    pub fn upload_scan_json(&self, path: &Path) -> Value {
        let bytes = std::fs::read(path).unwrap();
        let resp = self.post_scan_bytes(bytes, "application/octet-stream");
        assert_created(
            resp,
            201,
            "scan_id",
            "/v1/scans",
            &format!("upload {}", path.display()),
        )
    }

    /// POSTs a JSON simulation request of `scan_id`.
    pub fn post_simulation(&self, scan_id: &str, request: &Value) -> Response {
        self.client
            .post(self.url(&format!("/v1/scans/{scan_id}/simulations")))
            .json(request)
            .send()
            .unwrap()
    }

    /// POSTs a body of any content type as a simulation request of `scan_id`.
    pub fn post_simulation_raw(
        &self,
        scan_id: &str,
        content_type: &str,
        body: impl Into<Vec<u8>>,
    ) -> Response {
        self.client
            .post(self.url(&format!("/v1/scans/{scan_id}/simulations")))
            .header("content-type", content_type)
            .body(body.into())
            .send()
            .unwrap()
    }

    /// Submits a JSON simulation, expecting 202 with a queued job; the job's id.
    pub fn submit(&self, scan_id: &str, request: &Value) -> String {
        accepted_job_id(self.post_simulation(scan_id, request))
    }

    /// Polls `GET /v1/jobs/{id}` until its state is one of `states`; the last status. Fails
    /// on timeout, or when the job ends in a state that is not wanted.
    pub fn wait_for_state(&self, job_id: &str, states: &[&str], timeout: Duration) -> Value {
        self.wait_for_state_observing(job_id, states, timeout, |_| {})
    }

    /// As [`ServerProcess::wait_for_state`], showing every status polled to `observe`.
    pub fn wait_for_state_observing(
        &self,
        job_id: &str,
        states: &[&str],
        timeout: Duration,
        mut observe: impl FnMut(&Value),
    ) -> Value {
        let deadline = Instant::now() + timeout;
        loop {
            let status = self.get_json(&format!("/v1/jobs/{job_id}"));
            observe(&status);
            let state = status["state"].as_str().unwrap_or("?").to_string();
            if states.contains(&state.as_str()) {
                return status;
            }
            let terminal = ["done", "failed", "cancelled"].contains(&state.as_str());
            if terminal || Instant::now() > deadline {
                panic!(
                    "job {job_id} is {state}, waited for {states:?} ({}): {status:#}\nserver log:\n{}",
                    if terminal { "it will not change" } else { "timed out" },
                    tail(&self.log(), 40)
                );
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        self.kill();
    }
}

/// The last `n` lines of `text`.
pub fn tail(text: &str, n: usize) -> String {
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

/// Whether `id` has the contract's form: 32 lowercase hex digits.
pub fn is_id(id: &str) -> bool {
    id.len() == 32
        && id
            .bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

/// Expects a 202 answer with `Location: /v1/jobs/{id}` and a queued job; its id.
pub fn accepted_job_id(resp: Response) -> String {
    let body = assert_created(resp, 202, "job_id", "/v1/jobs", "simulation refused");
    assert_eq!(body["state"], "queued", "{body}");
    body["job_id"].as_str().unwrap().to_string()
}

/// Expects `status` and a body naming a new resource by `id_key` (an id of 32 hex digits),
/// with `Location: <collection>/<id>`; the body. `what` prefixes the failure message.
fn assert_created(
    resp: Response,
    status: u16,
    id_key: &str,
    collection: &str,
    what: &str,
) -> Value {
    let got = resp.status();
    let location = resp
        .headers()
        .get("location")
        .map(|v| v.to_str().unwrap().to_string());
    let text = resp.text().unwrap();
    assert_eq!(got, status, "{what}: {text}");
    let body: Value = serde_json::from_str(&text).unwrap();
    let id = body[id_key].as_str().expect(id_key).to_string();
    assert!(is_id(&id), "{id_key} {id:?}");
    assert_eq!(
        location.as_deref(),
        Some(format!("{collection}/{id}").as_str())
    );
    body
}

/// Checks a problem+json answer: the status, the content type, the body's `status`, `type`
/// and `instance`, and that `detail` contains every one of `detail_words` (case-insensitive).
/// Gives the body.
pub fn assert_problem(resp: Response, status: u16, detail_words: &[&str]) -> Value {
    let got = resp.status().as_u16();
    let content_type = resp
        .headers()
        .get("content-type")
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    let has_request_id = resp.headers().contains_key("x-request-id");
    let text = resp.text().unwrap();
    assert_eq!(got, status, "expected {status}, got {got}: {text}");
    assert!(
        content_type.starts_with("application/problem+json"),
        "content type {content_type:?} for {text}"
    );
    assert!(has_request_id, "no x-request-id on the problem {text}");
    let body: Value = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{e}: {text}"));
    assert_eq!(body["status"], status, "{body}");
    let kind = body["type"].as_str().unwrap_or("");
    assert!(kind.starts_with("urn:lungmotion:problem:"), "type {kind:?}");
    assert!(
        body["title"].as_str().is_some_and(|t| !t.is_empty()),
        "{body}"
    );
    assert!(body["instance"].as_str().is_some(), "no instance: {body}");
    let detail = body["detail"].as_str().unwrap_or("").to_lowercase();
    for word in detail_words {
        assert!(
            detail.contains(&word.to_lowercase()),
            "detail {detail:?} does not mention {word:?}"
        );
    }
    body
}

/// Lung volume change from the scanned (end-exhale) state over `breaths` breaths of 4 s
/// sampled at 10 Hz: 250·(1 − cos 2πt/4) mL, so 500 mL tidal, end-inhale at t = 2, 6, …
pub fn breathing_trace(breaths: usize) -> (Vec<f64>, Vec<f64>) {
    let samples = breaths * 40;
    let time_s: Vec<f64> = (0..=samples).map(|i| i as f64 / 10.0).collect();
    let volume_ml = time_s
        .iter()
        .map(|t| 250.0 * (1.0 - (2.0 * std::f64::consts::PI * t / 4.0).cos()))
        .collect();
    (time_s, volume_ml)
}

/// The trace as the CLI's CSV (`time_s,volume_ml`), every digit kept so the server and the
/// CLI read the same numbers.
pub fn trace_csv(time_s: &[f64], volume_ml: &[f64]) -> String {
    let mut csv = String::from("time_s,volume_ml\n");
    for (t, v) in time_s.iter().zip(volume_ml) {
        csv.push_str(&format!("{t:?},{v:?}\n"));
    }
    csv
}

/// Two points inside the phantom's right lung: the tumour centre and the apex landmark moved
/// 15 mm down into the lung (as `lungmotion demo` does), from `sample-volumes/phantom.json`.
pub fn tracked_points() -> Vec<(String, [f64; 3])> {
    let text = std::fs::read_to_string(sample("phantom.json")).unwrap();
    let json: Value = serde_json::from_str(&text).unwrap();
    let landmark = |name: &str, dz_mm: f64| -> [f64; 3] {
        let p: [f64; 3] = serde_json::from_value(json["landmarks"][name].clone()).unwrap();
        [p[0], p[1], p[2] + dz_mm]
    };
    vec![
        ("tumour".into(), landmark("tumour_centre_lps_mm", 0.0)),
        ("apex".into(), landmark("right_lung_apex_lps_mm", -15.0)),
    ]
}

/// The points as the CLI's points CSV.
pub fn points_csv(points: &[(String, [f64; 3])]) -> String {
    let mut csv = String::from("name,x_mm,y_mm,z_mm\n");
    for (name, p) in points {
        csv.push_str(&format!("{name},{:?},{:?},{:?}\n", p[0], p[1], p[2]));
    }
    csv
}

/// A JSON simulation request: the trace, the points, the element size and `phases` output
/// instants (no quick looks, to keep the jobs short).
pub fn simulation_request(
    breaths: usize,
    points: &[(String, [f64; 3])],
    element_size_mm: f64,
    phases: usize,
) -> Value {
    let (time_s, volume_ml) = breathing_trace(breaths);
    let points: Vec<Value> = points
        .iter()
        .map(|(name, p)| json!({"name": name, "lps_mm": p}))
        .collect();
    json!({
        "trace": {"time_s": time_s, "volume_ml": volume_ml},
        "points": points,
        "element_size_mm": element_size_mm,
        "motion": {"instants": {"kind": "phases", "count": phases}},
        "outputs": {"quicklooks": false},
    })
}

/// A tiny job: 12 mm elements, 2 breaths, `phases` frames, no points.
pub fn tiny_request(phases: usize) -> Value {
    simulation_request(2, &[], 12.0, phases)
}

/// Zips the bundled DICOM series (68 files, deflated) into `dest`.
pub fn zip_dicom_series(dest: &Path) {
    let dir = sample("phantom-dicom");
    let mut names: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    names.sort();
    let mut zip = zip::ZipWriter::new(File::create(dest).unwrap());
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    for path in names {
        let name = format!(
            "series/{}",
            path.file_name().unwrap().to_string_lossy().into_owned()
        );
        zip.start_file(name, options).unwrap();
        zip.write_all(&std::fs::read(&path).unwrap()).unwrap();
    }
    zip.finish().unwrap();
}

/// Every `*.json` file under `dir`, recursively.
pub fn json_files(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries {
            let path = e.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|x| x == "json") {
                found.push(path);
            }
        }
    }
    found
}

/// Names of the entries of `dir` (empty when it does not exist), sorted.
pub fn entries(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

/// A done job's output directory as a directory to read: the server's `jobs/<id>/out`, or
/// with its blobs in S3 (where the data directory keeps no outputs) the objects under
/// `lm/jobs/<id>/out/` fetched straight from the bucket into `dest` (emptied first).
pub fn job_outputs(server: &ServerProcess, job: &str, dest: &Path) -> PathBuf {
    let Some(s3) = server.objects() else {
        return server.data_dir().join("jobs").join(job).join("out");
    };
    let _ = std::fs::remove_dir_all(dest);
    let prefix = format!("lm/jobs/{job}/out/");
    let keys = s3.keys(TEST_BUCKET, &prefix);
    assert!(!keys.is_empty(), "no outputs of job {job} in the bucket");
    for key in keys {
        let path = dest.join(&key[prefix.len()..]);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, s3.object(TEST_BUCKET, &key).0).unwrap();
    }
    dest.to_path_buf()
}

/// The keys of the server's objects under `relative` (`jobs/<id>/`, `scans/<id>/`, or `""`
/// for all) in its bucket; none when its blobs are not in S3.
pub fn objects_under(server: &ServerProcess, relative: &str) -> Vec<String> {
    server
        .objects()
        .map(|s3| s3.keys(TEST_BUCKET, &format!("lm/{relative}")))
        .unwrap_or_default()
}

/// The entries of the store's `tmp/` that are not the server's own writability probe.
pub fn stray_tmp_files(data_dir: &Path) -> Vec<String> {
    entries(&data_dir.join("tmp"))
        .into_iter()
        .filter(|n| n != "writable")
        .collect()
}

/// The largest component difference between two displacement fields on one grid, mm, and
/// the largest displacement of the second (the reference), mm.
pub fn field_difference_mm(field: &[[f32; 3]], reference: &[[f32; 3]]) -> (f32, f32) {
    assert_eq!(field.len(), reference.len(), "fields on different grids");
    let difference = field
        .iter()
        .flatten()
        .zip(reference.iter().flatten())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    let peak = reference
        .iter()
        .map(|v| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt())
        .fold(0.0f32, f32::max);
    (difference, peak)
}

/// Runs `lungmotion <args>` to its end, failing the test with its standard error if it fails.
pub fn run_cli(args: &[&dyn AsRef<std::ffi::OsStr>]) {
    let output = Command::new(env!("CARGO_BIN_EXE_lungmotion"))
        .args(args.iter().map(|a| a.as_ref()))
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "lungmotion {:?}: {}",
        args.first().map(|a| a.as_ref()),
        String::from_utf8_lossy(&output.stderr)
    );
}

/// Checks the `Range` answers of the file GET `path` against the file's bytes `whole`: one
/// range (`a-b`, `a-`, `-n`, clipped past the end) is `206` with its bytes and
/// `Content-Range`; a range past the end is `416` with `Content-Range: bytes */len`; several
/// ranges are the whole file (`200`); every answer says `Accept-Ranges: bytes`.
pub fn assert_ranges_served(server: &ServerProcess, path: &str, whole: &[u8]) {
    let len = whole.len();
    assert!(
        len > 300,
        "{path}: too small a file for the range checks ({len} bytes)"
    );
    let get = |range: &str| {
        let resp = server
            .client()
            .get(server.url(path))
            .header("range", range)
            .send()
            .unwrap();
        let status = resp.status().as_u16();
        let header = |name: &str| {
            resp.headers()
                .get(name)
                .map(|v| v.to_str().unwrap().to_string())
                .unwrap_or_default()
        };
        let (accept, content_range) = (header("accept-ranges"), header("content-range"));
        (
            status,
            accept,
            content_range,
            resp.bytes().unwrap().to_vec(),
        )
    };
    let cases = [
        ("bytes=100-299", 100, 300),
        ("bytes=0-0", 0, 1),
        (&format!("bytes={}-", len - 77) as &str, len - 77, len),
        ("bytes=-123", len - 123, len),
        (&format!("bytes=200-{}", len + 1000) as &str, 200, len),
    ]
    .map(|(r, a, b)| (r.to_string(), a, b));
    for (range, start, end) in &cases {
        let (status, accept, content_range, body) = get(range);
        assert_eq!(status, 206, "{path} {range}");
        assert_eq!(accept, "bytes", "{path} {range}");
        assert_eq!(
            content_range,
            format!("bytes {start}-{}/{len}", end - 1),
            "{path} {range}"
        );
        assert!(body == whole[*start..*end], "{path} {range}: other bytes");
    }
    let (status, _, content_range, _) = get(&format!("bytes={len}-"));
    assert_eq!(status, 416, "{path} past the end");
    assert_eq!(content_range, format!("bytes */{len}"), "{path}");
    let (status, accept, content_range, body) = get("bytes=0-9,20-29");
    assert_eq!(status, 200, "{path}: several ranges");
    assert_eq!((accept.as_str(), content_range.as_str()), ("bytes", ""));
    assert!(body == whole, "{path}: several ranges give the whole file");
}

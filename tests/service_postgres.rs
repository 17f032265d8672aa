//! The service on PostgreSQL (`[store] postgres_url`): API processes (`lungmotion serve`) and
//! worker processes (`lungmotion worker`) sharing one database and one data directory, each
//! test with a PostgreSQL server of its own (see `service_support::postgres`).
//!
//! * A journey: upload, a job run by a separate worker, its results, cancellation, deletion,
//!   the workers in `/metrics`.
//! * Bad input: a database that cannot be reached at start (named, retried with a doubling
//!   wait), refused credentials (named at start and in `/readyz` while serving), a database
//!   stopped while serving (named in `/readyz`, ready again once it is back), a schema
//!   written by a newer lungmotion (refused by name at start, and in `/readyz` by a server
//!   already serving).
//! * Slow: two API processes and three workers, 100 jobs, one worker killed with SIGKILL in
//!   the middle of a job and one API process in the middle of an upload: every job ends `done`
//!   exactly once (the killed worker's job after its lease ran out), its fields byte-identical
//!   to `lungmotion run`'s, and the database, the data directory and (with
//!   `LUNGMOTION_TEST_OBJECT_STORE=s3`, one moto server for every process) the object store
//!   hold nothing of the killed upload or of no job.
#![cfg(feature = "cli")]

mod service_support;

use std::collections::HashMap;
use std::time::{Duration, Instant};

use std::io::Write;

use serde_json::Value;
use service_support::postgres::{free_port, run_to_exit, PgServer, WorkerProcess, PG_PASSWORD};
use service_support::s3::S3Server;
use service_support::*;

/// Longest wait for jobs (each takes seconds alone; the machine is shared).
const JOB_TIMEOUT: Duration = Duration::from_secs(900);
/// Longest wait for `/readyz` to see a change of the database.
const READY_TIMEOUT: Duration = Duration::from_secs(60);

/// An API process on `database`, over `data_dir`.
fn api(data_dir: &std::path::Path, url: &str, extra: &[(&str, &str)]) -> ServerProcess {
    let mut env = vec![("LUNGMOTION_POSTGRES_URL", url)];
    env.extend_from_slice(extra);
    ServerProcess::start_with_env(data_dir, &[], &env)
}

/// Polls `/readyz` until `accept` takes its status and body.
fn wait_ready(server: &ServerProcess, accept: impl Fn(u16, &Value) -> bool) -> (u16, Value) {
    let deadline = Instant::now() + READY_TIMEOUT;
    loop {
        let resp = server.get("/readyz");
        let status = resp.status().as_u16();
        let body: Value = resp.json().unwrap();
        if accept(status, &body) {
            return (status, body);
        }
        assert!(
            Instant::now() < deadline,
            "/readyz never changed: {status} {body}; the server's log:\n{}",
            tail(&server.log(), 40)
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[test]
fn a_database_unreachable_at_start_is_named_and_tried_again() {
    let scratch = Scratch::new("pg-unreachable");
    // Nothing listens there.
    let port = free_port();
    let url = format!("postgres://lm:secret@127.0.0.1:{port}/lungmotion");
    let data = scratch.join("data");
    for command in ["serve", "worker"] {
        let mut args = vec![command, "--data-dir", data.to_str().unwrap()];
        if command == "serve" {
            args.extend(["--listen", "127.0.0.1:0"]);
        }
        let (code, stderr) = run_to_exit(
            &args,
            &[
                ("LUNGMOTION_POSTGRES_URL", &url),
                ("LUNGMOTION_POSTGRES_CONNECT_TIMEOUT_S", "2"),
            ],
        );
        assert_eq!(code, Some(1), "lungmotion {command}: {stderr}");
        let server = format!("lm@127.0.0.1:{port}/lungmotion");
        for words in [server.as_str(), "unreachable after", "connect_timeout_s"] {
            assert!(
                stderr.contains(words),
                "{command}: {words:?} missing: {stderr}"
            );
        }
        assert!(
            stderr.contains("database unreachable, trying again"),
            "{command}: no retry logged: {stderr}"
        );
        assert!(
            !stderr.contains("secret"),
            "the password was shown: {stderr}"
        );
    }
}

#[test]
#[cfg_attr(
    not(postgres_binaries),
    ignore = "needs PostgreSQL's server programs (apt-get install postgresql; .ci/run installs them)"
)]
fn refused_credentials_are_named_at_start_and_in_readyz() {
    let scratch = Scratch::new("pg-credentials");
    let db = PgServer::start(&scratch.join("postgres"));
    let data = scratch.join("data");
    let wrong = db.url_with_password("not-the-password");
    let server_name = format!("lm@127.0.0.1:{}/lungmotion", db.port);
    for command in ["serve", "worker"] {
        let mut args = vec![command, "--data-dir", data.to_str().unwrap()];
        if command == "serve" {
            args.extend(["--listen", "127.0.0.1:0"]);
        }
        let (code, stderr) = run_to_exit(&args, &[("LUNGMOTION_POSTGRES_URL", &wrong)]);
        assert_eq!(code, Some(1), "lungmotion {command}: {stderr}");
        for words in [
            server_name.as_str(),
            "refused this connection",
            "password authentication failed",
        ] {
            assert!(
                stderr.contains(words),
                "{command}: {words:?} missing: {stderr}"
            );
        }
        // Credentials do not get better by waiting.
        assert!(!stderr.contains("trying again"), "{stderr}");
        assert!(!stderr.contains("not-the-password"), "{stderr}");
    }

    // Serving, then the password changes under it: /readyz says so, naming the server.
    let server = api(&data, &db.url(), &[]);
    let (_, body) = wait_ready(&server, |s, _| s == 200);
    assert_eq!(body["status"], "ready");
    assert_eq!(body["database"], "ok", "{body}");
    // One session: after the ALTER, the test's own password no longer logs in either. The
    // service's pooled connections are ended, so it must log in again.
    db.psql(
        "postgres",
        "ALTER ROLE lm PASSWORD 'changed-meanwhile'; \
         SELECT pg_terminate_backend(pid) FROM pg_stat_activity \
         WHERE usename = 'lm' AND pid <> pg_backend_pid()",
    );
    // A 503 is a problem document, the readiness answer its detail.
    let (status, body) = wait_ready(&server, |s, b| {
        s == 503 && b.to_string().contains("password authentication failed")
    });
    assert_eq!(status, 503);
    let text = body.to_string();
    for words in [
        "database unavailable",
        server_name.as_str(),
        "password authentication failed",
    ] {
        assert!(text.contains(words), "{words:?} missing: {body}");
    }
    // The readiness body (the problem's detail) reports the database in its own field too.
    let readiness: Value = serde_json::from_str(body["detail"].as_str().unwrap_or("{}"))
        .unwrap_or_else(|e| panic!("{e}: {body}"));
    assert!(
        readiness["database"]
            .as_str()
            .is_some_and(|d| d.contains("password authentication failed")),
        "{readiness}"
    );
    // The password back: ready again, without a restart.
    let restore = format!("ALTER ROLE lm PASSWORD '{PG_PASSWORD}'");
    let changed = PgServerPassword(&db, "changed-meanwhile");
    changed.psql(&restore);
    let (_, body) = wait_ready(&server, |s, _| s == 200);
    assert_eq!(body["status"], "ready");

    // The database gone while serving (its server stopped): named in /readyz, field and all;
    // back, ready again without a restart.
    db.stop();
    let (status, body) = wait_ready(&server, |s, _| s == 503);
    assert_eq!(status, 503);
    let readiness: Value = serde_json::from_str(body["detail"].as_str().unwrap_or("{}"))
        .unwrap_or_else(|e| panic!("{e}: {body}"));
    let said = readiness["status"].as_str().unwrap_or_default();
    assert!(
        said.starts_with("database unavailable") && said.contains(server_name.as_str()),
        "{readiness}"
    );
    assert!(
        readiness["database"]
            .as_str()
            .is_some_and(|d| d.contains(server_name.as_str())),
        "{readiness}"
    );
    db.resume();
    let (_, body) = wait_ready(&server, |s, _| s == 200);
    assert_eq!(body["database"], "ok", "{body}");
}

/// `psql` with another password than the test server's own.
struct PgServerPassword<'a>(&'a PgServer, &'a str);

impl PgServerPassword<'_> {
    fn psql(&self, sql: &str) {
        let bin = service_support::postgres::pg_bin_dir().unwrap();
        let out = std::process::Command::new(bin.join("psql"))
            .args(["-X", "-q", "-v", "ON_ERROR_STOP=1", "-h", "127.0.0.1"])
            .args(["-p", &self.0.port.to_string(), "-U", "lm", "-d", "postgres"])
            .args(["-c", sql])
            .env("PGPASSWORD", self.1)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}

#[test]
#[cfg_attr(
    not(postgres_binaries),
    ignore = "needs PostgreSQL's server programs (apt-get install postgresql; .ci/run installs them)"
)]
fn the_schema_is_made_by_the_service_an_older_one_upgraded_and_a_newer_one_refused_by_name() {
    let scratch = Scratch::new("pg-schema");
    let db = PgServer::start(&scratch.join("postgres"));
    let data = scratch.join("data");
    let server = api(&data, &db.url(), &[]);
    wait_ready(&server, |s, _| s == 200);
    let version = db.psql(
        "lungmotion",
        "SELECT version, written_by FROM lungmotion_schema",
    );
    assert_eq!(
        version.trim(),
        format!(
            "{}|{}",
            lungmotion::service::postgres::SCHEMA_VERSION,
            env!("CARGO_PKG_VERSION")
        ),
        "{version}"
    );
    for table in ["lungmotion_jobs", "lungmotion_scans", "lungmotion_workers"] {
        let n = db.psql("lungmotion", &format!("SELECT count(*) FROM {table}"));
        assert_eq!(n.trim(), "0", "{table}");
    }
    // A database of version 1 (before completion callbacks were due in the database) is
    // upgraded in place by the next process that opens it.
    drop(server);
    db.psql(
        "lungmotion",
        "DROP INDEX lungmotion_jobs_callbacks; \
         ALTER TABLE lungmotion_jobs DROP COLUMN callback_due; \
         UPDATE lungmotion_schema SET version = 1, written_by = '0.1.0'",
    );
    let server = api(&data, &db.url(), &[]);
    wait_ready(&server, |s, _| s == 200);
    let version = db.psql("lungmotion", "SELECT version FROM lungmotion_schema");
    assert_eq!(
        version.trim(),
        lungmotion::service::postgres::SCHEMA_VERSION.to_string()
    );
    let upgraded = db.psql(
        "lungmotion",
        "SELECT count(*) FROM pg_indexes WHERE indexname = 'lungmotion_jobs_callbacks'",
    );
    assert_eq!(
        upgraded.trim(),
        "1",
        "the version 2 index after the upgrade"
    );
    db.psql(
        "lungmotion",
        "UPDATE lungmotion_schema SET version = 99, written_by = '9.9.9'",
    );
    // A server already serving when a newer lungmotion upgrades the schema: /readyz names it.
    let (_, body) = wait_ready(&server, |s, _| s == 503);
    let readiness: Value = serde_json::from_str(body["detail"].as_str().unwrap_or("{}"))
        .unwrap_or_else(|e| panic!("{e}: {body}"));
    for words in ["schema is version 99", "written by lungmotion 9.9.9"] {
        assert!(
            readiness["database"]
                .as_str()
                .is_some_and(|d| d.contains(words)),
            "{words:?} missing: {readiness}"
        );
    }
    drop(server);
    for command in ["serve", "worker"] {
        let mut args = vec![command, "--data-dir", data.to_str().unwrap()];
        if command == "serve" {
            args.extend(["--listen", "127.0.0.1:0"]);
        }
        let (code, stderr) = run_to_exit(&args, &[("LUNGMOTION_POSTGRES_URL", &db.url())]);
        // A refusal: the settings point at a database this version must not touch.
        assert_eq!(code, Some(2), "lungmotion {command}: {stderr}");
        for words in [
            "schema is version 99",
            "written by lungmotion 9.9.9",
            &format!(
                "knows versions up to {}",
                lungmotion::service::postgres::SCHEMA_VERSION
            ),
            &format!("lm@127.0.0.1:{}/lungmotion", db.port),
        ] {
            assert!(
                stderr.contains(words),
                "{command}: {words:?} missing: {stderr}"
            );
        }
    }
    // Untouched.
    let version = db.psql("lungmotion", "SELECT version FROM lungmotion_schema");
    assert_eq!(version.trim(), "99");
}

/// Jobs the workers finished `done`, by job id, from their JSON logs' `run ended` lines.
fn done_runs(logs: &[String]) -> HashMap<String, usize> {
    let mut done = HashMap::new();
    for log in logs {
        for line in log.lines() {
            let Ok(entry) = serde_json::from_str::<Value>(line) else {
                continue;
            };
            let fields = &entry["fields"];
            if fields["message"] == "run ended" && fields["state"] == "done" {
                *done
                    .entry(fields["job"].as_str().unwrap_or_default().to_string())
                    .or_default() += 1;
            }
        }
    }
    done
}

#[test]
#[cfg_attr(
    not(postgres_binaries),
    ignore = "needs PostgreSQL's server programs (apt-get install postgresql; .ci/run installs them)"
)]
fn a_journey_through_an_api_process_and_a_separate_worker() {
    let scratch = Scratch::new("pg-journey");
    let db = PgServer::start(&scratch.join("postgres"));
    let data = scratch.join("data");
    let url = db.url();
    let env = [
        ("LUNGMOTION_POSTGRES_URL", url.as_str()),
        ("LUNGMOTION_LOG_FORMAT", "json"),
    ];
    let server = api(&data, &url, &env[1..]);
    // With LUNGMOTION_TEST_OBJECT_STORE=s3 the API process has an S3 server of its own; the
    // worker must keep its outputs there too.
    let objects_env = server.object_store_env();
    let mut worker_env = env.to_vec();
    worker_env.extend(objects_env.iter().map(|(k, v)| (k.as_str(), v.as_str())));
    let mut worker = WorkerProcess::start(
        &data,
        &scratch.join("worker.log"),
        &["--workers", "1"],
        &worker_env,
    );
    let scan = server.upload_scan(&sample("phantom-ct.nii.gz"));
    assert_eq!(server.get(&format!("/v1/scans/{scan}")).status(), 200);
    let listed = server.get_json("/v1/scans");
    assert_eq!(listed["total"], 1, "{listed}");

    let job = server.submit(&scan, &tiny_request(2));
    let status = server.wait_for_state(&job, &["done", "failed"], JOB_TIMEOUT);
    assert_eq!(status["state"], "done", "{status}\n{}", worker.log());
    assert_eq!(status["attempts"], 1);
    let summary = server.get_json(&format!("/v1/jobs/{job}/summary"));
    assert_eq!(summary["frames"].as_array().unwrap().len(), 2, "{summary}");
    assert_eq!(
        server
            .get(&format!("/v1/jobs/{job}/frames/1/displacement"))
            .status(),
        200
    );
    let jobs = server.get_json("/v1/jobs?state=done");
    assert_eq!(jobs["total"], 1, "{jobs}");
    assert_eq!(done_runs(&[worker.log()])[&job], 1);

    // The worker in /metrics, as it reports itself through the database.
    let deadline = Instant::now() + READY_TIMEOUT;
    loop {
        let text = server.get("/metrics").text().unwrap();
        let series = format!(
            "lungmotion_worker_jobs_finished{{worker=\"{}\",state=\"done\"}} 1",
            worker.id
        );
        if text.contains(&series) {
            assert!(text.contains("lungmotion_jobs{state=\"done\"} 1"), "{text}");
            break;
        }
        assert!(Instant::now() < deadline, "{series} missing: {text}");
        std::thread::sleep(Duration::from_millis(200));
    }

    // This API process has no callback secret: a callback is refused as on the directory
    // store (deliveries on PostgreSQL: tests/service_callbacks.rs with
    // LUNGMOTION_TEST_BACKEND=postgres).
    let mut with_callback = tiny_request(2);
    with_callback["callback_url"] = "http://127.0.0.1:9/hook".into();
    assert_problem(
        server.post_simulation(&scan, &with_callback),
        422,
        &["callback secret"],
    );

    // Cancelling a running job reaches the worker's run; the job ends cancelled, its partial
    // outputs gone.
    // 4 mm, 20 phases: about 5 s alone (at 8 mm the whole job took 0.8 s by 2026-12-05 and
    // could finish before the cancel reached it).
    let long = server.submit(&scan, &simulation_request(4, &tracked_points(), 4.0, 20));
    server.wait_for_state(&long, &["running"], JOB_TIMEOUT);
    let resp = server.delete(&format!("/v1/jobs/{long}"));
    assert_eq!(resp.status(), 202);
    let status = server.wait_for_state(&long, &["cancelled", "done", "failed"], JOB_TIMEOUT);
    assert_eq!(status["state"], "cancelled", "{status}");
    let left: Vec<String> = entries(&data.join("jobs").join(&long))
        .into_iter()
        .filter(|n| n.contains("partial") || n == "out")
        .collect();
    assert!(left.is_empty(), "{left:?}");

    // A queued job is cancelled at once (no worker takes it: the worker is gone).
    worker.kill();
    let queued = server.submit(&scan, &tiny_request(2));
    let resp = server.delete(&format!("/v1/jobs/{queued}"));
    assert_eq!(resp.status(), 202);
    assert_eq!(
        server.get_json(&format!("/v1/jobs/{queued}"))["state"],
        "cancelled"
    );

    // The scan is in use while a job on it is queued; deletions as with the directory store.
    let waiting = server.submit(&scan, &tiny_request(2));
    assert_eq!(server.delete(&format!("/v1/scans/{scan}")).status(), 409);
    assert_eq!(server.delete(&format!("/v1/jobs/{waiting}")).status(), 202);
    for id in [&job, &long, &queued, &waiting] {
        assert_eq!(
            server.delete(&format!("/v1/jobs/{id}")).status(),
            204,
            "{id}"
        );
        assert_eq!(server.get(&format!("/v1/jobs/{id}")).status(), 404);
        assert!(!data.join("jobs").join(id).exists());
    }
    assert_eq!(server.delete(&format!("/v1/scans/{scan}")).status(), 204);
    assert_eq!(server.get(&format!("/v1/scans/{scan}")).status(), 404);
    assert!(!data.join("scans").join(&scan).exists());
    let n = db.psql("lungmotion", "SELECT count(*) FROM lungmotion_jobs");
    assert_eq!(n.trim(), "0");
}

/// Starts `POST /v1/scans` of `announced` bytes on `base_url` over a raw connection and sends
/// them slowly (1 MiB every 50 ms) on a thread until the server goes away or all are sent; the
/// thread gives the bytes it sent.
fn slow_upload(base_url: &str, announced: usize) -> std::thread::JoinHandle<usize> {
    let addr = base_url.trim_start_matches("http://").to_string();
    std::thread::spawn(move || {
        let mut stream = std::net::TcpStream::connect(&addr).unwrap();
        let head = format!(
            "POST /v1/scans HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/octet-stream\r\n\
             Content-Length: {announced}\r\n\r\n"
        );
        stream.write_all(head.as_bytes()).unwrap();
        // What the bytes are does not matter: the upload never ends.
        let chunk = vec![0x5a_u8; 1 << 20];
        let mut sent = 0;
        while sent + chunk.len() <= announced {
            if stream.write_all(&chunk).is_err() {
                break;
            }
            sent += chunk.len();
            std::thread::sleep(Duration::from_millis(50));
        }
        sent
    })
}

/// GET `path` as JSON (200), tried again on a transport error: a kept-alive connection the
/// server closed after its idle timeout can be taken by the client at that very moment.
fn get_json_again(server: &ServerProcess, path: &str) -> Value {
    for _ in 0..3 {
        match server.client().get(server.url(path)).send() {
            Ok(resp) => {
                let status = resp.status();
                let text = resp.text().unwrap();
                assert_eq!(status, 200, "GET {path}: {text}");
                return serde_json::from_str(&text).unwrap();
            }
            Err(e) => {
                eprintln!("GET {path}: {e}; again");
                std::thread::sleep(Duration::from_millis(200));
            }
        }
    }
    server.get_json(path)
}

/// The entries of the data directory's `tmp/` made by process `pid` (their names start with
/// `<host>.<pid namespace>.<pid>_`), with their sizes.
fn tmp_entries_of(data: &std::path::Path, pid: u32) -> Vec<(String, u64)> {
    let mark = format!(".{pid}_");
    entries(&data.join("tmp"))
        .into_iter()
        .filter(|n| {
            n.split_once('_')
                .is_some_and(|(tag, _)| format!("{tag}_").ends_with(&mark))
        })
        .map(|n| {
            let bytes = std::fs::metadata(data.join("tmp").join(&n)).map_or(0, |m| m.len());
            (n, bytes)
        })
        .collect()
}

#[test]
#[cfg_attr(
    not(all(feature = "slow-tests", postgres_binaries)),
    ignore = "slow study (two API processes, three workers, 100 jobs, a worker and an API killed): cargo test --features slow-tests, with PostgreSQL's server programs"
)]
fn every_job_ends_done_once_when_a_worker_and_an_api_are_killed() {
    // LM_KILL_JOBS shrinks the study for a quick look; the figure is 100.
    let job_count: usize = std::env::var("LM_KILL_JOBS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(100);
    const PHASES: usize = 3;
    // LM_KILL_RETENTION_S: the API processes' retention interval (tmp/ is swept then).
    let retention_s = std::env::var("LM_KILL_RETENTION_S").unwrap_or_else(|_| "3".into());
    let scratch = Scratch::new("pg-kill");
    let db = PgServer::start(&scratch.join("postgres"));
    // With LUNGMOTION_TEST_OBJECT_STORE=s3, one S3 server that every process shares.
    let objects = object_store_backend().then(|| {
        let s3 = S3Server::start(&scratch.join("moto"));
        s3.create_bucket(TEST_BUCKET);
        s3
    });
    let data = scratch.join("data");
    let url = db.url();
    let mut owned_env: Vec<(String, String)> = objects
        .as_ref()
        .map(|s3| s3.service_env(TEST_BUCKET, "lm"))
        .unwrap_or_default();
    owned_env.extend(
        [
            ("LUNGMOTION_POSTGRES_URL", url.as_str()),
            // A short lease, so the test waits seconds for the dead worker's job.
            ("LUNGMOTION_LEASE_S", "4"),
            ("LUNGMOTION_LOG_FORMAT", "json"),
            ("LUNGMOTION_QUEUE_CAPACITY", "1000"),
            // Retention sweeps (tmp/ among them) every 3 s by default, so the test sees one soon.
            ("LUNGMOTION_RETENTION_INTERVAL_S", retention_s.as_str()),
        ]
        .map(|(k, v)| (k.to_string(), v.to_string())),
    );
    let env: Vec<(&str, &str)> = owned_env
        .iter()
        .map(|(k, v)| (k.as_str(), v.as_str()))
        .collect();
    // Four runs per job: with a 4 s lease, a machine that holds the test's processes up (a
    // shared CI machine) takes leases back from live workers too.
    const MAX_ATTEMPTS: u64 = 4;
    let config = scratch.join("service.toml");
    std::fs::write(&config, format!("max_attempts = {MAX_ATTEMPTS}\n")).unwrap();
    let config = config.to_str().unwrap();
    let start_api = || ServerProcess::start_sharing(&data, &["--config", config], &env);
    let mut apis = [start_api(), start_api()];
    let mut workers: Vec<WorkerProcess> = (0..3)
        .map(|i| {
            WorkerProcess::start(
                &data,
                &scratch.join(&format!("worker-{i}.log")),
                &["--workers", "1", "--config", config],
                &env,
            )
        })
        .collect();
    let ct = sample("phantom-ct.nii.gz");
    let scan = apis[1].upload_scan(&ct);
    // 12 mm, 2 breaths, 3 phases: about a second each on the phantom.
    let request = tiny_request(PHASES);
    let started = Instant::now();
    let jobs: Vec<String> = (0..job_count)
        .map(|i| apis[i % 2].submit(&scan, &request))
        .collect();
    let submitted_in = started.elapsed();

    // A job in the middle of its run, and the worker running it: SIGKILL.
    let (victim_job, victim_worker) = loop {
        let rows = db.psql(
            "lungmotion",
            "SELECT job_id, lease_owner, record->'progress'->>'stage' FROM lungmotion_jobs \
             WHERE state = 'running' AND record->'progress'->>'stage' = 'solving'",
        );
        if let Some(line) = rows.lines().next() {
            let mut parts = line.split('|');
            break (
                parts.next().unwrap().to_string(),
                parts.next().unwrap().to_string(),
            );
        }
        assert!(started.elapsed() < JOB_TIMEOUT, "no job reached solving");
        std::thread::sleep(Duration::from_millis(20));
    };
    let index = workers
        .iter()
        .position(|w| w.id == victim_worker)
        .unwrap_or_else(|| panic!("no worker {victim_worker}"));
    let killed_at = Instant::now();
    workers[index].kill();
    eprintln!("killed worker {victim_worker} during job {victim_job}");

    // An upload of 64 MiB to the first API process, which is SIGKILLed once 8 MiB are in.
    const ANNOUNCED: usize = 64 << 20;
    let api_pid = apis[0].pid();
    let uploader = slow_upload(apis[0].base_url(), ANNOUNCED);
    let deadline = Instant::now() + READY_TIMEOUT;
    let partial = loop {
        let mine = tmp_entries_of(&data, api_pid);
        if let Some((name, _)) = mine
            .iter()
            .find(|(n, b)| n.contains("upload") && *b >= 8 << 20)
        {
            break name.clone();
        }
        assert!(
            Instant::now() < deadline,
            "the upload never reached 8 MiB in tmp/: {mine:?}"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    apis[0].kill();
    let sent = uploader.join().unwrap();
    assert!(sent < ANNOUNCED, "the whole upload was sent ({sent} bytes)");
    eprintln!("killed API process {api_pid} during an upload ({sent} of {ANNOUNCED} bytes sent)");
    // What it left is the retention sweep's of the API process still running: gone within a
    // few sweeps.
    let api_killed_at = Instant::now();
    let deadline = api_killed_at + READY_TIMEOUT;
    while !tmp_entries_of(&data, api_pid).is_empty() {
        assert!(
            Instant::now() < deadline,
            "the killed upload was never swept from tmp/: {:?} (first seen: {partial})",
            tmp_entries_of(&data, api_pid)
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let swept_after = api_killed_at.elapsed();

    // Every job ends, watched through the API process still running; the killed worker's job
    // is taken back once its lease runs out and run again by another worker.
    let mut back_after = None;
    let deadline = Instant::now() + JOB_TIMEOUT;
    // The longest time between two polls: far above their 0.2 s, the test's processes were
    // held up (stopped, or starved of the CPU), and the times measured are not the service's.
    let mut longest_gap = Duration::ZERO;
    let mut last_poll = Instant::now();
    let statuses: HashMap<String, Value> = loop {
        longest_gap = longest_gap.max(last_poll.elapsed());
        last_poll = Instant::now();
        let page = get_json_again(&apis[1], "/v1/jobs?limit=500");
        let items = page["items"].as_array().unwrap();
        let now: HashMap<String, Value> = items
            .iter()
            .map(|s| (s["job_id"].as_str().unwrap().to_string(), s.clone()))
            .collect();
        assert_eq!(now.len(), job_count, "jobs lost or added: {page}");
        if back_after.is_none() && now[&victim_job]["attempts"] == 2 {
            back_after = Some(killed_at.elapsed());
        }
        let ended = |s: &Value| {
            ["done", "failed", "cancelled"].contains(&s["state"].as_str().unwrap_or(""))
        };
        if now.values().all(ended) {
            break now;
        }
        assert!(Instant::now() < deadline, "jobs never ended: {page}");
        std::thread::sleep(Duration::from_millis(200));
    };
    let elapsed = started.elapsed();

    // The killed API process's place taken again: a new one serves the same jobs.
    apis[0] = start_api();
    assert_eq!(
        apis[0].get_json(&format!("/v1/jobs/{victim_job}"))["state"],
        statuses[&victim_job]["state"]
    );

    // Done exactly once each (counted in every worker's log, the killed one's included), or
    // failed with its reason after its attempts.
    let logs: Vec<String> = workers.iter().map(|w| w.log()).collect();
    let done = done_runs(&logs);
    let mut failed = 0;
    for id in &jobs {
        let s = &statuses[id];
        match s["state"].as_str().unwrap() {
            "done" => assert_eq!(
                done.get(id),
                Some(&1),
                "job {id} done {:?} times",
                done.get(id)
            ),
            "failed" => {
                failed += 1;
                assert!(
                    s["error"].as_str().is_some_and(|e| !e.is_empty())
                        && s["attempts"].as_u64() == Some(MAX_ATTEMPTS),
                    "{id} failed without its reason or before its attempts: {s}"
                );
                eprintln!("job {id} failed after its attempts: {}", s["error"]);
                assert_eq!(done.get(id), None, "failed job {id} also done");
            }
            other => panic!("job {id} ended {other}: {s}"),
        }
    }
    assert!(
        statuses[&victim_job]["attempts"].as_u64().unwrap() >= 2,
        "{}",
        statuses[&victim_job]
    );
    let done_jobs: Vec<&String> = jobs
        .iter()
        .filter(|id| statuses[*id]["state"] == "done")
        .collect();

    // The fields are the CLI's, byte for byte: `lungmotion run` on the same CT, trace and
    // settings.
    let (time_s, volume_ml) = breathing_trace(2);
    std::fs::write(scratch.join("trace.csv"), trace_csv(&time_s, &volume_ml)).unwrap();
    std::fs::write(
        scratch.join("run.toml"),
        format!(
            "element_size_mm = 12\n[motion]\ninstants = {{ kind = \"phases\", count = {PHASES} }}\n\
             [outputs]\nquicklooks = false\n"
        ),
    )
    .unwrap();
    let cli_out = scratch.join("cli-out");
    run_cli(&[
        &"run",
        &"--ct",
        &ct,
        &"--trace",
        &scratch.join("trace.csv"),
        &"--config",
        &scratch.join("run.toml"),
        &"--out",
        &cli_out,
        &"--quiet",
    ]);
    let cli_fields: Vec<Vec<u8>> = (0..PHASES)
        .map(|k| std::fs::read(cli_out.join(format!("frames/{k}/displacement.nii.gz"))).unwrap())
        .collect();
    for id in &done_jobs {
        for (k, cli) in cli_fields.iter().enumerate() {
            let resp = apis[k % 2].get(&format!("/v1/jobs/{id}/frames/{k}/displacement"));
            assert_eq!(resp.status(), 200, "{id} frame {k}");
            let served = resp.bytes().unwrap();
            assert!(
                served[..] == cli[..],
                "job {id} frame {k}: {} bytes served, the CLI's {} bytes differ",
                served.len(),
                cli.len()
            );
        }
    }

    // No orphans: the database, the data directory and the object store hold the one scan
    // and the jobs, nothing of the killed upload, no partial outputs.
    let scans = db.psql("lungmotion", "SELECT scan_id FROM lungmotion_scans");
    assert_eq!(scans.trim(), scan, "scans in the database");
    let count = db.psql("lungmotion", "SELECT count(*) FROM lungmotion_jobs");
    assert_eq!(count.trim(), job_count.to_string());
    assert_eq!(stray_tmp_files(&data), Vec::<String>::new(), "tmp/");
    for name in entries(&data.join("scans")) {
        assert_eq!(name, scan, "a scan directory of no scan");
    }
    for name in entries(&data.join("jobs")) {
        assert!(jobs.contains(&name), "a job directory of no job: {name}");
        let partial: Vec<String> = entries(&data.join("jobs").join(&name))
            .into_iter()
            .filter(|n| n.contains("partial"))
            .collect();
        assert!(partial.is_empty(), "job {name}: {partial:?}");
    }
    let object_count = objects.as_ref().map_or(0, |s3| {
        let keys = s3.keys(TEST_BUCKET, "");
        for key in &keys {
            let owned = key.starts_with(&format!("lm/scans/{scan}/"))
                || key
                    .strip_prefix("lm/jobs/")
                    .and_then(|rest| rest.split_once('/'))
                    .is_some_and(|(id, _)| jobs.iter().any(|j| j == id));
            assert!(owned, "an object of no scan or job: {key}");
        }
        for id in &done_jobs {
            let key = format!("lm/jobs/{id}/out/frames/0/displacement.nii.gz");
            assert!(keys.contains(&key), "{key} missing");
        }
        keys.len()
    });

    let minutes = elapsed.as_secs_f64() / 60.0;
    eprintln!(
        "measured: {job_count} jobs (12 mm, {PHASES} phases; blobs in {}) on 2 API processes and 3 \
         workers, one worker and one API process killed: all ended ({} done, {failed} failed after \
         {MAX_ATTEMPTS} runs) in {:.1} s ({:.1} jobs/min; \
         submitted in {:.1} s); the killed worker's job ran again {:.1} s after the kill (lease 4 \
         s); the killed upload's {} in tmp/ swept {:.1} s after its API process died; fields \
         byte-identical to `lungmotion run`; {object_count} objects, all of live scans and jobs; \
         longest gap between two polls of the jobs {:.1} s",
        if objects.is_some() { "S3 (moto)" } else { "the data directory" },
        done_jobs.len(),
        elapsed.as_secs_f64(),
        job_count as f64 / minutes,
        submitted_in.as_secs_f64(),
        back_after.map_or(f64::NAN, |d| d.as_secs_f64()),
        partial,
        swept_after.as_secs_f64(),
        longest_gap.as_secs_f64(),
    );
}

/// Whether `data` holds a copy of the scan's upload (`scans/<id>/<file>`, any name but the
/// mark and the stored ingest).
fn upload_copy(data: &std::path::Path, scan: &str) -> bool {
    entries(&data.join("scans").join(scan))
        .iter()
        .any(|n| n.ends_with(".nii.gz"))
}

#[test]
fn api_processes_need_no_shared_directory_their_upload_copies_are_a_bounded_cache() {
    // Two API processes and a worker, each with a data directory of its own, on one database
    // and one S3 server (moto): the uploads' copies in an API's data directory are a cache of
    // the objects, bounded by fetched_scans_mib (0 here: only copies in use are kept), so
    // they are evicted after the upload and fetched again when a target is checked against
    // the CT, by the process that received the upload or by another.
    let scratch = Scratch::new("pg-api-cache");
    let db = PgServer::start(&scratch.join("postgres"));
    let s3 = S3Server::start(&scratch.join("moto"));
    s3.create_bucket(TEST_BUCKET);
    let url = db.url();
    let mut owned_env = s3.service_env(TEST_BUCKET, "lm");
    owned_env.extend(
        [
            ("LUNGMOTION_POSTGRES_URL", url.as_str()),
            ("LUNGMOTION_FETCHED_SCANS_MIB", "0"),
        ]
        .map(|(k, v)| (k.to_string(), v.to_string())),
    );
    let env: Vec<(&str, &str)> = owned_env
        .iter()
        .map(|(k, v)| (k.as_str(), v.as_str()))
        .collect();
    let dirs = ["api-a", "api-b", "worker"].map(|d| {
        let dir = scratch.join(d);
        std::fs::create_dir_all(&dir).unwrap();
        dir.join("data")
    });
    let a = ServerProcess::start_sharing(&dirs[0], &[], &env);
    let b = ServerProcess::start_sharing(&dirs[1], &[], &env);
    let worker = WorkerProcess::start(
        &dirs[2],
        &scratch.join("worker").join("worker.log"),
        &["--workers", "1"],
        &env,
    );

    // Received by A, put in the bucket, then its copy evicted (nothing holds it).
    let scan = a.upload_scan(&sample("phantom-ct.nii.gz"));
    assert!(!s3
        .keys(TEST_BUCKET, &format!("lm/scans/{scan}/"))
        .is_empty());
    assert!(
        !upload_copy(&dirs[0], &scan),
        "the upload's copy stayed: {:?}\n{}",
        entries(&dirs[0].join("scans").join(&scan)),
        tail(&a.log(), 20)
    );
    assert!(!dirs[1].join("scans").join(&scan).exists());

    // B never saw the upload: checking a target against the CT fetches it from the bucket.
    let truth = std::fs::read(sample("phantom-truth.nii.gz")).unwrap();
    let put_target = |server: &ServerProcess| {
        server
            .client()
            .put(server.url(&format!("/v1/scans/{scan}/targets/gtv")))
            .header("content-type", "application/octet-stream")
            .body(truth.clone())
            .send()
            .unwrap()
    };
    let resp = put_target(&b);
    assert!(resp.status().is_success(), "{:?}", resp.text());
    assert!(
        b.log().contains("scan fetched from the object store"),
        "{}",
        tail(&b.log(), 20)
    );
    // A fetches its evicted copy again the same way.
    let resp = put_target(&a);
    assert!(resp.status().is_success(), "{:?}", resp.text());
    assert!(
        a.log().contains("scan fetched from the object store"),
        "{}",
        tail(&a.log(), 20)
    );
    // Once no request holds them, the next upload's eviction takes both older copies.
    let second = b.upload_scan(&sample("phantom-ct.nii.gz"));
    assert!(!upload_copy(&dirs[1], &scan) && !upload_copy(&dirs[1], &second));

    // A job submitted through A on the target, run by the worker from its own directory.
    let mut request = tiny_request(2);
    request["target"] = serde_json::json!({"upload": "gtv", "label": 8});
    let job = a.submit(&scan, &request);
    let status = b.wait_for_state(&job, &["done", "failed"], JOB_TIMEOUT);
    assert_eq!(status["state"], "done", "{status}\n{}", worker.log());
    assert_eq!(
        b.get(&format!("/v1/jobs/{job}/frames/1/displacement"))
            .status(),
        200
    );

    // The job deleted through B, the scan through A (which holds a copy from its target
    // check, removed with it): the objects go, and no API process has a copy left. The
    // worker's copy, fetched for the job, stays until its next fetch evicts it (unused: the
    // record is gone), as a copy in another API process's directory would.
    assert_eq!(b.delete(&format!("/v1/jobs/{job}")).status(), 204);
    assert_eq!(a.delete(&format!("/v1/scans/{scan}")).status(), 204);
    assert!(s3
        .keys(TEST_BUCKET, &format!("lm/scans/{scan}/"))
        .is_empty());
    assert_eq!(b.get(&format!("/v1/scans/{scan}")).status(), 404);
    for dir in &dirs[..2] {
        assert!(!upload_copy(dir, &scan), "{}", dir.display());
    }
    assert!(
        upload_copy(&dirs[2], &scan),
        "the worker fetched the scan for the job"
    );
}

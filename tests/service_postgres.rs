//! The service on PostgreSQL (`[store] postgres_url`): API processes (`lungmotion serve`) and
//! worker processes (`lungmotion worker`) sharing one database and one data directory, each
//! test with a PostgreSQL server of its own (see `service_support::postgres`).
//!
//! * A journey: upload, a job run by a separate worker, its results, cancellation, deletion,
//!   the workers in `/metrics`.
//! * Bad input: a database that cannot be reached at start (named, retried with a doubling
//!   wait), refused credentials (named at start and in `/readyz` while serving), a schema
//!   written by a newer lungmotion (refused by name).
//! * Slow: two API processes and three workers, one worker killed with SIGKILL in the middle
//!   of a job: every job ends `done` exactly once, the killed worker's job after its lease ran
//!   out.
#![cfg(feature = "cli")]

mod service_support;

use std::collections::HashMap;
use std::time::{Duration, Instant};

use serde_json::Value;
use service_support::postgres::{free_port, run_to_exit, PgServer, WorkerProcess, PG_PASSWORD};
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
    // The password back: ready again, without a restart.
    let restore = format!("ALTER ROLE lm PASSWORD '{PG_PASSWORD}'");
    let changed = PgServerPassword(&db, "changed-meanwhile");
    changed.psql(&restore);
    let (_, body) = wait_ready(&server, |s, _| s == 200);
    assert_eq!(body["status"], "ready");
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
fn the_schema_is_made_by_the_service_and_a_newer_one_is_refused_by_name() {
    let scratch = Scratch::new("pg-schema");
    let db = PgServer::start(&scratch.join("postgres"));
    let data = scratch.join("data");
    {
        let server = api(&data, &db.url(), &[]);
        wait_ready(&server, |s, _| s == 200);
    }
    let version = db.psql(
        "lungmotion",
        "SELECT version, written_by FROM lungmotion_schema",
    );
    assert_eq!(
        version.trim(),
        format!("1|{}", env!("CARGO_PKG_VERSION")),
        "{version}"
    );
    for table in ["lungmotion_jobs", "lungmotion_scans", "lungmotion_workers"] {
        let n = db.psql("lungmotion", &format!("SELECT count(*) FROM {table}"));
        assert_eq!(n.trim(), "0", "{table}");
    }
    db.psql(
        "lungmotion",
        "UPDATE lungmotion_schema SET version = 99, written_by = '9.9.9'",
    );
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
            "knows versions up to 1",
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
    let mut worker = WorkerProcess::start(
        &data,
        &scratch.join("worker.log"),
        &["--workers", "1"],
        &env,
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

    // A callback would never be sent across processes yet: refused, not dropped.
    let mut with_callback = tiny_request(2);
    with_callback["callback_url"] = "http://127.0.0.1:9/hook".into();
    assert_problem(
        server.post_simulation(&scan, &with_callback),
        422,
        &["callbacks", "PostgreSQL"],
    );

    // Cancelling a running job reaches the worker's run; the job ends cancelled, its partial
    // outputs gone.
    let long = server.submit(&scan, &simulation_request(2, &tracked_points(), 8.0, 10));
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

#[test]
#[cfg_attr(
    not(all(feature = "slow-tests", postgres_binaries)),
    ignore = "slow study (two API processes, three workers, one killed): cargo test --features slow-tests, with PostgreSQL's server programs"
)]
fn every_job_ends_done_once_when_a_worker_is_killed_mid_job() {
    const JOBS: usize = 6;
    let scratch = Scratch::new("pg-kill");
    let db = PgServer::start(&scratch.join("postgres"));
    let data = scratch.join("data");
    let url = db.url();
    // A short lease, so the test waits seconds for the dead worker's job.
    let env = [
        ("LUNGMOTION_POSTGRES_URL", url.as_str()),
        ("LUNGMOTION_LEASE_S", "4"),
        ("LUNGMOTION_LOG_FORMAT", "json"),
    ];
    let apis = [api(&data, &url, &env[1..]), api(&data, &url, &env[1..])];
    let mut workers: Vec<WorkerProcess> = (0..3)
        .map(|i| {
            WorkerProcess::start(
                &data,
                &scratch.join(&format!("worker-{i}.log")),
                &["--workers", "1"],
                &env,
            )
        })
        .collect();
    let scan = apis[0].upload_scan(&sample("phantom-ct.nii.gz"));
    // 8 mm, 6 phases: seconds each on the phantom.
    let request = simulation_request(2, &tracked_points(), 8.0, 6);
    let started = Instant::now();
    let jobs: Vec<String> = (0..JOBS)
        .map(|i| apis[i % 2].submit(&scan, &request))
        .collect();

    // A job in the middle of its run, and the worker running it.
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
        std::thread::sleep(Duration::from_millis(100));
    };
    let index = workers
        .iter()
        .position(|w| w.id == victim_worker)
        .unwrap_or_else(|| panic!("no worker {victim_worker}"));
    let killed_at = Instant::now();
    workers[index].kill();
    eprintln!("killed worker {victim_worker} during job {victim_job}");

    // Taken back once its lease runs out, and run again by another worker.
    let mut back_after = None;
    let deadline = Instant::now() + JOB_TIMEOUT;
    let statuses: Vec<Value> = loop {
        let now: Vec<Value> = jobs
            .iter()
            .map(|id| apis[1].get_json(&format!("/v1/jobs/{id}")))
            .collect();
        let victim = &now[jobs.iter().position(|j| *j == victim_job).unwrap()];
        if back_after.is_none() && victim["attempts"] == 2 {
            back_after = Some(killed_at.elapsed());
        }
        let ended = |s: &Value| {
            ["done", "failed", "cancelled"].contains(&s["state"].as_str().unwrap_or(""))
        };
        if now.iter().all(ended) {
            break now;
        }
        assert!(Instant::now() < deadline, "jobs never ended: {now:?}");
        std::thread::sleep(Duration::from_millis(100));
    };
    let elapsed = started.elapsed();
    let logs: Vec<String> = workers.iter().map(|w| w.log()).collect();
    for (id, s) in jobs.iter().zip(&statuses) {
        assert_eq!(s["state"], "done", "{id}: {s}");
        let summary = apis[0].get_json(&format!("/v1/jobs/{id}/summary"));
        assert_eq!(summary["frames"].as_array().unwrap().len(), 6);
    }
    let victim = &statuses[jobs.iter().position(|j| *j == victim_job).unwrap()];
    assert!(victim["attempts"].as_u64().unwrap() >= 2, "{victim}");
    let done = done_runs(&logs);
    for id in &jobs {
        assert_eq!(
            done.get(id),
            Some(&1),
            "job {id} done {:?} times",
            done.get(id)
        );
    }
    let left: Vec<String> = entries(&data.join("jobs").join(&victim_job))
        .into_iter()
        .filter(|n| n.contains("partial"))
        .collect();
    assert!(left.is_empty(), "{left:?}");
    eprintln!(
        "{JOBS} jobs on 3 workers (one killed) in {:.1} s; the killed worker's job ran again {:.1} s after the kill (lease 4 s)",
        elapsed.as_secs_f64(),
        back_after.map_or(f64::NAN, |d| d.as_secs_f64())
    );
}

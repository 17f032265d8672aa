//! The PostgreSQL queue's own cost (issue 17), on a PostgreSQL server of the benchmark's own
//! (Debian's binaries under `/usr/lib/postgresql/<version>/bin`: `initdb` in a temporary
//! directory, `pg_ctl start` on a free loopback port with `fsync=off`, as the `postgres` user
//! when run as root; the part is skipped, saying why, without them).
//!
//! * **Per job, the queue alone**: [`QUEUE_JOBS`] no-op jobs (a queued row with its request
//!   and a 2-phase trace, no files to run) submitted, then for each, one after the other as one
//!   worker thread does: the claim (`SELECT … FOR UPDATE SKIP LOCKED`, the row marked running
//!   and leased), one heartbeat (the lease renewal a running job makes every third of its
//!   lease, at most every second) and the completion (the `done` record written under the
//!   lease, the lease released). Each call is timed from the caller's side, through the pool
//!   and the client's runtime as a worker makes it. Then the same jobs claimed and completed
//!   (with one heartbeat each) by 1, 2 and 4 threads at once: the queue's own ceiling in jobs
//!   per minute, no simulation in it.
//! * **Jobs per minute with 1, 2 and 4 workers** on short jobs (the bundled phantom at 12 mm,
//!   2 phases, no quick looks, as `docs/measure-postgres-workers.sh`): one API server
//!   ([`crate::service::start`]) and N workers ([`crate::service::worker::start_worker`], one
//!   simulation thread each, as `lungmotion worker --workers 1`), all in this process on one
//!   data directory; the jobs are submitted at once and timed from the first submission until
//!   the last is seen `done` (polled every 50 ms). Rounds interleave 1, 2 and 4 workers, so
//!   a change of the machine's load falls on all three; medians over the rounds. Each worker
//!   starts fresh, so its first job reads the scan's stored ingest, as a new worker process
//!   would.

use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde::Serialize;
use serde_json::json;

use super::super::{Outcome, TimeStats};
use crate::run::RunConfig;
use crate::service::ids::ScanId;
use crate::service::postgres::{Postgres, PostgresSettings};
use crate::service::records::Records;
use crate::service::store::{now_rfc3339, JobRecord, JobRequest, JobState, ScanRecord, Store};
use crate::service::worker::start_worker;
use crate::service::{start, ServiceConfig};
use crate::{Error, IoContext, IoOp, Result};

/// No-op jobs through the queue for the per-job times.
pub const QUEUE_JOBS: usize = 200;
/// No-op jobs in quick mode.
pub const QUICK_QUEUE_JOBS: usize = 40;
/// Workers (and threads of the queue-only ceiling) measured side by side.
pub const WORKER_COUNTS: [usize; 3] = [1, 2, 4];
/// Short jobs per worker count and round.
pub const SHORT_JOBS: usize = 12;
/// Short jobs per worker count in quick mode.
pub const QUICK_SHORT_JOBS: usize = 4;
/// Rounds of 1, 2 and 4 workers.
pub const ROUNDS: usize = 3;
/// Element edge of the short jobs, mm.
pub const SHORT_JOB_ELEMENT_SIZE_MM: f64 = 12.0;
/// Output phases of a short job.
pub const SHORT_JOB_PHASES: usize = 2;
/// How often the benchmark looks for the last `done`, ms.
const DONE_POLL_MS: u64 = 50;
/// Longest wait for one round's jobs.
const ROUND_TIMEOUT: Duration = Duration::from_secs(900);

/// Median time of each queue call per job, from the caller's side.
#[derive(Debug, Clone, Serialize)]
pub struct QueueOverhead {
    /// No-op jobs timed.
    pub jobs: usize,
    /// Submission (the row inserted under the scan's lock, the queue counted, NOTIFY).
    pub submit: TimeStats,
    /// Claim: the oldest queued job taken with `FOR UPDATE SKIP LOCKED`, marked running, leased.
    pub claim: TimeStats,
    /// One heartbeat: the lease renewed (a running job makes one every third of its lease,
    /// at most every second).
    pub heartbeat: TimeStats,
    /// Completion: the `done` record written under the lease, the lease released.
    pub complete: TimeStats,
    /// Median claim + median heartbeat + median completion, s: the queue's cost of a job that
    /// ends within one renewal interval (each further second of run adds one heartbeat).
    pub per_job_s: f64,
    /// No-op jobs per minute taken and completed (one heartbeat each) by 1, 2 and 4 threads
    /// at once: the queue's own ceiling.
    pub queue_only_jobs_per_min: Vec<ThreadsRate>,
}

/// No-op jobs per minute with a number of claiming threads.
#[derive(Debug, Clone, Serialize)]
pub struct ThreadsRate {
    /// Threads claiming at once.
    pub threads: usize,
    /// Jobs taken and completed.
    pub jobs: usize,
    /// Wall time, s.
    pub wall_s: f64,
    /// Jobs per minute.
    pub jobs_per_min: f64,
}

/// Short jobs run by a number of workers.
#[derive(Debug, Clone, Serialize)]
pub struct WorkerThroughput {
    /// Workers, one simulation thread each.
    pub workers: usize,
    /// Jobs per round.
    pub jobs: usize,
    /// From the first submission to the last `done`, per round.
    pub wall: TimeStats,
    /// Jobs per minute of the median round.
    pub jobs_per_min: f64,
    /// Jobs per minute of each round, in order.
    pub rounds_jobs_per_min: Vec<f64>,
}

/// What the queue part measured.
#[derive(Debug, Clone, Serialize)]
pub struct QueueBenchReport {
    /// The PostgreSQL server (`SHOW server_version`) and how it was run.
    pub postgres: String,
    /// The queue calls per job.
    pub overhead: Outcome<QueueOverhead>,
    /// Short jobs with 1, 2 and 4 workers, side by side.
    pub workers: Outcome<Vec<WorkerThroughput>>,
}

/// A PostgreSQL server of the benchmark's own, stopped and removed when dropped.
struct BenchDatabase {
    bin: PathBuf,
    dir: PathBuf,
    port: u16,
    as_root: bool,
}

impl BenchDatabase {
    /// The newest `/usr/lib/postgresql/<version>/bin` holding `initdb`.
    fn bin_dir() -> Option<PathBuf> {
        let mut dirs: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
            .ok()?
            .flatten()
            .filter_map(|e| {
                let version = e.file_name().to_string_lossy().parse::<u32>().ok()?;
                let bin = e.path().join("bin");
                bin.join("initdb").is_file().then_some((version, bin))
            })
            .collect();
        dirs.sort();
        dirs.pop().map(|(_, bin)| bin)
    }

    fn start(dir: &Path) -> Result<BenchDatabase> {
        let bin = Self::bin_dir().ok_or_else(|| {
            Error::External(
                "PostgreSQL's binaries (/usr/lib/postgresql/*/bin/initdb) are missing: \
                 apt-get install postgresql"
                    .into(),
            )
        })?;
        std::fs::create_dir_all(dir).at(IoOp::CreateDir, dir)?;
        let as_root = Command::new("id")
            .arg("-u")
            .output()
            .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
            .unwrap_or(false);
        if as_root {
            run_tool(
                Command::new("chown")
                    .args(["-R", "postgres:postgres"])
                    .arg(dir),
            )?;
        }
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map(|a| a.port())
            .at(IoOp::Open, "a free loopback port")?;
        let db = BenchDatabase {
            bin,
            dir: dir.to_path_buf(),
            port,
            as_root,
        };
        let data = dir.join("data");
        run_tool(db.tool("initdb").arg("-D").arg(&data).args([
            "-U",
            "lm",
            "-A",
            "trust",
            "--no-sync",
            "-E",
            "UTF8",
            "--locale=C",
        ]))?;
        run_tool(
            db.tool("pg_ctl")
                .arg("-D")
                .arg(&data)
                .arg("-o")
                .arg(format!(
                    "-p {} -k {} -c listen_addresses=127.0.0.1 -c fsync=off",
                    db.port,
                    dir.display()
                ))
                .arg("-l")
                .arg(dir.join("postgres.log"))
                .args(["-w", "start"]),
        )?;
        run_tool(db.tool("psql").args([
            "-h",
            "127.0.0.1",
            "-p",
            &db.port.to_string(),
            "-U",
            "lm",
            "-d",
            "postgres",
            "-qc",
            "CREATE DATABASE lungmotion",
        ]))?;
        Ok(db)
    }

    /// One of the server's programs, as the `postgres` user when this runs as root.
    fn tool(&self, name: &str) -> Command {
        let program = self.bin.join(name);
        if self.as_root {
            let mut c = Command::new("runuser");
            c.args(["-u", "postgres", "--"]).arg(program);
            c
        } else {
            Command::new(program)
        }
    }

    fn url(&self) -> String {
        format!("postgres://lm@127.0.0.1:{}/lungmotion", self.port)
    }

    fn version(&self) -> String {
        self.tool("psql")
            .args([
                "-h",
                "127.0.0.1",
                "-p",
                &self.port.to_string(),
                "-U",
                "lm",
                "-d",
                "postgres",
                "-Atc",
                "SHOW server_version",
            ])
            .output()
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
            .unwrap_or_default()
    }
}

impl Drop for BenchDatabase {
    fn drop(&mut self) {
        let _ = self
            .tool("pg_ctl")
            .arg("-D")
            .arg(self.dir.join("data"))
            .args(["-m", "immediate", "stop"])
            .output();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Runs a command to its end; an error names it with its output when it fails.
fn run_tool(command: &mut Command) -> Result<()> {
    let shown = format!("{command:?}");
    let out = command
        .output()
        .map_err(|e| Error::External(format!("{shown}: {e}")))?;
    if out.status.success() {
        return Ok(());
    }
    Err(Error::External(format!(
        "{shown}: {}: {}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )))
}

/// Runs the queue part in `work` (a temporary directory); see the module documentation.
pub fn run_queue_bench(work: &Path, quick: bool) -> QueueBenchReport {
    let db = match BenchDatabase::start(&work.join("postgres")) {
        Ok(db) => db,
        Err(e) => {
            let why = format!("no PostgreSQL server: {e}");
            return QueueBenchReport {
                postgres: String::new(),
                overhead: Outcome::Skipped(why.clone()),
                workers: Outcome::Skipped(why),
            };
        }
    };
    let postgres = format!(
        "PostgreSQL {} on loopback, fsync=off, a server of the benchmark's own",
        db.version()
    );
    let settings = PostgresSettings::new(db.url());
    let (jobs, short_jobs, rounds) = if quick {
        (QUICK_QUEUE_JOBS, QUICK_SHORT_JOBS, 1)
    } else {
        (QUEUE_JOBS, SHORT_JOBS, ROUNDS)
    };
    let overhead = Outcome::from_result(queue_overhead(work, &settings, jobs));
    let workers = Outcome::from_result(worker_throughput(work, &settings, short_jobs, rounds));
    drop(db);
    QueueBenchReport {
        postgres,
        overhead,
        workers,
    }
}

/// A no-op job's request: a 2-phase trace and the defaults.
fn no_op_request() -> JobRequest {
    let (time_s, volume_ml) = short_trace();
    JobRequest {
        config: RunConfig::default(),
        time_s,
        volume_ml,
        trace_source: "benchmark".into(),
        points: Vec::new(),
        callback_url: None,
        target: None,
        pacs_ct: None,
        push: false,
    }
}

/// Two 4 s breaths of 500 mL at 10 Hz.
fn short_trace() -> (Vec<f64>, Vec<f64>) {
    let time_s: Vec<f64> = (0..=80).map(|i| i as f64 / 10.0).collect();
    let volume_ml = time_s
        .iter()
        .map(|t| 250.0 * (1.0 - (2.0 * std::f64::consts::PI * t / 4.0).cos()))
        .collect();
    (time_s, volume_ml)
}

/// Submits `jobs` no-op jobs on a scan of their own; their records.
fn submit_no_op_jobs(pg: &Postgres, store: &Store, jobs: usize) -> Result<(Vec<f64>, ScanId)> {
    let scan = ScanRecord {
        scan_id: ScanId::random(),
        created_at: now_rfc3339(),
        format: "nifti".into(),
        upload_bytes: 1,
        file_name: "scan.nii.gz".into(),
        ingest: json!({}),
        series: None,
    };
    let upload = store.tmp_path("bench-upload");
    std::fs::write(&upload, b"x").at(IoOp::Write, &upload)?;
    pg.put_scan(&scan, &upload)?;
    let request = no_op_request();
    let mut times = Vec::with_capacity(jobs);
    for _ in 0..jobs {
        let record = JobRecord::queued(scan.scan_id);
        let t = Instant::now();
        match pg.submit(&record, &request, None, usize::MAX)? {
            Ok(true) => {}
            other => {
                return Err(Error::External(format!(
                    "a no-op job was not queued: {other:?}"
                )))
            }
        }
        times.push(t.elapsed().as_secs_f64());
    }
    Ok((times, scan.scan_id))
}

/// Claims, renews and completes one job as `worker`; the three times, or `None` when the
/// queue is empty.
fn one_job(pg: &Postgres, worker: &str) -> Result<Option<[f64; 3]>> {
    let t = Instant::now();
    let Some(mut record) = pg.claim(worker)? else {
        return Ok(None);
    };
    let claim = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let lease = pg.renew(record.job_id, worker)?;
    let heartbeat = t.elapsed().as_secs_f64();
    if lease != crate::service::postgres::Lease::Held {
        return Err(Error::External(format!(
            "job {}: the lease was {lease:?} right after the claim",
            record.job_id
        )));
    }
    record.state = JobState::Done;
    record.finished_at = Some(now_rfc3339());
    let t = Instant::now();
    if !pg.save_leased(&record, worker)? {
        return Err(Error::External(format!(
            "job {}: the completion was not written (lease lost)",
            record.job_id
        )));
    }
    let complete = t.elapsed().as_secs_f64();
    Ok(Some([claim, heartbeat, complete]))
}

fn queue_overhead(work: &Path, settings: &PostgresSettings, jobs: usize) -> Result<QueueOverhead> {
    let data = work.join("queue-data");
    let store = Store::open_shared(&data)?;
    let pg = Postgres::connect(settings, store.clone())?;
    // Warm the pool's connections and the statements' plans.
    let (_, _) = submit_no_op_jobs(&pg, &store, 8)?;
    while one_job(&pg, "bench-warmup")?.is_some() {}

    let (submit, _) = submit_no_op_jobs(&pg, &store, jobs)?;
    let (mut claim, mut heartbeat, mut complete) = (Vec::new(), Vec::new(), Vec::new());
    while let Some([c, h, d]) = one_job(&pg, "bench-worker")? {
        claim.push(c);
        heartbeat.push(h);
        complete.push(d);
    }
    if claim.len() != jobs {
        return Err(Error::External(format!(
            "{} of {jobs} no-op jobs were claimed",
            claim.len()
        )));
    }
    let mut queue_only = Vec::new();
    for threads in WORKER_COUNTS {
        submit_no_op_jobs(&pg, &store, jobs)?;
        let started = Instant::now();
        let handles: Vec<_> = (0..threads)
            .map(|i| {
                let pg = pg.clone();
                std::thread::spawn(move || -> Result<usize> {
                    let worker = format!("bench-thread-{i}");
                    let mut n = 0;
                    while one_job(&pg, &worker)?.is_some() {
                        n += 1;
                    }
                    Ok(n)
                })
            })
            .collect();
        let mut done = 0;
        for h in handles {
            done += h
                .join()
                .map_err(|_| Error::External("a claiming thread panicked".into()))??;
        }
        let wall_s = started.elapsed().as_secs_f64();
        queue_only.push(ThreadsRate {
            threads,
            jobs: done,
            wall_s,
            jobs_per_min: done as f64 * 60.0 / wall_s,
        });
    }
    let (claim, heartbeat, complete) = (
        TimeStats::new(&claim),
        TimeStats::new(&heartbeat),
        TimeStats::new(&complete),
    );
    Ok(QueueOverhead {
        jobs,
        submit: TimeStats::new(&submit),
        per_job_s: claim.median_s + heartbeat.median_s + complete.median_s,
        claim,
        heartbeat,
        complete,
        queue_only_jobs_per_min: queue_only,
    })
}

/// The short jobs' request.
fn short_request() -> serde_json::Value {
    let (time_s, volume_ml) = short_trace();
    json!({
        "trace": {"time_s": time_s, "volume_ml": volume_ml},
        "element_size_mm": SHORT_JOB_ELEMENT_SIZE_MM,
        "motion": {"instants": {"kind": "phases", "count": SHORT_JOB_PHASES}},
        "outputs": {"quicklooks": false},
    })
}

fn worker_throughput(
    work: &Path,
    settings: &PostgresSettings,
    jobs: usize,
    rounds: usize,
) -> Result<Vec<WorkerThroughput>> {
    let data = work.join("workers-data");
    let config = ServiceConfig {
        listen: SocketAddr::from(([127, 0, 0, 1], 0)),
        data_dir: data.clone(),
        workers: 1,
        queue_capacity: 10_000,
        postgres: Some(settings.clone()),
        run: RunConfig {
            element_size_mm: SHORT_JOB_ELEMENT_SIZE_MM,
            ..RunConfig::default()
        },
        ..ServiceConfig::default()
    };
    let server = start(config.clone())?;
    let client = reqwest::blocking::Client::builder()
        .no_proxy()
        .timeout(Duration::from_secs(300))
        .build()
        .map_err(|e| Error::External(format!("HTTP client: {e}")))?;
    let base = server.base_url.clone();
    let ct = crate::run::demo::sample_volumes_dir().join("phantom-ct.nii.gz");
    let bytes = std::fs::read(&ct).at(IoOp::Read, &ct)?;
    let scan = post_json(
        &client,
        &format!("{base}/v1/scans"),
        bytes,
        "application/octet-stream",
    )?;
    let scan_id = scan["scan_id"]
        .as_str()
        .ok_or_else(|| Error::External(format!("upload answered {scan}")))?
        .to_string();
    let request = serde_json::to_vec(&short_request())
        .map_err(|e| Error::External(format!("the short job's request: {e}")))?;
    let mut walls: Vec<Vec<f64>> = vec![Vec::new(); WORKER_COUNTS.len()];
    for _ in 0..rounds {
        for (k, &n) in WORKER_COUNTS.iter().enumerate() {
            let workers = (0..n)
                .map(|_| start_worker(&config))
                .collect::<Result<Vec<_>>>()?;
            let started = Instant::now();
            let mut ids = Vec::with_capacity(jobs);
            for _ in 0..jobs {
                let job = post_json(
                    &client,
                    &format!("{base}/v1/scans/{scan_id}/simulations"),
                    request.clone(),
                    "application/json",
                )?;
                ids.push(
                    job["job_id"]
                        .as_str()
                        .ok_or_else(|| Error::External(format!("submission answered {job}")))?
                        .to_string(),
                );
            }
            let outcome = wait_all_done(&client, &base, &ids, started);
            for w in workers {
                w.stop();
            }
            walls[k].push(outcome?);
        }
    }
    drop(server);
    Ok(WORKER_COUNTS
        .iter()
        .zip(walls)
        .map(|(&workers, walls)| {
            let wall = TimeStats::new(&walls);
            WorkerThroughput {
                workers,
                jobs,
                jobs_per_min: jobs as f64 * 60.0 / wall.median_s,
                rounds_jobs_per_min: walls.iter().map(|w| jobs as f64 * 60.0 / w).collect(),
                wall,
            }
        })
        .collect())
}

/// POSTs `body`; the JSON answer of a 2xx, else an error with it.
fn post_json(
    client: &reqwest::blocking::Client,
    url: &str,
    body: Vec<u8>,
    content_type: &str,
) -> Result<serde_json::Value> {
    let response = client
        .post(url)
        .header(reqwest::header::CONTENT_TYPE, content_type)
        .body(body)
        .send()
        .map_err(|e| Error::External(format!("POST {url}: {e}")))?;
    let status = response.status();
    let text = response
        .text()
        .map_err(|e| Error::External(format!("POST {url}: {e}")))?;
    if !status.is_success() {
        return Err(Error::External(format!("POST {url}: {status}: {text}")));
    }
    serde_json::from_str(&text).map_err(|e| Error::External(format!("POST {url}: {e}: {text}")))
}

/// Waits until every job in `ids` is `done`; the seconds since `started` when the last was
/// seen so. A job ending otherwise is an error naming it.
fn wait_all_done(
    client: &reqwest::blocking::Client,
    base: &str,
    ids: &[String],
    started: Instant,
) -> Result<f64> {
    let mut left: Vec<&String> = ids.iter().collect();
    while !left.is_empty() {
        if started.elapsed() > ROUND_TIMEOUT {
            return Err(Error::External(format!(
                "{} jobs not done after {} s",
                left.len(),
                ROUND_TIMEOUT.as_secs()
            )));
        }
        let mut still = Vec::new();
        for id in left {
            let url = format!("{base}/v1/jobs/{id}");
            let status: serde_json::Value = client
                .get(&url)
                .send()
                .and_then(|r| r.json())
                .map_err(|e| Error::External(format!("GET {url}: {e}")))?;
            match status["state"].as_str() {
                Some("done") => {}
                Some("failed") | Some("cancelled") => {
                    return Err(Error::External(format!("job {id} ended: {status}")))
                }
                _ => still.push(id),
            }
        }
        left = still;
        if !left.is_empty() {
            std::thread::sleep(Duration::from_millis(DONE_POLL_MS));
        }
    }
    Ok(started.elapsed().as_secs_f64())
}

//! HTTP service benchmark (issue 5): upload throughput of a 300-slice DICOM zip, the service's
//! overhead against the CLI for the same job, and requests per second over loopback.
//!
//! One in-process server ([`crate::service::start`], 127.0.0.1:0, one worker, a temporary data
//! directory, `[run]` defaults with 8 mm elements) and one client runtime (tokio + reqwest,
//! one keep-alive client) in the same process: **client and server share the machine's
//! cores**, so every rate here is a lower bound of what a dedicated server would do.
//!
//! * **Upload**: the bundled phantom CT (`sample-volumes/phantom-ct.nii.gz`, 76 × 56 × 68 at
//!   5 mm) upsampled by trilinear interpolation to 300 slices of 512 × 512 (quick: 256 × 256)
//!   keeping its physical extent, written as a CT series (int16, Explicit VR Little Endian,
//!   512 KiB per 512² slice) and zipped Stored (as PACS exports usually are) and Deflated. Each
//!   zip is streamed from its file to `POST /v1/scans`. Three times are taken per upload: until
//!   the client hands over the body's last byte (`body_sent`; up to the TCP send + receive
//!   buffer maxima may still be in flight then), until the 201 (`to_201`, which includes
//!   ingest), and the difference (`after_body`: the rest of the receive + load + ingest +
//!   store). `load_ct` on the same zip in-process and the ingest timings of the 201 body split
//!   `after_body` into parsing, segmentation, meshing and a rest; body sent + rest bounds the
//!   receive time from above. Median of 3 (quick: 1).
//! * **Overhead**: the phantom NIfTI and a generated trace (two Lujan breaths of 500 mL,
//!   8 s at 25 Hz; default 10 phases) run (a) in-process by `run_breathing` (the CLI's work)
//!   and (b) through the service: POST the simulation → poll `GET /v1/jobs/{id}` every 20 ms
//!   → GET the frame list and every frame's displacement field. Rounds interleave (a) and (b),
//!   alternating which goes first; medians, ratio and absolute difference.
//! * **Load**: a built-in load tool, C = 16 concurrent tasks on one keep-alive client for
//!   5 s (quick: 1.5 s) after a 0.2 s warm-up, on `GET /v1/jobs/{id}` of a done job and on
//!   `GET /v1/jobs/{id}/frames/0/displacement` (the whole body read): requests per second,
//!   latency percentiles, MiB/s, errors. When `wrk` is on PATH it is run on the same URLs
//!   (2 threads, 16 connections) and reported beside ours.
//!
//! * **POPI** (issue 13, target 6): serving at clinical scale, the POPI CT (512 × 512 × 141)
//!   uploaded as a stored zip, three 10-phase jobs at the run's default element size: fields
//!   written per second after the solves (the jobs' `timings_s.frame_files`) and the load above
//!   on its `frames/0/displacement` (see [`popi`]); quick: one job, the short load. Skipped
//!   without the shared data.
//!
//! * **Queue** (issue 17): the PostgreSQL queue's own calls per job (claim, heartbeat,
//!   completion; medians) and jobs per minute with 1, 2 and 4 workers on short jobs, side by
//!   side in one run, on a PostgreSQL server of the benchmark's own (see [`queue`]).
//!
//! Nothing here asserts a speed; failures of one part are recorded and the others still run.

mod load;
mod overhead;
mod popi;
pub mod queue;
mod report;
mod upload;

use std::net::SocketAddr;
use std::path::PathBuf;

use serde::Serialize;
use serde_json::Value;

use super::{cpu_model, utc_now, Outcome, TimeStats};
use crate::datasets::popi_chest_ct;
use crate::process::{load_average, peak_rss_bytes};
use crate::run::RunConfig;
use crate::service::{start, ServerHandle, ServiceConfig};
use crate::{Error, IoContext, IoOp, Result};
use load::wrk_load;
pub use popi::PopiServing;

/// Slices of the uploaded DICOM series (the 300).
pub const UPLOAD_SLICES: usize = 300;
/// Rows and columns of each uploaded slice (a clinical CT).
pub const FULL_SLICE_PIXELS: usize = 512;
/// Rows and columns of each uploaded slice in quick mode.
pub const QUICK_SLICE_PIXELS: usize = 256;
/// Element edge of the server's `[run]` defaults in this benchmark, mm.
pub const BENCH_ELEMENT_SIZE_MM: f64 = 8.0;
/// Length of the generated trace, s (two 4 s breaths, so phases have a full cycle).
pub const TRACE_DURATION_S: f64 = 8.0;
/// Sampling rate of the generated trace, Hz.
pub const TRACE_RATE_HZ: f64 = 25.0;
/// Interval between two status polls of a running job, ms.
pub const POLL_INTERVAL_MS: u64 = 20;
/// Concurrent tasks of the load tool.
pub const LOAD_CONCURRENCY: usize = 16;
/// Timed load per endpoint, s.
pub const LOAD_DURATION_S: f64 = 5.0;
/// Timed load per endpoint in quick mode, s.
pub const QUICK_LOAD_DURATION_S: f64 = 1.5;
/// Untimed load before each timed one, s (connections opened, caches warm).
pub const LOAD_WARMUP_S: f64 = 0.2;
/// Threads of `wrk` (one per core of the 2-core machine).
pub const WRK_THREADS: usize = 2;

const MIB: f64 = 1024.0 * 1024.0;

/// What to run.
#[derive(Debug, Clone, Serialize)]
pub struct ServiceBenchOptions {
    /// 256 × 256 slices, one repeat, 1.5 s of load: a smoke test of the harness.
    pub quick: bool,
}

impl ServiceBenchOptions {
    fn repeats(&self) -> usize {
        if self.quick {
            1
        } else {
            3
        }
    }

    fn slice_pixels(&self) -> usize {
        if self.quick {
            QUICK_SLICE_PIXELS
        } else {
            FULL_SLICE_PIXELS
        }
    }

    fn load_duration_s(&self) -> f64 {
        if self.quick {
            QUICK_LOAD_DURATION_S
        } else {
            LOAD_DURATION_S
        }
    }
}

/// Upload of one DICOM zip to `POST /v1/scans`.
#[derive(Debug, Clone, Serialize)]
pub struct DicomZipUpload {
    /// Zip entry compression: `stored` or `deflated`.
    pub compression: String,
    /// Slices written (files in the zip).
    pub slices: usize,
    /// Rows × columns of each slice.
    pub slice_pixels: [usize; 2],
    /// Voxel spacing of the series, mm (i, j, slice).
    pub spacing_mm: [f64; 3],
    /// Sum of the DICOM files' sizes, bytes.
    pub dicom_bytes: u64,
    /// Size of the zip, bytes.
    pub zip_bytes: u64,
    /// Writing the zip from the series files, s.
    pub zip_write_s: f64,
    /// From the request's start until the client's body stream was exhausted.
    pub body_sent: TimeStats,
    /// From the request's start until the 201 (transfer + load + ingest + store).
    pub to_201: TimeStats,
    /// From the body's end until the 201 (the server's work after receiving).
    pub after_body: TimeStats,
    /// Zip MiB over the median `body_sent`.
    pub transfer_mib_per_s: f64,
    /// Zip MiB over the median `to_201`.
    pub end_to_end_mib_per_s: f64,
    /// Zip MiB over (median `body_sent` + `server_rest_s` when positive): a lower bound of the
    /// receive rate, since the last bytes of the body may still sit in loopback socket
    /// buffers when the client hands them over (see `socket_buffer_max_bytes`).
    pub transfer_lower_bound_mib_per_s: f64,
    /// `load_ct` on the same zip, in-process (unzip + DICOM parse + volume).
    pub load_ct_in_process: TimeStats,
    /// Segmentation as the server's 201 reports it (median), s.
    pub server_segmentation_s: f64,
    /// Voxel grid, mesh and groups as the server's 201 reports it (median), s.
    pub server_model_s: f64,
    /// Median `after_body` − median `load_ct` − segmentation − model: the server's own
    /// overhead (moving the upload into the store, records, response), s; may be slightly
    /// negative within noise.
    pub server_rest_s: f64,
    /// Slices the server read (`ingest.source.series.slice_count`).
    pub server_slice_count: usize,
    /// Elements of the model the server built.
    pub elements: usize,
    /// Lung volume the server found, mL.
    pub lung_volume_ml: f64,
}

/// The same breathing job in-process and through the service.
#[derive(Debug, Clone, Serialize)]
pub struct ServiceOverhead {
    /// CT of the job (file name).
    pub ct: String,
    /// Element edge, mm.
    pub element_size_mm: f64,
    /// Displacement fields of the job.
    pub frames: usize,
    /// Bytes of all frames' fields fetched per service run.
    pub field_bytes: u64,
    /// Upload + ingest of the phantom NIfTI (once, before the rounds; not in `service`), s.
    pub nifti_upload_s: f64,
    /// (a) `run_breathing` in-process: the CLI's work.
    pub cli: TimeStats,
    /// (b) submit → done (polled) → every field fetched.
    pub service: TimeStats,
    /// Part of (b) until the poll saw `done`.
    pub service_until_done: TimeStats,
    /// Part of (b) fetching the frame list and every field.
    pub service_fetch: TimeStats,
    /// Status polls of the last service round.
    pub polls_last_round: usize,
    /// Median (b) over median (a).
    pub ratio: f64,
    /// Median (b) − median (a), s.
    pub overhead_s: f64,
    /// Whether every fetched field was byte-identical to the in-process run's file.
    pub fields_identical_to_cli: bool,
}

/// Requests against one URL for a fixed time.
#[derive(Debug, Clone, Serialize)]
pub struct LoadResult {
    /// The route, with placeholders.
    pub endpoint: String,
    /// `built-in` (tokio + reqwest) or `wrk`.
    pub tool: String,
    /// Concurrent requests (tasks or connections).
    pub concurrency: usize,
    /// Timed duration, s.
    pub duration_s: f64,
    /// Successful requests.
    pub requests: u64,
    /// Failed requests (transport errors and non-2xx).
    pub errors: u64,
    /// Successful requests per second.
    pub requests_per_s: f64,
    /// Median latency, ms.
    pub latency_p50_ms: f64,
    /// 99th percentile latency, ms.
    pub latency_p99_ms: f64,
    /// Slowest request, ms (not reported by wrk's percentile table: its max).
    pub latency_max_ms: f64,
    /// Response bodies received, MiB/s (wrk: its Transfer/sec, headers included).
    pub mib_per_s: f64,
    /// Body bytes of one response.
    pub body_bytes: u64,
}

/// Everything [`run_service_bench`] measured.
#[derive(Debug, Clone, Serialize)]
pub struct ServiceBenchReport {
    /// Options of the run.
    pub options: ServiceBenchOptions,
    /// Logical cores, shared by the client and the server.
    pub cores: usize,
    /// CPU model.
    pub cpu_model: String,
    /// UTC date of the run.
    pub date_utc: String,
    /// 1-, 5- and 15-minute load averages at the start.
    pub load_average_at_start: Option<[f64; 3]>,
    /// Crate version.
    pub lungmotion_version: String,
    /// Workers of the server.
    pub server_workers: usize,
    /// Largest TCP send plus receive buffer (`net.ipv4.tcp_wmem` + `tcp_rmem` maxima): how
    /// much of an upload can be in flight when the client has handed over its last byte.
    pub socket_buffer_max_bytes: Option<u64>,
    /// DICOM zip uploads (stored, deflated).
    pub uploads: Vec<Outcome<DicomZipUpload>>,
    /// Service against the CLI.
    pub overhead: Outcome<ServiceOverhead>,
    /// Built-in load tool, per endpoint.
    pub load: Vec<Outcome<LoadResult>>,
    /// wrk on the same endpoints (skipped when absent).
    pub wrk: Vec<Outcome<LoadResult>>,
    /// The POPI CT through the service: fields written per second, requests per second.
    pub popi: Outcome<PopiServing>,
    /// The PostgreSQL queue: its calls per job, and jobs per minute with 1, 2 and 4 workers.
    pub queue: queue::QueueBenchReport,
    /// Peak resident memory of the process (client + server) at the end, bytes.
    pub peak_rss_bytes: Option<u64>,
}

/// Removes the benchmark's temporary directory however the run ends.
struct WorkDir(PathBuf);

impl Drop for WorkDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The server under test and the client talking to it.
struct Bench {
    base_url: String,
    client: reqwest::Client,
    runtime: tokio::runtime::Runtime,
    work: PathBuf,
    run_config: RunConfig,
}

/// Runs the service benchmark; see the module documentation.
pub fn run_service_bench(options: &ServiceBenchOptions) -> Result<ServiceBenchReport> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let load_average_at_start = load_average();
    let unique = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    let work = WorkDir(std::env::temp_dir().join(format!(
        "lungmotion-bench-service-{}-{unique}",
        std::process::id()
    )));
    std::fs::create_dir_all(&work.0).at(IoOp::CreateDir, &work.0)?;
    let run_config = RunConfig {
        element_size_mm: BENCH_ELEMENT_SIZE_MM,
        ..RunConfig::default()
    };
    let config = ServiceConfig {
        listen: SocketAddr::from(([127, 0, 0, 1], 0)),
        data_dir: work.0.join("data"),
        workers: 1,
        run: run_config.clone(),
        ..ServiceConfig::default()
    };
    let server_workers = config.workers;
    let server: ServerHandle = start(config)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(cores.max(1))
        .enable_all()
        .thread_name("bench-client")
        .build()
        .map_err(|e| Error::External(format!("the benchmark client's runtime: {e}")))?;
    let client = reqwest::Client::builder()
        .no_proxy()
        .pool_max_idle_per_host(LOAD_CONCURRENCY * 2)
        .build()
        .map_err(|e| Error::External(format!("HTTP client: {e}")))?;
    let bench = Bench {
        base_url: server.base_url.clone(),
        client,
        runtime,
        work: work.0.clone(),
        run_config,
    };

    let repeats = options.repeats();
    let overhead = bench.overhead(repeats);
    let (load, wrk) = match &overhead {
        Ok((_, job_id)) => {
            let duration = options.load_duration_s();
            let targets = [
                (
                    "GET /v1/jobs/{id}",
                    format!("{}/v1/jobs/{job_id}", bench.base_url),
                ),
                (
                    "GET /v1/jobs/{id}/frames/0/displacement",
                    format!("{}/v1/jobs/{job_id}/frames/0/displacement", bench.base_url),
                ),
            ];
            let load = targets
                .iter()
                .map(|(route, url)| Outcome::from_result(bench.load(route, url, duration)))
                .collect();
            let wrk = targets
                .iter()
                .map(|(route, url)| wrk_load(route, url, duration))
                .collect();
            (load, wrk)
        }
        Err(e) => {
            let why = format!("no done job to load: {e}");
            (
                vec![Outcome::Skipped(why.clone())],
                vec![Outcome::Skipped(why)],
            )
        }
    };
    let popi = match popi_chest_ct() {
        None => Outcome::Skipped("shared data not found (set LUNGMOTION_SHARED_DATA)".into()),
        Some(dir) => {
            Outcome::from_result(bench.popi_serving(dir, repeats, options.load_duration_s()))
        }
    };
    let uploads = match bench.uploads(options.slice_pixels(), repeats) {
        Ok(u) => u,
        Err(e) => vec![Outcome::Failed(e.to_string())],
    };
    let overhead = match overhead {
        Ok((o, _)) => Outcome::Measured(o),
        Err(e) => Outcome::Failed(e.to_string()),
    };
    drop(bench);
    server.shutdown()?;
    let queue = queue::run_queue_bench(&work.0, options.quick);
    let peak_rss_bytes = peak_rss_bytes();
    drop(work);
    Ok(ServiceBenchReport {
        options: options.clone(),
        cores,
        cpu_model: cpu_model(),
        date_utc: utc_now(),
        load_average_at_start,
        lungmotion_version: env!("CARGO_PKG_VERSION").into(),
        server_workers,
        socket_buffer_max_bytes: socket_buffer_max_bytes(),
        uploads,
        overhead,
        load,
        wrk,
        popi,
        queue,
        peak_rss_bytes,
    })
}

/// An HTTP failure as an error naming the request.
fn http_error(what: &str, e: impl std::fmt::Display) -> Error {
    Error::External(format!("{what}: {e}"))
}

/// The response's JSON body if its status is `expected`, else an error with the body.
async fn expect_json(
    what: &str,
    response: reqwest::Response,
    expected: reqwest::StatusCode,
) -> Result<Value> {
    let status = response.status();
    let text = response.text().await.map_err(|e| http_error(what, e))?;
    if status != expected {
        return Err(http_error(
            what,
            format!("expected {expected}, got {status}: {text}"),
        ));
    }
    serde_json::from_str(&text).map_err(|e| http_error(what, format!("response body: {e}")))
}

/// Largest TCP send buffer plus largest receive buffer, bytes (the third field of each sysctl).
fn socket_buffer_max_bytes() -> Option<u64> {
    let max = |name: &str| -> Option<u64> {
        std::fs::read_to_string(format!("/proc/sys/net/ipv4/{name}"))
            .ok()?
            .split_whitespace()
            .nth(2)?
            .parse()
            .ok()
    };
    Some(max("tcp_wmem")? + max("tcp_rmem")?)
}

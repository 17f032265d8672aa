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
//! Nothing here asserts a speed; failures of one part are recorded and the others still run.

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use serde::Serialize;
use serde_json::Value;

use super::ingest::upsample_trilinear;
use super::{cpu_model, utc_now, Outcome, TimeStats};
use crate::breathing::LujanBreathing;
use crate::formats::dicom::{write_ct_series, CtSeriesMetadata};
use crate::ingest::scan::load_ct;
use crate::process::{load_average, peak_rss_bytes};
use crate::run::demo::sample_volumes_dir;
use crate::run::{run_breathing, RunConfig, RunInputs, SilentObserver};
use crate::service::{start, ServerHandle, ServiceConfig};
use crate::{Error, Result};

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
    std::fs::create_dir_all(&work.0)?;
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
        .build()?;
    let client = reqwest::Client::builder()
        .no_proxy()
        .pool_max_idle_per_host(LOAD_CONCURRENCY * 2)
        .build()
        .map_err(|e| Error::InvalidInput(format!("HTTP client: {e}")))?;
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
    let uploads = match bench.uploads(options.slice_pixels(), repeats) {
        Ok(u) => u,
        Err(e) => vec![Outcome::Failed(e.to_string())],
    };
    let overhead = match overhead {
        Ok((o, _)) => Outcome::Measured(o),
        Err(e) => Outcome::Failed(e.to_string()),
    };
    let peak_rss_bytes = peak_rss_bytes();
    drop(bench);
    server.shutdown()?;
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
        peak_rss_bytes,
    })
}

/// An HTTP failure as an error naming the request.
fn http_error(what: &str, e: impl std::fmt::Display) -> Error {
    Error::InvalidInput(format!("{what}: {e}"))
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

/// Timings of one streamed upload.
struct UploadTiming {
    body_sent_s: f64,
    to_201_s: f64,
    scan: Value,
}

impl Bench {
    /// Streams `path` to `POST /v1/scans` and waits for the 201.
    async fn upload(&self, path: &Path, content_type: &str) -> Result<UploadTiming> {
        let what = format!("POST /v1/scans ({})", path.display());
        let len = std::fs::metadata(path)?.len();
        let file = tokio::fs::File::open(path).await?;
        let body_end: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
        let mark = body_end.clone();
        let mut handed_over = 0u64;
        // hyper stops polling a body once Content-Length bytes are out, so the end of the body
        // is the instant its last chunk is handed over, not the end of the stream.
        let stream =
            tokio_util::io::ReaderStream::with_capacity(file, 1 << 18).inspect(move |chunk| {
                if let Ok(c) = chunk {
                    handed_over += c.len() as u64;
                    if handed_over >= len {
                        if let Ok(mut m) = mark.lock() {
                            *m = Some(Instant::now());
                        }
                    }
                }
            });
        let start = Instant::now();
        let response = self
            .client
            .post(format!("{}/v1/scans", self.base_url))
            .header(reqwest::header::CONTENT_TYPE, content_type)
            .header(reqwest::header::CONTENT_LENGTH, len)
            .body(reqwest::Body::wrap_stream(stream))
            .send()
            .await
            .map_err(|e| http_error(&what, e))?;
        let scan = expect_json(&what, response, reqwest::StatusCode::CREATED).await?;
        let to_201_s = start.elapsed().as_secs_f64();
        let body_sent_s = body_end
            .lock()
            .ok()
            .and_then(|m| *m)
            .ok_or_else(|| http_error(&what, "the end of the request body was not observed"))?
            .duration_since(start)
            .as_secs_f64();
        Ok(UploadTiming {
            body_sent_s,
            to_201_s,
            scan,
        })
    }

    /// Deletes a stored scan (204 expected).
    async fn delete_scan(&self, scan_id: &str) -> Result<()> {
        let what = format!("DELETE /v1/scans/{scan_id}");
        let response = self
            .client
            .delete(format!("{}/v1/scans/{scan_id}", self.base_url))
            .send()
            .await
            .map_err(|e| http_error(&what, e))?;
        if response.status() != reqwest::StatusCode::NO_CONTENT {
            let status = response.status();
            let text = response.text().await.unwrap_or_default();
            return Err(http_error(
                &what,
                format!("expected 204, got {status}: {text}"),
            ));
        }
        Ok(())
    }

    /// Writes the 300-slice series, zips it stored and deflated, uploads each `repeats` times.
    fn uploads(&self, pixels: usize, repeats: usize) -> Result<Vec<Outcome<DicomZipUpload>>> {
        let phantom = load_ct(&sample_volumes_dir().join("phantom-ct.nii.gz"))?.ct;
        let ct = upsample_trilinear(&phantom, [pixels, pixels, UPLOAD_SLICES])?;
        drop(phantom);
        let spacing_mm = ct.geometry.spacing_mm;
        let series_dir = self.work.join("series");
        let meta = CtSeriesMetadata {
            uid_seed: 5,
            series_description: format!(
                "lungmotion phantom upsampled to {pixels}x{pixels}x{UPLOAD_SLICES}"
            ),
            ..CtSeriesMetadata::default()
        };
        let files = write_ct_series(&ct, &series_dir, &meta)?;
        drop(ct);
        let mut dicom_bytes = 0u64;
        for f in &files {
            dicom_bytes += std::fs::metadata(f)?.len();
        }
        let mut out = Vec::new();
        for (name, method) in [
            ("stored", zip::CompressionMethod::Stored),
            ("deflated", zip::CompressionMethod::Deflated),
        ] {
            let zip_path = self.work.join(format!("series-{name}.zip"));
            let t = Instant::now();
            let written = write_zip(&files, &zip_path, method);
            let zip_write_s = t.elapsed().as_secs_f64();
            let measured = written.and_then(|zip_bytes| {
                let rounds = self.upload_rounds(&zip_path, repeats);
                let _ = std::fs::remove_file(&zip_path);
                let r = rounds?;
                let zip_mib = zip_bytes as f64 / MIB;
                let server_rest_s = r.after_body.median_s
                    - r.load_ct_in_process.median_s
                    - r.server_segmentation_s
                    - r.server_model_s;
                Ok(DicomZipUpload {
                    compression: name.into(),
                    slices: files.len(),
                    slice_pixels: [pixels, pixels],
                    spacing_mm,
                    dicom_bytes,
                    zip_bytes,
                    zip_write_s,
                    transfer_mib_per_s: zip_mib / r.body_sent.median_s,
                    end_to_end_mib_per_s: zip_mib / r.to_201.median_s,
                    transfer_lower_bound_mib_per_s: zip_mib
                        / (r.body_sent.median_s + server_rest_s.max(0.0)),
                    server_rest_s,
                    body_sent: r.body_sent,
                    to_201: r.to_201,
                    after_body: r.after_body,
                    load_ct_in_process: r.load_ct_in_process,
                    server_segmentation_s: r.server_segmentation_s,
                    server_model_s: r.server_model_s,
                    server_slice_count: r.server_slice_count,
                    elements: r.elements,
                    lung_volume_ml: r.lung_volume_ml,
                })
            });
            out.push(Outcome::from_result(measured));
        }
        let _ = std::fs::remove_dir_all(&series_dir);
        Ok(out)
    }

    /// Upload rounds of one zip, each followed by `load_ct` of the same zip in-process.
    fn upload_rounds(&self, zip_path: &Path, repeats: usize) -> Result<UploadRounds> {
        let mut body_sent = Vec::with_capacity(repeats);
        let mut to_201 = Vec::with_capacity(repeats);
        let mut after_body = Vec::with_capacity(repeats);
        let mut load_s = Vec::with_capacity(repeats);
        let mut segmentation_s = Vec::with_capacity(repeats);
        let mut model_s = Vec::with_capacity(repeats);
        let mut last_scan = Value::Null;
        for _ in 0..repeats {
            let timing = self.runtime.block_on(async {
                let timing = self.upload(zip_path, "application/zip").await?;
                let id = timing.scan["scan_id"]
                    .as_str()
                    .ok_or_else(|| http_error("POST /v1/scans", "no scan_id in the 201"))?
                    .to_string();
                self.delete_scan(&id).await?;
                Ok::<_, Error>(timing)
            })?;
            body_sent.push(timing.body_sent_s);
            to_201.push(timing.to_201_s);
            after_body.push(timing.to_201_s - timing.body_sent_s);
            let timings = &timing.scan["ingest"]["timings_s"];
            segmentation_s.push(timings["segmentation"].as_f64().unwrap_or(f64::NAN));
            model_s.push(timings["model"].as_f64().unwrap_or(f64::NAN));
            last_scan = timing.scan;
            let t = Instant::now();
            let scan = load_ct(zip_path)?;
            load_s.push(t.elapsed().as_secs_f64());
            drop(scan);
        }
        let median = |v: &[f64]| TimeStats::new(v).median_s;
        let ingest = &last_scan["ingest"];
        Ok(UploadRounds {
            body_sent: TimeStats::new(&body_sent),
            to_201: TimeStats::new(&to_201),
            after_body: TimeStats::new(&after_body),
            load_ct_in_process: TimeStats::new(&load_s),
            server_segmentation_s: median(&segmentation_s),
            server_model_s: median(&model_s),
            server_slice_count: ingest["source"]["series"]["slice_count"]
                .as_u64()
                .unwrap_or(0) as usize,
            elements: ingest["elements"].as_u64().unwrap_or(0) as usize,
            lung_volume_ml: ingest["lung_volume_ml"].as_f64().unwrap_or(f64::NAN),
        })
    }

    /// Interleaved rounds of the same job in-process and through the service; returns the
    /// measurement and the id of a done job for the load runs.
    fn overhead(&self, rounds: usize) -> Result<(ServiceOverhead, String)> {
        let ct_path = sample_volumes_dir().join("phantom-ct.nii.gz");
        let curve = LujanBreathing::default();
        let trace = curve.trace(TRACE_DURATION_S, TRACE_RATE_HZ)?;
        let inputs = RunInputs {
            ct_path: ct_path.clone(),
            trace: trace.clone(),
            trace_source: "generated: Lujan breathing (service benchmark)".into(),
            points: Vec::new(),
        };
        let request = serde_json::json!({
            "trace": {"time_s": trace.time_s, "volume_ml": trace.volume_change_ml}
        });
        let request = serde_json::to_vec(&request)
            .map_err(|e| Error::InvalidInput(format!("simulation request: {e}")))?;
        let (scan_id, nifti_upload_s) = self.runtime.block_on(async {
            let t = self.upload(&ct_path, "application/gzip").await?;
            let id = t.scan["scan_id"]
                .as_str()
                .ok_or_else(|| http_error("POST /v1/scans", "no scan_id in the 201"))?
                .to_string();
            Ok::<_, Error>((id, t.to_201_s))
        })?;

        let mut cli = Vec::with_capacity(rounds);
        let mut service = Vec::with_capacity(rounds);
        let mut until_done = Vec::with_capacity(rounds);
        let mut fetch = Vec::with_capacity(rounds);
        let mut reference_fields: Vec<Vec<u8>> = Vec::new();
        let mut identical = true;
        let mut last_job = String::new();
        let mut polls_last_round = 0;
        let mut field_bytes = 0;
        for round in 0..rounds {
            let run_cli = |cli: &mut Vec<f64>, reference: &mut Vec<Vec<u8>>| -> Result<()> {
                let out = self.work.join(format!("cli-{round}"));
                let t = Instant::now();
                let summary = run_breathing(&inputs, &self.run_config, &out, &mut SilentObserver)?;
                cli.push(t.elapsed().as_secs_f64());
                if reference.is_empty() {
                    for k in 0..summary.frames.len() {
                        let path = out
                            .join("frames")
                            .join(k.to_string())
                            .join("displacement.nii.gz");
                        reference.push(std::fs::read(&path)?);
                    }
                }
                let _ = std::fs::remove_dir_all(&out);
                Ok(())
            };
            if round % 2 == 0 {
                run_cli(&mut cli, &mut reference_fields)?;
            }
            let job = self
                .runtime
                .block_on(self.service_job(&scan_id, &request))?;
            service.push(job.until_done_s + job.fetch_s);
            until_done.push(job.until_done_s);
            fetch.push(job.fetch_s);
            if round % 2 == 1 {
                run_cli(&mut cli, &mut reference_fields)?;
            }
            identical &= job.fields == reference_fields;
            field_bytes = job.fields.iter().map(|f| f.len() as u64).sum();
            polls_last_round = job.polls;
            last_job = job.job_id;
        }
        let cli = TimeStats::new(&cli);
        let service = TimeStats::new(&service);
        Ok((
            ServiceOverhead {
                ct: "sample-volumes/phantom-ct.nii.gz".into(),
                element_size_mm: self.run_config.element_size_mm,
                frames: reference_fields.len(),
                field_bytes,
                nifti_upload_s,
                ratio: service.median_s / cli.median_s,
                overhead_s: service.median_s - cli.median_s,
                cli,
                service,
                service_until_done: TimeStats::new(&until_done),
                service_fetch: TimeStats::new(&fetch),
                polls_last_round,
                fields_identical_to_cli: identical,
            },
            last_job,
        ))
    }

    /// Submits the job, polls it to the end and fetches every frame's field.
    async fn service_job(&self, scan_id: &str, request: &[u8]) -> Result<ServiceJob> {
        let what = format!("POST /v1/scans/{scan_id}/simulations");
        let start = Instant::now();
        let response = self
            .client
            .post(format!("{}/v1/scans/{scan_id}/simulations", self.base_url))
            .header(reqwest::header::CONTENT_TYPE, "application/json")
            .body(request.to_vec())
            .send()
            .await
            .map_err(|e| http_error(&what, e))?;
        let status = expect_json(&what, response, reqwest::StatusCode::ACCEPTED).await?;
        let job_id = status["job_id"]
            .as_str()
            .ok_or_else(|| http_error(&what, "no job_id in the 202"))?
            .to_string();
        let job_url = format!("{}/v1/jobs/{job_id}", self.base_url);
        let mut polls = 0;
        loop {
            tokio::time::sleep(Duration::from_millis(POLL_INTERVAL_MS)).await;
            polls += 1;
            let what = format!("GET /v1/jobs/{job_id}");
            let response = self
                .client
                .get(&job_url)
                .send()
                .await
                .map_err(|e| http_error(&what, e))?;
            let status = expect_json(&what, response, reqwest::StatusCode::OK).await?;
            match status["state"].as_str() {
                Some("done") => break,
                Some("queued") | Some("running") => {}
                other => {
                    return Err(http_error(
                        &what,
                        format!(
                            "job ended {}: {}",
                            other.unwrap_or("in an unknown state"),
                            status["error"]
                        ),
                    ))
                }
            }
        }
        let until_done_s = start.elapsed().as_secs_f64();
        let what = format!("GET /v1/jobs/{job_id}/frames");
        let response = self
            .client
            .get(format!("{job_url}/frames"))
            .send()
            .await
            .map_err(|e| http_error(&what, e))?;
        let list = expect_json(&what, response, reqwest::StatusCode::OK).await?;
        let links: Vec<String> = list["frames"]
            .as_array()
            .ok_or_else(|| http_error(&what, "no frames array"))?
            .iter()
            .map(|f| f["displacement"].as_str().unwrap_or_default().to_string())
            .collect();
        let mut fields = Vec::with_capacity(links.len());
        for link in &links {
            let what = format!("GET {link}");
            let response = self
                .client
                .get(format!("{}{link}", self.base_url))
                .send()
                .await
                .map_err(|e| http_error(&what, e))?;
            if response.status() != reqwest::StatusCode::OK {
                return Err(http_error(&what, format!("status {}", response.status())));
            }
            let body = response.bytes().await.map_err(|e| http_error(&what, e))?;
            fields.push(body.to_vec());
        }
        Ok(ServiceJob {
            job_id,
            until_done_s,
            fetch_s: start.elapsed().as_secs_f64() - until_done_s,
            polls,
            fields,
        })
    }

    /// C tasks hitting `url` for `duration_s` after a short warm-up.
    fn load(&self, route: &str, url: &str, duration_s: f64) -> Result<LoadResult> {
        self.runtime.block_on(async {
            let url: Arc<str> = Arc::from(url);
            let warm_end = Instant::now() + Duration::from_secs_f64(LOAD_WARMUP_S);
            self.load_tasks(&url, warm_end, 0).await?;
            let start = Instant::now();
            let end = start + Duration::from_secs_f64(duration_s);
            // Room for a few thousand requests per task, so the loop does not reallocate.
            let tallies = self.load_tasks(&url, end, 1 << 15).await?;
            let elapsed_s = start.elapsed().as_secs_f64();
            let mut latencies: Vec<f64> =
                Vec::with_capacity(tallies.iter().map(|t| t.latencies_s.len()).sum::<usize>());
            let (mut errors, mut bytes, mut body_bytes) = (0u64, 0u64, 0u64);
            for t in &tallies {
                latencies.extend_from_slice(&t.latencies_s);
                errors += t.errors;
                bytes += t.bytes;
                body_bytes = body_bytes.max(t.body_bytes);
            }
            latencies.sort_by(f64::total_cmp);
            let requests = latencies.len() as u64;
            Ok(LoadResult {
                endpoint: route.into(),
                tool: "built-in (tokio + reqwest, one keep-alive client)".into(),
                concurrency: LOAD_CONCURRENCY,
                duration_s: elapsed_s,
                requests,
                errors,
                requests_per_s: requests as f64 / elapsed_s,
                latency_p50_ms: percentile(&latencies, 0.50) * 1e3,
                latency_p99_ms: percentile(&latencies, 0.99) * 1e3,
                latency_max_ms: latencies.last().copied().unwrap_or(f64::NAN) * 1e3,
                mib_per_s: bytes as f64 / MIB / elapsed_s,
                body_bytes,
            })
        })
    }

    /// Runs the load tasks until `end` and collects their tallies.
    async fn load_tasks(
        &self,
        url: &Arc<str>,
        end: Instant,
        capacity: usize,
    ) -> Result<Vec<Tally>> {
        let handles: Vec<_> = (0..LOAD_CONCURRENCY)
            .map(|_| tokio::spawn(load_task(self.client.clone(), url.clone(), end, capacity)))
            .collect();
        let mut tallies = Vec::with_capacity(handles.len());
        for h in handles {
            tallies.push(h.await.map_err(|e| http_error("load task", e))?);
        }
        Ok(tallies)
    }
}

/// The measured part of [`DicomZipUpload`] (see its fields).
struct UploadRounds {
    body_sent: TimeStats,
    to_201: TimeStats,
    after_body: TimeStats,
    load_ct_in_process: TimeStats,
    server_segmentation_s: f64,
    server_model_s: f64,
    server_slice_count: usize,
    elements: usize,
    lung_volume_ml: f64,
}

/// One service run of the job.
struct ServiceJob {
    job_id: String,
    until_done_s: f64,
    fetch_s: f64,
    polls: usize,
    fields: Vec<Vec<u8>>,
}

/// What one load task saw.
struct Tally {
    latencies_s: Vec<f64>,
    errors: u64,
    bytes: u64,
    body_bytes: u64,
}

/// Requests `url` back to back until `end`, reading every body to its end without keeping it.
async fn load_task(client: reqwest::Client, url: Arc<str>, end: Instant, capacity: usize) -> Tally {
    let mut tally = Tally {
        latencies_s: Vec::with_capacity(capacity),
        errors: 0,
        bytes: 0,
        body_bytes: 0,
    };
    while Instant::now() < end {
        let t = Instant::now();
        let mut response = match client.get(&*url).send().await {
            Ok(r) => r,
            Err(_) => {
                tally.errors += 1;
                continue;
            }
        };
        let ok = response.status().is_success();
        let mut body = 0u64;
        let mut broken = false;
        loop {
            match response.chunk().await {
                Ok(Some(c)) => body += c.len() as u64,
                Ok(None) => break,
                Err(_) => {
                    broken = true;
                    break;
                }
            }
        }
        if ok && !broken {
            tally.latencies_s.push(t.elapsed().as_secs_f64());
            tally.bytes += body;
            tally.body_bytes = body;
        } else {
            tally.errors += 1;
        }
    }
    tally
}

/// Nearest-rank percentile `p` (0–1) of sorted `values`; NaN when empty.
fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (p * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

/// Zips `files` (flat, by file name) into `zip_path`; returns the zip's size.
fn write_zip(files: &[PathBuf], zip_path: &Path, method: zip::CompressionMethod) -> Result<u64> {
    let what = zip_path.display().to_string();
    let out = std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(zip_path)?);
    let mut zip = zip::ZipWriter::new(out);
    let options = zip::write::SimpleFileOptions::default().compression_method(method);
    for f in files {
        let name = f
            .file_name()
            .and_then(|n| n.to_str())
            .ok_or_else(|| Error::InvalidInput(format!("{what}: odd file name {}", f.display())))?;
        zip.start_file(name, options)
            .map_err(|e| Error::InvalidInput(format!("{what}: {e}")))?;
        let mut input = std::fs::File::open(f)?;
        std::io::copy(&mut input, &mut zip)?;
    }
    let out = zip
        .finish()
        .map_err(|e| Error::InvalidInput(format!("{what}: {e}")))?;
    drop(out);
    Ok(std::fs::metadata(zip_path)?.len())
}

/// Runs `wrk` on `url` when it is on PATH.
fn wrk_load(route: &str, url: &str, duration_s: f64) -> Outcome<LoadResult> {
    let seconds = duration_s.ceil().max(1.0) as u64;
    let output = std::process::Command::new("wrk")
        .arg(format!("-t{WRK_THREADS}"))
        .arg(format!("-c{LOAD_CONCURRENCY}"))
        .arg(format!("-d{seconds}s"))
        .arg("--latency")
        .arg(url)
        .output();
    match output {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            Outcome::Skipped("wrk is not on PATH".into())
        }
        Err(e) => Outcome::Failed(format!("wrk: {e}")),
        Ok(o) if !o.status.success() => Outcome::Failed(format!(
            "wrk exited with {}: {}",
            o.status,
            String::from_utf8_lossy(&o.stderr).trim()
        )),
        Ok(o) => match parse_wrk(&String::from_utf8_lossy(&o.stdout), route, seconds as f64) {
            Some(r) => Outcome::Measured(r),
            None => Outcome::Failed(format!(
                "wrk output not understood: {}",
                String::from_utf8_lossy(&o.stdout)
            )),
        },
    }
}

/// A wrk duration (`850.00us`, `1.20ms`, `2.00s`, `1.00m`) in seconds.
fn wrk_seconds(text: &str) -> Option<f64> {
    let split = text.find(|c: char| c.is_ascii_alphabetic())?;
    let (number, unit) = text.split_at(split);
    let v: f64 = number.parse().ok()?;
    Some(match unit {
        "us" => v * 1e-6,
        "ms" => v * 1e-3,
        "s" => v,
        "m" => v * 60.0,
        "h" => v * 3600.0,
        _ => return None,
    })
}

/// A wrk size (`1.50MB`, `12.3KB`, `800B`; binary multiples) in bytes.
fn wrk_bytes(text: &str) -> Option<f64> {
    let split = text.find(|c: char| c.is_ascii_alphabetic())?;
    let (number, unit) = text.split_at(split);
    let v: f64 = number.parse().ok()?;
    let scale = match unit {
        "B" => 1.0,
        "KB" => 1024.0,
        "MB" => MIB,
        "GB" => MIB * 1024.0,
        "TB" => MIB * MIB,
        _ => return None,
    };
    Some(v * scale)
}

/// Reads wrk's `--latency` report.
fn parse_wrk(out: &str, route: &str, duration_s: f64) -> Option<LoadResult> {
    let mut p50 = None;
    let mut p99 = None;
    let mut max = f64::NAN;
    let mut rps = None;
    let mut transfer = None;
    let mut requests = None;
    let mut errors = 0u64;
    let mut elapsed_s = duration_s;
    for line in out.lines() {
        let fields: Vec<&str> = line.split_whitespace().collect();
        match fields.as_slice() {
            ["50%", v] => p50 = wrk_seconds(v),
            ["99%", v] => p99 = wrk_seconds(v),
            ["Latency", _avg, _stdev, m, ..] => max = wrk_seconds(m).unwrap_or(f64::NAN),
            ["Requests/sec:", v] => rps = v.parse::<f64>().ok(),
            ["Transfer/sec:", v] => transfer = wrk_bytes(v),
            [n, "requests", "in", t, ..] => {
                requests = n.parse::<u64>().ok();
                if let Some(s) = wrk_seconds(t.trim_end_matches(',')) {
                    elapsed_s = s;
                }
            }
            ["Non-2xx", "or", "3xx", "responses:", n] => errors += n.parse::<u64>().unwrap_or(0),
            ["Socket", "errors:", rest @ ..] => {
                errors += rest
                    .iter()
                    .filter_map(|x| x.trim_end_matches(',').parse::<u64>().ok())
                    .sum::<u64>()
            }
            _ => {}
        }
    }
    let requests = requests?;
    Some(LoadResult {
        endpoint: route.into(),
        tool: format!("wrk -t{WRK_THREADS} -c{LOAD_CONCURRENCY}"),
        concurrency: LOAD_CONCURRENCY,
        duration_s: elapsed_s,
        requests: requests.saturating_sub(errors),
        errors,
        requests_per_s: rps?,
        latency_p50_ms: p50? * 1e3,
        latency_p99_ms: p99? * 1e3,
        latency_max_ms: max * 1e3,
        mib_per_s: transfer? / MIB,
        body_bytes: 0,
    })
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

/// First line of an error message, table-safe.
fn one_line(e: &str) -> String {
    e.lines().next().unwrap_or("").replace('|', "/")
}

impl ServiceBenchReport {
    /// The report as Markdown (tables with units).
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "# lungmotion HTTP service benchmark\n");
        let _ = writeln!(
            s,
            "{} UTC, lungmotion {}, {} ({} logical cores); load average at start {}. \
             Server in-process ({} worker, 127.0.0.1, `[run]` at {} mm); **client and server \
             share the {} cores**, so rates are lower bounds for a dedicated server.{}\n",
            self.date_utc,
            self.lungmotion_version,
            self.cpu_model,
            self.cores,
            self.load_average_at_start
                .map_or("unknown".into(), |l| format!(
                    "{:.2} / {:.2} / {:.2}",
                    l[0], l[1], l[2]
                )),
            self.server_workers,
            BENCH_ELEMENT_SIZE_MM,
            self.cores,
            if self.options.quick {
                " Quick mode: one repeat, small slices, short load (numbers indicative only)."
            } else {
                ""
            }
        );
        self.write_uploads(&mut s);
        self.write_overhead(&mut s);
        self.write_load(&mut s);
        if let Some(p) = self.peak_rss_bytes {
            let _ = writeln!(
                s,
                "\nProcess peak resident memory (VmHWM, client + server + in-process runs): {:.0} MiB.",
                p as f64 / MIB
            );
        }
        s
    }

    fn write_uploads(&self, s: &mut String) {
        let _ = writeln!(s, "## Upload of a {UPLOAD_SLICES}-slice DICOM zip\n");
        let _ = writeln!(
            s,
            "`POST /v1/scans`, body streamed from the zip file (Content-Length set). The series is \
             the phantom CT upsampled (trilinear, same extent) to {UPLOAD_SLICES} slices, int16. \
             *Body sent*: until the client handed over the body's last byte; up to {} of it \
             may then still sit in loopback socket buffers (TCP send + receive maxima), so \
             *MiB/s sent* overstates the receive rate for small zips; *to 201*: includes load + \
             segmentation + meshing + store; *after body* = to 201 − body sent. `load_ct` \
             in-process on the same zip, and the segmentation and model times the 201 reports, \
             split *after body*; *rest* is what remains (the rest of the receive, store, \
             response), so *receive MiB/s ≥* = zip / (body sent + rest) bounds the receive rate \
             from below. Median [min – max] of {} run(s).\n",
            self.socket_buffer_max_bytes
                .map_or("an unknown amount".into(), |b| format!("{:.0} MiB", b as f64 / MIB)),
            self.options.repeats()
        );
        let _ = writeln!(
            s,
            "| Zip | Slices | Slice px | Spacing mm | DICOM MiB | Zip MiB | Body sent s | MiB/s sent | Receive MiB/s ≥ | To 201 s | End-to-end MiB/s | After body s | load_ct s | Segmentation s | Model s | Rest s | Server slices | Elements |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
        );
        for u in &self.uploads {
            match u {
                Outcome::Measured(u) => {
                    let _ = writeln!(
                        s,
                        "| {} | {} | {}×{} | {:.2}×{:.2}×{:.2} | {:.1} | {:.1} | {:.2} [{:.2} – {:.2}] | {:.1} | {:.1} | {:.2} [{:.2} – {:.2}] | {:.1} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {} | {} |",
                        u.compression,
                        u.slices,
                        u.slice_pixels[0],
                        u.slice_pixels[1],
                        u.spacing_mm[0],
                        u.spacing_mm[1],
                        u.spacing_mm[2],
                        u.dicom_bytes as f64 / MIB,
                        u.zip_bytes as f64 / MIB,
                        u.body_sent.median_s,
                        u.body_sent.min_s,
                        u.body_sent.max_s,
                        u.transfer_mib_per_s,
                        u.transfer_lower_bound_mib_per_s,
                        u.to_201.median_s,
                        u.to_201.min_s,
                        u.to_201.max_s,
                        u.end_to_end_mib_per_s,
                        u.after_body.median_s,
                        u.load_ct_in_process.median_s,
                        u.server_segmentation_s,
                        u.server_model_s,
                        u.server_rest_s,
                        u.server_slice_count,
                        u.elements
                    );
                }
                Outcome::Failed(e) | Outcome::Skipped(e) => {
                    let _ = writeln!(s, "| {} |{}", one_line(e), " |".repeat(17));
                }
            }
        }
    }

    fn write_overhead(&self, s: &mut String) {
        let _ = writeln!(s, "\n## Service against the CLI, same job\n");
        match &self.overhead {
            Outcome::Measured(o) => {
                let _ = writeln!(
                    s,
                    "`{}`, generated trace (two Lujan breaths, {TRACE_DURATION_S} s at \
                     {TRACE_RATE_HZ} Hz), server defaults at {} mm, {} frames. (a) \
                     `run_breathing` in-process (the CLI's work: load, ingest, solve, write \
                     fields, quick looks, summary); (b) POST the simulation → poll \
                     `GET /v1/jobs/{{id}}` every {POLL_INTERVAL_MS} ms → GET the frame list and \
                     all {} fields ({:.1} MiB). Interleaved rounds, medians [min – max]. The \
                     scan's upload ({:.2} s) is not in (b). Fields byte-identical to the \
                     CLI's: {}.\n",
                    o.ct,
                    o.element_size_mm,
                    o.frames,
                    o.frames,
                    o.field_bytes as f64 / MIB,
                    o.nifti_upload_s,
                    if o.fields_identical_to_cli {
                        "yes"
                    } else {
                        "**no**"
                    }
                );
                let _ = writeln!(
                    s,
                    "| (a) CLI s | (b) service s | of which until done s | of which fetching s | b / a | b − a s | polls |\n|---|---|---|---|---|---|---|"
                );
                let _ = writeln!(
                    s,
                    "| {:.3} [{:.3} – {:.3}] | {:.3} [{:.3} – {:.3}] | {:.3} | {:.3} | {:.2} | {:+.3} | {} |",
                    o.cli.median_s,
                    o.cli.min_s,
                    o.cli.max_s,
                    o.service.median_s,
                    o.service.min_s,
                    o.service.max_s,
                    o.service_until_done.median_s,
                    o.service_fetch.median_s,
                    o.ratio,
                    o.overhead_s,
                    o.polls_last_round
                );
            }
            Outcome::Failed(e) | Outcome::Skipped(e) => {
                let _ = writeln!(s, "Not measured: {}", one_line(e));
            }
        }
    }

    fn write_load(&self, s: &mut String) {
        let _ = writeln!(s, "\n## Load over loopback\n");
        let _ = writeln!(
            s,
            "{LOAD_CONCURRENCY} concurrent requests for {} s after a {LOAD_WARMUP_S} s \
             warm-up, on a done job of the phantom. The load tool runs in the same process \
             and on the same {} cores as the server. wrk's MiB/s is its Transfer/sec \
             (headers included).\n",
            self.options.load_duration_s(),
            self.cores
        );
        let _ = writeln!(
            s,
            "| Endpoint | Tool | Requests | Errors | Req/s | p50 ms | p99 ms | max ms | MiB/s | Body bytes |\n|---|---|---|---|---|---|---|---|---|---|"
        );
        for o in self.load.iter().chain(&self.wrk) {
            match o {
                Outcome::Measured(l) => {
                    let _ = writeln!(
                        s,
                        "| `{}` | {} | {} | {} | {:.0} | {:.2} | {:.2} | {:.1} | {:.1} | {} |",
                        l.endpoint,
                        l.tool,
                        l.requests,
                        l.errors,
                        l.requests_per_s,
                        l.latency_p50_ms,
                        l.latency_p99_ms,
                        l.latency_max_ms,
                        l.mib_per_s,
                        if l.body_bytes > 0 {
                            l.body_bytes.to_string()
                        } else {
                            "–".into()
                        }
                    );
                }
                Outcome::Failed(e) | Outcome::Skipped(e) => {
                    let _ = writeln!(s, "| {} |{}", one_line(e), " |".repeat(9));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_use_the_nearest_rank() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), 50.0);
        assert_eq!(percentile(&v, 0.99), 99.0);
        assert_eq!(percentile(&[3.0], 0.99), 3.0);
        assert!(percentile(&[], 0.5).is_nan());
    }

    #[test]
    fn wrk_report_is_read() {
        let out = "Running 2s test @ http://127.0.0.1:1/v1/jobs/x\n  2 threads and 16 connections\n  Thread Stats   Avg      Stdev     Max   +/- Stdev\n    Latency     1.50ms  300.00us  12.00ms   90.00%\n    Req/Sec     5.00k   100.00     6.00k    70.00%\n  Latency Distribution\n     50%    1.40ms\n     75%    1.60ms\n     90%    1.90ms\n     99%    3.00ms\n  20000 requests in 2.00s, 30.00MB read\n  Non-2xx or 3xx responses: 4\nRequests/sec:  10000.00\nTransfer/sec:     15.00MB\n";
        let r = parse_wrk(out, "GET /v1/jobs/{id}", 2.0).unwrap();
        assert_eq!(r.requests, 19_996);
        assert_eq!(r.errors, 4);
        assert!((r.latency_p50_ms - 1.4).abs() < 1e-9);
        assert!((r.latency_p99_ms - 3.0).abs() < 1e-9);
        assert!((r.latency_max_ms - 12.0).abs() < 1e-9);
        assert!((r.mib_per_s - 15.0).abs() < 1e-9);
        assert!((r.requests_per_s - 10_000.0).abs() < 1e-9);
        assert!(parse_wrk("garbage", "x", 1.0).is_none());
        assert!((wrk_seconds("850.00us").unwrap() - 850e-6).abs() < 1e-15);
    }

    #[test]
    fn zip_holds_every_file_and_stored_is_not_smaller() {
        let dir = std::env::temp_dir().join(format!("lm-bench-zip-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let files: Vec<PathBuf> = (0..3)
            .map(|i| {
                let p = dir.join(format!("IMG{i}.dcm"));
                std::fs::write(&p, vec![i as u8; 4096]).unwrap();
                p
            })
            .collect();
        let stored = write_zip(&files, &dir.join("s.zip"), zip::CompressionMethod::Stored).unwrap();
        let deflated =
            write_zip(&files, &dir.join("d.zip"), zip::CompressionMethod::Deflated).unwrap();
        assert!(stored > 3 * 4096, "{stored}");
        assert!(deflated < stored, "{deflated} vs {stored}");
        let entries = crate::formats::archive::read_zip_file(
            &dir.join("d.zip"),
            &crate::formats::archive::ArchiveLimits::default(),
        )
        .unwrap();
        assert_eq!(entries.len(), 3);
        let _ = std::fs::remove_dir_all(&dir);
    }
}

//! The same breathing job in-process (the CLI's work) and through the service, interleaved.

use std::time::{Duration, Instant};

use super::{
    expect_json, http_error, Bench, ServiceOverhead, POLL_INTERVAL_MS, TRACE_DURATION_S,
    TRACE_RATE_HZ,
};
use crate::bench::TimeStats;
use crate::breathing::LujanBreathing;
use crate::run::demo::sample_volumes_dir;
use crate::run::{run_breathing, RunInputs, SilentObserver};
use crate::{Error, IoContext, IoOp, Result};

impl Bench {
    /// Interleaved rounds of the same job in-process and through the service; returns the
    /// measurement and the id of a done job for the load runs.
    pub(super) fn overhead(&self, rounds: usize) -> Result<(ServiceOverhead, String)> {
        let ct_path = sample_volumes_dir().join("phantom-ct.nii.gz");
        let curve = LujanBreathing::default();
        let trace = curve.trace(TRACE_DURATION_S, TRACE_RATE_HZ)?;
        let inputs = RunInputs {
            ct_path: ct_path.clone(),
            trace: trace.clone(),
            trace_source: "generated: Lujan breathing (service benchmark)".into(),
            points: Vec::new(),
            target: None,
        };
        let request = simulation_request(&trace, serde_json::Map::new())?;
        let (scan_id, nifti_upload_s) = self.stored_scan(&ct_path, "application/gzip")?;

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
                        reference.push(std::fs::read(&path).at(IoOp::Read, &path)?);
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

    /// Uploads `path` to `POST /v1/scans`; the scan's id and the time to its 201.
    pub(super) fn stored_scan(
        &self,
        path: &std::path::Path,
        content_type: &str,
    ) -> Result<(String, f64)> {
        self.runtime.block_on(async {
            let t = self.upload(path, content_type).await?;
            let id = t.scan["scan_id"]
                .as_str()
                .ok_or_else(|| http_error("POST /v1/scans", "no scan_id in the 201"))?
                .to_string();
            Ok((id, t.to_201_s))
        })
    }

    /// Submits the job, polls it to the end and fetches every frame's field.
    pub(super) async fn service_job(&self, scan_id: &str, request: &[u8]) -> Result<ServiceJob> {
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
}

/// One service run of the job.
pub(super) struct ServiceJob {
    pub(super) job_id: String,
    pub(super) until_done_s: f64,
    pub(super) fetch_s: f64,
    polls: usize,
    pub(super) fields: Vec<Vec<u8>>,
}

/// The body of `POST /v1/scans/{id}/simulations` for `trace`, with `options` (run settings)
/// beside it.
pub(super) fn simulation_request(
    trace: &crate::breathing::BreathingTrace,
    mut options: serde_json::Map<String, serde_json::Value>,
) -> Result<Vec<u8>> {
    options.insert(
        "trace".into(),
        serde_json::json!({"time_s": trace.time_s, "volume_ml": trace.volume_change_ml}),
    );
    serde_json::to_vec(&options).map_err(|e| Error::argument("simulation request", e.to_string()))
}

//! Serving at clinical scale (issue 13, target 6): the POPI CT (512 × 512 × 141, a real
//! patient; `../shared/data/popi-chest-ct`) uploaded as a zipped DICOM series, a 10-phase job
//! at the run's default element size, then the rate of the fields the job writes after its
//! solves (from the job's own `timings_s`) and `GET …/frames/0/displacement` requests per
//! second on that field (its lung box, about 9.7 M voxels and 5 MB gzipped).

use std::path::PathBuf;

use serde::Serialize;
use serde_json::Value;

use super::load::wrk_load;
use super::overhead::simulation_request;
use super::upload::write_zip;
use super::{expect_json, http_error, Bench, LoadResult, TRACE_DURATION_S, TRACE_RATE_HZ};
use crate::bench::{Outcome, TimeStats};
use crate::breathing::LujanBreathing;
use crate::run::RunConfig;
use crate::{IoContext, IoOp, Result};

/// The POPI job through the service and the requests for its fields.
#[derive(Debug, Clone, Serialize)]
pub struct PopiServing {
    /// DICOM files of the series.
    pub slices: usize,
    /// Size of the uploaded zip (entries stored), bytes.
    pub zip_bytes: u64,
    /// `POST /v1/scans` of the zip until its 201 (transfer, reading, segmentation, model), s.
    pub upload_to_201_s: f64,
    /// Element edge of the jobs (the run's default), mm.
    pub element_size_mm: f64,
    /// Displacement fields per job.
    pub frames: usize,
    /// Grid of each field (the lung box on the CT's voxels), voxels.
    pub field_dims: [usize; 3],
    /// Gzipped size of frame 0's field, bytes.
    pub field_bytes: u64,
    /// Submit → `done` seen by a 20 ms poll, per job.
    pub until_done: TimeStats,
    /// The jobs' key-volume solves and frame interpolation (`timings_s.motion_solve`).
    pub motion_solve: TimeStats,
    /// The jobs' writing of every frame's field after the solves (`timings_s.frame_files`:
    /// sampling on the lung box, NIfTI, gzip, file).
    pub frame_files: TimeStats,
    /// Fields written per second after the solves: frames over the median `frame_files`.
    pub fields_written_per_s: f64,
    /// Fetching the frame list and every field, one after the other, per job.
    pub fetch_all: TimeStats,
    /// Built-in load tool on `GET /v1/jobs/{id}/frames/0/displacement`.
    pub load: Outcome<LoadResult>,
    /// wrk on the same URL (skipped when absent).
    pub wrk: Outcome<LoadResult>,
}

impl Bench {
    /// Uploads the POPI series, runs `jobs` 10-phase jobs on it and loads its field for
    /// `duration_s`.
    pub(super) fn popi_serving(
        &self,
        dicom_dir: PathBuf,
        jobs: usize,
        duration_s: f64,
    ) -> Result<PopiServing> {
        let mut files: Vec<PathBuf> = std::fs::read_dir(&dicom_dir)
            .at(IoOp::List, &dicom_dir)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file())
            .collect();
        files.sort();
        let zip_path = self.work.join("popi-stored.zip");
        let zip_bytes = write_zip(&files, &zip_path, zip::CompressionMethod::Stored)?;
        let element_size_mm = RunConfig::default().element_size_mm;
        let trace = LujanBreathing::default().trace(TRACE_DURATION_S, TRACE_RATE_HZ)?;
        let mut options = serde_json::Map::new();
        options.insert("element_size_mm".into(), element_size_mm.into());
        let request = simulation_request(&trace, options)?;
        let (scan_id, upload_to_201_s) = self.stored_scan(&zip_path, "application/zip")?;
        let _ = std::fs::remove_file(&zip_path);

        let mut until_done = Vec::with_capacity(jobs);
        let mut fetch_all = Vec::with_capacity(jobs);
        let mut motion_solve = Vec::with_capacity(jobs);
        let mut frame_files = Vec::with_capacity(jobs);
        let mut last = None;
        for _ in 0..jobs.max(1) {
            let job = self
                .runtime
                .block_on(self.service_job(&scan_id, &request))?;
            let summary = self.runtime.block_on(self.job_summary(&job.job_id))?;
            let timing = |key: &str| {
                summary["timings_s"][key].as_f64().ok_or_else(|| {
                    http_error(
                        "GET /v1/jobs/{id}/summary",
                        format!("no timings_s.{key} in the job's summary"),
                    )
                })
            };
            motion_solve.push(timing("motion_solve")?);
            frame_files.push(timing("frame_files")?);
            until_done.push(job.until_done_s);
            fetch_all.push(job.fetch_s);
            last = Some((job, summary));
        }
        let (job, summary) = last.expect("at least one job ran");
        let dims = &summary["field_grid"]["geometry"]["dims"];
        let field_dims = std::array::from_fn(|a| dims[a].as_u64().unwrap_or(0) as usize);
        let url = format!(
            "{}/v1/jobs/{}/frames/0/displacement",
            self.base_url, job.job_id
        );
        let route = "GET /v1/jobs/{id}/frames/0/displacement (POPI)";
        let frame_files = TimeStats::new(&frame_files);
        Ok(PopiServing {
            slices: files.len(),
            zip_bytes,
            upload_to_201_s,
            element_size_mm,
            frames: job.fields.len(),
            field_dims,
            field_bytes: job.fields.first().map_or(0, |f| f.len() as u64),
            until_done: TimeStats::new(&until_done),
            motion_solve: TimeStats::new(&motion_solve),
            fields_written_per_s: job.fields.len() as f64 / frame_files.median_s,
            frame_files,
            fetch_all: TimeStats::new(&fetch_all),
            load: Outcome::from_result(self.load(route, &url, duration_s)),
            wrk: wrk_load(route, &url, duration_s),
        })
    }

    /// `GET /v1/jobs/{id}/summary`.
    async fn job_summary(&self, job_id: &str) -> Result<Value> {
        let what = format!("GET /v1/jobs/{job_id}/summary");
        let response = self
            .client
            .get(format!("{}/v1/jobs/{job_id}/summary", self.base_url))
            .send()
            .await
            .map_err(|e| http_error(&what, e))?;
        expect_json(&what, response, reqwest::StatusCode::OK).await
    }
}

//! Upload of the 300-slice DICOM zip (stored and deflated) to `POST /v1/scans`, timed in parts.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use futures_util::StreamExt;
use serde_json::Value;

use super::{expect_json, http_error, Bench, DicomZipUpload, MIB, UPLOAD_SLICES};
use crate::bench::ingest::upsample_trilinear;
use crate::bench::{Outcome, TimeStats};
use crate::formats::dicom::{write_ct_series, CtSeriesMetadata};
use crate::ingest::scan::load_ct;
use crate::run::demo::sample_volumes_dir;
use crate::{Error, IoContext, IoOp, Result};

/// Timings of one streamed upload.
pub(super) struct UploadTiming {
    body_sent_s: f64,
    pub(super) to_201_s: f64,
    pub(super) scan: Value,
}

impl Bench {
    /// Streams `path` to `POST /v1/scans` and waits for the 201.
    pub(super) async fn upload(&self, path: &Path, content_type: &str) -> Result<UploadTiming> {
        let what = format!("POST /v1/scans ({})", path.display());
        let len = std::fs::metadata(path).at(IoOp::Metadata, path)?.len();
        let file = tokio::fs::File::open(path).await.at(IoOp::Open, path)?;
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
    pub(super) fn uploads(
        &self,
        pixels: usize,
        repeats: usize,
    ) -> Result<Vec<Outcome<DicomZipUpload>>> {
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
            dicom_bytes += std::fs::metadata(f).at(IoOp::Metadata, f)?.len();
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

/// Zips `files` (flat, by file name) into `zip_path`; returns the zip's size.
pub(super) fn write_zip(
    files: &[PathBuf],
    zip_path: &Path,
    method: zip::CompressionMethod,
) -> Result<u64> {
    let out = std::io::BufWriter::with_capacity(
        1 << 20,
        std::fs::File::create(zip_path).at(IoOp::Create, zip_path)?,
    );
    let mut zip = zip::ZipWriter::new(out);
    let options = zip::write::SimpleFileOptions::default().compression_method(method);
    for f in files {
        let name = f
            .file_name()
            .and_then(|n| n.to_str())
            .ok_or_else(|| Error::format(zip_path, format!("odd file name {}", f.display())))?;
        zip.start_file(name, options)
            .map_err(|e| Error::format(zip_path, e.to_string()))?;
        let mut input = std::fs::File::open(f).at(IoOp::Open, f)?;
        std::io::copy(&mut input, &mut zip).at(IoOp::Write, zip_path)?;
    }
    let out = zip
        .finish()
        .map_err(|e| Error::format(zip_path, e.to_string()))?;
    drop(out);
    Ok(std::fs::metadata(zip_path)
        .at(IoOp::Metadata, zip_path)?
        .len())
}

#[cfg(test)]
mod tests {
    use super::*;

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

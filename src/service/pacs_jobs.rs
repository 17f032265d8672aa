//! A job's exchanges with the service's PACS, on its worker thread: the CT series pulled
//! (QIDO-RS, WADO-RS) and stored as the job's scan, checked as an upload is (its ingest in
//! the same isolation, held to the same limits); after the run, the DICOM outputs pushed
//! (STOW-RS). Both go through [`crate::pacs`]'s client, whose push skips the instances the
//! server already holds: the outputs' UIDs derive from the CT's, so a re-run job (a
//! restart, a client's resubmission) stores nothing twice.

use std::path::PathBuf;

use super::config::IngestIsolation;
use super::ids::ScanId;
use super::isolation::{adopt_stored_ingest, ingest_isolated, IngestLimits};
use super::pacs_settings::PacsSettings;
use super::records::Records;
use super::store::{now_rfc3339, PacsSeries, ScanRecord, Store};
use crate::pacs::{pull_series, push_with, PushReport};
use crate::run::RunConfig;
use crate::{Error, Result};

/// The file name of a pulled series in its scan directory (a directory of instances).
const PULLED_SERIES: &str = "series";
/// What the pulled series is called in the refusal of its ingest (the job's error names the
/// study, the series and the server before it).
const PULLED_SERIES_SHOWN_AS: &str = "the series";

/// What jobs need to reach the PACS and to check what they pull.
#[derive(Debug, Clone)]
pub struct PacsAccess {
    /// The server and its credentials.
    pub settings: PacsSettings,
    /// Most bytes a pulled series may bring (the service's `max_upload_mib`).
    pub max_series_bytes: u64,
    /// Where the pulled series' ingest runs (as an upload's).
    pub isolation: IngestIsolation,
    /// What that ingest may spend (as an upload's).
    pub limits: IngestLimits,
}

/// Removes a directory of `tmp/` when dropped (a pull that failed half-way).
struct TempDir(PathBuf);

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

impl PacsAccess {
    /// The PACS access of a service configured with `config` (none without `[pacs]`): the
    /// upload's size bound, isolation and limits apply to what is pulled.
    pub fn of_service(config: &super::config::ServiceConfig) -> Option<Self> {
        config.pacs.clone().map(|settings| PacsAccess {
            settings,
            max_series_bytes: config.max_upload_bytes,
            isolation: config.ingest_isolation.clone(),
            limits: IngestLimits {
                timeout: std::time::Duration::from_secs_f64(config.ingest_timeout_s),
                memory_mib: config.ingest_memory_mib,
            },
        })
    }

    /// Pulls `series` (or the study's one CT series) into the store as scan `scan_id`,
    /// ingested with `run`'s settings; the series UID pulled. A refusal of the series names
    /// the server, the study and the series.
    pub fn import_series(
        &self,
        store: &Store,
        records: &dyn Records,
        scan_id: ScanId,
        series: &PacsSeries,
        run: &RunConfig,
    ) -> Result<String> {
        let client = self.settings.client(self.max_series_bytes)?;
        let staging = TempDir(store.tmp_path("pull"));
        let dir = staging.0.join(PULLED_SERIES);
        let (series_uid, files) =
            pull_series(&client, &series.study, series.series.as_deref(), &dir)?;
        let bytes = files
            .iter()
            .filter_map(|f| std::fs::metadata(f).ok())
            .map(|m| m.len())
            .sum();
        let stored_ingest = staging.0.join("ingest.bin");
        let ingest = ingest_isolated(
            &self.isolation,
            &dir,
            run,
            self.limits,
            PULLED_SERIES_SHOWN_AS,
            Some(&stored_ingest),
        )
        .map_err(|e| {
            Error::Ingest(format!(
                "the CT series {series_uid} of study {} pulled from {}: {}",
                series.study, self.settings.root_url, e.detail
            ))
        })?;
        let record = ScanRecord {
            scan_id,
            created_at: now_rfc3339(),
            format: "dicomweb".into(),
            upload_bytes: bytes,
            file_name: PULLED_SERIES.into(),
            ingest,
            series: None,
        };
        // In the object store (when there is one) before the record makes it visible, so a
        // worker on another machine running a later job on this scan fetches it from there.
        store.put_scan_blobs(&record, &dir, Some(&stored_ingest))?;
        if let Err(e) = records.put_scan(&record, &dir) {
            let _ = store.delete_scan(scan_id);
            return Err(e);
        }
        adopt_stored_ingest(store, scan_id, &stored_ingest);
        // Marked evictable as it was stored (see `Store::put_scan_files`); evicted by the next
        // fetch or upload beyond the bound, once this job no longer needs it.
        Ok(series_uid)
    }

    /// Pushes every DICOM file under `output` (a job's output directory), skipping what the
    /// server already holds; a refusal says the run itself succeeded.
    pub fn push_outputs(&self, output: PathBuf) -> Result<PushReport> {
        let client = self.settings.client(self.max_series_bytes)?;
        push_with(&client, &[output]).map_err(|e| match e {
            Error::Pacs {
                url,
                status,
                reason,
            } => Error::Pacs {
                url,
                status,
                reason: format!(
                    "{reason} (the run succeeded and its outputs can be downloaded; pushing its \
                     DICOM outputs failed: submit the job again to push what is missing)"
                ),
            },
            other => other,
        })
    }
}

//! The service's on-disk store: one directory per scan and per job, every record a JSON file
//! replaced atomically (temporary file, fsync, rename, fsync of the directory), so a crash at
//! any instant leaves either the old or the new record, never half of one.
//!
//! Layout under the data directory:
//! * `scans/<scan_id>/scan.json` ([`ScanRecord`]) and the upload as received
//!   (`scan.nii.gz`, `scan.nii`, `scan.nrrd` or `scan.zip`), and
//!   `scans/<scan_id>/targets/<name>/` for each target uploaded to it: `target.json`
//!   ([`TargetRecord`]) and the file (with an object store, the targets are there instead,
//!   see [`super::blobs`]);
//! * `jobs/<job_id>/job.json` ([`JobRecord`]), `request.json` ([`JobRequest`]), `target/`
//!   (its copy of an uploaded target, when it follows one) and `out/`, the run's output
//!   directory in the CLI's layout, published whole when the run succeeds;
//! * `tmp/`: uploads in progress and directories being deleted, each entry named after the
//!   process writing it; emptied at start (shared by API and worker processes: only what dead
//!   processes left, see [`Store::sweep_shared_tmp`]).
//!
//! A scan, job or target directory appears by renaming a complete directory from `tmp/`, and
//! disappears by renaming it back into `tmp/` before removal, so a listing never sees half of one.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use serde::{Deserialize, Serialize};

use super::blobs::BlobStore;
use super::callbacks::CallbackDelivery;
use super::ids::{JobId, ScanId};
use super::targets::{JobTarget, TargetRecord, JOB_TARGET_DIR};
use crate::durable::{directory_bytes, sync_dir, write_durable};
use crate::run::{RunConfig, TrackedPoint};
use crate::{Error, IoContext, IoOp, Result};

/// A scan as stored: what was uploaded and what ingest found.
#[derive(Debug, Clone, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ScanRecord {
    /// Its id.
    #[schema(value_type = String)]
    pub scan_id: ScanId,
    /// When it was uploaded (RFC 3339, UTC).
    pub created_at: String,
    /// What the upload was: `nifti`, `nrrd` or `dicom-zip`.
    pub format: String,
    /// Bytes received.
    pub upload_bytes: u64,
    /// The upload's file name inside the scan directory.
    pub file_name: String,
    /// The ingest summary (the CLI's `ingest.json`).
    #[schema(value_type = Object)]
    pub ingest: serde_json::Value,
    /// The DICOM series the scan was ingested from when the upload named one (`?series=`)
    /// or the server's `[run] series` chose it: its jobs and target checks read the same one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<String>)]
    pub series: Option<crate::formats::dicom::SeriesChoice>,
}

impl ScanRecord {
    /// The series to read this scan's CT with: the one it was ingested from, else `default`.
    pub fn series_or(
        &self,
        default: Option<crate::formats::dicom::SeriesChoice>,
    ) -> Option<crate::formats::dicom::SeriesChoice> {
        self.series.clone().or(default)
    }
}

/// A scan record and the bytes its directory holds.
pub type StoredScan = (ScanRecord, u64);

/// Where a job is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    /// Waiting for a worker.
    Queued,
    /// A worker is running it.
    Running,
    /// A client cancelled it while it ran; it stops at the solver's next check (within a
    /// Newton or Krylov iteration, a frame or a stage) and becomes `cancelled`.
    Cancelling,
    /// Finished; its outputs are published.
    Done,
    /// Stopped with an error (see `error`).
    Failed,
    /// Cancelled by a client.
    Cancelled,
}

impl JobState {
    /// Whether the job will not change any more.
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobState::Done | JobState::Failed | JobState::Cancelled
        )
    }

    /// The state's name as in the API.
    pub fn name(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Cancelling => "cancelling",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    /// Every state, for metrics.
    pub const ALL: [JobState; 6] = [
        JobState::Queued,
        JobState::Running,
        JobState::Cancelling,
        JobState::Done,
        JobState::Failed,
        JobState::Cancelled,
    ];
}

/// How far a job has got.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct JobProgress {
    /// The run's current stage (`loading_scan`, `ingest`, `solving`, `writing_frames`,
    /// `finishing`), none before it starts.
    pub stage: Option<String>,
    /// What the stage does.
    pub stage_label: Option<String>,
    /// Rough fraction of the work done, 0–1.
    pub fraction: f64,
    /// Frames written so far.
    pub frames_written: usize,
    /// Frames the run will write: known when the run starts (the output instants are
    /// computed from the trace before the CT is read).
    pub frames_total: Option<usize>,
    /// Equilibria the solver has reached so far (key volumes, load steps, solved frames).
    #[serde(default)]
    pub equilibria: usize,
    /// Lung volume change of the latest equilibrium from the scanned state, mL.
    #[serde(default)]
    pub volume_change_ml: Option<f64>,
    /// Seconds since the run started.
    #[serde(default)]
    pub elapsed_s: Option<f64>,
    /// Estimated seconds left: once frames are being written, the mean time per frame so
    /// far times the frames left, plus the summary's share; none before.
    #[serde(default)]
    pub seconds_left: Option<f64>,
}

/// A job as stored (`job.json`).
#[derive(Debug, Clone, Serialize, Deserialize, utoipa::ToSchema)]
pub struct JobRecord {
    /// Its id.
    #[schema(value_type = String)]
    pub job_id: JobId,
    /// The scan it simulates.
    #[schema(value_type = String)]
    pub scan_id: ScanId,
    /// Where it is.
    pub state: JobState,
    /// How far it has got.
    pub progress: JobProgress,
    /// Why it failed or was cancelled.
    pub error: Option<String>,
    /// Runs started (a server stopping mid-run leads to another).
    pub attempts: u32,
    /// Submitted (RFC 3339, UTC).
    pub created_at: String,
    /// The last run started.
    pub started_at: Option<String>,
    /// It reached a final state.
    pub finished_at: Option<String>,
    /// Its completion callback, when the request gave a `callback_url`: `waiting` for the
    /// job to end, then `pending`, `delivered` or `failed`, with the POSTs made.
    #[serde(default)]
    pub callback: Option<CallbackDelivery>,
    /// What it takes from and gives to the service's PACS, when its CT comes from there or
    /// it pushes its outputs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pacs: Option<PacsActivity>,
}

/// A CT series on the service's PACS, as a request names it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PacsSeries {
    /// StudyInstanceUID.
    pub study: String,
    /// SeriesInstanceUID; without it, the study's one CT series (found by QIDO-RS).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub series: Option<String>,
}

/// A job's exchanges with the service's PACS.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct PacsActivity {
    /// The server's DICOMweb root.
    pub server: String,
    /// The CT series pulled (its series UID once found), when the CT comes from the PACS.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ct: Option<PacsSeries>,
    /// Whether the job pushes its DICOM outputs (virtual CT series, REGs, RTSTRUCT) when done.
    pub push: bool,
    /// Instances the push stored, once it ran.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stored: Option<usize>,
    /// Instances the push found already on the server (an earlier push of the same
    /// outputs), not sent again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub already_stored: Option<usize>,
    /// Why the push failed after a run that succeeded: the job is failed, its outputs are
    /// complete and served.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub push_error: Option<String>,
}

impl JobRecord {
    /// Whether the job's outputs are complete: it is done, or only its push to the PACS
    /// failed after the run published them.
    pub fn outputs_complete(&self) -> bool {
        self.state == JobState::Done
            || (self.state == JobState::Failed
                && self.pacs.as_ref().is_some_and(|p| p.push_error.is_some()))
    }
}

impl JobRecord {
    /// A new queued job of `scan_id` with a fresh id.
    pub fn queued(scan_id: ScanId) -> Self {
        JobRecord {
            job_id: JobId::random(),
            scan_id,
            state: JobState::Queued,
            progress: JobProgress::default(),
            error: None,
            attempts: 0,
            created_at: now_rfc3339(),
            started_at: None,
            finished_at: None,
            callback: None,
            pacs: None,
        }
    }
}

/// What a job runs (`request.json`): the merged options, the trace and the points.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct JobRequest {
    /// Options: the server's defaults with the request's merged over them.
    pub config: RunConfig,
    /// Trace times, s.
    pub time_s: Vec<f64>,
    /// Lung volume change from the scanned state, mL.
    pub volume_ml: Vec<f64>,
    /// Where the trace came from.
    pub trace_source: String,
    /// Points to track.
    pub points: Vec<StoredPoint>,
    /// Where to POST the job's outcome when it ends (checked when submitted).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub callback_url: Option<String>,
    /// The target to follow: a point as the request gave it (`point:<x>,<y>,<z>:r=<mm>`),
    /// or a target uploaded to the scan, copied into the job's `target/`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<JobTarget>,
    /// The CT series to pull from the service's PACS (the job's scan is then made from it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pacs_ct: Option<PacsSeries>,
    /// Whether to push the DICOM outputs to the service's PACS when the run succeeds.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub push: bool,
}

/// A tracked point in `request.json`.
#[derive(Debug, Clone, Serialize, Deserialize, utoipa::ToSchema)]
pub struct StoredPoint {
    /// The client's name for it.
    pub name: String,
    /// Position at the scanned state, LPS mm.
    pub lps_mm: [f64; 3],
}

impl From<&StoredPoint> for TrackedPoint {
    fn from(p: &StoredPoint) -> Self {
        TrackedPoint {
            name: p.name.clone(),
            rest_lps_mm: p.lps_mm,
        }
    }
}

/// Now as RFC 3339 UTC, to the second.
pub fn now_rfc3339() -> String {
    humantime::format_rfc3339_seconds(SystemTime::now()).to_string()
}

/// The data directory.
#[derive(Debug, Clone)]
pub struct Store {
    root: PathBuf,
    /// Held while a target directory is replaced or removed, or a job copies a target, so
    /// that two uploads of one name never interleave their renames.
    targets: Arc<Mutex<()>>,
    /// Whether other processes use it at the same time (see [`Store::open_shared`]).
    shared: bool,
    /// The object store holding the uploads and outputs, when one is configured: the data
    /// directory then keeps a local copy of the scans and runs' scratch outputs only.
    blobs: Option<BlobStore>,
    /// Held while this process fetches a scan or evicts fetched copies, so that two of its
    /// jobs never fetch one scan at once and a fetch never races an eviction.
    fetches: Arc<Mutex<()>>,
}

/// A job's hold on the local copy of its scan: while it lives, no eviction removes the copy.
/// A shared lock on the copy's mark file, which every process of this host sees (evictions
/// take it exclusively, without waiting, and skip a copy in use).
#[derive(Debug)]
pub struct ScanCopyHold(Option<std::fs::File>);

/// A job's target fetched from the object store, removed when dropped.
#[derive(Debug)]
pub struct FetchedTarget(Option<PathBuf>);

impl Drop for FetchedTarget {
    fn drop(&mut self) {
        if let Some(dir) = self.0.take() {
            let _ = std::fs::remove_dir_all(&dir);
            // The job's directory too when nothing else is left in it on this machine.
            if let Some(job) = dir.parent() {
                let _ = std::fs::remove_dir(job);
            }
        }
    }
}

/// A scan's target as kept in the object store (`scans/<scan>/targets/<name>/target.json`):
/// its record and its file's key below the target's, new for every upload, so that
/// replacing a target is the one PUT of this record.
#[derive(Debug, Serialize, Deserialize)]
struct TargetObject {
    record: TargetRecord,
    /// `<upload id>/<file name>`.
    object: String,
}

/// The target's record kept in the object store, `None` when the scan has no target `name`.
fn target_object(blobs: &BlobStore, scan: ScanId, name: &str) -> Result<Option<TargetObject>> {
    let key = format!("scans/{scan}/{SCAN_TARGETS}/{name}/{TARGET_RECORD}");
    let Some(bytes) = blobs.read(&key)? else {
        return Ok(None);
    };
    let stored: TargetObject = serde_json::from_slice(&bytes).map_err(|e| Error::Store {
        record: key.clone(),
        reason: format!("corrupt record: {e}"),
    })?;
    // The key of its file stays below the target's (a record naming another would have a
    // replacement delete that).
    let plain = |part: &str| !part.is_empty() && part != "." && part != "..";
    match stored.object.split_once('/') {
        Some((id, file)) if plain(id) && plain(file) && !file.contains('/') => Ok(Some(stored)),
        _ => Err(Error::Store {
            record: key,
            reason: format!("corrupt record: file key {:?}", stored.object),
        }),
    }
}

/// A scan's target file in the data directory for a job's copy (see
/// [`Store::target_file_for_job`]); a copy fetched from the object store is removed when
/// this is dropped.
#[derive(Debug)]
pub struct LocalTargetFile {
    /// The file, named as the target's record names it.
    pub path: PathBuf,
    /// The staging directory of a fetched copy.
    fetched: Option<PathBuf>,
}

impl Drop for LocalTargetFile {
    fn drop(&mut self) {
        if let Some(dir) = self.fetched.take() {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

impl ScanCopyHold {
    /// A hold on nothing: the scan is this process's own (its upload or pull), never evicted.
    pub fn none() -> Self {
        ScanCopyHold(None)
    }

    /// Whether this holds a fetched copy (rather than the process's own).
    pub fn holds(&self) -> bool {
        self.0.is_some()
    }
}

/// What storing an uploaded target came to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TargetStored {
    /// It is the scan's first target of that name.
    Created,
    /// It replaced the target of that name.
    Replaced,
    /// The scan is gone; nothing was stored.
    ScanMissing,
}

const SCAN_RECORD: &str = "scan.json";
const STORED_INGEST: &str = "ingest.bin";
/// In a scan's directory: its upload (or pulled series) and stored ingest there are a copy
/// fetched from the object store, which eviction may remove. Holds the copy's file name (the
/// record may live in PostgreSQL, which eviction does not ask).
const FETCHED_MARK: &str = ".fetched";
const JOB_RECORD: &str = "job.json";
const JOB_REQUEST: &str = "request.json";
const TARGET_RECORD: &str = "target.json";
const SCAN_TARGETS: &str = "targets";
/// Age after which an entry of a shared store's `tmp/` is a killed process's leftover: longer
/// than any upload or ingest is allowed to take.
pub const SHARED_TMP_MAX_AGE: std::time::Duration = std::time::Duration::from_secs(86_400);
/// Age under which the objects of a scan or job with no record are left alone: a scan's
/// upload and stored ingest are put before its record is written (an upload being received
/// now has objects and no record yet).
pub const ORPHAN_BLOB_MIN_AGE: std::time::Duration = std::time::Duration::from_secs(3_600);
/// The run's output directory inside a job's directory.
pub const JOB_OUTPUT: &str = "out";

/// The process that made an entry of `tmp/`, as its name starts: `<host>.<pid namespace>.<pid>_`.
/// The host (letters, digits and `-`) and the pid namespace (the inode of `/proc/self/ns/pid`;
/// 0 where there is none) say whether this process can tell if the owner is alive: two
/// containers of one host with one hostname have pid namespaces of their own.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TmpOwner {
    host: String,
    namespace: u64,
    pid: u32,
}

impl TmpOwner {
    /// This process.
    pub fn this_process() -> &'static TmpOwner {
        static OWNER: std::sync::OnceLock<TmpOwner> = std::sync::OnceLock::new();
        OWNER.get_or_init(|| TmpOwner {
            host: host_name(),
            namespace: pid_namespace(),
            pid: std::process::id(),
        })
    }

    /// `<host>.<namespace>.<pid>`.
    fn tag(&self) -> String {
        format!("{}.{}.{}", self.host, self.namespace, self.pid)
    }

    /// The owner an entry's name starts with, if it has one.
    pub fn of_entry(name: &str) -> Option<TmpOwner> {
        let (tag, _) = name.split_once('_')?;
        let mut parts = tag.rsplitn(3, '.');
        let pid = parts.next()?.parse().ok()?;
        let namespace = parts.next()?.parse().ok()?;
        let host = parts.next()?.to_string();
        Some(TmpOwner {
            host,
            namespace,
            pid,
        })
    }

    /// Whether the owner is a process of this host and pid namespace that no longer exists
    /// (never this process; a process of elsewhere is never judged dead).
    pub fn is_dead_here(&self) -> bool {
        let here = TmpOwner::this_process();
        if self.host != here.host || self.namespace != here.namespace || self.pid == here.pid {
            return false;
        }
        let Ok(pid) = libc::pid_t::try_from(self.pid) else {
            return false;
        };
        if pid <= 0 {
            return false;
        }
        // Signal 0 only checks: ESRCH is "no such process"; EPERM means it exists.
        if unsafe { libc::kill(pid, 0) } == 0 {
            return false;
        }
        std::io::Error::last_os_error().raw_os_error() == Some(libc::ESRCH)
    }
}

/// This machine's host name, kept to letters, digits and `-` (so it never holds the tag's
/// separators).
fn host_name() -> String {
    let mut buf = [0u8; 256];
    let ok = unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) } == 0;
    let end = buf.iter().position(|b| *b == 0).unwrap_or(buf.len());
    let name: String = if ok { &buf[..end] } else { &b"host"[..] }
        .iter()
        .map(|b| {
            if b.is_ascii_alphanumeric() || *b == b'-' {
                *b as char
            } else {
                '-'
            }
        })
        .collect();
    if name.is_empty() {
        "host".into()
    } else {
        name
    }
}

/// The inode of this process's pid namespace (`/proc/self/ns/pid` → `pid:[4026531836]`); 0
/// where it cannot be read.
fn pid_namespace() -> u64 {
    std::fs::read_link("/proc/self/ns/pid")
        .ok()
        .and_then(|target| {
            let text = target.to_string_lossy().into_owned();
            let inside = text.split_once('[')?.1.split_once(']')?.0.to_string();
            inside.parse().ok()
        })
        .unwrap_or(0)
}

impl Store {
    /// Opens (creating) the store at `root` and empties `tmp/` of an earlier process's leftovers.
    pub fn open(root: &Path) -> Result<Self> {
        let store = Store {
            root: root.to_path_buf(),
            targets: Arc::default(),
            shared: false,
            blobs: None,
            fetches: Arc::default(),
        };
        for dir in ["scans", "jobs"] {
            let dir = root.join(dir);
            std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
        }
        let tmp = store.tmp_dir();
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).at(IoOp::Remove, &tmp)?;
        }
        std::fs::create_dir_all(&tmp).at(IoOp::CreateDir, &tmp)?;
        // Proves the store is writable now rather than at the first upload.
        write_durable(&tmp.join("writable"), b"ok")?;
        Ok(store)
    }

    /// Opens (creating) a store that other processes use at the same time (API and worker
    /// processes on PostgreSQL): `tmp/` keeps what they are writing, and only what dead
    /// processes left is removed (see [`Store::sweep_shared_tmp`]).
    pub fn open_shared(root: &Path) -> Result<Self> {
        let store = Store {
            root: root.to_path_buf(),
            targets: Arc::default(),
            shared: true,
            blobs: None,
            fetches: Arc::default(),
        };
        for dir in ["scans", "jobs", "tmp"] {
            let dir = root.join(dir);
            std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
        }
        store.sweep_shared_tmp()?;
        store.probe_writable()?;
        Ok(store)
    }

    /// Removes the entries of a shared store's `tmp/` that no live process is writing: those
    /// whose owner (named in the entry, see [`Store::tmp_path`]) is a process of this host and
    /// pid namespace that no longer exists (an API process killed in the middle of an upload),
    /// and any older than [`SHARED_TMP_MAX_AGE`] (a process of another machine, or an entry
    /// without an owner). Runs when a shared store is opened and at every retention sweep;
    /// nothing for a store of one process, whose `tmp/` is emptied when it opens. The number
    /// of entries removed.
    pub fn sweep_shared_tmp(&self) -> Result<usize> {
        if !self.shared {
            return Ok(0);
        }
        let tmp = self.tmp_dir();
        let mut removed = 0;
        for entry in std::fs::read_dir(&tmp).at(IoOp::List, &tmp)?.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            let abandoned = TmpOwner::of_entry(&name).is_some_and(|o| o.is_dead_here());
            let old = entry
                .metadata()
                .and_then(|m| m.modified())
                .ok()
                .and_then(|t| t.elapsed().ok())
                .is_some_and(|age| age > SHARED_TMP_MAX_AGE);
            if abandoned || old {
                let path = entry.path();
                if std::fs::remove_dir_all(&path)
                    .or_else(|_| std::fs::remove_file(&path))
                    .is_ok()
                {
                    removed += 1;
                    tracing::info!(
                        entry = %name,
                        reason = if abandoned { "its process is gone" } else { "age" },
                        "removed a leftover of tmp/"
                    );
                }
            }
        }
        Ok(removed)
    }

    /// Writes and removes a probe file of this call's own in `tmp/`: processes sharing the
    /// store must not race for one name.
    fn probe_writable(&self) -> Result<()> {
        let probe = self.tmp_path("writable");
        write_durable(&probe, b"ok")?;
        std::fs::remove_file(&probe).at(IoOp::Remove, &probe)
    }

    /// This store with its uploads and outputs also in `blobs` (see [`super::blobs`]).
    pub fn with_blobs(mut self, blobs: Option<BlobStore>) -> Self {
        self.blobs = blobs;
        self
    }

    /// The object store of the uploads and outputs, when one is configured.
    pub fn blobs(&self) -> Option<&BlobStore> {
        self.blobs.as_ref()
    }

    /// Puts a scan's received `upload` and its stored ingest `stored` (when that file exists)
    /// in the object store under the scan's keys, before its record makes it visible; nothing
    /// without one.
    pub fn put_scan_blobs(
        &self,
        record: &ScanRecord,
        upload: &Path,
        stored: Option<&Path>,
    ) -> Result<()> {
        let Some(blobs) = &self.blobs else {
            return Ok(());
        };
        let id = record.scan_id;
        let put = (|| {
            let key = format!("scans/{id}/{}", record.file_name);
            // A series pulled from the PACS is a directory of instances.
            if upload.is_dir() {
                blobs.put_tree(&key, upload)?;
            } else {
                blobs.put_file(&key, upload)?;
            }
            match stored {
                Some(stored) if stored.is_file() => {
                    blobs.put_file(&format!("scans/{id}/{STORED_INGEST}"), stored)?;
                }
                _ => {}
            }
            Ok(())
        })();
        if put.is_err() {
            let _ = blobs.delete_prefix(&format!("scans/{id}"));
        }
        put
    }

    /// Makes sure a scan's upload or pulled series (and its stored ingest, when the object
    /// store has one) is in the data directory, fetching them from the object store when this
    /// process has no copy (a worker on another machine), and holds that copy for the caller's
    /// run. After a fetch, the fetched copies beyond `fetched_scans_mib` that no job holds are
    /// removed, least recently used first (see [`Store::evict_fetched_scans`]).
    pub fn ensure_scan_local(&self, record: &ScanRecord) -> Result<ScanCopyHold> {
        let Some(blobs) = &self.blobs else {
            return Ok(ScanCopyHold::none());
        };
        let _one_at_a_time = lock(&self.fetches);
        let id = record.scan_id;
        let file = self.scan_file(record);
        let dir = self.scan_dir(id);
        let mark = dir.join(FETCHED_MARK);
        // The upload's own copy (or a pull's, or a shared mount's): never evicted.
        if file.exists() && !mark.exists() {
            return Ok(ScanCopyHold::none());
        }
        std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
        // Held before looking: an eviction by another process is over once the hold is had.
        let hold = hold_copy(&mark, &record.file_name)?;
        if file.exists() {
            return Ok(hold);
        }
        let started = std::time::Instant::now();
        let staging = self.tmp_path("fetch");
        std::fs::create_dir_all(&staging).at(IoOp::CreateDir, &staging)?;
        let fetched = self.fetch_scan_into(blobs, record, &staging);
        let _ = std::fs::remove_dir_all(&staging);
        let bytes = fetched?;
        tracing::info!(scan = %id, bytes, seconds = started.elapsed().as_secs_f64(), "scan fetched from the object store");
        match self.evict_fetched_scans(blobs.fetched_scans_bytes()) {
            Ok(_) => {}
            Err(e) => tracing::warn!("evicting fetched scan copies: {e}"),
        }
        Ok(hold)
    }

    /// Fetches a scan's upload (a file, or the tree of a pulled series) and stored ingest
    /// into `staging`, then moves them into the scan's directory; the bytes fetched.
    fn fetch_scan_into(
        &self,
        blobs: &BlobStore,
        record: &ScanRecord,
        staging: &Path,
    ) -> Result<u64> {
        let id = record.scan_id;
        let key = format!("scans/{id}/{}", record.file_name);
        let staged = staging.join(&record.file_name);
        let mut bytes = if blobs.fetch_file(&key, &staged)? {
            std::fs::metadata(&staged)
                .at(IoOp::Metadata, &staged)?
                .len()
        } else {
            match blobs.fetch_tree(&key, &staged)? {
                (0, _) => {
                    return Err(Error::ObjectStore {
                        store: blobs.shown().to_string(),
                        key: Some(key),
                        reason: "the scan's upload is not in the object store".into(),
                    })
                }
                (_, bytes) => bytes,
            }
        };
        let file = self.scan_file(record);
        if let Err(e) = std::fs::rename(&staged, &file) {
            // Another process sharing this data directory fetched the same series first.
            if !(staged.is_dir() && file.is_dir()) {
                return Err(Error::io(IoOp::Rename, &staged, e));
            }
        }
        let stored = self.stored_ingest_file(id);
        if !stored.is_file() {
            let staged = staging.join(STORED_INGEST);
            if blobs.fetch_file(&format!("scans/{id}/{STORED_INGEST}"), &staged)? {
                bytes += std::fs::metadata(&staged)
                    .at(IoOp::Metadata, &staged)?
                    .len();
                std::fs::rename(&staged, &stored).at(IoOp::Rename, &staged)?;
            }
        }
        Ok(bytes)
    }

    /// Removes the copies of scans fetched from the object store that no job holds, least
    /// recently used first (a copy is used when a job takes its hold), until the fetched copies
    /// left hold at most `limit` bytes; a copy's scan directory and mark stay, so a later job
    /// fetches it again. The upload's own copy on the API's machine, a pull's, and whatever a
    /// scan directory holds besides (records, targets) are never touched. The bytes removed.
    pub fn evict_fetched_scans(&self, limit: u64) -> Result<u64> {
        let scans = self.root.join("scans");
        let mut copies = Vec::new();
        for entry in std::fs::read_dir(&scans).at(IoOp::List, &scans)?.flatten() {
            let dir = entry.path();
            let mark = dir.join(FETCHED_MARK);
            let Ok(name) = std::fs::read_to_string(&mark) else {
                continue;
            };
            // A plain name only (a mark being written is still empty): never the directory
            // itself, which holds the directory store's record and the targets.
            let name = name.trim();
            if name.is_empty() || name.contains('/') || name == "." || name == ".." {
                continue;
            }
            let parts = [dir.join(name), dir.join(STORED_INGEST)];
            let bytes: u64 = parts.iter().map(|p| entry_bytes(p)).sum();
            if bytes == 0 {
                continue;
            }
            let used = std::fs::metadata(&mark)
                .and_then(|m| m.modified())
                .unwrap_or(SystemTime::UNIX_EPOCH);
            copies.push((used, mark, parts, bytes));
        }
        copies.sort_by_key(|c| c.0);
        let mut total: u64 = copies.iter().map(|c| c.3).sum();
        let mut removed = 0;
        for (_, mark, parts, bytes) in copies {
            if total <= limit {
                break;
            }
            let Ok(file) = std::fs::File::open(&mark) else {
                continue;
            };
            // A job's hold (shared) makes this fail at once: that copy is in use.
            if file.try_lock().is_err() {
                continue;
            }
            for part in &parts {
                let _ = std::fs::remove_dir_all(part).or_else(|_| std::fs::remove_file(part));
            }
            total -= bytes;
            removed += bytes;
            tracing::info!(copy = %mark.parent().unwrap_or(&mark).display(), bytes, "evicted a fetched scan copy");
        }
        Ok(removed)
    }

    /// Puts a finished run's outputs (`jobs/<id>/out/`) in the object store, logging what it
    /// took; nothing without one.
    pub fn put_job_output_blobs(&self, id: JobId) -> Result<()> {
        let Some(blobs) = &self.blobs else {
            return Ok(());
        };
        let (files, bytes, took) = blobs.put_outputs(&id.to_string(), &self.job_output_dir(id))?;
        tracing::info!(job = %id, files, bytes, seconds = took.as_secs_f64(), store = blobs.shown(), "outputs put in the object store");
        Ok(())
    }

    /// Removes from the object store the objects of scans and jobs that have no record
    /// (`scans` and `jobs` are the ids that have one) once the newest of them is older than
    /// [`ORPHAN_BLOB_MIN_AGE`] at `now`: what an API process killed between putting a scan's
    /// upload and writing its record left, or the outputs of a job deleted while a worker was
    /// putting them. Nothing without an object store. How many scans' and jobs' objects went.
    pub fn sweep_orphan_blobs(
        &self,
        scans: &std::collections::HashSet<String>,
        jobs: &std::collections::HashSet<String>,
        now: SystemTime,
    ) -> Result<usize> {
        let Some(blobs) = &self.blobs else {
            return Ok(0);
        };
        let mut removed = 0;
        for (kind, known) in [("scans", scans), ("jobs", jobs)] {
            for (owner, newest) in blobs.owners(kind)? {
                let old = now.duration_since(newest).unwrap_or_default() > ORPHAN_BLOB_MIN_AGE;
                if known.contains(&owner) || !old {
                    continue;
                }
                let objects = blobs.delete_prefix(&format!("{kind}/{owner}"))?;
                removed += 1;
                tracing::warn!(
                    kind,
                    owner = %owner,
                    objects,
                    store = blobs.shown(),
                    "removed objects of no record from the object store"
                );
            }
        }
        Ok(removed)
    }

    /// Removes the local copy of a job's outputs once they are in the object store (the data
    /// directory then only held them while the run wrote them); nothing without one.
    pub fn drop_local_job_output(&self, id: JobId) {
        if self.blobs.is_none() {
            return;
        }
        let out = self.job_output_dir(id);
        if let Err(e) = std::fs::remove_dir_all(&out) {
            if e.kind() != std::io::ErrorKind::NotFound {
                tracing::warn!(job = %id, "cannot remove the local copy of the outputs: {e}");
            }
        }
        // On a worker's own data directory nothing else is left of the job, and its deletion
        // happens on the API's machine; a directory with a record or a target stays.
        let _ = std::fs::remove_dir(self.job_dir(id));
    }

    /// Removes `relative/` from the object store, if there is one; whether anything was there.
    fn delete_blobs(&self, relative: &str) -> Result<bool> {
        match &self.blobs {
            Some(blobs) => Ok(blobs.delete_prefix(relative)? > 0),
            None => Ok(false),
        }
    }

    /// The data directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Where uploads are received and deletions happen.
    pub fn tmp_dir(&self) -> PathBuf {
        self.root.join("tmp")
    }

    /// A fresh, unused path in `tmp/`: `<owner>_<what>-<uuid>`, the owner naming this process
    /// (see [`TmpOwner`]) so that what it leaves when killed can be told from what a live
    /// process sharing the store is writing.
    pub fn tmp_path(&self, what: &str) -> PathBuf {
        self.tmp_dir().join(format!(
            "{}_{what}-{}",
            TmpOwner::this_process().tag(),
            uuid::Uuid::new_v4().simple()
        ))
    }

    /// Whether the store can be written (for readiness).
    pub fn is_writable(&self) -> bool {
        if self.shared {
            return self.probe_writable().is_ok();
        }
        write_durable(&self.tmp_dir().join("writable"), b"ok").is_ok()
    }

    /// A scan's directory.
    pub fn scan_dir(&self, id: ScanId) -> PathBuf {
        self.root.join("scans").join(id.to_string())
    }

    /// The uploaded file of a scan.
    pub fn scan_file(&self, record: &ScanRecord) -> PathBuf {
        self.scan_dir(record.scan_id).join(&record.file_name)
    }

    /// Where the ingest of a scan's upload is stored (see [`crate::ingest::stored`]); inside
    /// the scan's directory, so deleting the scan deletes it and retention counts its bytes.
    pub fn stored_ingest_file(&self, id: ScanId) -> PathBuf {
        self.scan_dir(id).join(STORED_INGEST)
    }

    /// Stores a scan: moves the received `upload` in and writes its record, all at once.
    pub fn put_scan(&self, record: &ScanRecord, upload: &Path) -> Result<()> {
        self.put_scan_files(record, upload, true)
    }

    /// Moves the received `upload` into the scan's new directory, with `scan.json` when
    /// `with_record` (the directory store's record; PostgreSQL keeps its own), all at once.
    pub fn put_scan_files(
        &self,
        record: &ScanRecord,
        upload: &Path,
        with_record: bool,
    ) -> Result<()> {
        let staging = self.tmp_path("scan");
        std::fs::create_dir_all(&staging).at(IoOp::CreateDir, &staging)?;
        let file = staging.join(&record.file_name);
        std::fs::rename(upload, &file).at(IoOp::Rename, upload)?;
        if with_record {
            write_json(&staging.join(SCAN_RECORD), record)?;
        }
        if self.blobs.is_some() {
            // With an object store the objects are the scan; this copy is a cache of them
            // from the start, bounded and evicted like a fetched one (see
            // [`Store::evict_fetched_scans`]), so no process needs another's data directory.
            write_durable(&staging.join(FETCHED_MARK), record.file_name.as_bytes())?;
        }
        publish_dir(&staging, &self.scan_dir(record.scan_id))
    }

    /// After this process stored a scan (an upload): removes the cached copies of scans beyond
    /// `fetched_scans_mib` that no job holds, least recently used first, as after a fetch;
    /// nothing without an object store. A failure is logged: the copies then stay.
    pub fn evict_after_store(&self) {
        let Some(blobs) = &self.blobs else {
            return;
        };
        let _one_at_a_time = lock(&self.fetches);
        if let Err(e) = self.evict_fetched_scans(blobs.fetched_scans_bytes()) {
            tracing::warn!("evicting cached scan copies: {e}");
        }
    }

    /// Bytes of a scan's directory in this data directory (no object store asked).
    pub fn local_scan_bytes(&self, id: ScanId) -> u64 {
        directory_bytes(&self.scan_dir(id))
    }

    /// Bytes a scan holds, as retention counts them: its directory (upload, stored ingest, targets); with an object
    /// store its objects and its record beside them, the local copy of the objects being a
    /// cache that comes and goes (see [`Store::evict_fetched_scans`]).
    pub fn scan_bytes(&self, id: ScanId) -> u64 {
        let dir = self.scan_dir(id);
        let Some(blobs) = &self.blobs else {
            return directory_bytes(&dir);
        };
        let objects: u64 = blobs
            .list(&format!("scans/{id}"))
            .map(|listed| listed.iter().map(|(_, bytes)| bytes).sum())
            .unwrap_or(0);
        objects + entry_bytes(&dir.join(SCAN_RECORD))
    }

    /// A scan's record, `None` when there is no such scan.
    pub fn scan(&self, id: ScanId) -> Result<Option<ScanRecord>> {
        self.read_record(&self.scan_dir(id).join(SCAN_RECORD))
    }

    /// Removes a scan (and its objects); `false` when there was none.
    pub fn delete_scan(&self, id: ScanId) -> Result<bool> {
        let local = self.remove_dir(&self.scan_dir(id))?;
        let objects = self.delete_blobs(&format!("scans/{id}"))?;
        Ok(local || objects)
    }

    /// A target's directory in its scan's.
    fn target_dir(&self, scan: ScanId, name: &str) -> PathBuf {
        self.scan_dir(scan).join(SCAN_TARGETS).join(name)
    }

    /// Where the uploaded file of a scan's target is in the data directory (without an object
    /// store; with one, see [`Store::target_file_for_job`]).
    pub fn target_file(&self, scan: ScanId, record: &TargetRecord) -> PathBuf {
        self.target_dir(scan, &record.name).join(&record.file_name)
    }

    /// Stores a target of scan `scan`: moves the received `upload` in beside its record, all
    /// at once, replacing a target of the same name (the old one stays whole when this fails).
    /// `name` must have passed [`super::targets::check_target_name`].
    pub fn put_target(
        &self,
        scan: ScanId,
        record: &TargetRecord,
        upload: &Path,
    ) -> Result<TargetStored> {
        if let Some(blobs) = &self.blobs {
            return self.put_target_object(blobs, scan, record, upload);
        }
        let staging = self.tmp_path("target");
        std::fs::create_dir_all(&staging).at(IoOp::CreateDir, &staging)?;
        let staged = (|| {
            let file = staging.join(&record.file_name);
            std::fs::rename(upload, &file).at(IoOp::Rename, upload)?;
            write_json(&staging.join(TARGET_RECORD), record)?;
            sync_dir(&staging);
            Ok(())
        })();
        if let Err(e) = staged {
            let _ = std::fs::remove_dir_all(&staging);
            return Err(e);
        }
        let _one_at_a_time = lock(&self.targets);
        let targets = self.scan_dir(scan).join(SCAN_TARGETS);
        // Not create_dir_all: that would bring back a scan removed meanwhile.
        match std::fs::create_dir(&targets) {
            Ok(()) => sync_dir(&self.scan_dir(scan)),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                let _ = std::fs::remove_dir_all(&staging);
                return Ok(TargetStored::ScanMissing);
            }
            Err(e) => {
                let _ = std::fs::remove_dir_all(&staging);
                return Err(Error::io(IoOp::CreateDir, &targets, e));
            }
        }
        let dir = targets.join(&record.name);
        let replaced = self.tmp_path("replaced");
        let had_one = match std::fs::rename(&dir, &replaced) {
            Ok(()) => true,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
            Err(e) => {
                let _ = std::fs::remove_dir_all(&staging);
                return Err(Error::io(IoOp::Rename, &dir, e));
            }
        };
        if let Err(e) = std::fs::rename(&staging, &dir) {
            // The old target goes back: a failed upload loses nothing already stored.
            if had_one {
                let _ = std::fs::rename(&replaced, &dir);
            }
            let _ = std::fs::remove_dir_all(&staging);
            return Err(Error::io(IoOp::Replace, &dir, e));
        }
        sync_dir(&targets);
        if had_one {
            let _ = std::fs::remove_dir_all(&replaced);
        }
        Ok(if had_one {
            TargetStored::Replaced
        } else {
            TargetStored::Created
        })
    }

    /// A scan's target, `None` when it has none of that name (or the name is no name).
    pub fn target(&self, scan: ScanId, name: &str) -> Result<Option<TargetRecord>> {
        if super::targets::check_target_name(name).is_err() {
            return Ok(None);
        }
        if let Some(blobs) = &self.blobs {
            return Ok(target_object(blobs, scan, name)?.map(|t| t.record));
        }
        self.read_record(&self.target_dir(scan, name).join(TARGET_RECORD))
    }

    /// A scan's targets by name; unreadable ones are left out and logged.
    pub fn list_targets(&self, scan: ScanId) -> Result<Vec<TargetRecord>> {
        if let Some(blobs) = &self.blobs {
            let mut targets = Vec::new();
            for (path, _) in blobs.list(&format!("scans/{scan}/{SCAN_TARGETS}"))? {
                let Some(name) = path.strip_suffix(&format!("/{TARGET_RECORD}")) else {
                    continue;
                };
                match self.target(scan, name) {
                    Ok(Some(record)) => targets.push(record),
                    // Deleted since the listing.
                    Ok(None) => {}
                    Err(e) => tracing::warn!(scan = %scan, "target {name}: {e}"),
                }
            }
            targets.sort_by(|a, b| a.name.cmp(&b.name));
            return Ok(targets);
        }
        let dir = self.scan_dir(scan).join(SCAN_TARGETS);
        let entries = match std::fs::read_dir(&dir) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(Error::io(IoOp::List, &dir, e)),
        };
        let mut targets = Vec::new();
        for entry in entries {
            let entry = entry.at(IoOp::List, &dir)?;
            let name = entry.file_name().to_string_lossy().into_owned();
            match self.target(scan, &name) {
                Ok(Some(record)) => targets.push(record),
                Ok(None) => {}
                Err(e) => tracing::warn!(scan = %scan, "target {name}: {e}"),
            }
        }
        targets.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(targets)
    }

    /// Removes a scan's target (jobs keep their copies); `false` when there was none.
    pub fn delete_target(&self, scan: ScanId, name: &str) -> Result<bool> {
        if super::targets::check_target_name(name).is_err() {
            return Ok(false);
        }
        let _one_at_a_time = lock(&self.targets);
        let local = self.remove_dir(&self.target_dir(scan, name))?;
        let objects = self.delete_blobs(&format!("scans/{scan}/{SCAN_TARGETS}/{name}"))?;
        Ok(local || objects)
    }

    /// [`Store::put_target`] with an object store: the file goes to a key of its own
    /// (`scans/<scan>/targets/<name>/<upload id>/<file>`), then `target.json` naming it
    /// replaces the old one in one PUT, then the old file goes. A reader sees the old target
    /// or the new one whole; a failed upload leaves the old one as it was. A scan deleted
    /// meanwhile is not noticed here (the store does not hold the scan records with
    /// PostgreSQL): the caller checks it after, and removes the target when it is gone.
    fn put_target_object(
        &self,
        blobs: &BlobStore,
        scan: ScanId,
        record: &TargetRecord,
        upload: &Path,
    ) -> Result<TargetStored> {
        let dir = format!("scans/{scan}/{SCAN_TARGETS}/{}", record.name);
        let _one_at_a_time = lock(&self.targets);
        let previous = target_object(blobs, scan, &record.name)?;
        let upload_id = uuid::Uuid::new_v4().simple().to_string();
        let object = format!("{upload_id}/{}", record.file_name);
        let stored = TargetObject {
            record: record.clone(),
            object: object.clone(),
        };
        let json = serde_json::to_vec_pretty(&stored).map_err(|e| Error::Store {
            record: format!("{dir}/{TARGET_RECORD}"),
            reason: format!("cannot serialise: {e}"),
        })?;
        let file_key = format!("{dir}/{object}");
        let put = blobs
            .put_file(&file_key, upload)
            .and_then(|_| blobs.put_bytes(&format!("{dir}/{TARGET_RECORD}"), json));
        if let Err(e) = put {
            let _ = blobs.delete_prefix(&format!("{dir}/{upload_id}"));
            return Err(e);
        }
        let _ = std::fs::remove_file(upload);
        if let Some(previous) = &previous {
            // Its upload's directory (a listing prefix is a directory, never one object's key);
            // `target_object` checked that the key is `<upload id>/<file>`.
            let upload = previous.object.split('/').next().unwrap_or_default();
            if let Err(e) = blobs.delete_prefix(&format!("{dir}/{upload}")) {
                // Left under the scan's prefix: it goes with the scan.
                tracing::warn!(scan = %scan, "cannot remove the replaced target's file: {e}");
            }
        }
        Ok(if previous.is_some() {
            TargetStored::Replaced
        } else {
            TargetStored::Created
        })
    }

    /// The file of a scan's target `record` in the data directory, for a job's copy: the
    /// stored file itself, or with an object store a copy fetched into `tmp/` (removed when
    /// the returned guard is dropped). `None` when the target was replaced or deleted since
    /// `record` was read (the request was checked against that one).
    pub fn target_file_for_job(
        &self,
        scan: ScanId,
        record: &TargetRecord,
    ) -> Result<Option<LocalTargetFile>> {
        let Some(blobs) = &self.blobs else {
            return Ok(Some(LocalTargetFile {
                path: self.target_file(scan, record),
                fetched: None,
            }));
        };
        let dir = format!("scans/{scan}/{SCAN_TARGETS}/{}", record.name);
        let Some(stored) =
            target_object(blobs, scan, &record.name)?.filter(|stored| &stored.record == record)
        else {
            return Ok(None);
        };
        let staging = self.tmp_path("target-copy");
        std::fs::create_dir_all(&staging).at(IoOp::CreateDir, &staging)?;
        let fetched = LocalTargetFile {
            path: staging.join(&record.file_name),
            fetched: Some(staging),
        };
        if !blobs.fetch_file(&format!("{dir}/{}", stored.object), &fetched.path)? {
            return Ok(None);
        }
        Ok(Some(fetched))
    }

    /// Where a job's copy of its uploaded target is.
    pub fn job_target_dir(&self, id: JobId) -> PathBuf {
        self.job_dir(id).join(JOB_TARGET_DIR)
    }

    /// A job's directory.
    pub fn job_dir(&self, id: JobId) -> PathBuf {
        self.root.join("jobs").join(id.to_string())
    }

    /// A job's output directory (the run's `--out`).
    pub fn job_output_dir(&self, id: JobId) -> PathBuf {
        self.job_dir(id).join(JOB_OUTPUT)
    }

    /// Stores a new job: its request, its record and its copy of the uploaded target file
    /// `target` (linked, else copied, into `target/` under the file's own name), all at once.
    pub fn put_job(
        &self,
        record: &JobRecord,
        request: &JobRequest,
        target: Option<&Path>,
    ) -> Result<()> {
        self.put_job_files(record.job_id, target, Some((record, request)))
    }

    /// Makes a new job's directory with its copy of the target file `target`, and with
    /// `records` (`job.json`, `request.json`) for the directory store, all at once.
    pub fn put_job_files(
        &self,
        id: JobId,
        target: Option<&Path>,
        records: Option<(&JobRecord, &JobRequest)>,
    ) -> Result<()> {
        let staging = self.tmp_path("job");
        std::fs::create_dir_all(&staging).at(IoOp::CreateDir, &staging)?;
        let staged = (|| {
            if let Some(source) = target {
                let dir = staging.join(JOB_TARGET_DIR);
                std::fs::create_dir(&dir).at(IoOp::CreateDir, &dir)?;
                let copy = dir.join(source.file_name().unwrap_or_default());
                let _one_at_a_time = lock(&self.targets);
                // A link costs nothing and the scan's file is never written again (a new
                // upload is a new file); a copy where links are not allowed.
                if std::fs::hard_link(source, &copy).is_err() {
                    std::fs::copy(source, &copy).at(IoOp::Read, source)?;
                    std::fs::File::open(&copy)
                        .and_then(|f| f.sync_all())
                        .at(IoOp::Sync, &copy)?;
                }
                sync_dir(&dir);
            }
            if let Some((record, request)) = records {
                write_json(&staging.join(JOB_REQUEST), request)?;
                write_json(&staging.join(JOB_RECORD), record)?;
            }
            Ok(())
        })();
        if let Err(e) = staged {
            let _ = std::fs::remove_dir_all(&staging);
            return Err(e);
        }
        // The job's copy of its target in the object store too (before the record makes the
        // job visible), for a worker on another machine (see ensure_job_target_local).
        if let (Some(blobs), Some(source)) = (&self.blobs, target) {
            let name = source.file_name().unwrap_or_default().to_string_lossy();
            let key = format!("jobs/{id}/{JOB_TARGET_DIR}/{name}");
            if let Err(e) = blobs.put_file(&key, &staging.join(JOB_TARGET_DIR).join(&*name)) {
                let _ = std::fs::remove_dir_all(&staging);
                let _ = blobs.delete_prefix(&format!("jobs/{id}"));
                return Err(e);
            }
        }
        publish_dir(&staging, &self.job_dir(id))
    }

    /// Makes sure a job's copy of its uploaded target (`target/<file>`) is in the data
    /// directory, fetching it from the object store when this process has none (a worker on
    /// another machine than the API process the job was submitted to); nothing without one.
    /// A fetched copy is removed when the returned guard is dropped (after the run): the
    /// job's deletion happens on the API's machine and would never reach it.
    pub fn ensure_job_target_local(&self, id: JobId, file: &str) -> Result<FetchedTarget> {
        let Some(blobs) = &self.blobs else {
            return Ok(FetchedTarget(None));
        };
        let dir = self.job_target_dir(id);
        let local = dir.join(file);
        if local.is_file() {
            return Ok(FetchedTarget(None));
        }
        std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
        let key = format!("jobs/{id}/{JOB_TARGET_DIR}/{file}");
        if !blobs.fetch_file(&key, &local)? {
            return Err(Error::ObjectStore {
                store: blobs.shown().to_string(),
                key: Some(key),
                reason: "the job's copy of its target is not in the object store".into(),
            });
        }
        tracing::info!(job = %id, file, "target fetched from the object store");
        Ok(FetchedTarget(Some(dir)))
    }

    /// Replaces a job's record.
    pub fn save_job(&self, record: &JobRecord) -> Result<()> {
        write_json(&self.job_dir(record.job_id).join(JOB_RECORD), record)
    }

    /// A job's record, `None` when there is no such job.
    pub fn job(&self, id: JobId) -> Result<Option<JobRecord>> {
        self.read_record(&self.job_dir(id).join(JOB_RECORD))
    }

    /// A job's request.
    pub fn job_request(&self, id: JobId) -> Result<JobRequest> {
        let path = self.job_dir(id).join(JOB_REQUEST);
        self.read_record(&path)?.ok_or_else(|| Error::Store {
            record: self.record_name(&path),
            reason: "missing".into(),
        })
    }

    /// Removes a job and its outputs; `false` when there was none.
    pub fn delete_job(&self, id: JobId) -> Result<bool> {
        let local = self.remove_dir(&self.job_dir(id))?;
        let objects = self.delete_blobs(&format!("jobs/{id}"))?;
        Ok(local || objects)
    }

    /// Removes a job's published outputs (`out/`), as for a job cancelled after its run
    /// finished; `false` when there were none.
    pub fn remove_job_output(&self, id: JobId) -> Result<bool> {
        let local = self.remove_dir(&self.job_output_dir(id))?;
        let objects = self.delete_blobs(&format!("jobs/{id}/{JOB_OUTPUT}"))?;
        Ok(local || objects)
    }

    /// Every job record, for recovery at start; unreadable ones are reported, not fatal.
    pub fn list_jobs(&self) -> Result<(Vec<JobRecord>, Vec<String>)> {
        let dir = self.root.join("jobs");
        let mut jobs = Vec::new();
        let mut problems = Vec::new();
        for entry in std::fs::read_dir(&dir).at(IoOp::List, &dir)? {
            let entry = entry.at(IoOp::List, &dir)?;
            let name = entry.file_name().to_string_lossy().into_owned();
            let Some(id) = JobId::parse(&name) else {
                problems.push(format!("jobs/{name}: not a job directory, ignored"));
                continue;
            };
            match self.job(id) {
                Ok(Some(record)) => jobs.push(record),
                Ok(None) => problems.push(format!("jobs/{name}: no {JOB_RECORD}, ignored")),
                Err(e) => problems.push(format!("jobs/{name}: {e}")),
            }
        }
        jobs.sort_by(|a, b| a.created_at.cmp(&b.created_at));
        Ok((jobs, problems))
    }

    /// Every scan record with the bytes its directory holds, for retention; unreadable ones
    /// are reported, not fatal (and never removed: what they are is not known).
    pub fn list_scans(&self) -> Result<(Vec<StoredScan>, Vec<String>)> {
        let dir = self.root.join("scans");
        let mut scans = Vec::new();
        let mut problems = Vec::new();
        for entry in std::fs::read_dir(&dir).at(IoOp::List, &dir)? {
            let entry = entry.at(IoOp::List, &dir)?;
            let name = entry.file_name().to_string_lossy().into_owned();
            let Some(id) = ScanId::parse(&name) else {
                problems.push(format!("scans/{name}: not a scan directory, ignored"));
                continue;
            };
            match self.scan(id) {
                Ok(Some(record)) => {
                    let bytes = directory_bytes(&entry.path());
                    scans.push((record, bytes));
                }
                Ok(None) => problems.push(format!("scans/{name}: no {SCAN_RECORD}, ignored")),
                Err(e) => problems.push(format!("scans/{name}: {e}")),
            }
        }
        Ok((scans, problems))
    }

    /// Bytes held by a job's directory (record, request, outputs and partial outputs).
    pub fn job_bytes(&self, id: JobId) -> u64 {
        let objects = self.blobs.as_ref().map_or(0, |blobs| {
            blobs
                .list(&format!("jobs/{id}"))
                .map(|listed| listed.iter().map(|(_, bytes)| bytes).sum())
                .unwrap_or(0)
        });
        directory_bytes(&self.job_dir(id)) + objects
    }

    /// Removes a stopped run's partial output directories (`.out.partial-<pid>`); how many.
    pub fn clear_partial_outputs(&self, id: JobId) -> Result<usize> {
        let dir = self.job_dir(id);
        let mut removed = 0;
        let entries = match std::fs::read_dir(&dir) {
            Ok(entries) => entries,
            // A worker on another machine than the API process has no directory of the job
            // until its run makes one.
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
            Err(e) => return Err(Error::io(IoOp::List, &dir, e)),
        };
        for entry in entries {
            let entry = entry.at(IoOp::List, &dir)?;
            if entry
                .file_name()
                .to_string_lossy()
                .starts_with(&format!(".{JOB_OUTPUT}.partial"))
            {
                let partial = entry.path();
                std::fs::remove_dir_all(&partial).at(IoOp::Remove, &partial)?;
                removed += 1;
            }
        }
        Ok(removed)
    }

    fn remove_dir(&self, dir: &Path) -> Result<bool> {
        let doomed = self.tmp_path("deleted");
        match std::fs::rename(dir, &doomed) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(false),
            Err(e) => return Err(Error::io(IoOp::Rename, dir, e)),
        }
        sync_dir(dir.parent().unwrap_or(&self.root));
        std::fs::remove_dir_all(&doomed).at(IoOp::Remove, &doomed)?;
        Ok(true)
    }

    /// A record's name relative to the data directory, as store errors give it.
    fn record_name(&self, path: &Path) -> String {
        path.strip_prefix(&self.root)
            .unwrap_or(path)
            .display()
            .to_string()
    }

    /// A record, `None` when its file does not exist.
    fn read_record<T: serde::de::DeserializeOwned>(&self, path: &Path) -> Result<Option<T>> {
        let bytes = match std::fs::read(path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Error::io(IoOp::Read, path, e)),
        };
        serde_json::from_slice(&bytes)
            .map(Some)
            .map_err(|e| Error::Store {
                record: self.record_name(path),
                reason: format!("corrupt record: {e}"),
            })
    }
}

fn lock(m: &Mutex<()>) -> std::sync::MutexGuard<'_, ()> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let bytes = serde_json::to_vec_pretty(value).map_err(|e| Error::Format {
        path: path.to_path_buf(),
        reason: format!("cannot serialise: {e}"),
    })?;
    write_durable(path, &bytes)
}

/// Opens (creating) a fetched copy's mark, names the copy's file in it, takes a shared lock
/// on it (waiting for an eviction in progress) and stamps it as used now.
fn hold_copy(mark: &Path, file_name: &str) -> Result<ScanCopyHold> {
    let file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(mark)
        .at(IoOp::Write, mark)?;
    // Part of opening it for use (IoOp has no lock of its own).
    file.lock_shared().at(IoOp::Open, mark)?;
    if file.metadata().map(|m| m.len()).unwrap_or(0) == 0 {
        std::io::Write::write_all(&mut &file, file_name.as_bytes()).at(IoOp::Write, mark)?;
    }
    // The time eviction orders copies by: this use.
    file.set_modified(SystemTime::now()).at(IoOp::Write, mark)?;
    Ok(ScanCopyHold(Some(file)))
}

/// Bytes of a file, or of everything under a directory; 0 when there is nothing.
fn entry_bytes(path: &Path) -> u64 {
    match std::fs::metadata(path) {
        Ok(m) if m.is_dir() => directory_bytes(path),
        Ok(m) => m.len(),
        Err(_) => 0,
    }
}

fn publish_dir(staging: &Path, target: &Path) -> Result<()> {
    sync_dir(staging);
    std::fs::rename(staging, target).at(IoOp::Replace, target)?;
    if let Some(parent) = target.parent() {
        sync_dir(parent);
    }
    Ok(())
}

/// Makes a directory's entries (renames) durable; best effort where directories cannot be opened.
#[cfg(test)]
mod tests {
    use super::*;

    fn temp_store(name: &str) -> (PathBuf, Store) {
        let dir = std::env::temp_dir().join(format!("lm-store-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let store = Store::open(&dir).unwrap();
        (dir, store)
    }

    #[test]
    fn a_shared_tmp_loses_what_dead_processes_left_and_keeps_the_rest() {
        let dir = std::env::temp_dir().join(format!("lm-store-shared-tmp-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let store = Store::open_shared(&dir).unwrap();
        let here = TmpOwner::this_process();
        // A process that has ended (reaped), and one alive.
        let mut ended = std::process::Command::new("true").spawn().unwrap();
        ended.wait().unwrap();
        let mut alive = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        let as_owner = |pid: u32| {
            TmpOwner {
                pid,
                ..here.clone()
            }
            .tag()
        };
        let dead_upload = format!("{}_upload-1-scan.nii.gz", as_owner(ended.id()));
        let dead_dir = format!("{}_scan-2", as_owner(ended.id()));
        let live_upload = format!("{}_upload-3", as_owner(alive.id()));
        let elsewhere = format!("other-host.{}.{}_upload-4", here.namespace, ended.id());
        let other_namespace = format!(
            "{}.{}.{}_upload-5",
            here.host,
            here.namespace.wrapping_add(1),
            ended.id()
        );
        let unowned = "upload-6".to_string();
        let own = store.tmp_path("upload");
        for name in [
            &dead_upload,
            &live_upload,
            &elsewhere,
            &other_namespace,
            &unowned,
        ] {
            std::fs::write(store.tmp_dir().join(name), b"partial").unwrap();
        }
        std::fs::create_dir_all(store.tmp_dir().join(&dead_dir).join("inner")).unwrap();
        std::fs::write(&own, b"mine").unwrap();
        assert_eq!(
            TmpOwner::of_entry(own.file_name().unwrap().to_str().unwrap()).as_ref(),
            Some(here)
        );

        assert_eq!(store.sweep_shared_tmp().unwrap(), 2);
        let mut left: Vec<String> = std::fs::read_dir(store.tmp_dir())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        left.sort();
        let mut kept = vec![
            live_upload.clone(),
            elsewhere,
            other_namespace,
            unowned,
            own.file_name().unwrap().to_string_lossy().into_owned(),
        ];
        kept.sort();
        assert_eq!(left, kept);
        // Reopening (another process starting) sweeps alike.
        alive.kill().unwrap();
        alive.wait().unwrap();
        let reopened = Store::open_shared(&dir).unwrap();
        assert_eq!(reopened.sweep_shared_tmp().unwrap(), 0);
        assert!(
            !store.tmp_dir().join(&live_upload).exists(),
            "the live process's upload went once it died"
        );
        assert_eq!(std::fs::read_dir(store.tmp_dir()).unwrap().count(), 4);
        // A store of one process has nothing to sweep (its tmp/ is emptied when it opens).
        let _ = std::fs::remove_dir_all(&dir);
        let single = Store::open(&dir).unwrap();
        assert_eq!(single.sweep_shared_tmp().unwrap(), 0);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A blob store in `<dir>/blobs` through the `file://` backend of the object store.
    fn file_blobs(dir: &Path) -> BlobStore {
        let url = format!("file://{}", dir.join("blobs").display());
        BlobStore::open(&super::super::blobs::BlobSettings::new(url)).unwrap()
    }

    /// A machine's store in `data`, sharing `blobs` with the others.
    fn shared_store(data: &Path, blobs: &BlobStore) -> Store {
        Store::open_shared(data)
            .unwrap()
            .with_blobs(Some(blobs.clone()))
    }

    #[test]
    fn objects_of_no_record_go_once_old_and_the_rest_stay() {
        let dir = std::env::temp_dir().join(format!("lm-store-orphans-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let blobs = file_blobs(&dir);
        let store = shared_store(&dir.join("data"), &blobs);
        let file = dir.join("file");
        std::fs::write(&file, b"bytes").unwrap();
        for key in [
            "scans/kept-scan/scan.nii.gz",
            "scans/lost-scan/scan.nii.gz",
            "scans/lost-scan/ingest.bin",
            "jobs/kept-job/out/summary.json",
            "jobs/lost-job/out/frames/0/displacement.nii.gz",
        ] {
            blobs.put_file(key, &file).unwrap();
        }
        let scans = ["kept-scan".to_string()].into_iter().collect();
        let jobs = ["kept-job".to_string()].into_iter().collect();
        // Young: perhaps an upload whose record is being written.
        let now = SystemTime::now();
        assert_eq!(store.sweep_orphan_blobs(&scans, &jobs, now).unwrap(), 0);
        assert_eq!(blobs.list("scans").unwrap().len(), 3);
        let later = now + ORPHAN_BLOB_MIN_AGE + std::time::Duration::from_secs(60);
        assert_eq!(store.sweep_orphan_blobs(&scans, &jobs, later).unwrap(), 2);
        let left = |kind: &str| -> Vec<String> {
            blobs
                .owners(kind)
                .unwrap()
                .into_iter()
                .map(|(owner, _)| owner)
                .collect()
        };
        assert_eq!(left("scans"), vec!["kept-scan"]);
        assert_eq!(left("jobs"), vec!["kept-job"]);
        // Without an object store, nothing to do.
        let plain = Store::open_shared(&dir.join("data")).unwrap();
        assert_eq!(plain.sweep_orphan_blobs(&scans, &jobs, later).unwrap(), 0);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn fetched_scan_copies_are_evicted_least_recently_used_first_and_never_in_use() {
        let dir = std::env::temp_dir().join(format!("lm-store-evict-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let blobs = file_blobs(&dir);
        // The API's machine: the uploads are its own copies.
        let api = shared_store(&dir.join("api"), &blobs);
        let record = |file_name: &str, format: &str| ScanRecord {
            scan_id: ScanId::random(),
            created_at: now_rfc3339(),
            format: format.into(),
            upload_bytes: 0,
            file_name: file_name.into(),
            ingest: serde_json::json!({}),
            series: None,
        };
        // Three uploads of 1 000 bytes (one with a stored ingest of 500 more) and a pulled
        // series of two instances (800 bytes).
        let mut scans = Vec::new();
        for (i, bytes) in [1000usize, 1000, 1000].into_iter().enumerate() {
            let scan = record("scan.nii.gz", "nifti");
            let upload = api.tmp_path("upload");
            std::fs::write(&upload, vec![i as u8; bytes]).unwrap();
            let stored = api.tmp_path("stored");
            if i == 0 {
                std::fs::write(&stored, vec![7u8; 500]).unwrap();
            }
            api.put_scan_blobs(&scan, &upload, Some(&stored)).unwrap();
            api.put_scan(&scan, &upload).unwrap();
            scans.push(scan);
        }
        let series = record("series", "dicomweb");
        let pulled = api.tmp_path("pull");
        std::fs::create_dir_all(pulled.join("sub")).unwrap();
        std::fs::write(pulled.join("1.2.3.dcm"), vec![1u8; 400]).unwrap();
        std::fs::write(pulled.join("sub").join("1.2.3.4"), vec![2u8; 400]).unwrap();
        api.put_scan_blobs(&series, &pulled, None).unwrap();
        api.put_scan(&series, &pulled).unwrap();

        // A worker on another machine: nothing local, everything fetched.
        let worker = shared_store(&dir.join("worker"), &blobs);
        let use_scan = |scan: &ScanRecord| {
            let hold = worker.ensure_scan_local(scan).unwrap();
            assert!(hold.holds(), "a fetched copy is held");
            // Distinct use times, whatever the file system's clock granularity.
            std::thread::sleep(std::time::Duration::from_millis(20));
            hold
        };
        let here = |scan: &ScanRecord| worker.scan_file(scan).exists();
        drop(use_scan(&scans[0]));
        assert_eq!(
            std::fs::read(worker.stored_ingest_file(scans[0].scan_id)).unwrap(),
            vec![7u8; 500]
        );
        drop(use_scan(&series));
        assert_eq!(
            std::fs::read(worker.scan_file(&series).join("sub").join("1.2.3.4")).unwrap(),
            vec![2u8; 400]
        );
        drop(use_scan(&scans[1]));
        let running = use_scan(&scans[2]);
        // 1 500 + 800 + 1 000 + 1 000 bytes fetched; at most 2 900 kept: the least recently
        // used (the first upload with its stored ingest) goes, alone.
        assert_eq!(worker.evict_fetched_scans(2900).unwrap(), 1500);
        assert!(!here(&scans[0]) && !worker.stored_ingest_file(scans[0].scan_id).exists());
        assert!(here(&series) && here(&scans[1]) && here(&scans[2]));
        // The series used again is now the most recent but for the running job's scan,
        // which is never evicted while held, even with nothing allowed.
        drop(use_scan(&series));
        assert_eq!(worker.evict_fetched_scans(0).unwrap(), 1800);
        assert!(!here(&scans[1]) && !here(&series) && here(&scans[2]));
        drop(running);
        assert_eq!(worker.evict_fetched_scans(0).unwrap(), 1000);
        assert!(!here(&scans[2]));
        // An evicted copy comes back whole at the next use.
        drop(use_scan(&scans[0]));
        assert_eq!(
            std::fs::read(worker.scan_file(&scans[0])).unwrap(),
            vec![0u8; 1000]
        );
        // The uploads' own copies on the API's machine are a cache of the objects too: held
        // while used, evicted least recently used first, fetched again on the next use.
        let held = api.ensure_scan_local(&scans[1]).unwrap();
        assert!(held.holds(), "the API's copy is held like a fetched one");
        // (The API keeps no stored ingest here: 1 000 + 1 000 + 800 bytes.)
        assert_eq!(api.evict_fetched_scans(0).unwrap(), 1000 + 1000 + 800);
        assert!(api.scan_file(&scans[1]).exists() && !api.scan_file(&scans[0]).exists());
        drop(held);
        assert_eq!(api.evict_fetched_scans(0).unwrap(), 1000);
        assert!(!api.scan_file(&scans[1]).exists());
        assert!(api.ensure_scan_local(&scans[1]).unwrap().holds());
        assert_eq!(
            std::fs::read(api.scan_file(&scans[1])).unwrap(),
            vec![1u8; 1000]
        );
        // Without an object store the data directory is the store: nothing is a copy.
        let plain = Store::open_shared(&dir.join("plain")).unwrap();
        let kept = record("scan.nii.gz", "nifti");
        let upload = plain.tmp_path("upload");
        std::fs::write(&upload, vec![3u8; 100]).unwrap();
        plain.put_scan(&kept, &upload).unwrap();
        assert_eq!(plain.evict_fetched_scans(0).unwrap(), 0);
        assert!(!plain.ensure_scan_local(&kept).unwrap().holds());
        assert!(plain.scan_file(&kept).exists());
        // Deleting a scan removes its objects, a pulled series' tree among them.
        assert!(api.delete_scan(series.scan_id).unwrap());
        assert!(blobs
            .list(&format!("scans/{}", series.scan_id))
            .unwrap()
            .is_empty());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn scans_and_jobs_round_trip_and_vanish_whole() {
        let (dir, store) = temp_store("roundtrip");
        let upload = store.tmp_path("upload");
        std::fs::write(&upload, b"bytes").unwrap();
        let scan = ScanRecord {
            scan_id: ScanId::random(),
            created_at: now_rfc3339(),
            format: "nifti".into(),
            upload_bytes: 5,
            file_name: "scan.nii".into(),
            ingest: serde_json::json!({"elements": 3}),
            series: None,
        };
        store.put_scan(&scan, &upload).unwrap();
        let back = store.scan(scan.scan_id).unwrap().unwrap();
        assert_eq!(back.ingest["elements"], 3);
        assert_eq!(std::fs::read(store.scan_file(&back)).unwrap(), b"bytes");
        assert!(store.scan(ScanId::random()).unwrap().is_none());

        let job = JobRecord::queued(scan.scan_id);
        let request = JobRequest {
            config: RunConfig::default(),
            time_s: vec![0.0, 1.0],
            volume_ml: vec![0.0, 100.0],
            trace_source: "test".into(),
            points: vec![],
            callback_url: None,
            target: None,
            pacs_ct: None,
            push: false,
        };
        store.put_job(&job, &request, None).unwrap();
        let mut running = store.job(job.job_id).unwrap().unwrap();
        assert_eq!(running.state, JobState::Queued);
        running.state = JobState::Running;
        store.save_job(&running).unwrap();
        assert_eq!(
            store.job(job.job_id).unwrap().unwrap().state,
            JobState::Running
        );
        assert_eq!(store.job_request(job.job_id).unwrap().volume_ml[1], 100.0);
        std::fs::create_dir_all(store.job_dir(job.job_id).join(".out.partial-1")).unwrap();
        store.clear_partial_outputs(job.job_id).unwrap();
        assert!(!store.job_dir(job.job_id).join(".out.partial-1").exists());
        let (jobs, problems) = store.list_jobs().unwrap();
        assert_eq!((jobs.len(), problems.len()), (1, 0));

        assert!(store.delete_job(job.job_id).unwrap());
        assert!(!store.delete_job(job.job_id).unwrap());
        assert!(store.delete_scan(scan.scan_id).unwrap());
        assert!(store.scan(scan.scan_id).unwrap().is_none());
        // Reopening empties tmp/ and keeps nothing half-written.
        std::fs::write(store.tmp_path("upload"), b"partial").unwrap();
        let store = Store::open(&dir).unwrap();
        assert_eq!(std::fs::read_dir(store.tmp_dir()).unwrap().count(), 1);
        let _ = std::fs::remove_dir_all(&dir);
    }

    fn target_record(name: &str) -> TargetRecord {
        TargetRecord {
            name: name.into(),
            kind: super::super::targets::TargetKind::Mask,
            format: "nifti".into(),
            upload_bytes: 3,
            created_at: now_rfc3339(),
            file_name: format!("{name}.nii"),
            labels: vec![],
            rois: vec![],
            notes: vec![],
        }
    }

    #[test]
    fn targets_are_replaced_whole_kept_when_a_replacement_fails_and_copied_into_jobs() {
        let (dir, store) = temp_store("targets");
        let upload = store.tmp_path("upload");
        std::fs::write(&upload, b"ct").unwrap();
        let scan = ScanRecord {
            scan_id: ScanId::random(),
            created_at: now_rfc3339(),
            format: "nifti".into(),
            upload_bytes: 2,
            file_name: "scan.nii".into(),
            ingest: serde_json::json!({}),
            series: None,
        };
        store.put_scan(&scan, &upload).unwrap();
        let id = scan.scan_id;
        let put = |bytes: &[u8], record: &TargetRecord| {
            let file = store.tmp_path("target-upload");
            std::fs::write(&file, bytes).unwrap();
            store.put_target(id, record, &file)
        };
        let tumour = target_record("tumour");
        assert_eq!(put(b"one", &tumour).unwrap(), TargetStored::Created);
        assert_eq!(put(b"two", &tumour).unwrap(), TargetStored::Replaced);
        let file = store.target_file(id, &tumour);
        assert_eq!(std::fs::read(&file).unwrap(), b"two");
        // A replacement whose file cannot be moved in leaves the stored one whole.
        assert!(store
            .put_target(id, &tumour, &store.tmp_path("missing"))
            .is_err());
        assert_eq!(std::fs::read(&file).unwrap(), b"two");
        assert_eq!(store.target(id, "tumour").unwrap(), Some(tumour.clone()));
        assert_eq!(
            put(b"x", &target_record("gtv")).unwrap(),
            TargetStored::Created
        );
        let names: Vec<String> = store
            .list_targets(id)
            .unwrap()
            .into_iter()
            .map(|t| t.name)
            .collect();
        assert_eq!(names, ["gtv", "tumour"]);
        assert_eq!(store.target(id, "../scan.json").unwrap(), None);
        // A job keeps its copy when the scan's target goes.
        let job = JobRecord::queued(id);
        let request = JobRequest {
            config: RunConfig::default(),
            time_s: vec![0.0, 1.0],
            volume_ml: vec![0.0, 100.0],
            trace_source: "test".into(),
            points: vec![],
            callback_url: None,
            target: None,
            pacs_ct: None,
            push: false,
        };
        store.put_job(&job, &request, Some(&file)).unwrap();
        assert!(store.delete_target(id, "tumour").unwrap());
        assert!(!store.delete_target(id, "tumour").unwrap());
        let copy = store.job_target_dir(job.job_id).join("tumour.nii");
        assert_eq!(std::fs::read(copy).unwrap(), b"two");
        // Nothing is stored for a scan that is gone, and the scan is not brought back.
        assert!(store.delete_scan(id).unwrap());
        assert_eq!(put(b"late", &tumour).unwrap(), TargetStored::ScanMissing);
        assert!(!store.scan_dir(id).exists());
        let left: Vec<_> = std::fs::read_dir(store.tmp_dir())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .filter(|n| n != "writable")
            .collect();
        assert!(left.is_empty(), "{left:?}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn targets_with_an_object_store_are_objects_every_process_sees_and_go_with_deletion() {
        let dir =
            std::env::temp_dir().join(format!("lm-store-target-objects-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let blobs = file_blobs(&dir);
        // Two machines: the API process the target is uploaded to, and another.
        let api = shared_store(&dir.join("api"), &blobs);
        let other = shared_store(&dir.join("other"), &blobs);
        let scan = ScanId::random();
        let keys = |under: &str| -> Vec<String> {
            blobs
                .list(&format!("scans/{scan}/targets/{under}"))
                .unwrap()
                .into_iter()
                .map(|(k, _)| k)
                .collect()
        };
        let put = |store: &Store, bytes: &[u8], record: &TargetRecord| {
            let file = store.tmp_path("target-upload");
            std::fs::write(&file, bytes).unwrap();
            let stored = store.put_target(scan, record, &file);
            assert!(!file.exists(), "the upload is not left in tmp/");
            stored
        };
        let tumour = target_record("tumour");
        assert_eq!(put(&api, b"one", &tumour).unwrap(), TargetStored::Created);
        assert_eq!(other.target(scan, "tumour").unwrap(), Some(tumour.clone()));
        assert!(
            !api.scan_dir(scan).join(SCAN_TARGETS).exists(),
            "no copy in the data directory"
        );
        // Replaced from the other machine, as a different format: one record, one file.
        let mut replacement = target_record("tumour");
        replacement.file_name = "tumour.nrrd".into();
        replacement.format = "nrrd".into();
        assert_eq!(
            put(&other, b"two", &replacement).unwrap(),
            TargetStored::Replaced
        );
        let left = keys("tumour");
        assert_eq!(left.len(), 2, "{left:?}");
        assert!(left.contains(&"target.json".to_string()), "{left:?}");
        assert!(left.iter().any(|k| k.ends_with("/tumour.nrrd")), "{left:?}");
        assert_eq!(
            api.target(scan, "tumour").unwrap(),
            Some(replacement.clone())
        );
        // A replacement that cannot be read leaves the stored one as it was.
        assert!(api
            .put_target(scan, &tumour, &api.tmp_path("missing"))
            .is_err());
        assert_eq!(keys("tumour"), left);
        assert_eq!(
            api.target(scan, "tumour").unwrap(),
            Some(replacement.clone())
        );
        assert_eq!(
            put(&api, b"x", &target_record("gtv")).unwrap(),
            TargetStored::Created
        );
        let names: Vec<String> = other
            .list_targets(scan)
            .unwrap()
            .into_iter()
            .map(|t| t.name)
            .collect();
        assert_eq!(names, ["gtv", "tumour"]);
        assert_eq!(other.target(scan, "../x").unwrap(), None);
        // A job's copy: fetched for the submission, gone with its guard; none for a record
        // that is no longer the stored one.
        let copy = other
            .target_file_for_job(scan, &replacement)
            .unwrap()
            .expect("the stored target");
        assert_eq!(copy.path.file_name().unwrap(), "tumour.nrrd");
        assert_eq!(std::fs::read(&copy.path).unwrap(), b"two");
        let fetched = copy.path.clone();
        drop(copy);
        assert!(!fetched.exists() && !fetched.parent().unwrap().exists());
        assert!(other.target_file_for_job(scan, &tumour).unwrap().is_none());
        // Deleting a target removes its objects, from any machine.
        assert!(other.delete_target(scan, "gtv").unwrap());
        assert!(!api.delete_target(scan, "gtv").unwrap());
        assert!(keys("gtv").is_empty());
        assert_eq!(api.target(scan, "gtv").unwrap(), None);
        // Deleting the scan removes the rest.
        assert!(api.delete_scan(scan).unwrap());
        assert!(blobs.list(&format!("scans/{scan}")).unwrap().is_empty());
        assert!(other.list_targets(scan).unwrap().is_empty());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_corrupt_record_is_named_not_swallowed() {
        let (dir, store) = temp_store("corrupt");
        let id = JobId::random();
        std::fs::create_dir_all(store.job_dir(id)).unwrap();
        std::fs::write(store.job_dir(id).join(JOB_RECORD), b"{\"job_id\": ").unwrap();
        let (jobs, problems) = store.list_jobs().unwrap();
        assert!(jobs.is_empty());
        assert!(problems[0].contains("corrupt record"), "{problems:?}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}

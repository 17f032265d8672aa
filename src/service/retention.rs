//! Retention: finished jobs (done, failed, cancelled) and scans no queued, running or
//! cancelling job uses are removed once older than `retention_max_age_days`, then oldest
//! first while the store is larger than `retention_max_store_gib`; a tokio interval task
//! sweeps once at start and every `retention_interval_s`.
//!
//! A job's age runs from when it finished, a scan's from its last use (its upload or the
//! latest job submitted on it). A job whose completion callback is still being delivered is
//! kept until that ends. Each removal is one rename of the whole directory (record and files
//! together) into `tmp/` under the job board's lock, so no listing sees half of one and no job
//! can be submitted on a scan being removed.
//!
//! Each sweep also removes what killed processes left: the entries of a shared store's `tmp/`
//! whose process is gone ([`Store::sweep_shared_tmp`]) and, with an object store, the objects
//! of no scan or job record once an hour old ([`Store::sweep_orphan_blobs`]).

use std::collections::{HashMap, HashSet};
use std::path::Path;
use std::time::{Duration, SystemTime};

use super::backend::Jobs;
use super::config::RetentionSettings;
use super::ids::{JobId, ScanId};
use super::jobs::ScanRemoval;
use super::records::Records;
use super::routes::SharedState;
use super::store::{JobRecord, Store};
use crate::Result;

/// Bytes in a GiB.
const GIB: f64 = (1u64 << 30) as f64;

/// What one sweep found and did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SweepReport {
    /// Bytes the scans and jobs hold after the sweep.
    pub stored_bytes: u64,
    /// Jobs removed.
    pub jobs_removed: u64,
    /// Bytes of the jobs removed.
    pub job_bytes_removed: u64,
    /// Scans removed.
    pub scans_removed: u64,
    /// Bytes of the scans removed.
    pub scan_bytes_removed: u64,
}

/// Something retention may remove.
#[derive(Debug, Clone, Copy)]
enum Item {
    Job(JobId),
    Scan(ScanId),
}

/// A removable item with its age reference and size.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    item: Item,
    since: SystemTime,
    bytes: u64,
}

/// One sweep over the store at time `now` (see the module doc).
pub fn sweep(
    jobs: &Jobs,
    store: &Store,
    scan_records: &dyn Records,
    settings: &RetentionSettings,
    now: SystemTime,
) -> Result<SweepReport> {
    // What killed processes sharing the store left in tmp/ (an upload cut off, say).
    if let Err(e) = store.sweep_shared_tmp() {
        tracing::warn!("cannot sweep tmp/: {e}");
    }
    let records = jobs.records()?;
    let (scans, problems) = scan_records.list_scans()?;
    for p in problems {
        tracing::warn!("store: {p}");
    }
    let mut stored_bytes = 0u64;
    let mut candidates = Vec::new();
    let live_scans: HashSet<ScanId> = records
        .iter()
        .filter(|r| !r.state.is_terminal())
        .map(|r| r.scan_id)
        .collect();
    let mut last_job_on_scan: HashMap<ScanId, SystemTime> = HashMap::new();
    for record in &records {
        let bytes = store.job_bytes(record.job_id);
        stored_bytes += bytes;
        let submitted = parse_time(Some(&record.created_at), &store.job_dir(record.job_id));
        let last = last_job_on_scan.entry(record.scan_id).or_insert(submitted);
        *last = (*last).max(submitted);
        if record.state.is_terminal() {
            candidates.push(Candidate {
                item: Item::Job(record.job_id),
                since: finished_time(record, store),
                bytes,
            });
        }
    }
    // Objects of no scan or job (an API process killed between putting an upload and writing
    // its record).
    let scan_ids: HashSet<String> = scans.iter().map(|(s, _)| s.scan_id.to_string()).collect();
    let job_ids: HashSet<String> = records.iter().map(|r| r.job_id.to_string()).collect();
    if let Err(e) = store.sweep_orphan_blobs(&scan_ids, &job_ids, now) {
        tracing::warn!("cannot sweep the object store for objects of no record: {e}");
    }
    for (scan, _) in scans {
        // With an object store, its objects (the local copy is a cache).
        let bytes = store.scan_bytes(scan.scan_id);
        stored_bytes += bytes;
        if live_scans.contains(&scan.scan_id) {
            continue;
        }
        let uploaded = parse_time(Some(&scan.created_at), &store.scan_dir(scan.scan_id));
        let since = last_job_on_scan
            .get(&scan.scan_id)
            .map_or(uploaded, |t| (*t).max(uploaded));
        candidates.push(Candidate {
            item: Item::Scan(scan.scan_id),
            since,
            bytes,
        });
    }
    candidates.sort_by_key(|c| c.since);
    let max_age = (settings.max_age_days > 0.0)
        .then(|| Duration::from_secs_f64(settings.max_age_days * 86_400.0));
    let max_bytes = (settings.max_store_gib > 0.0).then_some((settings.max_store_gib * GIB) as u64);
    let mut report = SweepReport::default();
    for c in candidates {
        let expired =
            max_age.is_some_and(|age| now.duration_since(c.since).unwrap_or_default() > age);
        let over = max_bytes.is_some_and(|most| stored_bytes > most);
        if !expired && !over {
            // The rest are younger and the store is within its bound.
            break;
        }
        let removed = match c.item {
            Item::Job(id) => jobs.remove_expired(id)?,
            Item::Scan(id) => jobs.remove_unused_scan(id)? == ScanRemoval::Removed,
        };
        if !removed {
            continue;
        }
        stored_bytes = stored_bytes.saturating_sub(c.bytes);
        let why = if expired { "age" } else { "store size" };
        match c.item {
            Item::Job(id) => {
                report.jobs_removed += 1;
                report.job_bytes_removed += c.bytes;
                tracing::info!(job = %id, bytes = c.bytes, reason = why, "retention removed a finished job");
            }
            Item::Scan(id) => {
                report.scans_removed += 1;
                report.scan_bytes_removed += c.bytes;
                tracing::info!(scan = %id, bytes = c.bytes, reason = why, "retention removed an unused scan");
            }
        }
    }
    if let Some(most) = max_bytes.filter(|most| stored_bytes > *most) {
        tracing::warn!(
            stored_bytes,
            retention_max_store_bytes = most,
            "the store is over retention_max_store_gib with only live jobs and their scans left"
        );
    }
    report.stored_bytes = stored_bytes;
    Ok(report)
}

/// When a finished job finished (its submission when an older record lacks the time).
fn finished_time(record: &JobRecord, store: &Store) -> SystemTime {
    let when = record.finished_at.as_ref().unwrap_or(&record.created_at);
    parse_time(Some(when), &store.job_dir(record.job_id))
}

/// A record's RFC 3339 time, else the modification time of its directory, else now (so an
/// unreadable time never makes an item look old).
fn parse_time(text: Option<&String>, dir: &Path) -> SystemTime {
    text.and_then(|t| humantime::parse_rfc3339(t).ok())
        .or_else(|| std::fs::metadata(dir).and_then(|m| m.modified()).ok())
        .unwrap_or_else(SystemTime::now)
}

/// Sweeps once now and then every `retention_interval_s` on the HTTP runtime (the file
/// work on its blocking threads), updating the metrics after each sweep.
pub fn spawn_retention(state: SharedState) {
    tokio::spawn(async move {
        let period = Duration::from_secs_f64(state.config.retention.interval_s);
        let mut ticks = tokio::time::interval(period);
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            ticks.tick().await;
            let worker = state.clone();
            let swept = tokio::task::spawn_blocking(move || {
                sweep(
                    &worker.jobs,
                    &worker.store,
                    &*worker.records,
                    &worker.config.retention,
                    SystemTime::now(),
                )
            })
            .await;
            match swept {
                Ok(Ok(report)) => state.metrics.observe_retention(&report),
                Ok(Err(e)) => tracing::error!("retention sweep failed: {e}"),
                Err(e) => tracing::error!("retention sweep task failed: {e}"),
            }
        }
    });
}

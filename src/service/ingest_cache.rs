//! Scans read and ingested (CT, segmentation, mesh, groups, wall), kept in memory for the
//! jobs that follow, keyed by the scan and the settings that shape the ingest (element size,
//! material, diaphragm motion, series choice and segmentation settings), so several jobs on
//! one scan read and ingest it once, and a job with other settings ingests anew.
//!
//! The upload's own ingest is not among them: it runs in a child process (see
//! [`super::isolation`]) and its result cannot be handed over (the ingest of the POPI CT is
//! about 0.6 GB, most of it the CT and the wall's 1 mm distance field, and the model has no
//! file form yet), so the first job of a scan and settings reads and ingests it once more.
//!
//! Bounded by `ingest_cache_mib`: the least recently used entries go first, and an entry
//! larger than the whole budget is not kept.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;

use super::ids::ScanId;
use crate::run::{IngestedScan, RunConfig};

/// What an ingest depends on besides the scan.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IngestKey {
    scan: ScanId,
    settings: String,
}

impl IngestKey {
    /// The key of `scan` ingested with `config`'s ingest settings and series choice.
    pub fn new(scan: ScanId, config: &RunConfig) -> Self {
        IngestKey {
            scan,
            settings: format!(
                "{:?} {:?}",
                config.ingest_settings(),
                config.dicom_read_options()
            ),
        }
    }
}

struct Entry {
    key: IngestKey,
    ingested: Arc<IngestedScan>,
    bytes: u64,
}

/// The cache and its counters.
pub struct IngestCache {
    budget_bytes: u64,
    entries: Mutex<VecDeque<Entry>>,
    /// Jobs that found their scan's ingest here.
    pub reused: Counter,
    /// Jobs that read and ingested their scan.
    pub ingested: Counter,
    /// Bytes held.
    pub bytes: Gauge,
}

impl IngestCache {
    /// An empty cache holding at most `budget_mib` MiB (0: keeps nothing).
    pub fn new(budget_mib: u64) -> Self {
        IngestCache {
            budget_bytes: budget_mib.saturating_mul(1 << 20),
            entries: Mutex::new(VecDeque::new()),
            reused: Counter::default(),
            ingested: Counter::default(),
            bytes: Gauge::default(),
        }
    }

    fn entries(&self) -> MutexGuard<'_, VecDeque<Entry>> {
        self.entries.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The ingest stored under `key`, now the most recently used; counts a reuse.
    pub fn get(&self, key: &IngestKey) -> Option<Arc<IngestedScan>> {
        let mut entries = self.entries();
        let i = entries.iter().position(|e| &e.key == key)?;
        let entry = entries.remove(i)?;
        let found = entry.ingested.clone();
        entries.push_back(entry);
        self.reused.inc();
        Some(found)
    }

    /// Keeps `ingested` under `key` (a job's own ingest, counted as one), dropping the least
    /// recently used entries beyond the budget.
    pub fn insert_ingested(&self, key: IngestKey, ingested: Arc<IngestedScan>) {
        self.ingested.inc();
        self.insert(key, ingested);
    }

    /// Keeps `ingested` under `key`, dropping the least recently used beyond the budget.
    pub fn insert(&self, key: IngestKey, ingested: Arc<IngestedScan>) {
        let bytes = ingested.approximate_bytes();
        let mut entries = self.entries();
        entries.retain(|e| e.key != key);
        if bytes <= self.budget_bytes {
            entries.push_back(Entry {
                key,
                ingested,
                bytes,
            });
        }
        let mut held: u64 = entries.iter().map(|e| e.bytes).sum();
        while held > self.budget_bytes {
            let Some(oldest) = entries.pop_front() else {
                break;
            };
            held -= oldest.bytes;
        }
        self.bytes.set(held as i64);
    }

    /// Forgets every ingest of `scan` (it was deleted).
    pub fn forget_scan(&self, scan: ScanId) {
        let mut entries = self.entries();
        entries.retain(|e| e.key.scan != scan);
        self.bytes
            .set(entries.iter().map(|e| e.bytes).sum::<u64>() as i64);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_key_changes_with_the_settings_that_shape_the_ingest_only() {
        let scan = ScanId::random();
        let base = RunConfig::default();
        let key = IngestKey::new(scan, &base);
        let mut other_frames = base.clone();
        other_frames.outputs.quicklooks = !base.outputs.quicklooks;
        other_frames.motion.solve_every_frame = true;
        assert_eq!(IngestKey::new(scan, &other_frames), key);
        let coarser = RunConfig {
            element_size_mm: base.element_size_mm + 2.0,
            ..base.clone()
        };
        assert_ne!(IngestKey::new(scan, &coarser), key);
        let mut softer = base.clone();
        softer.material.youngs_modulus_pa *= 2.0;
        assert_ne!(IngestKey::new(scan, &softer), key);
        assert_ne!(IngestKey::new(ScanId::random(), &base), key);
    }
}

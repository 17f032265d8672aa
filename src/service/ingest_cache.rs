//! Scans read and ingested (CT, segmentation, mesh, groups, wall), kept in memory for the
//! jobs that follow, keyed by the scan and the settings that shape the ingest (element size,
//! material, diaphragm motion, series choice and segmentation settings), so several jobs on
//! one scan read and ingest it once, and a job with other settings ingests anew.
//!
//! The upload's own ingest runs in a child process (see [`super::isolation`]), whose memory
//! cannot be handed over (about 0.6 GB for the POPI CT, most of it the CT and the wall's 1 mm
//! distance field). It leaves its costly part in the scan's directory instead, in the file
//! form of [`crate::ingest::stored`] (segmentation and wall field, keyed by the same ingest
//! identity as this cache): the first job of a scan whose settings match reads the CT and
//! that file and rebuilds the rest of the model (on the POPI CT at 8 mm, 1.4 s of ingest
//! stage instead of 9.7 s, measured under load); a job with other settings, or a file that cannot be trusted, ingests anew.
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
            settings: config.ingest_identity(),
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
    /// Jobs that read their scan and took its ingest from the file its upload stored.
    pub stored: Counter,
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
            stored: Counter::default(),
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

    /// Keeps `ingested` under `key` (a job's ingest taken from its scan's stored ingest,
    /// counted as one), dropping the least recently used entries beyond the budget.
    pub fn insert_from_stored(&self, key: IngestKey, ingested: Arc<IngestedScan>) {
        self.stored.inc();
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

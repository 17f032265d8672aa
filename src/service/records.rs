//! Where the service keeps its job and scan records, behind one interface: the data
//! directory ([`Store`], one JSON file per record) or PostgreSQL (rows; see
//! [`super::postgres`]). The files themselves (uploads, targets, outputs) are in the data
//! directory, or in the object store when one is configured ([`super::blobs`]), with either
//! backend; only the records (and with PostgreSQL the queue) move.

use std::path::Path;

use super::ids::{JobId, ScanId};
use super::store::{JobRecord, JobRequest, ScanRecord, Store, StoredScan};
use crate::Result;

/// The job and scan records of the service, whichever backend holds them.
pub trait Records: Send + Sync {
    /// Stores a scan: moves the received `upload` into the scan's directory and records it,
    /// all at once.
    fn put_scan(&self, record: &ScanRecord, upload: &Path) -> Result<()>;
    /// A scan's record, `None` when there is no such scan.
    fn scan(&self, id: ScanId) -> Result<Option<ScanRecord>>;
    /// Removes a scan and its files; `false` when there was none.
    fn delete_scan(&self, id: ScanId) -> Result<bool>;
    /// Every scan record with the bytes its directory holds; unreadable ones are reported.
    fn list_scans(&self) -> Result<(Vec<StoredScan>, Vec<String>)>;
    /// Stores a new job: its record, its request and its copy of the target file `target`.
    fn put_job(
        &self,
        record: &JobRecord,
        request: &JobRequest,
        target: Option<&Path>,
    ) -> Result<()>;
    /// Replaces a job's record.
    fn save_job(&self, record: &JobRecord) -> Result<()>;
    /// A job's record, `None` when there is no such job.
    fn job(&self, id: JobId) -> Result<Option<JobRecord>>;
    /// A job's request.
    fn job_request(&self, id: JobId) -> Result<JobRequest>;
    /// Removes a job, its record and its files; `false` when there was none.
    fn delete_job(&self, id: JobId) -> Result<bool>;
    /// Every job record, oldest first; unreadable ones are reported, not fatal.
    fn list_jobs(&self) -> Result<(Vec<JobRecord>, Vec<String>)>;
}

impl Records for Store {
    fn put_scan(&self, record: &ScanRecord, upload: &Path) -> Result<()> {
        Store::put_scan(self, record, upload)
    }
    fn scan(&self, id: ScanId) -> Result<Option<ScanRecord>> {
        Store::scan(self, id)
    }
    fn delete_scan(&self, id: ScanId) -> Result<bool> {
        Store::delete_scan(self, id)
    }
    fn list_scans(&self) -> Result<(Vec<StoredScan>, Vec<String>)> {
        Store::list_scans(self)
    }
    fn put_job(
        &self,
        record: &JobRecord,
        request: &JobRequest,
        target: Option<&Path>,
    ) -> Result<()> {
        Store::put_job(self, record, request, target)
    }
    fn save_job(&self, record: &JobRecord) -> Result<()> {
        Store::save_job(self, record)
    }
    fn job(&self, id: JobId) -> Result<Option<JobRecord>> {
        Store::job(self, id)
    }
    fn job_request(&self, id: JobId) -> Result<JobRequest> {
        Store::job_request(self, id)
    }
    fn delete_job(&self, id: JobId) -> Result<bool> {
        Store::delete_job(self, id)
    }
    fn list_jobs(&self) -> Result<(Vec<JobRecord>, Vec<String>)> {
        Store::list_jobs(self)
    }
}

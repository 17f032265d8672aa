//! Prometheus metrics (OpenMetrics text at `/metrics`): requests by route and status, their
//! latency, jobs by state, the queue and upload volume, the store's size and what retention
//! removed, and completion callbacks. Routes are the matched templates
//! (`/v1/jobs/{id}`), never the ids, so the label set stays bounded.

use std::sync::Mutex;

use prometheus_client::encoding::text::encode;
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::registry::Registry;

use super::ingest_cache::IngestCache;
use super::jobs::JobCounts;
use super::retention::SweepReport;
use super::store::JobState;

/// Labels of an HTTP request.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RequestLabels {
    method: String,
    route: String,
    status: u16,
}

/// Labels of a latency series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RouteLabels {
    method: String,
    route: String,
}

/// Labels of what retention removed: `job` or `scan`.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct KindLabels {
    kind: &'static str,
}

/// Labels of a callback attempt: `delivered` or `failed`.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct OutcomeLabels {
    outcome: &'static str,
}

/// Labels of a worker process's series (PostgreSQL): its id.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct WorkerLabels {
    worker: String,
}

/// Labels of a worker process's finished jobs: its id and how they ended.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct WorkerOutcomeLabels {
    worker: String,
    state: &'static str,
}

/// Labels of the job gauge.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StateLabels {
    state: &'static str,
}

/// Upper bounds of the latency buckets, s.
const LATENCY_BUCKETS_S: [f64; 12] = [
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.1, 0.5, 2.5, 10.0,
];

type LatencyFamily = Family<RouteLabels, Histogram, fn() -> Histogram>;

/// The service's metrics.
pub struct ServiceMetrics {
    registry: Mutex<Registry>,
    requests: Family<RequestLabels, Counter>,
    latency: LatencyFamily,
    jobs: Family<StateLabels, Gauge>,
    queue_depth: Gauge,
    running: Gauge,
    upload_bytes: Counter,
    scans_ingested: Counter,
    store_bytes: Gauge,
    retention_removed: Family<KindLabels, Counter>,
    retention_removed_bytes: Family<KindLabels, Counter>,
    callback_attempts: Family<OutcomeLabels, Counter>,
    worker_running: Family<WorkerLabels, Gauge>,
    worker_threads: Family<WorkerLabels, Gauge>,
    worker_seen: Family<WorkerLabels, Gauge<f64, std::sync::atomic::AtomicU64>>,
    worker_finished: Family<WorkerOutcomeLabels, Gauge>,
}

fn latency_histogram() -> Histogram {
    // A status read is sub-millisecond, an upload with its ingest seconds.
    Histogram::new(LATENCY_BUCKETS_S.iter().copied())
}

impl Default for ServiceMetrics {
    fn default() -> Self {
        let mut registry = Registry::default();
        let requests = Family::<RequestLabels, Counter>::default();
        registry.register(
            "lungmotion_http_requests",
            "HTTP requests answered, by method, route template and status",
            requests.clone(),
        );
        let latency: LatencyFamily = Family::new_with_constructor(latency_histogram);
        registry.register(
            "lungmotion_http_request_duration_seconds",
            "Time to answer a request (headers; streamed bodies may take longer)",
            latency.clone(),
        );
        let jobs = Family::<StateLabels, Gauge>::default();
        registry.register(
            "lungmotion_jobs",
            "Jobs in the store, by state",
            jobs.clone(),
        );
        let queue_depth = Gauge::default();
        registry.register(
            "lungmotion_queue_depth",
            "Jobs waiting for a worker",
            queue_depth.clone(),
        );
        let running = Gauge::default();
        registry.register(
            "lungmotion_jobs_running",
            "Jobs running now",
            running.clone(),
        );
        let upload_bytes = Counter::default();
        registry.register(
            "lungmotion_upload_bytes",
            "Scan bytes received",
            upload_bytes.clone(),
        );
        let scans_ingested = Counter::default();
        registry.register(
            "lungmotion_scans_ingested",
            "Scans uploaded and ingested",
            scans_ingested.clone(),
        );
        let store_bytes = Gauge::default();
        registry.register(
            "lungmotion_store_bytes",
            "Bytes the stored scans and jobs hold, as of the latest retention sweep",
            store_bytes.clone(),
        );
        let retention_removed = Family::<KindLabels, Counter>::default();
        registry.register(
            "lungmotion_retention_removed",
            "Finished jobs and unused scans removed by retention, by kind",
            retention_removed.clone(),
        );
        let retention_removed_bytes = Family::<KindLabels, Counter>::default();
        registry.register(
            "lungmotion_retention_removed_bytes",
            "Bytes freed by retention, by kind",
            retention_removed_bytes.clone(),
        );
        let callback_attempts = Family::<OutcomeLabels, Counter>::default();
        registry.register(
            "lungmotion_callback_attempts",
            "Completion callback POSTs, by outcome (delivered: a 2xx answer)",
            callback_attempts.clone(),
        );
        let worker_running = Family::<WorkerLabels, Gauge>::default();
        registry.register(
            "lungmotion_worker_running",
            "Jobs a worker process runs now (PostgreSQL store), as it last reported",
            worker_running.clone(),
        );
        let worker_threads = Family::<WorkerLabels, Gauge>::default();
        registry.register(
            "lungmotion_worker_threads",
            "Simulation threads of a worker process (PostgreSQL store)",
            worker_threads.clone(),
        );
        let worker_seen =
            Family::<WorkerLabels, Gauge<f64, std::sync::atomic::AtomicU64>>::default();
        registry.register(
            "lungmotion_worker_last_report_age_seconds",
            "Seconds since a worker process last reported (every third of a lease while alive)",
            worker_seen.clone(),
        );
        let worker_finished = Family::<WorkerOutcomeLabels, Gauge>::default();
        registry.register(
            "lungmotion_worker_jobs_finished",
            "Jobs a worker process finished since it started, by final state",
            worker_finished.clone(),
        );
        ServiceMetrics {
            registry: Mutex::new(registry),
            worker_running,
            worker_threads,
            worker_seen,
            worker_finished,
            store_bytes,
            retention_removed,
            retention_removed_bytes,
            callback_attempts,
            requests,
            latency,
            jobs,
            queue_depth,
            running,
            upload_bytes,
            scans_ingested,
        }
    }
}

impl ServiceMetrics {
    /// Counts one answered request.
    pub fn observe_request(&self, method: &str, route: &str, status: u16, seconds: f64) {
        self.requests
            .get_or_create(&RequestLabels {
                method: method.to_string(),
                route: route.to_string(),
                status,
            })
            .inc();
        self.latency
            .get_or_create(&RouteLabels {
                method: method.to_string(),
                route: route.to_string(),
            })
            .observe(seconds);
    }

    /// Counts a stored scan and its bytes.
    pub fn observe_upload(&self, bytes: u64) {
        self.upload_bytes.inc_by(bytes);
        self.scans_ingested.inc();
    }

    /// Records a retention sweep: the store's size and what it removed.
    pub fn observe_retention(&self, report: &SweepReport) {
        self.store_bytes
            .set(i64::try_from(report.stored_bytes).unwrap_or(i64::MAX));
        for (kind, items, bytes) in [
            ("job", report.jobs_removed, report.job_bytes_removed),
            ("scan", report.scans_removed, report.scan_bytes_removed),
        ] {
            let labels = KindLabels { kind };
            self.retention_removed.get_or_create(&labels).inc_by(items);
            self.retention_removed_bytes
                .get_or_create(&labels)
                .inc_by(bytes);
        }
    }

    /// Counts one completion callback POST.
    pub fn observe_callback_attempt(&self, delivered: bool) {
        let outcome = if delivered { "delivered" } else { "failed" };
        self.callback_attempts
            .get_or_create(&OutcomeLabels { outcome })
            .inc();
    }

    /// Adds the ingest cache's series: jobs that reused an ingest, jobs that ingested, jobs
    /// that took their scan's stored ingest, and the bytes the cache holds.
    pub fn register_ingest_cache(&self, cache: &IngestCache) {
        let mut registry = self.registry.lock().unwrap_or_else(|p| p.into_inner());
        registry.register(
            "lungmotion_job_ingests_reused",
            "Jobs that reused a scan read and ingested with the same settings by an earlier job",
            cache.reused.clone(),
        );
        registry.register(
            "lungmotion_job_ingests",
            "Jobs that read and ingested their scan",
            cache.ingested.clone(),
        );
        registry.register(
            "lungmotion_job_ingests_stored",
            "Jobs that read their scan and took its segmentation and wall from the ingest its upload stored",
            cache.stored.clone(),
        );
        registry.register(
            "lungmotion_ingest_cache_bytes",
            "Memory held by scans kept read and ingested for the next job (approximate)",
            cache.bytes.clone(),
        );
    }

    /// The text exposition, with the job gauges read from `counts` now.
    pub fn render(&self, counts: &JobCounts) -> String {
        for (state, n) in JobState::ALL.iter().zip(counts.by_state) {
            self.jobs
                .get_or_create(&StateLabels {
                    state: state.name(),
                })
                .set(n as i64);
        }
        self.queue_depth.set(counts.queued as i64);
        self.running.set(counts.running as i64);
        // Workers that stopped reporting drop out of the exposition.
        self.worker_running.clear();
        self.worker_threads.clear();
        self.worker_seen.clear();
        self.worker_finished.clear();
        for w in &counts.workers {
            let labels = WorkerLabels {
                worker: w.worker_id.clone(),
            };
            self.worker_running.get_or_create(&labels).set(w.running);
            self.worker_threads.get_or_create(&labels).set(w.threads);
            self.worker_seen.get_or_create(&labels).set(w.seen_s_ago);
            for (state, n) in [
                ("done", w.done),
                ("failed", w.failed),
                ("cancelled", w.cancelled),
            ] {
                self.worker_finished
                    .get_or_create(&WorkerOutcomeLabels {
                        worker: w.worker_id.clone(),
                        state,
                    })
                    .set(n);
            }
        }
        let mut text = String::new();
        let registry = self.registry.lock().unwrap_or_else(|p| p.into_inner());
        if encode(&mut text, &registry).is_err() {
            text.clear();
        }
        text
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposition_names_the_series() {
        let m = ServiceMetrics::default();
        m.observe_request("GET", "/v1/jobs/{id}", 200, 0.001);
        m.observe_upload(1234);
        let counts = JobCounts {
            by_state: [2, 1, 0, 0, 0, 0],
            queued: 2,
            running: 1,
            workers: vec![crate::service::postgres::WorkerStatus {
                worker_id: "host-1-ab".into(),
                threads: 2,
                running: 1,
                done: 5,
                ..Default::default()
            }],
        };
        let text = m.render(&counts);
        assert!(text.contains(
            "lungmotion_http_requests_total{method=\"GET\",route=\"/v1/jobs/{id}\",status=\"200\"} 1"
        ), "{text}");
        assert!(
            text.contains("lungmotion_upload_bytes_total 1234"),
            "{text}"
        );
        assert!(
            text.contains("lungmotion_jobs{state=\"queued\"} 2"),
            "{text}"
        );
        assert!(text.contains("lungmotion_queue_depth 2"), "{text}");
        for series in [
            "lungmotion_worker_running{worker=\"host-1-ab\"} 1",
            "lungmotion_worker_jobs_finished{worker=\"host-1-ab\",state=\"done\"} 5",
        ] {
            assert!(text.contains(series), "{series} missing: {text}");
        }
        m.observe_retention(&SweepReport {
            stored_bytes: 5000,
            jobs_removed: 2,
            job_bytes_removed: 700,
            scans_removed: 1,
            scan_bytes_removed: 300,
        });
        m.observe_callback_attempt(false);
        let text = m.render(&counts);
        for series in [
            "lungmotion_store_bytes 5000",
            "lungmotion_retention_removed_total{kind=\"job\"} 2",
            "lungmotion_retention_removed_bytes_total{kind=\"scan\"} 300",
            "lungmotion_callback_attempts_total{outcome=\"failed\"} 1",
        ] {
            assert!(text.contains(series), "{series} missing: {text}");
        }
        assert!(
            text.contains("lungmotion_http_request_duration_seconds_bucket"),
            "{text}"
        );
    }
}

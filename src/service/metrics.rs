//! Prometheus metrics (OpenMetrics text at `/metrics`): requests by route and status, their
//! latency, jobs by state, the queue and upload volume. Routes are the matched templates
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
        ServiceMetrics {
            registry: Mutex::new(registry),
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

    /// Adds the ingest cache's series: jobs that reused an ingest, jobs that ingested, and
    /// the bytes the cache holds.
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
        assert!(
            text.contains("lungmotion_http_request_duration_seconds_bucket"),
            "{text}"
        );
    }
}

//! The OpenAPI 3.1 document served at `/openapi.json`, generated from the handlers' and
//! types' annotations so that it describes exactly what the code does.

use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi};

use super::problem::Problem;
use super::routes::{
    self, FrameEntry, FrameList, Health, JobLinks, JobStatus, ScanLinks, ScanView,
    SimulationRequest, TraceBody,
};
use super::store::{JobProgress, JobRecord, JobState, ScanRecord, StoredPoint};

/// The API description.
#[derive(OpenApi)]
#[openapi(
    info(
        title = "lungmotion",
        description = "Predicts how every point of a patient's lungs moves while they breathe: \
            upload a CT, submit a breathing curve, fetch a displacement field per instant \
            (NIfTI vector images, LPS millimetres). Errors are application/problem+json. \
            Every answer carries an `x-request-id` header (also in problem bodies and the \
            server's log): the client's own when it is 1–64 characters of `[A-Za-z0-9._-]`, \
            otherwise (or when absent) a fresh UUID. A request body that pauses longer than \
            body_read_timeout_s is answered 408; headers slower than header_read_timeout_s \
            close the connection.",
    ),
    paths(
        routes::upload_scan,
        routes::get_scan,
        routes::delete_scan,
        routes::create_simulation,
        routes::get_job,
        routes::delete_job,
        routes::job_summary,
        routes::job_frames,
        routes::frame_displacement,
        routes::job_trajectories,
        routes::healthz,
        routes::readyz,
        routes::metrics,
    ),
    components(schemas(
        Problem, ScanView, ScanLinks, ScanRecord, JobStatus, JobRecord, JobLinks, JobProgress,
        JobState,
        SimulationRequest, TraceBody, StoredPoint, FrameList, FrameEntry, Health
    )),
    modifiers(&BearerAuth),
    tags(
        (name = "scans", description = "CT uploads and their ingest"),
        (name = "jobs", description = "Simulations and their progress"),
        (name = "results", description = "Displacement fields, trajectories, summaries"),
        (name = "operations", description = "Health, readiness and metrics"),
    )
)]
pub struct ApiDoc;

struct BearerAuth;

impl Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
        );
    }
}

/// The document, with this build's version.
pub fn openapi_document() -> utoipa::openapi::OpenApi {
    let mut doc = ApiDoc::openapi();
    doc.info.version = env!("CARGO_PKG_VERSION").to_string();
    doc
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_route_is_documented() {
        let doc = serde_json::to_value(openapi_document()).unwrap();
        let paths = doc["paths"].as_object().unwrap();
        for p in [
            "/v1/scans",
            "/v1/scans/{id}",
            "/v1/scans/{id}/simulations",
            "/v1/jobs/{id}",
            "/v1/jobs/{id}/summary",
            "/v1/jobs/{id}/frames",
            "/v1/jobs/{id}/frames/{k}/displacement",
            "/v1/jobs/{id}/trajectories",
            "/healthz",
            "/readyz",
            "/metrics",
        ] {
            assert!(
                paths.contains_key(p),
                "{p} missing from the OpenAPI document"
            );
        }
        assert!(doc["openapi"].as_str().unwrap().starts_with("3.1"));
        assert!(doc["components"]["securitySchemes"]["bearer"].is_object());
        assert!(doc["components"]["schemas"]["JobStatus"].is_object());
        // The trace's options sit beside its samples, as in the CLI's [trace] table.
        let trace = &doc["components"]["schemas"]["TraceBody"]["properties"];
        for key in [
            "time_s",
            "time_ms",
            "volume_ml",
            "volume_l",
            "reference",
            "seconds_per_time_unit",
            "ml_per_volume_unit",
        ] {
            assert!(trace[key].is_object(), "TraceBody lacks {key}: {trace}");
        }
        let description = doc["info"]["description"].as_str().unwrap();
        assert!(description.contains("[A-Za-z0-9._-]"), "{description}");
    }
}

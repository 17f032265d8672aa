//! The OpenAPI 3.1 document served at `/openapi.json`, generated from the handlers' and
//! types' annotations so that it describes exactly what the code does; the run options'
//! schema is in [`run_options`], checked against the run configuration's keys.

use serde_json::{json, Value};
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi};

use super::callbacks::{
    CallbackBody, CallbackDelivery, CallbackState, MAX_CALLBACK_URL_CHARS, SIGNATURE_HEADER,
    TIMESTAMP_HEADER,
};
use super::problem::Problem;
use super::routes::{
    self, FrameEntry, FrameList, Health, JobLinks, JobPage, JobStatus, OutputFile, OutputFileList,
    ScanLinks, ScanPage, ScanView, SimulationRequest, TargetLinks, TargetList, TargetView,
    TraceBody,
};
use super::store::{
    JobProgress, JobRecord, JobState, PacsActivity, PacsSeries, ScanRecord, StoredPoint,
};
use super::targets::{MaskLabel, StructureRoi, TargetKind, TargetRecord, MAX_TARGET_NAME_CHARS};

pub mod run_options;

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
        routes::list_scans,
        routes::get_scan,
        routes::delete_scan,
        routes::put_target,
        routes::list_targets,
        routes::get_target,
        routes::delete_target,
        routes::create_simulation,
        routes::create_pacs_simulation,
        routes::list_jobs,
        routes::get_job,
        routes::delete_job,
        routes::job_summary,
        routes::job_frames,
        routes::frame_displacement,
        routes::job_trajectories,
        routes::job_files,
        routes::job_file,
        routes::job_archive,
        routes::healthz,
        routes::readyz,
        routes::metrics,
    ),
    components(schemas(
        Problem, ScanView, ScanLinks, ScanRecord, JobStatus, JobRecord, JobLinks, JobProgress,
        JobState, CallbackBody, CallbackDelivery, CallbackState,
        SimulationRequest, TraceBody, StoredPoint, FrameList, FrameEntry, Health, OutputFile,
        OutputFileList, ScanPage, JobPage, PacsSeries, PacsActivity, TargetView, TargetLinks,
        TargetList, TargetRecord, TargetKind, MaskLabel, StructureRoi
    )),
    modifiers(&BearerAuth),
    tags(
        (name = "scans", description = "CT uploads and their ingest, and the treatment targets \
            (masks, RTSTRUCTs) uploaded to them"),
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

/// The document, with this build's version, the 401 answer of every operation that needs
/// the token, and the run options as a schema.
pub fn openapi_document() -> Value {
    let mut doc = ApiDoc::openapi();
    doc.info.version = env!("CARGO_PKG_VERSION").to_string();
    let mut doc = serde_json::to_value(doc).unwrap_or_else(|e| {
        json!({"openapi": "3.1.0", "info": {"title": "lungmotion", "description": e.to_string()}})
    });
    declare_unauthorized(&mut doc);
    describe_run_options(&mut doc);
    describe_callbacks(&mut doc);
    doc
}

/// Describes the completion callback on the simulation's operation: the POST the server makes
/// to the request's `callback_url`, its body and its two signature headers.
fn describe_callbacks(doc: &mut Value) {
    let Some(operation) = doc.pointer_mut("/paths/~1v1~1scans~1{id}~1simulations/post") else {
        return;
    };
    operation["callbacks"] = json!({
        "jobFinished": {
            "{$request.body#/callback_url}": {
                "post": {
                    "summary": "The job ended (done, failed or cancelled)",
                    "description": "Sent once the job ends, at least once: retried with \
                        exponential backoff (callback_retry_base_s doubled per attempt, at most \
                        5 min apart, callback_max_attempts POSTs of callback_timeout_s each) \
                        until a 2xx answer; a 4xx other than 408 and 429 stops the retries. \
                        Redirects are not followed. Verify the signature over the raw bytes \
                        `<X-Lungmotion-Timestamp>.<body>` with the server's callback secret \
                        (HMAC-SHA256, constant-time comparison) and refuse timestamps more than \
                        a few minutes old. The outcome is in the job's `callback`.",
                    "parameters": [
                        {"name": SIGNATURE_HEADER, "in": "header", "required": true,
                         "description": "`sha256=` and the lowercase hex HMAC-SHA256 of \
                            `<timestamp>.<body>` keyed by the callback secret",
                         "schema": {"type": "string", "pattern": "^sha256=[0-9a-f]{64}$"}},
                        {"name": TIMESTAMP_HEADER, "in": "header", "required": true,
                         "description": "When the POST was signed, Unix seconds; part of the \
                            signed bytes",
                         "schema": {"type": "string", "pattern": "^[0-9]+$"}},
                    ],
                    "requestBody": {"required": true, "content": {"application/json": {
                        "schema": {"$ref": "#/components/schemas/CallbackBody"}}}},
                    "responses": {
                        "2XX": {"description": "Delivered; not sent again"},
                        "4XX": {"description": "Refused; not sent again (except 408 and 429)"},
                        "5XX": {"description": "Sent again after the backoff"}
                    }
                }
            }
        }
    });
}

/// Adds the `401` answer to every operation that declares a security requirement.
fn declare_unauthorized(doc: &mut Value) {
    let Some(paths) = doc.get_mut("paths").and_then(Value::as_object_mut) else {
        return;
    };
    for operation in paths
        .values_mut()
        .filter_map(Value::as_object_mut)
        .flat_map(|item| item.values_mut())
    {
        let secured = operation
            .get("security")
            .and_then(Value::as_array)
            .is_some_and(|s| !s.is_empty());
        if let (true, Some(responses)) = (
            secured,
            operation
                .get_mut("responses")
                .and_then(Value::as_object_mut),
        ) {
            responses.entry("401").or_insert_with(|| {
                json!({
                    "description": "Missing or wrong bearer token (LUNGMOTION_API_TOKEN)",
                    "content": {"application/problem+json": {
                        "schema": {"$ref": "#/components/schemas/Problem"}
                    }}
                })
            });
        }
    }
}

/// Puts the run options' schema in the components and makes the simulation request the
/// trace and points beside them.
fn describe_run_options(doc: &mut Value) {
    let Some(schemas) = doc
        .pointer_mut("/components/schemas")
        .and_then(Value::as_object_mut)
    else {
        return;
    };
    schemas.insert("RunOptions".into(), run_options::schema());
    schemas.insert(
        "SimulationRequest".into(),
        json!({
            "description": "A simulation request: the breathing trace, points to track, and \
                any run option (see RunOptions), merged over the server's [run] defaults \
                (objects key by key; a tagged choice such as motion.instants replaces the \
                default whole). Unknown keys are refused (422) by name.",
            "allOf": [
                {
                    "type": "object",
                    "required": ["trace"],
                    "properties": {
                        "trace": {"$ref": "#/components/schemas/TraceBody"},
                        "points": {
                            "type": "array",
                            "description": "Points to track (LPS mm, at the scanned state)",
                            "items": {"$ref": "#/components/schemas/StoredPoint"}
                        },
                        "callback_url": {
                            "type": "string",
                            "format": "uri",
                            "maxLength": MAX_CALLBACK_URL_CHARS,
                            "description": "Where to POST the job's outcome when it ends \
                                (see the operation's callbacks). https, or http to loopback \
                                (beyond it only when the server sets \
                                callback_allow_plain_http); no user:password@. Refused (422) \
                                when the server has no callback secret."
                        },
                        "ct": {
                            "type": "object",
                            "description": "The CT as a series on the server's PACS (only at \
                                POST /v1/simulations; 422 no-pacs when the server has none)",
                            "required": ["dicomweb"],
                            "additionalProperties": false,
                            "properties": {
                                "dicomweb": {"$ref": "#/components/schemas/PacsSeries"}
                            }
                        },
                        "target": {
                            "description": "The treatment target to follow (per-frame masks, \
                                ITV, centroid motion per axis, RTSTRUCT; files under \
                                target/ and target-motion.csv, figures in summary.json → \
                                target): a point and radius, or a file uploaded to the scan \
                                (PUT /v1/scans/{id}/targets/{name}). Never a path on the \
                                server's disk. An upload is checked against the scan's target \
                                when the job is submitted (unknown name, label not in the \
                                mask, ROI missing or unusable: 422) and the job keeps its own \
                                copy; only at POST /v1/scans/{id}/simulations.",
                            "oneOf": [
                                {
                                    "type": "string",
                                    "pattern": "^point:",
                                    "description": "point:<x>,<y>,<z>:r=<radius mm>, LPS mm \
                                        (radius up to 150 mm)",
                                    "examples": ["point:-95,20,-80:r=15"]
                                },
                                {
                                    "type": "object",
                                    "description": "A mask uploaded to the scan, every \
                                        nonzero voxel or one label",
                                    "required": ["upload"],
                                    "additionalProperties": false,
                                    "properties": {
                                        "upload": {
                                            "type": "string",
                                            "pattern": "^[A-Za-z0-9][A-Za-z0-9._-]*$",
                                            "maxLength": MAX_TARGET_NAME_CHARS,
                                            "description": "The target's name on the scan"
                                        },
                                        "label": {
                                            "type": "integer",
                                            "minimum": 1,
                                            "maximum": 255,
                                            "description": "Only this label is the target"
                                        }
                                    }
                                },
                                {
                                    "type": "object",
                                    "description": "An ROI of an RTSTRUCT uploaded to the scan",
                                    "required": ["upload", "roi"],
                                    "additionalProperties": false,
                                    "properties": {
                                        "upload": {
                                            "type": "string",
                                            "pattern": "^[A-Za-z0-9][A-Za-z0-9._-]*$",
                                            "maxLength": MAX_TARGET_NAME_CHARS,
                                            "description": "The target's name on the scan"
                                        },
                                        "roi": {
                                            "type": "string",
                                            "minLength": 1,
                                            "description": "ROIName (exact, else the one name \
                                                equal ignoring case)"
                                        }
                                    }
                                }
                            ]
                        },
                        "push": {
                            "type": "boolean",
                            "description": "Push the DICOM outputs (virtual CT series, REGs, \
                                RTSTRUCT) to the server's PACS when the run succeeds, skipping \
                                the instances it already holds (so a re-run pushes nothing \
                                twice); default: the server's [pacs] push. A refusal by the PACS \
                                fails the job with the server's answer."
                        }
                    }
                },
                {"$ref": "#/components/schemas/RunOptions"}
            ]
        }),
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_route_is_documented() {
        let doc = openapi_document();
        let paths = doc["paths"].as_object().unwrap();
        for p in [
            "/v1/scans",
            "/v1/scans/{id}",
            "/v1/scans/{id}/simulations",
            "/v1/scans/{id}/targets",
            "/v1/scans/{id}/targets/{name}",
            "/v1/simulations",
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
        // The completion callback: its field, its POST, its body and both signature headers.
        let request = &doc["components"]["schemas"]["SimulationRequest"]["allOf"][0];
        assert_eq!(
            request["properties"]["callback_url"]["maxLength"], MAX_CALLBACK_URL_CHARS,
            "{request}"
        );
        let callback = &doc["paths"]["/v1/scans/{id}/simulations"]["post"]["callbacks"]
            ["jobFinished"]["{$request.body#/callback_url}"]["post"];
        let headers: Vec<&str> = callback["parameters"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["name"].as_str().unwrap())
            .collect();
        assert_eq!(headers, [SIGNATURE_HEADER, TIMESTAMP_HEADER], "{callback}");
        assert_eq!(
            callback["requestBody"]["content"]["application/json"]["schema"]["$ref"],
            "#/components/schemas/CallbackBody"
        );
        let body = &doc["components"]["schemas"]["CallbackBody"]["properties"];
        for key in ["event", "job_id", "state", "error", "links"] {
            assert!(body[key].is_object(), "CallbackBody lacks {key}: {body}");
        }
        let record = &doc["components"]["schemas"]["JobRecord"]["properties"];
        assert!(record["callback"].is_object(), "{record}");
        // A job's CT from the PACS and the push of its outputs.
        assert!(request["properties"]["ct"]["properties"]["dicomweb"].is_object());
        assert!(request["properties"]["push"].is_object(), "{request}");
        assert!(record["pacs"].is_object(), "{record}");
        // The target: a point, an uploaded mask with its label or an RTSTRUCT with its ROI.
        let target = &request["properties"]["target"]["oneOf"];
        assert_eq!(target[0]["type"], "string", "{target}");
        assert!(target[1]["properties"]["label"].is_object(), "{target}");
        assert!(target[2]["properties"]["roi"].is_object(), "{target}");
        let upload = &doc["paths"]["/v1/scans/{id}/targets/{name}"];
        for method in ["put", "get", "delete"] {
            assert!(upload[method].is_object(), "{method} {upload}");
        }
        assert!(upload["put"]["responses"]["422"].is_object());
        let record = &doc["components"]["schemas"]["TargetRecord"]["properties"];
        for key in ["kind", "labels", "rois", "notes"] {
            assert!(
                record[key].is_object(),
                "TargetRecord lacks {key}: {record}"
            );
        }
        let series = &doc["components"]["schemas"]["PacsSeries"]["properties"];
        assert!(
            series["study"].is_object() && series["series"].is_object(),
            "{series}"
        );
    }
}

//! A simulation request, JSON or CSV, turned into a job request: the body parsed, its options
//! merged over the server's run defaults, and everything checked that can be without running.

use axum::http::StatusCode;
use serde::Deserialize;
use serde_json::Value;
use utoipa::ToSchema;

use super::problem::{ApiError, ApiResult};
use super::store::{JobRequest, StoredPoint};
use crate::breathing::BreathingTrace;
use crate::run::RunConfig;

/// A breathing trace in a JSON request.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TraceBody {
    /// Sample times, s, strictly increasing.
    pub time_s: Vec<f64>,
    /// Lung volume change from the scanned state, mL.
    pub volume_ml: Vec<f64>,
}

/// A simulation request: the trace, points to track, and any `lungmotion run` option.
#[derive(Debug, Deserialize, ToSchema)]
pub struct SimulationRequest {
    /// The breathing trace.
    pub trace: TraceBody,
    /// Points to track (LPS mm, at the scanned state).
    #[serde(default)]
    pub points: Vec<StoredPoint>,
    /// Any key of the CLI's configuration (`element_size_mm`, `material`, `diaphragm`,
    /// `trace`, `motion`, `outputs`), merged over the server's defaults.
    #[serde(flatten)]
    #[schema(value_type = Object)]
    pub options: serde_json::Map<String, Value>,
}

/// A request's parts before they are checked together.
struct ParsedRequest {
    config: RunConfig,
    trace: BreathingTrace,
    points: Vec<StoredPoint>,
    source: &'static str,
}

/// A 422 with the slug every unusable simulation request gets.
fn invalid(message: String) -> ApiError {
    ApiError::unprocessable("invalid-simulation", message)
}

/// Merges request options over the server's defaults: objects key by key, except tagged
/// choices (`{"kind": ...}`), which replace the default whole.
fn merge_options(base: &mut Value, overrides: &serde_json::Map<String, Value>) {
    let Value::Object(base) = base else { return };
    for (key, value) in overrides {
        match (base.get_mut(key), value) {
            (Some(existing @ Value::Object(_)), Value::Object(o)) if !o.contains_key("kind") => {
                merge_options(existing, o)
            }
            _ => {
                base.insert(key.clone(), value.clone());
            }
        }
    }
}

/// The job request from a JSON or CSV body, checked as far as it can be without running.
pub(crate) fn parse_simulation(
    defaults: &RunConfig,
    content_type: &str,
    body: &[u8],
) -> ApiResult<JobRequest> {
    let parsed = if content_type.starts_with("application/json") || content_type.ends_with("+json")
    {
        parse_json_request(defaults, body)?
    } else if content_type.starts_with("text/csv") || content_type.starts_with("text/plain") {
        parse_csv_request(defaults, body)?
    } else {
        return Err(unsupported_media_type(content_type));
    };
    check_request(&parsed)?;
    let ParsedRequest {
        config,
        trace,
        points,
        source,
    } = parsed;
    Ok(JobRequest {
        config,
        time_s: trace.time_s,
        volume_ml: trace.volume_change_ml,
        trace_source: source.to_string(),
        points,
    })
}

/// A JSON body: the trace, the points, and options merged over the defaults.
fn parse_json_request(defaults: &RunConfig, body: &[u8]) -> ApiResult<ParsedRequest> {
    let value: Value = serde_json::from_slice(body).map_err(|e| {
        ApiError::bad_request("malformed-json", format!("the body is not valid JSON: {e}"))
    })?;
    if !value.is_object() {
        return Err(invalid(
            "the body must be a JSON object with a \"trace\"".into(),
        ));
    }
    let request: SimulationRequest =
        serde_json::from_value(value).map_err(|e| invalid(format!("simulation request: {e}")))?;
    let mut merged = serde_json::to_value(defaults)
        .map_err(|e| ApiError::internal(format!("default options: {e}")))?;
    merge_options(&mut merged, &request.options);
    let config: RunConfig =
        serde_json::from_value(merged).map_err(|e| invalid(format!("options: {e}")))?;
    let trace = BreathingTrace::new(request.trace.time_s, request.trace.volume_ml)
        .map_err(|e| invalid(e.to_string()))?;
    Ok(ParsedRequest {
        config,
        trace,
        points: request.points,
        source: "HTTP request (JSON)",
    })
}

/// A CSV body: the CLI's trace format, run with the server's defaults.
fn parse_csv_request(defaults: &RunConfig, body: &[u8]) -> ApiResult<ParsedRequest> {
    let text = std::str::from_utf8(body)
        .map_err(|_| ApiError::bad_request("malformed-csv", "the CSV body is not UTF-8"))?;
    let trace = BreathingTrace::parse(text, &defaults.trace)
        .map_err(|e| invalid(format!("breathing trace: {e}")))?;
    Ok(ParsedRequest {
        config: defaults.clone(),
        trace,
        points: Vec::new(),
        source: "HTTP request (CSV)",
    })
}

/// The 415 that says which two bodies a simulation request may be.
fn unsupported_media_type(content_type: &str) -> ApiError {
    ApiError::new(
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported-media-type",
        format!(
            "a simulation request is application/json ({{\"trace\": {{\"time_s\": [...], \
         \"volume_ml\": [...]}}, ...options}}) or text/csv (time_s,volume_ml), not {:?}",
            if content_type.is_empty() {
                "no content type"
            } else {
                content_type
            }
        ),
    )
}

/// Refuses what a run would refuse later: options, trace, output instants and points.
fn check_request(request: &ParsedRequest) -> ApiResult<()> {
    let ParsedRequest {
        config,
        trace,
        points,
        ..
    } = request;
    config.validate().map_err(|e| invalid(e.to_string()))?;
    trace.validate().map_err(|e| invalid(e.to_string()))?;
    config
        .motion_settings()
        .instants
        .times(trace)
        .map_err(|e| invalid(e.to_string()))?;
    check_points(points)
}

/// Point names end up in trajectories.csv, so they must be plain; coordinates finite.
fn check_points(points: &[StoredPoint]) -> ApiResult<()> {
    for (i, p) in points.iter().enumerate() {
        if p.name.trim().is_empty() || p.name.contains([',', '\n', '\r']) {
            return Err(invalid(format!(
                "points[{i}]: a name without commas or line breaks is needed"
            )));
        }
        if !p.lps_mm.iter().all(|c| c.is_finite()) {
            return Err(invalid(format!(
                "points[{i}] ({}): non-finite coordinate",
                p.name
            )));
        }
    }
    Ok(())
}
#[cfg(test)]
mod tests {
    use super::*;

    fn two_breaths() -> (Vec<f64>, Vec<f64>) {
        let t: Vec<f64> = (0..=80).map(|i| i as f64 * 0.1).collect();
        let v = t
            .iter()
            .map(|t| 250.0 * (1.0 - (std::f64::consts::TAU * t / 4.0).cos()))
            .collect();
        (t, v)
    }

    #[test]
    fn json_options_merge_over_the_server_defaults() {
        let mut defaults = RunConfig::default();
        defaults.material.poisson_ratio = 0.3;
        let (t, v) = two_breaths();
        let body = serde_json::json!({
            "trace": {"time_s": t, "volume_ml": v},
            "element_size_mm": 10,
            "material": {"youngs_modulus_pa": 800.0},
            "motion": {"instants": {"kind": "every_kth", "k": 20}},
            "points": [{"name": "tumour", "lps_mm": [1.0, 2.0, 3.0]}],
        });
        let request =
            parse_simulation(&defaults, "application/json", body.to_string().as_bytes()).unwrap();
        assert_eq!(request.config.element_size_mm, 10.0);
        assert_eq!(request.config.material.youngs_modulus_pa, 800.0);
        // Keys the request leaves out keep the server's value, even inside a table.
        assert_eq!(request.config.material.poisson_ratio, 0.3);
        assert_eq!(
            request.config.motion.instants,
            crate::breathing::OutputInstants::EveryKth { k: 20 }
        );
        assert_eq!(request.points[0].name, "tumour");
        assert_eq!(request.time_s.len(), 81);
    }

    #[test]
    fn bad_requests_are_refused_with_the_right_status_and_a_named_cause() {
        let defaults = RunConfig::default();
        let (t, v) = two_breaths();
        let status = |ct: &str, body: &str| {
            let e = parse_simulation(&defaults, ct, body.as_bytes()).unwrap_err();
            (e.status.as_u16(), e.detail)
        };
        let (s, d) = status("application/json", "{\"trace\": ");
        assert_eq!(s, 400, "{d}");
        let (s, d) = status("application/json", "[1, 2]");
        assert_eq!(s, 422, "{d}");
        let body =
            serde_json::json!({"trace": {"time_s": t, "volume_ml": v}, "element_sise_mm": 8});
        let (s, d) = status("application/json", &body.to_string());
        assert!(s == 422 && d.contains("element_sise_mm"), "{s} {d}");
        let body = serde_json::json!({"trace": {"time_s": [0, 1], "volume_ml": ["a", 1]}});
        let (s, d) = status("application/json", &body.to_string());
        assert_eq!(s, 422, "{d}");
        let (s, d) = status("text/csv", "time_s,volume_ml\n0,0\n1,NaN\n2,3\n");
        assert!(s == 422 && d.contains("NaN"), "{s} {d}");
        let (s, d) = status("text/csv", "time_s,volume_ml\n0,0\n2,1\n1,3\n");
        assert_eq!(s, 422, "{d}");
        let (s, d) = status("application/xml", "<trace/>");
        assert!(s == 415 && d.contains("application/json"), "{s} {d}");
        let body = serde_json::json!({"trace": {"time_s": t, "volume_ml": v},
            "points": [{"name": "a,b", "lps_mm": [0, 0, 0]}]});
        let (s, d) = status("application/json", &body.to_string());
        assert!(s == 422 && d.contains("points[0]"), "{s} {d}");
    }
}

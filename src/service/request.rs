//! A simulation request, JSON or CSV, turned into a job request: the body parsed, its options
//! merged over the server's run defaults, and everything checked that can be without running.

use axum::http::StatusCode;
use serde::Deserialize;
use serde_json::Value;
use utoipa::ToSchema;

use super::pacs_settings::PacsSettings;
use super::problem::{ApiError, ApiResult};
use super::store::{JobRequest, PacsSeries, StoredPoint};
use super::targets::{parse_request_target, JobTarget};
use crate::breathing::{BreathingTrace, TraceFormat, TraceOptions};
use crate::run::RunConfig;

/// A breathing trace in a JSON request: the CLI's JSON trace file (`time_s` or `time_ms`,
/// `volume_ml` or `volume_l`) with the run configuration's `[trace]` options beside the data,
/// each over the server's `[run.trace]` default and applied exactly as `lungmotion run`
/// applies them to a trace file.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TraceBody {
    /// Sample times, s, strictly increasing.
    #[serde(default)]
    pub time_s: Option<Vec<f64>>,
    /// Sample times, ms (instead of `time_s`).
    #[serde(default)]
    pub time_ms: Option<Vec<f64>>,
    /// Lung volume, mL: the change from the scanned state unless `reference` says absolute.
    #[serde(default)]
    pub volume_ml: Option<Vec<f64>>,
    /// Lung volume, L (instead of `volume_ml`).
    #[serde(default)]
    pub volume_l: Option<Vec<f64>>,
    /// `"change_from_scan"` (default) or `{"absolute": {"scanned_volume_ml": 2800}}`: the
    /// volumes are absolute lung volumes and the scanned lung holds `scanned_volume_ml`.
    #[serde(default)]
    #[schema(value_type = Object)]
    pub reference: Option<Value>,
    /// Multiplies the times to get seconds (instead of the unit in the key's name).
    #[serde(default)]
    pub seconds_per_time_unit: Option<f64>,
    /// Multiplies the volumes to get mL (instead of the unit in the key's name).
    #[serde(default)]
    pub ml_per_volume_unit: Option<f64>,
    /// Keep only the samples from the first time to the second, s.
    #[serde(default)]
    pub window_s: Option<[f64; 2]>,
}

impl TraceBody {
    /// The samples as the CLI's JSON trace file and the trace options, each option given
    /// here replacing the server's default, `format` fixed to JSON.
    fn split(self, defaults: &TraceOptions) -> ApiResult<(String, TraceOptions)> {
        let mut samples = serde_json::Map::new();
        for (key, values) in [
            ("time_s", self.time_s),
            ("time_ms", self.time_ms),
            ("volume_ml", self.volume_ml),
            ("volume_l", self.volume_l),
        ] {
            if let Some(values) = values {
                samples.insert(key.into(), values.into());
            }
        }
        let mut options = serde_json::to_value(defaults)
            .map_err(|e| ApiError::internal(format!("default trace options: {e}")))?;
        for (key, value) in [
            ("reference", self.reference),
            (
                "seconds_per_time_unit",
                self.seconds_per_time_unit.map(Value::from),
            ),
            (
                "ml_per_volume_unit",
                self.ml_per_volume_unit.map(Value::from),
            ),
            ("window_s", self.window_s.map(|w| Value::from(w.to_vec()))),
        ] {
            if let Some(value) = value {
                options[key] = value;
            }
        }
        let mut options: TraceOptions =
            serde_json::from_value(options).map_err(|e| invalid(format!("trace: {e}")))?;
        options.format = TraceFormat::Json;
        Ok((Value::Object(samples).to_string(), options))
    }
}

/// A simulation request: the trace, points to track, and any `lungmotion run` option.
#[derive(Debug, Deserialize, ToSchema)]
pub struct SimulationRequest {
    /// The breathing trace.
    pub trace: TraceBody,
    /// Points to track (LPS mm, at the scanned state).
    #[serde(default)]
    pub points: Vec<StoredPoint>,
    /// Where to POST the job's outcome when it ends (http or https; see the README).
    #[serde(default)]
    pub callback_url: Option<String>,
    /// The treatment target to follow (per-frame masks, ITV, motion per axis, RTSTRUCT):
    /// `"point:<x>,<y>,<z>:r=<radius mm>"` in LPS mm, or a target file uploaded to the scan
    /// (`PUT /v1/scans/{id}/targets/{name}`), `{"upload": name, "label": n}` for a mask or
    /// `{"upload": name, "roi": "GTV"}` for an RTSTRUCT. Never a path on the server's disk.
    #[serde(default)]
    #[schema(value_type = Object)]
    pub target: Option<Value>,
    /// The CT from the service's PACS, `{"dicomweb": {"study": UID, "series": UID}}` (series
    /// optional: the study's one CT series): only at `POST /v1/simulations`, and only when the
    /// server is configured with a PACS (`[pacs]`).
    #[serde(default)]
    pub ct: Option<CtSource>,
    /// Push the DICOM outputs (virtual CT series, REGs, RTSTRUCT) to the service's PACS when
    /// the run succeeds, skipping what it already holds; default: the server's `[pacs] push`.
    #[serde(default)]
    pub push: Option<bool>,
    /// Any key of the CLI's configuration (`element_size_mm`, `material`, `diaphragm`,
    /// `trace`, `motion`, `outputs`, `budget`), merged over the server's defaults.
    #[serde(flatten)]
    #[schema(value_type = Object)]
    pub options: serde_json::Map<String, Value>,
}

/// Where a job's CT comes from when it is not a stored scan.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CtSource {
    /// A series on the service's PACS.
    pub dicomweb: PacsSeries,
}

/// A request's parts before they are checked together.
struct ParsedRequest {
    config: RunConfig,
    trace: BreathingTrace,
    points: Vec<StoredPoint>,
    source: String,
    callback_url: Option<String>,
    target: Option<JobTarget>,
    pacs_ct: Option<PacsSeries>,
    push: Option<bool>,
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

/// The job request from a JSON or CSV body, checked as far as it can be without running;
/// `pacs` is the service's PACS, which a request may pull its CT from or push to.
pub(crate) fn parse_simulation(
    defaults: &RunConfig,
    pacs: Option<&PacsSettings>,
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
    check_pacs_use(&parsed, pacs)?;
    let ParsedRequest {
        config,
        trace,
        points,
        source,
        callback_url,
        target,
        pacs_ct,
        push,
    } = parsed;
    Ok(JobRequest {
        config,
        time_s: trace.time_s,
        volume_ml: trace.volume_change_ml,
        trace_source: source,
        points,
        callback_url,
        target,
        pacs_ct,
        push: push.unwrap_or_else(|| pacs.is_some_and(|p| p.push_by_default)),
    })
}

/// Where the trace came from, with what was done to it (an airflow column integrated, its
/// drift removed), as the CLI records it in `summary.json` → `trace.source`.
fn described_source(origin: &str, notes: &[String]) -> String {
    if notes.is_empty() {
        origin.to_string()
    } else {
        format!("{origin} ({})", notes.join("; "))
    }
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
    // The scan was read when it was uploaded; a series named here could not change it, and
    // silently ignoring it would run on a series the caller did not ask for.
    if let Some(series) = request.options.get("series") {
        return Err(invalid(format!(
            "series {series}: the DICOM series is chosen when the scan is uploaded \
             (POST /v1/scans?series=...); a simulation runs on the stored scan"
        )));
    }
    let mut merged = serde_json::to_value(defaults)
        .map_err(|e| ApiError::internal(format!("default options: {e}")))?;
    merge_options(&mut merged, &request.options);
    let mut config: RunConfig =
        serde_json::from_value(merged).map_err(|e| invalid(format!("options: {e}")))?;
    let (samples, trace_options) = request.trace.split(&defaults.trace)?;
    // The CLI's own reader on the CLI's own file format: units and reference applied alike.
    let reading = BreathingTrace::parse_with_notes(&samples, &trace_options)
        .map_err(|e| invalid(format!("breathing trace: {e}")))?;
    // Recorded in request.json and summary.json as the CLI records its [trace] table.
    config.trace = TraceOptions {
        format: defaults.trace.format,
        ..trace_options
    };
    Ok(ParsedRequest {
        config,
        source: described_source("HTTP request (JSON)", &reading.notes),
        trace: reading.trace,
        points: request.points,
        callback_url: request.callback_url,
        target: request.target.map(parse_request_target).transpose()?,
        pacs_ct: request.ct.map(|c| c.dicomweb),
        push: request.push,
    })
}

/// A CSV body: the CLI's trace format, run with the server's defaults.
fn parse_csv_request(defaults: &RunConfig, body: &[u8]) -> ApiResult<ParsedRequest> {
    let text = std::str::from_utf8(body)
        .map_err(|_| ApiError::bad_request("malformed-csv", "the CSV body is not UTF-8"))?;
    let reading = BreathingTrace::parse_with_notes(text, &defaults.trace)
        .map_err(|e| invalid(format!("breathing trace: {e}")))?;
    Ok(ParsedRequest {
        config: defaults.clone(),
        source: described_source("HTTP request (CSV)", &reading.notes),
        trace: reading.trace,
        points: Vec::new(),
        callback_url: None,
        target: None,
        pacs_ct: None,
        push: None,
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

/// Refuses what a run would refuse later: options, trace, output instants and points (the
/// target was checked as it was read).
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

/// Refuses a PACS series or a push when the server has no PACS, and UIDs that are not UIDs
/// (they go into the PACS's URLs).
fn check_pacs_use(request: &ParsedRequest, pacs: Option<&PacsSettings>) -> ApiResult<()> {
    let wants = match (&request.pacs_ct, request.push) {
        (Some(_), _) => Some("a CT from the PACS (\"ct\": {\"dicomweb\": ...})"),
        (None, Some(true)) => Some("\"push\": true"),
        _ => None,
    };
    if let (Some(what), None) = (wants, pacs) {
        return Err(ApiError::unprocessable(
            "no-pacs",
            format!(
                "{what}: this server has no PACS configured (the operator sets [pacs] url or \
                 LUNGMOTION_PACS_URL)"
            ),
        ));
    }
    if let Some(series) = &request.pacs_ct {
        for (key, uid) in [
            ("study", Some(&series.study)),
            ("series", series.series.as_ref()),
        ] {
            if let Some(uid) = uid {
                if !crate::pacs::is_uid(uid) {
                    return Err(invalid(format!(
                        "ct.dicomweb.{key} {:?} is not a DICOM UID (digits and dots, at most \
                         64 characters)",
                        uid.chars().take(80).collect::<String>()
                    )));
                }
            }
        }
    }
    Ok(())
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
    fn an_airflow_csv_body_is_integrated_and_the_job_records_what_was_done() {
        // Ten 4 s breaths of 500 mL as flow in L/s with a 30 mL/s sensor offset, at 10 Hz.
        let mut csv = String::from("time_s,flow_l_per_s\n");
        for i in 0..=400 {
            let t = i as f64 * 0.1;
            let flow_ml_s =
                250.0 * std::f64::consts::FRAC_PI_2 * (std::f64::consts::PI * t / 2.0).sin();
            csv.push_str(&format!("{t:.1},{:.6}\n", (flow_ml_s + 30.0) / 1000.0));
        }
        let request =
            parse_simulation(&RunConfig::default(), None, "text/csv", csv.as_bytes()).unwrap();
        assert!(
            request.trace_source.starts_with("HTTP request (CSV) (")
                && request.trace_source.contains("flow"),
            "{}",
            request.trace_source
        );
        let peak = request.volume_ml.iter().cloned().fold(f64::MIN, f64::max);
        assert!(peak > 400.0 && peak < 600.0, "{peak}");
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
        let request = parse_simulation(
            &defaults,
            None,
            "application/json",
            body.to_string().as_bytes(),
        )
        .unwrap();
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
    fn the_traces_options_beside_its_samples_apply_as_the_clis() {
        let defaults = RunConfig::default();
        let (t, v) = two_breaths();
        let absolute: Vec<f64> = v.iter().map(|v| v + 2800.0).collect();
        let body = serde_json::json!({"trace": {"time_s": t, "volume_ml": absolute,
            "reference": {"absolute": {"scanned_volume_ml": 2800.0}}}});
        let request = parse_simulation(
            &defaults,
            None,
            "application/json",
            body.to_string().as_bytes(),
        )
        .unwrap();
        let cli_options: TraceOptions =
            toml::from_str("reference = { absolute = { scanned_volume_ml = 2800 } }").unwrap();
        let absolute_text = serde_json::json!({"time_s": t, "volume_ml": absolute}).to_string();
        let cli = BreathingTrace::parse(&absolute_text, &cli_options).unwrap();
        assert_eq!(request.volume_ml, cli.volume_change_ml);
        assert_eq!(request.config.trace.reference, cli_options.reference);
        // Units: the key's name or a factor, as in a trace file.
        let ms: Vec<f64> = t.iter().map(|t| t * 1000.0).collect();
        let litres: Vec<f64> = v.iter().map(|v| v / 1000.0).collect();
        let body = serde_json::json!({"trace": {"time_ms": ms, "volume_l": litres}});
        let request = parse_simulation(
            &defaults,
            None,
            "application/json",
            body.to_string().as_bytes(),
        )
        .unwrap();
        assert!((request.time_s[80] - 8.0).abs() < 1e-12);
        assert!((request.volume_ml[40] - v[40]).abs() < 1e-9);
        let body = serde_json::json!({"trace": {"time_s": t, "volume_ml": litres,
            "ml_per_volume_unit": 1000.0}});
        let request = parse_simulation(
            &defaults,
            None,
            "application/json",
            body.to_string().as_bytes(),
        )
        .unwrap();
        assert!((request.volume_ml[40] - v[40]).abs() < 1e-9);
        // Absolute volumes of a large lung without the scanned volume: refused with the hint.
        let large: Vec<f64> = v.iter().map(|v| v + 5800.0).collect();
        let body = serde_json::json!({"trace": {"time_s": t, "volume_ml": large}});
        let e = parse_simulation(
            &defaults,
            None,
            "application/json",
            body.to_string().as_bytes(),
        )
        .unwrap_err();
        assert!(
            e.status == 422 && e.detail.contains("scanned lung volume"),
            "{e}"
        );
        for (bad, named) in [
            (
                serde_json::json!({"referense": "change_from_scan"}),
                "referense",
            ),
            (
                serde_json::json!({"reference": {"absolute": {}}}),
                "scanned_volume_ml",
            ),
            (
                serde_json::json!({"reference": {"absolute": {"scanned_volume_ml": -1}}}),
                "-1",
            ),
        ] {
            let mut trace = serde_json::json!({"time_s": t, "volume_ml": v});
            for (k, value) in bad.as_object().unwrap() {
                trace[k] = value.clone();
            }
            let body = serde_json::json!({ "trace": trace });
            let e = parse_simulation(
                &defaults,
                None,
                "application/json",
                body.to_string().as_bytes(),
            )
            .unwrap_err();
            assert!(e.status == 422 && e.detail.contains(named), "{named}: {e}");
        }
    }

    #[test]
    fn a_target_is_a_point_or_an_upload_and_never_a_server_path() {
        let defaults = RunConfig::default();
        let (t, v) = two_breaths();
        let request = |target: &str| {
            let body =
                serde_json::json!({"trace": {"time_s": t, "volume_ml": v}, "target": target});
            parse_simulation(
                &defaults,
                None,
                "application/json",
                body.to_string().as_bytes(),
            )
        };
        let ok = request("point:-95,20,-80:r=15").unwrap();
        assert_eq!(
            ok.target,
            Some(JobTarget::Point("point:-95,20,-80:r=15".into()))
        );
        let stored: JobRequest =
            serde_json::from_str(&serde_json::to_string(&ok).unwrap()).unwrap();
        assert_eq!(stored.target, ok.target);
        for (bad, named) in [
            ("/etc/passwd:label=1", "never as a path"),
            (
                "sample-volumes/phantom-truth.nii.gz:label=8",
                "never as a path",
            ),
            ("point:1,2:r=5", "2 coordinate(s)"),
            ("point:1,2,3:r=0", "radius"),
            ("point:1,2,NaN:r=5", "not a finite number"),
        ] {
            let e = request(bad).unwrap_err();
            assert!(e.status == 422 && e.detail.contains(named), "{bad}: {e}");
        }
    }

    #[test]
    fn a_pacs_series_or_a_push_needs_a_pacs_and_the_push_defaults_to_the_servers() {
        let defaults = RunConfig::default();
        let (t, v) = two_breaths();
        let body = |extra: serde_json::Value| {
            let mut body = serde_json::json!({"trace": {"time_s": t, "volume_ml": v}});
            for (k, value) in extra.as_object().unwrap() {
                body[k] = value.clone();
            }
            body.to_string()
        };
        let series =
            serde_json::json!({"ct": {"dicomweb": {"study": "1.2.3", "series": "1.2.3.4"}}});
        // No PACS on the server: refused by name, a push too.
        for extra in [series.clone(), serde_json::json!({"push": true})] {
            let e = parse_simulation(&defaults, None, "application/json", body(extra).as_bytes())
                .unwrap_err();
            assert!(e.status == 422 && e.slug == "no-pacs", "{e}");
        }
        let mut pacs = PacsSettings::new("dicomweb://127.0.0.1:8042/dicom-web").unwrap();
        let request = parse_simulation(
            &defaults,
            Some(&pacs),
            "application/json",
            body(series.clone()).as_bytes(),
        )
        .unwrap();
        assert_eq!(
            request.pacs_ct,
            Some(PacsSeries {
                study: "1.2.3".into(),
                series: Some("1.2.3.4".into())
            })
        );
        assert!(!request.push);
        // The server's default applies unless the request says.
        pacs.push_by_default = true;
        let csv: String = std::iter::once("time_s,volume_ml\n".to_string())
            .chain(t.iter().zip(&v).map(|(t, v)| format!("{t},{v}\n")))
            .collect();
        let request = parse_simulation(&defaults, Some(&pacs), "text/csv", csv.as_bytes()).unwrap();
        assert!(request.push);
        let request = parse_simulation(
            &defaults,
            Some(&pacs),
            "application/json",
            body(serde_json::json!({"push": false})).as_bytes(),
        )
        .unwrap();
        assert!(!request.push);
        for (bad, named) in [
            (
                serde_json::json!({"ct": {"dicomweb": {"study": "1.02"}}}),
                "ct.dicomweb.study",
            ),
            (
                serde_json::json!({"ct": {"dicomweb": {"study": "1.2", "series": "../x"}}}),
                "ct.dicomweb.series",
            ),
            (
                serde_json::json!({"ct": {"dicomweb": {"studdy": "1.2"}}}),
                "studdy",
            ),
            (serde_json::json!({"ct": {"path": "/etc"}}), "path"),
        ] {
            let e = parse_simulation(
                &defaults,
                Some(&pacs),
                "application/json",
                body(bad).as_bytes(),
            )
            .unwrap_err();
            assert!(e.status == 422 && e.detail.contains(named), "{named}: {e}");
        }
    }

    #[test]
    fn bad_requests_are_refused_with_the_right_status_and_a_named_cause() {
        let defaults = RunConfig::default();
        let (t, v) = two_breaths();
        let status = |ct: &str, body: &str| {
            let e = parse_simulation(&defaults, None, ct, body.as_bytes()).unwrap_err();
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
        let body = serde_json::json!({"trace": {"time_s": t, "volume_ml": v},
            "series": "number:3"});
        let (s, d) = status("application/json", &body.to_string());
        assert!(s == 422 && d.contains("uploaded"), "{s} {d}");
    }
}

//! The service with a PACS by configuration: a job takes its CT from a real DICOMweb server
//! (Orthanc behind HTTP Basic authentication) by study UID, runs, and pushes its virtual CT
//! series, REGs and RTSTRUCT back, nothing twice when the job is submitted again; a series
//! the server does not hold fails the job with the server's answer; a PACS that is down
//! fails the job naming it; a server without a PACS refuses PACS requests.
//!
//! Both backends: with `LUNGMOTION_TEST_BACKEND=postgres` (and `LUNGMOTION_TEST_OBJECT_STORE=s3`)
//! each server gets a database, a worker process (which pulls and pushes) and an S3 server of
//! its own (`.ci/run` runs this file so).

mod orthanc_support;
mod service_support;

use std::time::Duration;

use orthanc_support::{free_port, Orthanc};
use serde_json::{json, Value};
use service_support::{
    accepted_job_id, assert_problem, breathing_trace, sample, tiny_request, Scratch, ServerProcess,
};

/// The bundled DICOM series' StudyInstanceUID.
fn phantom_study_uid() -> String {
    orthanc_support::study_uid_of(&sample("phantom-dicom"))
}

/// A short job on a PACS series: 12 mm elements, two breaths, two phases, the virtual CT
/// as DICOM, REGs and the target's RTSTRUCT.
fn pacs_request(ct: Value, push: bool) -> Value {
    let (time_s, volume_ml) = breathing_trace(2);
    json!({
        "ct": ct,
        "push": push,
        "trace": {"time_s": time_s, "volume_ml": volume_ml},
        "element_size_mm": 12,
        "motion": {"instants": {"kind": "phases", "count": 2}},
        "outputs": {"quicklooks": false, "virtual_ct": "dicom", "registration": true,
                    "registration_spacing_mm": 6},
        "target": "point:-95,20,-80:r=12",
    })
}

fn post_pacs_simulation(server: &ServerProcess, request: &Value) -> reqwest::blocking::Response {
    server
        .client()
        .post(server.url("/v1/simulations"))
        .json(request)
        .send()
        .unwrap()
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "needs Orthanc with its DICOMweb plugin (.ci/run installs it): cargo test --features slow-tests --test service_pacs"
)]
fn a_job_pulls_its_ct_from_the_pacs_and_pushes_its_outputs_back_once() {
    let orthanc = Orthanc::start_with("service", Some(("lungmotion", "pacs-pass-1234")));
    let study = phantom_study_uid();
    assert_eq!(orthanc.store_files(&sample("phantom-dicom")), 68);
    let [(_, ct_series)] = &orthanc.series_of(&study)[..] else {
        panic!("one series stored")
    };
    let ct_series = ct_series.clone();
    let scratch = Scratch::new("pacs-jobs");
    let server = ServerProcess::start_with_env(
        &scratch.join("data"),
        &["--workers", "1"],
        &[
            ("LUNGMOTION_PACS_URL", &orthanc.root()),
            ("LUNGMOTION_PACS_USERNAME", "lungmotion"),
            ("LUNGMOTION_PACS_PASSWORD", "pacs-pass-1234"),
        ],
    );

    // By study alone: the study's one CT series is found, pulled, stored as the job's scan.
    let request = pacs_request(json!({"dicomweb": {"study": study}}), true);
    let job = accepted_job_id(post_pacs_simulation(&server, &request));
    let done = server.wait_for_state(&job, &["done"], Duration::from_secs(900));
    let pacs = &done["pacs"];
    assert_eq!(pacs["server"], orthanc.http_root(), "{done:#}");
    assert_eq!(pacs["ct"]["study"], study.as_str(), "{done:#}");
    assert_eq!(pacs["push"], true, "{done:#}");
    let scan = server.get_json(done["links"]["scan"].as_str().unwrap());
    assert_eq!(scan["format"], "dicomweb", "{scan:#}");
    assert_eq!(pacs["ct"]["series"], ct_series.as_str(), "{done:#}");

    // The job's outputs: the summary, a REG per frame, the virtual CT series, the RTSTRUCT.
    let summary = server.get_json(&format!("/v1/jobs/{job}/summary"));
    let frames = summary["frames"].as_array().unwrap().len();
    assert_eq!(frames, 2, "{summary:#}");
    let files = server.get_json(&format!("/v1/jobs/{job}/files"));
    let paths: Vec<&str> = files["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["path"].as_str().unwrap())
        .collect();
    for k in 0..frames {
        let reg = format!("frames/{k}/registration.dcm");
        assert!(paths.contains(&reg.as_str()), "{reg} not in {paths:?}");
    }
    let dicom_outputs = paths.iter().filter(|p| p.ends_with(".dcm")).count();

    // On the PACS: the planning CT, a virtual phase series per frame with MIP and AIP, a REG
    // per frame and the RTSTRUCT, all in the CT's study; every DICOM output was stored.
    let series = orthanc.series_of(&study);
    let count = |modality: &str| series.iter().filter(|(m, _)| m == modality).count();
    assert_eq!(count("CT"), 1 + frames + 2, "{series:?}");
    assert_eq!(count("REG"), frames, "{series:?}");
    assert_eq!(count("RTSTRUCT"), 1, "{series:?}");
    let stored = pacs["stored"].as_u64().unwrap() as usize;
    assert_eq!(stored, dicom_outputs, "{done:#} {paths:?}");
    assert_eq!(pacs["already_stored"], 0, "{done:#}");
    let (_, reg_series) = series.iter().find(|(m, _)| m == "REG").unwrap();
    let metadata = orthanc.metadata(&study, reg_series);
    assert_eq!(
        metadata[0]["00080016"]["Value"][0], "1.2.840.10008.5.1.4.1.1.66.3",
        "the stored REG read back is a Deformable Spatial Registration"
    );

    // Submitted again, naming the series: the same outputs, none stored twice.
    let request = pacs_request(
        json!({"dicomweb": {"study": study, "series": ct_series}}),
        true,
    );
    let again = accepted_job_id(post_pacs_simulation(&server, &request));
    let done = server.wait_for_state(&again, &["done"], Duration::from_secs(900));
    assert_eq!(done["pacs"]["stored"], 0, "{done:#}");
    assert_eq!(done["pacs"]["already_stored"], stored, "{done:#}");
    assert_eq!(orthanc.series_of(&study).len(), series.len());

    // Again with other settings (a rigid chest wall): the motion differs, so do the REGs,
    // the virtual phases and the structure set, and the PACS stores them beside the first
    // job's (the UIDs follow the content, not only the CT).
    let mut request = request;
    request["motion"]["rib_cage_share"] = json!(0);
    let rigid = accepted_job_id(post_pacs_simulation(&server, &request));
    let done = server.wait_for_state(&rigid, &["done"], Duration::from_secs(900));
    assert!(done["pacs"]["stored"].as_u64().unwrap() > 0, "{done:#}");
    let after = orthanc.series_of(&study);
    let count_after = |modality: &str| after.iter().filter(|(m, _)| m == modality).count();
    assert_eq!(count_after("RTSTRUCT"), 2, "{after:?}");
    assert!(count_after("REG") > frames, "{after:?}");
    assert!(count_after("CT") > 1 + frames + 2, "{after:?}");

    // A series the PACS does not hold: the job fails with the server's answer.
    let missing = "1.2.826.0.1.3680043.2.1125.99.1";
    let request = pacs_request(
        json!({"dicomweb": {"study": study, "series": missing}}),
        false,
    );
    let failed = accepted_job_id(post_pacs_simulation(&server, &request));
    let status = server.wait_for_state(&failed, &["failed"], Duration::from_secs(120));
    let error = status["error"].as_str().unwrap();
    assert!(
        error.contains(&orthanc.http_root())
            && error.contains("HTTP 404")
            && error.contains(missing),
        "{error}"
    );
    // No scan was made of it.
    let scan = server.get(status["links"]["scan"].as_str().unwrap());
    assert_eq!(scan.status(), 404);
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "needs Orthanc with its DICOMweb plugin (.ci/run installs it): cargo test --features slow-tests --test service_pacs"
)]
fn wrong_credentials_fail_the_job_with_the_servers_401() {
    let orthanc = Orthanc::start_with("service-auth", Some(("lungmotion", "right-password")));
    let scratch = Scratch::new("pacs-auth");
    let server = ServerProcess::start_with_env(
        &scratch.join("data"),
        &[],
        &[
            ("LUNGMOTION_PACS_URL", &orthanc.root()),
            ("LUNGMOTION_PACS_USERNAME", "lungmotion"),
            ("LUNGMOTION_PACS_PASSWORD", "wrong-password"),
        ],
    );
    let request = pacs_request(json!({"dicomweb": {"study": phantom_study_uid()}}), false);
    let job = accepted_job_id(post_pacs_simulation(&server, &request));
    let status = server.wait_for_state(&job, &["failed"], Duration::from_secs(120));
    let error = status["error"].as_str().unwrap();
    assert!(
        error.contains(&orthanc.http_root()) && error.contains("HTTP 401"),
        "{error}"
    );
    assert!(!error.contains("wrong-password"), "{error}");
}

#[test]
fn a_pacs_that_is_down_fails_the_job_naming_it_and_no_pacs_refuses_pacs_requests() {
    let scratch = Scratch::new("pacs-down");
    let down = format!("http://127.0.0.1:{}/dicom-web", free_port());
    let server = ServerProcess::start_with_env(
        &scratch.join("data"),
        &[],
        &[("LUNGMOTION_PACS_URL", &down)],
    );
    let request = pacs_request(
        json!({"dicomweb": {"study": "1.2.3", "series": "1.2.3.4"}}),
        true,
    );
    let job = accepted_job_id(post_pacs_simulation(&server, &request));
    let status = server.wait_for_state(&job, &["failed"], Duration::from_secs(120));
    let error = status["error"].as_str().unwrap();
    assert!(
        error.contains(&down) && error.contains("cannot connect"),
        "{error}"
    );
    assert_eq!(status["pacs"]["server"], down.as_str(), "{status:#}");
    // A job on an uploaded scan that runs and then cannot push: failed, saying the run
    // succeeded, and its outputs stay downloadable.
    let scan = server.upload_scan(&sample("phantom-ct.nii.gz"));
    let mut request = tiny_request(2);
    request["push"] = json!(true);
    request["outputs"]["registration"] = json!(true);
    request["outputs"]["registration_spacing_mm"] = json!(8);
    let job = accepted_job_id(server.post_simulation(&scan, &request));
    let status = server.wait_for_state(&job, &["failed"], Duration::from_secs(300));
    let error = status["error"].as_str().unwrap();
    assert!(
        error.contains(&down) && error.contains("the run succeeded"),
        "{error}"
    );
    let push_error = status["pacs"]["push_error"].as_str().unwrap();
    assert!(push_error.contains("cannot connect"), "{status:#}");
    let summary = server.get(&format!("/v1/jobs/{job}/summary"));
    assert_eq!(summary.status(), 200);
    let reg = server.get(&format!("/v1/jobs/{job}/files/frames/0/registration.dcm"));
    assert_eq!(reg.status(), 200);
    assert!(reg.bytes().unwrap().len() > 1000);
    // Not a UID: refused before anything is queued.
    let bad = pacs_request(json!({"dicomweb": {"study": "1.2.x"}}), false);
    assert_problem(
        post_pacs_simulation(&server, &bad),
        422,
        &["ct.dicomweb.study", "not a DICOM UID"],
    );
    // No `ct` at /v1/simulations.
    let mut no_ct = pacs_request(Value::Null, false);
    no_ct.as_object_mut().unwrap().remove("ct");
    assert_problem(post_pacs_simulation(&server, &no_ct), 422, &["no \"ct\""]);
    // A target uploaded to a scan cannot go with a CT not pulled yet: the way round is named.
    let mut uploaded = pacs_request(json!({"dicomweb": {"study": "1.2.3"}}), false);
    uploaded["target"] = json!({"upload": "gtv", "roi": "GTV"});
    assert_problem(
        post_pacs_simulation(&server, &uploaded),
        422,
        &[
            "\"gtv\"",
            "belong to a stored scan",
            "PUT /v1/scans/{scan_id}/targets",
        ],
    );
    drop(server);

    // A server without a PACS refuses a PACS series and a push by name.
    let server = ServerProcess::start(&scratch.join("data2"), &[]);
    let request = pacs_request(json!({"dicomweb": {"study": "1.2.3"}}), false);
    let body = assert_problem(
        post_pacs_simulation(&server, &request),
        422,
        &["no PACS configured", "LUNGMOTION_PACS_URL"],
    );
    assert!(
        body["type"].as_str().unwrap().ends_with("no-pacs"),
        "{body}"
    );
}

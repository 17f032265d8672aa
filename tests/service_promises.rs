//! The service's promises to an integrator, over a real socket: a DELETE during solving shows
//! `cancelling` and stops the solver (phantom everywhere, the POPI CT with the shared data),
//! progress that moves during solving with the frame count known from the start, one ingest
//! per scan and settings, every output file fetchable, and an OpenAPI document that lists
//! the 401s, the upload formats and the run options.
#![cfg(feature = "cli")]

mod service_support;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use service_support::*;

/// Longest wait for a job (the machine is shared).
const JOB_TIMEOUT: Duration = Duration::from_secs(900);

/// Polls the job until `ready` holds for its status (failing if it ends first); the status.
fn wait_until(server: &ServerProcess, job: &str, ready: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + JOB_TIMEOUT;
    loop {
        let status = server.get_json(&format!("/v1/jobs/{job}"));
        if ready(&status) {
            return status;
        }
        assert!(
            status["state"] == "queued" || status["state"] == "running",
            "the job ended first: {status}\n{}",
            tail(&server.log(), 30)
        );
        assert!(Instant::now() < deadline, "timed out: {status}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// DELETEs a job that is solving and follows it to `cancelled`: the answer is `cancelling`,
/// the state passes `cancelling`, nothing of its outputs remains. The seconds from DELETE
/// to `cancelled`.
fn cancel_while_solving(server: &ServerProcess, job: &str) -> f64 {
    wait_until(server, job, |s| {
        s["progress"]["stage"] == "solving" && s["progress"]["equilibria"].as_u64() >= Some(1)
    });
    let asked = Instant::now();
    let resp = server.delete(&format!("/v1/jobs/{job}"));
    assert_eq!(resp.status(), 202);
    let answer: Value = resp.json().unwrap();
    assert_eq!(answer["state"], "cancelling", "{answer}");
    let mut states = vec![answer["state"].as_str().unwrap().to_string()];
    let seconds = loop {
        let status = server.get_json(&format!("/v1/jobs/{job}"));
        let state = status["state"].as_str().unwrap().to_string();
        if states.last() != Some(&state) {
            states.push(state.clone());
        }
        if state == "cancelled" {
            break asked.elapsed().as_secs_f64();
        }
        assert!(
            state == "cancelling",
            "after DELETE the job is {state}: {status}"
        );
        assert!(
            asked.elapsed() < Duration::from_secs(120),
            "still {state} 120 s after DELETE"
        );
        std::thread::sleep(Duration::from_millis(10));
    };
    assert_eq!(states, ["cancelling", "cancelled"]);
    let job_dir = server.data_dir().join("jobs").join(job);
    let deadline = Instant::now() + Duration::from_secs(30);
    let leftovers = || -> Vec<String> {
        entries(&job_dir)
            .into_iter()
            .filter(|n| n.contains("partial") || n == "out")
            .collect()
    };
    while !leftovers().is_empty() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(leftovers(), Vec::<String>::new());
    assert_problem(
        server.get(&format!("/v1/jobs/{job}/files")),
        409,
        &["cancelled"],
    );
    seconds
}

#[test]
fn a_job_deleted_while_solving_is_cancelling_then_cancelled_with_no_outputs() {
    let scratch = Scratch::new("cancel-solving");
    let server = ServerProcess::start(&scratch.join("data"), &["--workers", "1"]);
    let scan = server.upload_scan(&sample("phantom-ct.nii.gz"));
    // 4 mm elements: each equilibrium takes long enough that the DELETE lands inside one.
    let job = server.submit(&scan, &simulation_request(2, &[], 4.0, 10));
    let seconds = cancel_while_solving(&server, &job);
    println!("phantom at 4 mm: cancelled {seconds:.2} s after DELETE");
}

/// Zips the POPI DICOM series into `dest`, stored (the pixels barely compress).
fn zip_popi(dest: &Path) {
    use std::io::Write;
    let dir = lungmotion::datasets::shared_data_dir()
        .expect("shared data")
        .join("popi-chest-ct/dicom");
    let mut names: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    names.sort();
    let mut zip = zip::ZipWriter::new(std::fs::File::create(dest).unwrap());
    let options =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for path in names {
        let name = format!("popi/{}", path.file_name().unwrap().to_string_lossy());
        zip.start_file(name, options).unwrap();
        zip.write_all(&std::fs::read(&path).unwrap()).unwrap();
    }
    zip.finish().unwrap();
}

#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the POPI CT in ../shared/data (or $LUNGMOTION_SHARED_DATA)"
)]
fn a_popi_job_deleted_while_solving_stops_and_keeps_nothing() {
    let scratch = Scratch::new("cancel-popi");
    let zip = scratch.join("popi.zip");
    zip_popi(&zip);
    let server = ServerProcess::start(&scratch.join("data"), &["--workers", "1"]);
    let scan = server.upload_scan(&zip);
    let runs = std::env::var("LM_POPI_CANCEL_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    for run in 0..runs {
        let job = server.submit(&scan, &simulation_request(2, &[], 8.0, 10));
        let seconds = cancel_while_solving(&server, &job);
        println!("POPI at 8 mm, run {run}: cancelled {seconds:.2} s after DELETE");
    }
}

/// The content type an output file must be served with.
fn expected_content_type(path: &str) -> &'static str {
    match path.rsplit('.').next().unwrap() {
        "gz" => "application/gzip",
        "json" => "application/json",
        "csv" => "text/csv",
        "png" => "image/png",
        "vtu" | "vtp" => "application/xml",
        "dcm" => "application/dicom",
        _ => "application/octet-stream",
    }
}

/// Every file under `dir`, relative, `/`-separated.
fn files_under(dir: &Path, prefix: &str, out: &mut Vec<String>) {
    for name in entries(dir) {
        let path = dir.join(&name);
        if path.is_dir() {
            files_under(&path, &format!("{prefix}{name}/"), out);
        } else {
            out.push(format!("{prefix}{name}"));
        }
    }
}

#[test]
fn progress_moves_while_solving_and_every_output_file_is_served() {
    let scratch = Scratch::new("progress-files");
    let server = ServerProcess::start(&scratch.join("data"), &["--workers", "1"]);
    let scan = server.upload_scan(&sample("phantom-ct.nii.gz"));
    let mut request = simulation_request(2, &tracked_points(), 8.0, 10);
    request["outputs"] = json!({"quicklooks": true, "metaimage": true, "mesh_vtu": true});
    let job = server.submit(&scan, &request);
    let mut polls = Vec::new();
    let done =
        server.wait_for_state_observing(&job, &["done"], JOB_TIMEOUT, |s| polls.push(s.clone()));

    let first_running = polls
        .iter()
        .find(|s| s["state"] == "running")
        .expect("never seen running");
    assert_eq!(
        first_running["progress"]["frames_total"], 10,
        "{first_running}"
    );
    let solving: Vec<&Value> = polls
        .iter()
        .filter(|s| s["progress"]["stage"] == "solving")
        .collect();
    let mut equilibria: Vec<u64> = solving
        .iter()
        .filter_map(|s| s["progress"]["equilibria"].as_u64())
        .collect();
    equilibria.dedup();
    assert!(
        equilibria.len() >= 2,
        "the equilibria seen during solving did not move: {equilibria:?}"
    );
    let fractions: Vec<f64> = solving
        .iter()
        .map(|s| s["progress"]["fraction"].as_f64().unwrap())
        .collect();
    assert!(
        fractions.windows(2).all(|w| w[1] >= w[0]) && fractions.last() > fractions.first(),
        "the fraction did not rise during solving: {fractions:?}"
    );
    assert!(solving
        .iter()
        .any(|s| s["progress"]["volume_change_ml"].is_number()));
    assert!(
        polls
            .iter()
            .filter(|s| s["progress"]["frames_written"].as_u64() >= Some(1))
            .filter(|s| s["state"] == "running")
            .all(|s| s["progress"]["seconds_left"].is_number()),
        "no time left estimated while frames were written"
    );

    // Every file of the job's output directory is listed and served as it is on disk.
    let listing = server.get_json(done["links"]["files"].as_str().unwrap());
    let listed: Vec<&Value> = listing["files"].as_array().unwrap().iter().collect();
    let mut on_disk = Vec::new();
    let out = server.data_dir().join("jobs").join(&job).join("out");
    files_under(&out, "", &mut on_disk);
    for must in [
        "ingest/lung-mask.nii.gz",
        "ingest/groups.nii.gz",
        "ingest/ingest.json",
        "ingest/mesh.vtu",
        "breathing.png",
        "frames/0/mesh.vtu",
        "frames/0/displacement.mha",
        "summary.json",
    ] {
        assert!(on_disk.iter().any(|p| p == must), "{must} not written");
    }
    let listed_paths: Vec<&str> = listed.iter().map(|f| f["path"].as_str().unwrap()).collect();
    assert_eq!(listed_paths, on_disk);
    for file in listed {
        let path = file["path"].as_str().unwrap();
        let resp = server.get(file["href"].as_str().unwrap());
        assert_eq!(resp.status(), 200, "{path}");
        let content_type = resp.headers()["content-type"].to_str().unwrap().to_string();
        assert_eq!(content_type, expected_content_type(path), "{path}");
        assert_eq!(file["content_type"], content_type.as_str());
        let bytes = resp.bytes().unwrap();
        assert_eq!(
            bytes.as_ref(),
            std::fs::read(out.join(path)).unwrap(),
            "{path}"
        );
        assert_eq!(file["bytes"], bytes.len() as u64, "{path}");
    }
    for outside in [
        "..%2Fjob.json",
        "../request.json",
        "ingest/..%2F..%2Fjob.json",
    ] {
        let resp = server.get(&format!("/v1/jobs/{job}/files/{outside}"));
        assert_eq!(resp.status(), 404, "{outside}");
        let resp = server.get(&format!("/v1/jobs/{job}/archives/{outside}"));
        assert_eq!(resp.status(), 404, "archive {outside}");
    }
    // A directory as one zip (a virtual 4D-CT phase's DICOM series is fetched this way).
    let resp = server.get(&format!("/v1/jobs/{job}/archives/ingest"));
    assert_eq!(resp.status(), 200);
    assert_eq!(resp.headers()["content-type"], "application/zip");
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(resp.bytes().unwrap())).unwrap();
    let ingest_files: Vec<&String> = on_disk
        .iter()
        .filter(|p| p.starts_with("ingest/"))
        .collect();
    assert_eq!(zip.len(), ingest_files.len());
    for path in ingest_files {
        let mut entry = zip.by_name(path.strip_prefix("ingest/").unwrap()).unwrap();
        let mut bytes = Vec::new();
        std::io::Read::read_to_end(&mut entry, &mut bytes).unwrap();
        assert_eq!(bytes, std::fs::read(out.join(path)).unwrap(), "{path}");
    }
    let resp = server.get(&format!("/v1/jobs/{job}/archives/summary.json"));
    assert_eq!(resp.status(), 404);
}

/// A metric's value in the `/metrics` text (0 when absent).
fn metric(server: &ServerProcess, name: &str) -> f64 {
    let text = server.get("/metrics").text().unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or(0.0)
}

#[test]
fn jobs_on_one_scan_ingest_once_per_settings() {
    let scratch = Scratch::new("ingest-once");
    let server = ServerProcess::start(&scratch.join("data"), &["--workers", "1"]);
    let scan = server.upload_scan(&sample("phantom-ct.nii.gz"));
    let run = |element_size_mm: f64, phases: usize| -> Value {
        let job = server.submit(&scan, &simulation_request(2, &[], element_size_mm, phases));
        server.wait_for_state(&job, &["done"], JOB_TIMEOUT);
        server.get_json(&format!("/v1/jobs/{job}/summary"))
    };
    let first = run(12.0, 2);
    assert!(
        first["timings_s"]["load_ct"].is_number(),
        "{}",
        first["timings_s"]
    );
    assert_eq!(metric(&server, "lungmotion_job_ingests_total"), 1.0);
    // Other frames, same ingest settings: the scan is not read or ingested again.
    let second = run(12.0, 3);
    assert!(
        second["timings_s"].get("load_ct").is_none(),
        "read again: {}",
        second["timings_s"]
    );
    assert_eq!(metric(&server, "lungmotion_job_ingests_total"), 1.0);
    assert_eq!(metric(&server, "lungmotion_job_ingests_reused_total"), 1.0);
    assert_eq!(second["ingest"], first["ingest"]);
    assert!(metric(&server, "lungmotion_ingest_cache_bytes") > 0.0);
    // Another element size is another ingest.
    let third = run(10.0, 2);
    assert!(third["timings_s"]["load_ct"].is_number());
    assert_eq!(metric(&server, "lungmotion_job_ingests_total"), 2.0);
    assert_ne!(third["ingest"]["elements"], first["ingest"]["elements"]);
}

#[test]
fn the_openapi_document_declares_401s_upload_formats_and_the_run_options() {
    let scratch = Scratch::new("openapi");
    let server = ServerProcess::start(&scratch.join("data"), &[]);
    let doc = server.get_json("/openapi.json");
    let mut secured = 0;
    for (path, item) in doc["paths"].as_object().unwrap() {
        for (method, op) in item.as_object().unwrap() {
            if op["security"].as_array().is_some_and(|s| !s.is_empty()) {
                secured += 1;
                let unauthorized = &op["responses"]["401"];
                assert!(
                    unauthorized["content"]["application/problem+json"].is_object(),
                    "{method} {path} declares security but no 401: {}",
                    op["responses"]
                );
            }
        }
    }
    assert!(secured >= 12, "{secured} secured operations");
    let upload = &doc["paths"]["/v1/scans"]["post"]["requestBody"];
    assert!(
        upload["content"]["application/x-nrrd"].is_object(),
        "{upload}"
    );
    assert!(upload["description"].as_str().unwrap().contains("NRRD"));

    let request = &doc["components"]["schemas"]["SimulationRequest"];
    assert!(
        request
            .to_string()
            .contains("#/components/schemas/RunOptions"),
        "{request}"
    );
    let options = &doc["components"]["schemas"]["RunOptions"]["properties"];
    for key in [
        "element_size_mm",
        "material",
        "diaphragm",
        "motion",
        "outputs",
    ] {
        assert!(options[key].is_object(), "RunOptions lacks {key}");
    }
    let instants = options["motion"]["properties"]["instants"]["oneOf"]
        .as_array()
        .unwrap();
    for (kind, field) in [
        ("every_kth", "k"),
        ("frame_rate", "hz"),
        ("phases", "count"),
    ] {
        let variant = instants
            .iter()
            .find(|v| v["properties"]["kind"]["const"] == kind)
            .unwrap_or_else(|| panic!("no {kind}"));
        assert!(
            variant["properties"][field].is_object(),
            "{kind} lacks {field}"
        );
    }
    assert!(doc["paths"]["/v1/jobs/{id}/files"]["get"].is_object());
    assert!(doc["paths"]["/v1/jobs/{id}/files/{path}"]["get"].is_object());
    assert!(doc["paths"]["/v1/jobs/{id}/archives/{path}"]["get"].is_object());
}

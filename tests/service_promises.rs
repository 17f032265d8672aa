//! The service's promises to an integrator, over a real socket: a DELETE during solving shows
//! `cancelling` and stops the solver (phantom everywhere, the POPI CT with the shared data),
//! progress that moves during solving with the frame count known from the start, one ingest
//! per scan and settings, every output file fetchable, and an OpenAPI document that lists
//! the 401s, the upload formats and the run options.
//!
//! `.ci/run` runs them again with `LUNGMOTION_TEST_OBJECT_STORE=s3`: the outputs are then
//! compared with the objects in the S3 server (moto), and a cancelled job or a deleted scan
//! must leave none there.
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
    assert_eq!(
        objects_under(server, &format!("jobs/{job}/")),
        Vec::<String>::new()
    );
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
    let out = job_outputs(&server, &job, &scratch.join("out"));
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
    let jobs = std::cell::RefCell::new(Vec::new());
    let run = |element_size_mm: f64, phases: usize| -> Value {
        let job = server.submit(&scan, &simulation_request(2, &[], element_size_mm, phases));
        server.wait_for_state(&job, &["done"], JOB_TIMEOUT);
        jobs.borrow_mut().push(job.clone());
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
    listings_page_through_every_scan_and_job(&server, &scan, &jobs.into_inner());
}

/// The listings on a server holding `scan` (with `jobs`, all done) and one more scan.
fn listings_page_through_every_scan_and_job(server: &ServerProcess, scan: &str, jobs: &[String]) {
    let other = server.upload_scan(&sample("phantom-ct.nii.gz"));
    let scans = server.get_json("/v1/scans");
    assert_eq!(scans["total"], 2, "{scans}");
    let listed: Vec<&str> = scans["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["scan_id"].as_str().unwrap())
        .collect();
    assert!(
        listed.contains(&scan) && listed.contains(&other.as_str()),
        "{listed:?}"
    );
    assert!(scans["next"].is_null());
    // Pages of two: every job once, newest first, the filters kept in the next link.
    let mut seen = Vec::new();
    let mut url = format!("/v1/jobs?limit=2&state=done&scan_id={scan}");
    let mut pages = 0;
    loop {
        let page = server.get_json(&url);
        pages += 1;
        assert_eq!(page["total"], jobs.len(), "{page}");
        for item in page["items"].as_array().unwrap() {
            assert_eq!(item["state"], "done");
            assert_eq!(item["scan_id"], scan);
            seen.push(item["job_id"].as_str().unwrap().to_string());
        }
        match page["next"].as_str() {
            Some(next) => {
                assert!(next.contains("state=done") && next.contains(scan), "{next}");
                url = next.to_string();
            }
            None => break,
        }
    }
    assert_eq!(pages, jobs.len().div_ceil(2));
    let mut expected = jobs.to_vec();
    expected.sort();
    let mut got = seen.clone();
    got.sort();
    assert_eq!(got, expected, "each job exactly once");
    let other_jobs = server.get_json(&format!("/v1/jobs?scan_id={other}"));
    assert_eq!(other_jobs["total"], 0);
    // A job that follows a target (the phantom's tumour as a ball) on the other scan.
    let mut request = simulation_request(2, &[], 12.0, 3);
    request["target"] = "point:-95,20,-80:r=12".into();
    let targeted = server.submit(&other, &request);
    server.wait_for_state(&targeted, &["done"], JOB_TIMEOUT);
    let summary = server.get_json(&format!("/v1/jobs/{targeted}/summary"));
    assert_eq!(summary["target"]["source"], "point:-95,20,-80:r=12");
    assert!(
        summary["target"]["peak_to_peak_mm"]["si"].as_f64().unwrap() > 1.0,
        "{}",
        summary["target"]
    );
    let itv = server.get(&format!("/v1/jobs/{targeted}/files/target/itv.nii.gz"));
    assert_eq!(itv.status(), 200);
    let resp = server.post_simulation(&other, &{
        let mut r = simulation_request(2, &[], 12.0, 3);
        r["target"] = "/etc/passwd:label=1".into();
        r
    });
    assert_eq!(resp.status(), 422);
    assert_eq!(
        server.get_json(&format!("/v1/jobs?scan_id={other}"))["total"],
        1
    );
    assert_eq!(server.get_json("/v1/jobs?state=failed")["total"], 0);
    for (query, slug) in [
        ("/v1/jobs?limit=0", "invalid-limit"),
        ("/v1/scans?limit=100000", "invalid-limit"),
        ("/v1/jobs?state=finished", "invalid-state"),
        ("/v1/jobs?scan_id=../etc", "invalid-scan-id"),
        ("/v1/jobs?after=not-a-cursor", "invalid-cursor"),
    ] {
        let resp = server.get(query);
        assert_eq!(resp.status(), 400, "{query}");
        let body: Value = resp.json().unwrap();
        assert!(
            body["type"].as_str().unwrap_or("").ends_with(slug),
            "{query}: {body}"
        );
    }
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
    assert!(doc["paths"]["/v1/jobs"]["get"].is_object());
    assert!(doc["paths"]["/v1/scans"]["get"].is_object());
    assert!(doc["components"]["schemas"]["JobPage"].is_object());
}

/// The server of the stored-ingest tests: one worker, 12 mm elements and two phases by
/// default, so the upload's ingest settings are a job's unless it asks for others.
fn coarse_server(scratch: &Scratch) -> ServerProcess {
    let config = scratch.join("service.toml");
    std::fs::write(
        &config,
        "[run]\nelement_size_mm = 12\n[run.motion]\ninstants = { kind = \"phases\", count = 2 }\n\
         [run.outputs]\nquicklooks = false\n",
    )
    .unwrap();
    ServerProcess::start(
        &scratch.join("data"),
        &["--workers", "1", "--config", config.to_str().unwrap()],
    )
}

/// The stored ingest of `scan` in the server's data directory.
fn stored_ingest(server: &ServerProcess, scan: &str) -> PathBuf {
    server
        .data_dir()
        .join("scans")
        .join(scan)
        .join("ingest.bin")
}

/// Runs a two-breath job of `scan` at 12 mm to `done`; its id and summary.
fn run_coarse_job(server: &ServerProcess, scan: &str) -> (String, Value) {
    let job = server.submit(scan, &simulation_request(2, &[], 12.0, 2));
    server.wait_for_state(&job, &["done"], JOB_TIMEOUT);
    let summary = server.get_json(&format!("/v1/jobs/{job}/summary"));
    (job, summary)
}

/// The frames' displacement fields of a finished job, by path (from the bucket with S3,
/// fetched into `copy`).
fn displacement_fields(server: &ServerProcess, job: &str, copy: &Path) -> Vec<(String, Vec<u8>)> {
    let out = job_outputs(server, job, copy);
    let mut paths = Vec::new();
    files_under(&out, "", &mut paths);
    paths.sort();
    let fields: Vec<(String, Vec<u8>)> = paths
        .into_iter()
        .filter(|p| p.ends_with("displacement.nii.gz"))
        .map(|p| {
            let bytes = std::fs::read(out.join(&p)).unwrap();
            (p, bytes)
        })
        .collect();
    assert_eq!(fields.len(), 2, "two phases");
    fields
}

#[test]
fn the_first_job_takes_the_ingest_its_upload_stored_with_the_same_fields() {
    let scratch = Scratch::new("stored-ingest");
    let server = coarse_server(&scratch);
    let scan = server.upload_scan(&sample("phantom-ct.nii.gz"));
    let stored = stored_ingest(&server, &scan);
    assert!(stored.is_file(), "the upload stored no ingest");
    let (job, summary) = run_coarse_job(&server, &scan);
    assert_eq!(metric(&server, "lungmotion_job_ingests_stored_total"), 1.0);
    assert_eq!(metric(&server, "lungmotion_job_ingests_total"), 0.0);
    let timings = &summary["timings_s"];
    assert!(timings["stored_ingest_read"].is_number(), "{timings}");
    assert!(timings["load_ct"].is_number(), "{timings}");
    println!(
        "phantom at 12 mm: ingest stage {:.3} s from the stored ingest ({} bytes)",
        timings["ingest"],
        std::fs::metadata(&stored).unwrap().len()
    );

    // The same CT ingested by its job: the same fields, byte for byte.
    let other = server.upload_scan(&sample("phantom-ct.nii.gz"));
    std::fs::remove_file(stored_ingest(&server, &other)).unwrap();
    let (own_job, own_summary) = run_coarse_job(&server, &other);
    assert_eq!(metric(&server, "lungmotion_job_ingests_total"), 1.0);
    assert!(own_summary["timings_s"].get("stored_ingest_read").is_none());
    println!(
        "phantom at 12 mm: ingest stage {:.3} s ingesting",
        own_summary["timings_s"]["ingest"]
    );
    assert_eq!(
        displacement_fields(&server, &job, &scratch.join("stored")),
        displacement_fields(&server, &own_job, &scratch.join("own"))
    );
    assert_eq!(
        summary["ingest"]["elements"],
        own_summary["ingest"]["elements"]
    );
    assert_eq!(
        summary["ingest"]["group_nodes"],
        own_summary["ingest"]["group_nodes"]
    );

    // A job with other ingest settings ingests, and leaves the stored ingest alone.
    let coarser = server.submit(&scan, &simulation_request(2, &[], 14.0, 2));
    server.wait_for_state(&coarser, &["done"], JOB_TIMEOUT);
    assert_eq!(metric(&server, "lungmotion_job_ingests_total"), 2.0);
    assert_eq!(metric(&server, "lungmotion_job_ingests_stored_total"), 1.0);

    // Deleting the scan deletes its stored ingest (and with S3 its objects).
    assert_eq!(server.delete(&format!("/v1/scans/{scan}")).status(), 204);
    assert!(!stored.exists());
    assert_eq!(
        objects_under(&server, &format!("scans/{scan}/")),
        Vec::<String>::new()
    );
}

#[test]
fn a_truncated_corrupt_or_other_version_stored_ingest_is_ignored_and_the_job_succeeds() {
    let scratch = Scratch::new("stored-ingest-bad");
    let server = coarse_server(&scratch);
    type Spoil = fn(&mut Vec<u8>);
    let spoils: [(&str, Spoil); 3] = [
        ("truncated", |b| b.truncate(b.len() / 2)),
        ("corrupt", |b| {
            let middle = b.len() / 2;
            b[middle] ^= 0x01;
        }),
        ("other version", |b| {
            b[8..12].copy_from_slice(&999u32.to_le_bytes())
        }),
    ];
    for (n, (what, spoil)) in spoils.iter().enumerate() {
        let scan = server.upload_scan(&sample("phantom-ct.nii.gz"));
        let path = stored_ingest(&server, &scan);
        let mut bytes = std::fs::read(&path).unwrap();
        spoil(&mut bytes);
        std::fs::write(&path, bytes).unwrap();
        let (_, summary) = run_coarse_job(&server, &scan);
        assert!(
            summary["timings_s"].get("stored_ingest_read").is_none(),
            "{what}: {}",
            summary["timings_s"]
        );
        assert_eq!(
            metric(&server, "lungmotion_job_ingests_total"),
            (n + 1) as f64,
            "{what}"
        );
    }
    assert_eq!(metric(&server, "lungmotion_job_ingests_stored_total"), 0.0);
    let log = server.log();
    assert_eq!(
        log.matches("stored ingest ignored").count(),
        3,
        "{}",
        tail(&log, 30)
    );
    for reason in ["header announces", "checksum", "format version 999"] {
        assert!(log.contains(reason), "{reason}: {}", tail(&log, 30));
    }
}

#[test]
fn a_job_deleted_during_its_ingest_is_cancelled_without_finishing_the_ingest() {
    use lungmotion::phantom::{generate_thorax_phantom, PhantomSettings};
    let scratch = Scratch::new("cancel-ingest");
    // A phantom at 1.25 mm: 304 × 224 × 272 voxels, a clinical CT's ingest in seconds.
    let phantom = generate_thorax_phantom(&PhantomSettings {
        spacing_mm: [1.25; 3],
        ..PhantomSettings::default()
    })
    .unwrap();
    let ct = scratch.join("fine-ct.nii.gz");
    lungmotion::formats::nifti::write_nifti_ct(&ct, &phantom.ct).unwrap();
    let server = coarse_server(&scratch);
    let scan = server.upload_scan(&ct);
    // Other ingest settings than the upload's, so the job segments and meshes anew.
    let job = server.submit(&scan, &simulation_request(2, &[], 10.0, 2));
    wait_until(&server, &job, |s| s["progress"]["stage"] == "ingest");
    let asked = Instant::now();
    assert_eq!(server.delete(&format!("/v1/jobs/{job}")).status(), 202);
    let status = server.wait_for_state(&job, &["cancelled"], JOB_TIMEOUT);
    let seconds = asked.elapsed().as_secs_f64();
    println!("1.25 mm phantom: cancelled {seconds:.2} s after a DELETE during the ingest");
    assert_eq!(status["state"], "cancelled", "{status}");
    assert_eq!(metric(&server, "lungmotion_job_ingests_total"), 0.0);
}

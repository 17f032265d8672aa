//! The service with its uploads and outputs in an S3 object store (`[store] object_store_url`),
//! against a real S3-protocol server: moto's (`service_support::s3`), one per test on a free
//! loopback port.
//!
//! * A journey: a scan uploaded and a job run through the object store, every output file
//!   byte-identical to the same job's on the directory store, nothing of the outputs left in
//!   the data directory, every object removed with the job and the scan; a scan whose local
//!   copy is gone is fetched back from the store by the worker. Prints the field GET's median
//!   latency on both stores and the time the outputs took to go into the store.
//! * A large upload goes in parts (multipart; the object's ETag counts them).
//! * Presigned GETs: a `307` to a URL that serves the very object.
//! * Bad input: a bucket that does not exist and refused credentials, named at start; both
//!   named by `/readyz` (`503`) when they go wrong while serving.
//! * Three machines: two API processes and a `lungmotion worker` with data directories of
//!   their own, sharing only PostgreSQL and the bucket: a target uploaded to one API process
//!   is an object the other lists and submits a job with, the worker fetches the scan and the
//!   job's copy of the target, the API serves the worker's outputs from the store, and the
//!   target deleted through either leaves no object.
//! * A series pulled from a PACS (Orthanc) by one worker is put in the store; a second worker
//!   on a third machine fetches it for a later job on that scan; deleting leaves no object.
#![cfg(feature = "cli")]

mod orthanc_support;
mod service_support;

use std::time::{Duration, Instant};

use service_support::postgres::run_to_exit;
use service_support::s3::{S3Server, TEST_KEY_ID, TEST_SECRET};
use service_support::*;

/// Longest wait for a job (seconds alone; the machine is shared).
const JOB_TIMEOUT: Duration = Duration::from_secs(600);
/// The bucket of the tests.
const BUCKET: &str = "lungmotion-test";

/// A server on `data_dir` with its blobs in `s3://BUCKET/<prefix>` on `s3`, plus `extra`.
fn s3_server(
    data_dir: &std::path::Path,
    s3: &S3Server,
    prefix: &str,
    args: &[&str],
    extra: &[(&str, &str)],
) -> ServerProcess {
    let owned = s3.service_env(BUCKET, prefix);
    let mut env: Vec<(&str, &str)> = owned
        .iter()
        .map(|(k, v)| (k.as_str(), v.as_str()))
        .collect();
    env.extend_from_slice(extra);
    ServerProcess::start_with_env(data_dir, args, &env)
}

/// GET `path` expecting 200; its bytes.
fn bytes(server: &ServerProcess, path: &str) -> Vec<u8> {
    let resp = server.get(path);
    let status = resp.status();
    let body = resp.bytes().unwrap().to_vec();
    assert_eq!(
        status,
        200,
        "GET {path}: {}",
        String::from_utf8_lossy(&body[..body.len().min(400)])
    );
    body
}

/// The median of `n` GETs of `path`, whole body read, s.
fn median_get_s(server: &ServerProcess, path: &str, n: usize) -> f64 {
    let mut times: Vec<f64> = (0..n)
        .map(|_| {
            let started = Instant::now();
            let _ = bytes(server, path);
            started.elapsed().as_secs_f64()
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[n / 2]
}

/// The `seconds` field of the server's log line saying the outputs went into the store.
fn upload_seconds(log: &str) -> Option<(f64, String)> {
    let line = log
        .lines()
        .find(|l| l.contains("outputs put in the object store"))?;
    let field = |name: &str| {
        let start = line.find(&format!("{name}="))? + name.len() + 1;
        let rest = &line[start..];
        Some(rest.split_whitespace().next()?.to_string())
    };
    Some((
        field("seconds")?.parse().ok()?,
        format!(
            "{} files, {} bytes",
            field("files").unwrap_or_default(),
            field("bytes").unwrap_or_default()
        ),
    ))
}

#[test]
fn a_journey_through_the_object_store_matches_the_directory_store_and_leaves_no_orphans() {
    let scratch = Scratch::new("objstore-journey");
    let s3 = S3Server::start(&scratch.join("moto"));
    s3.create_bucket(BUCKET);
    let server = s3_server(
        &scratch.join("data"),
        &s3,
        "site-a",
        &["--workers", "1"],
        &[],
    );
    std::fs::create_dir_all(scratch.join("plain")).unwrap();
    let plain = ServerProcess::start(&scratch.join("plain").join("data"), &["--workers", "1"]);
    let ct = sample("phantom-ct.nii.gz");

    let scan_id = server.upload_scan(&ct);
    let plain_scan = plain.upload_scan(&ct);
    let scan_keys = s3.keys(BUCKET, &format!("site-a/scans/{scan_id}/"));
    assert_eq!(
        scan_keys,
        vec![
            format!("site-a/scans/{scan_id}/ingest.bin"),
            format!("site-a/scans/{scan_id}/scan.nii.gz"),
        ]
    );
    let (stored_ct, _) = s3.object(BUCKET, &format!("site-a/scans/{scan_id}/scan.nii.gz"));
    assert!(
        stored_ct == std::fs::read(&ct).unwrap(),
        "the stored upload differs"
    );

    let request = simulation_request(2, &tracked_points(), 12.0, 4);
    let job = server.submit(&scan_id, &request);
    let plain_job = plain.submit(&plain_scan, &request);
    server.wait_for_state(&job, &["done"], JOB_TIMEOUT);
    plain.wait_for_state(&plain_job, &["done"], JOB_TIMEOUT);

    // The data directory keeps no outputs: they are in the store only.
    let local_out = server.data_dir().join("jobs").join(&job).join("out");
    assert!(
        !local_out.exists(),
        "{} is still there",
        local_out.display()
    );

    let files = server.get_json(&format!("/v1/jobs/{job}/files"))["files"]
        .as_array()
        .unwrap()
        .clone();
    let plain_files = plain.get_json(&format!("/v1/jobs/{plain_job}/files"))["files"]
        .as_array()
        .unwrap()
        .clone();
    let paths = |files: &[serde_json::Value]| -> Vec<String> {
        files
            .iter()
            .map(|f| f["path"].as_str().unwrap().to_string())
            .collect()
    };
    assert_eq!(paths(&files), paths(&plain_files), "the file lists differ");
    assert!(files.len() >= 10, "{files:?}");
    let out_keys = s3.keys(BUCKET, &format!("site-a/jobs/{job}/out/"));
    assert_eq!(
        out_keys,
        paths(&files)
            .iter()
            .map(|p| format!("site-a/jobs/{job}/out/{p}"))
            .collect::<Vec<_>>(),
        "objects and listed files differ"
    );
    for (f, p) in files.iter().zip(&plain_files) {
        let path = f["path"].as_str().unwrap();
        let served = bytes(&server, &format!("/v1/jobs/{job}/files/{path}"));
        assert_eq!(served.len() as u64, f["bytes"].as_u64().unwrap(), "{path}");
        assert_eq!(f["content_type"], p["content_type"], "{path}");
        // The summary and the ingest summary hold wall times; everything else is the same
        // computation's bytes.
        if path == "summary.json" || path == "ingest/ingest.json" {
            continue;
        }
        let reference = bytes(&plain, &format!("/v1/jobs/{plain_job}/files/{path}"));
        assert!(
            served == reference,
            "{path} differs from the directory store's"
        );
    }
    let summary = server.get_json(&format!("/v1/jobs/{job}/summary"));
    let plain_summary = plain.get_json(&format!("/v1/jobs/{plain_job}/summary"));
    let without_times = |summary: &serde_json::Value| -> Vec<serde_json::Value> {
        let mut frames = summary["frames"].as_array().unwrap().clone();
        for f in &mut frames {
            let f = f.as_object_mut().unwrap();
            f.remove("wall_time_s");
            f.remove("write_time_s");
        }
        frames
    };
    assert_eq!(without_times(&summary), without_times(&plain_summary));
    let frames = server.get_json(&format!("/v1/jobs/{job}/frames"));
    assert_eq!(frames["frames"].as_array().unwrap().len(), 4);
    // Ranges, each a ranged GET of the object, as the object's bytes.
    let (field_object, _) = s3.object(
        BUCKET,
        &format!("site-a/jobs/{job}/out/frames/1/displacement.nii.gz"),
    );
    assert_ranges_served(
        &server,
        &format!("/v1/jobs/{job}/frames/1/displacement"),
        &field_object,
    );
    assert_ranges_served(
        &server,
        &format!("/v1/jobs/{job}/files/frames/1/displacement.nii.gz"),
        &field_object,
    );
    for k in 0..4 {
        let field = format!("/v1/jobs/{job}/frames/{k}/displacement");
        assert!(
            bytes(&server, &field)
                == bytes(
                    &plain,
                    &format!("/v1/jobs/{plain_job}/frames/{k}/displacement")
                ),
            "frame {k}"
        );
        assert!(
            bytes(&server, &format!("{field}?format=mha"))
                == bytes(
                    &plain,
                    &format!("/v1/jobs/{plain_job}/frames/{k}/displacement?format=mha")
                ),
            "frame {k} as MetaImage"
        );
    }
    assert_problem(
        server.get(&format!("/v1/jobs/{job}/frames/9/displacement")),
        404,
        &["4 frames"],
    );
    assert_problem(
        server.get(&format!("/v1/jobs/{job}/files/frames/0/nothing.nii.gz")),
        404,
        &["wrote no file"],
    );
    assert!(
        bytes(&server, &format!("/v1/jobs/{job}/trajectories"))
            == bytes(&plain, &format!("/v1/jobs/{plain_job}/trajectories"))
    );
    let zipped = bytes(&server, &format!("/v1/jobs/{job}/archives/frames/0"));
    let mut archive = zip::ZipArchive::new(std::io::Cursor::new(zipped)).unwrap();
    let plain_zip = bytes(&plain, &format!("/v1/jobs/{plain_job}/archives/frames/0"));
    let plain_archive = zip::ZipArchive::new(std::io::Cursor::new(plain_zip)).unwrap();
    assert_eq!(archive.len(), plain_archive.len());
    assert!(archive.by_name("displacement.nii.gz").is_ok());

    // The cost of the object store for a field GET, against the directory store.
    let n = 41;
    let field = "frames/0/displacement";
    let from_s3 = median_get_s(&server, &format!("/v1/jobs/{job}/{field}"), n);
    let from_dir = median_get_s(&plain, &format!("/v1/jobs/{plain_job}/{field}"), n);
    let size = bytes(&server, &format!("/v1/jobs/{job}/{field}")).len();
    println!(
        "measured: GET {field} ({size} bytes), median of {n}: object store (moto) {:.1} ms, \
         directory store {:.1} ms",
        from_s3 * 1e3,
        from_dir * 1e3
    );
    match upload_seconds(&server.log()) {
        Some((s, what)) => println!(
            "measured: the job's outputs ({what}) went into the object store in {:.3} s",
            s
        ),
        None => panic!(
            "no upload line in the server's log:\n{}",
            tail(&server.log(), 30)
        ),
    }

    // A worker that has no copy of the scan (another machine's) fetches it from the store.
    let local = server
        .data_dir()
        .join("scans")
        .join(&scan_id)
        .join("scan.nii.gz");
    std::fs::remove_file(&local).unwrap();
    std::fs::remove_file(local.with_file_name("ingest.bin")).unwrap();
    let again = server.submit(&scan_id, &simulation_request(2, &[], 12.0, 2));
    server.wait_for_state(&again, &["done"], JOB_TIMEOUT);
    assert!(server.log().contains("scan fetched from the object store"));
    assert!(std::fs::read(&local).unwrap() == std::fs::read(&ct).unwrap());

    // Deleting the jobs and the scan removes every object.
    for j in [&job, &again] {
        assert_eq!(server.delete(&format!("/v1/jobs/{j}")).status(), 204);
        assert!(
            s3.keys(BUCKET, &format!("site-a/jobs/{j}/")).is_empty(),
            "objects of job {j} left"
        );
        assert_eq!(server.get(&format!("/v1/jobs/{j}/files")).status(), 404);
    }
    assert_eq!(server.delete(&format!("/v1/scans/{scan_id}")).status(), 204);
    assert_eq!(
        s3.keys(BUCKET, "site-a/"),
        Vec::<String>::new(),
        "orphaned objects"
    );
}

/// The readiness body of a `/readyz` answer (a `503` comes as problem+json whose `detail` is
/// the readiness body); a detail that is no JSON as the body's `status`.
fn readyz_body(resp: reqwest::blocking::Response) -> serde_json::Value {
    let body: serde_json::Value = resp.json().unwrap();
    if body["status"].is_string() {
        return body;
    }
    let detail = body["detail"].as_str().unwrap_or_default();
    serde_json::from_str::<serde_json::Value>(detail)
        .unwrap_or_else(|_| serde_json::json!({ "status": detail }))
}

/// The `status` of a `/readyz` answer.
fn readyz_status(resp: reqwest::blocking::Response) -> String {
    readyz_body(resp)["status"]
        .as_str()
        .unwrap_or_default()
        .to_string()
}

/// The bundled phantom as an uncompressed NIfTI whose header declares `pad` more bytes before
/// the voxels (an extension area the readers skip): a valid CT of any size.
fn padded_nifti(pad: usize) -> Vec<u8> {
    let mut gz =
        flate2::read::GzDecoder::new(std::fs::File::open(sample("phantom-ct.nii.gz")).unwrap());
    let mut nii = Vec::new();
    std::io::Read::read_to_end(&mut gz, &mut nii).unwrap();
    let offset = f32::from_le_bytes(nii[108..112].try_into().unwrap()) as usize;
    let mut padded = nii[..offset].to_vec();
    padded.resize(offset + pad, 0);
    padded[108..112].copy_from_slice(&((offset + pad) as f32).to_le_bytes());
    padded.extend_from_slice(&nii[offset..]);
    padded
}

#[test]
fn a_large_upload_goes_in_parts_and_presigned_gets_redirect_to_the_object() {
    let scratch = Scratch::new("objstore-multipart");
    let s3 = S3Server::start(&scratch.join("moto"));
    s3.create_bucket(BUCKET);
    let config = scratch.join("service.toml");
    std::fs::write(
        &config,
        "[store]\nobject_store_multipart_part_mib = 5\npresigned_get = true\npresigned_ttl_s = 60\n",
    )
    .unwrap();
    let server = s3_server(
        &scratch.join("data"),
        &s3,
        "",
        &["--workers", "1", "--config", config.to_str().unwrap()],
        &[],
    );
    // 12 MiB and a little: three parts of 5 MiB at most.
    let upload = padded_nifti(12 << 20);
    let resp = server.post_scan_bytes(upload.clone(), "application/octet-stream");
    assert_eq!(resp.status(), 201, "{:?}", resp.text());
    let scan: serde_json::Value = resp.json().unwrap();
    let scan_id = scan["scan_id"].as_str().unwrap();
    assert_eq!(scan["upload_bytes"].as_u64(), Some(upload.len() as u64));
    let (stored, etag) = s3.object(BUCKET, &format!("scans/{scan_id}/scan.nii"));
    assert!(stored == upload, "the stored upload differs");
    assert!(
        etag.trim_matches('"').ends_with("-3"),
        "ETag {etag}: not a multipart upload of 3 parts"
    );

    let job = server.submit(scan_id, &tiny_request(2));
    server.wait_for_state(&job, &["done"], JOB_TIMEOUT);
    let no_redirects = reqwest::blocking::Client::builder()
        .redirect(reqwest::redirect::Policy::none())
        .build()
        .unwrap();
    for path in [
        "frames/1/displacement",
        "files/ingest/lung-mask.nii.gz",
        "summary",
    ] {
        let resp = no_redirects
            .get(server.url(&format!("/v1/jobs/{job}/{path}")))
            .send()
            .unwrap();
        assert_eq!(resp.status(), 307, "{path}");
        let location = resp.headers()["location"].to_str().unwrap().to_string();
        assert!(
            location.starts_with(&s3.endpoint())
                && location.contains("X-Amz-Signature=")
                && location.contains("X-Amz-Expires=60&"),
            "{location}"
        );
        let fetched = no_redirects.get(&location).send().unwrap();
        assert_eq!(fetched.status(), 200, "{location}");
        let fetched = fetched.bytes().unwrap().to_vec();
        let key = location[s3.endpoint().len() + BUCKET.len() + 2..]
            .split('?')
            .next()
            .unwrap()
            .to_string();
        let (object, _) = s3.object(BUCKET, &key);
        assert!(fetched == object && !fetched.is_empty(), "{path}");
    }
    // A forged or expired URL is not tested: moto (5.2.1) serves both without IAM checks, and
    // with them answers every presigned URL, valid or not, 500 (its check reads the
    // Authorization header only); README, "Presigned URLs are not checked".
    // The client that follows redirects (the default) gets the field.
    let field = bytes(&server, &format!("/v1/jobs/{job}/frames/0/displacement"));
    assert_eq!(&field[..2], &[0x1f, 0x8b], "not gzip");
}

#[test]
fn a_missing_bucket_and_refused_credentials_are_named_at_start_and_in_readyz() {
    let scratch = Scratch::new("objstore-refusals");
    let s3 = S3Server::start(&scratch.join("moto"));
    s3.create_bucket(BUCKET);
    let data = scratch.join("data");
    let data_arg = data.to_str().unwrap();
    let endpoint = s3.endpoint();
    let base = [
        ("LUNGMOTION_S3_ENDPOINT", endpoint.as_str()),
        ("AWS_ACCESS_KEY_ID", TEST_KEY_ID),
        ("AWS_SECRET_ACCESS_KEY", TEST_SECRET),
    ];
    let serve = ["serve", "--listen", "127.0.0.1:0", "--data-dir", data_arg];

    // A bucket that does not exist: refused at start, by name.
    let mut env = base.to_vec();
    env.push(("LUNGMOTION_OBJECT_STORE_URL", "s3://no-such-bucket/x"));
    let (code, stderr) = run_to_exit(&serve, &env);
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains("\"no-such-bucket\" does not exist") && stderr.contains(&endpoint),
        "{stderr}"
    );

    // A server serving while its bucket goes: /readyz says so, naming it. (Its secret from a
    // file, as a deployment gives it.)
    let secret_file = scratch.join("s3-secret");
    std::fs::write(&secret_file, format!("{TEST_SECRET}\n")).unwrap();
    let url = format!("s3://{BUCKET}/p");
    let server = ServerProcess::start_with_env(
        &data,
        &[],
        &[
            ("LUNGMOTION_OBJECT_STORE_URL", url.as_str()),
            ("LUNGMOTION_S3_ENDPOINT", endpoint.as_str()),
            ("AWS_ACCESS_KEY_ID", TEST_KEY_ID),
            ("AWS_SECRET_ACCESS_KEY_FILE", secret_file.to_str().unwrap()),
        ],
    );
    let ready = server.get_json("/readyz");
    assert_eq!(ready["object_store"], "ok", "{ready}");
    assert!(ready.get("database").is_none(), "{ready}");
    s3.delete_bucket(BUCKET);
    let resp = server.get("/readyz");
    assert_eq!(resp.status(), 503);
    let body = readyz_body(resp);
    let status = body["status"].as_str().unwrap_or_default();
    assert!(
        status.contains("object store unavailable: s3://lungmotion-test/p at http://127.0.0.1:")
            && status.contains(&format!("the bucket \"{BUCKET}\" does not exist")),
        "{status}"
    );
    // Its own field says the same.
    assert!(
        body["object_store"]
            .as_str()
            .is_some_and(|s| status.ends_with(s) && s.contains("does not exist")),
        "{body}"
    );
    s3.create_bucket(BUCKET);
    assert_eq!(server.get("/readyz").status(), 200);

    // Credentials the server stops accepting: /readyz names them.
    // moto checks them against its IAM from now on; the server's key is unknown there.
    s3.enforce_credentials();
    let resp = server.get("/readyz");
    assert_eq!(resp.status(), 503);
    let status = readyz_status(resp);
    assert!(
        status.contains(&format!(
            "object store unavailable: s3://{BUCKET}/p at {endpoint}: the server refused the \
             credentials for bucket \"{BUCKET}\""
        )),
        "{status}"
    );
    drop(server);

    // Refused credentials at start: named.
    let mut env = base.to_vec();
    env.push(("LUNGMOTION_OBJECT_STORE_URL", url.as_str()));
    let (code, stderr) = run_to_exit(&serve, &env);
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains("refused the credentials") && stderr.contains(&format!("s3://{BUCKET}/p")),
        "{stderr}"
    );
}

#[test]
fn an_api_process_and_a_worker_share_only_the_database_and_the_bucket() {
    use service_support::postgres::{PgServer, WorkerProcess};
    let scratch = Scratch::new("objstore-machines");
    let s3 = S3Server::start(&scratch.join("moto"));
    s3.create_bucket(BUCKET);
    let db = PgServer::start(&scratch.join("postgres"));
    let url = db.url();
    let owned = s3.service_env(BUCKET, "cohort");
    let mut env: Vec<(&str, &str)> = owned
        .iter()
        .map(|(k, v)| (k.as_str(), v.as_str()))
        .collect();
    env.push(("LUNGMOTION_POSTGRES_URL", url.as_str()));
    // Two machines: each process has a data directory of its own.
    std::fs::create_dir_all(scratch.join("api")).unwrap();
    let api = ServerProcess::start_with_env(&scratch.join("api").join("data"), &[], &env);
    let worker_data = scratch.join("worker-data");
    let worker = WorkerProcess::start(
        &worker_data,
        &scratch.join("worker.log"),
        &["--workers", "1"],
        &env,
    );
    let scan = api.upload_scan(&sample("phantom-ct.nii.gz"));
    // A second API process on a third machine (behind the same load balancer).
    std::fs::create_dir_all(scratch.join("api-2")).unwrap();
    let api_2 = ServerProcess::start_sharing(&scratch.join("api-2").join("data"), &[], &env);
    // A target uploaded to it, checked against the scan's CT (which it fetches from the
    // store), is an object every process sees: the first API process lists it and submits a
    // job following it, whose copy reaches the worker through the store (the phantom's
    // labels, its tumour as the mask's label 8).
    let resp = api_2
        .client()
        .put(api_2.url(&format!("/v1/scans/{scan}/targets/gtv")))
        .header("content-type", "application/octet-stream")
        .body(std::fs::read(sample("phantom-truth.nii.gz")).unwrap())
        .send()
        .unwrap();
    assert_eq!(resp.status(), 201, "{:?}", resp.text());
    let listed = api.get_json(&format!("/v1/scans/{scan}/targets"));
    assert_eq!(listed["items"][0]["name"], "gtv", "{listed}");
    assert!(
        listed["items"][0]["labels"]
            .as_array()
            .unwrap()
            .iter()
            .any(|l| l["label"] == 8),
        "{listed}"
    );
    for machine in [&api, &api_2] {
        let local = machine.data_dir().join("scans").join(&scan).join("targets");
        assert!(
            !local.exists(),
            "a local copy of the target: {}",
            local.display()
        );
    }
    let target_objects = s3.keys(BUCKET, &format!("cohort/scans/{scan}/targets/gtv/"));
    assert_eq!(
        target_objects.len(),
        2,
        "record and file: {target_objects:?}"
    );
    let mut request = simulation_request(2, &tracked_points(), 12.0, 3);
    request["target"] = serde_json::json!({"upload": "gtv", "label": 8});
    let job = api.submit(&scan, &request);
    let target_keys = s3.keys(BUCKET, &format!("cohort/jobs/{job}/target/"));
    assert_eq!(target_keys.len(), 1, "{target_keys:?}");
    let (target_object, _) = s3.object(BUCKET, &target_keys[0]);
    assert!(target_object == std::fs::read(sample("phantom-truth.nii.gz")).unwrap());
    api.wait_for_state(&job, &["done"], JOB_TIMEOUT);
    for line in [
        "scan fetched from the object store",
        "target fetched from the object store",
    ] {
        assert!(worker.log().contains(line), "{line}: {}", worker.log());
    }
    let summary = api.get_json(&format!("/v1/jobs/{job}/summary"));
    assert!(summary["target"].is_object(), "{summary}");
    // The worker keeps nothing of the job once it ran (its deletion happens elsewhere).
    assert!(!worker_data.join("jobs").join(&job).exists());
    for k in 0..3 {
        let served = bytes(&api, &format!("/v1/jobs/{job}/frames/{k}/displacement"));
        let (object, _) = s3.object(
            BUCKET,
            &format!("cohort/jobs/{job}/out/frames/{k}/displacement.nii.gz"),
        );
        assert!(served == object, "frame {k}");
    }
    assert!(!api.data_dir().join("jobs").join(&job).join("out").exists());
    // Deleted through the other API process, the target is gone for both and from the store;
    // the job keeps its copy until it is deleted itself.
    assert_eq!(
        api_2
            .delete(&format!("/v1/scans/{scan}/targets/gtv"))
            .status(),
        204
    );
    assert_eq!(
        api.get(&format!("/v1/scans/{scan}/targets/gtv")).status(),
        404
    );
    assert_eq!(
        s3.keys(BUCKET, &format!("cohort/scans/{scan}/targets/")),
        Vec::<String>::new()
    );
    assert_eq!(
        s3.keys(BUCKET, &format!("cohort/jobs/{job}/target/")).len(),
        1
    );
    assert_eq!(api.delete(&format!("/v1/jobs/{job}")).status(), 204);
    assert_eq!(api.delete(&format!("/v1/scans/{scan}")).status(), 204);
    assert_eq!(
        s3.keys(BUCKET, "cohort/"),
        Vec::<String>::new(),
        "orphaned objects"
    );
}

/// The bundled DICOM series' StudyInstanceUID.
fn phantom_study_uid() -> String {
    orthanc_support::study_uid_of(&sample("phantom-dicom"))
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "needs Orthanc with its DICOMweb plugin (.ci/run installs it): cargo test --features slow-tests --test service_objstore"
)]
fn a_series_pulled_from_the_pacs_reaches_a_worker_on_another_machine_through_the_store() {
    use orthanc_support::Orthanc;
    use service_support::postgres::{PgServer, WorkerProcess};
    let orthanc = Orthanc::start("objstore");
    assert_eq!(orthanc.store_files(&sample("phantom-dicom")), 68);
    let scratch = Scratch::new("objstore-pacs");
    let s3 = S3Server::start(&scratch.join("moto"));
    s3.create_bucket(BUCKET);
    let db = PgServer::start(&scratch.join("postgres"));
    let url = db.url();
    let pacs = orthanc.root();
    let owned = s3.service_env(BUCKET, "pacs");
    let mut env: Vec<(&str, &str)> = owned
        .iter()
        .map(|(k, v)| (k.as_str(), v.as_str()))
        .collect();
    env.push(("LUNGMOTION_POSTGRES_URL", url.as_str()));
    env.push(("LUNGMOTION_PACS_URL", pacs.as_str()));
    // Three machines: each process has a data directory of its own.
    std::fs::create_dir_all(scratch.join("api")).unwrap();
    let api = ServerProcess::start_with_env(&scratch.join("api").join("data"), &[], &env);
    let puller_data = scratch.join("puller-data");
    let mut puller = WorkerProcess::start(
        &puller_data,
        &scratch.join("puller.log"),
        &["--workers", "1"],
        &env,
    );

    let (time_s, volume_ml) = breathing_trace(2);
    let mut request = serde_json::json!({
        "ct": {"dicomweb": {"study": phantom_study_uid()}},
        "trace": {"time_s": time_s, "volume_ml": volume_ml},
        "element_size_mm": 12,
        "motion": {"instants": {"kind": "phases", "count": 2}},
        "outputs": {"quicklooks": false},
    });
    let resp = api
        .client()
        .post(api.url("/v1/simulations"))
        .json(&request)
        .send()
        .unwrap();
    let body: serde_json::Value = resp.json().unwrap();
    let (pulled_job, scan) = (
        body["job_id"].as_str().unwrap().to_string(),
        body["scan_id"].as_str().unwrap().to_string(),
    );
    let done = api.wait_for_state(&pulled_job, &["done"], JOB_TIMEOUT);
    assert_eq!(done["state"], "done", "{done}\n{}", puller.log());
    // The pulled series (68 instances) and its stored ingest are objects of the scan.
    let series_keys = s3.keys(BUCKET, &format!("pacs/scans/{scan}/series/"));
    assert_eq!(series_keys.len(), 68, "{series_keys:?}");
    let ingest_key = format!("pacs/scans/{scan}/ingest.bin");
    assert!(s3.keys(BUCKET, &ingest_key) == vec![ingest_key.clone()]);
    let local_series = puller_data.join("scans").join(&scan).join("series");
    for key in &series_keys[..3] {
        let name = key.rsplit('/').next().unwrap();
        let (object, _) = s3.object(BUCKET, key);
        assert!(
            object == std::fs::read(local_series.join(name)).unwrap(),
            "{key}"
        );
    }
    puller.kill();

    // A worker on a third machine runs a later job on that scan: it fetches the series.
    let other_data = scratch.join("other-data");
    let other = WorkerProcess::start(
        &other_data,
        &scratch.join("other.log"),
        &["--workers", "1"],
        &env,
    );
    request.as_object_mut().unwrap().remove("ct");
    let job = api.submit(&scan, &request);
    let done = api.wait_for_state(&job, &["done"], JOB_TIMEOUT);
    assert_eq!(done["state"], "done", "{done}\n{}", other.log());
    assert!(
        other.log().contains("scan fetched from the object store"),
        "{}",
        other.log()
    );
    assert_eq!(
        entries(&other_data.join("scans").join(&scan).join("series")).len(),
        68
    );
    // Nothing of the job stays on the worker's machine once its outputs are in the store.
    assert!(!other_data.join("jobs").join(&job).exists());
    // The same CT, settings and trace: the same fields.
    for k in 0..2 {
        let field = |job: &str| bytes(&api, &format!("/v1/jobs/{job}/frames/{k}/displacement"));
        assert!(field(&job) == field(&pulled_job), "frame {k}");
    }

    for id in [&pulled_job, &job] {
        assert_eq!(api.delete(&format!("/v1/jobs/{id}")).status(), 204);
    }
    assert_eq!(api.delete(&format!("/v1/scans/{scan}")).status(), 204);
    assert_eq!(
        s3.keys(BUCKET, "pacs/"),
        Vec::<String>::new(),
        "orphaned objects"
    );
}

//! The hostile-input corpus (issue 12 item 7): generated bad DICOM, NIfTI, NRRD, MetaImage,
//! zip, trace and HTTP inputs, each expecting a refusal that names the fault (or a correct
//! acceptance) within bounded time and memory, never a panic.
//!
//! Reader cases run one per child process of this binary under `ulimit -v` (see
//! `hostile_support`). HTTP cases run against a `lungmotion serve` child and check that it
//! keeps answering and leaves nothing in its store's `tmp/`; the service's own hostile tests
//! (slow clients, request ids, the nested-sequence upload) are in `service_hostile.rs`.

mod hostile_support;
mod service_support;

use std::time::Duration;

use hostile_support::{dicom, run_group, traces, volumes, zips, Group};
use serde_json::json;
use service_support::{assert_problem, entries, Scratch, ServerProcess};

const GROUPS: [(&str, Group); 7] = [
    ("dicom", dicom::cases),
    ("nifti", volumes::nifti_cases),
    ("nrrd", volumes::nrrd_cases),
    ("metaimage", volumes::metaimage_cases),
    ("zip", zips::cases),
    ("trace", traces::cases),
    ("fuzz-dicom", dicom::fuzz_finding_cases),
];

/// Runs one case when this binary is started as a hostile-input child; else does nothing.
#[test]
fn hostile_case_child() {
    hostile_support::child_main(&GROUPS);
}

#[test]
fn the_corpus_holds_at_least_150_generated_inputs() {
    let total: usize = GROUPS.iter().map(|(_, make)| make().len()).sum();
    eprintln!("{total} reader cases + {HTTP_CASES} HTTP cases");
    assert!(
        total + HTTP_CASES >= 150,
        "{total} reader cases + {HTTP_CASES} HTTP cases"
    );
}

#[test]
fn dicom_hostile_inputs() {
    run_group("dicom", dicom::cases);
}

/// Every finding of `fuzz/run.sh` (minimised into `tests/data/fuzz/`) as a regression test.
#[test]
fn dicom_fuzz_findings() {
    run_group("fuzz-dicom", dicom::fuzz_finding_cases);
}

#[test]
fn nifti_hostile_inputs() {
    run_group("nifti", volumes::nifti_cases);
}

#[test]
fn nrrd_hostile_inputs() {
    run_group("nrrd", volumes::nrrd_cases);
}

#[test]
fn metaimage_hostile_inputs() {
    run_group("metaimage", volumes::metaimage_cases);
}

#[test]
fn zip_hostile_inputs() {
    run_group("zip", zips::cases);
}

#[test]
fn trace_hostile_inputs() {
    run_group("trace", traces::cases);
}

/// HTTP cases in [`http_hostile_requests`], counted towards the 150.
const HTTP_CASES: usize = 22;

/// Sends hostile uploads and simulation requests to one server; each must get a 4xx problem
/// naming the fault, the server must keep answering, and its `tmp/` must end empty.
#[test]
fn http_hostile_requests() {
    let scratch = Scratch::new("hostile-http");
    let data = scratch.join("data");
    let server = ServerProcess::start(&data, &["--workers", "1"]);
    let mut count = 0;
    let mut upload = |bytes: Vec<u8>, content_type: &str, status: u16, words: &[&str]| {
        count += 1;
        let resp = server.post_scan_bytes(bytes, content_type);
        assert_problem(resp, status, words);
    };
    upload(Vec::new(), "application/octet-stream", 400, &["empty"]);
    upload(b"{\"scan\": 1}".to_vec(), "application/json", 415, &[]);
    upload(b"hello".to_vec(), "text/plain", 415, &[]);
    let noise: Vec<u8> = {
        let mut rng = hostile_support::Rng::new(7);
        (0..10_000).map(|_| rng.next_u64() as u8).collect()
    };
    upload(
        noise,
        "application/octet-stream",
        422,
        &["neither a nifti", "nor a zip"],
    );
    let series = zips::zip_of(&zips::series_entries());
    upload(
        series[..series.len() / 2].to_vec(),
        "application/zip",
        422,
        &["zip"],
    );
    let mut escaping = zips::series_entries();
    escaping.push(("../../evil.dcm".into(), b"x".to_vec()));
    upload(
        zips::zip_of(&escaping),
        "application/zip",
        422,
        &["refused"],
    );
    let mut bomb = zips::series_entries();
    bomb.push(("bomb".into(), vec![0u8; 64 << 20]));
    upload(zips::zip_of(&bomb), "application/zip", 422, &["bomb"]);
    let absurd = volumes::Nifti::ct()
        .i16(42, 16384)
        .i16(44, 16384)
        .i16(46, 8)
        .bytes();
    upload(absurd, "application/octet-stream", 422, &["16384"]);
    let mut nrrd_like = b"NRRD0004\ntype: short\nsizes: 99999999 9 9\n\n".to_vec();
    nrrd_like.extend_from_slice(&[0u8; 100]);
    upload(nrrd_like, "application/octet-stream", 422, &[]);
    upload(
        dicom::Slice::ct(0).bytes()[..300].to_vec(),
        "application/octet-stream",
        422,
        &["DICOM"],
    );
    // A multipart form without the `file` part, and one whose boundary never comes.
    let form =
        "--XyZ\r\nContent-Disposition: form-data; name=\"other\"\r\n\r\nhello\r\n--XyZ--\r\n";
    upload(
        form.as_bytes().to_vec(),
        "multipart/form-data; boundary=XyZ",
        400,
        &["file"],
    );
    upload(
        b"no boundary here".to_vec(),
        "multipart/form-data; boundary=XyZ",
        400,
        &[],
    );

    let mut simulate = |path: &str, content_type: &str, body: &str, status: u16, words: &[&str]| {
        count += 1;
        let resp = server
            .client()
            .post(server.url(path))
            .header("content-type", content_type)
            .body(body.to_string())
            .send()
            .unwrap();
        assert_problem(resp, status, words);
    };
    let missing = "/v1/scans/0123456789abcdef0123456789abcdef/simulations";
    let good_trace = json!({"trace": {"time_s": [0, 2, 4], "volume_ml": [0, 500, 0]}}).to_string();
    simulate(missing, "application/json", &good_trace, 404, &[]);
    simulate(
        "/v1/scans/..%2F..%2Fetc/simulations",
        "application/json",
        &good_trace,
        404,
        &[],
    );
    simulate(
        "/v1/scans/zzzz/simulations",
        "application/json",
        &good_trace,
        404,
        &[],
    );
    simulate(missing, "application/json", "{not json", 404, &[]);
    simulate("/v1/nothing/here", "application/json", "{}", 404, &[]);
    simulate(
        "/v1/jobs/0123456789abcdef0123456789abcdef/frames/99999999999999999999/displacement",
        "application/json",
        "",
        405,
        &[],
    );
    count += 1;
    assert_problem(server.get("/v1/jobs/not-an-id"), 404, &[]);
    count += 1;
    assert_problem(
        server.get("/v1/jobs/0123456789abcdef0123456789abcdef/frames/1/displacement"),
        404,
        &[],
    );
    count += 1;
    let long_path = format!("/v1/scans/{}", "a".repeat(16_000));
    let resp = server.get(&long_path);
    assert!(
        resp.status().is_client_error(),
        "a 16 kB path: {}",
        resp.status()
    );
    count += 1;
    let resp = server
        .client()
        .get(server.url("/healthz"))
        .header("x-request-id", "a".repeat(8_000))
        .send()
        .unwrap();
    assert!(
        resp.status().as_u16() < 500,
        "an 8 kB request id: {}",
        resp.status()
    );

    // Still answering, and nothing left behind.
    let resp = server.get("/healthz");
    assert_eq!(resp.status(), 200);
    assert_eq!(count, HTTP_CASES, "update HTTP_CASES");
    std::thread::sleep(Duration::from_millis(200));
    assert_eq!(leftovers(&data), Vec::<String>::new(), "left in tmp/");
    let peak_kib = hostile_support::peak_rss_kib(&server.pid().to_string());
    assert!(
        peak_kib < 2 << 20,
        "server peak RSS {} MiB",
        peak_kib / 1024
    );
    eprintln!(
        "http: {count} cases, server peak RSS {} MiB",
        peak_kib / 1024
    );
}

/// What the store's `tmp/` holds besides the readiness probe's `writable` file.
fn leftovers(data_dir: &std::path::Path) -> Vec<String> {
    let mut names = entries(&data_dir.join("tmp"));
    names.retain(|n| n != "writable");
    names
}

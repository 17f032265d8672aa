//! `lungmotion serve` over a real socket: the full journey on the bundled phantom (checked
//! against `lungmotion run` on the same inputs), every refused input with its status and
//! reason, bearer-token authentication, and the operational endpoints.
#![cfg(feature = "cli")]

mod service_support;

use std::io::{Read, Write};
use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

use lungmotion::formats::{metaimage, nifti};
use lungmotion::volume::VolumeGeometry;
use reqwest::blocking::multipart;
use serde_json::{json, Value};
use service_support::*;

/// Longest wait for one small job (a few seconds alone; the machine is shared).
const JOB_TIMEOUT: Duration = Duration::from_secs(600);

/// The phantom CT's grid, from `sample-volumes/phantom.json`.
fn phantom_geometry() -> (Vec<usize>, Vec<f64>, Vec<f64>) {
    let text = std::fs::read_to_string(sample("phantom.json")).unwrap();
    let json: Value = serde_json::from_str(&text).unwrap();
    let g = &json["geometry"];
    (
        serde_json::from_value(g["dims"].clone()).unwrap(),
        serde_json::from_value(g["spacing_mm"].clone()).unwrap(),
        serde_json::from_value(g["origin_lps_mm"].clone()).unwrap(),
    )
}

/// A field on the phantom CT's voxels: its spacing, and its origin a whole number of voxels
/// into the CT (the lung box of the default `field_grid`), not leaving the CT.
fn assert_on_phantom_grid(g: &VolumeGeometry, what: &str) {
    let (dims, spacing_mm, origin_mm) = phantom_geometry();
    for a in 0..3 {
        assert!(
            (g.spacing_mm[a] - spacing_mm[a]).abs() < 1e-4,
            "{what}: spacing {:?} vs {spacing_mm:?}",
            g.spacing_mm
        );
        let start = (g.origin_lps_mm[a] - origin_mm[a]) / spacing_mm[a];
        assert!(
            (start - start.round()).abs() < 1e-3 && start.round() >= 0.0,
            "{what}: origin {:?} is not a voxel of the CT from {origin_mm:?}",
            g.origin_lps_mm
        );
        assert!(
            start.round() as usize + g.dims[a] <= dims[a],
            "{what}: {:?} voxels from {start} leave the CT's {dims:?}",
            g.dims
        );
    }
}

fn assert_same_geometry(a: &VolumeGeometry, b: &VolumeGeometry, what: &str) {
    assert_eq!(a.dims, b.dims, "{what}: dims");
    for i in 0..3 {
        assert!(
            (a.spacing_mm[i] - b.spacing_mm[i]).abs() < 1e-5,
            "{what}: spacing"
        );
        assert!(
            (a.origin_lps_mm[i] - b.origin_lps_mm[i]).abs() < 1e-4,
            "{what}: origin {:?} vs {:?}",
            a.origin_lps_mm,
            b.origin_lps_mm
        );
        for j in 0..3 {
            assert!(
                (a.direction_lps[i][j] - b.direction_lps[i][j]).abs() < 1e-6,
                "{what}: direction"
            );
        }
    }
}

fn bytes_of(resp: reqwest::blocking::Response, what: &str) -> (String, String, Vec<u8>) {
    let status = resp.status();
    let header = |name: &str| {
        resp.headers()
            .get(name)
            .map(|v| v.to_str().unwrap().to_string())
            .unwrap_or_default()
    };
    let content_type = header("content-type");
    let disposition = header("content-disposition");
    let bytes = resp.bytes().unwrap().to_vec();
    assert_eq!(
        status,
        200,
        "{what}: {}",
        String::from_utf8_lossy(&bytes[..bytes.len().min(500)])
    );
    (content_type, disposition, bytes)
}

/// Polls a job to `done`, checking that its progress never goes back and ends complete;
/// the final status. `submitted` is the 202 body's progress fraction.
fn wait_done_with_rising_progress(server: &ServerProcess, job_id: &str) -> Value {
    let mut fractions = vec![0.0];
    let mut states = Vec::new();
    let status = server.wait_for_state_observing(job_id, &["done"], JOB_TIMEOUT, |s| {
        fractions.push(s["progress"]["fraction"].as_f64().unwrap());
        let state = s["state"].as_str().unwrap().to_string();
        if states.last() != Some(&state) {
            states.push(state);
        }
    });
    for w in fractions.windows(2) {
        assert!(w[1] >= w[0], "progress went back: {fractions:?}");
    }
    assert!(fractions.iter().all(|f| (0.0..=1.0).contains(f)));
    assert_eq!(*fractions.last().unwrap(), 1.0, "{fractions:?}");
    let p = &status["progress"];
    assert_eq!(p["frames_written"], p["frames_total"], "{status}");
    assert!(status["attempts"].as_u64() == Some(1), "{status}");
    assert!(status["finished_at"].as_str().is_some(), "{status}");
    assert!(status["error"].is_null(), "{status}");
    println!("job {job_id}: states {states:?}, progress {fractions:?}");
    status
}

#[test]
fn nifti_journey_gives_the_clis_displacement_field() {
    let scratch = Scratch::new("journey");
    let server = ServerProcess::start(&scratch.join("data"), &["--workers", "1"]);
    let ct = sample("phantom-ct.nii.gz");

    let scan = server.upload_scan_json(&ct);
    let scan_id = scan["scan_id"].as_str().unwrap().to_string();
    assert_eq!(scan["format"], "nifti");
    assert_eq!(
        scan["upload_bytes"].as_u64(),
        Some(std::fs::metadata(&ct).unwrap().len())
    );
    let created = scan["created_at"].as_str().unwrap();
    assert!(
        created.len() >= 20 && created.as_bytes()[10] == b'T',
        "created_at {created:?} is not RFC 3339"
    );
    let ingest = &scan["ingest"];
    assert!(
        ingest["lung_volume_ml"].as_f64().unwrap() > 1000.0,
        "{ingest}"
    );
    assert!(ingest["elements"].as_u64().unwrap() > 0, "{ingest}");
    assert!(ingest["nodes"].as_u64().unwrap() > 0, "{ingest}");
    for key in [
        "element_size_mm",
        "group_nodes",
        "source",
        "segmentation",
        "model",
        "warnings",
    ] {
        assert!(!ingest[key].is_null(), "ingest lacks {key}: {ingest}");
    }
    assert_eq!(scan["links"]["self"], format!("/v1/scans/{scan_id}"));
    assert_eq!(
        scan["links"]["simulations"],
        format!("/v1/scans/{scan_id}/simulations")
    );
    let again = server.get_json(&format!("/v1/scans/{scan_id}"));
    assert_eq!(again["ingest"], scan["ingest"]);
    assert_eq!(again["created_at"], scan["created_at"]);

    let points = tracked_points();
    let request = simulation_request(2, &points, 12.0, 4);
    let submitted_at = Instant::now();
    let job_id = server.submit(&scan_id, &request);
    let status = wait_done_with_rising_progress(&server, &job_id);
    println!(
        "measured: one job (12 mm, 2 breaths at 10 Hz, 4 phases, 2 points) took {:.2} s from \
         POST to done",
        submitted_at.elapsed().as_secs_f64()
    );
    assert_eq!(status["scan_id"], scan_id.as_str());
    assert_eq!(status["progress"]["frames_total"], 4);

    let summary = server.get_json(&format!("/v1/jobs/{job_id}/summary"));
    let frames = server.get_json(&format!("/v1/jobs/{job_id}/frames"));
    let frames = frames["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 4);
    assert_eq!(summary["frames"].as_array().unwrap().len(), 4);
    for (i, f) in frames.iter().enumerate() {
        assert_eq!(f["index"], i);
        assert_eq!(
            f["displacement"],
            format!("/v1/jobs/{job_id}/frames/{i}/displacement")
        );
        for key in [
            "time_s",
            "target_volume_ml",
            "simulated_volume_ml",
            "pressure_pa",
        ] {
            assert!(f[key].as_f64().is_some_and(f64::is_finite), "{f}");
        }
    }
    // End-inhale, where the field is largest and a difference would show most.
    let k = frames
        .iter()
        .max_by(|a, b| {
            let d = |f: &Value| f["max_displacement_mm"].as_f64().unwrap();
            d(a).total_cmp(&d(b))
        })
        .unwrap()["index"]
        .as_u64()
        .unwrap() as usize;
    let peak_mm = frames[k]["max_displacement_mm"].as_f64().unwrap();
    assert!(peak_mm > 1.0, "end-inhale moves only {peak_mm} mm");

    let resp = server.get(&format!("/v1/jobs/{job_id}/trajectories"));
    let (content_type, _, csv) = bytes_of(resp, "trajectories");
    assert!(content_type.starts_with("text/csv"), "{content_type}");
    let csv = String::from_utf8(csv).unwrap();
    assert!(csv.contains("tumour") && csv.contains("apex"), "{csv}");
    assert_eq!(
        csv.lines().count(),
        1 + 4 * points.len(),
        "one row per frame and point: {csv}"
    );

    let resp = server.get(&format!("/v1/jobs/{job_id}/frames/{k}/displacement"));
    let (content_type, disposition, field_gz) = bytes_of(resp, "displacement");
    assert_eq!(content_type, "application/gzip");
    assert!(
        disposition.starts_with("attachment")
            && disposition.contains(&format!("-frame-{k}.nii.gz")),
        "{disposition}"
    );
    // The stored file: in the data directory, or (LUNGMOTION_TEST_OBJECT_STORE=s3) the object.
    let relative = format!("out/frames/{k}/displacement.nii.gz");
    let stored = match server.objects() {
        Some(s3) => {
            s3.object(TEST_BUCKET, &format!("lm/jobs/{job_id}/{relative}"))
                .0
        }
        None => {
            std::fs::read(server.data_dir().join("jobs").join(&job_id).join(&relative)).unwrap()
        }
    };
    assert!(
        stored == field_gz,
        "the served field differs from the stored {relative}"
    );
    // Ranges of it, from the data directory or the object store, as the stored bytes.
    let field_path = format!("/v1/jobs/{job_id}/frames/{k}/displacement");
    assert_ranges_served(&server, &field_path, &stored);
    let file_path = format!("/v1/jobs/{job_id}/files/frames/{k}/displacement.nii.gz");
    assert_ranges_served(&server, &file_path, &stored);
    let (served_geometry, served) =
        nifti::read_nifti_vector_field_bytes(&field_gz, "served field").unwrap();
    assert_on_phantom_grid(&served_geometry, "served field");

    let resp = server.get(&format!(
        "/v1/jobs/{job_id}/frames/{k}/displacement?format=mha"
    ));
    let (content_type, disposition, mha) = bytes_of(resp, "displacement as mha");
    assert_eq!(content_type, "application/octet-stream");
    assert!(
        disposition.contains(&format!("-frame-{k}.mha")),
        "{disposition}"
    );
    let mha_path = scratch.join("served.mha");
    std::fs::write(&mha_path, &mha).unwrap();
    let (mha_geometry, components, mha_values) = metaimage::read_mha(&mha_path).unwrap();
    assert_eq!(components, 3);
    assert_same_geometry(&mha_geometry, &served_geometry, "mha vs nifti");
    assert_eq!(mha_values.len(), served.len() * 3);
    let mha_vs_nifti = served
        .iter()
        .flatten()
        .zip(&mha_values)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert_eq!(mha_vs_nifti, 0.0, "MetaImage and NIfTI differ");

    // The CLI on the very same inputs.
    let (time_s, volume_ml) = breathing_trace(2);
    std::fs::write(scratch.join("trace.csv"), trace_csv(&time_s, &volume_ml)).unwrap();
    std::fs::write(scratch.join("points.csv"), points_csv(&points)).unwrap();
    std::fs::write(
        scratch.join("run.toml"),
        "element_size_mm = 12\n[motion]\ninstants = { kind = \"phases\", count = 4 }\n\
         [outputs]\nquicklooks = false\n",
    )
    .unwrap();
    let cli_out = scratch.join("cli-out");
    let cli_started = Instant::now();
    run_cli(&[
        &"run",
        &"--ct",
        &ct,
        &"--trace",
        &scratch.join("trace.csv"),
        &"--config",
        &scratch.join("run.toml"),
        &"--points",
        &scratch.join("points.csv"),
        &"--out",
        &cli_out,
        &"--quiet",
    ]);
    println!(
        "measured: the same job with `lungmotion run` took {:.2} s",
        cli_started.elapsed().as_secs_f64()
    );
    let (cli_geometry, cli_field) =
        nifti::read_nifti_vector_field(&cli_out.join(format!("frames/{k}/displacement.nii.gz")))
            .unwrap();
    assert_same_geometry(&served_geometry, &cli_geometry, "service vs CLI");
    assert_eq!(served.len(), cli_field.len());
    let (max_difference_mm, cli_peak_mm) = field_difference_mm(&served, &cli_field);
    println!(
        "measured: frame {k}: max voxel difference service vs CLI = {max_difference_mm:e} mm \
         (peak displacement {cli_peak_mm:.3} mm)"
    );
    assert!(cli_peak_mm > 1.0, "the CLI's field is nearly zero");
    assert!(
        max_difference_mm <= 1e-4,
        "service and CLI fields differ by {max_difference_mm} mm"
    );
    let cli_trajectories = std::fs::read_to_string(cli_out.join("trajectories.csv")).unwrap();
    assert_eq!(
        cli_trajectories.lines().next(),
        csv.lines().next(),
        "trajectories header"
    );
}

#[test]
fn dicom_zip_upload_and_csv_simulation_complete_on_the_cts_grid() {
    let scratch = Scratch::new("dicom");
    let config = scratch.join("service.toml");
    std::fs::write(
        &config,
        "[run]\nelement_size_mm = 12\n[run.motion]\ninstants = { kind = \"phases\", count = 3 }\n\
         [run.outputs]\nquicklooks = false\n",
    )
    .unwrap();
    let server = ServerProcess::start(
        &scratch.join("data"),
        &["--workers", "1", "--config", config.to_str().unwrap()],
    );
    let zip_path = scratch.join("phantom-dicom.zip");
    zip_dicom_series(&zip_path);
    let zip_bytes = std::fs::read(&zip_path).unwrap();
    let zip_len = zip_bytes.len() as u64;
    let resp = server.post_scan_bytes(zip_bytes, "application/zip");
    assert_eq!(resp.status(), 201);
    let scan: Value = resp.json().unwrap();
    assert_eq!(scan["format"], "dicom-zip", "{scan}");
    assert_eq!(scan["upload_bytes"].as_u64(), Some(zip_len));
    assert!(scan["ingest"]["lung_volume_ml"].as_f64().unwrap() > 1000.0);
    assert_eq!(scan["ingest"]["element_size_mm"].as_f64(), Some(12.0));
    let scan_id = scan["scan_id"].as_str().unwrap();

    let (time_s, volume_ml) = breathing_trace(2);
    let resp = server.post_simulation_raw(scan_id, "text/csv", trace_csv(&time_s, &volume_ml));
    let job_id = accepted_job_id(resp);
    wait_done_with_rising_progress(&server, &job_id);
    let frames = server.get_json(&format!("/v1/jobs/{job_id}/frames"));
    assert_eq!(frames["frames"].as_array().unwrap().len(), 3, "{frames}");
    let resp = server.get(&format!("/v1/jobs/{job_id}/frames/1/displacement"));
    let (_, _, gz) = bytes_of(resp, "displacement");
    let (geometry, field) = nifti::read_nifti_vector_field_bytes(&gz, "served field").unwrap();
    assert_on_phantom_grid(&geometry, "DICOM job's field");
    assert!(
        field.iter().flatten().any(|c| c.abs() > 0.5),
        "the field does not move"
    );
    // No points were given: there is nothing to track.
    assert_problem(
        server.get(&format!("/v1/jobs/{job_id}/trajectories")),
        404,
        &["points"],
    );
}

/// A deflated zip whose one entry is `mib` MiB of zeros, written as it is compressed so the
/// test never holds the inflated bytes.
fn write_zip_bomb(path: &Path, mib: usize) {
    let mut zip = zip::ZipWriter::new(std::fs::File::create(path).unwrap());
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .large_file(false);
    zip.start_file("series/IMG0001.dcm", options).unwrap();
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..mib {
        zip.write_all(&zeros).unwrap();
    }
    zip.finish().unwrap();
}

fn zip_with_entry(name: &str, data: &[u8]) -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    zip.start_file(name, options).unwrap();
    zip.write_all(data).unwrap();
    zip.finish().unwrap().into_inner()
}

fn small_png() -> Vec<u8> {
    let mut bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut bytes, 16, 16);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().unwrap();
        let pixels: Vec<u8> = (0..256u32).map(|i| (i * 37 % 251) as u8).collect();
        writer.write_image_data(&pixels).unwrap();
    }
    bytes
}

/// Deterministic noise (xorshift), so a failure can be reproduced.
fn noise(len: usize) -> Vec<u8> {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    (0..len)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 24) as u8
        })
        .collect()
}

#[test]
fn every_bad_input_is_refused_with_its_status_and_reason() {
    let scratch = Scratch::new("bad");
    let data = scratch.join("data");
    let server = ServerProcess::start(&data, &["--workers", "1"]);
    let scan_id = server.upload_scan(&sample("phantom-ct.nii.gz"));
    let mut details = Vec::new();
    let mut check = |resp, status, words: &[&str]| {
        let body = assert_problem(resp, status, words);
        details.push(body["detail"].as_str().unwrap().to_string());
        body
    };
    let sims = format!("/v1/scans/{scan_id}/simulations");
    let trace =
        |time_s: Vec<f64>, volume_ml: Vec<f64>| json!({"time_s": time_s, "volume_ml": volume_ml});
    let (time_s, volume_ml) = breathing_trace(2);

    // Simulation bodies.
    let body = check(
        server.post_simulation_raw(&scan_id, "application/json", "{\"trace\": {\"time_s\": [0,"),
        400,
        &["json"],
    );
    assert_eq!(body["instance"], sims.as_str());
    check(
        server.post_simulation(
            &scan_id,
            &json!({"trace": {"time_s": "soon", "volume_ml": [0, 1]}}),
        ),
        422,
        &["invalid type", "soon"],
    );
    check(
        server.post_simulation(&scan_id, &json!(["not", "an", "object"])),
        422,
        &["object"],
    );
    check(
        server.post_simulation(&scan_id, &json!({"points": []})),
        422,
        &["trace"],
    );
    let mut unknown = tiny_request(2);
    unknown["element_sise_mm"] = json!(8);
    check(
        server.post_simulation(&scan_id, &unknown),
        422,
        &["element_sise_mm"],
    );
    let mut unknown_nested = tiny_request(2);
    unknown_nested["motion"]["instantz"] = json!(3);
    check(
        server.post_simulation(&scan_id, &unknown_nested),
        422,
        &["instantz"],
    );
    let mut bad_size = tiny_request(2);
    bad_size["element_size_mm"] = json!(0.5);
    check(
        server.post_simulation(&scan_id, &bad_size),
        422,
        &["element"],
    );
    check(
        server.post_simulation_raw(&scan_id, "application/xml", "<trace/>"),
        415,
        &["application/json", "text/csv"],
    );
    check(
        server.post_simulation_raw(
            &scan_id,
            "text/csv",
            "time_s,volume_ml\n0,0\n0.1,5\n0.2,NaN\n0.3,8\n",
        ),
        422,
        &["sample 3", "nan"],
    );
    let mut unsorted_t = time_s.clone();
    unsorted_t.swap(5, 6);
    check(
        server.post_simulation(
            &scan_id,
            &json!({"trace": trace(unsorted_t, volume_ml.clone())}),
        ),
        422,
        &["increas"],
    );
    check(
        server.post_simulation(
            &scan_id,
            &json!({"trace": trace(vec![0.0, 0.1], vec![0.0])}),
        ),
        422,
        &[],
    );
    // A trace window outside the trace keeps nothing.
    let mut windowed = tiny_request(2);
    windowed["trace"]["window_s"] = json!([1000.0, 1001.0]);
    check(
        server.post_simulation(&scan_id, &windowed),
        422,
        &["holds 0 sample"],
    );
    // A trace that does not breathe has no phases to output.
    check(
        server.post_simulation(
            &scan_id,
            &json!({"trace": trace(vec![0.0, 1.0, 2.0], vec![5.0, 5.0, 5.0])}),
        ),
        422,
        &["far less than a breath"],
    );
    let mut bad_point = tiny_request(2);
    bad_point["points"] = json!([{"name": "a,b", "lps_mm": [0, 0, 0]}]);
    check(
        server.post_simulation(&scan_id, &bad_point),
        422,
        &["points[0]"],
    );

    // Ids.
    let absent = "0123456789abcdef0123456789abcdef";
    check(server.get(&format!("/v1/scans/{absent}")), 404, &[absent]);
    check(server.get(&format!("/v1/jobs/{absent}")), 404, &[absent]);
    check(server.get(&format!("/v1/jobs/{absent}/summary")), 404, &[]);
    check(
        server.post_simulation(absent, &tiny_request(2)),
        404,
        &[absent],
    );
    for malformed in [
        "not-an-id",
        "0123456789ABCDEF0123456789ABCDEF",
        "0123456789abcdef0123456789abcde",
        "0123456789abcdef0123456789abcdef0",
        "..%2F..%2Fetc",
    ] {
        check(server.get(&format!("/v1/scans/{malformed}")), 404, &[]);
        check(server.get(&format!("/v1/jobs/{malformed}")), 404, &[]);
        check(server.delete(&format!("/v1/jobs/{malformed}")), 404, &[]);
    }

    // Results of an unfinished job, and of a finished one that lacks the frame.
    let first = server.submit(&scan_id, &tiny_request(2));
    let second = server.submit(&scan_id, &tiny_request(2));
    // One worker: the second waits until the first is done, so it cannot be done yet.
    check(
        server.get(&format!("/v1/jobs/{second}/summary")),
        409,
        &["queued", "done"],
    );
    check(server.get(&format!("/v1/jobs/{second}/frames")), 409, &[]);
    check(
        server.get(&format!("/v1/jobs/{second}/frames/0/displacement")),
        409,
        &[],
    );
    server.wait_for_state(&first, &["done"], JOB_TIMEOUT);
    check(
        server.get(&format!("/v1/jobs/{first}/frames/2/displacement")),
        404,
        &["frame 2"],
    );
    check(
        server.get(&format!(
            "/v1/jobs/{first}/frames/99999999999999999999/displacement"
        )),
        404,
        &["frame"],
    );
    check(
        server.get(&format!("/v1/jobs/{first}/frames/-1/displacement")),
        404,
        &["frame"],
    );
    check(
        server.get(&format!(
            "/v1/jobs/{first}/frames/0/displacement?format=dicom"
        )),
        400,
        &["dicom"],
    );
    check(
        server.get(&format!("/v1/jobs/{first}/trajectories")),
        404,
        &["points"],
    );

    // Uploads.
    let ct = std::fs::read(sample("phantom-ct.nii.gz")).unwrap();
    check(
        server.post_scan_bytes(ct[..ct.len() / 2].to_vec(), "application/gzip"),
        422,
        &["truncated"],
    );
    check(
        server.post_scan_bytes(noise(100_000), "application/octet-stream"),
        422,
        &["neither a nifti", "dicom"],
    );
    check(
        server.post_scan_bytes(small_png(), "image/png"),
        422,
        &["neither a nifti"],
    );
    check(
        server.post_scan_bytes(Vec::new(), "application/octet-stream"),
        400,
        &["empty"],
    );
    check(
        server.post_scan_bytes(b"{\"scan\": \"phantom\"}".to_vec(), "application/json"),
        415,
        &["application/octet-stream"],
    );
    check(
        server.post_scan_bytes(b"not a form".to_vec(), "multipart/form-data; boundary=xyz"),
        400,
        &["multipart"],
    );
    let no_file_part = multipart::Form::new().text("note", "the scan is missing");
    check(
        server
            .client()
            .post(server.url("/v1/scans"))
            .multipart(no_file_part)
            .send()
            .unwrap(),
        400,
        &["file"],
    );
    let bomb_path = scratch.join("bomb.zip");
    write_zip_bomb(&bomb_path, 300);
    let bomb = std::fs::read(&bomb_path).unwrap();
    assert!(bomb.len() < 2 << 20, "the bomb is {} bytes", bomb.len());
    let body = check(server.post_scan_bytes(bomb, "application/zip"), 422, &[]);
    let detail = body["detail"].as_str().unwrap();
    assert!(
        ["ratio", "limit", "bomb"]
            .iter()
            .any(|w| detail.contains(w)),
        "the zip bomb's refusal does not say why: {detail}"
    );
    check(
        server.post_scan_bytes(zip_with_entry("../evil.dcm", b"DICM"), "application/zip"),
        422,
        &["evil.dcm"],
    );
    check(
        server.post_scan_bytes(zip_with_entry("/etc/evil.dcm", b"DICM"), "application/zip"),
        422,
        &["evil.dcm"],
    );
    check(
        server.post_scan_bytes(
            zip_with_entry("series/notes.txt", b"no DICOM here"),
            "application/zip",
        ),
        422,
        &[],
    );
    let zip_path = scratch.join("series.zip");
    zip_dicom_series(&zip_path);
    let zip = std::fs::read(&zip_path).unwrap();
    check(
        server.post_scan_bytes(zip[..zip.len() / 2].to_vec(), "application/zip"),
        422,
        &[],
    );

    // A multipart upload is accepted.
    let form = multipart::Form::new().text("note", "before the file").part(
        "file",
        multipart::Part::bytes(ct.clone())
            .file_name("phantom-ct.nii.gz")
            .mime_str("application/gzip")
            .unwrap(),
    );
    let resp = server
        .client()
        .post(server.url("/v1/scans"))
        .multipart(form)
        .send()
        .unwrap();
    assert_eq!(resp.status(), 201);
    let multipart_scan: Value = resp.json().unwrap();
    assert_eq!(multipart_scan["format"], "nifti");
    assert_eq!(
        multipart_scan["upload_bytes"].as_u64(),
        Some(ct.len() as u64)
    );

    // After every refusal: the good scans answer, nothing else was stored, tmp/ is clean.
    server.get_json(&format!("/v1/scans/{scan_id}"));
    let mut stored = vec![
        scan_id.clone(),
        multipart_scan["scan_id"].as_str().unwrap().to_string(),
    ];
    stored.sort();
    assert_eq!(entries(&data.join("scans")), stored);
    assert_eq!(stray_tmp_files(&data), Vec::<String>::new());
    server.wait_for_state(&second, &["done"], JOB_TIMEOUT);
    let data_dir = data.canonicalize().unwrap().display().to_string();
    let leaks: Vec<&String> = details
        .iter()
        .filter(|d| d.contains(&data_dir) || d.contains("/tmp/"))
        .collect();
    assert!(
        leaks.is_empty(),
        "problem details reveal the server's file paths: {leaks:#?}"
    );
}

/// A 413 problem naming the limit, or, when the server answered and closed before the client
/// had sent the whole body, the connection closed under the client (hyper's client then
/// reports the failed send rather than the early answer).
fn assert_too_large(sent: reqwest::Result<reqwest::blocking::Response>, what: &str) {
    match sent {
        Ok(resp) => {
            assert_problem(resp, 413, &["max_upload_mib"]);
            println!("{what} upload over the limit: 413");
        }
        Err(e) => {
            assert!(e.is_body() || e.is_request(), "{what}: {e:?}");
            println!("{what} upload over the limit: connection closed by the server ({e})");
        }
    }
}

#[test]
fn uploads_over_the_limit_are_refused_and_nothing_is_stored() {
    let scratch = Scratch::new("limit");
    let data = scratch.join("data");
    let server = ServerProcess::start_with_env(&data, &[], &[("LUNGMOTION_MAX_UPLOAD_MIB", "1")]);
    // Declared length over the limit; no declared length (chunked), cut off while streaming;
    // and as a multipart part.
    let c = server.client();
    let declared = c
        .post(server.url("/v1/scans"))
        .header("content-type", "application/octet-stream")
        .body(noise(3 << 20))
        .send();
    assert_too_large(declared, "declared length");
    let chunked = reqwest::blocking::Body::new(std::io::Cursor::new(noise(3 << 20)).take(3 << 20));
    let sent = c
        .post(server.url("/v1/scans"))
        .header("content-type", "application/octet-stream")
        .body(chunked)
        .send();
    assert_too_large(sent, "chunked");
    let form = multipart::Form::new().part("file", multipart::Part::bytes(noise(3 << 20)));
    let sent = c.post(server.url("/v1/scans")).multipart(form).send();
    assert_too_large(sent, "multipart");
    assert_eq!(entries(&data.join("scans")), Vec::<String>::new());
    assert_eq!(stray_tmp_files(&data), Vec::<String>::new());
    // The server still works: the 0.5 MB phantom fits.
    let scan_id = server.upload_scan(&sample("phantom-ct.nii.gz"));
    assert_eq!(entries(&data.join("scans")), vec![scan_id]);
}

const TOKEN: &str = "s3cret-token-for-tests";

#[test]
fn the_v1_api_needs_the_bearer_token_and_open_listening_needs_one() {
    let scratch = Scratch::new("auth");
    let server = ServerProcess::start_with_env(
        &scratch.join("data"),
        &[],
        &[("LUNGMOTION_API_TOKEN", TOKEN)],
    );
    let c = server.client();
    let absent = "0123456789abcdef0123456789abcdef";
    for resp in [
        c.get(server.url(&format!("/v1/scans/{absent}")))
            .send()
            .unwrap(),
        c.post(server.url("/v1/scans"))
            .body(vec![1u8, 2, 3])
            .send()
            .unwrap(),
    ] {
        let challenge = resp
            .headers()
            .get("www-authenticate")
            .map(|v| v.to_str().unwrap().to_string())
            .unwrap_or_default();
        assert!(
            challenge.starts_with("Bearer"),
            "WWW-Authenticate {challenge:?}"
        );
        assert_problem(resp, 401, &[]);
    }
    let wrong = c
        .get(server.url(&format!("/v1/jobs/{absent}")))
        .bearer_auth("s3cret-token-for-test")
        .send()
        .unwrap();
    assert!(wrong.headers().contains_key("www-authenticate"));
    assert_problem(wrong, 401, &[]);
    let basic = c
        .get(server.url(&format!("/v1/jobs/{absent}")))
        .basic_auth("admin", Some(TOKEN))
        .send()
        .unwrap();
    assert_problem(basic, 401, &[]);
    // With the token: the request goes through (and the absent scan is a plain 404).
    let resp = c
        .get(server.url(&format!("/v1/scans/{absent}")))
        .bearer_auth(TOKEN)
        .send()
        .unwrap();
    assert_problem(resp, 404, &[]);
    let resp = c
        .post(server.url("/v1/scans"))
        .bearer_auth(TOKEN)
        .header("content-type", "application/gzip")
        .body(std::fs::read(sample("phantom-ct.nii.gz")).unwrap())
        .send()
        .unwrap();
    assert_eq!(resp.status(), 201);
    let scan_id = resp.json::<Value>().unwrap()["scan_id"]
        .as_str()
        .unwrap()
        .to_string();
    let resp = c
        .get(server.url(&format!("/v1/scans/{scan_id}")))
        .bearer_auth(TOKEN)
        .send()
        .unwrap();
    assert_eq!(resp.status(), 200);
    assert_problem(server.get(&format!("/v1/scans/{scan_id}")), 401, &[]);
    let closed: Vec<(&str, u16)> = ["/healthz", "/readyz", "/metrics", "/openapi.json"]
        .into_iter()
        .map(|open| (open, server.get(open).status().as_u16()))
        .filter(|(_, status)| *status != 200)
        .collect();
    assert!(
        closed.is_empty(),
        "these need no token, but answered: {closed:?}"
    );

    // Beyond loopback without a token: refused at start, naming the variable.
    let mut child = serve_command(&scratch.join("open-data"), &["--listen", "0.0.0.0:0"], &[])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("serve --listen 0.0.0.0:0 without a token kept running");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut stderr = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut stderr)
        .unwrap();
    let mut stdout = String::new();
    child
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut stdout)
        .unwrap();
    assert!(!status.success(), "it started: {stdout}");
    assert_eq!(status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("LUNGMOTION_API_TOKEN"), "{stderr}");
    assert!(!stdout.contains("listening"), "{stdout}");
}

#[test]
fn operational_endpoints_answer_and_every_response_has_a_request_id() {
    let scratch = Scratch::new("ops");
    let server = ServerProcess::start(&scratch.join("data"), &["--workers", "1"]);
    let resp = server.get("/healthz");
    assert!(resp.headers().contains_key("x-request-id"));
    assert_eq!(resp.json::<Value>().unwrap(), json!({"status": "ok"}));
    let ready = server.get_json("/readyz");
    assert_eq!(ready["status"], "ready");
    assert_eq!(ready["workers"], 1);
    assert_eq!(ready["queued"], 0);
    assert_eq!(ready["running"], 0);
    // The database and the object store each reported, when the server has them.
    for (field, configured) in [
        ("database", postgres_backend()),
        ("object_store", object_store_backend()),
    ] {
        match configured {
            true => assert_eq!(ready[field], "ok", "{ready}"),
            false => assert!(ready.get(field).is_none(), "{ready}"),
        }
    }

    let resp = server
        .client()
        .get(server.url("/v1/scans/0123456789abcdef0123456789abcdef"))
        .header("x-request-id", "test-request-42")
        .send()
        .unwrap();
    assert_eq!(
        resp.headers()
            .get("x-request-id")
            .map(|v| v.to_str().unwrap()),
        Some("test-request-42")
    );
    let body = assert_problem(resp, 404, &[]);
    assert_eq!(body["request_id"], "test-request-42");
    assert_eq!(
        body["instance"],
        "/v1/scans/0123456789abcdef0123456789abcdef"
    );

    let body = assert_problem(server.get("/v2/nothing-here"), 404, &["/v2/nothing-here"]);
    assert!(body["request_id"].as_str().is_some_and(|s| !s.is_empty()));
    let resp = server
        .client()
        .put(server.url("/v1/scans"))
        .body("x")
        .send()
        .unwrap();
    assert_problem(resp, 405, &[]);

    let resp = server.get("/metrics");
    assert_eq!(resp.status(), 200);
    let metrics = resp.text().unwrap();
    for series in [
        "lungmotion_http_requests_total",
        "lungmotion_http_request_duration_seconds",
        "lungmotion_jobs",
        "lungmotion_queue_depth",
        "lungmotion_upload_bytes_total",
    ] {
        assert!(
            metrics.contains(series),
            "/metrics lacks {series}:\n{metrics}"
        );
    }
    // The requests above are counted by route and status.
    assert!(
        metrics
            .lines()
            .any(|l| l.starts_with("lungmotion_http_requests_total") && l.contains("404")),
        "{metrics}"
    );

    let doc = server.get_json("/openapi.json");
    assert!(
        doc["openapi"].as_str().unwrap().starts_with("3.1"),
        "{}",
        doc["openapi"]
    );
    for path in [
        "/v1/scans",
        "/v1/scans/{id}",
        "/v1/scans/{id}/simulations",
        "/v1/jobs/{id}",
        "/v1/jobs/{id}/summary",
        "/v1/jobs/{id}/frames",
        "/v1/jobs/{id}/frames/{k}/displacement",
        "/v1/jobs/{id}/trajectories",
        "/healthz",
    ] {
        assert!(doc["paths"][path].is_object(), "openapi lacks {path}");
    }
    assert!(doc["paths"]["/v1/scans"]["post"].is_object());
}

/// A zip of the bundled series twice: as it is, and as a second series (new series and
/// instance UIDs, series number 2); the first series' UID.
fn two_series_zip() -> (Vec<u8>, String) {
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::tags;
    let mut names: Vec<_> = std::fs::read_dir(sample("phantom-dicom"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    names.sort();
    let mut bytes = Vec::new();
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(&mut bytes));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    let mut first_uid = String::new();
    for (n, path) in names.iter().enumerate() {
        zip.start_file(format!("a/{n:03}.dcm"), options).unwrap();
        zip.write_all(&std::fs::read(path).unwrap()).unwrap();
        let mut obj = dicom_object::open_file(path).unwrap();
        first_uid = obj
            .element(tags::SERIES_INSTANCE_UID)
            .unwrap()
            .to_str()
            .unwrap()
            .trim_end_matches('\0')
            .to_string();
        let put = |obj: &mut dicom_object::DefaultDicomObject, tag, vr, value: String| {
            obj.put(DataElement::new(tag, vr, PrimitiveValue::from(value)));
        };
        put(
            &mut obj,
            tags::SERIES_INSTANCE_UID,
            VR::UI,
            "1.2.826.0.1.3680043.2.1125.55.2".into(),
        );
        put(
            &mut obj,
            tags::SOP_INSTANCE_UID,
            VR::UI,
            format!("1.2.826.0.1.3680043.2.1125.55.3.{}", n + 1),
        );
        put(&mut obj, tags::SERIES_NUMBER, VR::IS, "2".into());
        obj.update_meta(|meta| {
            meta.media_storage_sop_instance_uid =
                format!("1.2.826.0.1.3680043.2.1125.55.3.{}", n + 1);
        });
        let mut copy = Vec::new();
        obj.write_all(&mut copy).unwrap();
        zip.start_file(format!("b/{n:03}.dcm"), options).unwrap();
        zip.write_all(&copy).unwrap();
    }
    zip.finish().unwrap();
    (bytes, first_uid)
}

#[test]
fn a_scan_keeps_the_series_its_upload_named_for_its_jobs() {
    let scratch = Scratch::new("series-choice");
    let server = ServerProcess::start(&scratch.join("data"), &["--workers", "1"]);
    let (zip, uid) = two_series_zip();
    // Without a choice: refused, the series listed.
    assert_problem(
        server.post_scan_bytes(zip.clone(), "application/zip"),
        422,
        &["1.2.826.0.1.3680043.2.1125.55.2"],
    );
    let resp = server
        .client()
        .post(server.url(&format!("/v1/scans?series=uid:{uid}")))
        .header("content-type", "application/zip")
        .body(zip)
        .send()
        .unwrap();
    assert_eq!(resp.status(), 201);
    let scan: Value = resp.json().unwrap();
    assert_eq!(scan["series"], format!("uid:{uid}"), "{scan:#}");
    // The job reads the same series (the server's default would refuse the zip).
    let job = server.submit(scan["scan_id"].as_str().unwrap(), &tiny_request(2));
    let done = server.wait_for_state(&job, &["done", "failed"], Duration::from_secs(600));
    assert_eq!(done["state"], "done", "{done:#}");
}

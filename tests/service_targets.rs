//! Treatment targets over HTTP on a real server: a mask and an RTSTRUCT uploaded to the
//! phantom's DICOM scan, checked against its CT at upload, followed by jobs whose target
//! outputs equal `lungmotion run --target` on the same inputs; and every bad target refused
//! with a message naming it, leaving what was stored untouched and nothing half-written.
#![cfg(feature = "cli")]

mod service_support;

use std::path::Path;
use std::time::Duration;

use lungmotion::formats::dicom::read_dicom_series;
use lungmotion::formats::nifti::{read_nifti_labels, read_nifti_labels_bytes, write_nifti_labels};
use lungmotion::outputs::radiotherapy::rtstruct::{write_rtstruct, RoiContours};
use lungmotion::volume::Volume;
use reqwest::blocking::Response;
use serde_json::{json, Value};
use service_support::*;

/// Longest wait for one small job (a few seconds alone; the machine is shared).
const JOB_TIMEOUT: Duration = Duration::from_secs(600);
/// The mask's name: distinctive, so the log can be searched for it (a client may name a
/// target after the patient; the name is never logged).
const MASK: &str = "QUIXOTE-gtv";
/// The phantom's tumour in `phantom-truth.nii.gz`.
const TUMOUR_LABEL: u8 = 8;

fn put_target(server: &ServerProcess, scan: &str, name: &str, bytes: Vec<u8>) -> Response {
    server
        .client()
        .put(server.url(&format!("/v1/scans/{scan}/targets/{name}")))
        .header("content-type", "application/octet-stream")
        .body(bytes)
        .send()
        .unwrap()
}

/// The phantom's tumour as a mask on the DICOM series' grid.
fn tumour_mask() -> Volume<u8> {
    let labels = read_nifti_labels(&sample("phantom-truth.nii.gz")).unwrap();
    let data = labels
        .as_slice()
        .iter()
        .map(|&v| u8::from(v == TUMOUR_LABEL))
        .collect();
    Volume::from_data(labels.geometry, data).unwrap()
}

/// An RTSTRUCT on the phantom's DICOM CT holding the tumour as ROI `GTV`, in the CT's frame
/// of reference or in `frame` when given.
fn tumour_rtstruct(path: &Path, frame: Option<&str>) {
    let series = read_dicom_series(&sample("phantom-dicom")).unwrap();
    let mut study = series.study.clone();
    if let Some(uid) = frame {
        study.frame_of_reference_uid = uid.into();
    }
    let gtv = RoiContours::of_mask("GTV", "GTV", [255, 0, 0], &tumour_mask());
    write_rtstruct(path, &study, &series.volume.geometry, &[gtv], "plan").unwrap();
}

/// A finished job's file.
fn job_file(server: &ServerProcess, job: &str, path: &str) -> Vec<u8> {
    let resp = server.get(&format!("/v1/jobs/{job}/files/{path}"));
    assert_eq!(resp.status().as_u16(), 200, "{path}");
    resp.bytes().unwrap().to_vec()
}

/// The target section of a summary: planning volume, ITV volume and centroids per frame.
fn target_figures(summary: &Value) -> (f64, f64, Vec<[f64; 3]>) {
    let t = &summary["target"];
    let centroids = t["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| serde_json::from_value(f["centroid_lps_mm"].clone()).unwrap())
        .collect();
    (
        t["planning_volume_cc"].as_f64().unwrap(),
        t["itv_volume_cc"].as_f64().unwrap(),
        centroids,
    )
}

fn assert_same_target(a: &(f64, f64, Vec<[f64; 3]>), b: &(f64, f64, Vec<[f64; 3]>), what: &str) {
    assert!(
        (a.0 - b.0).abs() < 1e-9,
        "{what}: planning {} vs {}",
        a.0,
        b.0
    );
    assert!((a.1 - b.1).abs() < 1e-9, "{what}: ITV {} vs {}", a.1, b.1);
    assert_eq!(a.2.len(), b.2.len(), "{what}: frames");
    let gap =
        a.2.iter()
            .zip(&b.2)
            .flat_map(|(p, q)| (0..3).map(move |i| (p[i] - q[i]).abs()))
            .fold(0.0f64, f64::max);
    println!("measured: {what}: largest centroid difference {gap:e} mm");
    assert!(gap < 1e-6, "{what}: centroids differ by {gap} mm");
}

#[test]
fn uploaded_masks_and_rtstructs_are_followed_as_the_cli_follows_them_and_bad_ones_are_named() {
    let scratch = Scratch::new("targets");
    let data = scratch.join("data");
    let server = ServerProcess::start_with_env(
        &data,
        &["--workers", "1"],
        &[("LUNGMOTION_MAX_UPLOAD_MIB", "1")],
    );
    let zip = scratch.join("phantom.zip");
    zip_dicom_series(&zip);
    let scan = server.upload_scan(&zip);
    let scan_view = server.get_json(&format!("/v1/scans/{scan}"));
    assert_eq!(
        scan_view["links"]["targets"],
        format!("/v1/scans/{scan}/targets")
    );

    // A mask on the scan's grid: its labels, as the CT's voxels hold them.
    let truth = std::fs::read(sample("phantom-truth.nii.gz")).unwrap();
    let resp = put_target(&server, &scan, MASK, truth.clone());
    assert_eq!(resp.status().as_u16(), 201);
    assert_eq!(
        resp.headers()["location"],
        format!("/v1/scans/{scan}/targets/{MASK}").as_str()
    );
    let mask: Value = resp.json().unwrap();
    assert_eq!(mask["kind"], "mask");
    let labels: Vec<u64> = mask["labels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["label"].as_u64().unwrap())
        .collect();
    assert!(labels.contains(&(TUMOUR_LABEL as u64)), "{mask}");
    let tumour_voxels = tumour_mask().as_slice().iter().filter(|&&v| v != 0).count();
    let listed = mask["labels"]
        .as_array()
        .unwrap()
        .iter()
        .find(|l| l["label"] == TUMOUR_LABEL)
        .unwrap();
    assert_eq!(listed["voxels"].as_u64(), Some(tumour_voxels as u64));

    // An RTSTRUCT in the CT's frame of reference, its ROI rasterised on the CT.
    let rtstruct = scratch.join("plan.dcm");
    tumour_rtstruct(&rtstruct, None);
    let resp = put_target(&server, &scan, "plan", std::fs::read(&rtstruct).unwrap());
    assert_eq!(resp.status().as_u16(), 201);
    let plan: Value = resp.json().unwrap();
    assert_eq!(plan["kind"], "rtstruct");
    assert_eq!(plan["rois"][0]["name"], "GTV", "{plan}");
    assert_eq!(
        plan["rois"][0]["voxels"].as_u64(),
        Some(tumour_voxels as u64),
        "the ROI read back is the mask it was drawn from: {plan}"
    );
    let list = server.get_json(&format!("/v1/scans/{scan}/targets"));
    let names: Vec<&str> = list["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, [MASK, "plan"]);

    // A job on the mask's label; the upload deleted once the job is queued changes nothing
    // for it (it runs on its own copy).
    let mut request = tiny_request(4);
    request["target"] = json!({"upload": MASK, "label": TUMOUR_LABEL});
    let mask_job = server.submit(&scan, &request);
    assert_eq!(
        server
            .delete(&format!("/v1/scans/{scan}/targets/{MASK}"))
            .status()
            .as_u16(),
        204
    );
    assert_problem(
        server.get(&format!("/v1/scans/{scan}/targets/{MASK}")),
        404,
        &[MASK],
    );
    let mut request = tiny_request(4);
    request["target"] = json!({"upload": "plan", "roi": "gtv"});
    let rtstruct_job = server.submit(&scan, &request);
    for job in [&mask_job, &rtstruct_job] {
        let status = server.wait_for_state(job, &["done", "failed"], JOB_TIMEOUT);
        assert_eq!(status["state"], "done", "{status}");
    }

    // The outputs of `--target`, served by the job's file routes.
    let summary = server.get_json(&format!("/v1/jobs/{mask_job}/summary"));
    for path in [
        "target-motion.csv",
        "target/planning-target.nii.gz",
        "target/itv.nii.gz",
        "target/rtstruct.dcm",
        "frames/0/target.nii.gz",
    ] {
        assert!(!job_file(&server, &mask_job, path).is_empty(), "{path}");
    }
    let csv = String::from_utf8(job_file(&server, &mask_job, "target-motion.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 4, "{csv}");
    let mask_itv = read_nifti_labels_bytes(
        &job_file(&server, &mask_job, "target/itv.nii.gz"),
        "mask job ITV",
    )
    .unwrap();
    let rtstruct_summary = server.get_json(&format!("/v1/jobs/{rtstruct_job}/summary"));
    assert!(
        rtstruct_summary["target"]["source"]
            .as_str()
            .unwrap()
            .ends_with("plan.dcm:gtv"),
        "{}",
        rtstruct_summary["target"]["source"]
    );
    let rtstruct_itv = read_nifti_labels_bytes(
        &job_file(&server, &rtstruct_job, "target/itv.nii.gz"),
        "RTSTRUCT job ITV",
    )
    .unwrap();
    assert_eq!(
        mask_itv.as_slice(),
        rtstruct_itv.as_slice(),
        "the ROI drawn from the mask gives the mask's ITV"
    );
    assert_same_target(
        &target_figures(&summary),
        &target_figures(&rtstruct_summary),
        "mask job vs RTSTRUCT job",
    );

    // The CLI on the same inputs.
    let (time_s, volume_ml) = breathing_trace(2);
    std::fs::write(scratch.join("trace.csv"), trace_csv(&time_s, &volume_ml)).unwrap();
    std::fs::write(
        scratch.join("run.toml"),
        "element_size_mm = 12\n[motion]\ninstants = { kind = \"phases\", count = 4 }\n\
         [outputs]\nquicklooks = false\n",
    )
    .unwrap();
    let cli_out = scratch.join("cli-out");
    let target = format!(
        "{}:label={TUMOUR_LABEL}",
        sample("phantom-truth.nii.gz").display()
    );
    run_cli(&[
        &"run",
        &"--ct",
        &sample("phantom-dicom"),
        &"--trace",
        &scratch.join("trace.csv"),
        &"--config",
        &scratch.join("run.toml"),
        &"--target",
        &target,
        &"--out",
        &cli_out,
        &"--quiet",
    ]);
    let cli_summary: Value =
        serde_json::from_str(&std::fs::read_to_string(cli_out.join("summary.json")).unwrap())
            .unwrap();
    assert_same_target(
        &target_figures(&summary),
        &target_figures(&cli_summary),
        "service vs CLI",
    );
    let cli_itv = read_nifti_labels(&cli_out.join("target/itv.nii.gz")).unwrap();
    assert_eq!(
        cli_itv.as_slice(),
        mask_itv.as_slice(),
        "ITV service vs CLI"
    );
    assert_eq!(
        std::fs::read_to_string(cli_out.join("target-motion.csv")).unwrap(),
        csv,
        "target-motion.csv service vs CLI"
    );

    // A replacement (the same RTSTRUCT again): 200, one target of that name (with an object
    // store: the old upload's object gone, checked below).
    let resp = put_target(&server, &scan, "plan", std::fs::read(&rtstruct).unwrap());
    assert_eq!(resp.status().as_u16(), 200);

    // Bad uploads, each refused by name, the stored target left as it was.
    let before = server.get_json(&format!("/v1/scans/{scan}/targets/plan"));
    let mut shifted = read_nifti_labels(&sample("phantom-truth.nii.gz")).unwrap();
    shifted.geometry.origin_lps_mm[2] += 5.0;
    let shifted_path = scratch.join("shifted.nii.gz");
    write_nifti_labels(&shifted_path, &shifted).unwrap();
    let other_frame = scratch.join("other-frame.dcm");
    tumour_rtstruct(&other_frame, Some("1.2.826.0.1.3680043.2.1125.7.7.7"));
    let ct_slice = std::fs::read_dir(sample("phantom-dicom"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .next()
        .unwrap();
    for (name, bytes, status, words) in [
        (
            "plan",
            std::fs::read(&shifted_path).unwrap(),
            422,
            &["the target upload `plan`", "not on the CT's grid"][..],
        ),
        (
            "plan",
            std::fs::read(&other_frame).unwrap(),
            422,
            &["frame of reference", "1.2.826.0.1.3680043.2.1125.7.7.7"][..],
        ),
        (
            "plan",
            std::fs::read(&ct_slice).unwrap(),
            422,
            &["not an RT Structure Set"][..],
        ),
        (
            "plan",
            b"time_s,volume_ml\n0,0\n".to_vec(),
            422,
            &["neither a NIfTI", "RTSTRUCT"][..],
        ),
        (
            "plan",
            std::fs::read(&zip).unwrap(),
            422,
            &["zip is not accepted"][..],
        ),
        ("plan", Vec::new(), 400, &["empty"][..]),
        (
            "..%2Fscan.json",
            truth.clone(),
            400,
            &["\"../scan.json\"", "'/'"][..],
        ),
        ("a%20b", truth.clone(), 400, &["' '"][..]),
        (".hidden", truth.clone(), 400, &["start with a letter"][..]),
    ] {
        let detail = assert_problem(put_target(&server, &scan, name, bytes), status, words);
        println!("refused {name}: {}", detail["detail"]);
    }
    let resp = server
        .client()
        .put(server.url(&format!("/v1/scans/{scan}/targets/plan")))
        .header("content-type", "application/json")
        .body("{\"path\": \"/etc/passwd\"}")
        .send()
        .unwrap();
    assert_problem(resp, 415, &["RTSTRUCT"]);
    // On a client of its own: the server answers before reading the body and closes the
    // connection, which a shared pool would hand to the next request.
    let oversize = client()
        .put(server.url(&format!("/v1/scans/{scan}/targets/plan")))
        .header("content-type", "application/octet-stream")
        .body(vec![7u8; 2 << 20])
        .send();
    match oversize {
        Ok(resp) => {
            assert_problem(resp, 413, &["max_upload_mib", "target files"]);
        }
        Err(e) => assert!(e.is_body() || e.is_request(), "oversize: {e:?}"),
    }
    assert_problem(
        put_target(
            &server,
            "0123456789abcdef0123456789abcdef",
            "plan",
            truth.clone(),
        ),
        404,
        &["no scan"],
    );
    assert_eq!(
        server.get_json(&format!("/v1/scans/{scan}/targets/plan")),
        before,
        "a refused replacement keeps the stored target"
    );
    assert_eq!(stray_tmp_files(&data), Vec::<String>::new());
    let local_targets = entries(&data.join("scans").join(&scan).join("targets"));
    match server.objects() {
        // With an object store the targets are objects (which every API process and worker
        // sees), none in the data directory: the stored one's record and file, and nothing
        // of the deleted mask or the refused replacements.
        Some(s3) => {
            assert!(local_targets.is_empty(), "{local_targets:?}");
            let prefix = format!("lm/scans/{scan}/targets/");
            let keys = s3.keys(TEST_BUCKET, &prefix);
            let names: Vec<&str> = keys.iter().map(|k| &k[prefix.len()..]).collect();
            assert_eq!(names.len(), 2, "{names:?}");
            assert!(names.contains(&"plan/target.json"), "{names:?}");
            assert!(
                names
                    .iter()
                    .any(|n| n.starts_with("plan/") && n.ends_with("/plan.dcm")),
                "{names:?}"
            );
        }
        None => assert_eq!(local_targets, ["plan"]),
    }

    // Bad targets in simulation requests, each refused by name before anything is queued.
    let jobs_before = entries(&data.join("jobs"));
    for (target, words) in [
        (
            json!({"upload": MASK, "label": TUMOUR_LABEL}),
            &["no uploaded target", "it has plan"][..],
        ),
        (
            json!({"upload": "plan", "roi": "PTV"}),
            &["no ROI named `PTV`", "ROIs present: GTV"][..],
        ),
        (json!({"upload": "plan"}), &["name its ROI", "GTV"][..]),
        (json!({"upload": "plan", "label": 1}), &["not a label"][..]),
        (json!({"upload": "../plan", "roi": "GTV"}), &["'/'"][..]),
        (
            json!(format!(
                "{}:label=8",
                sample("phantom-truth.nii.gz").display()
            )),
            &["never as a path"][..],
        ),
    ] {
        let mut request = tiny_request(4);
        request["target"] = target.clone();
        let body = assert_problem(server.post_simulation(&scan, &request), 422, words);
        println!("refused target {target}: {}", body["detail"]);
    }
    assert_eq!(entries(&data.join("jobs")), jobs_before);

    // Deleting the scan (its jobs first) leaves nothing of its targets, here or in the
    // object store.
    for job in [&mask_job, &rtstruct_job] {
        assert_eq!(server.delete(&format!("/v1/jobs/{job}")).status(), 204);
    }
    assert_eq!(server.delete(&format!("/v1/scans/{scan}")).status(), 204);
    assert!(!data.join("scans").join(&scan).exists());
    if let Some(s3) = server.objects() {
        let left = s3.keys(TEST_BUCKET, "lm/");
        assert!(
            left.is_empty(),
            "objects left after the deletions: {left:?}"
        );
    }
    let log = server.log();
    assert!(
        !log.contains(MASK),
        "the target's name reached the log:\n{}",
        tail(&log, 40)
    );
}

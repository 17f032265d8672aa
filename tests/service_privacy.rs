//! The service never lets identifying DICOM fields out: a series whose PatientName and
//! PatientID are distinctive strings is uploaded as a zip to a real server logging at debug
//! level, simulated, and fetched; neither string may appear in the server's log, in any
//! response, or in any JSON record of the store.
#![cfg(feature = "cli")]

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use lungmotion::formats::dicom::{write_ct_series, CtSeriesMetadata};
use lungmotion::formats::nifti::read_nifti;

const PATIENT_NAME: &str = "QUIXOTE^DULCINEA^TOBOSO";
const PATIENT_ID: &str = "MRN-7731-55190";
/// A folder named after the patient, as some exports do: the uploader's own file names may
/// come back to the uploader, but never into the server's log.
const PATIENT_FOLDER: &str = "SANCHO-PANZA-FOLDER";

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lm-privacy-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The bundled phantom as a DICOM series carrying the identifying fields, zipped.
fn identified_series_zip(dir: &Path) -> PathBuf {
    let ct =
        read_nifti(&Path::new(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-ct.nii.gz"))
            .unwrap();
    let series = dir.join("series");
    let meta = CtSeriesMetadata {
        patient_name: PATIENT_NAME.into(),
        patient_id: PATIENT_ID.into(),
        ..CtSeriesMetadata::default()
    };
    let files = write_ct_series(&ct, &series, &meta).unwrap();
    let zip_path = dir.join("series.zip");
    let mut zip = zip::ZipWriter::new(std::fs::File::create(&zip_path).unwrap());
    let options =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for f in &files {
        let name = format!(
            "{PATIENT_FOLDER}/{}",
            f.file_name().unwrap().to_string_lossy()
        );
        zip.start_file(name, options).unwrap();
        zip.write_all(&std::fs::read(f).unwrap()).unwrap();
    }
    // A file the reader skips, so that a warning naming it is produced.
    zip.start_file(format!("{PATIENT_FOLDER}/notes.txt"), options)
        .unwrap();
    zip.write_all(b"not a DICOM file").unwrap();
    zip.finish().unwrap();
    // The written files really carry the fields (else the test would prove nothing).
    let raw = std::fs::read(&files[0]).unwrap();
    assert!(raw
        .windows(PATIENT_ID.len())
        .any(|w| w == PATIENT_ID.as_bytes()));
    zip_path
}

struct Server {
    child: Child,
    base: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_server(data_dir: &Path, log: &Path) -> Server {
    let mut child = Command::new(env!("CARGO_BIN_EXE_lungmotion"))
        .args([
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--workers",
            "1",
            "--data-dir",
        ])
        .arg(data_dir)
        .env("LUNGMOTION_LOG", "debug")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let base = line
        .trim()
        .strip_prefix("lungmotion serve: listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_string();
    Server { child, base }
}

fn assert_clean(what: &str, text: &str) {
    for secret in [PATIENT_NAME, PATIENT_ID, "QUIXOTE", "DULCINEA"] {
        assert!(!text.contains(secret), "{what} contains {secret:?}");
    }
}

#[test]
fn identifying_dicom_fields_never_reach_logs_responses_or_records() {
    let dir = scratch("phi");
    let zip_path = identified_series_zip(&dir);
    let data_dir = dir.join("data");
    let log = dir.join("server.log");
    let server = start_server(&data_dir, &log);
    let client = reqwest::blocking::Client::builder()
        .timeout(Duration::from_secs(300))
        .build()
        .unwrap();
    let mut responses = String::new();

    let upload = client
        .post(format!("{}/v1/scans", server.base))
        .header("content-type", "application/zip")
        .body(std::fs::read(&zip_path).unwrap())
        .send()
        .unwrap();
    assert_eq!(upload.status(), 201);
    let scan: serde_json::Value = serde_json::from_str(&upload.text().unwrap()).unwrap();
    responses.push_str(&scan.to_string());
    assert_eq!(scan["format"], "dicom-zip");
    let scan_id = scan["scan_id"].as_str().unwrap();

    let t: Vec<f64> = (0..=80).map(|i| i as f64 * 0.1).collect();
    let v: Vec<f64> = t
        .iter()
        .map(|t| 250.0 * (1.0 - (std::f64::consts::TAU * t / 4.0).cos()))
        .collect();
    let request = serde_json::json!({
        "trace": {"time_s": t, "volume_ml": v},
        "element_size_mm": 12,
        "motion": {"instants": {"kind": "phases", "count": 2}},
    });
    let job: serde_json::Value = client
        .post(format!("{}/v1/scans/{scan_id}/simulations", server.base))
        .json(&request)
        .send()
        .unwrap()
        .json()
        .unwrap();
    let job_id = job["job_id"].as_str().unwrap().to_string();
    let deadline = Instant::now() + Duration::from_secs(300);
    loop {
        let status = client
            .get(format!("{}/v1/jobs/{job_id}", server.base))
            .send()
            .unwrap()
            .text()
            .unwrap();
        responses.push_str(&status);
        let state: serde_json::Value = serde_json::from_str(&status).unwrap();
        match state["state"].as_str().unwrap() {
            "done" => break,
            "queued" | "running" => {}
            other => panic!("job ended {other}: {status}"),
        }
        assert!(Instant::now() < deadline, "job did not finish: {status}");
        std::thread::sleep(Duration::from_millis(200));
    }
    for path in ["summary", "frames"] {
        responses.push_str(
            &client
                .get(format!("{}/v1/jobs/{job_id}/{path}", server.base))
                .send()
                .unwrap()
                .text()
                .unwrap(),
        );
    }
    drop(server);

    assert_clean("the responses", &responses);
    let log_text = std::fs::read_to_string(&log).unwrap();
    assert!(
        log_text.contains(scan_id),
        "the log is not the server's debug log"
    );
    assert_clean("the server log", &log_text);
    assert!(
        !log_text.contains(PATIENT_FOLDER),
        "the server log names the upload's folders"
    );
    // The skipped file was reported to the uploader, so the warning path was exercised.
    assert!(
        scan["ingest"]["warnings"].to_string().contains("notes.txt"),
        "{}",
        scan["ingest"]["warnings"]
    );
    let mut records = 0;
    let mut stack = vec![data_dir.clone()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let p = entry.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|e| e == "json") {
                assert_clean(
                    &p.display().to_string(),
                    &std::fs::read_to_string(&p).unwrap(),
                );
                records += 1;
            }
        }
    }
    assert!(records >= 4, "only {records} JSON records found");
    let _ = std::fs::remove_dir_all(&dir);
}

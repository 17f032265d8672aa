//! The service against hostile or broken clients, over real sockets: connections that send
//! their headers a byte at a time or stop half-way, bodies shorter than they announced,
//! request ids carrying markup or raw bytes, and an upload whose DICOM file nests sequences
//! 200 000 deep. Also the run's `trace` options over HTTP, against the CLI.
//!
//! Both backends: with `LUNGMOTION_TEST_BACKEND=postgres` (and `LUNGMOTION_TEST_OBJECT_STORE=s3`)
//! each server gets a database, a worker process and an S3 server of its own (`.ci/run` runs
//! this file so).
#![cfg(feature = "cli")]

mod service_support;

use std::io::{ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use service_support::*;

/// The server's address from its base URL.
fn addr(server: &ServerProcess) -> SocketAddr {
    server
        .base_url()
        .trim_start_matches("http://")
        .parse()
        .unwrap()
}

/// Whether the server has closed `stream` (without blocking: the stream is non-blocking).
fn closed_by_server(stream: &mut TcpStream) -> bool {
    let mut buf = [0u8; 4096];
    loop {
        match stream.read(&mut buf) {
            Ok(0) => return true,
            // A response (there should be none before the headers are complete): keep reading.
            Ok(_) => continue,
            Err(e) if e.kind() == ErrorKind::WouldBlock => return false,
            Err(_) => return true,
        }
    }
}

/// Opens `count` connections that send `prefix` at once and then, every `tick`, one more
/// byte of `trickle` (nothing when it is empty); for each, the seconds after the start at
/// which the server closed it (`None`: still open at `deadline`).
fn hold_slow_connections(
    server: &ServerProcess,
    count: usize,
    prefix: &[u8],
    trickle: &[u8],
    tick: Duration,
    deadline: Duration,
) -> Vec<Option<f64>> {
    let started = Instant::now();
    let mut streams: Vec<(TcpStream, Option<f64>)> = (0..count)
        .map(|_| {
            let s = TcpStream::connect_timeout(&addr(server), Duration::from_secs(10)).unwrap();
            s.set_nonblocking(true).unwrap();
            (s, None)
        })
        .collect();
    for (s, _) in &mut streams {
        // Beyond the cap a connection waits in the backlog: its bytes wait in the kernel.
        let _ = s.write(prefix);
    }
    let mut k = 0;
    while started.elapsed() < deadline && streams.iter().any(|(_, c)| c.is_none()) {
        for (s, closed) in streams.iter_mut().filter(|(_, c)| c.is_none()) {
            let written = match trickle.get(k) {
                Some(byte) => s.write(std::slice::from_ref(byte)),
                None => Ok(0),
            };
            if matches!(&written, Err(e) if e.kind() != ErrorKind::WouldBlock)
                || closed_by_server(s)
            {
                *closed = Some(started.elapsed().as_secs_f64());
            }
        }
        k += 1;
        std::thread::sleep(tick);
    }
    streams.into_iter().map(|(_, c)| c).collect()
}

/// Polls `/healthz` every 100 ms on fresh connections until `stop`; each answer's latency.
fn probe_health(
    server: &ServerProcess,
    stop: Arc<AtomicBool>,
) -> std::thread::JoinHandle<Vec<f64>> {
    let url = server.url("/healthz");
    std::thread::spawn(move || {
        let client = reqwest::blocking::Client::builder()
            .pool_max_idle_per_host(0)
            .timeout(Duration::from_secs(60))
            .build()
            .unwrap();
        let mut latencies = Vec::new();
        while !stop.load(Ordering::SeqCst) {
            let asked = Instant::now();
            let resp = client.get(&url).send().expect("/healthz did not answer");
            assert_eq!(resp.status(), 200, "/healthz");
            latencies.push(asked.elapsed().as_secs_f64());
            std::thread::sleep(Duration::from_millis(100));
        }
        latencies
    })
}

/// A request's headers that never end: a header line after another.
fn endless_headers(start: &str) -> Vec<u8> {
    let mut bytes = start.as_bytes().to_vec();
    for i in 0..2000 {
        bytes.extend_from_slice(format!("X-Slow-{i}: aaaaaaaaaaaaaaaa\r\n").as_bytes());
    }
    bytes
}

/// Slow connections against a server with a cap of `cap` and a 1 s header timeout: every
/// one is closed, within `limit_s`, and `/healthz` answers throughout.
fn slow_connections_are_closed(
    name: &str,
    count: usize,
    cap: usize,
    (prefix, trickle): (&[u8], &[u8]),
    limit_s: f64,
) {
    let scratch = Scratch::new(name);
    let cap_arg = cap.to_string();
    let server = ServerProcess::start(
        &scratch.join("data"),
        &[
            "--workers",
            "1",
            "--max-connections",
            &cap_arg,
            "--header-read-timeout-s",
            "1",
        ],
    );
    let stop = Arc::new(AtomicBool::new(false));
    let prober = probe_health(&server, stop.clone());
    let closed = hold_slow_connections(
        &server,
        count,
        prefix,
        trickle,
        Duration::from_millis(100),
        Duration::from_secs_f64(limit_s + 20.0),
    );
    stop.store(true, Ordering::SeqCst);
    let latencies = prober.join().expect("/healthz stopped answering");
    let still_open = closed.iter().filter(|c| c.is_none()).count();
    let last_s = closed.iter().flatten().copied().fold(0.0, f64::max);
    let slowest_probe_s = latencies.iter().copied().fold(0.0, f64::max);
    println!(
        "measured: {count} slow connections (cap {cap}, header timeout 1 s): {} closed, the \
         last after {last_s:.1} s; /healthz answered {} times, slowest {slowest_probe_s:.2} s",
        count - still_open,
        latencies.len()
    );
    assert_eq!(
        still_open, 0,
        "{still_open} of {count} connections held open"
    );
    assert!(
        last_s <= limit_s,
        "the last connection closed after {last_s:.1} s"
    );
    // Each probe beyond the first waits behind slow connections, so few fit in the run.
    assert!(
        latencies.len() >= 2,
        "/healthz answered only {} times",
        latencies.len()
    );
    // Beyond the cap a probe waits in the backlog behind the slow connections queued before
    // it, which the header timeout lets in `cap` at a time, one batch a second.
    let batches_ahead = (count as f64 / cap as f64).ceil();
    assert!(
        slowest_probe_s < batches_ahead + 3.0,
        "/healthz took {slowest_probe_s:.2} s"
    );
    // The server is still whole: a normal request on a fresh connection.
    assert_eq!(server.get_json("/healthz")["status"], "ok");
}

#[test]
fn connections_sending_headers_a_byte_at_a_time_are_closed_and_healthz_answers() {
    // 200 connections, 4 times the cap: accepted 50 at a time as the timeout frees slots.
    let headers = endless_headers("GET /healthz HTTP/1.1\r\nHost: x\r\n");
    slow_connections_are_closed("slowloris", 200, 50, (b"", &headers), 12.0);
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow study (1 100 connections): cargo test --features slow-tests"
)]
fn eleven_hundred_half_sent_requests_are_closed_and_healthz_answers() {
    slow_connections_are_closed(
        "halfsent",
        1100,
        256,
        (
            b"POST /v1/scans HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\n",
            b"",
        ),
        15.0,
    );
}

/// Sends `head` (request line and headers) and `body_part` of a body that announced more,
/// then reads the answer; its status line and the seconds it took after the last byte sent.
fn short_body_answer(server: &ServerProcess, head: &str, body_part: &[u8]) -> (String, f64) {
    let mut s = TcpStream::connect(addr(server)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    s.write_all(head.as_bytes()).unwrap();
    s.write_all(body_part).unwrap();
    let sent = Instant::now();
    let mut answer = Vec::new();
    let _ = s.read_to_end(&mut answer);
    let text = String::from_utf8_lossy(&answer).into_owned();
    (text, sent.elapsed().as_secs_f64())
}

#[test]
fn a_body_shorter_than_its_content_length_is_answered_408_and_nothing_is_kept() {
    let scratch = Scratch::new("shortbody");
    let data = scratch.join("data");
    let server = ServerProcess::start(&data, &["--workers", "1", "--body-read-timeout-s", "1"]);
    let upload_head =
        "POST /v1/scans HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\n\
                       Content-Length: 100000\r\nX-Request-Id: short-upload\r\n\r\n";
    let (answer, after_s) = short_body_answer(&server, upload_head, &[0x1f; 1000]);
    println!("measured: an upload 99 000 bytes short was answered after {after_s:.2} s");
    assert!(answer.starts_with("HTTP/1.1 408"), "{answer}");
    assert!(answer.contains("body_read_timeout_s"), "{answer}");
    assert!(
        answer.contains("urn:lungmotion:problem:body-timeout"),
        "{answer}"
    );
    assert!(
        answer.contains("short-upload"),
        "the request id is lost: {answer}"
    );
    assert!(after_s < 10.0, "answered after {after_s:.2} s");

    let json_head = "POST /v1/scans/0123456789abcdef0123456789abcdef/simulations HTTP/1.1\r\n\
                     Host: x\r\nContent-Type: application/json\r\nContent-Length: 5000\r\n\r\n";
    let (answer, after_s) = short_body_answer(&server, json_head, b"{\"trace\": {\"time_s\": [0,");
    println!("measured: a JSON request 4 975 bytes short was answered after {after_s:.2} s");
    assert!(answer.starts_with("HTTP/1.1 408"), "{answer}");
    assert!(answer.contains("body-timeout"), "{answer}");
    assert!(after_s < 10.0, "answered after {after_s:.2} s");
    assert_eq!(stray_tmp_files(&data), Vec::<String>::new());
    assert_eq!(entries(&data.join("scans")), Vec::<String>::new());
    assert_eq!(server.get_json("/healthz")["status"], "ok");
}

/// The `x-request-id` the server answers `raw_id` with, and the problem body's.
fn answered_request_id(server: &ServerProcess, raw_id: &[u8]) -> (Vec<u8>, Value) {
    let mut s = TcpStream::connect(addr(server)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let mut request = b"GET /v1/scans/0123456789abcdef0123456789abcdef HTTP/1.1\r\nHost: x\r\n\
                        Connection: close\r\nX-Request-Id: "
        .to_vec();
    request.extend_from_slice(raw_id);
    request.extend_from_slice(b"\r\n\r\n");
    s.write_all(&request).unwrap();
    let mut answer = Vec::new();
    s.read_to_end(&mut answer).unwrap();
    let split = answer
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("no end of headers");
    let (head, body) = (&answer[..split], &answer[split + 4..]);
    assert!(
        head.starts_with(b"HTTP/1.1 404"),
        "{}",
        String::from_utf8_lossy(head)
    );
    let echoed = head
        .split(|&b| b == b'\n')
        .find_map(|line| {
            let line = line.strip_suffix(b"\r").unwrap_or(line);
            let lower = line.to_ascii_lowercase();
            lower
                .starts_with(b"x-request-id:")
                .then(|| line[13..].trim_ascii().to_vec())
        })
        .expect("no x-request-id in the answer");
    let body: Value = serde_json::from_slice(body).expect("problem body");
    (echoed, body)
}

fn is_uuid(id: &[u8]) -> bool {
    id.len() == 36
        && id.iter().enumerate().all(|(i, &b)| {
            if [8, 13, 18, 23].contains(&i) {
                b == b'-'
            } else {
                b.is_ascii_hexdigit()
            }
        })
}

#[test]
fn only_safe_request_ids_are_echoed_others_are_replaced_by_a_uuid() {
    let scratch = Scratch::new("requestid");
    let server = ServerProcess::start(&scratch.join("data"), &["--workers", "1"]);
    let sixty_four = "a".repeat(64);
    for kept in ["abc.DEF_1-2", "7", sixty_four.as_str()] {
        let (echoed, body) = answered_request_id(&server, kept.as_bytes());
        assert_eq!(echoed, kept.as_bytes(), "{kept:?} not kept");
        assert_eq!(body["request_id"], kept);
    }
    let sixty_five = "a".repeat(65);
    let hostile: [&[u8]; 5] = [
        b"<script>alert(1)</script>",
        &[0xff, 0xfe],
        b"id with spaces",
        b"a/b%0d%0a",
        sixty_five.as_bytes(),
    ];
    for given in hostile {
        let (echoed, body) = answered_request_id(&server, given);
        assert!(
            is_uuid(&echoed),
            "{:?} answered with {:?}",
            String::from_utf8_lossy(given),
            String::from_utf8_lossy(&echoed)
        );
        assert_eq!(body["request_id"].as_str().unwrap().as_bytes(), echoed);
    }
    let log = server.log();
    assert!(!log.contains("<script>"), "the hostile id reached the log");
}

/// A DICOM Part 10 file (explicit VR little endian, CT) whose data set is `depth` sequences,
/// each of undefined length holding one item of undefined length holding the next.
fn nested_sequences_dicom(depth: usize) -> Vec<u8> {
    fn element(out: &mut Vec<u8>, group: u16, elem: u16, vr: &[u8; 2], value: &[u8]) {
        out.extend_from_slice(&group.to_le_bytes());
        out.extend_from_slice(&elem.to_le_bytes());
        out.extend_from_slice(vr);
        out.extend_from_slice(&(value.len() as u16).to_le_bytes());
        out.extend_from_slice(value);
    }
    // File meta information version: OB, whose length takes 4 bytes after 2 reserved ones.
    let mut meta = vec![0x02, 0x00, 0x01, 0x00, b'O', b'B', 0, 0, 2, 0, 0, 0, 0, 1];
    element(
        &mut meta,
        0x0002,
        0x0002,
        b"UI",
        b"1.2.840.10008.5.1.4.1.1.2\0",
    );
    element(&mut meta, 0x0002, 0x0003, b"UI", b"1.2.3.4.5.6.7.8.9\0");
    element(&mut meta, 0x0002, 0x0010, b"UI", b"1.2.840.10008.1.2.1\0");
    let mut file = vec![0u8; 128];
    file.extend_from_slice(b"DICM");
    element(
        &mut file,
        0x0002,
        0x0000,
        b"UL",
        &(meta.len() as u32).to_le_bytes(),
    );
    file.extend_from_slice(&meta);
    element(&mut file, 0x0008, 0x0060, b"CS", b"CT");
    element(&mut file, 0x0020, 0x000e, b"UI", b"1.2.3.4.5.6.7.8.10\0");
    let open_sequence: [u8; 12] = [
        0x08, 0x00, 0x15, 0x11, b'S', b'Q', 0, 0, 0xff, 0xff, 0xff, 0xff,
    ];
    let open_item: [u8; 8] = [0xfe, 0xff, 0x00, 0xe0, 0xff, 0xff, 0xff, 0xff];
    let close_item: [u8; 8] = [0xfe, 0xff, 0x0d, 0xe0, 0, 0, 0, 0];
    let close_sequence: [u8; 8] = [0xfe, 0xff, 0xdd, 0xe0, 0, 0, 0, 0];
    for _ in 0..depth {
        file.extend_from_slice(&open_sequence);
        file.extend_from_slice(&open_item);
    }
    for _ in 0..depth {
        file.extend_from_slice(&close_item);
        file.extend_from_slice(&close_sequence);
    }
    file
}

#[test]
fn an_upload_nesting_200000_sequences_is_refused_and_the_server_keeps_answering() {
    let scratch = Scratch::new("nested");
    let data = scratch.join("data");
    let server = ServerProcess::start(&data, &["--workers", "1"]);
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    // Stored, not deflated: the repetitive file would otherwise trip the zip ratio cap first.
    let options =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    zip.start_file("series/nested.dcm", options).unwrap();
    zip.write_all(&nested_sequences_dicom(200_000)).unwrap();
    let zip = zip.finish().unwrap().into_inner();
    let asked = Instant::now();
    let resp = server.post_scan_bytes(zip, "application/zip");
    let status = resp.status().as_u16();
    let body = assert_problem(resp, 422, &[]);
    println!(
        "measured: the nested-sequence upload was answered {status} after {:.2} s: {}",
        asked.elapsed().as_secs_f64(),
        body["detail"]
    );
    let kind = body["type"].as_str().unwrap();
    assert!(
        kind.ends_with("scan-reader-crashed") || kind.ends_with("invalid-scan"),
        "{body}"
    );
    assert!(body["detail"].as_str().unwrap().len() > 20, "{body}");
    assert_eq!(server.get_json("/healthz")["status"], "ok");
    assert_eq!(stray_tmp_files(&data), Vec::<String>::new());
    assert_eq!(entries(&data.join("scans")), Vec::<String>::new());
    // And it still does its work.
    server.upload_scan(&sample("phantom-ct.nii.gz"));
}

/// A gzip NIfTI CT of 512 × 512 × `slices` whose HU values ramp and wrap, so that it compresses
/// well below the readers' 250× ratio cap yet needs its full size in memory to be read.
fn large_ramp_ct(path: &std::path::Path, slices: usize) {
    use lungmotion::volume::{Volume, VolumeGeometry};
    let geometry = VolumeGeometry::axis_aligned([512, 512, slices], [0.8, 0.8, 2.0], [0.0; 3]);
    let data = (0..512 * 512 * slices)
        .map(|n| ((n * 7 + n / 512 * 13 + n / (512 * 512) * 3) % 2000) as f32 - 1000.0)
        .collect();
    let ct = Volume::from_data(geometry, data).unwrap();
    lungmotion::formats::nifti::write_nifti_ct(path, &ct).unwrap();
}

#[test]
fn an_upload_needing_more_than_ingest_memory_mib_is_refused_by_name_and_the_server_lives() {
    // The readers size their budget from the room under the child's address-space limit, so
    // the refusal comes before the allocation, naming the limit.
    let scratch = Scratch::new("ingest-memory");
    let data = scratch.join("data");
    let ct = scratch.join("large.nii.gz");
    large_ramp_ct(&ct, 60);
    let upload = std::fs::read(&ct).unwrap();
    let inflated = 512 * 512 * 60 * 2;
    println!(
        "measured: a {:.1} MB upload inflating {:.0}× to {} MB of voxels",
        upload.len() as f64 / 1e6,
        inflated as f64 / upload.len() as f64,
        inflated / 1_000_000
    );
    let server = ServerProcess::start_with_env(
        &data,
        &["--workers", "1"],
        &[("LUNGMOTION_INGEST_MEMORY_MIB", "256")],
    );
    let asked = Instant::now();
    let resp = server.post_scan_bytes(upload, "application/gzip");
    let body = assert_problem(
        resp,
        422,
        &["address-space limit", "ingest_memory_mib", "budget"],
    );
    println!(
        "measured: refused after {:.2} s: {}",
        asked.elapsed().as_secs_f64(),
        body["detail"]
    );
    assert!(
        body["type"].as_str().unwrap().ends_with("invalid-scan"),
        "{body}"
    );
    assert_eq!(server.get_json("/healthz")["status"], "ok");
    assert_eq!(stray_tmp_files(&data), Vec::<String>::new());
    assert_eq!(entries(&data.join("scans")), Vec::<String>::new());
    // The limit is the child's alone: the same server still ingests a real scan.
    server.upload_scan(&sample("phantom-ct.nii.gz"));
}

#[test]
fn the_traces_reference_over_http_gives_the_clis_frames() {
    let scratch = Scratch::new("tracereference");
    let server = ServerProcess::start(&scratch.join("data"), &["--workers", "1"]);
    let ct = sample("phantom-ct.nii.gz");
    let scan_id = server.upload_scan(&ct);
    // Absolute lung volumes, as a spirometer referenced to the scan records them.
    let scanned_ml = 2750.0;
    let (time_s, change_ml) = breathing_trace(2);
    let absolute_ml: Vec<f64> = change_ml.iter().map(|v| v + scanned_ml).collect();
    let request = json!({
        "trace": {
            "time_s": time_s,
            "volume_ml": absolute_ml,
            "reference": {"absolute": {"scanned_volume_ml": scanned_ml}},
        },
        "element_size_mm": 12.0,
        "motion": {"instants": {"kind": "phases", "count": 3}},
        "outputs": {"quicklooks": false},
    });
    let job_id = server.submit(&scan_id, &request);
    server.wait_for_state(&job_id, &["done"], Duration::from_secs(900));
    let served = server.get_json(&format!("/v1/jobs/{job_id}/summary"));

    let trace = json!({"time_s": time_s, "volume_ml": absolute_ml});
    std::fs::write(scratch.join("trace.json"), trace.to_string()).unwrap();
    std::fs::write(
        scratch.join("run.toml"),
        format!(
            "element_size_mm = 12\n[trace]\nreference = {{ absolute = {{ scanned_volume_ml = \
             {scanned_ml:?} }} }}\n[motion]\ninstants = {{ kind = \"phases\", count = 3 }}\n\
             [outputs]\nquicklooks = false\n"
        ),
    )
    .unwrap();
    let cli_out = scratch.join("cli-out");
    run_cli(&[
        &"run",
        &"--quiet",
        &"--ct",
        &ct,
        &"--trace",
        &scratch.join("trace.json"),
        &"--config",
        &scratch.join("run.toml"),
        &"--out",
        &cli_out,
    ]);
    let cli: Value =
        serde_json::from_str(&std::fs::read_to_string(cli_out.join("summary.json")).unwrap())
            .unwrap();
    let (served_frames, cli_frames) = (
        served["frames"].as_array().unwrap(),
        cli["frames"].as_array().unwrap(),
    );
    assert_eq!(served_frames.len(), 3);
    assert_eq!(served_frames.len(), cli_frames.len());
    for (s, c) in served_frames.iter().zip(cli_frames) {
        assert_eq!(s["time_s"], c["time_s"]);
        assert_eq!(s["target_volume_ml"], c["target_volume_ml"], "{s}\n{c}");
        // Changes from the scan, not absolute volumes: the reference was applied.
        assert!(
            s["target_volume_ml"].as_f64().unwrap().abs() <= 500.0 + 1e-9,
            "{s}"
        );
    }
    let peak = |f: &Value| f["target_volume_ml"].as_f64().unwrap();
    let k = (0..3)
        .max_by(|&a, &b| peak(&served_frames[a]).total_cmp(&peak(&served_frames[b])))
        .unwrap();
    let field_gz = server
        .get(&format!("/v1/jobs/{job_id}/frames/{k}/displacement"))
        .bytes()
        .unwrap();
    let (_, served_field) =
        lungmotion::formats::nifti::read_nifti_vector_field_bytes(&field_gz, "served").unwrap();
    let (_, cli_field) = lungmotion::formats::nifti::read_nifti_vector_field(
        &cli_out.join(format!("frames/{k}/displacement.nii.gz")),
    )
    .unwrap();
    let (difference_mm, peak_mm) = field_difference_mm(&served_field, &cli_field);
    println!(
        "measured: frame {k} with reference = absolute: service vs CLI differ by at most \
         {difference_mm:e} mm (peak {peak_mm:.2} mm)"
    );
    assert!(peak_mm > 1.0, "the CLI's field is nearly zero");
    assert!(difference_mm <= 1e-4, "{difference_mm} mm apart");
    assert_eq!(
        served["config"]["trace"]["reference"], cli["config"]["trace"]["reference"],
        "summary's recorded reference"
    );
}

//! The service benchmark's quick run: every part measured, sane and complete (no timing
//! thresholds: the machine is shared).
#![cfg(feature = "bench")]

use lungmotion::bench::service::queue::{QUICK_QUEUE_JOBS, QUICK_SHORT_JOBS, WORKER_COUNTS};
use lungmotion::bench::service::{
    run_service_bench, ServiceBenchOptions, LOAD_CONCURRENCY, QUICK_SLICE_PIXELS, UPLOAD_SLICES,
};
use lungmotion::bench::Outcome;

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow study (service benchmark under load): cargo test --features slow-tests"
)]
fn quick_service_bench_measures_upload_overhead_and_load() {
    let report = run_service_bench(&ServiceBenchOptions { quick: true }).unwrap();
    assert_eq!(report.server_workers, 1);

    assert_eq!(report.uploads.len(), 2, "stored and deflated rows");
    let mut zip_sizes = Vec::new();
    for u in &report.uploads {
        let Outcome::Measured(u) = u else {
            panic!("upload not measured: {u:?}");
        };
        assert_eq!(u.slices, UPLOAD_SLICES, "{u:?}");
        assert_eq!(
            u.server_slice_count, UPLOAD_SLICES,
            "the server read every slice"
        );
        assert_eq!(u.slice_pixels, [QUICK_SLICE_PIXELS; 2]);
        // int16 pixels plus headers.
        let pixel_bytes = (UPLOAD_SLICES * QUICK_SLICE_PIXELS * QUICK_SLICE_PIXELS * 2) as u64;
        assert!(u.dicom_bytes > pixel_bytes, "{u:?}");
        assert!(
            u.transfer_mib_per_s > 0.0 && u.transfer_mib_per_s.is_finite(),
            "{u:?}"
        );
        assert!(u.end_to_end_mib_per_s > 0.0, "{u:?}");
        assert!(
            u.transfer_lower_bound_mib_per_s > 0.0
                && u.transfer_lower_bound_mib_per_s <= u.transfer_mib_per_s,
            "{u:?}"
        );
        assert!(
            u.transfer_mib_per_s >= u.end_to_end_mib_per_s,
            "the body is sent before the 201: {u:?}"
        );
        assert!(u.body_sent.median_s <= u.to_201.median_s, "{u:?}");
        assert!(u.load_ct_in_process.median_s > 0.0, "{u:?}");
        assert!(
            u.server_segmentation_s > 0.0 && u.server_model_s > 0.0,
            "{u:?}"
        );
        assert!(u.elements > 0 && u.lung_volume_ml > 0.0, "{u:?}");
        zip_sizes.push((u.compression.clone(), u.zip_bytes, u.dicom_bytes));
    }
    assert_eq!(zip_sizes[0].0, "stored");
    assert!(
        zip_sizes[0].1 > zip_sizes[0].2,
        "a stored zip holds every byte: {zip_sizes:?}"
    );
    assert!(
        zip_sizes[1].1 < zip_sizes[0].1,
        "deflate compresses: {zip_sizes:?}"
    );

    let Outcome::Measured(o) = &report.overhead else {
        panic!("overhead not measured: {:?}", report.overhead);
    };
    assert_eq!(o.frames, 10, "default 10 phases");
    assert!(
        o.fields_identical_to_cli,
        "service fields differ from the CLI's"
    );
    assert!(o.cli.median_s > 0.0 && o.service.median_s > 0.0, "{o:?}");
    assert!(o.ratio.is_finite() && o.ratio > 0.0, "{o:?}");
    assert!(o.polls_last_round >= 1 && o.field_bytes > 0, "{o:?}");

    assert_eq!(report.load.len(), 2);
    for l in &report.load {
        let Outcome::Measured(l) = l else {
            panic!("load not measured: {l:?}");
        };
        assert_eq!(l.errors, 0, "{l:?}");
        assert_eq!(l.concurrency, LOAD_CONCURRENCY);
        assert!(l.requests > 0 && l.requests_per_s > 0.0, "{l:?}");
        assert!(
            l.latency_p50_ms > 0.0 && l.latency_p50_ms <= l.latency_p99_ms,
            "{l:?}"
        );
        assert!(l.body_bytes > 0 && l.mib_per_s > 0.0, "{l:?}");
    }
    // wrk is optional: when it ran it must have succeeded.
    for w in &report.wrk {
        match w {
            Outcome::Measured(w) => assert!(w.requests > 0 && w.errors == 0, "{w:?}"),
            Outcome::Skipped(_) => {}
            Outcome::Failed(e) => panic!("wrk failed: {e}"),
        }
    }
    // Serving at clinical scale: the POPI CT through the service, when the shared data is here.
    match &report.popi {
        Outcome::Measured(p) => {
            assert_eq!(p.slices, 141, "{p:?}");
            assert_eq!(p.frames, 10, "{p:?}");
            assert_eq!(p.until_done.runs, 1, "quick mode runs one job: {p:?}");
            // The lung box: a fraction of the CT's 37 M voxels, millions all the same.
            let voxels: usize = p.field_dims.iter().product();
            assert!(voxels > 1_000_000 && voxels < 512 * 512 * 141 / 2, "{p:?}");
            assert!(p.field_bytes > 0, "{p:?}");
            assert!(
                p.frame_files.median_s > 0.0 && p.frame_files.median_s < p.until_done.median_s,
                "the fields are written within the job: {p:?}"
            );
            assert!(p.fields_written_per_s > 0.0 && p.fields_written_per_s.is_finite());
            let Outcome::Measured(l) = &p.load else {
                panic!("POPI load not measured: {:?}", p.load);
            };
            assert_eq!(l.errors, 0, "{l:?}");
            assert!(l.requests > 0, "{l:?}");
            assert_eq!(
                l.body_bytes, p.field_bytes,
                "the whole field every time: {l:?}"
            );
        }
        Outcome::Skipped(why) => {
            assert!(lungmotion::datasets::popi_chest_ct().is_none(), "{why}");
        }
        Outcome::Failed(e) => panic!("POPI serving failed: {e}"),
    }
    assert!(report.peak_rss_bytes.is_some_and(|b| b > 0));
    assert!(report.socket_buffer_max_bytes.is_some_and(|b| b > 0));

    // The PostgreSQL queue (.ci/run installs PostgreSQL): every call timed, every job done.
    let Outcome::Measured(q) = &report.queue.overhead else {
        panic!("queue calls not measured: {:?}", report.queue.overhead);
    };
    assert_eq!(q.jobs, QUICK_QUEUE_JOBS);
    for t in [&q.submit, &q.claim, &q.heartbeat, &q.complete] {
        assert_eq!(t.runs, QUICK_QUEUE_JOBS, "{q:?}");
        assert!(t.median_s > 0.0 && t.median_s < 5.0, "{q:?}");
    }
    assert!(q.per_job_s > 0.0, "{q:?}");
    let threads: Vec<usize> = q
        .queue_only_jobs_per_min
        .iter()
        .map(|r| r.threads)
        .collect();
    assert_eq!(threads, WORKER_COUNTS, "{q:?}");
    for r in &q.queue_only_jobs_per_min {
        assert_eq!(r.jobs, QUICK_QUEUE_JOBS, "every job taken once: {r:?}");
    }
    let Outcome::Measured(rows) = &report.queue.workers else {
        panic!("workers not measured: {:?}", report.queue.workers);
    };
    let workers: Vec<usize> = rows.iter().map(|r| r.workers).collect();
    assert_eq!(workers, WORKER_COUNTS);
    for r in rows {
        assert_eq!(r.jobs, QUICK_SHORT_JOBS, "{r:?}");
        assert!(r.jobs_per_min > 0.0 && r.jobs_per_min.is_finite(), "{r:?}");
    }

    let md = report.to_markdown();
    println!("{md}");
    for section in [
        "## Upload of a 300-slice DICOM zip",
        "## Service against the CLI",
        "## Load over loopback",
        "## The PostgreSQL queue",
        "## Serving at clinical scale: the POPI CT",
        "share the",
    ] {
        assert!(md.contains(section), "missing {section}:\n{md}");
    }
    let json = serde_json::to_value(&report).unwrap();
    assert!(
        json["uploads"][0]["measured"]["zip_bytes"]
            .as_u64()
            .unwrap()
            > 0
    );
}

/// The full benchmark (512 × 512 slices, 3 repeats, 5 s of load), for
/// `cargo test --release --test bench_service -- --ignored --nocapture` until the CLI runs it;
/// writes `bench-service.{json,md}` into `LUNGMOTION_BENCH_OUT` when set.
#[test]
#[ignore = "minutes; run in release"]
fn full_service_bench() {
    let report = run_service_bench(&ServiceBenchOptions { quick: false }).unwrap();
    let md = report.to_markdown();
    println!("{md}");
    if let Some(dir) = std::env::var_os("LUNGMOTION_BENCH_OUT") {
        let dir = std::path::PathBuf::from(dir);
        std::fs::create_dir_all(&dir).unwrap();
        let json = serde_json::to_string_pretty(&report).unwrap();
        std::fs::write(dir.join("bench-service.json"), json).unwrap();
        std::fs::write(dir.join("bench-service.md"), md).unwrap();
    }
    for u in &report.uploads {
        assert!(u.measured().is_some(), "{u:?}");
    }
    assert!(
        report.overhead.measured().is_some(),
        "{:?}",
        report.overhead
    );
}

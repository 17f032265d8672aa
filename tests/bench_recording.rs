//! Smoke test of the recording benchmark's quick mode (the POPI CT at 16 mm, the stand-in
//! recording's first 8 s): the stand-in is built from the real MIMIC waveform, the run goes
//! through the CLI's trace reader and `run_breathing_with`, and the report is coherent,
//! whatever the speed of the machine.
#![cfg(feature = "bench")]

use lungmotion::bench::recording::{
    run_recording_bench, standin, RecordingBenchOptions, QUICK_DURATION_S,
};

#[test]
#[cfg_attr(
    any(not(feature = "slow-tests"), not(shared_data)),
    ignore = "slow study (recording benchmark): cargo test --features slow-tests with the shared CT data (../shared/data)"
)]
fn quick_recording_bench_runs_the_stand_in_through_the_pipeline() {
    let out = std::env::temp_dir().join(format!("lm-bench-recording-{}", std::process::id()));
    std::fs::create_dir_all(&out).unwrap();
    let options = RecordingBenchOptions::quick();
    let report = run_recording_bench(&options, &out).expect("benchmark ran");
    let json = serde_json::to_string(&report).expect("report serialises");
    let md = report.to_markdown();
    println!("{md}");

    let trace = report.recording.measured().expect("stand-in written");
    // 8 s at 100 Hz, both ends included; tidal breathing only (before the manoeuvre at 20 s),
    // scaled so that the median breath of the 55 s is 500 mL from the median trough.
    assert_eq!(
        trace.samples,
        (QUICK_DURATION_S * standin::RATE_HZ) as usize + 1
    );
    assert!((trace.duration_s - QUICK_DURATION_S).abs() < 1e-9, "{json}");
    let [lo, hi] = trace.volume_range_ml;
    assert!(lo > -200.0 && hi > 300.0 && hi < 1000.0, "{json}");
    assert!(
        trace.breaths >= 10,
        "a 55 s MIMIC window holds ~18 breaths: {json}"
    );
    let written = std::fs::read_to_string(&trace.csv).unwrap();
    assert!(written.starts_with("time_s,volume_ml\n"), "{written:.40}");

    let runs = report.runs.measured().expect("the quick run completed");
    assert_eq!(runs.each.len(), 1);
    let run = &runs.each[0];
    // A field every 0.5 s over 0 … 8 s.
    assert_eq!(run.frames, 17, "{json}");
    assert!(run.elements > 500, "{json}");
    assert!(
        run.work.keys >= 3 && run.work.solves >= run.work.keys,
        "{json}"
    );
    assert!(run.work.newton_iterations >= run.work.solves, "{json}");
    if let Some(e) = run.measured_error_mm {
        assert!(e <= run.tolerance_mm, "{json}");
    }
    assert!(run.max_volume_error_ml < 2.5, "{json}");
    assert!(run.bytes_written > 0 && run.wall_s > 0.0, "{json}");
    assert!(runs.same_work_every_run);
    // The target is set for the whole recording at 8 mm: a quick run does not judge it.
    assert_eq!(runs.target_met, None, "{json}");
    assert!(md.contains("not the target's runs"), "{md}");
    // The run's scratch output is removed; the stand-in and nothing else is left.
    assert!(!out.join("recording-run").exists());
    std::fs::remove_dir_all(&out).unwrap();
}

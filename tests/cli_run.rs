//! `lungmotion run` as scripts use it: a CSV trace, a points file and a TOML configuration in;
//! the promised files out, each read back; bad inputs refused with the reason.
#![cfg(feature = "cli")]

mod common;

use std::path::{Path, PathBuf};
use std::process::Output;

use common::{absent_temp_dir, bin, sample};

use lungmotion::formats::{metaimage, nifti, vtk};
use lungmotion::outputs::trajectories::read_trajectories;

/// An empty scratch directory for one test.
fn temp_dir(name: &str) -> PathBuf {
    let d = absent_temp_dir(&format!("run-{name}"));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn run(args: &[&str], files: &Path, out: &Path) -> Output {
    run_on(&sample("phantom-ct.nii.gz"), args, files, out)
}

/// `lungmotion run --quiet` on `ct`; `{dir}` in `args` stands for `files`.
fn run_on(ct: &Path, args: &[&str], files: &Path, out: &Path) -> Output {
    bin()
        .arg("run")
        .arg("--ct")
        .arg(ct)
        .arg("--out")
        .arg(out)
        .arg("--quiet")
        .args(
            args.iter()
                .map(|a| a.replace("{dir}", &files.display().to_string())),
        )
        .output()
        .unwrap()
}

/// A sine breath of 300 mL over 4 s sampled at 5 Hz, in the documented default CSV.
fn write_trace(path: &Path) {
    common::write_breaths(path, 300.0, 0.2, 4.0);
}

#[test]
fn run_writes_every_promised_file_in_its_stated_convention() {
    let dir = temp_dir("files");
    let out = dir.join("out");
    write_trace(&dir.join("trace.csv"));
    std::fs::write(
        dir.join("points.csv"),
        "name,x_mm,y_mm,z_mm\ntumour,-95,20,-80\n",
    )
    .unwrap();
    std::fs::write(
        dir.join("run.toml"),
        "[motion]\ninstants = { kind = \"every_kth\", k = 5 }\n[outputs]\ningest_files = false\n",
    )
    .unwrap();
    let o = run(
        &[
            "--trace",
            "{dir}/trace.csv",
            "--points",
            "{dir}/points.csv",
            "--config",
            "{dir}/run.toml",
            "--element-size",
            "12",
            "--mha",
            "--vtu",
        ],
        &dir,
        &out,
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("end-inhale"), "{stdout}");

    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let frames = summary["frames"].as_array().unwrap();
    // Samples 0, 5, 10, 15, 20 of 21.
    assert_eq!(frames.len(), 5);
    assert_eq!(summary["model"]["element_size_mm"], 12.0);
    assert!(!out.join("ingest").exists());
    let peak = &frames[2];
    assert!((peak["time_s"].as_f64().unwrap() - 2.0).abs() < 1e-9);
    assert!((peak["target_volume_ml"].as_f64().unwrap() - 300.0).abs() < 1e-6);

    let (geometry, field) =
        nifti::read_nifti_vector_field(&out.join("frames/2/displacement.nii.gz")).unwrap();
    let (mha_geometry, channels, values) =
        metaimage::read_mha(&out.join("frames/2/displacement.mha")).unwrap();
    assert_eq!(channels, 3);
    assert!(geometry.same_grid(&mha_geometry, 1e-6));
    assert_eq!(values.len(), 3 * field.len());
    for (a, b) in field.iter().zip(values.chunks_exact(3)) {
        assert_eq!(a.as_slice(), b);
    }
    // The deformed mesh carries the same motion: its largest displacement is the frame's.
    let mesh = vtk::read_vtu(&out.join("frames/2/mesh.vtu")).unwrap();
    let (_, data) = mesh
        .point_data
        .iter()
        .find(|(n, _)| n == "displacement_mm")
        .unwrap();
    let vtk::DataArray::VectorsF32(d) = data else {
        panic!("displacement_mm is not a vector array")
    };
    let max = d
        .iter()
        .map(|v| v.iter().map(|&c| (c as f64).powi(2)).sum::<f64>().sqrt())
        .fold(0.0, f64::max);
    let reported = peak["max_displacement_mm"].as_f64().unwrap();
    assert!(
        (max - reported).abs() < 1e-3 * reported.max(1.0),
        "{max} vs {reported}"
    );

    let rows = read_trajectories(&out.join("trajectories.csv")).unwrap();
    assert_eq!(rows.len(), 5);
    assert!(rows[2].displacement_mm[2] < -2.0, "{:?}", rows[2]);
    assert!(
        out.join("breathing.png").is_file() && out.join("end-inhale-displacement.png").is_file()
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_traces_points_and_configurations_are_named() {
    let dir = temp_dir("bad");
    let out = dir.join("out");
    std::fs::write(
        dir.join("unsorted.csv"),
        "time_s,volume_ml\n0,0\n1,100\n0.5,50\n2,0\n",
    )
    .unwrap();
    std::fs::write(dir.join("trace.csv"), "time_s,volume_ml\n0,0\n1,300\n2,0\n").unwrap();
    std::fs::write(dir.join("points.csv"), "name,x_mm,y_mm\ntumour,1,2\n").unwrap();
    std::fs::write(dir.join("typo.toml"), "element_sise_mm = 6\n").unwrap();
    let cases: [(&[&str], &str); 12] = [
        (&["--trace", "{dir}/unsorted.csv"], "unsorted.csv"),
        (
            &["--trace", "{dir}/trace.csv", "--trace-window", "5:9"],
            "holds 0 sample",
        ),
        (
            &["--trace", "{dir}/trace.csv", "--trace-window", "1-2"],
            "expected START:END",
        ),
        (&["--trace", "{dir}/missing.csv"], "missing.csv"),
        (
            &["--trace", "{dir}/trace.csv", "--points", "{dir}/points.csv"],
            "points.csv",
        ),
        (
            &["--trace", "{dir}/trace.csv", "--config", "{dir}/typo.toml"],
            "element_sise_mm",
        ),
        (
            &["--trace", "{dir}/trace.csv", "--spring-law", "quadratic"],
            "unknown spring law `quadratic`",
        ),
        (
            &["--trace", "{dir}/trace.csv", "--spring-law", "cubic:-1"],
            "λ₁/λ₂ = -1 is outside",
        ),
        (
            &["--trace", "{dir}/trace.csv", "--diaphragm", "piston"],
            "`piston` is not a diaphragm motion: cranio-caudal, sliding or free",
        ),
        (
            &["--trace", "{dir}/trace.csv", "--sliding", "curvy"],
            "`curvy` is not a sliding mode",
        ),
        (
            &["--trace", "{dir}/trace.csv", "--hourglass", "twist"],
            "`twist` is not an hourglass response: full-integration, incompatible-modes or springs",
        ),
        (
            &[
                "--trace",
                "{dir}/trace.csv",
                "--continuum-correction",
                "mooney",
            ],
            "`mooney` is not a continuum correction",
        ),
    ];
    for (args, named) in cases {
        let o = run(args, &dir, &out);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{args:?} succeeded");
        assert!(stderr.contains(named), "{args:?}: {stderr}");
        assert!(!out.exists(), "{args:?} created the output");
    }
    let o = run(&["--trace", "{dir}/unsorted.csv"], &dir, &out);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("increas"), "{stderr}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn help_explains_the_trace_and_the_field_convention() {
    let o = bin().args(["run", "--help"]).output().unwrap();
    let help = String::from_utf8_lossy(&o.stdout);
    for needle in [
        "time_s,volume_ml",
        "LPS",
        "end-inhale",
        "--element-size",
        "--points",
        "--trace-window",
    ] {
        assert!(
            help.contains(needle),
            "`run --help` lacks {needle}:\n{help}"
        );
    }
}

/// Runs `command` to its end, killing it (and failing) if it is still running after a minute:
/// a refused `serve` must not start listening.
fn exit_code_within_a_minute(command: &mut std::process::Command) -> (Option<i32>, String) {
    use std::process::Stdio;
    use std::time::{Duration, Instant};
    let mut child = command
        .stdout(Stdio::null())
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
            panic!("{command:?} kept running");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut stderr).unwrap();
    (status.code(), stderr)
}

#[test]
fn exit_status_is_2_for_refused_input_in_every_subcommand_and_1_for_failures_while_working() {
    let dir = temp_dir("exit");
    let out = dir.join("out");
    std::fs::write(dir.join("trace.csv"), "time_s,volume_ml\n0,0\n1,300\n2,0\n").unwrap();
    std::fs::write(dir.join("nan.csv"), "time_s,volume_ml\n0,0\n1,NaN\n2,0\n").unwrap();
    std::fs::write(dir.join("typo.toml"), "element_sise_mm = 6\n").unwrap();
    std::fs::write(dir.join("service.toml"), "wokers = 3\n").unwrap();
    let refused_runs: [&[&str]; 2] = [
        &["--trace", "{dir}/nan.csv"],
        &["--trace", "{dir}/trace.csv", "--config", "{dir}/typo.toml"],
    ];
    for args in refused_runs {
        let o = run(args, &dir, &out);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "run {args:?}: {stderr}");
    }
    // A usage error (clap's own) is the same 2.
    let o = bin().args(["run", "--no-such-option"]).output().unwrap();
    assert_eq!(o.status.code(), Some(2));

    let service_toml = dir.join("service.toml").display().to_string();
    let refused_serves: [&[&str]; 3] = [
        &["--workers", "0"],
        &["--listen", "localhost"],
        &["--config", &service_toml],
    ];
    for args in refused_serves {
        let mut serve = bin();
        serve.arg("serve").arg("--data-dir").arg(dir.join("data"));
        for name in lungmotion::service::config::ENV_VARS {
            serve.env_remove(name);
        }
        let (code, stderr) = exit_code_within_a_minute(serve.args(args));
        assert_eq!(code, Some(2), "serve {args:?}: {stderr}");
    }

    // An output directory that cannot be created is refused as `run` refuses one (2), by
    // `phantom` too; writing a file fails while working (1): the CT's name is taken by a
    // directory (which stops root too).
    let phantom = |out: &Path| bin().arg("phantom").arg("--out").arg(out).output().unwrap();
    let o = phantom(&dir.join("trace.csv").join("phantom"));
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("output directory"), "{stderr}");
    let blocked = dir.join("phantom");
    std::fs::create_dir_all(blocked.join("phantom-ct.nii.gz").join("taken")).unwrap();
    let o = phantom(&blocked);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("cannot replace") && stderr.contains("phantom-ct.nii.gz"),
        "{stderr}"
    );

    let o = bin().arg("--help").output().unwrap();
    let help = String::from_utf8_lossy(&o.stdout);
    assert!(help.contains("Exit status"), "{help}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Two sine breaths of 300 mL over 4 s each at 5 Hz: enough for the default 10 phases.
fn write_two_breaths(path: &Path) {
    common::write_breaths(path, 300.0, 0.2, 8.0);
}

#[test]
fn a_scripted_run_logs_its_stages_and_frames_with_the_elapsed_time() {
    // Before issue 18 the progress bar printed nothing when stderr was not a terminal.
    let dir = temp_dir("progress");
    let out = dir.join("out");
    write_two_breaths(&dir.join("trace.csv"));
    let o = bin()
        .arg("run")
        .arg("--ct")
        .arg(sample("phantom-ct.nii.gz"))
        .arg("--trace")
        .arg(dir.join("trace.csv"))
        .arg("--out")
        .arg(&out)
        .args(["--element-size", "12"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let lines: Vec<&str> = stderr.lines().collect();
    let position = |needle: &str| {
        lines
            .iter()
            .position(|l| l.contains(needle) && l.contains(" s] "))
            .unwrap_or_else(|| panic!("no progress line with {needle:?}:\n{stderr}"))
    };
    let stages = [
        "loading the CT",
        "segmenting the lungs",
        "solving the breathing cycle",
        "writing displacement fields",
        "writing the summary",
        "run finished",
    ];
    let at: Vec<usize> = stages.iter().map(|s| position(s)).collect();
    assert!(
        at.windows(2).all(|w| w[0] < w[1]),
        "out of order:\n{stderr}"
    );
    // The default 10 phases: the first and the last frame are always logged.
    position("frames: 1/10 written");
    position("frames: 10/10 written");
    assert!(
        stderr.contains("lungmotion: [    0.0 s] loading the CT"),
        "{stderr}"
    );

    // --quiet silences them all.
    let o = run(
        &["--trace", "{dir}/trace.csv", "--element-size", "12"],
        &dir,
        &out,
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(!stderr.contains(" s] "), "{stderr}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The bundled phantom moved 10 mm up: another CT, as far as any identity goes.
fn write_another_ct(path: &Path) {
    let mut ct = nifti::read_nifti(&sample("phantom-ct.nii.gz")).unwrap();
    ct.geometry.origin_lps_mm[2] += 10.0;
    nifti::write_nifti_ct(path, &ct).unwrap();
}

#[test]
fn an_earlier_run_of_another_ct_is_replaced_only_with_overwrite() {
    let dir = temp_dir("overwrite");
    let out = dir.join("out");
    write_two_breaths(&dir.join("trace.csv"));
    write_another_ct(&dir.join("other-ct.nii.gz"));
    let fingerprint = |out: &Path| {
        let summary: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap())
                .unwrap();
        summary["ct_fingerprint"].as_str().unwrap().to_string()
    };
    let args = ["--trace", "{dir}/trace.csv", "--element-size", "12"];
    let o = run(&args, &dir, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let first = fingerprint(&out);
    assert!(first.starts_with("fnv1a64:"), "{first}");

    // The same CT again replaces it.
    let o = run(&args, &dir, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(fingerprint(&out), first);

    // Another CT is refused, naming the directory and what it holds, and changes nothing.
    let other = dir.join("other-ct.nii.gz");
    let o = run_on(&other, &args, &dir, &out);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    for needle in [
        out.display().to_string(),
        "a run of another CT".into(),
        first.clone(),
        "--overwrite".into(),
    ] {
        assert!(stderr.contains(&needle), "lacks {needle:?}: {stderr}");
    }
    assert_eq!(fingerprint(&out), first);
    let siblings: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".out"))
        .collect();
    assert!(siblings.is_empty(), "{siblings:?}");

    let mut overwrite = args.to_vec();
    overwrite.push("--overwrite");
    let o = run_on(&other, &overwrite, &dir, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_ne!(fingerprint(&out), first);

    // What is not a lungmotion run is never replaced, --overwrite or not.
    let foreign = dir.join("foreign");
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("summary.json"), "{\"software\": \"other\"}").unwrap();
    let o = run(
        &["--trace", "{dir}/trace.csv", "--overwrite"],
        &dir,
        &foreign,
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("lungmotion did not write"), "{stderr}");
    assert_eq!(
        std::fs::read_to_string(foreign.join("summary.json")).unwrap(),
        "{\"software\": \"other\"}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_airflow_trace_is_integrated_and_the_run_says_what_was_done() {
    let dir = temp_dir("airflow");
    let out = dir.join("out");
    // Four 300 mL breaths over 4 s each as airflow in L/s, the sensor reading 20 mL/s high
    // (three end-expirations between them: the fewest the drift is estimated from).
    let w = std::f64::consts::PI / 4.0;
    let mut csv = String::from("time_s,flow_l_per_s\n");
    for i in 0..=400 {
        let t = i as f64 * 0.04;
        csv.push_str(&format!(
            "{t:.2},{:.6}\n",
            0.3 * w * (2.0 * w * t).sin() + 0.02
        ));
    }
    std::fs::write(dir.join("flow.csv"), csv).unwrap();
    let o = run(
        &["--trace", "{dir}/flow.csv", "--element-size", "12"],
        &dir,
        &out,
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(
        stderr.contains("lungmotion: trace: airflow column 'flow_l_per_s' integrated"),
        "{stderr}"
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let source = summary["trace"]["source"].as_str().unwrap();
    assert!(
        source.contains("flow.csv (airflow column 'flow_l_per_s'")
            && source.contains("mL/s removed"),
        "{source}"
    );
    let [lo, hi] = [0, 1].map(|i| summary["trace"]["volume_range_ml"][i].as_f64().unwrap());
    assert!(lo.abs() < 3.0 && (hi - 300.0).abs() < 3.0, "{lo} … {hi} mL");
    std::fs::remove_dir_all(&dir).unwrap();
}

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
    bin()
        .arg("run")
        .arg("--ct")
        .arg(sample("phantom-ct.nii.gz"))
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
    let mut csv = String::from("time_s,volume_ml\n");
    for i in 0..=20 {
        let t = i as f64 * 0.2;
        let v = 300.0 * (std::f64::consts::PI * t / 4.0).sin().powi(2);
        csv.push_str(&format!("{t:.1},{v:.3}\n"));
    }
    std::fs::write(path, csv).unwrap();
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
    let cases: [(&[&str], &str); 4] = [
        (&["--trace", "{dir}/unsorted.csv"], "unsorted.csv"),
        (&["--trace", "{dir}/missing.csv"], "missing.csv"),
        (
            &["--trace", "{dir}/trace.csv", "--points", "{dir}/points.csv"],
            "points.csv",
        ),
        (
            &["--trace", "{dir}/trace.csv", "--config", "{dir}/typo.toml"],
            "element_sise_mm",
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

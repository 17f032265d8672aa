//! Every run has a time and an equilibrium budget: a run that reaches one stops with an error
//! naming it (CLI exit status 3, an HTTP job `failed` with that reason) and leaves no output;
//! budgets that make no sense are refused by name in the configuration, on the command line
//! and over HTTP; `summary.json` records the budgets and what the run used.
#![cfg(feature = "cli")]

mod common;
mod service_support;

use std::path::{Path, PathBuf};
use std::process::Output;
use std::time::Duration;

use serde_json::{json, Value};

use lungmotion::run::{run_breathing, RunConfig, RunInputs, SilentObserver};
use lungmotion::{BudgetKind, Error};

/// A scratch directory for one test (not created).
fn scratch(name: &str) -> PathBuf {
    common::absent_temp_dir(&format!("budget-{name}"))
}

/// `lungmotion run --quiet` on `ct` with the trace at `trace` into `out`, plus `args`.
fn run_cli(ct: &Path, trace: &Path, out: &Path, args: &[&str]) -> Output {
    common::bin()
        .arg("run")
        .arg("--ct")
        .arg(ct)
        .arg("--trace")
        .arg(trace)
        .arg("--out")
        .arg(out)
        .arg("--quiet")
        .args(args)
        .output()
        .unwrap()
}

/// Names in `dir`, sorted (empty when it does not exist).
fn names_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map(|r| {
            r.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

#[test]
fn the_equilibrium_budget_stops_the_solves_with_the_named_error_and_publishes_nothing() {
    let dir = scratch("lib");
    std::fs::create_dir_all(&dir).unwrap();
    let trace = lungmotion::breathing::BreathingTrace::new(
        (0..=80).map(|i| f64::from(i) / 10.0).collect(),
        (0..=80)
            .map(|i| 250.0 * (1.0 - (std::f64::consts::PI * f64::from(i) / 20.0).cos()))
            .collect(),
    )
    .unwrap();
    let inputs = RunInputs {
        ct_path: common::sample("phantom-ct.nii.gz"),
        trace,
        trace_source: "generated".into(),
        points: Vec::new(),
        target: None,
    };
    let mut config = RunConfig {
        element_size_mm: 12.0,
        ..RunConfig::default()
    };
    config.outputs.quicklooks = false;

    // Within the budgets: the summary records them and what was used.
    let out = dir.join("done");
    let summary = run_breathing(&inputs, &config, &out, &mut SilentObserver).unwrap();
    let written: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let budget = &written["budget"];
    assert_eq!(budget["time_s"], 1800.0, "{budget}");
    assert_eq!(budget["max_equilibria"], 10_000, "{budget}");
    let used = budget["equilibria"].as_u64().unwrap();
    assert!(
        used >= 2,
        "a cycle needs at least two key volumes: {budget}"
    );
    assert_eq!(used as usize, summary.budget.equilibria);
    assert!(budget["elapsed_s"].as_f64().unwrap() > 0.0, "{budget}");
    assert_eq!(written["config"]["budget"]["max_equilibria"], 10_000);

    // One equilibrium fewer than the cycle needs stops it in the solves.
    config.budget.max_equilibria = (used - 1) as i64;
    let stopped = dir.join("stopped");
    let e = run_breathing(&inputs, &config, &stopped, &mut SilentObserver).unwrap_err();
    let Error::BudgetExceeded(stop) = &e else {
        panic!("not a budget stop: {e}");
    };
    assert_eq!(stop.budget, BudgetKind::Equilibria);
    assert_eq!(stop.limit, (used - 1) as f64);
    assert_eq!(stop.equilibria, (used - 1) as usize);
    assert_eq!(stop.stage, "solving the breathing cycle");
    assert!(stop.volume_reached_ml.is_some(), "{stop:?}");
    assert_eq!(stop.target_ml, Some(500.0));
    let text = e.to_string();
    for needle in [
        "equilibrium budget",
        "max_equilibria",
        "larger element size",
        "no output",
    ] {
        assert!(text.contains(needle), "{needle}: {text}");
    }
    assert!(!stopped.exists(), "{:?}", names_in(&stopped));
    // Nothing left beside it either (the staging directory went with the run).
    assert_eq!(names_in(&dir), vec!["done".to_string()]);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_run_stopped_by_its_budget_exits_3_naming_it_and_leaves_the_earlier_run_as_it_was() {
    let dir = scratch("cli");
    std::fs::create_dir_all(&dir).unwrap();
    let trace = dir.join("trace.csv");
    common::write_breaths(&trace, 300.0, 0.2, 8.0);
    let ct = common::sample("phantom-ct.nii.gz");
    let out = dir.join("out");
    let o = run_cli(&ct, &trace, &out, &["--element-size", "12"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary_before = std::fs::read(out.join("summary.json")).unwrap();
    let files_before = names_in(&out);

    let o = run_cli(
        &ct,
        &trace,
        &out,
        &["--element-size", "12", "--max-equilibria", "1"],
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{stderr}");
    for needle in [
        "equilibrium budget",
        "1 equilibrium solves used of 1 allowed",
        "--max-equilibria",
    ] {
        assert!(stderr.contains(needle), "{needle}: {stderr}");
    }
    assert_eq!(
        std::fs::read(out.join("summary.json")).unwrap(),
        summary_before
    );
    assert_eq!(names_in(&out), files_before);
    assert_eq!(
        names_in(&dir),
        vec!["out".to_string(), "trace.csv".to_string()]
    );

    // A fresh output directory is not even created.
    let fresh = dir.join("fresh");
    let o = run_cli(
        &ct,
        &trace,
        &fresh,
        &["--element-size", "12", "--max-equilibria", "1"],
    );
    assert_eq!(o.status.code(), Some(3));
    assert!(!fresh.exists());

    let help = common::bin().arg("--help").output().unwrap();
    let help = String::from_utf8_lossy(&help.stdout);
    assert!(help.contains("3  stopped by its budget"), "{help}");
    let help = common::bin().args(["run", "--help"]).output().unwrap();
    let help = String::from_utf8_lossy(&help.stdout);
    assert!(help.contains("--time-budget <SECONDS>"), "{help}");
    assert!(help.contains("--max-equilibria <N>"), "{help}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn the_time_budget_stops_a_long_run_on_the_cip_ct_with_the_named_error() {
    let Some(cip) = lungmotion::datasets::cip_chest_ct64() else {
        eprintln!("skipped: the CIP chest CT is not in the shared data");
        return;
    };
    let dir = scratch("time");
    std::fs::create_dir_all(&dir).unwrap();
    let trace = dir.join("trace.csv");
    common::write_breaths(&trace, 500.0, 0.1, 8.0);
    let out = dir.join("out");
    // 3 mm on CIP takes minutes: a 1 s budget is reached whichever stage it is in.
    let o = run_cli(
        &cip.join("ct-64.nrrd"),
        &trace,
        &out,
        &["--element-size", "3", "--time-budget", "1"],
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{stderr}");
    for needle in [
        "time budget",
        "of 1 s allowed",
        "[budget] time_s",
        "--time-budget",
    ] {
        assert!(stderr.contains(needle), "{needle}: {stderr}");
    }
    assert!(!out.exists());
    assert_eq!(names_in(&dir), vec!["trace.csv".to_string()]);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn budgets_that_make_no_sense_are_refused_by_name_in_the_config_and_on_the_command_line() {
    for (toml, key, why) in [
        ("[budget]\ntime_s = -5.0", "budget.time_s", "-5 s"),
        ("[budget]\ntime_s = 0", "budget.time_s", "before it starts"),
        ("[budget]\ntime_s = nan", "budget.time_s", "NaN"),
        ("[budget]\ntime_s = 1e9", "budget.time_s", "7 days"),
        ("[budget]\ntime_s = 0.5", "budget.time_s", "1 s minimum"),
        (
            "[budget]\nmax_equilibria = 0",
            "budget.max_equilibria",
            "at least 1",
        ),
        (
            "[budget]\nmax_equilibria = -2",
            "budget.max_equilibria",
            "-2",
        ),
        (
            "[budget]\nmax_equilibria = 5000000",
            "budget.max_equilibria",
            "maximum",
        ),
    ] {
        let e = RunConfig::from_toml(toml).unwrap_err().to_string();
        assert!(e.contains(key) && e.contains(why), "{toml}: {e}");
    }
    let e = RunConfig::from_toml("[budget]\ntime = 60")
        .unwrap_err()
        .to_string();
    assert!(e.contains("time"), "{e}");
    let c = RunConfig::from_toml("[budget]\ntime_s = 60\nmax_equilibria = 40").unwrap();
    assert_eq!((c.budget.time_s, c.budget.max_equilibria), (60.0, 40));

    let dir = scratch("bad");
    std::fs::create_dir_all(&dir).unwrap();
    let trace = dir.join("trace.csv");
    common::write_breaths(&trace, 300.0, 0.2, 8.0);
    std::fs::write(dir.join("bad.toml"), "[budget]\ntime_s = -1\n").unwrap();
    let ct = common::sample("phantom-ct.nii.gz");
    let out = dir.join("out");
    let config = dir.join("bad.toml").display().to_string();
    let cases: [(&[&str], &str); 8] = [
        (&["--time-budget", "-1"], "--time-budget"),
        (&["--time-budget", "0"], "before it starts"),
        (&["--time-budget", "NaN"], "NaN"),
        (&["--time-budget", "1e9"], "7 days"),
        (&["--time-budget", "soon"], "not a number of seconds"),
        (&["--max-equilibria", "0"], "--max-equilibria"),
        (&["--max-equilibria", "2.5"], "whole number"),
        (&["--config", &config], "budget.time_s"),
    ];
    for (args, named) in cases {
        let o = run_cli(&ct, &trace, &out, args);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains(named), "{args:?}: {stderr}");
        assert!(!out.exists(), "{args:?} created the output");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_http_job_stopped_by_its_budget_fails_with_the_reason_and_bad_budgets_are_422() {
    use service_support::{assert_problem, entries, sample, tiny_request, Scratch, ServerProcess};
    let scratch = Scratch::new("budget");
    let data = scratch.join("data");
    let server = ServerProcess::start(&data, &["--workers", "1"]);
    let scan_id = server.upload_scan(&sample("phantom-ct.nii.gz"));

    let mut request = tiny_request(10);
    request["budget"] = json!({"max_equilibria": 1});
    let job = server.submit(&scan_id, &request);
    let status = server.wait_for_state(&job, &["failed", "done"], Duration::from_secs(600));
    assert_eq!(status["state"], "failed", "{status}");
    let error = status["error"].as_str().unwrap_or_default();
    for needle in [
        "equilibrium budget",
        "max_equilibria",
        "1 equilibrium solves used of 1 allowed",
    ] {
        assert!(error.contains(needle), "{needle}: {status}");
    }
    let job_dir = data.join("jobs").join(&job);
    let leftovers: Vec<String> = entries(&job_dir)
        .into_iter()
        .filter(|n| n.contains("partial") || n == "out")
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");

    for (budget, words) in [
        (json!({"time_s": -3}), vec!["budget.time_s", "-3 s"]),
        (
            json!({"time_s": 0}),
            vec!["budget.time_s", "before it starts"],
        ),
        (json!({"time_s": 1e12}), vec!["budget.time_s", "7 days"]),
        (json!({"max_equilibria": 0}), vec!["budget.max_equilibria"]),
        (json!({"time": 60}), vec!["time"]),
    ] {
        let mut request = tiny_request(2);
        request["budget"] = budget.clone();
        assert_problem(server.post_simulation(&scan_id, &request), 422, &words);
    }
    let schema = server.get_json("/openapi.json");
    let text = schema.to_string();
    assert!(
        text.contains("max_equilibria") && text.contains("time_s"),
        "no budget in the schema"
    );
}

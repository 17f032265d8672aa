//! An interrupted `lungmotion run` leaves nothing behind: SIGTERM during the solves removes the
//! staging directory and exits with the documented status; a staging directory left by a
//! killed run is removed by the next run into the same place, one in use is not.
#![cfg(all(feature = "cli", unix))]

mod common;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{absent_temp_dir, bin, sample};

/// The exit status the README documents for an interrupted run.
const INTERRUPTED: i32 = 130;

fn temp_dir(name: &str) -> PathBuf {
    let d = absent_temp_dir(&format!("interrupt-{name}"));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Twenty 500 mL breaths, 4 s each, at 10 Hz.
fn write_long_trace(path: &Path) {
    common::write_breaths(path, 500.0, 0.1, 80.0);
}

/// Entries of `dir` whose names start with `prefix`.
fn entries_starting(dir: &Path, prefix: &str) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(prefix))
        .collect()
}

fn send(signal: &str, child: &Child) {
    let status = Command::new("kill")
        .args([signal, &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
}

/// Waits for the child's exit for at most `limit`, killing it (and failing) after that.
fn wait_within(child: &mut Child, limit: Duration) -> std::process::ExitStatus {
    let deadline = Instant::now() + limit;
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("still running {limit:?} after the signal");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn sigterm_during_the_solves_removes_the_staging_directory_and_exits_130() {
    let dir = temp_dir("term");
    let out = dir.join("out");
    write_long_trace(&dir.join("trace.csv"));
    // Every sample solved: minutes of work at 5 mm, so the signal lands in the solves.
    std::fs::write(
        dir.join("run.toml"),
        "[motion]\ninstants = { kind = \"every_sample\" }\nsolve_every_frame = true\n",
    )
    .unwrap();
    let mut child = bin()
        .arg("run")
        .arg("--ct")
        .arg(sample("phantom-ct.nii.gz"))
        .arg("--trace")
        .arg(dir.join("trace.csv"))
        .arg("--config")
        .arg(dir.join("run.toml"))
        .arg("--out")
        .arg(&out)
        .args(["--element-size", "5"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut seen = String::new();
    // The progress lines (stderr is a pipe) say when the solves have started.
    while !seen.contains("solving the breathing cycle") {
        let mut line = String::new();
        if stderr.read_line(&mut line).unwrap() == 0 {
            panic!("the run ended before solving:\n{seen}");
        }
        seen.push_str(&line);
    }
    let staging = entries_starting(&dir, ".out.partial-");
    assert_eq!(staging.len(), 1, "{staging:?}");
    std::thread::sleep(Duration::from_millis(500));
    send("-TERM", &child);
    let status = wait_within(&mut child, Duration::from_secs(30));
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut stderr, &mut rest).unwrap();
    assert_eq!(status.code(), Some(INTERRUPTED), "{seen}{rest}");
    assert!(rest.contains("interrupted by SIGTERM"), "{rest}");
    assert!(entries_starting(&dir, ".out").is_empty());
    assert!(!out.exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_staging_directory_of_a_killed_run_is_removed_by_the_next_run_and_a_live_one_is_kept() {
    let dir = temp_dir("stale");
    let out = dir.join("out");
    write_long_trace(&dir.join("trace.csv"));
    // A run killed with SIGKILL: its process is gone, its lock free.
    let mut gone = Command::new("true").spawn().unwrap();
    gone.wait().unwrap();
    let stale = dir.join(format!(".out.partial-{}", gone.id()));
    std::fs::create_dir_all(stale.join("frames/0")).unwrap();
    std::fs::write(stale.join("frames/0/displacement.nii.gz"), vec![0u8; 4096]).unwrap();
    std::fs::write(stale.join(".lungmotion-run.lock"), "").unwrap();
    let moved_aside = dir.join(format!(".out.old-{}", gone.id()));
    std::fs::create_dir_all(&moved_aside).unwrap();
    // A run still writing: this process holds its lock.
    let live = dir.join(format!(".out.partial-{}", std::process::id()));
    std::fs::create_dir_all(&live).unwrap();
    let lock = std::fs::File::create(live.join(".lungmotion-run.lock")).unwrap();
    lock.lock().unwrap();
    // Another output's leftovers are not this run's business.
    let neighbour = dir.join(format!(".other.partial-{}", gone.id()));
    std::fs::create_dir_all(&neighbour).unwrap();

    let o = bin()
        .arg("run")
        .arg("--ct")
        .arg(sample("phantom-ct.nii.gz"))
        .arg("--trace")
        .arg(dir.join("trace.csv"))
        .arg("--out")
        .arg(&out)
        .args(["--element-size", "12", "--quiet"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!stale.exists() && !moved_aside.exists());
    assert!(live.exists() && neighbour.exists());
    assert!(out.join("summary.json").is_file());
    drop(lock);
    std::fs::remove_dir_all(&dir).unwrap();
}

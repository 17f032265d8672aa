//! The hostile-input harness: each case runs in a child process of the test binary under an
//! address-space limit, so a panic, an abort on a failed allocation or a stack overflow fails
//! that one case (by name) instead of the whole test binary, and an allocation driven by a
//! declared length fails even when the machine could afford it.

#![allow(dead_code)]

pub mod dicom;
pub mod traces;
pub mod volumes;
pub mod zips;

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Address space of a child, KiB (`ulimit -v`): the readers died under 2 GB.
pub const ADDRESS_SPACE_LIMIT_KIB: u64 = 2 << 20;
/// Largest peak resident memory a case may reach, KiB: the inputs are kilobytes (a few are
/// tens of megabytes, made in the child), the test volumes 16 × 16 × 4.
pub const PEAK_RSS_LIMIT_KIB: u64 = 512 << 10;
/// Longest a case may take on a loaded 2-core machine (the issue measured 31 s and 66 s).
pub const CASE_TIME_LIMIT: Duration = Duration::from_secs(20);
/// Longest error message accepted, bytes: a reason names the fault, it does not echo the input.
const MAX_MESSAGE_BYTES: usize = 4000;
/// The child is killed after this (a hang, not a slow refusal).
const CHILD_KILL_AFTER: Duration = Duration::from_secs(90);

/// The environment variables that make the test binary a child running one case.
const GROUP_VAR: &str = "LM_HOSTILE_GROUP";
const CASE_VAR: &str = "LM_HOSTILE_CASE";
/// The line of the child's stdout that carries its result.
const RESULT_PREFIX: &str = "HOSTILE-RESULT ";

/// What a case must end in.
#[derive(Debug, Clone, Copy)]
pub enum Expect {
    /// An error whose message contains every word (case-insensitive).
    Refused(&'static [&'static str]),
    /// Success; the summary contains every word (case-insensitive), e.g. a warning.
    Accepted(&'static [&'static str]),
    /// For mutated inputs whose fate cannot be told in advance: success, or an error that
    /// names the input by the given word and stays short (a reason, not a dump).
    Either(&'static str),
}

/// A reader's answer: a one-line summary of what was read, or the error message.
pub type Outcome = Result<String, String>;

/// One hostile input: how to make and read it (in a scratch directory) and what must happen.
pub struct Case {
    /// Unique within its group; says what is wrong with the input.
    pub name: String,
    /// What must happen.
    pub expect: Expect,
    /// Generates the input under the scratch directory and reads it.
    pub run: Box<dyn Fn(&Path) -> Outcome>,
    /// The child's address-space limit, KiB.
    pub address_space_kib: u64,
}

impl Case {
    /// A case that must pass today.
    pub fn new(
        name: impl Into<String>,
        expect: Expect,
        run: impl Fn(&Path) -> Outcome + 'static,
    ) -> Case {
        Case {
            name: name.into(),
            expect,
            run: Box::new(run),
            address_space_kib: ADDRESS_SPACE_LIMIT_KIB,
        }
    }

    /// Gives the child a larger address space, so an allocation a reader should never ask for
    /// succeeds and shows in the peak RSS instead of failing politely under the limit.
    pub fn with_address_space_kib(mut self, kib: u64) -> Case {
        self.address_space_kib = kib;
        self
    }
}

/// The group's cases by name, as a `fn` so the parent and the child build the same list.
pub type Group = fn() -> Vec<Case>;

/// What the child reports.
#[derive(Debug)]
struct ChildResult {
    outcome: Outcome,
    elapsed: Duration,
    peak_rss_kib: u64,
}

/// Entry point of the child: runs the case named by the environment, if any, and prints its
/// result. Called from the one `#[test]` the parent re-runs.
pub fn child_main(groups: &[(&str, Group)]) {
    let (Ok(group), Ok(index)) = (std::env::var(GROUP_VAR), std::env::var(CASE_VAR)) else {
        return; // An ordinary test run: nothing to do.
    };
    let cases = groups
        .iter()
        .find(|(name, _)| *name == group)
        .map(|(_, make)| make())
        .unwrap_or_else(|| panic!("no case group {group}"));
    let case = &cases[index.parse::<usize>().expect("case index")];
    let scratch =
        std::env::temp_dir().join(format!("lm-hostile-{group}-{index}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&scratch);
    std::fs::create_dir_all(&scratch).expect("create the scratch directory");
    reset_peak_rss();
    let start = Instant::now();
    let outcome = (case.run)(&scratch);
    let elapsed = start.elapsed();
    let peak = peak_rss_kib("self");
    let _ = std::fs::remove_dir_all(&scratch);
    let json = serde_json::json!({
        "ok": outcome.is_ok(),
        "text": match &outcome { Ok(s) | Err(s) => s.chars().take(20_000).collect::<String>() },
        "text_len": match &outcome { Ok(s) | Err(s) => s.len() },
        "us": elapsed.as_micros() as u64,
        "peak_rss_kib": peak,
    });
    println!("{RESULT_PREFIX}{json}");
}

/// Runs every case of `group` in its own child process and fails, listing every case that
/// did not end as expected.
pub fn run_group(group: &str, make: Group) {
    let cases = make();
    let mut failures = Vec::new();
    let mut ran = 0;
    let (mut slowest, mut heaviest) = ((Duration::ZERO, String::new()), (0u64, String::new()));
    for (index, case) in cases.iter().enumerate() {
        ran += 1;
        match run_child(group, index, case.address_space_kib) {
            Ok(result) => {
                if std::env::var_os("LM_HOSTILE_VERBOSE").is_some() {
                    let text = match &result.outcome {
                        Ok(s) | Err(s) => s.chars().take(200).collect::<String>(),
                    };
                    eprintln!(
                        "{group} #{index} {}: {:?}, {} MiB: {text}",
                        case.name,
                        result.elapsed,
                        result.peak_rss_kib / 1024
                    );
                }
                if result.elapsed > slowest.0 {
                    slowest = (result.elapsed, case.name.clone());
                }
                if result.peak_rss_kib > heaviest.0 {
                    heaviest = (result.peak_rss_kib, case.name.clone());
                }
                if let Err(why) = judge(case, &result) {
                    failures.push(format!("{}: {why}", case.name));
                }
            }
            Err(why) => failures.push(format!("{}: {why}", case.name)),
        }
    }
    eprintln!(
        "{group}: {ran} cases; slowest {:?} ({}), peak RSS {} MiB ({})",
        slowest.0,
        slowest.1,
        heaviest.0 / 1024,
        heaviest.1
    );
    assert!(ran > 0, "no case in group {group}");
    assert!(
        failures.is_empty(),
        "{} of {ran} {group} cases failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// Whether a case's result is what it expects, and if not why.
fn judge(case: &Case, result: &ChildResult) -> Result<(), String> {
    if result.elapsed > CASE_TIME_LIMIT {
        return Err(format!(
            "took {:?} (limit {CASE_TIME_LIMIT:?})",
            result.elapsed
        ));
    }
    if result.peak_rss_kib > PEAK_RSS_LIMIT_KIB {
        return Err(format!("peak RSS {} MiB", result.peak_rss_kib / 1024));
    }
    let has_all = |text: &str, words: &[&str]| {
        let lower = text.to_lowercase();
        words.iter().all(|w| lower.contains(&w.to_lowercase()))
    };
    if let Err(m) = &result.outcome {
        // A reason, not a dump of the input.
        if m.len() > MAX_MESSAGE_BYTES {
            return Err(format!(
                "a {}-byte message: {}…",
                m.len(),
                &m[..m.floor_char_boundary(300)]
            ));
        }
    }
    match (case.expect, &result.outcome) {
        (Expect::Refused(words), Err(m)) if has_all(m, words) => Ok(()),
        (Expect::Accepted(words), Ok(s)) if has_all(s, words) => Ok(()),
        (Expect::Either(_), Ok(_)) => Ok(()),
        (Expect::Either(name), Err(m)) if m.contains(name) => Ok(()),
        (expect, outcome) => Err(format!("expected {expect:?}, got {outcome:?}")),
    }
}

/// Runs case `index` of `group` in a child process under the address-space limit.
fn run_child(group: &str, index: usize, address_space_kib: u64) -> Result<ChildResult, String> {
    let exe = std::env::current_exe().expect("the test binary");
    let mut child = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "ulimit -v {address_space_kib} && exec \"$0\" \"$@\""
        ))
        .arg(exe)
        .args([
            "hostile_case_child",
            "--exact",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(GROUP_VAR, group)
        .env(CASE_VAR, index.to_string())
        // Few malloc arenas, so the address-space limit measures allocations, not reservations.
        .env("MALLOC_ARENA_MAX", "2")
        .env("RUST_BACKTRACE", "0")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("cannot start the child: {e}"))?;
    let mut stdout = child.stdout.take().unwrap();
    let mut stderr = child.stderr.take().unwrap();
    let out_reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stdout.read_to_string(&mut s);
        s
    });
    let err_reader = std::thread::spawn(move || {
        let mut s = Vec::new();
        let _ = stderr.read_to_end(&mut s);
        String::from_utf8_lossy(&s).into_owned()
    });
    let deadline = Instant::now() + CHILD_KILL_AFTER;
    let status = loop {
        if let Some(status) = child.try_wait().map_err(|e| e.to_string())? {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            return Err(format!("still running after {CHILD_KILL_AFTER:?}: killed"));
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let stdout = out_reader.join().unwrap_or_default();
    let stderr = err_reader.join().unwrap_or_default();
    // libtest prints `test hostile_case_child ... ` before the line on the same row.
    let Some(line) = stdout
        .lines()
        .find_map(|l| l.split_once(RESULT_PREFIX).map(|(_, r)| r))
    else {
        return Err(format!(
            "the reader did not return ({status}); its stderr ends:\n{}",
            last_lines(&stderr, 6)
        ));
    };
    let v: serde_json::Value = serde_json::from_str(line).map_err(|e| e.to_string())?;
    let text = v["text"].as_str().unwrap_or_default().to_string();
    let text = if v["text_len"].as_u64().unwrap_or(0) as usize > text.len() {
        format!("{text}… ({} bytes in all)", v["text_len"])
    } else {
        text
    };
    Ok(ChildResult {
        outcome: if v["ok"].as_bool() == Some(true) {
            Ok(text)
        } else {
            Err(text)
        },
        elapsed: Duration::from_micros(v["us"].as_u64().unwrap_or(0)),
        peak_rss_kib: v["peak_rss_kib"].as_u64().unwrap_or(0),
    })
}

fn last_lines(text: &str, n: usize) -> String {
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

/// Resets the kernel's peak-RSS mark of this process (`VmHWM`), so the case's own peak is read.
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// The peak resident set of `process` (a pid, or `self`: since the last reset), KiB (0 where
/// /proc is missing).
pub fn peak_rss_kib(process: &str) -> u64 {
    std::fs::read_to_string(format!("/proc/{process}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        })
        .unwrap_or(0)
}

/// A small deterministic generator (SplitMix64), so every run makes the same inputs.
pub struct Rng(u64);

impl Rng {
    /// Seeded.
    pub fn new(seed: u64) -> Rng {
        Rng(seed)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `0..n`.
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
}

/// Flips `count` random bytes of `bytes[range]` to random values.
pub fn flip_bytes(bytes: &mut [u8], range: std::ops::Range<usize>, count: usize, rng: &mut Rng) {
    let range = range.start.min(bytes.len())..range.end.min(bytes.len());
    if range.is_empty() {
        return;
    }
    for _ in 0..count {
        let at = range.start + rng.below(range.len());
        bytes[at] ^= (rng.next_u64() as u8) | 1;
    }
}

/// Writes `bytes` as `dir/name` and gives the path.
pub fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let path = dir.join(name);
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).unwrap();
    }
    std::fs::write(&path, bytes).unwrap();
    path
}

/// Loads a CT as `lungmotion ingest --ct` does; the summary names the grid and the warnings.
pub fn load(path: &Path) -> Outcome {
    lungmotion::ingest::scan::load_ct(path)
        .map(|scan| {
            format!(
                "{:?} grid {:?} spacing {:?}; warnings: {}",
                scan.format,
                scan.ct.geometry.dims,
                scan.ct.geometry.spacing_mm,
                scan.warnings.join(" | ")
            )
        })
        .map_err(|e| e.to_string())
}

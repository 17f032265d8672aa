//! Where the ingest of an uploaded scan runs, so that no upload can take the server down.
//!
//! A hostile file can make a reader recurse until the stack is exhausted (a DICOM data set of
//! 200 000 nested sequences did); Rust does not unwind a stack overflow, it aborts the whole
//! process, so no thread or `catch_unwind` contains it. The server therefore reads and
//! meshes each upload in a child process, the `lungmotion` binary run as
//! `lungmotion serve --ingest-child`: the request goes in on stdin as JSON, the ingest summary
//! or the refusal comes back on stdout, and a child that crashes, is killed or overruns
//! `ingest_timeout_s` costs one `422` answer, never the server. Embedders without the binary
//! (the benchmarks, tests of the library) run it on the server's blocking threads instead,
//! which contains panics, not an overflow.
//!
//! The child reads on a thread with the default stack, as the job workers have, not on its
//! main thread (8 MiB under the usual `ulimit -s`): a file whose reading fits the child's
//! stack then also fits the job worker's, which reads the stored scan again in the server's
//! process. Measured on the 200 000-deep file with `lungmotion ingest`: it overflows a
//! 1 GiB main-thread stack and is read (then refused, no pixel data) with 4 GiB, at 2.1 GB
//! peak memory, so no stack size a server could give would contain it.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use axum::http::StatusCode;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::config::IngestIsolation;
use super::ids::ScanId;
use super::problem::{ApiError, ApiResult};
use super::store::Store;
use crate::ingest::pipeline::ingest_scan;
use crate::ingest::scan::load_ct_with;
use crate::ingest::stored::write_stored_ingest;
use crate::run::RunConfig;

/// Largest request a child reads on stdin and answer the server reads on stdout.
const MAX_MESSAGE_BYTES: u64 = 64 << 20;

/// How often the server looks whether the child has finished.
const CHILD_POLL: Duration = Duration::from_millis(20);

/// Lines of the child's standard error kept to tell why it ended without an answer.
const STDERR_TAIL_LINES: usize = 40;

/// What the ingest of one upload may spend.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IngestLimits {
    /// Wall time before the ingest is stopped.
    pub timeout: Duration,
    /// Address space of the ingest child, MiB (0: unlimited; an ingest on a thread cannot be
    /// limited apart from the server).
    pub memory_mib: u64,
}

/// What the server asks of an ingest child.
#[derive(Debug, Serialize, Deserialize)]
struct ChildRequest {
    /// The uploaded file, named as the readers expect (`.nii.gz`, `.zip` …).
    upload: PathBuf,
    /// The run defaults whose ingest settings apply.
    run: RunConfig,
    /// Address space the child limits itself to before reading, MiB (0: none).
    #[serde(default)]
    memory_mib: u64,
    /// What the client calls the file in the refusals (`the upload`).
    #[serde(default = "the_upload")]
    shown_as: String,
    /// Where to leave the ingest in its file form for the scan's first job, if anywhere.
    #[serde(default)]
    stored_ingest: Option<PathBuf>,
}

/// What a scan upload is called in its refusals.
pub const THE_UPLOAD: &str = "the upload";

fn the_upload() -> String {
    THE_UPLOAD.into()
}

/// What an ingest child answers.
#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum ChildAnswer {
    /// The ingest summary (the CLI's `ingest.json`).
    Summary(Value),
    /// The refusal as the client is to see it.
    Refused {
        status: u16,
        slug: String,
        detail: String,
    },
}

/// Reads and meshes the upload at `upload` with the ingest settings of `run`, and leaves
/// the ingest at `stored_ingest` in its file form (see [`crate::ingest::stored`]; a failure to
/// write it is logged, the upload stands); the ingest summary, or the refusal with the file
/// called `shown_as` ("the upload", "the series pulled from the PACS"; never a server path).
pub fn ingest_upload(
    upload: &Path,
    run: &RunConfig,
    shown_as: &str,
    stored_ingest: Option<&Path>,
) -> ApiResult<Value> {
    let shown = upload.display().to_string();
    // The scan field names the upload (or `upload:entry` in a zip); reasons may list the
    // files a DICOM reader skipped, so their text is redacted too.
    let refused = |e: crate::Error| {
        ApiError::from_input_error_showing(e, |p| {
            p.to_string_lossy().replacen(&shown, shown_as, 1).into()
        })
        .redact_path(upload, shown_as)
    };
    let scan = load_ct_with(upload, &run.dicom_read_options()).map_err(refused)?;
    let outcome = ingest_scan(&scan, &run.ingest_settings()).map_err(refused)?;
    if let Some(path) = stored_ingest {
        let t = std::time::Instant::now();
        match write_stored_ingest(path, &run.ingest_identity(), &scan.ct.geometry, &outcome) {
            Ok(bytes) => tracing::info!(
                bytes,
                seconds = t.elapsed().as_secs_f64(),
                "ingest stored for the scan's jobs"
            ),
            Err(e) => tracing::warn!("the ingest could not be stored; jobs ingest anew: {e}"),
        }
    }
    serde_json::to_value(&outcome.summary)
        .map_err(|e| ApiError::internal(format!("ingest summary: {e}")))
}

/// [`ingest_upload`] where `isolation` says, a child held to `limits`, the file called
/// `shown_as` in refusals, the ingest stored at `stored_ingest`. Blocks.
pub fn ingest_isolated(
    isolation: &IngestIsolation,
    upload: &Path,
    run: &RunConfig,
    limits: IngestLimits,
    shown_as: &str,
    stored_ingest: Option<&Path>,
) -> ApiResult<Value> {
    match isolation {
        IngestIsolation::Thread => ingest_upload(upload, run, shown_as, stored_ingest),
        IngestIsolation::ChildProcess { program } => {
            in_child(program, upload, run, limits, shown_as, stored_ingest)
        }
    }
}

/// Moves the ingest the upload's child stored at `stored` into scan `id`'s directory, where
/// its first job looks for it; without it (not written, or the scan already deleted) the job
/// ingests anew.
pub fn adopt_stored_ingest(store: &Store, id: ScanId, stored: &Path) {
    if !stored.is_file() {
        return;
    }
    if let Err(e) = std::fs::rename(stored, store.stored_ingest_file(id)) {
        tracing::warn!(scan = %id, "cannot keep the stored ingest; the first job ingests anew: {e}");
    }
}

/// Caps this process's address space at `mib` MiB (`RLIMIT_AS`), so that a reader's runaway
/// allocation fails inside the ingest child instead of pushing the machine into swap or the
/// kernel's OOM killer, which might pick the server.
#[cfg(unix)]
fn limit_address_space(mib: u64) -> std::io::Result<()> {
    let bytes = mib.saturating_mul(1 << 20) as libc::rlim_t;
    let limit = libc::rlimit {
        rlim_cur: bytes,
        rlim_max: bytes,
    };
    // SAFETY: setrlimit reads the struct we pass and changes only this process's limits.
    if unsafe { libc::setrlimit(libc::RLIMIT_AS, &limit) } == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

#[cfg(not(unix))]
fn limit_address_space(_mib: u64) -> std::io::Result<()> {
    Ok(())
}

/// Runs `work` on a thread with the default stack (the job workers'); a panic becomes a 500.
fn on_worker_sized_thread<T: Send>(work: impl FnOnce() -> ApiResult<T> + Send) -> ApiResult<T> {
    std::thread::scope(|scope| {
        let thread = std::thread::Builder::new()
            .name("lungmotion-ingest".into())
            .spawn_scoped(scope, work)
            .map_err(|e| ApiError::internal(format!("cannot start the ingest thread: {e}")))?;
        thread.join().unwrap_or_else(|panic| {
            Err(ApiError::internal(format!(
                "the scan reader panicked: {}",
                panic_text(panic.as_ref())
            )))
        })
    })
}

fn panic_text(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<String>()
        .cloned()
        .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_else(|| "unknown panic".into())
}

/// The child's side (`lungmotion serve --ingest-child`): one request from `input`, its
/// answer to `output`. A failure to read or answer is the server's to report.
pub fn serve_ingest_child(input: impl Read, mut output: impl Write) -> std::io::Result<()> {
    let mut request = Vec::new();
    input.take(MAX_MESSAGE_BYTES).read_to_end(&mut request)?;
    let answer = match serde_json::from_slice::<ChildRequest>(&request) {
        Ok(request) => {
            let limited = match request.memory_mib {
                0 => Ok(()),
                mib => limit_address_space(mib).map_err(|e| {
                    ApiError::internal(format!(
                        "ingest child: cannot limit its memory to {mib} MiB: {e}"
                    ))
                }),
            };
            let ingest = limited.and_then(|()| {
                on_worker_sized_thread(|| {
                    ingest_upload(
                        &request.upload,
                        &request.run,
                        &request.shown_as,
                        request.stored_ingest.as_deref(),
                    )
                })
            });
            match ingest {
                Ok(summary) => ChildAnswer::Summary(summary),
                Err(e) => ChildAnswer::Refused {
                    status: e.status.as_u16(),
                    slug: e.slug.to_string(),
                    detail: e.detail,
                },
            }
        }
        Err(e) => ChildAnswer::Refused {
            status: 500,
            slug: "internal".into(),
            detail: format!("ingest child: unreadable request: {e}"),
        },
    };
    serde_json::to_writer(&mut output, &answer)?;
    output.flush()
}

/// Runs the ingest in `program serve --ingest-child`, killed after `limits.timeout`.
fn in_child(
    program: &Path,
    upload: &Path,
    run: &RunConfig,
    limits: IngestLimits,
    shown_as: &str,
    stored_ingest: Option<&Path>,
) -> ApiResult<Value> {
    let timeout = limits.timeout;
    let request = serde_json::to_vec(&ChildRequest {
        upload: upload.to_path_buf(),
        run: run.clone(),
        memory_mib: limits.memory_mib,
        shown_as: shown_as.to_string(),
        stored_ingest: stored_ingest.map(Path::to_path_buf),
    })
    .map_err(|e| ApiError::internal(format!("ingest child request: {e}")))?;
    let mut child = Command::new(program)
        .args(["serve", "--ingest-child"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| {
            ApiError::internal(format!(
                "cannot start {} for the ingest: {e}",
                program.display()
            ))
        })?;
    // The request is small next to the pipe's buffer; the answer is read on its own thread so
    // a large one cannot block the child while the server waits for it to exit.
    if let Some(mut stdin) = child.stdin.take() {
        if let Err(e) = stdin.write_all(&request) {
            tracing::warn!("ingest child: cannot send the request: {e}");
        }
    }
    let stdout = child.stdout.take();
    let reader = std::thread::spawn(move || {
        let mut answer = Vec::new();
        if let Some(out) = stdout {
            let _ = out.take(MAX_MESSAGE_BYTES).read_to_end(&mut answer);
        }
        answer
    });
    let stderr = child.stderr.take();
    let diagnostics = std::thread::spawn(move || stderr.map(relay_stderr).unwrap_or_default());
    let started = Instant::now();
    let status = loop {
        match child.try_wait() {
            Ok(Some(status)) => break Some(status),
            Ok(None) if started.elapsed() >= timeout => break None,
            Ok(None) => std::thread::sleep(CHILD_POLL),
            Err(e) => return Err(ApiError::internal(format!("ingest child: {e}"))),
        }
    };
    let Some(status) = status else {
        let _ = child.kill();
        let _ = child.wait();
        let _ = reader.join();
        let _ = diagnostics.join();
        return Err(ApiError::unprocessable(
            "ingest-timeout",
            format!(
                "reading and meshing {shown_as} took longer than {} s (ingest_timeout_s) and was \
                 stopped",
                timeout.as_secs_f64()
            ),
        ));
    };
    let answer = reader.join().unwrap_or_default();
    let stderr_tail = diagnostics.join().unwrap_or_default();
    match serde_json::from_slice::<ChildAnswer>(&answer) {
        Ok(ChildAnswer::Summary(summary)) => Ok(summary),
        Ok(ChildAnswer::Refused {
            status,
            slug,
            detail,
        }) => Err(ApiError::new(
            StatusCode::from_u16(status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR),
            known_slug(&slug),
            detail,
        )),
        Err(_) => Err(crashed(status, &stderr_tail, limits.memory_mib, shown_as)),
    }
}

/// Passes the child's standard error on to the server's (its log lines belong in the
/// server's log) and keeps the last lines, which say why a child died without an answer.
fn relay_stderr(stderr: impl Read) -> String {
    use std::io::BufRead;
    let mut tail = std::collections::VecDeque::with_capacity(STDERR_TAIL_LINES);
    // Bounded per line: a child cannot make the server hold an endless one.
    let mut lines = std::io::BufReader::new(stderr.take(MAX_MESSAGE_BYTES));
    let mut line = Vec::new();
    while matches!(lines.read_until(b'\n', &mut line), Ok(n) if n > 0) {
        let text = String::from_utf8_lossy(&line).trim_end().to_string();
        eprintln!("{text}");
        if tail.len() == STDERR_TAIL_LINES {
            tail.pop_front();
        }
        tail.push_back(text);
        line.clear();
    }
    Vec::from(tail).join("\n")
}

/// The refusal of an upload whose reader ended the child without an answer, told from its
/// exit signal and the last lines it wrote (Rust's runtime names an allocation it could not
/// make and a stack overflow before it aborts).
fn crashed(status: ExitStatus, stderr_tail: &str, memory_mib: u64, shown_as: &str) -> ApiError {
    if memory_mib != 0 && stderr_tail.contains("memory allocation of") {
        tracing::error!("ingest child ran out of its {memory_mib} MiB on an upload");
        return ApiError::unprocessable(
            "ingest-out-of-memory",
            format!(
                "reading {shown_as} needed more than the {memory_mib} MiB an ingest may use \
                 (ingest_memory_mib) and was stopped; nothing was stored"
            ),
        );
    }
    #[cfg(unix)]
    let signal = {
        use std::os::unix::process::ExitStatusExt;
        status.signal()
    };
    #[cfg(not(unix))]
    let signal: Option<i32> = None;
    let how = match signal {
        // What Rust's stack-overflow handler and `abort` raise.
        Some(6) if stderr_tail.contains("has overflowed its stack") => {
            "overflowed its stack (signal 6)".to_string()
        }
        Some(6) => "aborted (signal 6: a stack overflow or an abort)".to_string(),
        Some(9) => "killed (signal 9: most likely out of memory)".to_string(),
        Some(11) => "crashed (signal 11: invalid memory access)".to_string(),
        Some(s) => format!("ended by signal {s}"),
        None => format!("ended with status {}", status.code().unwrap_or(-1)),
    };
    tracing::error!("ingest child {how} on an upload");
    ApiError::unprocessable(
        "scan-reader-crashed",
        format!(
            "reading {shown_as} {how}; the file is malformed beyond what the readers can \
             refuse by name (for example nested far deeper than any CT); nothing was stored"
        ),
    )
}

/// The `'static` slug of a refusal the child named (an unknown one is internal).
fn known_slug(slug: &str) -> &'static str {
    [
        "invalid-scan",
        "ingest-failed",
        "invalid-input",
        "ingest-timeout",
        "ingest-out-of-memory",
        "scan-reader-crashed",
    ]
    .into_iter()
    .find(|known| *known == slug)
    .unwrap_or("internal")
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;
    use std::os::unix::process::ExitStatusExt;

    #[test]
    fn a_dead_childs_last_words_name_its_cause() {
        // A raw wait status of 6: killed by SIGABRT, as Rust's runtime ends both cases.
        let aborted = ExitStatus::from_raw(6);
        let oom = crashed(
            aborted,
            "reading\nmemory allocation of 251658240 bytes failed",
            256,
            THE_UPLOAD,
        );
        assert_eq!(oom.slug, "ingest-out-of-memory");
        assert!(oom.detail.contains("256 MiB") && oom.detail.contains("ingest_memory_mib"));
        let overflow = crashed(
            aborted,
            "thread 'lungmotion-ingest' has overflowed its stack\nfatal runtime error",
            256,
            THE_UPLOAD,
        );
        assert_eq!(overflow.slug, "scan-reader-crashed");
        assert!(
            overflow.detail.contains("overflowed its stack"),
            "{}",
            overflow.detail
        );
        // Without a limit an allocation failure is not blamed on one.
        let unlimited = crashed(
            aborted,
            "memory allocation of 8 bytes failed",
            0,
            THE_UPLOAD,
        );
        assert_eq!(unlimited.slug, "scan-reader-crashed");
        let killed = crashed(
            ExitStatus::from_raw(9),
            "",
            256,
            "the series pulled from the PACS",
        );
        assert!(killed.detail.contains("signal 9"), "{}", killed.detail);
        assert!(
            killed
                .detail
                .starts_with("reading the series pulled from the PACS killed"),
            "{}",
            killed.detail
        );
    }

    #[test]
    fn a_refused_series_is_called_what_it_is_never_by_the_servers_path() {
        let dir = std::env::temp_dir().join(format!("lm-isolation-{}", std::process::id()));
        let series = dir.join("series");
        std::fs::create_dir_all(&series).unwrap();
        std::fs::write(series.join("IM0001"), b"not a DICOM file").unwrap();
        let e = ingest_upload(&series, &RunConfig::default(), "the series", None).unwrap_err();
        assert!(e.status == 422, "{e}");
        assert!(e.detail.contains("the series"), "{e}");
        assert!(!e.detail.contains("the upload"), "{e}");
        assert!(!e.detail.contains(&dir.display().to_string()), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_childs_standard_error_is_kept_to_its_last_lines() {
        let text: String = (0..100).map(|i| format!("line {i}\n")).collect();
        let tail = relay_stderr(text.as_bytes());
        assert_eq!(tail.lines().count(), STDERR_TAIL_LINES);
        assert!(
            tail.starts_with("line 60") && tail.ends_with("line 99"),
            "{tail}"
        );
    }
}

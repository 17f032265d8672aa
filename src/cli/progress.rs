//! Progress of a run on stderr: on a terminal a spinner per stage and a bar over the frames;
//! otherwise (a script, a log file, a batch system) plain lines with the elapsed time at a
//! steady pace, so a long run is never silent.

use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use lungmotion::run::{RunObserver, RunStage};
use lungmotion::simulation::{CancelFlag, SolveProgress, SolveProgressSink};

/// Least time between two progress lines about solves or frames (stage lines always print).
const LINE_INTERVAL: Duration = Duration::from_secs(5);
/// After this long without a line, one says the current stage is still running.
const HEARTBEAT_INTERVAL: Duration = Duration::from_secs(10);

/// Progress on stderr, and the cancel flag the run is stopped by.
pub struct ProgressDisplay {
    view: View,
    cancel: Option<CancelFlag>,
}

/// How progress is shown.
enum View {
    Quiet,
    Bar(Arc<Mutex<BarState>>),
    Lines(LineLog),
}

impl ProgressDisplay {
    /// A display that shows nothing when `quiet`, a bar on a terminal and lines otherwise.
    pub fn new(quiet: bool) -> Self {
        let view = if quiet {
            View::Quiet
        } else if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
            View::Bar(Arc::default())
        } else {
            View::Lines(LineLog::start())
        };
        ProgressDisplay { view, cancel: None }
    }

    /// Stops the run (inside solves too) when `flag` is raised.
    pub fn with_cancel(mut self, flag: CancelFlag) -> Self {
        self.cancel = Some(flag);
        self
    }

    /// Clears the bar, or logs the end of the run with its elapsed time.
    pub fn finish(&mut self) {
        match &mut self.view {
            View::Quiet => {}
            View::Bar(state) => lock(state).clear(),
            View::Lines(log) => {
                log.line("run finished");
                log.stop();
            }
        }
    }
}

impl RunObserver for ProgressDisplay {
    fn stage(&mut self, stage: RunStage) {
        match &self.view {
            View::Quiet => {}
            View::Bar(state) => lock(state).stage(stage),
            View::Lines(log) => log.stage(stage),
        }
    }

    fn frame_written(&mut self, done: usize, total: usize) {
        match &self.view {
            View::Quiet => {}
            View::Bar(state) => lock(state).frame(done, total),
            View::Lines(log) => log.frame(done, total),
        }
    }

    fn cancelled(&self) -> bool {
        self.cancel
            .as_ref()
            .is_some_and(|f| f.load(Ordering::SeqCst))
    }

    fn cancel_flag(&self) -> Option<CancelFlag> {
        self.cancel.clone()
    }

    fn solve_progress(&self) -> Option<SolveProgressSink> {
        match &self.view {
            View::Quiet => None,
            View::Bar(state) => {
                let state = state.clone();
                Some(SolveProgressSink(Arc::new(move |p| lock(&state).solved(p))))
            }
            View::Lines(log) => {
                let shared = log.shared.clone();
                Some(SolveProgressSink(Arc::new(move |p| shared.solved(p))))
            }
        }
    }
}

/// Locks `m`, going on with the data if a panicking thread poisoned it (progress is cosmetic).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// What solving has reached, in words: "solving: 7 equilibria, +312 mL".
fn solve_words(p: SolveProgress) -> String {
    // Whole millilitres, so a volume just under zero reads "+0", not "-0".
    let ml = p.volume_change_ml.round() as i64;
    format!("solving: {} equilibria, {ml:+} mL", p.equilibria)
}

/// The terminal display: the stage's spinner (or the frames' bar) and the latest solve.
#[derive(Default)]
struct BarState {
    bar: Option<indicatif::ProgressBar>,
    stage: &'static str,
    solve: Option<SolveProgress>,
}

impl BarState {
    fn clear(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }

    fn stage(&mut self, stage: RunStage) {
        self.clear();
        self.stage = stage.label();
        let bar = indicatif::ProgressBar::new_spinner();
        bar.enable_steady_tick(Duration::from_millis(120));
        self.bar = Some(bar);
        self.show_message();
    }

    fn frame(&mut self, done: usize, total: usize) {
        let bar = self.bar.get_or_insert_with(indicatif::ProgressBar::hidden);
        if bar.length() != Some(total as u64) {
            bar.set_style(
                indicatif::ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} frames")
                    .expect("valid template")
                    .progress_chars("=> "),
            );
            bar.set_length(total as u64);
        }
        bar.set_position(done as u64);
    }

    fn solved(&mut self, p: SolveProgress) {
        self.solve = Some(p);
        self.show_message();
    }

    fn show_message(&self) {
        if let Some(bar) = &self.bar {
            bar.set_message(match self.solve {
                Some(p) => format!("{} ({})", self.stage, solve_words(p)),
                None => self.stage.to_string(),
            });
        }
    }
}

/// Plain progress lines when stderr is not a terminal, and the thread that keeps them coming.
struct LineLog {
    shared: Arc<LineShared>,
    heartbeat: Option<(std::sync::mpsc::Sender<()>, std::thread::JoinHandle<()>)>,
}

/// What the run, the solving thread and the heartbeat share.
struct LineShared {
    started: Instant,
    state: Mutex<LineState>,
}

/// The latest of everything, and when the last line went out.
struct LineState {
    last_line: Instant,
    stage: &'static str,
    solve: Option<SolveProgress>,
    frames: Option<(usize, usize)>,
}

impl LineLog {
    /// Starts the clock and the heartbeat.
    fn start() -> Self {
        let now = Instant::now();
        let shared = Arc::new(LineShared {
            started: now,
            state: Mutex::new(LineState {
                last_line: now,
                stage: "starting",
                solve: None,
                frames: None,
            }),
        });
        let (stop, stopped) = std::sync::mpsc::channel::<()>();
        let beat = shared.clone();
        let handle = std::thread::Builder::new()
            .name("progress-heartbeat".into())
            .spawn(move || {
                while let Err(std::sync::mpsc::RecvTimeoutError::Timeout) =
                    stopped.recv_timeout(Duration::from_secs(1))
                {
                    beat.heartbeat();
                }
            })
            .ok();
        LineLog {
            shared,
            heartbeat: handle.map(|h| (stop, h)),
        }
    }

    fn line(&self, text: &str) {
        self.shared.print(&mut lock(&self.shared.state), text);
    }

    fn stage(&self, stage: RunStage) {
        let mut state = lock(&self.shared.state);
        state.stage = stage.label();
        self.shared.print(&mut state, stage.label());
    }

    fn frame(&self, done: usize, total: usize) {
        let mut state = lock(&self.shared.state);
        state.frames = Some((done, total));
        // The first and the last frame always, the ones between at the steady pace.
        if done <= 1 || done == total || state.last_line.elapsed() >= LINE_INTERVAL {
            let status = state.status();
            self.shared.print(&mut state, &status);
        }
    }

    /// Stops the heartbeat (idempotent).
    fn stop(&mut self) {
        if let Some((stop, handle)) = self.heartbeat.take() {
            drop(stop);
            let _ = handle.join();
        }
    }
}

impl Drop for LineLog {
    fn drop(&mut self) {
        self.stop();
    }
}

impl LineShared {
    /// Writes one line with the elapsed time and notes when.
    fn print(&self, state: &mut LineState, text: &str) {
        eprintln!(
            "lungmotion: [{:>7.1} s] {text}",
            self.started.elapsed().as_secs_f64()
        );
        state.last_line = Instant::now();
    }

    fn solved(&self, p: SolveProgress) {
        let mut state = lock(&self.state);
        state.solve = Some(p);
        if state.last_line.elapsed() >= LINE_INTERVAL {
            let status = state.status();
            self.print(&mut state, &status);
        }
    }

    /// After a silence, says what is still running and how far it got.
    fn heartbeat(&self) {
        let mut state = lock(&self.state);
        if state.last_line.elapsed() < HEARTBEAT_INTERVAL {
            return;
        }
        let status = state.status();
        let text = if status.is_empty() {
            format!("still {}", state.stage)
        } else {
            format!("still {} ({status})", state.stage)
        };
        self.print(&mut state, &text);
    }
}

impl LineState {
    /// The solves and the frames so far: "solving: 7 equilibria, +312 mL; frames: 3/10
    /// written" (either part alone until the other has begun).
    fn status(&self) -> String {
        let solve = self.solve.map(solve_words);
        let frames = self
            .frames
            .map(|(done, total)| format!("frames: {done}/{total} written"));
        [solve, frames]
            .into_iter()
            .flatten()
            .collect::<Vec<_>>()
            .join("; ")
    }
}

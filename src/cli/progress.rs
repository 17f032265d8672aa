//! Progress of a run on stderr: a spinner per stage and a bar over the frames.

/// Progress on stderr: a spinner per stage and a bar over the frames.
pub struct ProgressDisplay {
    bar: Option<indicatif::ProgressBar>,
    quiet: bool,
}

impl ProgressDisplay {
    /// A display that shows nothing when `quiet`.
    pub fn new(quiet: bool) -> Self {
        ProgressDisplay { bar: None, quiet }
    }

    /// Clears the current spinner or bar.
    pub fn finish(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}

impl lungmotion::run::RunObserver for ProgressDisplay {
    fn stage(&mut self, stage: lungmotion::run::RunStage) {
        if self.quiet {
            return;
        }
        self.finish();
        let bar = indicatif::ProgressBar::new_spinner().with_message(stage.label());
        bar.enable_steady_tick(std::time::Duration::from_millis(120));
        self.bar = Some(bar);
    }

    fn frame_written(&mut self, done: usize, total: usize) {
        if self.quiet {
            return;
        }
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
}

//! The recording benchmark's Markdown report: the recording, each run's time, work and output,
//! and the target's verdict.

use std::fmt::Write as _;

use super::{RecordingBenchReport, RecordingRuns};
use crate::bench::Outcome;
use crate::markdown::{one_line, or_dash, Table};

impl RecordingBenchReport {
    /// The report as Markdown.
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        let o = &self.options;
        let _ = writeln!(
            s,
            "# The whole spirometer recording on the POPI CT\n\n{} cores; load average {} at the \
             start, {} at the end. {} mm elements, a field every {} s, {} run(s).\n",
            self.cores,
            load(self.load_average_at_start),
            load(self.load_average_at_end),
            o.element_size_mm,
            1.0 / o.frame_rate_hz,
            o.repeats.max(1),
        );
        match &self.recording {
            Outcome::Measured(r) => {
                let _ = writeln!(
                    s,
                    "Recording: {} samples over {:.1} s, {:.0} to {:+.0} mL; the waveform's \
                     scale ({:.1} mL per unit) from the median of {} breaths; `{}`.\n",
                    r.samples,
                    r.duration_s,
                    r.volume_range_ml[0],
                    r.volume_range_ml[1],
                    r.scale_ml_per_unit,
                    r.breaths,
                    r.csv
                );
            }
            Outcome::Failed(e) => {
                let _ = writeln!(s, "Recording: failed: {}\n", one_line(e));
            }
            Outcome::Skipped(why) => {
                let _ = writeln!(s, "Recording: skipped: {why}\n");
            }
        }
        match &self.runs {
            Outcome::Measured(runs) => self.write_runs(runs, &mut s),
            Outcome::Failed(e) => {
                let _ = writeln!(s, "Runs: failed: {}\n", one_line(e));
            }
            Outcome::Skipped(why) => {
                let _ = writeln!(s, "Runs: skipped: {why}\n");
            }
        }
        s
    }

    /// The runs' table and the verdict.
    fn write_runs(&self, runs: &RecordingRuns, s: &mut String) {
        let mut t = Table::new([
            "run",
            "wall s",
            "CPU s",
            "ingest s",
            "solve s",
            "fields s",
            "frames",
            "keys",
            "solves",
            "Newton",
            "Krylov",
            "error mm",
            "written MB",
            "peak MiB",
        ]);
        for (i, r) in runs.each.iter().enumerate() {
            let stage = |k: &str| or_dash(r.stages_s.get(k), |v| format!("{v:.1}"));
            t.row([
                (i + 1).to_string(),
                format!("{:.1}", r.wall_s),
                or_dash(r.cpu_s, |v| format!("{v:.1}")),
                stage("ingest"),
                stage("motion_solve"),
                stage("frame_files"),
                r.frames.to_string(),
                r.work.keys.to_string(),
                r.work.solves.to_string(),
                r.work.newton_iterations.to_string(),
                r.work.krylov_iterations.to_string(),
                or_dash(r.measured_error_mm, |v| {
                    format!("{v:.3} ≤ {}", r.tolerance_mm)
                }),
                format!("{:.0}", r.bytes_written as f64 / 1e6),
                or_dash(r.peak_memory_mib, |v| format!("{v:.0}")),
            ]);
        }
        t.write_to(s);
        let _ = writeln!(
            s,
            "\nWall time {:.1} s median [{:.1} – {:.1}] ×{}; CPU {:.1} s median ({:.1} s per \
             core); same solver work every run: {}.\n\n**Target: the whole recording at 8 mm \
             in ≤ {:.0} s with every frame within its tolerance: {}.**\n",
            runs.time.median_s,
            runs.time.min_s,
            runs.time.max_s,
            runs.time.runs,
            runs.cpu.median_s,
            runs.cpu_per_core_s,
            if runs.same_work_every_run {
                "yes"
            } else {
                "no"
            },
            self.target_s,
            match runs.target_met {
                Some(true) => "met",
                Some(false) => "missed",
                None => "not measured (these are not the target's runs)",
            }
        );
        // Every run of one build solves the same keys, so their warnings repeat: each is
        // listed once, with how many runs gave it.
        let mut warnings: Vec<(&String, usize)> = Vec::new();
        for w in runs.each.iter().flat_map(|r| &r.warnings) {
            match warnings.iter_mut().find(|(seen, _)| *seen == w) {
                Some((_, count)) => *count += 1,
                None => warnings.push((w, 1)),
            }
        }
        for (w, count) in warnings {
            let _ = writeln!(
                s,
                "- warning ({count} of {} runs): {}",
                runs.each.len(),
                one_line(w)
            );
        }
    }
}

fn load(l: Option<[f64; 3]>) -> String {
    or_dash(l, |l| format!("{:.2}, {:.2}, {:.2}", l[0], l[1], l[2]))
}

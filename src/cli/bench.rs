//! `lungmotion bench`: the speed and memory benchmarks, one report pair per suite.

use std::path::{Path, PathBuf};

use lungmotion::bench::ingest::{run_ingest_bench, IngestBenchOptions};
use lungmotion::bench::motion::{run_motion_bench, MotionBenchOptions};
use lungmotion::bench::recording::{run_recording_bench, RecordingBenchOptions};
use lungmotion::bench::scale::{run_scale_bench, ScaleBenchOptions};
use lungmotion::bench::service::{run_service_bench, ServiceBenchOptions};
use lungmotion::bench::{run_bench, BenchOptions};
use lungmotion::durable::write_atomic;

use super::prepare_out;

/// Benchmark groups.
#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BenchSuite {
    // No doc comments here: clap would list them in `bench --help`, described under --suite.
    Core,
    Ingest,
    Motion,
    Recording,
    Service,
    Scale,
    All,
}

impl BenchSuite {
    /// Whether this choice runs `suite`.
    fn includes(self, suite: BenchSuite) -> bool {
        // The element-size study takes hours in full: only asked for by name.
        self == suite || (self == BenchSuite::All && suite != BenchSuite::Scale)
    }
}

/// Options of `lungmotion bench`.
#[derive(clap::Args)]
pub struct BenchArgs {
    /// Directory for the reports.
    #[arg(long, default_value = "bench-out")]
    out: PathBuf,
    /// Seconds-long smoke run on small blocks (numbers not meaningful).
    #[arg(long)]
    quick: bool,
    /// Block sizes (cells per edge) also solved by CalculiX; 40 (64 000 elements) takes
    /// about 5 minutes linear. Empty to skip.
    #[arg(long, value_delimiter = ',', default_value = "20,30")]
    calculix_cells: Vec<usize>,
    /// Also run CalculiX with NLGEOM (our physics class; about 1 min at 20³, 10 min at 30³).
    #[arg(long)]
    nlgeom: bool,
    /// Which benchmarks: `core` (mechanics), `ingest` (segmentation of the CIP case and of
    /// a 512×512×300 CT), `motion` (10-phase tidal cycle on the CIP case at 8 and 4 mm:
    /// cycle time, fields served per second, interpolation error; fields served on the POPI
    /// CT's grid), `service` (HTTP: upload of a 300-slice DICOM zip, service against
    /// in-process run, requests per second; the POPI CT's jobs, fields written per second and
    /// requests for its fields), `scale`
    /// (run time against error for element sizes 16 to 2 mm on the CIP and POPI CTs, with a
    /// PNG plot; about 3 minutes in full on 2 cores, not part of `all`), `recording` (the whole 55 s spirometer
    /// recording on the POPI CT at 8 mm, a field every 0.5 s, three whole runs) or `all`.
    #[arg(long, value_enum, default_value_t = BenchSuite::All)]
    suite: BenchSuite,
    /// Element sizes of the scale suite, mm, on every case (default 16,12,10,8,6,5,4,3,2).
    #[arg(long, value_delimiter = ',')]
    scale_sizes: Vec<f64>,
    /// Wall-clock budget of each size's cycle in the scale suite, seconds.
    #[arg(long, default_value_t = 600.0)]
    scale_budget: f64,
}

impl BenchArgs {
    /// Runs the chosen suites in order, each writing its reports before the next starts.
    pub fn execute(self) -> anyhow::Result<()> {
        let out = &self.out;
        prepare_out(out)?;
        eprintln!("lungmotion: benchmarking (medians of repeated runs; keep the machine quiet)");
        if self.suite.includes(BenchSuite::Core) {
            let report = run_bench(&self.core_options())?;
            write_bench_report(out, "bench", &report, &report.to_markdown())?;
        }
        if self.suite.includes(BenchSuite::Ingest) {
            let options = IngestBenchOptions {
                quick: self.quick,
                ..IngestBenchOptions::default()
            };
            let report = run_ingest_bench(&options)?;
            write_bench_report(out, "bench-ingest", &report, &report.to_markdown())?;
        }
        if self.suite.includes(BenchSuite::Motion) {
            let options = if self.quick {
                MotionBenchOptions::quick()
            } else {
                MotionBenchOptions::default()
            };
            let report = run_motion_bench(&options)?;
            write_bench_report(out, "bench-motion", &report, &report.to_markdown())?;
        }
        if self.suite.includes(BenchSuite::Recording) {
            let options = if self.quick {
                RecordingBenchOptions::quick()
            } else {
                RecordingBenchOptions::default()
            };
            let report = run_recording_bench(&options, out)?;
            write_bench_report(out, "bench-recording", &report, &report.to_markdown())?;
        }
        if self.suite.includes(BenchSuite::Scale) {
            let mut options = if self.quick {
                ScaleBenchOptions::quick()
            } else {
                ScaleBenchOptions::full()
            };
            if !self.scale_sizes.is_empty() {
                for case in &mut options.cases {
                    case.element_sizes_mm = self.scale_sizes.clone();
                }
            }
            if !self.quick {
                options.budget_s = self.scale_budget;
            }
            let report = run_scale_bench(&options)?;
            write_bench_report(out, "bench-scale", &report, &report.to_markdown())?;
            report.write_plot(out)?;
        }
        if self.suite.includes(BenchSuite::Service) {
            let report = run_service_bench(&ServiceBenchOptions { quick: self.quick })?;
            write_bench_report(out, "bench-service", &report, &report.to_markdown())?;
        }
        Ok(())
    }

    /// The core suite's options: quick or full, with the CalculiX block sizes of a full run.
    fn core_options(&self) -> BenchOptions {
        let mut options = if self.quick {
            BenchOptions::quick()
        } else {
            BenchOptions::default()
        };
        if !self.quick {
            options.calculix_block_cells = self.calculix_cells.clone();
        }
        options.calculix_nlgeom = self.nlgeom;
        options
    }
}

/// Writes `<stem>.json` and `<stem>.md` into `out` and prints the Markdown.
fn write_bench_report(
    out: &Path,
    stem: &str,
    report: &impl serde::Serialize,
    markdown: &str,
) -> anyhow::Result<()> {
    let json = out.join(format!("{stem}.json"));
    write_atomic(&json, serde_json::to_string_pretty(report)?.as_bytes())?;
    write_atomic(&out.join(format!("{stem}.md")), markdown.as_bytes())?;
    println!("{markdown}");
    eprintln!("lungmotion: wrote {}", json.display());
    Ok(())
}

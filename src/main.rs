//! `lungmotion` command line: a thin shell over the library.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};

use lungmotion::bench::{run_bench, BenchOptions};
use lungmotion::durable::write_atomic;
use lungmotion::validation::report::{run_validation, ValidateOptions};

/// Predicts lung motion over a breathing curve with Baudet's parameterised hexahedral
/// mass–spring model.
#[derive(Parser)]
#[command(name = "lungmotion", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// Benchmark groups.
#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum BenchSuite {
    Core,
    Ingest,
    Motion,
    Service,
    All,
}

#[derive(Subcommand)]
enum Command {
    /// Predict lung motion over a breathing curve: one CT and one trace in, a displacement
    /// field per requested instant out.
    ///
    /// The trace is lung volume over time, CSV with the header `time_s,volume_ml` where
    /// volume_ml is the change from the scanned state in mL (JSON `{"time_s": [...],
    /// "volume_ml": [...]}` also read; absolute volumes and other units via --config). By
    /// default 10 phases of the first breathing cycle are output (phase 0 = end-inhale), like
    /// a 4D-CT; the lung is driven by the surface pressure that gives each frame's volume.
    ///
    /// Writes into --out: frames/<k>/displacement.nii.gz (vector field on the CT's grid,
    /// components in LPS millimetres as ITK/elastix read them, zero outside the lungs),
    /// summary.json (per-frame time, target and simulated volume, pressure, displacement,
    /// solver effort), trajectories.csv (tracked points), breathing.png and
    /// end-inhale-displacement.png, and ingest/ (lung mask, groups, mesh). The directory is
    /// replaced only when the run succeeds.
    #[command(verbatim_doc_comment)]
    Run(RunArgs),
    /// Run the whole job on the bundled phantom (sample-volumes/) with two generated 500 mL
    /// breaths, tracking the tumour, the right apex and the right base.
    Demo {
        /// Output directory.
        #[arg(long, default_value = "demo-out")]
        out: PathBuf,
        /// Edge of the cubic elements in millimetres (8 keeps the demo to seconds).
        #[arg(long, default_value_t = 8.0)]
        element_size: f64,
        /// No progress bar.
        #[arg(long, short)]
        quiet: bool,
    },
    /// Turn a CT into the mechanical model: segment both lungs, build cubic elements and tag
    /// the anatomical constraint groups; writes lung-mask.nii.gz, groups.nii.gz, ingest.json,
    /// surface.vtp, mesh.vtu and quick-look PNGs.
    Ingest {
        /// The CT: a DICOM directory, a zip of one DICOM series, a NIfTI (.nii, .nii.gz) or a
        /// NRRD file (told apart by content).
        #[arg(long)]
        ct: PathBuf,
        /// Directory for the outputs (created if missing; files in it are replaced atomically).
        #[arg(long)]
        out: PathBuf,
        /// Edge of the cubic elements in millimetres (2–16).
        #[arg(long)]
        element_size: Option<f64>,
        /// Your own constraint groups: a label map on the CT's grid with the codes listed in
        /// ingest.json (1 hilum, 2 mediastinal, 3 costal, 4 diaphragmatic, 5 apex).
        #[arg(long)]
        groups: Option<PathBuf>,
    },
    /// Write the procedural thorax phantom (CT as NIfTI and as a DICOM series, its exact
    /// tissue labels and a description) that the README's main job and the tests run on.
    Phantom {
        /// Directory for the phantom files.
        #[arg(long, default_value = "sample-volumes")]
        out: PathBuf,
        /// Random seed of the noise (same seed, same bytes).
        #[arg(long)]
        seed: Option<u64>,
        /// Leave the tumour out.
        #[arg(long)]
        no_tumour: bool,
    },
    /// Measure the model's accuracy: patch tests against closed forms and composite cases
    /// against CalculiX; writes validation.json and validation.md.
    Validate {
        /// Directory for the reports.
        #[arg(long, default_value = "validation-out")]
        out: PathBuf,
        /// Smaller composite resolutions (cantilever to 4×4×16, L to 8³) and stability grid.
        #[arg(long)]
        quick: bool,
        /// Skip the CalculiX comparisons (no `ccx` needed).
        #[arg(long)]
        no_calculix: bool,
        /// Instead: the breathing model's end-inhale frame (500 mL, CIP lungs at 8 mm) against
        /// CalculiX C3D8 and C3D8I with NLGEOM (needs ../shared/data; about 3 minutes);
        /// writes lung_calculix.json and lung_calculix.md.
        #[arg(long, conflicts_with_all = ["quick", "no_calculix"])]
        lung: bool,
    },
    /// Measure speed and memory: force-evaluation throughput (1 thread and all threads),
    /// memory per element and node, quasi-static solves of pressurised blocks, and CalculiX on
    /// the same blocks; writes bench.json and bench.md (medians, side-by-side ratios).
    Bench {
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
        /// cycle time, fields served per second, interpolation error), `service` (HTTP: upload of a
        /// 300-slice DICOM zip, service against in-process run, requests per second) or `all`.
        #[arg(long, value_enum, default_value_t = BenchSuite::All)]
        suite: BenchSuite,
    },
    /// Serve the pipeline over HTTP: upload a scan, submit breathing curves, follow the jobs,
    /// fetch displacement fields (see README, "HTTP service", and GET /openapi.json).
    ///
    /// Settings come from --config (TOML), then the environment (LUNGMOTION_LISTEN,
    /// LUNGMOTION_DATA_DIR, LUNGMOTION_WORKERS, LUNGMOTION_QUEUE_CAPACITY,
    /// LUNGMOTION_MAX_UPLOAD_MIB, LUNGMOTION_API_TOKEN, LUNGMOTION_API_TOKEN_FILE), then these
    /// options. A bearer token is required to listen beyond loopback. SIGTERM or Ctrl-C stops
    /// it gracefully: running jobs get shutdown_grace_s, then go back to the queue.
    #[command(verbatim_doc_comment)]
    Serve {
        /// Address and port (default 127.0.0.1:8080; port 0 picks a free one).
        #[arg(long)]
        listen: Option<String>,
        /// Where scans, jobs and results are stored (default ./lungmotion-data).
        #[arg(long)]
        data_dir: Option<PathBuf>,
        /// Service configuration (TOML; its [run] table holds the simulation defaults).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Simulations run at once (default: one per core).
        #[arg(long)]
        workers: Option<usize>,
        /// Simulations that may wait for a worker; beyond, 429 (default 16).
        #[arg(long)]
        queue_capacity: Option<usize>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if let Command::Serve {
        listen,
        data_dir,
        config,
        workers,
        queue_capacity,
    } = cli.command
    {
        init_logging("info");
        return serve(listen, data_dir, config, workers, queue_capacity);
    }
    init_logging("warn");
    let result = match cli.command {
        Command::Run(args) => run(args),
        Command::Demo {
            out,
            element_size,
            quiet,
        } => demo(out, element_size, quiet),
        Command::Ingest {
            ct,
            out,
            element_size,
            groups,
        } => ingest(ct, out, element_size, groups),
        Command::Phantom {
            out,
            seed,
            no_tumour,
        } => phantom(out, seed, no_tumour),
        Command::Validate {
            out,
            quick,
            no_calculix,
            lung,
        } => {
            if lung {
                validate_lung(out)
            } else {
                validate(out, quick, !no_calculix)
            }
        }
        Command::Bench {
            out,
            quick,
            calculix_cells,
            nlgeom,
            suite,
        } => bench(out, quick, calculix_cells, nlgeom, suite),
        Command::Serve { .. } => unreachable!("handled above"),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("lungmotion: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Logs go to stderr; `LUNGMOTION_LOG` (e.g. `debug`, `lungmotion=trace`) sets the level and
/// `LUNGMOTION_LOG_FORMAT=json` writes one JSON object per line for log collectors.
fn init_logging(default_level: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_env("LUNGMOTION_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_level));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    if std::env::var("LUNGMOTION_LOG_FORMAT").is_ok_and(|f| f.eq_ignore_ascii_case("json")) {
        builder.json().with_current_span(true).init();
    } else {
        builder
            .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
            .init();
    }
}

/// Options of `lungmotion run`.
#[derive(clap::Args)]
struct RunArgs {
    /// The CT: a DICOM directory, a zip of one DICOM series, a NIfTI (.nii, .nii.gz) or a
    /// NRRD file (told apart by content).
    #[arg(long)]
    ct: PathBuf,
    /// The breathing trace (CSV or JSON, see above).
    #[arg(long)]
    trace: PathBuf,
    /// Output directory (new, empty, or an earlier run's, which is replaced on success).
    #[arg(long)]
    out: PathBuf,
    /// Edge of the cubic elements in millimetres (2–16; default 6, or the config's).
    #[arg(long)]
    element_size: Option<f64>,
    /// TOML settings: material, driver, output instants, trace units, optional outputs.
    /// The format is documented in the README; command-line options win.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Points to follow (e.g. a tumour centre): CSV with the header name,x_mm,y_mm,z_mm, in
    /// LPS millimetres (DICOM patient coordinates, as a planning system shows them).
    #[arg(long)]
    points: Option<PathBuf>,
    /// Also write each frame as MetaImage (displacement.mha).
    #[arg(long)]
    mha: bool,
    /// Also write each frame's deformed mesh (mesh.vtu, for ParaView).
    #[arg(long)]
    vtu: bool,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
}

fn run(args: RunArgs) -> anyhow::Result<()> {
    use lungmotion::breathing::BreathingTrace;
    use lungmotion::run::{RunConfig, RunInputs};
    let mut config = match &args.config {
        Some(path) => RunConfig::from_toml_file(path)?,
        None => RunConfig::default(),
    };
    if let Some(mm) = args.element_size {
        config.element_size_mm = mm;
    }
    config.outputs.metaimage |= args.mha;
    config.outputs.mesh_vtu |= args.vtu;
    let trace = BreathingTrace::read(&args.trace, &config.trace)?;
    let inputs = RunInputs {
        ct_path: args.ct,
        trace,
        trace_source: args.trace.display().to_string(),
        points: match &args.points {
            Some(path) => lungmotion::outputs::trajectories::read_points(path)?,
            None => Vec::new(),
        },
    };
    run_and_report(&inputs, &config, &args.out, args.quiet)
}

fn demo(out: PathBuf, element_size_mm: f64, quiet: bool) -> anyhow::Result<()> {
    use lungmotion::run::demo::{demo_inputs, sample_volumes_dir};
    let config = lungmotion::run::RunConfig {
        element_size_mm,
        ..lungmotion::run::RunConfig::default()
    };
    let inputs = demo_inputs(&sample_volumes_dir())?;
    eprintln!(
        "lungmotion: demo on {} with {}",
        inputs.ct_path.display(),
        inputs.trace_source
    );
    run_and_report(&inputs, &config, &out, quiet)
}

fn run_and_report(
    inputs: &lungmotion::run::RunInputs,
    config: &lungmotion::run::RunConfig,
    out: &std::path::Path,
    quiet: bool,
) -> anyhow::Result<()> {
    let mut progress = ProgressDisplay::new(quiet);
    let summary = lungmotion::run::run_breathing(inputs, config, out, &mut progress)?;
    progress.finish();
    for w in &summary.warnings {
        eprintln!("lungmotion: warning: {w}");
    }
    let m = &summary.model;
    println!(
        "{} elements of {} mm, {} nodes; rest volume {:.0} mL",
        m.elements, m.element_size_mm, m.nodes, m.rest_volume_ml
    );
    println!("frame  time_s  target_ml  simulated_ml  pressure_pa  max_mm  mean_mm");
    for f in &summary.frames {
        let s = &f.summary;
        println!(
            "{:>5}  {:>6.3}  {:>9.1}  {:>12.1}  {:>11.2}  {:>6.2}  {:>7.2}",
            s.index,
            s.time_s,
            s.target_volume_ml,
            s.simulated_volume_ml,
            s.pressure_pa,
            s.max_displacement_mm,
            s.mean_displacement_mm
        );
    }
    let e = &summary.end_inhale;
    println!(
        "end-inhale (frame {}): max displacement {:.1} mm at LPS ({:.0}, {:.0}, {:.0}) mm \
         ({} lung, {}); base moves {:+.1} mm, apex {:+.1} mm in z",
        e.frame,
        e.max_displacement_mm,
        e.max_displacement_at_lps_mm[0],
        e.max_displacement_at_lps_mm[1],
        e.max_displacement_at_lps_mm[2],
        e.max_displacement_lung,
        e.max_displacement_group,
        e.mean_base_dz_mm,
        e.mean_apex_dz_mm
    );
    for p in &summary.points {
        let d = p.displacement_mm[e.frame];
        println!(
            "{}: end-inhale displacement ({:+.1}, {:+.1}, {:+.1}) mm, |d| = {:.1} mm",
            p.name,
            d[0],
            d[1],
            d[2],
            (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
        );
    }
    println!(
        "solved in {:.2} s ({} key volumes), {:.2} s in all; wrote {}",
        summary
            .timings_s
            .get("motion_solve")
            .copied()
            .unwrap_or(0.0),
        summary.motion.keyframes.as_ref().map_or(0, |k| k.keys),
        summary.timings_s.get("total").copied().unwrap_or(0.0),
        out.join("summary.json").display()
    );
    Ok(())
}

/// Progress on stderr: a spinner per stage and a bar over the frames.
struct ProgressDisplay {
    bar: Option<indicatif::ProgressBar>,
    quiet: bool,
}

impl ProgressDisplay {
    fn new(quiet: bool) -> Self {
        ProgressDisplay { bar: None, quiet }
    }

    fn finish(&mut self) {
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

fn ingest(
    ct: PathBuf,
    out: PathBuf,
    element_size: Option<f64>,
    groups: Option<PathBuf>,
) -> anyhow::Result<()> {
    use lungmotion::ingest::{load_ct, IngestSettings};
    use lungmotion::outputs::ingest_files::write_ingest_outputs;
    prepare_out(&out)?;
    let mut settings = IngestSettings::default();
    if let Some(mm) = element_size {
        settings.model.element_size_mm = mm;
    }
    if let Some(path) = &groups {
        let labels = lungmotion::formats::nifti::read_nifti_labels(path)
            .with_context(|| format!("reading the constraint groups {}", path.display()))?;
        settings.model.group_overrides = Some(labels);
    }
    eprintln!("lungmotion: reading {}", ct.display());
    let scan = load_ct(&ct)?;
    for w in &scan.warnings {
        eprintln!("lungmotion: warning: {w}");
    }
    let g = scan.ct.geometry;
    eprintln!(
        "lungmotion: CT {}×{}×{} voxels of {:.3}×{:.3}×{:.3} mm; segmenting the lungs",
        g.dims[0], g.dims[1], g.dims[2], g.spacing_mm[0], g.spacing_mm[1], g.spacing_mm[2]
    );
    let outcome = lungmotion::ingest::ingest_scan(&scan, &settings)?;
    let s = &outcome.summary;
    for w in s.warnings.iter().skip(scan.warnings.len()) {
        eprintln!("lungmotion: warning: {w}");
    }
    let written = write_ingest_outputs(&out, &scan.ct, &outcome)
        .with_context(|| format!("writing the ingest outputs into {}", out.display()))?;
    println!(
        "lungs {:.0} mL (right {:.0} mL, left {:.0} mL); {} elements of {} mm, {} nodes",
        s.lung_volume_ml,
        s.right_volume_ml,
        s.left_volume_ml,
        s.elements,
        s.element_size_mm,
        s.nodes
    );
    let groups: Vec<String> = s
        .group_nodes
        .iter()
        .map(|(name, n)| format!("{name} {n}"))
        .collect();
    println!("constraint groups (nodes): {}", groups.join(", "));
    for p in written {
        eprintln!("lungmotion: wrote {}", p.display());
    }
    Ok(())
}

fn phantom(out: PathBuf, seed: Option<u64>, no_tumour: bool) -> anyhow::Result<()> {
    use lungmotion::phantom::{write_phantom_files, PhantomSettings};
    prepare_out(&out)?;
    let mut settings = PhantomSettings::default();
    if let Some(seed) = seed {
        settings.seed = seed;
    }
    if no_tumour {
        settings.tumour = None;
    }
    for p in write_phantom_files(&settings, &out)? {
        eprintln!("lungmotion: wrote {}", p.display());
    }
    Ok(())
}

/// Creates the report directory before any work, so a bad `--out` fails at once, by name.
fn prepare_out(out: &std::path::Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(out)
        .with_context(|| format!("cannot create the output directory {}", out.display()))
}

fn validate(out: PathBuf, quick: bool, calculix: bool) -> anyhow::Result<()> {
    prepare_out(&out)?;
    let options = ValidateOptions { quick, calculix };
    let report = run_validation(&options, &mut |step| {
        eprintln!("lungmotion: running {step}")
    })?;
    report
        .write(&out)
        .with_context(|| format!("writing the reports into {}", out.display()))?;
    println!("{}", report.to_markdown());
    eprintln!(
        "lungmotion: wrote {} and {}",
        out.join("validation.json").display(),
        out.join("validation.md").display()
    );
    Ok(())
}

fn validate_lung(out: PathBuf) -> anyhow::Result<()> {
    use lungmotion::validation::lung_calculix::{
        compare_end_inhale_with_calculix, LungCalculixSettings,
    };
    prepare_out(&out)?;
    eprintln!("lungmotion: end-inhale frame of the CIP lungs against CalculiX (minutes)");
    let report = compare_end_inhale_with_calculix(&LungCalculixSettings::default())?;
    report
        .write(&out)
        .with_context(|| format!("writing the reports into {}", out.display()))?;
    println!("{}", report.to_markdown());
    eprintln!(
        "lungmotion: wrote {}",
        out.join("lung_calculix.json").display()
    );
    Ok(())
}

/// Writes `<stem>.json` and `<stem>.md` into `out` and prints the Markdown.
fn write_bench_report(
    out: &std::path::Path,
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

fn bench(
    out: PathBuf,
    quick: bool,
    calculix_cells: Vec<usize>,
    nlgeom: bool,
    suite: BenchSuite,
) -> anyhow::Result<()> {
    prepare_out(&out)?;
    eprintln!("lungmotion: benchmarking (medians of repeated runs; keep the machine quiet)");
    if matches!(suite, BenchSuite::Core | BenchSuite::All) {
        let mut options = if quick {
            BenchOptions::quick()
        } else {
            BenchOptions::default()
        };
        if !quick {
            options.calculix_block_cells = calculix_cells;
        }
        options.calculix_nlgeom = nlgeom;
        let report = run_bench(&options)?;
        write_bench_report(&out, "bench", &report, &report.to_markdown())?;
    }
    if matches!(suite, BenchSuite::Ingest | BenchSuite::All) {
        use lungmotion::bench::ingest::{run_ingest_bench, IngestBenchOptions};
        let options = IngestBenchOptions {
            quick,
            ..IngestBenchOptions::default()
        };
        let report = run_ingest_bench(&options)?;
        write_bench_report(&out, "bench-ingest", &report, &report.to_markdown())?;
    }
    if matches!(suite, BenchSuite::Motion | BenchSuite::All) {
        use lungmotion::bench::motion::{run_motion_bench, MotionBenchOptions};
        let options = if quick {
            MotionBenchOptions::quick()
        } else {
            MotionBenchOptions::default()
        };
        let report = run_motion_bench(&options)?;
        write_bench_report(&out, "bench-motion", &report, &report.to_markdown())?;
    }
    if matches!(suite, BenchSuite::Service | BenchSuite::All) {
        use lungmotion::bench::service::{run_service_bench, ServiceBenchOptions};
        let report = run_service_bench(&ServiceBenchOptions { quick })?;
        write_bench_report(&out, "bench-service", &report, &report.to_markdown())?;
    }
    Ok(())
}

/// `lungmotion serve`: exit code 2 when the settings are refused, 1 when serving fails.
fn serve(
    listen: Option<String>,
    data_dir: Option<PathBuf>,
    config: Option<PathBuf>,
    workers: Option<usize>,
    queue_capacity: Option<usize>,
) -> ExitCode {
    use lungmotion::service::config::parse_listen;
    use lungmotion::service::{serve_blocking, ServiceConfig};
    let env = |name: &str| std::env::var(name).ok();
    // Flags override the file and the environment; the result is validated once.
    let settings = ServiceConfig::from_sources(config.as_deref(), &env).and_then(|mut c| {
        if let Some(listen) = listen {
            c.listen = parse_listen(&listen)
                .map_err(|m| lungmotion::Error::InvalidInput(format!("--listen {m}")))?;
        }
        if let Some(dir) = data_dir {
            c.data_dir = dir;
        }
        if let Some(n) = workers {
            c.workers = n;
        }
        if let Some(n) = queue_capacity {
            c.queue_capacity = n;
        }
        c.validate()?;
        Ok(c)
    });
    let settings = match settings {
        Ok(s) => s,
        Err(e) => {
            eprintln!("lungmotion serve: {e}");
            return ExitCode::from(2);
        }
    };
    match serve_blocking(settings) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("lungmotion serve: error: {e}");
            ExitCode::FAILURE
        }
    }
}

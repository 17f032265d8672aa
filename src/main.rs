//! `lungmotion` command line: a thin shell over the library. The subcommands and their help
//! are here; each one's options and work are in `cli/` (one module per subcommand).

mod cli;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

use cli::bench::BenchArgs;
use cli::exit::{finish, EXIT_STATUS_HELP};
use cli::ingest::IngestArgs;
use cli::logging::init_logging;
use cli::phantom::PhantomArgs;
use cli::run::{DemoArgs, RunArgs};
use cli::serve::{ServeArgs, WorkerArgs};
use cli::validate::ValidateArgs;

/// Predicts lung motion over a breathing curve with Baudet's parameterised hexahedral
/// mass–spring model.
#[derive(Parser)]
#[command(name = "lungmotion", version, about, long_about = None, after_help = EXIT_STATUS_HELP)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Predict lung motion over a breathing curve: one CT and one trace in, a displacement
    /// field per requested instant out.
    ///
    /// The trace is lung volume over time, CSV with the header `time_s,volume_ml` where
    /// volume_ml is the change from the scanned state in mL (JSON `{"time_s": [...],
    /// "volume_ml": [...]}` also read; absolute volumes and other units via --config). An
    /// airflow column instead (flow_l_per_s or flow_ml_per_s, positive into the lungs) is
    /// integrated from the first sample, its drift removed, and the run says so. By
    /// default 10 phases of the first breathing cycle are output (phase 0 = end-inhale), like
    /// a 4D-CT; the lung is driven by the surface pressure that gives each frame's volume.
    /// Other instants in the config's [motion] table: instants = { kind = "phases", count =
    /// N }, { kind = "every_sample" }, { kind = "every_kth", k = K } (every K-th sample) or
    /// { kind = "frame_rate", hz = F } (F frames per second over the whole trace).
    ///
    /// Writes into --out: frames/<k>/displacement.nii.gz (vector field on the CT's voxels
    /// around the lungs, or the whole grid with field_grid = "ct"; components in LPS
    /// millimetres as ITK/elastix read them, zero outside the lungs),
    /// summary.json (per-frame time, target and simulated volume, pressure, displacement,
    /// solver effort), trajectories.csv (tracked points), breathing.png and
    /// end-inhale-displacement.png (deepest-expiration-displacement.png for a trace that
    /// never rises above the scan), and ingest/ (lung mask, groups, mesh). The directory is
    /// replaced only when the run succeeds, and an earlier run of another CT only with
    /// --overwrite. When stderr is not a terminal, progress is logged as lines with the
    /// elapsed time. Ctrl-C, SIGTERM or SIGHUP stop the run and remove its partial output
    /// (exit status 130).
    #[command(verbatim_doc_comment)]
    Run(RunArgs),
    /// Run the whole job on the bundled phantom (sample-volumes/) with two generated 500 mL
    /// breaths, tracking the tumour, the right apex and the right base.
    Demo(DemoArgs),
    /// Turn a CT into the mechanical model: segment both lungs, build cubic elements and tag
    /// the anatomical constraint groups; writes lung-mask.nii.gz, groups.nii.gz, ingest.json,
    /// surface.vtp, mesh.vtu and quick-look PNGs.
    Ingest(IngestArgs),
    /// Write the procedural thorax phantom (CT as NIfTI and as a DICOM series, its exact
    /// tissue labels and a description) that the README's main job and the tests run on.
    Phantom(PhantomArgs),
    /// Measure the model's accuracy: patch tests against closed forms and composite cases
    /// against CalculiX; writes validation.json and validation.md.
    Validate(ValidateArgs),
    /// Measure speed and memory: force-evaluation throughput (1 thread and all threads),
    /// memory per element and node, quasi-static solves of pressurised blocks, and CalculiX on
    /// the same blocks; writes bench.json and bench.md (medians, side-by-side ratios).
    Bench(BenchArgs),
    /// Serve the pipeline over HTTP: upload a scan, submit breathing curves, follow the jobs,
    /// fetch displacement fields (see README, "HTTP service", and GET /openapi.json).
    ///
    /// Settings come from --config (TOML), then the environment (LUNGMOTION_LISTEN,
    /// LUNGMOTION_DATA_DIR, LUNGMOTION_WORKERS, LUNGMOTION_QUEUE_CAPACITY,
    /// LUNGMOTION_MAX_UPLOAD_MIB, LUNGMOTION_API_TOKEN, LUNGMOTION_API_TOKEN_FILE,
    /// LUNGMOTION_MAX_CONNECTIONS, LUNGMOTION_HEADER_READ_TIMEOUT_S,
    /// LUNGMOTION_BODY_READ_TIMEOUT_S, LUNGMOTION_INGEST_TIMEOUT_S), then these options. A bearer token is required to listen beyond loopback. SIGTERM or Ctrl-C stops
    /// it gracefully: running jobs get shutdown_grace_s, then go back to the queue.
    #[command(verbatim_doc_comment)]
    Serve(ServeArgs),
    /// Run simulation jobs from the PostgreSQL queue that `lungmotion serve` processes fill
    /// ([store] postgres_url or LUNGMOTION_POSTGRES_URL), writing the outputs into the shared
    /// data directory (see README, "Running it across machines"). SIGTERM or Ctrl-C stops it:
    /// running jobs get shutdown_grace_s, then go back to the queue.
    #[command(verbatim_doc_comment)]
    Worker(WorkerArgs),
    /// Exchange DICOM with a PACS over DICOMweb: `pacs pull` fetches a CT series (QIDO-RS,
    /// WADO-RS), `pacs push` stores a run's DICOM outputs (STOW-RS), never twice.
    Pacs(cli::pacs::PacsArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // The service logs its requests; the batch commands only what goes wrong.
    if let Command::Serve(args) = cli.command {
        init_logging("info");
        return args.execute();
    }
    if let Command::Worker(args) = cli.command {
        init_logging("info");
        return args.execute();
    }
    init_logging("warn");
    finish(match cli.command {
        Command::Run(args) => args.execute(),
        Command::Demo(args) => args.execute(),
        Command::Ingest(args) => args.execute(),
        Command::Phantom(args) => args.execute(),
        Command::Validate(args) => args.execute(),
        Command::Bench(args) => args.execute(),
        Command::Pacs(args) => args.execute(),
        Command::Serve(_) | Command::Worker(_) => unreachable!("handled above"),
    })
}

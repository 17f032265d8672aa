//! `lungmotion serve`: the HTTP service in the foreground. The options are only gathered
//! here; file, environment and options are merged by [`ServiceConfig::resolve`].

use std::path::PathBuf;
use std::process::ExitCode;

use lungmotion::service::isolation::serve_ingest_child;
use lungmotion::service::worker::work_blocking;
use lungmotion::service::{serve_blocking, IngestIsolation, ServeOverrides, ServiceConfig};

use super::exit::exit_code;

/// Options of `lungmotion serve`.
#[derive(clap::Args)]
pub struct ServeArgs {
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
    /// Connections served at once; further ones wait to be accepted (default 256).
    #[arg(long)]
    max_connections: Option<usize>,
    /// Seconds a client may take to send a request's headers before it is disconnected
    /// (default 10).
    #[arg(long)]
    header_read_timeout_s: Option<f64>,
    /// Seconds a request body may pause before the request is answered 408 (default 30).
    #[arg(long)]
    body_read_timeout_s: Option<f64>,
    /// Internal: ingest one upload as the server's child process (request on stdin, answer
    /// on stdout), so that a reader crashing on a hostile file ends only the child.
    #[arg(long, hide = true)]
    ingest_child: bool,
}

impl ServeArgs {
    /// Serves until SIGTERM or Ctrl-C. Refused settings exit 2 and a failure while serving
    /// exits 1, as for every subcommand ([`super::exit`]).
    pub fn execute(self) -> ExitCode {
        if self.ingest_child {
            return match serve_ingest_child(std::io::stdin().lock(), std::io::stdout().lock()) {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    eprintln!("lungmotion serve --ingest-child: cannot answer the server: {e}");
                    ExitCode::FAILURE
                }
            };
        }
        let env = |name: &str| std::env::var(name).ok();
        let overrides = ServeOverrides {
            listen: self.listen,
            data_dir: self.data_dir,
            workers: self.workers,
            queue_capacity: self.queue_capacity,
            max_connections: self.max_connections,
            header_read_timeout_s: self.header_read_timeout_s,
            body_read_timeout_s: self.body_read_timeout_s,
        };
        let mut settings = match ServiceConfig::resolve(self.config.as_deref(), &env, &overrides) {
            Ok(s) => s,
            Err(e) => {
                eprintln!("lungmotion serve: {e}");
                return exit_code(&e);
            }
        };
        // Uploads are ingested by this very binary in a child process.
        match std::env::current_exe() {
            Ok(program) => settings.ingest_isolation = IngestIsolation::ChildProcess { program },
            Err(e) => tracing::warn!(
                "cannot find this program ({e}); uploads are ingested in the server's process"
            ),
        }
        match serve_blocking(settings) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("lungmotion serve: error: {e}");
                exit_code(&e)
            }
        }
    }
}

/// Options of `lungmotion worker`.
#[derive(clap::Args)]
pub struct WorkerArgs {
    /// The shared data directory of the uploads and outputs (the API processes' own).
    #[arg(long)]
    data_dir: Option<PathBuf>,
    /// Service configuration (TOML): its [store] postgres_url names the database.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Simulations this process runs at once (default: one per core).
    #[arg(long)]
    workers: Option<usize>,
}

impl WorkerArgs {
    /// Takes jobs until SIGTERM or Ctrl-C. Refused settings exit 2 and a failure exits 1.
    pub fn execute(self) -> ExitCode {
        let env = |name: &str| std::env::var(name).ok();
        let overrides = ServeOverrides {
            data_dir: self.data_dir,
            workers: self.workers,
            ..ServeOverrides::default()
        };
        let mut settings = match ServiceConfig::resolve(self.config.as_deref(), &env, &overrides) {
            Ok(s) => s,
            Err(e) => {
                eprintln!("lungmotion worker: {e}");
                return exit_code(&e);
            }
        };
        // A job pulling its CT from the PACS ingests it in a child process, as uploads are.
        if let Ok(program) = std::env::current_exe() {
            settings.ingest_isolation = IngestIsolation::ChildProcess { program };
        }
        match work_blocking(settings) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("lungmotion worker: error: {e}");
                exit_code(&e)
            }
        }
    }
}

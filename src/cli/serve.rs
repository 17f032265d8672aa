//! `lungmotion serve`: the HTTP service in the foreground. The options are only gathered
//! here; file, environment and options are merged by [`ServiceConfig::resolve`].

use std::path::PathBuf;
use std::process::ExitCode;

use lungmotion::service::{serve_blocking, ServeOverrides, ServiceConfig};

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
}

impl ServeArgs {
    /// Serves until SIGTERM or Ctrl-C. Refused settings exit 2 and a failure while serving
    /// exits 1, as for every subcommand ([`super::exit`]).
    pub fn execute(self) -> ExitCode {
        let env = |name: &str| std::env::var(name).ok();
        let overrides = ServeOverrides {
            listen: self.listen,
            data_dir: self.data_dir,
            workers: self.workers,
            queue_capacity: self.queue_capacity,
        };
        let settings = match ServiceConfig::resolve(self.config.as_deref(), &env, &overrides) {
            Ok(s) => s,
            Err(e) => {
                eprintln!("lungmotion serve: {e}");
                return exit_code(&e);
            }
        };
        match serve_blocking(settings) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("lungmotion serve: error: {e}");
                exit_code(&e)
            }
        }
    }
}

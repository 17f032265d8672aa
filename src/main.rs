//! `lungmotion` command line: a thin shell over the library.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

use lungmotion::validation::report::{run_validation, ValidateOptions};

/// Predicts lung motion over a breathing curve with Baudet's parameterised hexahedral
/// mass–spring model.
#[derive(Parser)]
#[command(name = "lungmotion", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Measure the model's accuracy: patch tests against closed forms and composite cases
    /// against CalculiX; writes validation.json and validation.md.
    Validate {
        /// Directory for the reports.
        #[arg(long, default_value = "validation-out")]
        out: PathBuf,
        /// Smaller composite resolutions (cantilever to 4×4×16, L to 8³).
        #[arg(long)]
        quick: bool,
        /// Skip the CalculiX comparisons (no `ccx` needed).
        #[arg(long)]
        no_calculix: bool,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Validate {
            out,
            quick,
            no_calculix,
        } => validate(out, quick, !no_calculix),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("lungmotion: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn validate(out: PathBuf, quick: bool, calculix: bool) -> anyhow::Result<()> {
    let options = ValidateOptions { quick, calculix };
    let report = run_validation(&options, &mut |step| {
        eprintln!("lungmotion: running {step}")
    })?;
    report.write(&out)?;
    println!("{}", report.to_markdown());
    eprintln!(
        "lungmotion: wrote {} and {}",
        out.join("validation.json").display(),
        out.join("validation.md").display()
    );
    Ok(())
}

//! `lungmotion validate`: the accuracy studies (patch tests, composite cases against
//! CalculiX) or, with `--lung`, the breathing model's end-inhale frame against CalculiX.

use std::path::PathBuf;

use anyhow::Context;
use lungmotion::validation::report::{run_validation, ValidateOptions};

use super::prepare_out;

/// Options of `lungmotion validate`.
#[derive(clap::Args)]
pub struct ValidateArgs {
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
}

impl ValidateArgs {
    /// Runs the chosen study and writes its reports.
    pub fn execute(self) -> anyhow::Result<()> {
        if self.lung {
            validate_lung(&self.out)
        } else {
            let options = ValidateOptions {
                quick: self.quick,
                calculix: !self.no_calculix,
            };
            validate(&self.out, &options)
        }
    }
}

/// The accuracy studies: reports written, Markdown printed.
fn validate(out: &std::path::Path, options: &ValidateOptions) -> anyhow::Result<()> {
    prepare_out(out)?;
    let report = run_validation(options, &mut |step| eprintln!("lungmotion: running {step}"))?;
    report
        .write(out)
        .with_context(|| format!("writing the reports into {}", out.display()))?;
    println!("{}", report.to_markdown());
    eprintln!(
        "lungmotion: wrote {} and {}",
        out.join("validation.json").display(),
        out.join("validation.md").display()
    );
    Ok(())
}

/// The end-inhale frame of the CIP lungs against CalculiX: reports written, Markdown printed.
fn validate_lung(out: &std::path::Path) -> anyhow::Result<()> {
    use lungmotion::validation::lung_calculix::{
        compare_end_inhale_with_calculix, LungCalculixSettings,
    };
    prepare_out(out)?;
    eprintln!("lungmotion: end-inhale frame of the CIP lungs against CalculiX (minutes)");
    let report = compare_end_inhale_with_calculix(&LungCalculixSettings::default())?;
    report
        .write(out)
        .with_context(|| format!("writing the reports into {}", out.display()))?;
    println!("{}", report.to_markdown());
    eprintln!(
        "lungmotion: wrote {}",
        out.join("lung_calculix.json").display()
    );
    Ok(())
}

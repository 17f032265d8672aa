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
    /// Skip the pressure–volume curves of the CIP lungs (rest to +2 L per material law, 8 mm;
    /// several minutes; skipped anyway without ../shared/data).
    #[arg(long)]
    no_pressure_volume: bool,
    /// Instead: the breathing model's end-inhale frame (500 mL, CIP lungs at 8 mm; the default
    /// material, then Baudet's springs alone into `springs/`) against CalculiX C3D8 and C3D8I
    /// with NLGEOM (needs ../shared/data; about 3 minutes each); writes lung_calculix.json
    /// and lung_calculix.md (and springs/ likewise).
    #[arg(long, conflicts_with_all = ["quick", "no_calculix", "no_pressure_volume"])]
    lung: bool,
    /// Instead: the model against a 4D-CT: a folder of phase folders (each a DICOM series),
    /// a zip of them, or a folder of one NIfTI/NRRD file per phase; writes report.json,
    /// report.md and overlays/ into --out.
    #[arg(long = "4dct", value_name = "INPUT", conflicts_with_all = ["quick", "no_calculix", "lung"])]
    four_dct: Option<PathBuf>,
    /// With --4dct: the reference phase, by name or 0-based index (default: the phase with
    /// the smallest lung volume, i.e. end-exhale).
    #[arg(long, value_name = "NAME|INDEX", requires = "four_dct")]
    reference_phase: Option<String>,
    /// With --4dct: landmarks, a folder of DIR-Lab .txt files (one per phase, 1-based voxel
    /// indices `x y z` per line) or a CSV in LPS mm (phase,point,x_mm,y_mm,z_mm).
    #[arg(long, value_name = "PATH", requires = "four_dct")]
    landmarks: Option<PathBuf>,
    /// With --4dct: a run configuration (TOML, as `lungmotion run --config`): element size,
    /// material, segmentation, boundary options.
    #[arg(long, value_name = "TOML", requires = "four_dct")]
    config: Option<PathBuf>,
    /// With --4dct: edge of the cubic elements, mm (overrides the configuration's).
    #[arg(long, value_name = "MM", requires = "four_dct")]
    element_size: Option<f64>,
    /// With --4dct: leave out the PNG overlays.
    #[arg(long, requires = "four_dct")]
    no_overlays: bool,
}

impl ValidateArgs {
    /// Runs the chosen study and writes its reports.
    pub fn execute(self) -> anyhow::Result<()> {
        if let Some(input) = &self.four_dct {
            validate_four_dct(input, &self)
        } else if self.lung {
            validate_lung(&self.out)
        } else {
            let options = ValidateOptions {
                quick: self.quick,
                calculix: !self.no_calculix,
                pressure_volume: !self.no_pressure_volume,
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
    use lungmotion::model::Material;
    use lungmotion::validation::lung_calculix::{
        compare_end_inhale_with_calculix, LungCalculixSettings,
    };
    prepare_out(out)?;
    // The run's default material (neo-Hookean, C3D8's hourglass response) against CalculiX's
    // NEO HOOKE, then Baudet's springs alone against St Venant–Kirchhoff, from one command.
    for (material, dir, what) in [
        (
            Material::default(),
            out.to_path_buf(),
            "the default material",
        ),
        (
            Material::LUNG,
            out.join("springs"),
            "Baudet's springs alone",
        ),
    ] {
        eprintln!(
            "lungmotion: end-inhale frame of the CIP lungs against CalculiX, {what} (minutes)"
        );
        let settings = LungCalculixSettings {
            material,
            ..LungCalculixSettings::default()
        };
        let report = compare_end_inhale_with_calculix(&settings)?;
        report
            .write(&dir)
            .with_context(|| format!("writing the reports into {}", dir.display()))?;
        println!("{}", report.to_markdown());
        eprintln!(
            "lungmotion: wrote {}",
            dir.join("lung_calculix.json").display()
        );
    }
    Ok(())
}

/// The model against a 4D-CT: reports written, Markdown printed.
fn validate_four_dct(input: &std::path::Path, args: &ValidateArgs) -> anyhow::Result<()> {
    use lungmotion::run::RunConfig;
    use lungmotion::validation::four_dct::{validate_four_dct, FourDctOptions};
    use lungmotion::validation::landmarks::LandmarkInput;
    let mut config = match &args.config {
        Some(path) => RunConfig::from_toml_file(path)?,
        None => RunConfig::default(),
    };
    if let Some(size) = args.element_size {
        config.element_size_mm = size;
    }
    let options = FourDctOptions {
        reference_phase: args.reference_phase.clone(),
        landmarks: args
            .landmarks
            .as_deref()
            .map(LandmarkInput::detect)
            .transpose()?,
        config,
        overlays: !args.no_overlays,
    };
    prepare_out(&args.out)?;
    let report = validate_four_dct(input, &args.out, &options, &mut |step| {
        eprintln!("lungmotion: {step}")
    })?;
    println!("{}", report.to_markdown());
    eprintln!(
        "lungmotion: wrote {} and {}",
        args.out.join("report.json").display(),
        args.out.join("report.md").display()
    );
    Ok(())
}

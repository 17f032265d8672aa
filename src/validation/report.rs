//! The validation suite as one run: each study's report, written as JSON and markdown.

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use super::composite::{run_composite, CompositeOptions, CompositeReport};
use super::contact::{run_contact_study, ContactReport, DropConfig};
use super::material_laws::{run_material_law_study, MaterialLawReport};
use super::patch::{run_patch_tests, PatchConfig, PatchReport};
use super::pressure_volume::{
    run_pressure_volume_study, PressureVolumeConfig, PressureVolumeReport,
};
use super::stability::{run_stability_study, StabilityConfig, StabilityReport};
use super::sweep::{run_strain_sweeps, SweepConfig, SweepReport};
use crate::durable::write_atomic;
use crate::{IoContext, IoOp, Result};

/// Which studies to run.
#[derive(Debug, Clone, Serialize)]
pub struct ValidateOptions {
    /// Smaller composite resolutions and stability grid (about a minute instead of several).
    pub quick: bool,
    /// Run the CalculiX comparisons (needs `ccx`).
    pub calculix: bool,
    /// Run the pressure–volume study on the CIP lungs (needs the shared data; minutes).
    pub pressure_volume: bool,
}

/// Every study's result.
#[derive(Debug, Clone, Serialize)]
pub struct ValidationReport {
    /// Software version.
    pub version: &'static str,
    /// Options of the run.
    pub options: ValidateOptions,
    /// Single-element patch tests.
    pub patch: PatchReport,
    /// Strain sweeps 0–20 % and bulk ±15 % against the thesis's error curves.
    pub sweep: SweepReport,
    /// The spring and volumetric laws against continuum laws on one cube.
    pub material_laws: MaterialLawReport,
    /// Explicit integrator: automatic time step across materials and sizes, overstep caught.
    pub stability: StabilityReport,
    /// Penalty contact: a block dropped on a plane against Hunt and Crossley's closed form.
    pub contact: ContactReport,
    /// Composite cases against CalculiX (absent when skipped).
    pub composite: Option<CompositeReport>,
    /// The model's pressure–volume curves on the CIP lungs (absent when skipped).
    pub pressure_volume: Option<PressureVolumeReport>,
    /// Why the pressure–volume study was skipped, when it was.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pressure_volume_skipped: Option<String>,
    /// Wall time of the whole suite, seconds.
    pub wall_time_s: f64,
}

/// Runs the suite; `progress` receives one line per study as it starts.
pub fn run_validation(
    options: &ValidateOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<ValidationReport> {
    let start = Instant::now();
    progress("patch tests (single element, closed forms)");
    let patch = run_patch_tests(&PatchConfig::default())?;
    progress("strain sweeps (traction 0–20 %, bulk ±15 %)");
    let sweep = run_strain_sweeps(&SweepConfig::default())?;
    progress(
        "spring and volumetric laws (one cube against neo-Hookean, hyperfoam, Birzle's lung law)",
    );
    let material_laws = run_material_law_study()?;
    progress("stability stress test (automatic time step, 1.5× overstep)");
    let stability = run_stability_study(&if options.quick {
        StabilityConfig::quick()
    } else {
        StabilityConfig::full()
    })?;
    progress("contact (a block dropped on a plane, Hunt–Crossley closed form)");
    let contact = run_contact_study(&DropConfig::default())?;
    let composite = if options.calculix {
        progress("composite cases against CalculiX (cantilever, L)");
        let opts = if options.quick {
            CompositeOptions::quick()
        } else {
            CompositeOptions::full()
        };
        Some(run_composite(&opts)?)
    } else {
        None
    };
    let (pressure_volume, pressure_volume_skipped) = if !options.pressure_volume {
        (
            None,
            Some("not asked for (--no-pressure-volume)".to_string()),
        )
    } else if crate::datasets::cip_chest_ct64().is_none() {
        (
            None,
            Some(format!(
                "the CIP chest CT is absent (set {} to the shared data directory)",
                crate::datasets::SHARED_DATA_ENV
            )),
        )
    } else {
        progress("pressure–volume curves (CIP lungs, 8 mm, rest to +2 L, per material law)");
        let config = PressureVolumeConfig::standard();
        (Some(run_pressure_volume_study(&config)?), None)
    };
    Ok(ValidationReport {
        version: env!("CARGO_PKG_VERSION"),
        options: options.clone(),
        patch,
        sweep,
        material_laws,
        stability,
        contact,
        composite,
        pressure_volume,
        pressure_volume_skipped,
        wall_time_s: start.elapsed().as_secs_f64(),
    })
}

impl ValidationReport {
    /// The report as markdown, one section per study.
    pub fn to_markdown(&self) -> String {
        let mut s = format!(
            "# lungmotion validation report\n\nVersion {}, {} mode, CalculiX {}. Suite wall time {:.1} s.\n\n",
            self.version,
            if self.options.quick { "quick" } else { "full" },
            if self.options.calculix { "on" } else { "off" },
            self.wall_time_s
        );
        for section in [
            self.patch.to_markdown(),
            self.sweep.to_markdown(),
            self.material_laws.to_markdown(),
            self.stability.to_markdown(),
            self.contact.to_markdown(),
        ] {
            s.push_str(&section);
            s.push('\n');
        }
        if let Some(c) = &self.composite {
            s.push_str(&c.to_markdown());
            s.push('\n');
        }
        if let Some(pv) = &self.pressure_volume {
            s.push_str(&pv.to_markdown());
            s.push('\n');
        } else if let Some(why) = &self.pressure_volume_skipped {
            s.push_str(&format!("## Pressure–volume curve\n\nSkipped: {why}.\n\n"));
        }
        s
    }

    /// Writes `validation.json`, `validation.md` and, with the P–V study, its PNG into `dir` (created if needed), each via a
    /// temporary file and a rename so a reader never sees half a report.
    pub fn write(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir).at(IoOp::CreateDir, dir)?;
        let json = serde_json::to_string_pretty(self)
            .map_err(|e| crate::Error::External(format!("serialising the report: {e}")))?;
        write_atomic(&dir.join("validation.json"), json.as_bytes())?;
        if let Some(pv) = &self.pressure_volume {
            pv.write_png(dir)?;
        }
        write_atomic(&dir.join("validation.md"), self.to_markdown().as_bytes())?;
        Ok(())
    }
}

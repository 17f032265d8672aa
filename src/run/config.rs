//! Run configuration: a TOML file (every field optional, unknown fields refused) whose values
//! the command line may override. `lungmotion run --config` documents the format; an empty
//! file is the default run.
//!
//! ```toml
//! element_size_mm = 6.0
//! series = "number:3"                 # a folder with several DICOM series: which to read
//!                                      # (uid:<UID>, number:<N>, description:<text>)
//! diaphragm = "cranio_caudal"          # or "free", or "sliding" (the base slides on a descending dome)
//! sliding = "tangent_plane"            # or "wall_surface": sliding nodes stay on the curved wall
//! [material]
//! youngs_modulus_pa = 390.0
//! poisson_ratio = 0.3
//! density_kg_per_m3 = 700.0
//! spring_law = "linear"               # "cubic" (fitted to neo-Hookean) or { cubic = 3.0 }
//! # volumetric_law = "hyperfoam"      # or "neo_hookean", "lung_birzle": the elements'
//!                                      # hydrostatic response follows that law
//! continuum_correction = "neo_hookean" # or "hyperfoam", "lung_birzle"; "none": the springs'
//!                                      # own; the elements' whole response to homogeneous
//!                                      # deformation follows the law (not beside
//!                                      # volumetric_law)
//! hourglass = "full_integration"       # or "incompatible_modes" (C3D8I), "springs" (Baudet's
//!                                      # own): where bending and twist stiffness comes from
//! [tissue]                             # heterogeneous lung (see `model::tissue`)
//! from_ct = false                      # each element's E and ρ from the CT's Hounsfield units
//! stiffness_exponent = 2.0             # E ∝ (tissue fraction)ⁿ, the median element at E
//! max_stiffness_ratio = 10.0           # clamp, either way
//! stiffness_step = 0.05                # ratios rounded to 5 % steps (one class per step)
//! target_stiffness_ratio = 1.0         # the run's target this many times E (needs a target)
//! # hu_to_youngs_modulus_pa = [[-950, 100], [-850, 390], [-500, 3000]]   # instead of the law
//! [trace]
//! reference = "change_from_scan"       # or { absolute = { scanned_volume_ml = 2800 } }
//! # window_s = [10.0, 40.0]            # keep only these seconds (e.g. the tidal breaths)
//! [motion]
//! driver = { kind = "volume" }         # or { kind = "compliance", compliance_ml_per_pa = 2.0 }
//! # driver = { kind = "compliance", pressure_volume = [[0, 0], [500, 900], [1000, 1500]] }
//!                                      # a non-linear compliance: rows [pressure Pa, volume mL],
//!                                      # distending pressure and volume change from the scan,
//!                                      # both rising, through [0, 0], interpolated linearly
//! instants = { kind = "phases", count = 10 }   # every_sample | every_kth k | frame_rate hz
//! interpolation_tolerance_mm = 0.1
//! solve_every_frame = false
//! rib_cage_share = 0.333               # share of each breath the chest wall makes (0: rigid)
//! dome_flattening = 0.0                # diaphragm = "sliding": how much less the rim descends
//! mediastinum = "sliding"              # or "contact": the mediastinal face may leave the heart
//! # [motion.dynamic]                 # optional: bellows law, explicit dynamics (hysteresis)
//! # resistance_pa_s_per_ml = 0.05
//! # inertance_pa_s2_per_ml = 0.001
//! # voigt_damping_ratio = 0.1
//! # surface_damping_ratio = 0.01    # springs of surface elements (default: as the interior)
//! [outputs]
//! metaimage = false                    # frames/<k>/displacement.mha beside the NIfTI
//! mesh_vtu = false                     # frames/<k>/mesh.vtu (deformed mesh for ParaView)
//! ingest_files = true                  # ingest/: lung mask, groups, mesh, ingest.json
//! quicklooks = true                    # breathing-curve and end-inhale PNGs
//! field_grid = "lung_box"              # or "ct": the fields on the whole CT grid
//! registration = false                 # frames/<k>/registration.dcm: DICOM deformable REG
//! registration_spacing_mm = 3.0        # its grid spacing over the lungs (0.5–20 mm)
//! virtual_ct = "off"                   # "nifti", "dicom" or "both": the CT at each frame
//! outside_lung_decay_mm = 15.0         # how far the motion reaches beyond the lungs
//! [budget]                             # what a run may spend before it is stopped
//! time_s = 1800.0                      # wall clock, reading the CT to summary.json (1 s – 7 days)
//! max_equilibria = 10000               # equilibrium solves: key volumes, their load-step
//!                                      # halvings and per-frame solves (1 – 1 000 000)
//! ```

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::breathing::{OutputInstants, TraceOptions};
use crate::formats::dicom::{DicomReadOptions, SeriesChoice};
use crate::ingest::lung_model::{DiaphragmMotion, SlidingMode, DEFAULT_ELEMENT_SIZE_MM};
use crate::model::tissue::TissueSettings;
use crate::model::Material;
use crate::motion::DriverKind;
use crate::outputs::displacement_field::FieldGrid;
use crate::outputs::radiotherapy::virtual_ct::VirtualCtOutput;
use crate::{Error, IoContext, IoOp, Result};

/// Largest configuration file read, bytes (a real one is well under 2 kB).
const MAX_CONFIG_BYTES: u64 = 1 << 20;
/// How a run configuration names itself in errors.
const SETTINGS: &str = "configuration";

/// Everything a breathing run can be told besides its inputs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RunConfig {
    /// Edge of the cubic elements, mm (2–16).
    pub element_size_mm: f64,
    /// The DICOM series to read when the CT input holds several; `None`: the only CT
    /// series that is not a scout.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub series: Option<SeriesChoice>,
    /// How the diaphragmatic face moves.
    pub diaphragm: DiaphragmMotion,
    /// How the sliding faces (costal, mediastinal, apex) follow the wall.
    pub sliding: SlidingMode,
    /// Lung tissue.
    pub material: Material,
    /// How the tissue varies from element to element (CT density, a stiffer target).
    pub tissue: TissueSettings,
    /// How the trace file is read.
    pub trace: TraceOptions,
    /// Driver, output instants and solver accuracy.
    pub motion: MotionConfig,
    /// Which optional files are written.
    pub outputs: OutputConfig,
    /// What the run may spend before it is stopped.
    pub budget: BudgetConfig,
}

/// Default wall-clock budget of a run, s: half an hour, well beyond a clinical run (seconds to
/// a minute) and short enough that a run that cannot finish is not left grinding for hours.
pub const DEFAULT_TIME_BUDGET_S: f64 = 1800.0;
/// Largest wall-clock budget accepted, s (a week): beyond it a value is a unit mistake.
pub const MAX_TIME_BUDGET_S: f64 = 7.0 * 24.0 * 3600.0;
/// Default budget of equilibrium solves: a cycle interpolated from key volumes needs only those, a trace solved
/// frame by frame at every sample of a few minutes a few thousand.
pub const DEFAULT_MAX_EQUILIBRIA: i64 = 10_000;
/// Largest equilibrium budget accepted.
pub const MAX_EQUILIBRIA_LIMIT: i64 = 1_000_000;

/// What a run may spend: wall-clock time and equilibrium solves. Every run has both; a run
/// that reaches one stops (inside a solve, within about a second) with
/// [`Error::BudgetExceeded`], leaving no output.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BudgetConfig {
    /// Wall-clock time of the whole run, reading the CT to `summary.json`, s.
    pub time_s: f64,
    /// Equilibrium solves (key volumes, their load-step halvings, per-frame solves).
    pub max_equilibria: i64,
}

impl Default for BudgetConfig {
    fn default() -> Self {
        BudgetConfig {
            time_s: DEFAULT_TIME_BUDGET_S,
            max_equilibria: DEFAULT_MAX_EQUILIBRIA,
        }
    }
}

impl BudgetConfig {
    /// Why `time_s` cannot be a time budget, if it cannot (shared by the configuration, the
    /// command line and HTTP requests).
    pub fn time_problem(time_s: f64) -> Option<String> {
        if time_s.is_nan() {
            Some("NaN is not a number of seconds".into())
        } else if time_s <= 0.0 {
            Some(format!(
                "{time_s} s would stop the run before it starts; every run has a time budget \
                 (leave it out for the default {DEFAULT_TIME_BUDGET_S} s)"
            ))
        } else if time_s < 1.0 {
            Some(format!("{time_s} s is below the 1 s minimum"))
        } else if time_s > MAX_TIME_BUDGET_S {
            Some(format!(
                "{time_s} s is beyond the {MAX_TIME_BUDGET_S} s (7 days) maximum"
            ))
        } else {
            None
        }
    }

    /// Why `count` cannot be an equilibrium budget, if it cannot.
    pub fn equilibria_problem(count: i64) -> Option<String> {
        if count < 1 {
            Some(format!(
                "{count} allows no equilibrium solve; at least 1 (leave it out for the default \
                 {DEFAULT_MAX_EQUILIBRIA})"
            ))
        } else if count > MAX_EQUILIBRIA_LIMIT {
            Some(format!(
                "{count} is beyond the {MAX_EQUILIBRIA_LIMIT} maximum"
            ))
        } else {
            None
        }
    }
}

/// Driver, output instants and accuracy of a run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MotionConfig {
    /// Volume (default) or compliance driver.
    pub driver: DriverKind,
    /// Which instants get a displacement field.
    pub instants: OutputInstants,
    /// Largest interpolation error allowed against direct solves, mm.
    pub interpolation_tolerance_mm: f64,
    /// Solve every frame instead of interpolating between key volumes.
    pub solve_every_frame: bool,
    /// Volume driver tolerance as a fraction of the tidal volume.
    pub volume_tolerance_fraction: f64,
    /// Share of every volume change the chest wall makes by moving outward (0: a rigid
    /// wall, all of it from the diaphragm).
    pub rib_cage_share: f64,
    /// With `diaphragm = "sliding"`: how much less the dome's rim descends than its top
    /// (0: the dome translates).
    pub dome_flattening: f64,
    /// How the mediastinal face meets the heart: held on the wall, or one-sided contact.
    pub mediastinum: crate::motion::MediastinumContact,
    /// Dynamic mode (bellows law, explicit integration) instead of quasi-static frames.
    pub dynamic: Option<DynamicConfig>,
}

/// The bellows law P = V/C + R·dV/dt + I·d²V/dt² of the optional dynamic mode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DynamicConfig {
    /// Compliance C, mL/Pa; absent: measured on the model at the trace's largest volume.
    pub compliance_ml_per_pa: Option<f64>,
    /// Airway resistance R, Pa·s/mL (physiological ≈ 0.2; this model's C is ≈ 3.5× the
    /// physiological one, so R ≈ 0.05 gives a physiological time constant RC).
    pub resistance_pa_s_per_ml: f64,
    /// Inertance I, Pa·s²/mL.
    pub inertance_pa_s2_per_ml: f64,
    /// Voigt damping of every spring, fraction of critical.
    pub voigt_damping_ratio: f64,
    /// Voigt damping of the springs of surface elements, if it differs from the interior's.
    pub surface_damping_ratio: Option<f64>,
}

impl Default for DynamicConfig {
    fn default() -> Self {
        DynamicConfig {
            compliance_ml_per_pa: None,
            resistance_pa_s_per_ml: 0.05,
            inertance_pa_s2_per_ml: 0.001,
            voigt_damping_ratio: 0.1,
            surface_damping_ratio: None,
        }
    }
}

impl DynamicConfig {
    /// The integrator settings.
    pub fn settings(&self) -> crate::motion::dynamic::DynamicSettings {
        crate::motion::dynamic::DynamicSettings {
            compliance_ml_per_pa: self.compliance_ml_per_pa,
            resistance_pa_s_per_ml: self.resistance_pa_s_per_ml,
            inertance_pa_s2_per_ml: self.inertance_pa_s2_per_ml,
            voigt_damping_ratio: self.voigt_damping_ratio,
            surface_damping_ratio: self.surface_damping_ratio,
            ..crate::motion::dynamic::DynamicSettings::default()
        }
    }
}

/// Optional outputs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OutputConfig {
    /// Also write each frame's field as MetaImage (`displacement.mha`).
    pub metaimage: bool,
    /// Also write each frame's deformed mesh (`mesh.vtu`).
    pub mesh_vtu: bool,
    /// Write the ingest results (`ingest/`).
    pub ingest_files: bool,
    /// Write the PNG quick looks.
    pub quicklooks: bool,
    /// The displacement fields' grid: the box around the lungs (default) or the whole CT.
    pub field_grid: FieldGrid,
    /// Write each frame's DICOM Deformable Spatial Registration (`registration.dcm`).
    pub registration: bool,
    /// Spacing of the registration's vector grid over the lungs, mm.
    pub registration_spacing_mm: f64,
    /// The virtual 4D-CT (the CT at each frame, MIP, AIP) as NIfTI, DICOM, both, or not.
    pub virtual_ct: VirtualCtOutput,
    /// Decay length (Gaussian σ) of the motion outside the lungs under the virtual CT, mm.
    pub outside_lung_decay_mm: f64,
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            element_size_mm: DEFAULT_ELEMENT_SIZE_MM,
            series: None,
            diaphragm: DiaphragmMotion::default(),
            sliding: SlidingMode::default(),
            material: Material::default(),
            tissue: TissueSettings::default(),
            trace: TraceOptions::default(),
            motion: MotionConfig::default(),
            outputs: OutputConfig::default(),
            budget: BudgetConfig::default(),
        }
    }
}

impl Default for MotionConfig {
    fn default() -> Self {
        let m = crate::motion::MotionSettings::default();
        MotionConfig {
            driver: m.driver,
            instants: m.instants,
            interpolation_tolerance_mm: m.interpolation_tolerance_mm,
            solve_every_frame: m.solve_every_frame,
            volume_tolerance_fraction: m.volume_tolerance_fraction,
            // The run's default is physiological (the library's, for any scene, is rigid).
            rib_cage_share: crate::motion::PHYSIOLOGICAL_RIB_CAGE_SHARE,
            dome_flattening: 0.0,
            mediastinum: crate::motion::MediastinumContact::Sliding,
            dynamic: None,
        }
    }
}

impl Default for OutputConfig {
    fn default() -> Self {
        OutputConfig {
            metaimage: false,
            mesh_vtu: false,
            ingest_files: true,
            quicklooks: true,
            field_grid: FieldGrid::default(),
            registration: false,
            registration_spacing_mm:
                crate::outputs::radiotherapy::registration::DEFAULT_REGISTRATION_SPACING_MM,
            virtual_ct: VirtualCtOutput::Off,
            outside_lung_decay_mm: crate::outputs::radiotherapy::ct_motion::DEFAULT_DECAY_LENGTH_MM,
        }
    }
}

impl RunConfig {
    /// How the CT is read when it is DICOM: the configured series choice.
    pub fn dicom_read_options(&self) -> DicomReadOptions {
        DicomReadOptions {
            series: self.series.clone(),
            ..DicomReadOptions::default()
        }
    }

    /// Reads a TOML configuration; the error names the file and the offending key.
    pub fn from_toml_file(path: &Path) -> Result<Self> {
        let meta = std::fs::metadata(path).at(IoOp::Read, path)?;
        if meta.len() > MAX_CONFIG_BYTES {
            return Err(Error::Config {
                settings: SETTINGS,
                file: Some(path.to_path_buf()),
                key: None,
                reason: format!(
                    "{} bytes is not a configuration file (limit {MAX_CONFIG_BYTES})",
                    meta.len()
                ),
            });
        }
        let text = std::fs::read_to_string(path).at(IoOp::Read, path)?;
        Self::from_toml(&text).map_err(|e| match e {
            Error::Config {
                settings,
                key,
                reason,
                ..
            } => Error::Config {
                settings,
                file: Some(path.to_path_buf()),
                key,
                reason,
            },
            // A refused material or dynamic setting, named by its own message.
            other => Error::Config {
                settings: SETTINGS,
                file: Some(path.to_path_buf()),
                key: None,
                reason: other.to_string(),
            },
        })
    }

    /// Parses TOML text and validates it.
    pub fn from_toml(text: &str) -> Result<Self> {
        let config: RunConfig = toml::from_str(text).map_err(|e| {
            let (key, reason) = super::toml_key::describe(text, &e);
            Error::Config {
                settings: SETTINGS,
                file: None,
                key,
                reason,
            }
        })?;
        config.validate()?;
        Ok(config)
    }

    /// What the ingest of a scan read with this configuration depends on, as one text: the
    /// ingest settings and the DICOM read options (the series choice). Configurations with
    /// the same text ingest a scan alike; the service keys its kept and stored ingests by it.
    pub fn ingest_identity(&self) -> String {
        format!(
            "{:?} {:?}",
            self.ingest_settings(),
            self.dicom_read_options()
        )
    }

    /// The ingest settings these options imply (element size, material, diaphragm, sliding).
    pub fn ingest_settings(&self) -> crate::ingest::pipeline::IngestSettings {
        crate::ingest::pipeline::IngestSettings {
            model: crate::ingest::lung_model::LungModelSettings {
                element_size_mm: self.element_size_mm,
                material: self.material,
                diaphragm: self.diaphragm,
                sliding: self.sliding,
                ..Default::default()
            },
            ..Default::default()
        }
    }

    /// Refuses values no run can use, naming the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, reason: String| {
            Err(Error::Config {
                settings: SETTINGS,
                file: None,
                key: Some(key.to_string()),
                reason,
            })
        };
        let h = self.element_size_mm;
        if !(h.is_finite() && (2.0..=16.0).contains(&h)) {
            return bad("element_size_mm", format!("{h} mm is not within 2–16 mm"));
        }
        if let Some(reason) = BudgetConfig::time_problem(self.budget.time_s) {
            return bad("budget.time_s", reason);
        }
        if let Some(reason) = BudgetConfig::equilibria_problem(self.budget.max_equilibria) {
            return bad("budget.max_equilibria", reason);
        }
        self.material.validate()?;
        if let Some((key, reason)) = self.tissue.problem() {
            return bad(key, reason);
        }
        if let Err(e) = crate::outputs::radiotherapy::registration::check_spacing(
            self.outputs.registration_spacing_mm,
        ) {
            return bad("outputs.registration_spacing_mm", e.to_string());
        }
        let decay = self.outputs.outside_lung_decay_mm;
        if !(decay.is_finite() && (1.0..=500.0).contains(&decay)) {
            return bad(
                "outputs.outside_lung_decay_mm",
                format!("{decay} mm is not within 1–500 mm"),
            );
        }
        let m = &self.motion;
        if !(m.interpolation_tolerance_mm.is_finite() && m.interpolation_tolerance_mm > 0.0) {
            return bad(
                "motion.interpolation_tolerance_mm",
                format!("{} mm must be positive", m.interpolation_tolerance_mm),
            );
        }
        let f = m.volume_tolerance_fraction;
        if !(f.is_finite() && f > 0.0 && f <= 0.1) {
            return bad(
                "motion.volume_tolerance_fraction",
                format!("{f} must be in (0, 0.1]"),
            );
        }
        if crate::motion::chest_wall::check_rib_cage_share(m.rib_cage_share).is_err() {
            return bad(
                "motion.rib_cage_share",
                format!(
                    "{} is not a fraction of the tidal volume within 0 (a rigid chest wall) … {}",
                    m.rib_cage_share,
                    crate::motion::chest_wall::MAX_RIB_CAGE_SHARE
                ),
            );
        }
        if self.diaphragm == DiaphragmMotion::Sliding && m.driver != DriverKind::Volume {
            return bad(
                "motion.driver",
                "the compliance driver sets the pressure, but with diaphragm = \"sliding\" the \
                 walls make the volume: use { kind = \"volume\" }"
                    .to_string(),
            );
        }
        if let Err(e) = crate::motion::diaphragm::check_dome_flattening(m.dome_flattening) {
            return bad("motion.dome_flattening", e.to_string());
        }
        if let Some((key, reason)) = m.driver.problem() {
            return bad(key, reason);
        }
        if let Some(d) = &m.dynamic {
            d.settings().validate()?;
            if self.diaphragm == DiaphragmMotion::Sliding {
                return bad(
                    "diaphragm",
                    "\"sliding\" works with the quasi-static motion only: the dynamic bellows \
                     drive the lungs with pressure, and with a sliding diaphragm the walls make \
                     the volume; use \"cranio_caudal\" or drop [motion.dynamic]"
                        .to_string(),
                );
            }
        }
        if let crate::breathing::VolumeReference::Absolute { scanned_volume_ml } =
            self.trace.reference
        {
            if !(scanned_volume_ml.is_finite() && scanned_volume_ml > 0.0) {
                return bad(
                    "trace.reference.absolute.scanned_volume_ml",
                    format!("{scanned_volume_ml} mL must be positive"),
                );
            }
        }
        Ok(())
    }

    /// How the walls move with the breath.
    pub fn wall_motion(&self) -> crate::motion::WallMotion {
        crate::motion::WallMotion {
            rib_cage_share: self.motion.rib_cage_share,
            dome_flattening: self.motion.dome_flattening,
            mediastinum: self.motion.mediastinum,
        }
    }

    /// The motion settings this configuration asks for.
    pub fn motion_settings(&self) -> crate::motion::MotionSettings {
        let m = &self.motion;
        crate::motion::MotionSettings {
            driver: m.driver.clone(),
            instants: m.instants,
            interpolation_tolerance_mm: m.interpolation_tolerance_mm,
            solve_every_frame: m.solve_every_frame,
            volume_tolerance_fraction: m.volume_tolerance_fraction,
            rib_cage_share: m.rib_cage_share,
            ..crate::motion::MotionSettings::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_file_is_the_default_and_the_doc_example_parses() {
        assert_eq!(RunConfig::from_toml("").unwrap(), RunConfig::default());
        let doc = include_str!("config.rs")
            .lines()
            .skip_while(|l| !l.starts_with("//! ```toml"))
            .skip(1)
            .take_while(|l| !l.starts_with("//! ```"))
            .map(|l| l.trim_start_matches("//!").trim_start())
            .collect::<Vec<_>>()
            .join("\n");
        let c = RunConfig::from_toml(&doc).unwrap();
        assert_eq!(c.motion.instants, OutputInstants::Phases { count: 10 });
        let c = RunConfig::from_toml(
            "element_size_mm = 8\n[motion]\ndriver = { kind = \"compliance\", \
             compliance_ml_per_pa = 2.0 }\ninstants = { kind = \"frame_rate\", hz = 5.0 }\n\
             [trace]\nreference = { absolute = { scanned_volume_ml = 2800.0 } }",
        )
        .unwrap();
        assert_eq!(c.element_size_mm, 8.0);
        assert_eq!(c.motion.instants, OutputInstants::FrameRate { hz: 5.0 });
        assert!(matches!(
            c.motion.driver,
            DriverKind::Compliance {
                compliance_ml_per_pa: Some(_),
                pressure_volume: None,
            }
        ));
        let c = RunConfig::from_toml(
            "[material]\nspring_law = { cubic = 2.5 }\nvolumetric_law = \"lung_birzle\"",
        )
        .unwrap();
        assert_eq!(c.material.spring_law, crate::model::SpringLaw::Cubic(2.5));
        assert_eq!(
            c.material.volumetric_law,
            Some(crate::model::ContinuumLaw::LungBirzle)
        );
        let c = RunConfig::from_toml("[material]\ncontinuum_correction = \"neo_hookean\"").unwrap();
        assert_eq!(
            c.material.continuum_correction,
            Some(crate::model::ContinuumLaw::NeoHookean)
        );
        let c = RunConfig::from_toml("[material]\nspring_law = \"cubic\"").unwrap();
        assert_eq!(
            c.material.spring_law,
            crate::model::SpringLaw::CubicNeoHookean
        );
    }

    #[test]
    fn the_continuum_correction_is_read_written_and_kept_apart_from_a_volumetric_law() {
        use crate::model::ContinuumLaw;
        let correction = |toml: &str| {
            RunConfig::from_toml(toml)
                .unwrap()
                .material
                .continuum_correction
        };
        assert_eq!(correction(""), Some(ContinuumLaw::NeoHookean));
        assert_eq!(
            correction("[material]\npoisson_ratio = 0.4"),
            Some(ContinuumLaw::NeoHookean)
        );
        assert_eq!(
            correction("[material]\ncontinuum_correction = \"neo_hookean\""),
            Some(ContinuumLaw::NeoHookean)
        );
        assert_eq!(
            correction("[material]\ncontinuum_correction = \"none\""),
            None
        );
        assert_eq!(
            correction("[material]\nvolumetric_law = \"hyperfoam\""),
            None
        );
        assert_eq!(
            correction("[material]\ncontinuum_correction = \"hyperfoam\""),
            Some(ContinuumLaw::Hyperfoam)
        );
        // JSON (the API): null is the springs alone, and writing then reading keeps "none".
        let m: Material = serde_json::from_str(r#"{"continuum_correction": null}"#).unwrap();
        assert_eq!(m.continuum_correction, None);
        let m: Material = serde_json::from_str("{}").unwrap();
        assert_eq!(m, Material::default());
        let springs = Material::LUNG;
        let text = serde_json::to_string(&springs).unwrap();
        assert!(text.contains(r#""continuum_correction":"none""#), "{text}");
        assert_eq!(serde_json::from_str::<Material>(&text).unwrap(), springs);
        let corrected = serde_json::to_string(&Material::LUNG_CORRECTED).unwrap();
        assert_eq!(
            serde_json::from_str::<Material>(&corrected).unwrap(),
            Material::LUNG_CORRECTED
        );
        let hourglass = |text: &str| RunConfig::from_toml(text).unwrap().material.hourglass;
        use crate::model::HourglassLaw;
        assert_eq!(hourglass(""), HourglassLaw::FullIntegration);
        assert_eq!(
            hourglass("[material]\nhourglass = \"springs\""),
            HourglassLaw::Springs
        );
        assert_eq!(
            hourglass("[material]\nhourglass = \"incompatible_modes\""),
            HourglassLaw::IncompatibleModes
        );
        let unknown = serde_json::from_str::<Material>(r#"{"youngs_modulus": 1}"#).unwrap_err();
        assert!(unknown.to_string().contains("youngs_modulus"), "{unknown}");
    }

    #[test]
    fn a_pressure_volume_table_is_read_and_bad_tables_are_refused_with_key_value_and_reason() {
        let c = RunConfig::from_toml(
            "[motion]\ndriver = { kind = \"compliance\", pressure_volume = [[-50, -100], [0, 0], \
             [500, 900.5], [1000, 1500]] }",
        )
        .unwrap();
        let DriverKind::Compliance {
            compliance_ml_per_pa: None,
            pressure_volume: Some(table),
        } = &c.motion.driver
        else {
            panic!("{:?}", c.motion.driver);
        };
        assert_eq!(table.0[2], [500.0, 900.5]);
        assert_eq!(c.motion_settings().driver, c.motion.driver);
        let err = |t: &str| {
            RunConfig::from_toml(&format!(
                "[motion]\ndriver = {{ kind = \"compliance\", {t} }}"
            ))
            .unwrap_err()
            .to_string()
        };
        let key = "motion.driver.pressure_volume";
        for (table, value, reason) in [
            (
                "[[0, 0], [100, 300], [200, 250]]",
                "row 3 [200, 250]",
                "volume must rise",
            ),
            (
                "[[0, 0], [200, 300], [100, 400]]",
                "row 3 [100, 400]",
                "rows go by rising",
            ),
            ("[[0, 0], [100, nan]]", "row 2 [100, NaN]", "finite"),
            ("[[0, 0], [inf, 100]]", "row 2 [inf, 100]", "finite"),
            ("[[0, 0]]", "1 row(s)", "at least 2"),
            ("[]", "0 row(s)", "at least 2"),
            ("[[10, 0], [100, 300]]", "gives 10 Pa", "[0, 0]"),
            ("[[0, 0], [30000, 300]]", "30000 Pa", "unit mistake"),
        ] {
            let e = err(&format!("pressure_volume = {table}"));
            assert!(
                e.contains(key) && e.contains(value) && e.contains(reason),
                "{table}: {e}"
            );
        }
        let both = err("compliance_ml_per_pa = 2.0, pressure_volume = [[0, 0], [1, 2]]");
        assert!(
            both.contains(key) && both.contains("= 2") && both.contains("give one"),
            "{both}"
        );
        let shape = err("pressure_volume = [[0, 0, 1], [1, 2, 3]]");
        assert!(
            shape.contains("pressure_volume row 1 [0.0, 0.0, 1.0] has 3 value(s)"),
            "{shape}"
        );
        let typo = err("pressure_volum = [[0, 0], [1, 2]]");
        assert!(typo.contains("pressure_volum"), "{typo}");
    }

    #[test]
    fn bad_values_and_unknown_keys_are_named() {
        let err = |t: &str| RunConfig::from_toml(t).unwrap_err().to_string();
        assert!(err("element_size_mm = 40").contains("element_size_mm"));
        assert!(err("elemnt_size_mm = 4").contains("elemnt_size_mm"));
        assert!(err("[material]\npoisson_ratio = 0.5").contains("Poisson"));
        let cubic = err("[material]\nspring_law = { cubic = -1.0 }");
        assert!(
            cubic.contains("cubic ratio") && cubic.contains("-1"),
            "{cubic}"
        );
        let name = err("[material]\nspring_law = \"quadratic\"");
        assert!(
            name.contains("quadratic") && name.contains("cubic"),
            "{name}"
        );
        let key = err("[material]\nspring_law = { quartic = 1.0 }");
        assert!(key.contains("quartic"), "{key}");
        let law = err("[material]\nvolumetric_law = \"ogden\"");
        assert!(law.contains("ogden") && law.contains("hyperfoam"), "{law}");
        let law = err("[material]\ncontinuum_correction = \"mooney\"");
        assert!(
            law.contains("mooney")
                && law.contains("neo_hookean")
                && law.contains("material.continuum_correction: ")
                && law.contains("(line 2)"),
            "{law}"
        );
        let both = err(
            "[material]\ncontinuum_correction = \"neo_hookean\"\nvolumetric_law = \"hyperfoam\"",
        );
        assert!(
            both.contains("continuum_correction") && both.contains("volumetric_law"),
            "{both}"
        );
        assert!(err("[motion]\ninterpolation_tolerance_mm = -1").contains("interpolation"));
        let spacing = err("[outputs]\nregistration_spacing_mm = 0.1");
        assert!(
            spacing.contains("outputs.registration_spacing_mm") && spacing.contains("0.1 mm"),
            "{spacing}"
        );
        let flag = err("[outputs]\nregistration = \"yes\"");
        assert!(flag.contains("expected a boolean"), "{flag}");
        assert!(err("[motion]\ninstants = { kind = \"sometimes\" }").contains("sometimes"));
        assert!(
            err("element_size_mm = \"big\"").contains("element_size_mm")
                || err("element_size_mm = \"big\"").contains("invalid type")
        );
    }
}

//! `lungmotion run` and `lungmotion demo`: both resolve to one breathing run (inputs,
//! settings, output directory), run it with a progress display and print its summary.

use std::path::PathBuf;

use lungmotion::breathing::BreathingTrace;
use lungmotion::outputs::radiotherapy::virtual_ct::VirtualCtOutput;
use lungmotion::pacs::DicomWebAddress;
use lungmotion::run::demo::{demo_config, demo_inputs, sample_volumes_dir};
use lungmotion::run::{Overwrite, RunConfig, RunInputs};

use super::interrupt::Interrupt;
use super::progress::ProgressDisplay;

/// The `--overwrite` flag as the library's choice.
fn overwrite_of(flag: bool) -> Overwrite {
    if flag {
        Overwrite::AnyRun
    } else {
        Overwrite::SameCtOnly
    }
}

/// Options of `lungmotion run`.
#[derive(clap::Args)]
pub struct RunArgs {
    /// The CT: a DICOM directory, a zip of one DICOM series, a NIfTI (.nii, .nii.gz) or a
    /// NRRD file (told apart by content), or a series on a PACS:
    /// dicomweb://HOST:PORT/ROOT/studies/STUDY_UID[/series/SERIES_UID] (see `pacs pull`).
    #[arg(long)]
    ct: PathBuf,
    /// After a successful run, store its DICOM outputs on this DICOMweb server
    /// (dicomweb://HOST:PORT/ROOT), skipping the instances it already holds.
    #[arg(long, value_name = "DICOMWEB_ROOT")]
    push: Option<String>,
    /// The breathing trace (CSV or JSON, see above).
    #[arg(long)]
    trace: PathBuf,
    /// Output directory: new, empty, or an earlier run of the same CT, which is replaced on
    /// success (a run of another CT only with --overwrite; a directory that is not a
    /// lungmotion run never).
    #[arg(long)]
    out: PathBuf,
    /// Replace an earlier run in --out even if it was made from another CT.
    #[arg(long)]
    overwrite: bool,
    /// Edge of the cubic elements in millimetres (2–16; default 6, or the config's).
    #[arg(long)]
    element_size: Option<f64>,
    /// The DICOM series to read when the CT folder or zip holds several: uid:<UID>,
    /// number:<N>, description:<text>, or the bare value (default: the only CT series that
    /// is not a scout; or the config's `series`).
    #[arg(long)]
    series: Option<lungmotion::formats::dicom::SeriesChoice>,
    /// TOML settings: material, driver, output instants, trace units, optional outputs.
    /// The format is documented in the README; command-line options win.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Keep only the trace's samples from START to END seconds (`START:END`), e.g. the tidal
    /// breaths of a recording with vital-capacity manoeuvres (the config's `[trace] window_s`).
    #[arg(long, value_name = "START:END", value_parser = parse_window)]
    trace_window: Option<[f64; 2]>,
    /// Points to follow (e.g. a tumour centre): CSV with the header name,x_mm,y_mm,z_mm, in
    /// LPS millimetres (DICOM patient coordinates, as a planning system shows them).
    #[arg(long)]
    points: Option<PathBuf>,
    /// The treatment target to follow (its mask per frame, ITV, motion per axis, RTSTRUCT):
    /// <mask.nii.gz|.nrrd>[:label=<n>] on the CT's grid, <rtstruct.dcm>:<ROI name>, or
    /// point:<x>,<y>,<z>:r=<mm> (LPS millimetres).
    #[arg(long, value_name = "SPEC")]
    target: Option<lungmotion::outputs::radiotherapy::target::TargetSpec>,
    /// Also write each frame as MetaImage (displacement.mha).
    #[arg(long)]
    mha: bool,
    /// Also write each frame's deformed mesh (mesh.vtu, for ParaView).
    #[arg(long)]
    vtu: bool,
    /// Also write each frame's DICOM Deformable Spatial Registration
    /// (frames/<k>/registration.dcm; the config's `[outputs] registration`).
    #[arg(long)]
    registration: bool,
    /// Spacing of the registrations' vector grid over the lungs, mm (0.5–20, default 3);
    /// implies --registration.
    #[arg(long, value_name = "MM")]
    registration_spacing: Option<f64>,
    /// The virtual 4D-CT: the CT at each frame with its MIP and AIP, as `nifti`, `dicom`
    /// (CT series in the planning CT's study), `both`, or `off` (default, or the config's
    /// `[outputs] virtual_ct`).
    #[arg(long, value_name = "off|nifti|dicom|both")]
    virtual_ct: Option<VirtualCtOutput>,
    /// Share of each breath the chest wall makes by moving out (0 – 0.8; 0 a rigid wall, the
    /// diaphragm doing all of it; default 1/3, physiological in supine quiet breathing, or the
    /// config's `[motion] rib_cage_share`).
    #[arg(long, value_name = "FRACTION", value_parser = parse_rib_cage_share, allow_negative_numbers = true)]
    rib_cage_share: Option<f64>,
    /// How the costal, mediastinal and apex nodes follow the wall: `tangent-plane` (each on
    /// the plane tangent to the wall at rest; the default, or the config's `sliding`) or
    /// `wall-surface` (on the curved wall itself, at their rest distance from it).
    #[arg(long, value_name = "tangent-plane|wall-surface", value_parser = parse_sliding)]
    sliding: Option<lungmotion::ingest::lung_model::SlidingMode>,
    /// How the lung's base follows the diaphragm: `cranio-caudal` (each node on a vertical
    /// line, a piston; the default, or the config's `diaphragm`), `sliding` (on a dome that
    /// descends and flattens with the breath) or `free`.
    #[arg(long, value_name = "cranio-caudal|sliding|free", value_parser = parse_diaphragm)]
    diaphragm: Option<lungmotion::ingest::lung_model::DiaphragmMotion>,
    /// How the lungs' mediastinal face meets the heart: `sliding` (held on the wall; the
    /// default, or the config's `[motion] mediastinum`) or `contact` (one-sided: it may slide
    /// along the heart or leave it, never enter it).
    #[arg(long, value_name = "sliding|contact", value_parser = parse_mediastinum)]
    mediastinum: Option<lungmotion::motion::MediastinumContact>,
    /// Each spring's law T = λ₂·d + λ₁·d³: `linear` (Baudet), `cubic` (λ₁/λ₂ fitted to
    /// compressible neo-Hookean at the material's ν) or `cubic:<λ₁/λ₂>` (default linear, or the
    /// config's `[material] spring_law`).
    #[arg(long, value_name = "linear|cubic|cubic:C", allow_hyphen_values = true)]
    spring_law: Option<lungmotion::model::SpringLaw>,
    /// Corner forces that make each element's response to any homogeneous deformation
    /// (deviatoric and hydrostatic) follow a continuum law with the material's E and ν:
    /// `neo-hookean` (CalculiX `NEO HOOKE`), `hyperfoam`, `lung-birzle` or `none` (default
    /// neo-hookean, or the config's `[material] continuum_correction`; refused beside a
    /// volumetric law).
    #[arg(long, value_name = "neo-hookean|hyperfoam|lung-birzle|none", value_parser = parse_continuum_correction)]
    continuum_correction: Option<ContinuumCorrectionFlag>,
    /// Where each element's bending and twist (hourglass) response comes from: `full-integration`
    /// (a fully integrated trilinear brick, CalculiX C3D8), `incompatible-modes` (C3D8I) or
    /// `springs` (Baudet's springs alone) (default full-integration, or the config's
    /// `[material] hourglass`).
    #[arg(long, value_name = "full-integration|incompatible-modes|springs", value_parser = parse_hourglass)]
    hourglass: Option<lungmotion::model::HourglassLaw>,
    /// Wall-clock budget of the whole run, seconds (1 – 604800; default 1800, or the config's
    /// `[budget] time_s`): a run that reaches it stops within about a second, leaves no
    /// output and exits with status 3.
    #[arg(long, value_name = "SECONDS", value_parser = parse_time_budget, allow_negative_numbers = true)]
    time_budget: Option<f64>,
    /// Equilibrium solves the run may make (key volumes, their load-step halvings, per-frame
    /// solves; 1 – 1000000; default 10000, or the config's `[budget] max_equilibria`);
    /// reaching it stops the run like the time budget.
    #[arg(long, value_name = "N", value_parser = parse_max_equilibria, allow_negative_numbers = true)]
    max_equilibria: Option<i64>,
    /// No progress (the bar on a terminal, the progress lines otherwise).
    #[arg(long, short)]
    quiet: bool,
}

/// `--time-budget`: a number of seconds the configuration accepts.
fn parse_time_budget(text: &str) -> Result<f64, String> {
    let s: f64 = text
        .trim()
        .parse()
        .map_err(|_| format!("`{text}` is not a number of seconds"))?;
    match lungmotion::run::BudgetConfig::time_problem(s) {
        Some(reason) => Err(reason),
        None => Ok(s),
    }
}

/// A flag's value as the configuration names it (`-` accepted for `_`), read by the
/// configuration's own deserialiser so that flag and file accept the same names; `what` says
/// what was expected and lists the choices.
fn config_name<T: serde::de::DeserializeOwned>(text: &str, what: &str) -> Result<T, String> {
    use serde::de::IntoDeserializer;
    let name = text.trim().replace('-', "_");
    T::deserialize(name.as_str().into_deserializer())
        .map_err(|_: serde::de::value::Error| format!("`{text}` is not {what}"))
}

/// `--sliding`: the configuration's names, with `-` or `_`.
fn parse_sliding(text: &str) -> Result<lungmotion::ingest::lung_model::SlidingMode, String> {
    config_name(text, "a sliding mode: tangent-plane or wall-surface")
}

/// `--mediastinum`: the configuration's names.
fn parse_mediastinum(text: &str) -> Result<lungmotion::motion::MediastinumContact, String> {
    config_name(
        text,
        "a way for the mediastinal face to meet the heart: sliding or contact",
    )
}

/// `--continuum-correction`: a law, or `none` for the springs' own response.
#[derive(Debug, Clone, Copy)]
struct ContinuumCorrectionFlag(Option<lungmotion::model::ContinuumLaw>);

/// `--continuum-correction`: `neo-hookean`, `hyperfoam`, `lung-birzle` or `none` (underscores
/// accepted, as in the configuration).
fn parse_continuum_correction(text: &str) -> Result<ContinuumCorrectionFlag, String> {
    if text.trim() == "none" {
        return Ok(ContinuumCorrectionFlag(None));
    }
    config_name(
        text,
        "a continuum correction: neo-hookean, hyperfoam, lung-birzle or none",
    )
    .map(|law| ContinuumCorrectionFlag(Some(law)))
}

/// `--hourglass`: the configuration's names, with `-` or `_`.
fn parse_hourglass(text: &str) -> Result<lungmotion::model::HourglassLaw, String> {
    config_name(
        text,
        "an hourglass response: full-integration, incompatible-modes or springs",
    )
}

/// `--diaphragm`: the configuration's names, with `-` or `_`.
fn parse_diaphragm(text: &str) -> Result<lungmotion::ingest::lung_model::DiaphragmMotion, String> {
    config_name(text, "a diaphragm motion: cranio-caudal, sliding or free")
}

/// `--rib-cage-share`: a fraction the configuration accepts.
fn parse_rib_cage_share(text: &str) -> Result<f64, String> {
    let s: f64 = text
        .trim()
        .parse()
        .map_err(|_| format!("`{text}` is not a fraction of the tidal volume"))?;
    lungmotion::motion::chest_wall::check_rib_cage_share(s)
        .map(|()| s)
        .map_err(|e| e.to_string())
}

/// `--max-equilibria`: a count the configuration accepts.
fn parse_max_equilibria(text: &str) -> Result<i64, String> {
    let n: i64 = text
        .trim()
        .parse()
        .map_err(|_| format!("`{text}` is not a whole number of equilibrium solves"))?;
    match lungmotion::run::BudgetConfig::equilibria_problem(n) {
        Some(reason) => Err(reason),
        None => Ok(n),
    }
}

/// Options of `lungmotion demo`.
#[derive(clap::Args)]
pub struct DemoArgs {
    /// Output directory.
    #[arg(long, default_value = "demo-out")]
    out: PathBuf,
    /// Edge of the cubic elements in millimetres (8 keeps the demo to seconds).
    #[arg(long, default_value_t = 8.0)]
    element_size: f64,
    /// Replace an earlier run in --out even if it was made from another CT.
    #[arg(long)]
    overwrite: bool,
    /// No progress (the bar on a terminal, the progress lines otherwise).
    #[arg(long, short)]
    quiet: bool,
}

/// One breathing run, its options resolved: what goes in, how, and where it goes.
struct BreathingRun {
    inputs: RunInputs,
    config: RunConfig,
    out: PathBuf,
    overwrite: Overwrite,
    quiet: bool,
    /// The CT pulled from a PACS, removed when the run ends.
    pulled: Option<PulledSeries>,
    /// Where to push the DICOM outputs.
    push: Option<DicomWebAddress>,
}

/// A CT series pulled from a PACS into a temporary directory, removed on drop.
struct PulledSeries {
    dir: PathBuf,
}

impl PulledSeries {
    /// Pulls the series `address` names into a fresh temporary directory.
    fn pull(address: &DicomWebAddress, quiet: bool) -> anyhow::Result<Self> {
        let dir = std::env::temp_dir().join(format!("lungmotion-pull-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let pulled = PulledSeries { dir };
        let files = super::pacs::pull(address, &pulled.dir)?;
        if !quiet {
            eprintln!(
                "lungmotion: pulled {} instances from {}",
                files.len(),
                address.root_url
            );
        }
        Ok(pulled)
    }
}

impl Drop for PulledSeries {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

impl RunArgs {
    /// Runs the job the options describe and prints its summary.
    pub fn execute(self) -> anyhow::Result<()> {
        self.resolve()?.execute()
    }

    /// The configuration file with the options over it, then the trace read in the
    /// configuration's units, then the points.
    fn resolve(self) -> anyhow::Result<BreathingRun> {
        let mut config = match &self.config {
            Some(path) => RunConfig::from_toml_file(path)?,
            None => RunConfig::default(),
        };
        if let Some(mm) = self.element_size {
            config.element_size_mm = mm;
        }
        if let Some(series) = &self.series {
            config.series = Some(series.clone());
        }
        config.outputs.metaimage |= self.mha;
        config.outputs.mesh_vtu |= self.vtu;
        config.outputs.registration |= self.registration || self.registration_spacing.is_some();
        if let Some(mm) = self.registration_spacing {
            config.outputs.registration_spacing_mm = mm;
        }
        if let Some(output) = self.virtual_ct {
            config.outputs.virtual_ct = output;
        }
        if let Some(window) = self.trace_window {
            config.trace.window_s = Some(window);
        }
        if let Some(s) = self.time_budget {
            config.budget.time_s = s;
        }
        if let Some(law) = self.spring_law {
            config.material.spring_law = law;
        }
        if let Some(ContinuumCorrectionFlag(law)) = self.continuum_correction {
            config.material.continuum_correction = law;
        }
        if let Some(law) = self.hourglass {
            config.material.hourglass = law;
        }
        if let Some(s) = self.rib_cage_share {
            config.motion.rib_cage_share = s;
        }
        if let Some(mode) = self.sliding {
            config.sliding = mode;
        }
        if let Some(motion) = self.diaphragm {
            config.diaphragm = motion;
        }
        if let Some(m) = self.mediastinum {
            config.motion.mediastinum = m;
        }
        if let Some(n) = self.max_equilibria {
            config.budget.max_equilibria = n;
        }
        let reading = BreathingTrace::read_with_notes(&self.trace, &config.trace)?;
        // What was done to the file's columns goes to the console and, with the file's name,
        // into summary.json's trace source.
        let mut trace_source = self.trace.display().to_string();
        for note in &reading.notes {
            eprintln!("lungmotion: trace: {note}");
        }
        if !reading.notes.is_empty() {
            trace_source = format!("{trace_source} ({})", reading.notes.join("; "));
        }
        let push = self
            .push
            .as_deref()
            .map(DicomWebAddress::parse)
            .transpose()?;
        let ct_text = self.ct.to_string_lossy();
        let pulled = if DicomWebAddress::is_dicomweb(&ct_text) {
            Some(PulledSeries::pull(
                &DicomWebAddress::parse(&ct_text)?,
                self.quiet,
            )?)
        } else {
            None
        };
        let inputs = RunInputs {
            ct_path: pulled.as_ref().map_or(self.ct.clone(), |p| p.dir.clone()),
            trace: reading.trace,
            trace_source,
            points: match &self.points {
                Some(path) => lungmotion::outputs::trajectories::read_points(path)?,
                None => Vec::new(),
            },
            target: self.target,
        };
        Ok(BreathingRun {
            inputs,
            config,
            out: self.out,
            overwrite: overwrite_of(self.overwrite),
            quiet: self.quiet,
            pulled,
            push,
        })
    }
}

impl DemoArgs {
    /// Runs the job on the bundled phantom and prints its summary.
    pub fn execute(self) -> anyhow::Result<()> {
        let config = demo_config(self.element_size);
        let inputs = demo_inputs(&sample_volumes_dir())?;
        eprintln!(
            "lungmotion: demo on {} with {}",
            inputs.ct_path.display(),
            inputs.trace_source
        );
        BreathingRun {
            inputs,
            config,
            out: self.out,
            overwrite: overwrite_of(self.overwrite),
            quiet: self.quiet,
            pulled: None,
            push: None,
        }
        .execute()
    }
}

impl BreathingRun {
    /// Runs it with a progress display, stopping cleanly on Ctrl-C, SIGTERM or SIGHUP, then
    /// prints the warnings and the summary.
    fn execute(self) -> anyhow::Result<()> {
        let interrupt = Interrupt::install()?;
        let mut progress = ProgressDisplay::new(self.quiet).with_cancel(interrupt.flag());
        let result = lungmotion::run::run_breathing_with(
            &self.inputs,
            &self.config,
            &self.out,
            self.overwrite,
            &mut progress,
        );
        let summary = match (result, interrupt.received()) {
            (Ok(summary), _) => summary,
            (Err(e @ lungmotion::Error::Cancelled(_)), Some(signal)) => {
                return Err(anyhow::Error::new(e).context(format!(
                    "interrupted by {signal}: the partial output was removed and {} was left \
                     as it was",
                    self.out.display()
                )))
            }
            (Err(e), _) => return Err(e.into()),
        };
        progress.finish();
        for w in &summary.warnings {
            eprintln!("lungmotion: warning: {w}");
        }
        print_summary(&summary, &self.out);
        drop(self.pulled);
        if let Some(address) = &self.push {
            let report = super::pacs::push(&address.root_url, std::slice::from_ref(&self.out))?;
            println!(
                "pushed to {}: {} instances stored, {} already there",
                address.root_url, report.stored, report.already_stored
            );
        }
        Ok(())
    }
}

/// The run's summary on stdout: model, frame table, the breathing's extremes (end-inhale,
/// deepest expiration) with the tracked points there, timings.
fn print_summary(summary: &lungmotion::run::RunSummary, out: &std::path::Path) {
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
    let extremes: Vec<_> = summary.extremes().collect();
    if extremes.is_empty() {
        println!(
            "no frame leaves the scanned volume by more than {} mL: no breathing extreme to report",
            lungmotion::run::SCANNED_STATE_TOLERANCE_ML
        );
    }
    for e in &extremes {
        println!("{}", e.describe());
        for p in &summary.points {
            let d = p.displacement_mm[e.frame];
            println!(
                "{}: {} displacement ({:+.1}, {:+.1}, {:+.1}) mm, |d| = {:.1} mm",
                p.name,
                e.kind.label(),
                d[0],
                d[1],
                d[2],
                (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
            );
        }
    }
    if let Some(t) = &summary.target {
        let p = &t.peak_to_peak_mm;
        println!(
            "target {:.1} cc, ITV {:.1} cc; peak-to-peak motion LR {:.1} mm, AP {:.1} mm, \
             SI {:.1} mm{}",
            t.planning_volume_cc,
            t.itv_volume_cc,
            p.lr,
            p.ap,
            p.si,
            if t.tg76_motion_management_advised {
                " (over TG-76's 5 mm: motion management advised)"
            } else {
                ""
            }
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
}

/// `START:END` seconds.
fn parse_window(text: &str) -> Result<[f64; 2], String> {
    let (a, b) = text
        .split_once(':')
        .ok_or_else(|| format!("'{text}': expected START:END in seconds, e.g. 10:40"))?;
    let number = |v: &str| {
        v.trim()
            .parse::<f64>()
            .map_err(|_| format!("'{v}' in '{text}' is not a number of seconds"))
    };
    Ok([number(a)?, number(b)?])
}

#[cfg(test)]
mod tests {
    use super::*;
    use lungmotion::ingest::lung_model::{DiaphragmMotion, SlidingMode};
    use lungmotion::model::{ContinuumLaw, HourglassLaw};
    use lungmotion::motion::MediastinumContact;

    #[test]
    fn named_flags_take_the_configurations_names_with_hyphens_or_underscores() {
        assert_eq!(parse_sliding("wall-surface"), Ok(SlidingMode::WallSurface));
        assert_eq!(
            parse_sliding("tangent_plane"),
            Ok(SlidingMode::TangentPlane)
        );
        assert_eq!(
            parse_diaphragm(" cranio-caudal "),
            Ok(DiaphragmMotion::CranioCaudal)
        );
        assert_eq!(parse_diaphragm("free"), Ok(DiaphragmMotion::Free));
        assert_eq!(
            parse_mediastinum("contact"),
            Ok(MediastinumContact::Contact)
        );
        assert_eq!(
            parse_hourglass("incompatible-modes"),
            Ok(HourglassLaw::IncompatibleModes)
        );
        assert_eq!(
            parse_hourglass("full_integration"),
            Ok(HourglassLaw::FullIntegration)
        );
        assert_eq!(parse_hourglass("springs"), Ok(HourglassLaw::Springs));
        let law = |t| parse_continuum_correction(t).map(|f| f.0);
        assert_eq!(law("lung-birzle"), Ok(Some(ContinuumLaw::LungBirzle)));
        assert_eq!(law("neo_hookean"), Ok(Some(ContinuumLaw::NeoHookean)));
        assert_eq!(law("none"), Ok(None));
        assert_eq!(
            parse_diaphragm("piston"),
            Err("`piston` is not a diaphragm motion: cranio-caudal, sliding or free".into())
        );
        assert!(law("None")
            .unwrap_err()
            .contains("`None` is not a continuum correction"));
        assert!(parse_hourglass("").is_err());
    }
}

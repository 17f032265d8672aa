//! The tool's main job: one CT and one breathing trace in, a displacement field per requested
//! instant out. The CLI (`lungmotion run`, `lungmotion demo`) and the HTTP service are thin
//! shells over [`run_breathing`].
//!
//! Stages: load the CT → ingest (segmentation, cubic elements, constraint groups) → the lung
//! scene → quasi-static motion through the trace (key volumes solved, frames interpolated
//! within a measured error) → per-frame files → quick looks → `summary.json`. Everything is
//! written into a staging directory and published at the end ([`staging`]).
//!
//! Output layout and conventions (`<out>/`):
//! * `frames/<k>/displacement.nii.gz`: NIfTI-1 vector image (intent 1007, 3 float32
//!   components, millimetres) on the input CT's grid and affine; components in **LPS** as ITK
//!   and elastix expect (not RAS, whatever the NIfTI world frame); zero outside the lungs.
//!   `u(x)` is where the tissue at CT voxel `x` has moved: `x + u(x)` at that instant.
//!   Optionally `displacement.mha` (MetaImage, same convention) and `mesh.vtu` (the deformed
//!   mesh, LPS millimetres, point data `displacement_mm` and `group`, cell data `lung`).
//! * `trajectories.csv`: tracked points per frame (see [`crate::outputs::trajectories`]).
//! * `summary.json`: [`RunSummary`].
//! * `breathing.png`, `end-inhale-displacement.png` (or `deepest-expiration-displacement.png`
//!   for a trace that never rises above the scanned volume): quick looks.
//! * `ingest/`: the ingest outputs (lung mask, groups, mesh, `ingest.json`).

mod budget;
pub mod config;
pub mod demo;
mod frames;
mod quicklooks;
pub mod staging;
mod summary;
pub mod toml_key;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub use crate::outputs::trajectories::TrackedPoint;
pub use config::{BudgetConfig, MotionConfig, OutputConfig, RunConfig};
pub use summary::{
    BreathExtreme, BreathExtremeSummary, BudgetUsage, FrameFiles, FrameRecord, ModelSummary,
    PointTrajectory, RunSummary, TraceSummary, COSTAL_WALL_GAP_WARNING_MIN_MM,
    SCANNED_STATE_TOLERANCE_ML,
};

use crate::breathing::{BreathingTrace, InstantPlan};
use crate::durable::write_atomic;
use crate::formats::dicom::DicomStudyContext;
use crate::ingest::lung_model::ConstraintGroup;
use crate::ingest::pipeline::{ingest_scan_cancellable, IngestOutcome};
use crate::ingest::scan::{load_ct_cancellable, LoadedScan};
use crate::ingest::stored::{read_stored_ingest, StoredIngest};
use crate::ingest::Cancel;
use crate::model::tissue::ElementTissue;
use crate::motion::dynamic::{run_dynamic, DynamicReport};
use crate::motion::{run_motion, MotionReport, MotionSettings};
use crate::outputs::displacement_field::{FieldSampler, PointSampler};
use crate::outputs::ingest_files::write_ingest_outputs;
use crate::outputs::radiotherapy::ct_motion::CtMotionSettings;
use crate::outputs::radiotherapy::target_motion::{self, TargetTracker};
use crate::outputs::radiotherapy::virtual_ct::{
    check_phase_count, inverse_warnings, phase_labels, VirtualCtWriter,
};
use crate::simulation::Scene;
use crate::{Error, IoContext, IoOp, Result};
use frames::FrameSink;
use quicklooks::{write_quicklooks, LookBackdrop};
pub use staging::Overwrite;
use staging::{ct_fingerprint, CtIdentity, OutputStaging, SUMMARY_FILE};

/// The inputs of one run.
#[derive(Debug, Clone)]
pub struct RunInputs {
    /// CT: DICOM directory, zip or file, NIfTI or NRRD (told apart by content).
    pub ct_path: PathBuf,
    /// Lung volume change from the scanned state over time.
    pub trace: BreathingTrace,
    /// Where the trace came from, for the summary (a file name or "generated: …").
    pub trace_source: String,
    /// Points to track.
    pub points: Vec<TrackedPoint>,
    /// The treatment target to follow (warped per frame, ITV, RTSTRUCT), if any.
    pub target: Option<crate::outputs::radiotherapy::target::TargetSpec>,
}

/// Stages a run reports to its observer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RunStage {
    /// Reading the CT.
    LoadingScan,
    /// Segmenting the lungs and building the model.
    Ingest,
    /// Solving the key volumes of the breathing cycle.
    Solving,
    /// Writing the frames (the observer's `frame_written` follows).
    WritingFrames,
    /// Quick looks and the summary.
    Finishing,
}

impl RunStage {
    /// What the stage does, for progress displays.
    pub fn label(self) -> &'static str {
        match self {
            RunStage::LoadingScan => "loading the CT",
            RunStage::Ingest => "segmenting the lungs and building the model",
            RunStage::Solving => "solving the breathing cycle",
            RunStage::WritingFrames => "writing displacement fields",
            RunStage::Finishing => "writing the summary and quick looks",
        }
    }
}

/// Receives progress and may cancel a run (CLI progress bar, service job state).
pub trait RunObserver {
    /// A stage begins.
    fn stage(&mut self, _stage: RunStage) {}
    /// `done` of `total` frames are written.
    fn frame_written(&mut self, _done: usize, _total: usize) {}
    /// Whether the run should stop (checked between frames and stages).
    fn cancelled(&self) -> bool {
        false
    }
    /// A flag that, once raised, also stops the run inside equilibrium solves.
    fn cancel_flag(&self) -> Option<crate::simulation::CancelFlag> {
        None
    }
    /// Where to report each equilibrium the solves reach (called on the solving thread).
    fn solve_progress(&self) -> Option<crate::simulation::SolveProgressSink> {
        None
    }
}

/// A CT read and ingested (segmentation, cubic elements, constraint groups, wall): what a
/// run needs before its solves. The service keeps them so that several jobs on one scan
/// with the same ingest settings read and ingest it once.
pub struct IngestedScan {
    /// The CT as read.
    pub scan: LoadedScan,
    /// Its ingest.
    pub outcome: IngestOutcome,
}

impl IngestedScan {
    /// Reads `ct_path` and ingests it with `config`'s settings, reporting the two stages to
    /// `observer` and stopping when it cancels (between the stages, before each DICOM slice
    /// and between and inside the ingest's steps); adds the stages' wall times to `timings`
    /// (`load_ct`, `ingest`).
    pub fn read(
        ct_path: &Path,
        config: &RunConfig,
        observer: &mut dyn RunObserver,
        timings: &mut BTreeMap<String, f64>,
    ) -> Result<Self> {
        Self::read_using(ct_path, config, None, observer, timings).map(|(read, _)| read)
    }

    /// [`IngestedScan::read`], taking the segmentation and wall from the stored ingest at
    /// `stored` (see [`crate::ingest::stored`]) when it was made for this CT with these
    /// settings; a file that is missing or cannot be trusted is logged and the CT ingested
    /// anew. Whether the stored ingest was used (then `timings` also holds
    /// `stored_ingest_read`).
    pub fn read_using(
        ct_path: &Path,
        config: &RunConfig,
        stored: Option<&Path>,
        observer: &mut dyn RunObserver,
        timings: &mut BTreeMap<String, f64>,
    ) -> Result<(Self, bool)> {
        let flag = observer.cancel_flag();
        let cancel = Cancel::new(flag.as_deref());
        observer.stage(RunStage::LoadingScan);
        let t = Instant::now();
        let scan = load_ct_cancellable(ct_path, &config.dicom_read_options(), cancel.flag())?;
        timings.insert("load_ct".to_string(), t.elapsed().as_secs_f64());
        check_cancel(observer, "ingest")?;
        observer.stage(RunStage::Ingest);
        let t = Instant::now();
        let settings = config.ingest_settings();
        let from_file = match stored {
            Some(path) if path.is_file() => {
                match read_stored_ingest(path, &config.ingest_identity(), &scan, &settings, cancel)
                {
                    Ok(StoredIngest::Used(outcome)) => Some(*outcome),
                    Ok(StoredIngest::OtherSettings) => {
                        tracing::info!("the stored ingest has other settings; ingesting");
                        None
                    }
                    Err(e @ Error::Cancelled(_)) => return Err(e),
                    Err(e) => {
                        tracing::warn!("stored ingest ignored, ingesting anew: {e}");
                        None
                    }
                }
            }
            Some(_) => {
                tracing::info!("no stored ingest for this scan; ingesting");
                None
            }
            None => None,
        };
        let used_stored = from_file.is_some();
        let outcome = match from_file {
            Some(outcome) => {
                if let Some(&read_s) = outcome.summary.timings_s.get("stored_ingest_read") {
                    timings.insert("stored_ingest_read".to_string(), read_s);
                }
                outcome
            }
            None => ingest_scan_cancellable(&scan, &settings, cancel)?,
        };
        timings.insert("ingest".to_string(), t.elapsed().as_secs_f64());
        Ok((IngestedScan { scan, outcome }, used_stored))
    }

    /// Bytes held by its voxel grids and wall distance field (the bulk of it), for a
    /// cache's budget.
    pub fn approximate_bytes(&self) -> u64 {
        let voxels = |dims: [usize; 3]| dims.iter().product::<usize>() as u64;
        let seg = &self.outcome.segmentation;
        let model = &self.outcome.model;
        let ct_bytes = voxels(self.scan.ct.geometry.dims) * 4;
        let masks = [&seg.lungs, &seg.airways, &seg.body, &model.groups_volume]
            .iter()
            .map(|v| voxels(v.geometry.dims))
            .sum::<u64>();
        let wall = model.wall.sample_bytes() as u64;
        let mesh = model.mesh.mesh.rest_positions_m.len() as u64 * 64
            + model.mesh.mesh.elements.len() as u64 * 64;
        ct_bytes + masks + wall + mesh
    }
}

/// The loaded CT of a run: its own, let go once read, or the caller's (the service's cache).
enum ScanHold<'a> {
    Owned(Box<LoadedScan>),
    Borrowed(&'a LoadedScan),
}

impl<'a> ScanHold<'a> {
    fn get(&self) -> &LoadedScan {
        match self {
            ScanHold::Owned(scan) => scan,
            ScanHold::Borrowed(scan) => scan,
        }
    }

    /// The CT voxels, moved out when the run owns them.
    fn into_ct(self) -> std::borrow::Cow<'a, crate::volume::Volume<f32>> {
        match self {
            ScanHold::Owned(scan) => std::borrow::Cow::Owned(scan.ct),
            ScanHold::Borrowed(scan) => std::borrow::Cow::Borrowed(&scan.ct),
        }
    }
}

/// An observer that ignores everything.
pub struct SilentObserver;

impl RunObserver for SilentObserver {}

fn check_cancel(observer: &dyn RunObserver, stage: &str) -> Result<()> {
    if observer.cancelled() {
        return Err(Error::Cancelled(format!("stopped before {stage}")));
    }
    Ok(())
}

/// Runs the whole job and publishes `out_dir`; on any error nothing in `out_dir` changes.
///
/// # Examples
///
/// ```
/// use lungmotion::breathing::LujanBreathing;
/// use lungmotion::run::{run_breathing, RunConfig, RunInputs, SilentObserver};
///
/// let ct = concat!(env!("CARGO_MANIFEST_DIR"), "/sample-volumes/phantom-ct.nii.gz");
/// let inputs = RunInputs {
///     ct_path: ct.into(),
///     // Two 4-second breaths of 500 mL, sampled at 10 Hz.
///     trace: LujanBreathing::default().trace(8.0, 10.0)?,
///     trace_source: "generated".into(),
///     points: Vec::new(),
///     target: None,
/// };
/// let config = RunConfig { element_size_mm: 12.0, ..RunConfig::default() };
/// let out = std::env::temp_dir().join(format!("lm-doc-run-{}", std::process::id()));
/// let summary = run_breathing(&inputs, &config, &out, &mut SilentObserver)?;
/// // One displacement field per output instant (10 phases by default).
/// assert_eq!(summary.frames.len(), 10);
/// assert!(out.join("frames/0/displacement.nii.gz").is_file());
/// std::fs::remove_dir_all(&out)?;
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn run_breathing(
    inputs: &RunInputs,
    config: &RunConfig,
    out_dir: &Path,
    observer: &mut dyn RunObserver,
) -> Result<RunSummary> {
    run_breathing_with(inputs, config, out_dir, Overwrite::SameCtOnly, observer)
}

/// [`run_breathing`], replacing an earlier run of another CT in `out_dir` only if `overwrite`
/// says so (the CLI's `--overwrite`).
pub fn run_breathing_with(
    inputs: &RunInputs,
    config: &RunConfig,
    out_dir: &Path,
    overwrite: Overwrite,
    observer: &mut dyn RunObserver,
) -> Result<RunSummary> {
    run_breathing_on(inputs, config, out_dir, overwrite, observer, None)
}

/// [`run_breathing_with`] on `prepared`: the CT of `inputs.ct_path` already read and ingested
/// with `config`'s settings (the caller's promise), with the wall times of that reading to
/// report (none when it was read for an earlier run); or reading and ingesting it when `None`.
///
/// The run's budgets (`config.budget`) hold from here: one reached stops the run, inside a
/// solve if one is under way, with [`Error::BudgetExceeded`] and nothing published.
pub fn run_breathing_on(
    inputs: &RunInputs,
    config: &RunConfig,
    out_dir: &Path,
    overwrite: Overwrite,
    observer: &mut dyn RunObserver,
    prepared: Option<(&IngestedScan, BTreeMap<String, f64>)>,
) -> Result<RunSummary> {
    let farthest_ml = inputs
        .trace
        .volume_change_ml
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .max_by(|a, b| a.abs().total_cmp(&b.abs()));
    let mut budgeted = budget::Budgeted::new(observer, config.budget, farthest_ml);
    let result = run_within_budget(inputs, config, out_dir, overwrite, &mut budgeted, prepared);
    // The staging directory went with the failed run; the error says which budget, if one.
    result.map_err(|e| budgeted.explain(e))
}

/// [`run_breathing_on`] under its budgets.
fn run_within_budget(
    inputs: &RunInputs,
    config: &RunConfig,
    out_dir: &Path,
    overwrite: Overwrite,
    observer: &mut budget::Budgeted<'_>,
    prepared: Option<(&IngestedScan, BTreeMap<String, f64>)>,
) -> Result<RunSummary> {
    let t_total = Instant::now();
    let mut timings = BTreeMap::new();
    let (settings, plan) = check_inputs(inputs, config, observer)?;
    let times = &plan.times;
    let staging = OutputStaging::new(out_dir)?;

    // A CT read here is let go once its last readers are done (fingerprint, ingest files,
    // the quick look's backdrop): 148 MB of float voxels for a 512 × 512 × 141 CT.
    let own_outcome;
    let (scan, outcome) = match prepared {
        Some((ingested, read_timings)) => {
            timings = read_timings;
            observer.stage(RunStage::Ingest);
            (ScanHold::Borrowed(&ingested.scan), &ingested.outcome)
        }
        None => {
            let read = IngestedScan::read(&inputs.ct_path, config, observer, &mut timings)?;
            own_outcome = read.outcome;
            (ScanHold::Owned(Box::new(read.scan)), &own_outcome)
        }
    };
    let target_mask = match &inputs.target {
        Some(spec) => {
            let scan = scan.get();
            Some(spec.resolve(&scan.ct.geometry, scan.study.as_ref())?)
        }
        None => None,
    };
    let t = Instant::now();
    let tissue = crate::ingest::lung_model::element_tissue(
        &outcome.model,
        &scan.get().ct,
        &outcome.segmentation.lungs,
        target_mask.as_ref().map(|t| &t.mask),
        &config.tissue,
        config.material.youngs_modulus_pa,
    )?;
    if let Some((_, report)) = &tissue {
        timings.insert("element_tissue".to_string(), t.elapsed().as_secs_f64());
        tracing::info!(
            reference_hu = report.reference_hu,
            quantiles = ?report.stiffness_ratio_quantiles,
            target_elements = report.target_elements,
            "element tissue mapped"
        );
    }
    let target = open_target(
        target_mask,
        scan.get(),
        staging.dir(),
        &settings,
        times.len(),
    )?;
    let SceneOfScan {
        ct,
        lung,
        ct_dims,
        backdrop,
        study,
        kept,
    } = scene_of_scan(
        scan,
        ScanModel {
            outcome,
            tissue: tissue.as_ref().map(|(t, _)| t),
        },
        inputs,
        config,
        &staging,
        overwrite,
        &mut timings,
    )?;
    check_cancel(observer, "the solves")?;

    observer.stage(RunStage::Solving);
    let mut sink = FrameSink::open(
        &lung,
        &outcome.model,
        staging.dir(),
        &config.outputs,
        inputs,
        times,
        &study,
    )?;
    sink.target = target;
    if let Some(kept) = &kept {
        sink.set_virtual_ct(virtual_ct_writer(
            kept, &lung, inputs, config, &plan, &staging,
        )?);
    }
    let (report, dynamic) = run_the_motion(
        &lung.scene,
        inputs,
        config,
        &settings,
        &plan,
        &mut sink,
        observer,
    )
    .map_err(|e| name_element_groups(e, &outcome.model))?;
    let virtual_ct = sink.take_virtual_ct();
    let mut written = sink.finish();
    let virtual_ct = virtual_ct.map(VirtualCtWriter::finish).transpose()?;
    drop(kept);
    if let Some(v) = &virtual_ct {
        timings.insert("virtual_ct".to_string(), v.time_s);
    }
    log_memory("frames written");
    written.record_timings(report.wall_time_s, &mut timings);

    observer.stage(RunStage::Finishing);
    check_cancel(observer, "the summary")?;
    let t = Instant::now();
    if written.records.is_empty() {
        return Err(Error::argument("run output", "the run produced no frame"));
    }
    let extremes = written
        .extremes
        .iter()
        .map(|c| {
            summary::extreme_summary(
                c.kind,
                &outcome.model,
                &lung.scene,
                c.frame,
                &c.positions_m,
                &report,
            )
        })
        .collect();
    if let Some(file) = written.trajectory_file.take() {
        file.finish()?;
    }
    if let Some(backdrop) = &backdrop {
        write_quicklooks(
            staging.dir(),
            inputs,
            backdrop,
            &lung.field,
            &lung.scene.mesh,
            &mut written,
        )?;
    }
    drop(std::mem::take(&mut written.field_buffer_mm));
    let mut summary = RunSummary::new(
        inputs,
        config,
        outcome,
        report,
        dynamic,
        written.records,
        written.trajectories,
        extremes,
        summary::FieldGridSummary::of(config.outputs.field_grid, &lung.field, ct_dims),
        timings,
    );
    summary.ct_fingerprint = Some(ct.fingerprint);
    summary.tissue = tissue.map(|(_, report)| report);
    if let Some(tracker) = written.target.take() {
        summary.target = Some(tracker.finish()?);
    }
    if let Some(v) = virtual_ct {
        summary
            .warnings
            .extend(inverse_warnings(&v, VIRTUAL_CT_RESIDUAL_WARNING_MM));
        summary.virtual_ct = Some(v);
    }
    if let Some(note) = plan.note {
        summary.warnings.push(note.clone());
        summary.output_instants_note = Some(note);
    }
    log_memory("summary and quick looks");
    check_cancel(observer, "publishing")?;
    summary.budget = BudgetUsage {
        limits: config.budget,
        elapsed_s: observer.elapsed_s(),
        equilibria: observer.equilibria(),
    };
    record_final_timings(&mut summary, t, t_total);
    write_summary(staging.dir(), &summary)?;
    staging.publish()?;
    Ok(summary)
}

/// The run's target (resolved on the CT's grid), followed into `staging_dir`; refused here,
/// before the solves, when it does not fit the CT.
fn open_target(
    mask: Option<crate::outputs::radiotherapy::target::TargetMask>,
    scan: &LoadedScan,
    staging_dir: &Path,
    settings: &MotionSettings,
    frames: usize,
) -> Result<Option<TargetTracker>> {
    let Some(mask) = mask else {
        return Ok(None);
    };
    let names = target_motion::frame_names(&settings.instants, frames);
    TargetTracker::new(mask, staging_dir, names, scan.study.clone()).map(Some)
}

/// What a run keeps of its CT once the lung scene is built.
struct SceneOfScan<'a> {
    ct: CtIdentity,
    lung: LungScene,
    ct_dims: [usize; 3],
    backdrop: Option<LookBackdrop>,
    /// The CT's patient, study and frame of reference (generated for a NIfTI/NRRD CT).
    study: crate::formats::dicom::DicomStudyContext,
    /// The CT itself and its study, kept only for the virtual CT.
    kept: Option<KeptCt<'a>>,
}

/// The CT voxels and DICOM study a virtual CT is made from.
struct KeptCt<'a> {
    ct: std::borrow::Cow<'a, crate::volume::Volume<f32>>,
    study: crate::formats::dicom::DicomStudyContext,
}

/// A virtual CT between inverse-map nodes off by more than this raises a warning, mm.
const VIRTUAL_CT_RESIDUAL_WARNING_MM: f64 = 0.5;

/// The writer of the virtual CT of `kept` through the frames at `times`.
fn virtual_ct_writer<'a>(
    kept: &'a KeptCt<'a>,
    lung: &LungScene,
    inputs: &RunInputs,
    config: &RunConfig,
    plan: &InstantPlan,
    staging: &OutputStaging,
) -> Result<VirtualCtWriter<'a>> {
    let settings = CtMotionSettings {
        decay_length_mm: config.outputs.outside_lung_decay_mm,
        ..CtMotionSettings::default()
    };
    VirtualCtWriter::new(
        &kept.ct,
        kept.study.clone(),
        &lung.scene.mesh,
        settings,
        config.outputs.virtual_ct,
        phase_labels(&inputs.trace, plan),
        staging.dir(),
    )
}

/// What a run's scene is built from: the ingest, and each element's tissue when it varies.
struct ScanModel<'m> {
    outcome: &'m IngestOutcome,
    tissue: Option<&'m ElementTissue>,
}

/// Identifies the CT (refusing to replace another CT's run), builds the lung scene, writes
/// the ingest files and cuts out the quick look's backdrop; the CT is let go on return when
/// the run owns it. Adds `ingest`, `lung_scene` and `ingest_files` to `timings`.
fn scene_of_scan<'a>(
    scan: ScanHold<'a>,
    model: ScanModel<'_>,
    inputs: &RunInputs,
    config: &RunConfig,
    staging: &OutputStaging,
    overwrite: Overwrite,
    timings: &mut BTreeMap<String, f64>,
) -> Result<SceneOfScan<'a>> {
    let ScanModel { outcome, tissue } = model;
    let t = Instant::now();
    let ct = CtIdentity {
        path: inputs.ct_path.display().to_string(),
        fingerprint: ct_fingerprint(&scan.get().ct),
        series_uid: scan
            .get()
            .series
            .as_ref()
            .map(|s| s.series_instance_uid.clone()),
    };
    staging.check_replaces(&ct, overwrite)?;
    let study = scan.get().study.clone().unwrap_or_else(|| {
        let key = ct.fingerprint.trim_start_matches("fnv1a64:");
        DicomStudyContext::generated(u64::from_str_radix(key, 16).unwrap_or(0))
    });
    *timings.entry("ingest".to_string()).or_insert(0.0) += t.elapsed().as_secs_f64();
    log_memory("ingested");
    crate::process::return_freed_memory();
    log_memory("ingested, freed memory returned");
    // The ingest files (gzip and disk) and the scene (the mesh's and the field's indices)
    // share no data: built side by side, on the pool's two halves when both are free.
    let seconds = |t: Instant| t.elapsed().as_secs_f64();
    let (scene, files) = rayon::join(
        || {
            let t = Instant::now();
            build_lung_scene(
                outcome,
                &inputs.points,
                config.outputs.field_grid,
                &config.wall_motion(),
                tissue.map(|t| (t, config.tissue.stiffness_step)),
            )
            .map(|scene| (scene, seconds(t)))
        },
        || {
            let t = Instant::now();
            if config.outputs.ingest_files {
                write_ingest_files(staging.dir(), &scan.get().ct, outcome)?;
            }
            Ok::<_, Error>(seconds(t))
        },
    );
    let (lung, scene_s) = scene?;
    let files_s = files?;
    timings.insert("lung_scene".to_string(), scene_s);
    timings.insert("ingest_files".to_string(), files_s);
    let ct_dims = scan.get().ct.geometry.dims;
    let (kept, ct_for_look) = if config.outputs.virtual_ct.enabled() {
        let kept = KeptCt {
            ct: scan.into_ct(),
            study: study.clone(),
        };
        (Some(kept), None)
    } else {
        (None, Some(scan.into_ct()))
    };
    // A kept CT is lent to the look (which crops it), else the look takes it.
    let look_ct = ct_for_look.or_else(|| kept.as_ref().map(|k| std::borrow::Cow::Borrowed(&*k.ct)));
    let backdrop = match look_ct {
        Some(ct) if config.outputs.quicklooks => Some(LookBackdrop::of(
            ct,
            &outcome.segmentation.lungs,
            &lung.field,
        )?),
        _ => None,
    };
    log_memory("lung scene built, ingest files written, CT let go");
    Ok(SceneOfScan {
        ct,
        lung,
        ct_dims,
        backdrop,
        study,
        kept,
    })
}

/// Checks everything that can be checked without the CT; returns the motion settings (with
/// the observer's cancel flag) and the output instants.
fn check_inputs(
    inputs: &RunInputs,
    config: &RunConfig,
    observer: &dyn RunObserver,
) -> Result<(MotionSettings, InstantPlan)> {
    config.validate()?;
    config.tissue.check_target(inputs.target.is_some())?;
    inputs.trace.validate()?;
    let mut settings = config.motion_settings();
    settings.cancel = observer.cancel_flag();
    settings.progress = observer.solve_progress();
    let plan = settings.instants.plan(&inputs.trace)?;
    check_phase_count(config.outputs.virtual_ct, plan.times.len())?;
    Ok((settings, plan))
}

/// The lung scene of a run with the samplers that carry its node positions to the CT grid
/// and to the tracked points.
struct LungScene {
    scene: Scene,
    field: FieldSampler,
    points: PointSampler,
}

/// Builds the mechanical scene of the ingested lungs and locates the CT voxels and the
/// tracked points in its mesh.
fn build_lung_scene(
    outcome: &IngestOutcome,
    tracked: &[TrackedPoint],
    field_grid: crate::outputs::displacement_field::FieldGrid,
    walls: &crate::motion::WallMotion,
    tissue: Option<(&ElementTissue, f64)>,
) -> Result<LungScene> {
    let model = &outcome.model;
    let scene = match tissue {
        Some((tissue, step)) => crate::motion::run_scene_with_tissue(model, walls, tissue, step)?,
        None => crate::motion::run_scene(model, walls)?,
    };
    let mesh = &scene.mesh;
    let field = FieldSampler::new(
        &outcome.segmentation.lungs,
        mesh,
        &model.element_lung,
        field_grid,
    )?;
    let point_positions: Vec<[f64; 3]> = tracked.iter().map(|p| p.rest_lps_mm).collect();
    let points = PointSampler::new(&point_positions, mesh, &model.element_lung).map_err(|e| {
        Error::Points {
            file: None,
            point: None,
            reason: format!(
                "{}: {e}",
                tracked
                    .iter()
                    .map(|p| p.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        }
    })?;
    Ok(LungScene {
        scene,
        field,
        points,
    })
}

/// Writes the ingest results (lung mask, groups, mesh, `ingest.json`) into `<staging>/ingest`.
fn write_ingest_files(
    staging_dir: &Path,
    ct: &crate::volume::Volume<f32>,
    outcome: &IngestOutcome,
) -> Result<()> {
    let dir = staging_dir.join("ingest");
    std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
    write_ingest_outputs(&dir, ct, outcome)?;
    Ok(())
}

/// Adds the anatomical groups of the named element's nodes to a [`Error::VolumeUnreachable`],
/// which the solver, knowing only the mesh, leaves out.
pub(crate) fn name_element_groups(
    error: Error,
    model: &crate::ingest::lung_model::LungModel,
) -> Error {
    let Error::VolumeUnreachable(mut unreachable) = error else {
        return error;
    };
    let mut names: Vec<&str> = model.mesh.mesh.elements[unreachable.element]
        .iter()
        .map(|&n| {
            crate::ingest::lung_model::ConstraintGroup::from_code(model.node_group[n as usize])
                .map_or("interior", |g| g.name())
        })
        .collect();
    names.sort_unstable();
    names.dedup();
    unreachable.group = Some(names.join(", "));
    Error::VolumeUnreachable(unreachable)
}

/// Drives the scene through the trace, quasi-static or dynamic as configured, handing every
/// frame to `sink`; the dynamic report comes back beside the quasi-static-shaped one.
fn run_the_motion(
    scene: &Scene,
    inputs: &RunInputs,
    config: &RunConfig,
    settings: &MotionSettings,
    plan: &InstantPlan,
    sink: &mut FrameSink,
    observer: &mut dyn RunObserver,
) -> Result<(MotionReport, Option<DynamicReport>)> {
    Ok(match &config.motion.dynamic {
        None => (
            run_motion(
                scene,
                &config.material,
                &inputs.trace,
                settings,
                &mut |frame, positions| sink.frame(frame, positions, observer),
            )?,
            None,
        ),
        Some(dynamic) => {
            let r = run_dynamic(
                scene,
                &inputs.trace,
                &crate::motion::dynamic::DynamicSettings {
                    rib_cage_share: settings.rib_cage_share,
                    ..dynamic.settings()
                },
                &plan.times,
                &mut |f, positions| {
                    let mut frame = f.as_frame_summary();
                    frame.phase_percent = plan.phase_percent.as_ref().map(|p| p[f.index]);
                    sink.frame(&frame, positions, observer)
                },
            )?;
            (r.as_motion_report(settings, &config.material), Some(r))
        }
    })
}

/// Adds the last stage's and the whole run's wall times and the peak memory to `summary`.
fn record_final_timings(summary: &mut RunSummary, finishing_start: Instant, run_start: Instant) {
    summary.timings_s.insert(
        "summary_and_quicklooks".to_string(),
        finishing_start.elapsed().as_secs_f64(),
    );
    summary
        .timings_s
        .insert("total".to_string(), run_start.elapsed().as_secs_f64());
    summary.peak_memory_mib = crate::process::peak_rss_bytes().map(|b| b as f64 / (1 << 20) as f64);
}

/// Logs the resident and peak memory at a stage boundary (`LUNGMOTION_LOG=debug`), to see
/// which stage holds what.
fn log_memory(stage: &str) {
    let mib = |b: Option<u64>| b.map_or(-1.0, |b| b as f64 / f64::from(1 << 20));
    tracing::debug!(
        stage,
        rss_mib = mib(crate::process::current_rss_bytes()),
        peak_mib = mib(crate::process::peak_rss_bytes()),
        "run memory"
    );
}

/// Writes `summary.json` into the staging directory.
fn write_summary(staging_dir: &Path, summary: &RunSummary) -> Result<()> {
    write_atomic(
        &staging_dir.join(SUMMARY_FILE),
        serde_json::to_string_pretty(summary)
            .map_err(|e| Error::format(staging_dir.join(SUMMARY_FILE), format!("summary: {e}")))?
            .as_bytes(),
    )
}

/// Name of a [`ConstraintGroup`] code (`interior` for 0), for summaries.
fn group_name(code: u8) -> &'static str {
    ConstraintGroup::from_code(code).map_or("interior", |g| g.name())
}

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
//!   mesh, LPS millimetres, point data `displacement_mm`).
//! * `trajectories.csv`: tracked points per frame (see [`crate::outputs::trajectories`]).
//! * `summary.json`: [`RunSummary`].
//! * `breathing.png`, `end-inhale-displacement.png`: quick looks.
//! * `ingest/`: the ingest outputs (lung mask, groups, mesh, `ingest.json`).

pub mod config;
pub mod demo;
pub mod staging;
mod summary;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub use crate::outputs::trajectories::TrackedPoint;
pub use config::{MotionConfig, OutputConfig, RunConfig};
pub use summary::{
    EndInhaleSummary, FrameFiles, FrameRecord, ModelSummary, PointTrajectory, RunSummary,
    TraceSummary,
};

use crate::breathing::BreathingTrace;
use crate::durable::write_atomic;
use crate::formats::{metaimage, nifti, vtk};
use crate::ingest::lung_model::ConstraintGroup;
use crate::ingest::pipeline::ingest_scan;
use crate::ingest::scan::load_ct;
use crate::math::V3;
use crate::motion::dynamic::run_dynamic;
use crate::motion::{lung_scene, run_motion, FrameSummary};
use crate::outputs::displacement_field::{FieldSampler, PointSampler};
use crate::outputs::ingest_files::write_ingest_outputs;
use crate::outputs::trajectories::TrajectoryFile;
use crate::{Error, Result};
use staging::{OutputStaging, SUMMARY_FILE};

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
    /// A flag that, once raised, also stops the run between equilibrium solves.
    fn cancel_flag(&self) -> Option<crate::simulation::CancelFlag> {
        None
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
pub fn run_breathing(
    inputs: &RunInputs,
    config: &RunConfig,
    out_dir: &Path,
    observer: &mut dyn RunObserver,
) -> Result<RunSummary> {
    let t_total = Instant::now();
    let mut timings = BTreeMap::new();
    // Everything that can be checked without the CT is checked first.
    config.validate()?;
    inputs.trace.validate()?;
    let mut settings = config.motion_settings();
    settings.cancel = observer.cancel_flag();
    let times = settings.instants.times(&inputs.trace)?;
    let staging = OutputStaging::new(out_dir)?;

    observer.stage(RunStage::LoadingScan);
    let t = Instant::now();
    let scan = load_ct(&inputs.ct_path)?;
    timings.insert("load_ct".to_string(), t.elapsed().as_secs_f64());
    check_cancel(observer, "ingest")?;

    observer.stage(RunStage::Ingest);
    let t = Instant::now();
    let ingest_settings = config.ingest_settings();
    let outcome = ingest_scan(&scan, &ingest_settings)?;
    let model = &outcome.model;
    let scene = lung_scene(model)?;
    let mesh = &scene.mesh;
    let field = FieldSampler::new(&outcome.segmentation.lungs, mesh, &model.element_lung)?;
    let point_positions: Vec<[f64; 3]> = inputs.points.iter().map(|p| p.rest_lps_mm).collect();
    let points = PointSampler::new(&point_positions, mesh, &model.element_lung).map_err(|e| {
        Error::InvalidInput(format!(
            "tracked points ({}): {e}",
            inputs
                .points
                .iter()
                .map(|p| p.name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ))
    })?;
    if config.outputs.ingest_files {
        let dir = staging.dir().join("ingest");
        std::fs::create_dir_all(&dir)?;
        write_ingest_outputs(&dir, &scan.ct, &outcome)?;
    }
    timings.insert("ingest".to_string(), t.elapsed().as_secs_f64());
    check_cancel(observer, "the solves")?;

    observer.stage(RunStage::Solving);
    let geometry = scan.ct.geometry;
    let frames_dir = staging.dir().join("frames");
    std::fs::create_dir_all(&frames_dir)?;
    // End-inhale is the frame with the largest trace volume (the first, on a tie); known
    // before solving, so only that frame's field and positions are kept.
    let end_inhale_frame = times
        .iter()
        .map(|&t| inputs.trace.volume_at(t))
        .enumerate()
        .fold((0, f64::NEG_INFINITY), |best, (i, v)| {
            if v > best.1 {
                (i, v)
            } else {
                best
            }
        })
        .0;
    let mut sink = FrameSink {
        field: &field,
        points: &points,
        mesh,
        geometry,
        frames_dir,
        outputs: &config.outputs,
        total: times.len(),
        field_mm: vec![[0.0f32; 3]; geometry.voxel_count()],
        records: Vec::with_capacity(times.len()),
        trajectories: inputs
            .points
            .iter()
            .map(|p| PointTrajectory {
                name: p.name.clone(),
                rest_lps_mm: p.rest_lps_mm,
                displacement_mm: Vec::with_capacity(times.len()),
            })
            .collect(),
        trajectory_file: if inputs.points.is_empty() {
            None
        } else {
            Some(TrajectoryFile::create(
                &staging.dir().join("trajectories.csv"),
                &inputs.points,
            )?)
        },
        point_displacements: vec![[0.0f64; 3]; inputs.points.len()],
        end_inhale_frame,
        end_inhale: None,
        write_s: 0.0,
    };
    let (report, dynamic) = match &config.motion.dynamic {
        None => (
            run_motion(
                &scene,
                &config.material,
                &inputs.trace,
                &settings,
                &mut |frame, positions| sink.frame(frame, positions, observer),
            )?,
            None,
        ),
        Some(dynamic) => {
            let r = run_dynamic(
                &scene,
                &inputs.trace,
                &dynamic.settings(),
                &times,
                &mut |f, positions| sink.frame(&f.as_frame_summary(), positions, observer),
            )?;
            (r.as_motion_report(&settings, &config.material), Some(r))
        }
    };
    let FrameSink {
        records,
        trajectories,
        trajectory_file,
        end_inhale,
        write_s,
        ..
    } = sink;
    timings.insert("motion_solve".to_string(), report.wall_time_s - write_s);
    timings.insert("frame_files".to_string(), write_s);

    observer.stage(RunStage::Finishing);
    check_cancel(observer, "the summary")?;
    let t = Instant::now();
    let capture =
        end_inhale.ok_or_else(|| Error::InvalidInput("the run produced no frame".into()))?;
    let end_inhale =
        summary::end_inhale_summary(model, &scene, capture.frame, &capture.positions_m, &report);
    if let Some(file) = trajectory_file {
        file.finish()?;
    }
    if config.outputs.quicklooks {
        write_quicklooks(
            staging.dir(),
            inputs,
            &scan.ct,
            &outcome.segmentation.lungs,
            &records,
            &capture,
        )?;
    }
    let mut summary = RunSummary::new(
        inputs,
        config,
        &outcome,
        report,
        dynamic,
        records,
        trajectories,
        end_inhale,
        timings,
    );
    summary.timings_s.insert(
        "summary_and_quicklooks".to_string(),
        t.elapsed().as_secs_f64(),
    );
    summary
        .timings_s
        .insert("total".to_string(), t_total.elapsed().as_secs_f64());
    summary.peak_memory_mib = crate::process::peak_rss_bytes().map(|b| b as f64 / (1 << 20) as f64);
    write_atomic(
        &staging.dir().join(SUMMARY_FILE),
        serde_json::to_string_pretty(&summary)
            .map_err(|e| Error::InvalidInput(format!("summary: {e}")))?
            .as_bytes(),
    )?;
    staging.publish()?;
    Ok(summary)
}

/// Everything written per frame, shared by the quasi-static and the dynamic paths.
struct FrameSink<'a> {
    field: &'a FieldSampler,
    points: &'a PointSampler,
    mesh: &'a crate::model::HexMesh,
    geometry: crate::volume::VolumeGeometry,
    frames_dir: PathBuf,
    outputs: &'a OutputConfig,
    total: usize,
    field_mm: Vec<[f32; 3]>,
    records: Vec<FrameRecord>,
    trajectories: Vec<PointTrajectory>,
    trajectory_file: Option<TrajectoryFile>,
    point_displacements: Vec<[f64; 3]>,
    end_inhale_frame: usize,
    end_inhale: Option<EndInhaleCapture>,
    write_s: f64,
}

impl FrameSink<'_> {
    /// Samples the frame's field on the CT grid and writes its files and trajectory rows.
    fn frame(
        &mut self,
        frame: &FrameSummary,
        positions: &[V3],
        observer: &mut dyn RunObserver,
    ) -> Result<()> {
        check_cancel(observer, &format!("frame {}", frame.index))?;
        if frame.index == 0 {
            observer.stage(RunStage::WritingFrames);
        }
        let t = Instant::now();
        let mesh = self.mesh;
        self.field.sample_mm(mesh, positions, &mut self.field_mm);
        let dir = self.frames_dir.join(frame.index.to_string());
        std::fs::create_dir_all(&dir)?;
        let description = format!("frame {} t={:.3}s", frame.index, frame.time_s);
        nifti::write_nifti_vector_field(
            &dir.join("displacement.nii.gz"),
            &self.geometry,
            &self.field_mm,
            &description,
        )?;
        let mut files = FrameFiles {
            displacement_nifti: format!("frames/{}/displacement.nii.gz", frame.index),
            displacement_mha: None,
            mesh_vtu: None,
        };
        if self.outputs.metaimage {
            metaimage::write_mha(
                &dir.join("displacement.mha"),
                &self.geometry,
                3,
                self.field_mm.as_flattened(),
                &format!("displacement LPS mm; {description}"),
            )?;
            files.displacement_mha = Some(format!("frames/{}/displacement.mha", frame.index));
        }
        if self.outputs.mesh_vtu {
            vtk::write_vtu(
                &dir.join("mesh.vtu"),
                &vtk::vtu_from_hex_mesh(mesh, positions)?,
            )?;
            files.mesh_vtu = Some(format!("frames/{}/mesh.vtu", frame.index));
        }
        self.points
            .displacements_into(mesh, positions, &mut self.point_displacements);
        for (trajectory, d) in self.trajectories.iter_mut().zip(&self.point_displacements) {
            trajectory.displacement_mm.push(*d);
        }
        if let Some(file) = self.trajectory_file.as_mut() {
            file.write_frame(
                frame.index,
                frame.time_s,
                &self.point_displacements,
                self.points.inside_mesh(),
            )?;
        }
        let (node, _) = positions
            .iter()
            .zip(&mesh.rest_positions_m)
            .map(|(x, r)| (x - r).norm_squared())
            .enumerate()
            .fold(
                (0, -1.0),
                |best, (i, d)| if d > best.1 { (i, d) } else { best },
            );
        if frame.index == self.end_inhale_frame {
            self.end_inhale = Some(EndInhaleCapture {
                frame: frame.index,
                positions_m: positions.to_vec(),
                field_mm: self.field_mm.clone(),
            });
        }
        let write_time_s = t.elapsed().as_secs_f64();
        self.records.push(FrameRecord {
            summary: frame.clone(),
            max_displacement_at_lps_mm: (mesh.rest_positions_m[node] * 1e3).into(),
            files,
            write_time_s,
        });
        self.write_s += write_time_s;
        observer.frame_written(frame.index + 1, self.total);
        Ok(())
    }
}

/// The frame with the largest volume, kept for the quick look and the physical checks.
struct EndInhaleCapture {
    frame: usize,
    positions_m: Vec<V3>,
    field_mm: Vec<[f32; 3]>,
}

/// `breathing.png` (trace, targets, simulated volumes) and `end-inhale-displacement.png`
/// (coronal slice through the first tracked point, else the lungs' centroid).
fn write_quicklooks(
    dir: &Path,
    inputs: &RunInputs,
    ct: &crate::volume::Volume<f32>,
    lungs: &crate::volume::Volume<u8>,
    records: &[FrameRecord],
    end_inhale: &EndInhaleCapture,
) -> Result<()> {
    use crate::outputs::plots::{
        lung_centroid_lps_mm, render_breathing_curve, render_displacement_look, BreathingCurve,
        DisplacementLookInput,
    };
    use crate::outputs::quicklook::write_png;
    let column = |f: fn(&FrameSummary) -> f64| -> Vec<f64> {
        records.iter().map(|r| f(&r.summary)).collect()
    };
    let frame_time_s: Vec<f64> = column(|f| f.time_s);
    let frame_target_ml: Vec<f64> = column(|f| f.target_volume_ml);
    let frame_simulated_ml: Vec<f64> = column(|f| f.simulated_volume_ml);
    let plot = render_breathing_curve(&BreathingCurve {
        trace_time_s: &inputs.trace.time_s,
        trace_volume_ml: &inputs.trace.volume_change_ml,
        frame_time_s: &frame_time_s,
        frame_target_ml: &frame_target_ml,
        frame_simulated_ml: &frame_simulated_ml,
        title: "Breathing trace (line), frame targets (rings) and simulated volumes (dots)",
    })?;
    write_png(&dir.join("breathing.png"), &plot.image)?;
    let (coronal_y_mm, through) = match inputs.points.first() {
        Some(p) => (p.rest_lps_mm[1], p.name.clone()),
        None => (
            lung_centroid_lps_mm(lungs).map_or(ct.geometry.origin_lps_mm[1], |c| c[1]),
            "the lungs' centroid".to_string(),
        ),
    };
    let f = &records[end_inhale.frame].summary;
    let title = format!(
        "End-inhale (frame {}, t = {:.2} s, +{:.0} mL): displacement, coronal slice through {}",
        f.index, f.time_s, f.simulated_volume_ml, through
    );
    let look = render_displacement_look(&DisplacementLookInput {
        ct,
        lungs,
        displacement_mm: &end_inhale.field_mm,
        coronal_y_mm,
        colour_max_mm: None,
        title: &title,
    })?;
    write_png(&dir.join("end-inhale-displacement.png"), &look.image)
}

/// Name of a [`ConstraintGroup`] code (`interior` for 0), for summaries.
fn group_name(code: u8) -> &'static str {
    ConstraintGroup::from_code(code).map_or("interior", |g| g.name())
}

//! Per-frame outputs of a run: each frame's displacement files, its trajectory rows and its
//! record in `summary.json`, shared by the quasi-static and the dynamic paths.

use std::path::{Path, PathBuf};
use std::time::Instant;

use super::summary::{BreathExtreme, SCANNED_STATE_TOLERANCE_ML};
use super::{
    check_cancel, FrameFiles, FrameRecord, LungScene, OutputConfig, PointTrajectory, RunInputs,
    RunObserver, RunStage,
};
use crate::breathing::BreathingTrace;
use crate::formats::{metaimage, nifti, vtk};
use crate::ingest::lung_model::LungModel;
use crate::math::V3;
use crate::motion::FrameSummary;
use crate::outputs::displacement_field::{FieldSampler, PointSampler};
use crate::outputs::ingest_files::lung_mesh_vtu;
use crate::outputs::radiotherapy::mesh_motion::{MeshLattice, MeshMotion};
use crate::outputs::radiotherapy::registration::{
    RegistrationGrid, RegistrationWriter, REGISTRATION_MARGIN_MM,
};
use crate::outputs::radiotherapy::target_motion::TargetTracker;
use crate::outputs::radiotherapy::virtual_ct::VirtualCtWriter;
use crate::outputs::trajectories::TrajectoryFile;
use crate::volume::VolumeGeometry;
use crate::{IoContext, IoOp, Result};

/// Everything written per frame, shared by the quasi-static and the dynamic paths.
pub(super) struct FrameSink<'a> {
    field: &'a FieldSampler,
    points: &'a PointSampler,
    mesh: &'a crate::model::HexMesh,
    model: &'a LungModel,
    geometry: VolumeGeometry,
    frames_dir: PathBuf,
    outputs: &'a OutputConfig,
    total: usize,
    field_mm: Vec<[f32; 3]>,
    records: Vec<FrameRecord>,
    trajectories: Vec<PointTrajectory>,
    trajectory_file: Option<TrajectoryFile>,
    point_displacements: Vec<[f64; 3]>,
    extremes: ExtremeFrames,
    captures: Vec<ExtremeCapture>,
    pictured_positions_m: Option<Vec<V3>>,
    registrations: Option<FrameRegistrations>,
    write_s: f64,
    sample_s: f64,
    nifti_s: f64,
    /// The treatment target, followed frame by frame.
    pub(super) target: Option<TargetTracker>,
    /// Where the mesh's elements lie, for the target without a virtual CT (built once).
    target_lattice: Option<MeshLattice>,
    /// The virtual 4D-CT, when asked for: each frame's CT written as the frames stream past.
    virtual_ct: Option<VirtualCtWriter<'a>>,
}

impl<'a> FrameSink<'a> {
    /// Also writes the virtual CT of each frame with `writer`.
    pub(super) fn set_virtual_ct(&mut self, writer: VirtualCtWriter<'a>) {
        self.virtual_ct = Some(writer);
    }

    /// The virtual CT writer, to finish once the frames are through.
    pub(super) fn take_virtual_ct(&mut self) -> Option<VirtualCtWriter<'a>> {
        self.virtual_ct.take()
    }

    /// Prepares `frames/` and, with tracked points, `trajectories.csv` in the staging
    /// directory for one frame per instant of `times`, the fields on the sampler's grid;
    /// `model` gives the frame meshes their lung and group labels, `study` the DICOM objects
    /// their patient, study and frame of reference.
    pub(super) fn open(
        lung: &'a LungScene,
        model: &'a LungModel,
        staging_dir: &Path,
        outputs: &'a OutputConfig,
        inputs: &RunInputs,
        times: &[f64],
        study: &crate::formats::dicom::DicomStudyContext,
    ) -> Result<Self> {
        let frames_dir = staging_dir.join("frames");
        std::fs::create_dir_all(&frames_dir).at(IoOp::CreateDir, &frames_dir)?;
        let geometry = *lung.field.geometry();
        let registrations = if outputs.registration {
            Some(FrameRegistrations::open(
                &lung.scene.mesh,
                &geometry,
                study,
                &frames_dir,
                outputs.registration_spacing_mm,
            )?)
        } else {
            None
        };
        Ok(FrameSink {
            field: &lung.field,
            points: &lung.points,
            mesh: &lung.scene.mesh,
            model,
            geometry,
            frames_dir,
            outputs,
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
                    &staging_dir.join("trajectories.csv"),
                    &inputs.points,
                )?)
            },
            point_displacements: vec![[0.0f64; 3]; inputs.points.len()],
            extremes: ExtremeFrames::of(&inputs.trace, times),
            captures: Vec::with_capacity(2),
            pictured_positions_m: None,
            registrations,
            write_s: 0.0,
            sample_s: 0.0,
            nifti_s: 0.0,
            target: None,
            target_lattice: None,
            virtual_ct: None,
        })
    }

    /// What the frames left for the summary: records, trajectories, the extremes' captures.
    pub(super) fn finish(self) -> FramesWritten {
        let pictured = self.extremes.pictured().zip(self.pictured_positions_m).map(
            |((kind, frame), positions_m)| PicturedExtreme {
                kind,
                frame,
                positions_m,
            },
        );
        FramesWritten {
            records: self.records,
            trajectories: self.trajectories,
            trajectory_file: self.trajectory_file,
            extremes: self.captures,
            pictured,
            write_s: self.write_s,
            sample_s: self.sample_s,
            nifti_s: self.nifti_s,
            field_buffer_mm: self.field_mm,
            target: self.target,
        }
    }
}

/// What a [`FrameSink`] gathered over the run.
pub(super) struct FramesWritten {
    pub(super) records: Vec<FrameRecord>,
    pub(super) trajectories: Vec<PointTrajectory>,
    /// Still open: finished once the run gets through its last frame.
    pub(super) trajectory_file: Option<TrajectoryFile>,
    /// Node positions at each breathing extreme the trace reaches, in frame order.
    pub(super) extremes: Vec<ExtremeCapture>,
    /// The field of the extreme the quick look shows (end-inhale when there is one).
    pub(super) pictured: Option<PicturedExtreme>,
    /// Time spent writing frame files, s (all of the per-frame work, the two below included).
    pub(super) write_s: f64,
    /// Of which sampling the fields on their grid, s.
    pub(super) sample_s: f64,
    /// Of which encoding, compressing and writing the NIfTI fields, s.
    pub(super) nifti_s: f64,
    /// The frames' field buffer (zero outside the lungs), handed on to the quick look so the
    /// run never holds two fields.
    pub(super) field_buffer_mm: Vec<[f32; 3]>,
    /// The target, its frames done, to finish.
    pub(super) target: Option<TargetTracker>,
}

impl FramesWritten {
    /// Adds the solves' time (the motion's `motion_wall_s` less the frames') and the frames'
    /// (`frame_files`, of which `frame_sampling` and `frame_nifti`) to `timings`.
    pub(super) fn record_timings(
        &self,
        motion_wall_s: f64,
        timings: &mut std::collections::BTreeMap<String, f64>,
    ) {
        timings.insert("motion_solve".into(), motion_wall_s - self.write_s);
        timings.insert("frame_files".into(), self.write_s);
        timings.insert("frame_sampling".into(), self.sample_s);
        timings.insert("frame_nifti".into(), self.nifti_s);
    }
}

/// The output frames at the breathing's extremes, known from the trace before solving, so
/// only their positions (and one field, for the quick look) are kept.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct ExtremeFrames {
    /// The frame with the largest volume, if it lies above the scanned state.
    pub(super) end_inhale: Option<usize>,
    /// The frame with the smallest volume, if it lies below the scanned state.
    pub(super) deepest_expiration: Option<usize>,
}

impl ExtremeFrames {
    /// The extremes among the trace's volumes at `times` (the first frame on a tie).
    pub(super) fn of(trace: &BreathingTrace, times: &[f64]) -> Self {
        let volumes = || times.iter().map(|&t| trace.volume_at(t)).enumerate();
        let pick = |better: fn(f64, f64) -> bool| {
            volumes().fold(None, |best: Option<(usize, f64)>, (i, v)| match best {
                Some((_, b)) if !better(v, b) => best,
                _ => Some((i, v)),
            })
        };
        let largest = pick(|v, b| v > b);
        let smallest = pick(|v, b| v < b);
        ExtremeFrames {
            end_inhale: largest
                .filter(|&(_, v)| v > SCANNED_STATE_TOLERANCE_ML)
                .map(|(i, _)| i),
            deepest_expiration: smallest
                .filter(|&(_, v)| v < -SCANNED_STATE_TOLERANCE_ML)
                .map(|(i, _)| i),
        }
    }

    /// Which extreme frame `index` is, if any (end-inhale first).
    fn kind_of(&self, index: usize) -> Option<BreathExtreme> {
        if self.end_inhale == Some(index) {
            Some(BreathExtreme::EndInhale)
        } else if self.deepest_expiration == Some(index) {
            Some(BreathExtreme::DeepestExpiration)
        } else {
            None
        }
    }

    /// The extreme the quick look shows: end-inhale when the trace rises above the scanned
    /// state, else the deepest expiration.
    pub(super) fn pictured(&self) -> Option<(BreathExtreme, usize)> {
        self.end_inhale
            .map(|f| (BreathExtreme::EndInhale, f))
            .or(self
                .deepest_expiration
                .map(|f| (BreathExtreme::DeepestExpiration, f)))
    }
}

impl FrameSink<'_> {
    /// Samples the frame's field on the CT grid and writes its files and trajectory rows.
    pub(super) fn frame(
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
        // The buffer starts zeroed and only lung voxels change from frame to frame.
        self.field
            .sample_lung_voxels_mm(mesh, positions, &mut self.field_mm);
        self.sample_s += t.elapsed().as_secs_f64();
        let dir = self.frames_dir.join(frame.index.to_string());
        std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
        let description = format!("frame {} t={:.3}s", frame.index, frame.time_s);
        let t_nifti = Instant::now();
        nifti::write_nifti_vector_field(
            &dir.join("displacement.nii.gz"),
            &self.geometry,
            &self.field_mm,
            &description,
        )?;
        self.nifti_s += t_nifti.elapsed().as_secs_f64();
        let mut files = FrameFiles {
            displacement_nifti: format!("frames/{}/displacement.nii.gz", frame.index),
            displacement_mha: None,
            mesh_vtu: None,
            registration_dicom: None,
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
                &lung_mesh_vtu(
                    mesh,
                    positions,
                    &self.model.element_lung,
                    &self.model.node_group,
                )?,
            )?;
            files.mesh_vtu = Some(format!("frames/{}/mesh.vtu", frame.index));
        }
        if let Some(registrations) = self.registrations.as_mut() {
            files.registration_dicom = Some(registrations.write(frame, mesh, positions)?);
        }
        // The target moves as the virtual CT does when there is one (the motion over the
        // whole CT, so the ITV matches the phase images a planner contours on); else with the
        // mesh's own motion, as the tracked points and the registrations do.
        if self.virtual_ct.is_none() {
            if let Some(tracker) = self.target.as_mut() {
                if self.target_lattice.is_none() {
                    self.target_lattice = Some(MeshLattice::of(mesh)?);
                }
                let lattice = self.target_lattice.as_ref().expect("set just above");
                let motion = MeshMotion::new(lattice, mesh, positions);
                tracker.frame(frame.index, frame.time_s, &motion)?;
            }
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
        self.capture_extreme(frame.index, positions);
        if let Some(writer) = self.virtual_ct.as_mut() {
            let tracker = self.target.as_mut();
            writer.write_phase(
                frame.index,
                frame.time_s,
                mesh,
                positions,
                |motion| match tracker {
                    Some(t) => t.frame(frame.index, frame.time_s, motion),
                    None => Ok(()),
                },
            )?;
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

impl FrameSink<'_> {
    /// Keeps the positions of an extreme frame, and a second copy for the quick look if it
    /// shows this one (its field is sampled again then: 0.7 MB of positions instead of the
    /// 117 MB field of a POPI lung box held through the run).
    fn capture_extreme(&mut self, index: usize, positions: &[V3]) {
        let Some(kind) = self.extremes.kind_of(index) else {
            return;
        };
        self.captures.push(ExtremeCapture {
            kind,
            frame: index,
            positions_m: positions.to_vec(),
        });
        if self.extremes.pictured().map(|p| p.1) == Some(index) {
            self.pictured_positions_m = Some(positions.to_vec());
        }
    }
}

/// The frames' DICOM registrations, from the mesh's own motion (zero outside the lungs).
struct FrameRegistrations {
    lattice: MeshLattice,
    writer: RegistrationWriter,
}

impl FrameRegistrations {
    /// The writer on a grid of `spacing_mm` along the CT's axes (`ct_geometry`'s direction)
    /// over the rest mesh and its margin.
    fn open(
        mesh: &crate::model::HexMesh,
        ct_geometry: &VolumeGeometry,
        study: &crate::formats::dicom::DicomStudyContext,
        frames_dir: &Path,
        spacing_mm: f64,
    ) -> Result<Self> {
        let grid = RegistrationGrid::around(
            mesh.rest_positions_m.iter().map(|p| p * 1e3),
            &ct_geometry.direction(),
            spacing_mm,
            REGISTRATION_MARGIN_MM,
        )?;
        Ok(FrameRegistrations {
            lattice: MeshLattice::of(mesh)?,
            writer: RegistrationWriter::new(study.clone(), grid, frames_dir),
        })
    }

    /// Writes `frame`'s registration; returns its path relative to the output directory.
    fn write(
        &mut self,
        frame: &FrameSummary,
        mesh: &crate::model::HexMesh,
        positions: &[V3],
    ) -> Result<String> {
        // The phase (when the instants are phases) leads: it is what a planner looks for.
        let phase = frame
            .phase_percent
            .map_or(String::new(), |p| format!("phase {p:.0}% "));
        let label = format!(
            "{phase}frame {} t={:.2}s {:+.0} mL",
            frame.index, frame.time_s, frame.target_volume_ml
        );
        let motion = MeshMotion::new(&self.lattice, mesh, positions);
        self.writer.frame(frame.index, &label, &motion)?;
        Ok(format!("frames/{}/registration.dcm", frame.index))
    }
}

/// Node positions at a breathing extreme, kept for the physical checks.
pub(super) struct ExtremeCapture {
    pub(super) kind: BreathExtreme,
    pub(super) frame: usize,
    pub(super) positions_m: Vec<V3>,
}

/// The extreme the quick look shows, with the node positions its field is sampled from.
pub(super) struct PicturedExtreme {
    pub(super) kind: BreathExtreme,
    pub(super) frame: usize,
    pub(super) positions_m: Vec<V3>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn extremes_of(volumes_ml: &[f64]) -> ExtremeFrames {
        let times: Vec<f64> = (0..volumes_ml.len()).map(|i| i as f64).collect();
        let trace = BreathingTrace::new(times.clone(), volumes_ml.to_vec()).unwrap();
        ExtremeFrames::of(&trace, &times)
    }

    #[test]
    fn a_trace_that_only_deflates_has_no_end_inhale_but_a_deepest_expiration() {
        let e = extremes_of(&[0.0, -120.0, -436.0, -300.0, 0.0]);
        assert_eq!(e.end_inhale, None);
        assert_eq!(e.deepest_expiration, Some(2));
        assert_eq!(
            e.pictured(),
            Some((BreathExtreme::DeepestExpiration, 2)),
            "the quick look shows the expiration"
        );
    }

    #[test]
    fn a_trace_going_both_ways_reports_both_extremes_and_pictures_the_inhale() {
        let e = extremes_of(&[0.0, 500.0, 1150.0, 200.0, -436.0, -100.0]);
        assert_eq!(e.end_inhale, Some(2));
        assert_eq!(e.deepest_expiration, Some(4));
        assert_eq!(e.kind_of(4), Some(BreathExtreme::DeepestExpiration));
        assert_eq!(e.kind_of(3), None);
        assert_eq!(e.pictured(), Some((BreathExtreme::EndInhale, 2)));
    }

    #[test]
    fn a_tidal_trace_above_the_scan_has_only_an_end_inhale() {
        // The scanned state itself (0 mL, or within 1 mL of it) is no expiration.
        let e = extremes_of(&[0.0, 250.0, 500.0, 250.0, -0.5]);
        assert_eq!(e.end_inhale, Some(2));
        assert_eq!(e.deepest_expiration, None);
    }
}

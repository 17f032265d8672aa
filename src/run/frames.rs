//! Per-frame outputs of a run: each frame's displacement files, its trajectory rows and its
//! record in `summary.json`, shared by the quasi-static and the dynamic paths.

use std::path::{Path, PathBuf};
use std::time::Instant;

use super::{
    check_cancel, FrameFiles, FrameRecord, LungScene, OutputConfig, PointTrajectory, RunInputs,
    RunObserver, RunStage,
};
use crate::breathing::BreathingTrace;
use crate::formats::{metaimage, nifti, vtk};
use crate::math::V3;
use crate::motion::FrameSummary;
use crate::outputs::displacement_field::{FieldSampler, PointSampler};
use crate::outputs::trajectories::TrajectoryFile;
use crate::volume::VolumeGeometry;
use crate::{IoContext, IoOp, Result};

/// Everything written per frame, shared by the quasi-static and the dynamic paths.
pub(super) struct FrameSink<'a> {
    field: &'a FieldSampler,
    points: &'a PointSampler,
    mesh: &'a crate::model::HexMesh,
    geometry: VolumeGeometry,
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

impl<'a> FrameSink<'a> {
    /// Prepares `frames/` and, with tracked points, `trajectories.csv` in the staging
    /// directory for one frame per instant of `times`, the fields on the sampler's grid.
    pub(super) fn open(
        lung: &'a LungScene,
        staging_dir: &Path,
        outputs: &'a OutputConfig,
        inputs: &RunInputs,
        times: &[f64],
    ) -> Result<Self> {
        let frames_dir = staging_dir.join("frames");
        std::fs::create_dir_all(&frames_dir).at(IoOp::CreateDir, &frames_dir)?;
        let geometry = *lung.field.geometry();
        Ok(FrameSink {
            field: &lung.field,
            points: &lung.points,
            mesh: &lung.scene.mesh,
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
            end_inhale_frame: end_inhale_frame(&inputs.trace, times),
            end_inhale: None,
            write_s: 0.0,
        })
    }

    /// What the frames left for the summary: records, trajectories, the end-inhale capture.
    pub(super) fn finish(self) -> FramesWritten {
        FramesWritten {
            records: self.records,
            trajectories: self.trajectories,
            trajectory_file: self.trajectory_file,
            end_inhale: self.end_inhale,
            write_s: self.write_s,
        }
    }
}

/// What a [`FrameSink`] gathered over the run.
pub(super) struct FramesWritten {
    pub(super) records: Vec<FrameRecord>,
    pub(super) trajectories: Vec<PointTrajectory>,
    /// Still open: finished once the run gets through its last frame.
    pub(super) trajectory_file: Option<TrajectoryFile>,
    pub(super) end_inhale: Option<EndInhaleCapture>,
    /// Time spent writing frame files, s.
    pub(super) write_s: f64,
}

/// End-inhale is the frame with the largest trace volume (the first, on a tie); known
/// before solving, so only that frame's field and positions are kept.
fn end_inhale_frame(trace: &BreathingTrace, times: &[f64]) -> usize {
    times
        .iter()
        .map(|&t| trace.volume_at(t))
        .enumerate()
        .fold((0, f64::NEG_INFINITY), |best, (i, v)| {
            if v > best.1 {
                (i, v)
            } else {
                best
            }
        })
        .0
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
        self.field.sample_mm(mesh, positions, &mut self.field_mm);
        let dir = self.frames_dir.join(frame.index.to_string());
        std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
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
pub(super) struct EndInhaleCapture {
    pub(super) frame: usize,
    pub(super) positions_m: Vec<V3>,
    pub(super) field_mm: Vec<[f32; 3]>,
}

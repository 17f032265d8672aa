//! The target through the breathing, frame by frame: its warped mask, volume and centroid
//! per frame, the internal target volume (ITV, their union), the peak-to-peak motion per axis
//! and the files a planning team loads (`target-motion.csv`, the masks, the RTSTRUCT).
//!
//! Warping: CT voxel y is in a frame's target when the planning target mask, interpolated
//! trilinearly at the voxel's source `PhaseMotion::source_lps_mm(y)`, is at least ½ (a
//! translation by whole voxels moves the mask exactly). The centroid is the mean of
//! `PhaseMotion::moved_lps_mm` over the planning target's voxel centres (the forward map,
//! exact at every voxel). Axes are LPS: LR = x (+ towards the patient's left), AP = y
//! (+ posterior), SI = z (+ superior).
//!
//! Streaming: one frame's mask is held at a time; the ITV accumulates; only the per-frame
//! figures and, when an RTSTRUCT is written, each frame's contours are kept.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use rayon::prelude::*;
use serde::Serialize;

use super::rtstruct::{write_rtstruct, RoiContours};
use super::target::TargetMask;
use super::PhaseMotion;
use crate::breathing::OutputInstants;
use crate::durable::write_atomic;
use crate::formats::dicom::DicomStudyContext;
use crate::formats::nifti::write_nifti_labels;
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, IoContext, IoOp, Result};

/// AAPM TG-76: respiratory motion management is advised when the target moves more than
/// this, mm.
pub const TG76_MOTION_THRESHOLD_MM: f64 = 5.0;
/// Voxels added around the moved target's box where the inverse map is evaluated (covers
/// the voxels a sub-voxel inverse error or a stretch brings in).
const WARP_MARGIN_VOXELS: f64 = 3.0;
/// ITV file, relative to the run's output directory.
pub const ITV_FILE: &str = "target/itv.nii.gz";
/// The planning target's mask, relative to the run's output directory.
pub const PLANNING_TARGET_FILE: &str = "target/planning-target.nii.gz";
/// The RT Structure Set, relative to the run's output directory.
pub const RTSTRUCT_FILE: &str = "target/rtstruct.dcm";
/// The per-frame table, relative to the run's output directory.
pub const MOTION_CSV_FILE: &str = "target-motion.csv";

/// The `target` section of `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct TargetSummary {
    /// What the target was made from (`--target` as given).
    pub source: String,
    /// Axis and sign convention of every figure below.
    pub axes: &'static str,
    /// How the frames' masks are made.
    pub warp: &'static str,
    /// Volume of the planning target, cc.
    pub planning_volume_cc: f64,
    /// Centroid of the planning target, LPS mm.
    pub planning_centroid_lps_mm: [f64; 3],
    /// One entry per output frame.
    pub frames: Vec<TargetFrame>,
    /// Peak-to-peak motion of the centroid over the frames, per axis, mm.
    pub peak_to_peak_mm: AxisMotion,
    /// Volume of the ITV (union of the frames' targets), cc.
    pub itv_volume_cc: f64,
    /// The AAPM TG-76 threshold, mm.
    pub tg76_threshold_mm: f64,
    /// Whether some axis's peak-to-peak motion exceeds the TG-76 threshold.
    pub tg76_motion_management_advised: bool,
    /// Files written, relative to the output directory.
    pub files: TargetFiles,
    /// Things the user should know (why no RTSTRUCT, a target leaving the CT, …).
    pub notes: Vec<String>,
}

/// One frame of the target.
#[derive(Debug, Clone, Serialize)]
pub struct TargetFrame {
    /// Frame index.
    pub frame: usize,
    /// Time in the trace, s.
    pub time_s: f64,
    /// Its name in the RTSTRUCT (`phase 30%`, `frame 4`).
    pub name: String,
    /// Volume of the warped target, cc.
    pub volume_cc: f64,
    /// Centroid, LPS mm.
    pub centroid_lps_mm: [f64; 3],
    /// Centroid minus the planning centroid, per axis, mm.
    pub displacement_mm: AxisMotion,
}

/// A figure per anatomical axis, mm (LPS signs: + left, + posterior, + superior).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AxisMotion {
    /// Left–right (x).
    pub lr: f64,
    /// Anterior–posterior (y).
    pub ap: f64,
    /// Superior–inferior (z).
    pub si: f64,
}

impl AxisMotion {
    fn of(v: [f64; 3]) -> Self {
        AxisMotion {
            lr: v[0],
            ap: v[1],
            si: v[2],
        }
    }

    /// The largest of the three.
    pub fn max(&self) -> f64 {
        self.lr.max(self.ap).max(self.si)
    }
}

/// Files of the target, relative to the output directory.
#[derive(Debug, Clone, Serialize)]
pub struct TargetFiles {
    /// `target-motion.csv`.
    pub motion_csv: String,
    /// The ITV mask.
    pub itv_nifti: String,
    /// The planning target's mask.
    pub planning_target_nifti: String,
    /// `frames/<k>/target.nii.gz`, in frame order.
    pub frame_masks: Vec<String>,
    /// The RT Structure Set, when the CT came from DICOM.
    pub rtstruct: Option<String>,
}

/// The planning target cropped to its box, sampled trilinearly at any CT position.
struct CroppedMask {
    /// CT voxel of the box's voxel (0, 0, 0).
    start: [usize; 3],
    dims: [usize; 3],
    /// 0.0 or 1.0 per voxel, i fastest.
    values: Vec<f32>,
}

impl CroppedMask {
    fn of(mask: &Volume<u8>) -> Option<Self> {
        let g = &mask.geometry;
        let (mut lo, mut hi) = ([usize::MAX; 3], [0usize; 3]);
        for (n, _) in mask.as_slice().iter().enumerate().filter(|(_, &v)| v != 0) {
            let ijk = [
                n % g.dims[0],
                (n / g.dims[0]) % g.dims[1],
                n / (g.dims[0] * g.dims[1]),
            ];
            for a in 0..3 {
                lo[a] = lo[a].min(ijk[a]);
                hi[a] = hi[a].max(ijk[a]);
            }
        }
        if lo[0] == usize::MAX {
            return None;
        }
        let dims = [0, 1, 2].map(|a| hi[a] - lo[a] + 1);
        let mut values = Vec::with_capacity(dims.iter().product());
        for k in lo[2]..=hi[2] {
            for j in lo[1]..=hi[1] {
                let row = g.index(lo[0], j, k);
                values.extend(
                    mask.as_slice()[row..row + dims[0]]
                        .iter()
                        .map(|&v| f32::from(v != 0)),
                );
            }
        }
        Some(CroppedMask {
            start: lo,
            dims,
            values,
        })
    }

    /// The mask's value at continuous CT voxel index `v` (0 outside its box).
    fn trilinear(&self, v: Vector3<f64>) -> f32 {
        let local = [0, 1, 2].map(|a| v[a] - self.start[a] as f64);
        let base = local.map(f64::floor);
        let frac = [0, 1, 2].map(|a| (local[a] - base[a]) as f32);
        let mut sum = 0.0f32;
        for corner in 0..8 {
            let offset = [corner & 1, (corner >> 1) & 1, (corner >> 2) & 1];
            let mut weight = 1.0f32;
            let mut index = [0usize; 3];
            let mut inside = true;
            for a in 0..3 {
                let c = base[a] + offset[a] as f64;
                weight *= if offset[a] == 1 {
                    frac[a]
                } else {
                    1.0 - frac[a]
                };
                inside &= c >= 0.0 && c < self.dims[a] as f64;
                index[a] = c.max(0.0) as usize;
            }
            if inside && weight > 0.0 {
                sum += weight
                    * self.values[index[0] + self.dims[0] * (index[1] + self.dims[1] * index[2])];
            }
        }
        sum
    }
}

/// Follows the target through a run's frames; the run calls [`TargetTracker::frame`] once per
/// output frame, in order, then [`TargetTracker::finish`].
pub struct TargetTracker {
    ct: VolumeGeometry,
    source: String,
    interpreted_type: &'static str,
    planning: Volume<u8>,
    cropped: CroppedMask,
    rest_positions_lps_mm: Vec<[f64; 3]>,
    rest_centroid_lps_mm: [f64; 3],
    itv: Volume<u8>,
    frame_mask: Volume<u8>,
    out_dir: PathBuf,
    frame_names: Vec<String>,
    study: Option<DicomStudyContext>,
    frame_rois: Vec<RoiContours>,
    frames: Vec<TargetFrame>,
    frame_files: Vec<String>,
    notes: Vec<String>,
}

impl TargetTracker {
    /// A tracker of `target` (on the CT grid) writing into `out_dir` (the run's staging
    /// directory); `frame_names[k]` names frame k in the RTSTRUCT ([`frame_names`]); with the
    /// CT's DICOM `study`, the frames' contours are kept for the RTSTRUCT.
    pub fn new(
        target: TargetMask,
        out_dir: &Path,
        frame_names: Vec<String>,
        study: Option<DicomStudyContext>,
    ) -> Result<Self> {
        let ct = target.mask.geometry;
        let cropped = CroppedMask::of(&target.mask).ok_or_else(|| {
            Error::argument(format!("target `{}`", target.source), "it holds no voxel")
        })?;
        let rest_positions_lps_mm: Vec<[f64; 3]> = target
            .mask
            .as_slice()
            .iter()
            .enumerate()
            .filter(|(_, &v)| v != 0)
            .map(|(n, _)| {
                let d = ct.dims;
                let ijk = Vector3::new(
                    (n % d[0]) as f64,
                    ((n / d[0]) % d[1]) as f64,
                    (n / (d[0] * d[1])) as f64,
                );
                ct.voxel_to_lps_mm(ijk).into()
            })
            .collect();
        let rest_centroid_lps_mm = mean(&rest_positions_lps_mm);
        // An RTSTRUCT ROI named CTV… is a clinical target volume; anything else a gross one.
        let interpreted_type = if target.source.to_ascii_uppercase().contains(":CTV") {
            "CTV"
        } else {
            "GTV"
        };
        let study = study.filter(|s| !s.slices.is_empty());
        Ok(TargetTracker {
            ct,
            source: target.source,
            interpreted_type,
            cropped,
            rest_positions_lps_mm,
            rest_centroid_lps_mm,
            itv: Volume::filled(ct, 0u8)?,
            frame_mask: Volume::filled(ct, 0u8)?,
            planning: target.mask,
            out_dir: out_dir.to_path_buf(),
            frame_names,
            study,
            frame_rois: Vec::new(),
            frames: Vec::new(),
            frame_files: Vec::new(),
            notes: target.notes,
        })
    }

    /// Warps the target into frame `frame_index` (at `time_s` in the trace) through `motion`:
    /// its mask (`frames/<k>/target.nii.gz`), volume and centroid; adds it to the ITV.
    pub fn frame(
        &mut self,
        frame_index: usize,
        time_s: f64,
        motion: &dyn PhaseMotion,
    ) -> Result<()> {
        let moved: Vec<[f64; 3]> = self
            .rest_positions_lps_mm
            .par_iter()
            .map(|&p| motion.moved_lps_mm(p))
            .collect();
        let centroid = mean(&moved);
        let count = self.warp_mask(&moved, motion);
        let name = self
            .frame_names
            .get(frame_index)
            .cloned()
            .unwrap_or_else(|| format!("frame {frame_index}"));
        if count == 0 {
            self.notes.push(format!(
                "{name}: the warped target holds no CT voxel (it left the scan)"
            ));
        }
        let itv = self.itv.as_slice_mut();
        itv.par_iter_mut()
            .zip(self.frame_mask.as_slice().par_iter())
            .for_each(|(u, &m)| *u |= m);
        let relative = format!("frames/{frame_index}/target.nii.gz");
        let path = self.out_dir.join(&relative);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).at(IoOp::CreateDir, dir)?;
        }
        write_nifti_labels(&path, &self.frame_mask)?;
        if self.study.is_some() {
            self.frame_rois.push(RoiContours::of_mask(
                format!("{} {name}", self.interpreted_type),
                self.interpreted_type,
                phase_colour(self.frames.len()),
                &self.frame_mask,
            ));
        }
        let displacement = [0, 1, 2].map(|a| centroid[a] - self.rest_centroid_lps_mm[a]);
        self.frames.push(TargetFrame {
            frame: frame_index,
            time_s,
            name,
            volume_cc: cc(count, &self.ct),
            centroid_lps_mm: centroid,
            displacement_mm: AxisMotion::of(displacement),
        });
        self.frame_files.push(relative);
        Ok(())
    }

    /// Fills `frame_mask` with the voxels whose source lies in the planning target, looking
    /// only in the box of the moved target voxels (`moved`) plus a margin; returns the count.
    fn warp_mask(&mut self, moved: &[[f64; 3]], motion: &dyn PhaseMotion) -> usize {
        let ct = self.ct;
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for p in moved {
            let v = ct.lps_mm_to_voxel(Vector3::from(*p));
            for a in 0..3 {
                lo[a] = lo[a].min(v[a]);
                hi[a] = hi[a].max(v[a]);
            }
        }
        let first = [0, 1, 2].map(|a| (lo[a] - WARP_MARGIN_VOXELS).floor().max(0.0));
        let last = [0, 1, 2].map(|a| {
            (hi[a] + WARP_MARGIN_VOXELS)
                .ceil()
                .min(ct.dims[a] as f64 - 1.0)
        });
        let frame = self.frame_mask.as_slice_mut();
        frame.par_iter_mut().for_each(|v| *v = 0);
        if (0..3).any(|a| first[a].is_nan() || last[a].is_nan() || first[a] > last[a]) {
            return 0;
        }
        let [i0, j0, k0] = first.map(|v| v as usize);
        let [i1, j1, k1] = last.map(|v| v as usize);
        let cropped = &self.cropped;
        let slice_len = ct.dims[0] * ct.dims[1];
        frame
            .par_chunks_mut(slice_len)
            .enumerate()
            .filter(|(k, _)| (k0..=k1).contains(k))
            .map(|(k, slice)| {
                let mut count = 0;
                for j in j0..=j1 {
                    for i in i0..=i1 {
                        let y = ct.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64));
                        let source = motion.source_lps_mm(y.into());
                        let v = ct.lps_mm_to_voxel(Vector3::from(source));
                        if cropped.trilinear(v) >= 0.5 {
                            slice[i + ct.dims[0] * j] = 1;
                            count += 1;
                        }
                    }
                }
                count
            })
            .sum()
    }

    /// Writes the ITV, the planning target, `target-motion.csv` and (with a DICOM study)
    /// the RTSTRUCT; returns the `target` section of `summary.json`.
    pub fn finish(self) -> Result<TargetSummary> {
        let dir = self.out_dir.join("target");
        std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
        write_nifti_labels(&self.out_dir.join(ITV_FILE), &self.itv)?;
        write_nifti_labels(&self.out_dir.join(PLANNING_TARGET_FILE), &self.planning)?;
        write_atomic(
            &self.out_dir.join(MOTION_CSV_FILE),
            motion_csv(&self.frames).as_bytes(),
        )?;
        let mut notes = self.notes;
        let rtstruct = match &self.study {
            Some(study) => {
                let mut rois = vec![
                    RoiContours::of_mask("ITV", "ITV", [255, 0, 0], &self.itv),
                    RoiContours::of_mask(
                        format!("{} planning CT", self.interpreted_type),
                        self.interpreted_type,
                        [255, 255, 0],
                        &self.planning,
                    ),
                ];
                rois.extend(self.frame_rois);
                write_rtstruct(
                    &self.out_dir.join(RTSTRUCT_FILE),
                    study,
                    &self.ct,
                    &rois,
                    "lungmotion ITV and target per phase",
                )?;
                Some(RTSTRUCT_FILE.to_string())
            }
            None => {
                notes.push(
                    "no RTSTRUCT: the planning CT was not read from DICOM (NIfTI or NRRD), so \
                     there are no CT images for a structure set to reference; the ITV and \
                     the targets are in the NIfTI masks"
                        .into(),
                );
                None
            }
        };
        let count = self.itv.as_slice().iter().filter(|&&v| v != 0).count();
        let peak_to_peak = peak_to_peak(&self.frames);
        Ok(TargetSummary {
            source: self.source,
            axes: "LPS mm: LR = x (+ patient left), AP = y (+ posterior), SI = z (+ superior)",
            warp: "CT voxel y is in a frame's target when the planning target mask, trilinearly \
                   interpolated at the voxel's source position (inverse motion), is ≥ 0.5; \
                   centroids are the mean forward-moved planning target voxel; the motion is the \
                   virtual CT's (over the whole CT) when one is written, else the lung mesh's \
                   own (zero outside the lungs)",
            planning_volume_cc: cc(self.rest_positions_lps_mm.len(), &self.ct),
            planning_centroid_lps_mm: self.rest_centroid_lps_mm,
            tg76_motion_management_advised: peak_to_peak.max() > TG76_MOTION_THRESHOLD_MM,
            peak_to_peak_mm: peak_to_peak,
            itv_volume_cc: cc(count, &self.ct),
            tg76_threshold_mm: TG76_MOTION_THRESHOLD_MM,
            files: TargetFiles {
                motion_csv: MOTION_CSV_FILE.into(),
                itv_nifti: ITV_FILE.into(),
                planning_target_nifti: PLANNING_TARGET_FILE.into(),
                frame_masks: self.frame_files,
                rtstruct,
            },
            frames: self.frames,
            notes,
        })
    }
}

/// The frames' names in the RTSTRUCT: `phase 30%` for phase instants (phase 0 at
/// end-inhale), else `frame k`.
pub fn frame_names(instants: &OutputInstants, frames: usize) -> Vec<String> {
    (0..frames)
        .map(|k| match instants {
            OutputInstants::Phases { count } if *count > 0 => {
                format!("phase {}%", (100.0 * k as f64 / *count as f64).round())
            }
            _ => format!("frame {k}"),
        })
        .collect()
}

/// Mean of points.
fn mean(points: &[[f64; 3]]) -> [f64; 3] {
    let n = points.len().max(1) as f64;
    let sum = points
        .iter()
        .fold([0.0; 3], |s, p| [s[0] + p[0], s[1] + p[1], s[2] + p[2]]);
    sum.map(|v| v / n)
}

/// Volume of `count` voxels of `ct`, cc.
fn cc(count: usize, ct: &VolumeGeometry) -> f64 {
    count as f64 * ct.voxel_volume_mm3() / 1000.0
}

/// Largest minus smallest centroid coordinate over the frames, per axis.
fn peak_to_peak(frames: &[TargetFrame]) -> AxisMotion {
    let range = |a: usize| {
        let values = frames.iter().map(|f| f.centroid_lps_mm[a]);
        let hi = values.clone().fold(f64::NEG_INFINITY, f64::max);
        let lo = values.fold(f64::INFINITY, f64::min);
        if hi >= lo {
            hi - lo
        } else {
            0.0
        }
    };
    AxisMotion::of([range(0), range(1), range(2)])
}

/// A distinct colour per frame for the RTSTRUCT (hues around the circle).
fn phase_colour(n: usize) -> [u8; 3] {
    const PALETTE: [[u8; 3]; 10] = [
        [0, 128, 255],
        [0, 200, 200],
        [0, 200, 100],
        [120, 200, 0],
        [200, 200, 0],
        [255, 150, 0],
        [255, 80, 80],
        [220, 0, 180],
        [150, 80, 255],
        [80, 80, 255],
    ];
    PALETTE[n % PALETTE.len()]
}

/// `target-motion.csv`: one row per frame, the units in the header.
fn motion_csv(frames: &[TargetFrame]) -> String {
    let mut text = String::from(
        "frame,time_s,name,volume_cc,centroid_x_lps_mm,centroid_y_lps_mm,centroid_z_lps_mm,\
         lr_mm_plus_left,ap_mm_plus_posterior,si_mm_plus_superior\n",
    );
    for f in frames {
        let c = f.centroid_lps_mm;
        let d = f.displacement_mm;
        let _ = writeln!(
            text,
            "{},{:.4},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4}",
            f.frame, f.time_s, f.name, f.volume_cc, c[0], c[1], c[2], d.lr, d.ap, d.si
        );
    }
    text
}

//! The virtual 4D-CT: the planning CT pulled back through each output instant's motion,
//! written as NIfTI and as a DICOM CT series per phase in the planning CT's study, with the
//! maximum- and average-intensity projections (MIP, AIP) over the phases accumulated as the
//! phases stream past.

use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::ct_motion::{
    CtGridMotion, CtMotionLayout, CtMotionSettings, InverseReport, ABDOMEN_DECAY_FACTOR,
};
use super::PhaseMotion;
use crate::breathing::{BreathingTrace, InstantPlan};
use crate::formats::dicom::{
    write_ct_series, CtSeriesMetadata, DerivedSeries, DicomStudyContext, RespiratoryPhase,
};
use crate::formats::nifti::{write_nifti_ct_int16, CT_INT16_GZIP_LEVEL};
use crate::math::V3;
use crate::model::HexMesh;
use crate::volume::Volume;
use crate::{Error, Result};

/// Most virtual CT phases one run writes: each is a whole CT (74 MB as int16 for a
/// 512² × 141 chest CT, about 2 s to warp and write on two cores), and a 4D-CT has 10.
pub const MAX_VIRTUAL_PHASES: usize = 40;

/// Which virtual 4D-CT files a run writes (`[outputs] virtual_ct`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum VirtualCtOutput {
    /// None (the default of `run`).
    #[default]
    Off,
    /// `frames/<k>/virtual-ct.nii.gz`, `mip-ct.nii.gz`, `aip-ct.nii.gz`.
    Nifti,
    /// The DICOM CT series only (`frames/<k>/virtual-ct-dicom/`, `mip-ct-dicom/`, …).
    Dicom,
    /// Both.
    Both,
}

impl std::str::FromStr for VirtualCtOutput {
    type Err = String;

    /// `off`, `nifti`, `dicom` or `both`; the error names the values taken.
    fn from_str(value: &str) -> std::result::Result<Self, String> {
        match value {
            "off" => Ok(VirtualCtOutput::Off),
            "nifti" => Ok(VirtualCtOutput::Nifti),
            "dicom" => Ok(VirtualCtOutput::Dicom),
            "both" => Ok(VirtualCtOutput::Both),
            _ => Err(format!(
                "\"{value}\" is not one of \"off\", \"nifti\", \"dicom\", \"both\""
            )),
        }
    }
}

impl<'de> Deserialize<'de> for VirtualCtOutput {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        // Named here, with the values it takes: serde's own message names neither the key
        // nor that "off" exists.
        let value = String::deserialize(d)?;
        value
            .parse()
            .map_err(|e| serde::de::Error::custom(format!("outputs.virtual_ct = {e}")))
    }
}

impl VirtualCtOutput {
    /// Whether any virtual CT is written.
    pub fn enabled(self) -> bool {
        self != VirtualCtOutput::Off
    }

    fn nifti(self) -> bool {
        matches!(self, VirtualCtOutput::Nifti | VirtualCtOutput::Both)
    }

    fn dicom(self) -> bool {
        matches!(self, VirtualCtOutput::Dicom | VirtualCtOutput::Both)
    }
}

/// Refuses more virtual phases than [`MAX_VIRTUAL_PHASES`], saying why and what to do.
pub fn check_phase_count(output: VirtualCtOutput, instants: usize) -> Result<()> {
    if !output.enabled() || instants <= MAX_VIRTUAL_PHASES {
        return Ok(());
    }
    Err(Error::Config {
        settings: "configuration",
        file: None,
        key: Some("outputs.virtual_ct".into()),
        reason: format!(
            "the output instants give {instants} frames, and a virtual CT per frame would \
             write {instants} whole CTs (a 512 × 512 × 141 CT is 74 MB each); at most \
             {MAX_VIRTUAL_PHASES} are written. Ask for phases of one breath \
             ([motion] instants = {{ kind = \"phases\", count = 10 }}), fewer frames \
             (every_kth, frame_rate), or set virtual_ct = \"off\""
        ),
    })
}

/// Where one output instant lies in the breathing: its phase and its direction.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PhaseLabel {
    /// Percent of the respiratory cycle from end-inhale (0 %), when the instants are phases.
    pub percent: Option<f64>,
    /// `end-inhale`, `exhale`, `end-exhale` or `inhale`.
    pub breathing: &'static str,
    /// Time since the cycle's end-inhale for phases, else since the first frame, s.
    pub time_since_first_s: f64,
    /// The cycle's length when the instants are phases of one cycle, s.
    #[serde(skip)]
    pub cycle_s: Option<f64>,
}

impl PhaseLabel {
    /// The DICOM SeriesDescription of this phase (at most 64 characters).
    pub fn series_description(&self, time_s: f64) -> String {
        match self.percent {
            Some(p) => format!(
                "lungmotion virtual 4D-CT phase {p:.0}% ({})",
                self.breathing
            ),
            None => format!("lungmotion virtual CT t={time_s:.2} s ({})", self.breathing),
        }
    }

    fn cycle_position(&self) -> &'static str {
        match self.breathing {
            "end-inhale" => "MAXIMUM",
            "end-exhale" => "MINIMUM",
            "inhale" => "INSPIRATION",
            _ => "EXPIRATION",
        }
    }
}

/// The phase of each output time of `plan`: its percent of the cycle from end-inhale when
/// the instants are phases (the plan's `phase_percent`, as `FrameSummary.phase_percent`
/// reports it), the largest and smallest volumes named end-inhale and end-exhale, the others
/// by the trace's slope; the time since end-inhale and the cycle's length follow from the
/// percentages (a one-breath trace's frames need not start at phase 0 %).
pub fn phase_labels(trace: &BreathingTrace, plan: &InstantPlan) -> Vec<PhaseLabel> {
    let times = &plan.times;
    let volumes: Vec<f64> = times.iter().map(|&t| trace.volume_at(t)).collect();
    let largest = volumes
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|m| m.0);
    let smallest = volumes
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))
        .map(|m| m.0);
    let percents = plan
        .phase_percent
        .as_ref()
        .filter(|p| p.len() == times.len());
    // The cycle: from the 0 % frame to any later frame at p %, (t − t₀)·100/p.
    let cycle_s = percents.and_then(|p| {
        let zero = p.iter().position(|&x| x == 0.0)?;
        let t0 = times[zero];
        (0..times.len())
            .filter(|&k| p[k] > 0.0 && times[k] > t0)
            .map(|k| (times[k] - t0) * 100.0 / p[k])
            .next()
    });
    let first = times.first().copied().unwrap_or(0.0);
    let dt = 0.05;
    times
        .iter()
        .enumerate()
        .map(|(k, &t)| {
            let breathing = if Some(k) == largest {
                "end-inhale"
            } else if Some(k) == smallest {
                "end-exhale"
            } else if trace.volume_at(t + dt) >= trace.volume_at(t - dt) {
                "inhale"
            } else {
                "exhale"
            };
            let percent = percents.map(|p| p[k]);
            let since = match (percent, cycle_s) {
                (Some(p), Some(c)) => p / 100.0 * c,
                _ => t - first,
            };
            PhaseLabel {
                percent,
                breathing,
                time_since_first_s: since,
                cycle_s,
            }
        })
        .collect()
}

/// Pulls `ct` back through `motion` onto its own grid: each voxel y takes the trilinear HU
/// at `motion.source_lps_mm(y)` (clamped to the CT's edge), rounded to whole HU as a CT
/// series stores them. Parallel over slices; no allocation per voxel.
pub fn warp_ct_into(ct: &Volume<f32>, motion: &dyn PhaseMotion, out: &mut [f32]) {
    let g = ct.geometry;
    let [nx, ny, nz] = g.dims;
    assert_eq!(out.len(), g.voxel_count(), "one output per CT voxel");
    let data = ct.as_slice();
    let step = |a: usize| g.direction().column(a) * g.spacing_mm[a];
    let (di, dj, dk) = (step(0), step(1), step(2));
    let origin = g.origin();
    out.par_chunks_mut(nx * ny)
        .enumerate()
        .for_each(|(k, slice)| {
            for j in 0..ny {
                let row = origin + dj * j as f64 + dk * k as f64;
                for i in 0..nx {
                    let y = row + di * i as f64;
                    let x = motion.source_lps_mm(y.into());
                    let v = g.lps_mm_to_voxel(V3::from(x));
                    slice[i + nx * j] = trilinear(data, [nx, ny, nz], v).round();
                }
            }
        });
}

/// [`warp_ct_into`] for a motion over the CT's own grid, the way a run does it: the same
/// sources (worked in index units, [`CtGridMotion::row_source_map`]) and the same trilinear
/// HU, rounded to whole HU and stored as int16 (the CT's values must fit, which
/// [`VirtualCtWriter::new`] checks). Parallel over rows, scratch per worker, none per voxel.
pub fn warp_ct_int16(ct: &Volume<f32>, motion: &CtGridMotion, out: &mut [i16]) {
    let g = ct.geometry;
    let [nx, ny, nz] = g.dims;
    assert_eq!(out.len(), g.voxel_count(), "one output per CT voxel");
    assert_eq!(
        motion.ct_geometry().dims,
        g.dims,
        "the motion is laid over this CT"
    );
    let map = motion.row_source_map();
    let data = ct.as_slice();
    out.par_chunks_mut(nx).enumerate().for_each_init(
        || (vec![[0.0f64; 3]; map.line_len()], vec![[0.0f64; 3]; nx]),
        |(line, sources), (row, voxels)| {
            let (j, k) = (row % ny, row / ny);
            map.sources_of_row(motion, j, k, line, sources);
            for (v, s) in voxels.iter_mut().zip(sources.iter()) {
                // Saturating: the CT's values were checked to fit.
                *v = trilinear_at(data, [nx, ny, nz], *s).round() as i16;
            }
        },
    );
}

/// [`trilinear`] with the corner offsets worked once (an axis of one voxel has none).
#[inline]
fn trilinear_at(data: &[f32], dims: [usize; 3], v: [f64; 3]) -> f32 {
    let mut n = 0usize;
    let mut t = [0.0f32; 3];
    let mut offset = [0usize; 3];
    let mut stride = 1usize;
    for a in 0..3 {
        if dims[a] > 1 {
            let x = v[a].clamp(0.0, (dims[a] - 1) as f64);
            let i = (x.floor() as usize).min(dims[a] - 2);
            n += i * stride;
            t[a] = (x - i as f64) as f32;
            offset[a] = stride;
        }
        stride *= dims[a];
    }
    let [ox, oy, oz] = offset;
    let lerp = |p: f32, q: f32, w: f32| p + (q - p) * w;
    let x00 = lerp(data[n], data[n + ox], t[0]);
    let x10 = lerp(data[n + oy], data[n + oy + ox], t[0]);
    let x01 = lerp(data[n + oz], data[n + oz + ox], t[0]);
    let x11 = lerp(data[n + oz + oy], data[n + oz + oy + ox], t[0]);
    lerp(lerp(x00, x10, t[1]), lerp(x01, x11, t[1]), t[2])
}

/// Trilinear interpolation of `data` (i fastest) at voxel coordinates `v`, clamped.
fn trilinear(data: &[f32], dims: [usize; 3], v: V3) -> f32 {
    let mut base = [0usize; 3];
    let mut t = [0.0f32; 3];
    for a in 0..3 {
        let x = v[a].clamp(0.0, (dims[a] - 1) as f64);
        let i = (x.floor() as usize).min(dims[a].saturating_sub(2));
        base[a] = i;
        t[a] = (x - i as f64) as f32;
    }
    let step = [1, dims[0], dims[0] * dims[1]];
    let at = |a: usize, b: usize, c: usize| {
        let clamp = |x: usize, axis: usize| x.min(dims[axis] - 1);
        data[clamp(base[0] + a, 0) * step[0]
            + clamp(base[1] + b, 1) * step[1]
            + clamp(base[2] + c, 2) * step[2]]
    };
    let lerp = |p: f32, q: f32, w: f32| p + (q - p) * w;
    let x00 = lerp(at(0, 0, 0), at(1, 0, 0), t[0]);
    let x10 = lerp(at(0, 1, 0), at(1, 1, 0), t[0]);
    let x01 = lerp(at(0, 0, 1), at(1, 0, 1), t[0]);
    let x11 = lerp(at(0, 1, 1), at(1, 1, 1), t[0]);
    lerp(lerp(x00, x10, t[1]), lerp(x01, x11, t[1]), t[2])
}

/// One virtual phase in `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct VirtualPhaseRecord {
    /// Frame index.
    pub frame: usize,
    /// Time in the trace, s.
    pub time_s: f64,
    /// Its place in the breathing.
    #[serde(flatten)]
    pub label: PhaseLabel,
    /// How well the inverse map (the resampler's) undoes the motion.
    pub inverse_residual: InverseReport,
    /// `frames/<k>/virtual-ct.nii.gz`, when written.
    pub nifti: Option<String>,
    /// `frames/<k>/virtual-ct-dicom`, when written.
    pub dicom: Option<String>,
    /// Time to build the motion, warp and write this phase, s.
    pub time_to_write_s: f64,
}

/// The `virtual_ct` section of `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct VirtualCtSummary {
    /// Which files were asked for.
    pub output: VirtualCtOutput,
    /// Spacing of the motion grid the CT is pulled back through, mm.
    pub grid_spacing_mm: f64,
    /// Its nodes along i, j, k.
    pub grid_dims: [usize; 3],
    /// Decay length (Gaussian σ) of the motion outside the lungs, mm.
    pub decay_length_mm: f64,
    /// The decay length straight below the lungs is this many times longer.
    pub abdomen_decay_factor: f64,
    /// How the motion outside the lungs is made.
    pub outside_lungs: &'static str,
    /// One entry per phase.
    pub phases: Vec<VirtualPhaseRecord>,
    /// Maximum-intensity projection over the phases, NIfTI.
    pub mip_nifti: Option<String>,
    /// Average-intensity projection over the phases, NIfTI.
    pub aip_nifti: Option<String>,
    /// MIP as a DICOM CT series.
    pub mip_dicom: Option<String>,
    /// AIP as a DICOM CT series.
    pub aip_dicom: Option<String>,
    /// Bytes of every virtual CT file written.
    pub bytes_written: u64,
    /// Time spent on the virtual CT (motion, warp, files), s.
    pub time_s: f64,
}

/// What the extension outside the lungs is, for the summary.
const OUTSIDE_LUNGS: &str = "displacement of the nearest lung node times exp(-d^2/2L^2), L \
    lengthened below the lungs (abdomen under the diaphragm), then smoothed with the lungs \
    held fixed: no seam at the pleura";

/// Streams the virtual 4D-CT: one phase per frame, MIP and AIP accumulated, written at the
/// end.
pub struct VirtualCtWriter<'a> {
    ct: &'a Volume<f32>,
    study: DicomStudyContext,
    layout: CtMotionLayout,
    output: VirtualCtOutput,
    labels: Vec<PhaseLabel>,
    out_dir: PathBuf,
    /// The phase being written, whole HU (int16: half of f32's 148 MB on a POPI CT).
    phase: Volume<i16>,
    /// Running maximum over the phases.
    mip: Vec<i16>,
    /// Running sum over the phases (exact: 40 phases of int16 fit in i32).
    sum: Vec<i32>,
    phases: Vec<VirtualPhaseRecord>,
    bytes_written: u64,
    time_s: f64,
}

impl<'a> VirtualCtWriter<'a> {
    /// Prepares the virtual CT of `ct` (HU) for the frames of `labels`, written under
    /// `out_dir` (`frames/<k>/…`, the projections at its top), the DICOM series into
    /// `study`; the motion grid is laid over the CT and located in `mesh` once here.
    pub fn new(
        ct: &'a Volume<f32>,
        study: DicomStudyContext,
        mesh: &HexMesh,
        settings: CtMotionSettings,
        output: VirtualCtOutput,
        labels: Vec<PhaseLabel>,
        out_dir: &Path,
    ) -> Result<Self> {
        let t = Instant::now();
        check_fits_int16(ct)?;
        let layout = CtMotionLayout::new(&ct.geometry, mesh, settings)?;
        let n = ct.geometry.voxel_count();
        Ok(VirtualCtWriter {
            ct,
            study,
            layout,
            output,
            labels,
            out_dir: out_dir.to_path_buf(),
            phase: Volume::filled(ct.geometry, 0i16)?,
            mip: vec![i16::MIN; n],
            sum: vec![0i32; n],
            phases: Vec::new(),
            bytes_written: 0,
            time_s: t.elapsed().as_secs_f64(),
        })
    }

    /// The motion grid laid over the CT (the other radiotherapy outputs can share it).
    pub fn layout(&self) -> &CtMotionLayout {
        &self.layout
    }

    /// Builds frame `frame`'s motion from the node positions (metres), warps the CT,
    /// writes the phase and adds it to the MIP and AIP; `also` gets the same motion (the
    /// target follows it, so that the ITV matches the phase images).
    pub fn write_phase(
        &mut self,
        frame: usize,
        time_s: f64,
        mesh: &HexMesh,
        positions_m: &[V3],
        also: impl FnOnce(&dyn PhaseMotion) -> Result<()>,
    ) -> Result<()> {
        let t = Instant::now();
        let label = self.labels.get(frame).cloned().ok_or_else(|| {
            Error::argument(
                "virtual CT",
                format!("frame {frame} is beyond the {} planned", self.labels.len()),
            )
        })?;
        let motion = self.layout.motion(mesh, positions_m)?;
        warp_ct_int16(self.ct, &motion, self.phase.as_slice_mut());
        also(&motion)?;
        let report = *motion.inverse_report();
        drop(motion);
        self.mip
            .par_chunks_mut(ACCUMULATE_CHUNK)
            .zip(self.sum.par_chunks_mut(ACCUMULATE_CHUNK))
            .zip(self.phase.as_slice().par_chunks(ACCUMULATE_CHUNK))
            .for_each(|((m, s), p)| {
                for ((m, s), &v) in m.iter_mut().zip(s.iter_mut()).zip(p) {
                    *m = (*m).max(v);
                    *s += i32::from(v);
                }
            });
        let dir = self.out_dir.join("frames").join(frame.to_string());
        let mut record = VirtualPhaseRecord {
            frame,
            time_s,
            label: label.clone(),
            inverse_residual: report,
            nifti: None,
            dicom: None,
            time_to_write_s: 0.0,
        };
        if self.output.nifti() {
            let path = dir.join("virtual-ct.nii.gz");
            write_nifti_ct_int16(&path, &self.phase, CT_INT16_GZIP_LEVEL)?;
            self.bytes_written += file_bytes(&path);
            record.nifti = Some(format!("frames/{frame}/virtual-ct.nii.gz"));
        }
        if self.output.dicom() {
            let meta = self.phase_metadata(frame, time_s, &label);
            let files = write_ct_series(&self.phase, &dir.join("virtual-ct-dicom"), &meta)?;
            self.bytes_written += files.iter().map(|f| file_bytes(f)).sum::<u64>();
            record.dicom = Some(format!("frames/{frame}/virtual-ct-dicom"));
        }
        record.time_to_write_s = t.elapsed().as_secs_f64();
        self.time_s += record.time_to_write_s;
        self.phases.push(record);
        Ok(())
    }

    /// The DICOM description of phase `frame`.
    fn phase_metadata(&self, frame: usize, time_s: f64, label: &PhaseLabel) -> CtSeriesMetadata {
        let count = self.labels.len() as u32;
        CtSeriesMetadata {
            series_description: label.series_description(time_s),
            series_number: 9001 + frame as u32,
            derived: Some(DerivedSeries {
                study: self.study.clone(),
                series_key: frame as u64 + 1,
                image_type: "DERIVED\\SECONDARY\\AXIAL".into(),
                derivation_description: format!(
                    "planning CT pulled back through the lungmotion model's motion at t = \
                     {time_s:.3} s of the breathing trace"
                ),
                respiratory: Some(RespiratoryPhase {
                    nominal_percentage: label.percent.map(|p| p as f32),
                    cycle_position: label.cycle_position(),
                    time_since_end_inhale_ms: label.time_since_first_s * 1e3,
                    interval_ms: label.cycle_s.map(|s| s * 1e3),
                    temporal_position: frame as u32 + 1,
                    temporal_positions: count,
                }),
            }),
            ..CtSeriesMetadata::default()
        }
    }

    /// Writes the MIP and AIP over the phases written and returns the summary section.
    pub fn finish(mut self) -> Result<VirtualCtSummary> {
        let t = Instant::now();
        let count = self.phases.len();
        let mut summary = VirtualCtSummary {
            output: self.output,
            grid_spacing_mm: self.layout.settings().grid_spacing_mm,
            grid_dims: self.layout.grid_dims(),
            decay_length_mm: self.layout.settings().decay_length_mm,
            abdomen_decay_factor: ABDOMEN_DECAY_FACTOR,
            outside_lungs: OUTSIDE_LUNGS,
            phases: Vec::new(),
            mip_nifti: None,
            aip_nifti: None,
            mip_dicom: None,
            aip_dicom: None,
            bytes_written: 0,
            time_s: 0.0,
        };
        if count > 0 {
            let mip = std::mem::take(&mut self.mip);
            self.write_projection("mip", "MIP", 8001, mip, &mut summary)?;
            // Rounded half away from zero, as f32::round does; the mean of int16 fits int16.
            let n = count as f64;
            let aip: Vec<i16> = std::mem::take(&mut self.sum)
                .into_par_iter()
                .map(|s| (f64::from(s) / n).round() as i16)
                .collect();
            self.write_projection("aip", "AIP", 8002, aip, &mut summary)?;
        }
        self.time_s += t.elapsed().as_secs_f64();
        summary.phases = self.phases;
        summary.bytes_written = self.bytes_written;
        summary.time_s = self.time_s;
        Ok(summary)
    }

    /// Writes one projection (`stem` = mip or aip) as NIfTI and DICOM as asked.
    fn write_projection(
        &mut self,
        stem: &str,
        name: &str,
        series_number: u32,
        voxels: Vec<i16>,
        summary: &mut VirtualCtSummary,
    ) -> Result<()> {
        let volume = Volume::from_data(self.ct.geometry, voxels)?;
        let count = self.phases.len();
        if self.output.nifti() {
            let file = format!("{stem}-ct.nii.gz");
            let path = self.out_dir.join(&file);
            write_nifti_ct_int16(&path, &volume, CT_INT16_GZIP_LEVEL)?;
            self.bytes_written += file_bytes(&path);
            *if stem == "mip" {
                &mut summary.mip_nifti
            } else {
                &mut summary.aip_nifti
            } = Some(file);
        }
        if self.output.dicom() {
            let dir_name = format!("{stem}-ct-dicom");
            let meta = CtSeriesMetadata {
                series_description: format!("lungmotion virtual 4D-CT {name} ({count} phases)"),
                series_number,
                derived: Some(DerivedSeries {
                    study: self.study.clone(),
                    series_key: u64::from(series_number) << 32,
                    image_type: format!(
                        "DERIVED\\SECONDARY\\AXIAL\\{}",
                        if stem == "mip" { "MIP" } else { "AVERAGE" }
                    ),
                    derivation_description: format!(
                        "{name} over the {count} phases of the lungmotion virtual 4D-CT"
                    ),
                    respiratory: None,
                }),
                ..CtSeriesMetadata::default()
            };
            let files = write_ct_series(&volume, &self.out_dir.join(&dir_name), &meta)?;
            self.bytes_written += files.iter().map(|f| file_bytes(f)).sum::<u64>();
            *if stem == "mip" {
                &mut summary.mip_dicom
            } else {
                &mut summary.aip_dicom
            } = Some(dir_name);
        }
        Ok(())
    }
}

/// Voxels per task of the MIP/AIP update.
const ACCUMULATE_CHUNK: usize = 1 << 16;

/// Refuses a CT whose rounded values do not fit int16, the virtual CT's voxel type (HU of a
/// real CT lie within −1024…+3071, or a few ten thousands on an extended scale).
fn check_fits_int16(ct: &Volume<f32>) -> Result<()> {
    let (lo, hi) = ct
        .as_slice()
        .par_iter()
        .fold(
            || (f32::INFINITY, f32::NEG_INFINITY),
            |(lo, hi), &v| (lo.min(v), hi.max(v)),
        )
        .reduce(
            || (f32::INFINITY, f32::NEG_INFINITY),
            |a, b| (a.0.min(b.0), a.1.max(b.1)),
        );
    let fits = |v: f32| (f32::from(i16::MIN)..=f32::from(i16::MAX)).contains(&v.round());
    let finite = ct.as_slice().par_iter().all(|v| v.is_finite());
    if finite && (ct.as_slice().is_empty() || (fits(lo) && fits(hi))) {
        return Ok(());
    }
    Err(Error::argument(
        "virtual CT",
        format!(
            "the CT's values span {lo}…{hi} HU{}; the virtual CT stores whole HU as int16 \
             (−32768…32767): rescale the CT or set virtual_ct = \"off\"",
            if finite {
                ""
            } else {
                " and include non-finite values"
            }
        ),
    ))
}

/// Size of a file just written (0 if it cannot be read back, which the writer would have
/// reported).
fn file_bytes(path: &Path) -> u64 {
    std::fs::metadata(path).map_or(0, |m| m.len())
}

/// Warnings for phases whose inverse did not converge everywhere or whose residual between
/// nodes exceeds `limit_mm`.
pub fn inverse_warnings(summary: &VirtualCtSummary, limit_mm: f64) -> Vec<String> {
    summary
        .phases
        .iter()
        .filter(|p| {
            p.inverse_residual.unconverged_nodes > 0
                || p.inverse_residual.lung_cell_max_mm > limit_mm
        })
        .map(|p| {
            let r = &p.inverse_residual;
            format!(
                "virtual CT frame {}: the inverse motion did not converge at {} grid node(s) \
                 (largest residual {:.2} mm; in the lungs {:.2} mm at nodes, {:.2} mm between \
                 them): the virtual CT is less exact there; a finer element size or a smaller \
                 volume change gives a smoother motion",
                p.frame,
                r.unconverged_nodes,
                r.all_node_max_mm,
                r.lung_node_max_mm,
                r.lung_cell_max_mm
            )
        })
        .collect()
}

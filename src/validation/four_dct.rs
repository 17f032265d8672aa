//! `lungmotion validate --4dct`: the model against a clinic's own 4D-CT (Baudet's proposed
//! protocol, §4.2.3). Every phase is segmented; each phase's lung volume relative to the
//! reference phase is the breathing trace; the model is built from the reference phase and
//! driven quasi-statically to every phase's volume, exactly as `lungmotion run` drives it
//! ([`crate::motion::run_motion`] with the run configuration's motion settings); each
//! prediction is compared with the phase itself:
//!
//! * **Lung-mask Dice**: the reference lungs carried by the predicted motion (each voxel of
//!   the phase takes the reference label at its source, the inverse map the virtual CT uses,
//!   [`CtGridMotion`]) against the phase's own segmentation, beside the no-motion baseline
//!   (the reference lungs unmoved).
//! * **Diaphragm position**: per lung, the height of the lung base under the lung's centre
//!   (the median, over the voxel columns within [`BASE_COLUMN_RADIUS_MM`] of the reference
//!   lung's footprint centroid, of each column's lowest lung voxel), predicted and no-motion
//!   against the phase's own. Under the centre, not the highest point of the whole base:
//!   the lung's base over the heart is higher than the dome and would be taken instead.
//! * **Landmarks** (when given): the reference phase's points carried by the predicted
//!   motion against the phase's points; mean, SD, 95th percentile and maximum of the 3D
//!   error, beside the no-motion baseline (the reference points unmoved).
//! * **Overlays**: `overlays/<phase>-coronal.png`, the phase's CT on the coronal plane
//!   through the reference lungs' centroid, its own lung contour in green and the predicted
//!   one in magenta.
//!
//! `report.json` ([`FourDctReport`]) and `report.md` go into the output folder.

use std::path::{Path, PathBuf};
use std::time::Instant;

use nalgebra::Vector3;
use rayon::prelude::*;
use serde::Serialize;

use crate::breathing::{BreathingTrace, OutputInstants};
use crate::ingest::four_dct::{check_same_grid, list_four_dct_phases, FourDctLayout, PhaseSource};
use crate::ingest::pipeline::{ingest_scan, PLAUSIBLE_LUNG_ML};
use crate::ingest::scan::load_ct_with;
use crate::ingest::segmentation::{segment_lungs, LEFT_LUNG, RIGHT_LUNG};
use crate::motion::run_motion;
use crate::outputs::quicklook::{
    overview_pixel_mm, render_slice_with_pixel, write_png_with_text, HuWindow, Overlay, SlicePlane,
};
use crate::outputs::radiotherapy::ct_motion::{CtGridMotion, CtMotionLayout, CtMotionSettings};
use crate::outputs::radiotherapy::PhaseMotion;
use crate::run::RunConfig;
use crate::validation::landmarks::{read_landmarks, LandmarkInput, PhaseLandmarks};
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, IoContext, IoOp, Result};

/// Radius around the lung's footprint centroid whose columns give the lung base height, mm.
pub const BASE_COLUMN_RADIUS_MM: f64 = 15.0;
/// Seconds between the phases in the breathing trace handed to the solver: only the order
/// of the volumes matters to a quasi-static solve, and 1 s keeps any 4D-CT's volume steps
/// far below the trace's flow limit.
const PHASE_STEP_S: f64 = 1.0;

/// What `validate --4dct` is told besides its input and output folder.
#[derive(Debug, Clone)]
pub struct FourDctOptions {
    /// The reference phase by name or 0-based index; `None`: the phase with the smallest
    /// segmented lung volume (end-exhale, the usual planning phase).
    pub reference_phase: Option<String>,
    /// The landmarks, if any.
    pub landmarks: Option<LandmarkInput>,
    /// Segmentation, element size, material, boundary options and motion settings, as for
    /// `lungmotion run` (the output instants are replaced by one per phase).
    pub config: RunConfig,
    /// Write the coronal overlays.
    pub overlays: bool,
}

impl Default for FourDctOptions {
    fn default() -> Self {
        FourDctOptions {
            reference_phase: None,
            landmarks: None,
            config: RunConfig::default(),
            overlays: true,
        }
    }
}

/// Mean, SD, 95th percentile and maximum of a set of errors, mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ErrorStats {
    /// Number of values.
    pub count: usize,
    /// Mean, mm.
    pub mean_mm: f64,
    /// Standard deviation (population), mm.
    pub sd_mm: f64,
    /// 95th percentile (nearest rank), mm.
    pub p95_mm: f64,
    /// Maximum, mm.
    pub max_mm: f64,
}

impl ErrorStats {
    /// The statistics of `values` (all zero for none).
    pub fn of(values: &[f64]) -> ErrorStats {
        let n = values.len();
        if n == 0 {
            return ErrorStats {
                count: 0,
                mean_mm: 0.0,
                sd_mm: 0.0,
                p95_mm: 0.0,
                max_mm: 0.0,
            };
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
        let mut sorted = values.to_vec();
        sorted.sort_by(f64::total_cmp);
        let rank = ((0.95 * n as f64).ceil() as usize).clamp(1, n);
        ErrorStats {
            count: n,
            mean_mm: mean,
            sd_mm: var.sqrt(),
            p95_mm: sorted[rank - 1],
            max_mm: sorted[n - 1],
        }
    }
}

/// The lung base height of one lung at one phase, mm (LPS z, superior positive).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct BaseHeight {
    /// 1 right, 2 left.
    pub lung: u8,
    /// In the phase's own segmentation, mm.
    pub real_z_mm: Option<f64>,
    /// In the predicted lungs, mm.
    pub predicted_z_mm: Option<f64>,
    /// In the reference lungs (no motion), mm.
    pub no_motion_z_mm: Option<f64>,
    /// Predicted − real, mm.
    pub error_mm: Option<f64>,
    /// No motion − real, mm.
    pub no_motion_error_mm: Option<f64>,
}

/// Landmark errors of one phase.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LandmarkErrors {
    /// The model's prediction against the phase's points.
    pub model: ErrorStats,
    /// The reference points unmoved against the phase's points.
    pub no_motion: ErrorStats,
}

/// One phase's comparison.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PhaseReport {
    /// The phase's name.
    pub name: String,
    /// Its 0-based index in phase order.
    pub index: usize,
    /// Where its CT came from.
    pub source: PathBuf,
    /// Its segmented lung volume, mL.
    pub lung_volume_ml: f64,
    /// Right lung, mL.
    pub right_volume_ml: f64,
    /// Left lung, mL.
    pub left_volume_ml: f64,
    /// The trace: its volume minus the reference's, mL.
    pub volume_change_ml: f64,
    /// The volume change the model reached, mL.
    pub simulated_volume_change_ml: f64,
    /// Dice of the predicted lungs against its own (both lungs as one mask).
    pub dice: f64,
    /// Dice of the reference lungs unmoved against its own.
    pub no_motion_dice: f64,
    /// Lung base heights, right then left.
    pub lung_base: Vec<BaseHeight>,
    /// Landmark errors, when landmarks were given.
    pub landmarks: Option<LandmarkErrors>,
    /// The overlay, relative to the output folder, when written.
    pub overlay: Option<String>,
}

/// Which phase is the reference and why.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReferencePhase {
    /// Its name.
    pub name: String,
    /// Its 0-based index.
    pub index: usize,
    /// `smallest lung volume (end-exhale)` or `--reference-phase`.
    pub chosen_by: String,
}

/// Landmarks as the report names them.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LandmarkSummary {
    /// Where they came from.
    pub input: LandmarkInput,
    /// Points per phase.
    pub count: usize,
}

/// `report.json`: the model against a 4D-CT.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FourDctReport {
    /// lungmotion version.
    pub software_version: &'static str,
    /// The 4D-CT as given.
    pub input: PathBuf,
    /// How its phases were laid out.
    pub layout: FourDctLayout,
    /// The grid every phase shares.
    pub geometry: VolumeGeometry,
    /// The reference phase.
    pub reference: ReferencePhase,
    /// Edge of the model's elements, mm.
    pub element_size_mm: f64,
    /// Share of each volume change the moving chest wall makes.
    pub rib_cage_share: f64,
    /// The landmarks, when given.
    pub landmarks: Option<LandmarkSummary>,
    /// Every phase, in phase order.
    pub phases: Vec<PhaseReport>,
    /// Wall time of the whole validation, s.
    pub wall_time_s: f64,
}

/// A phase as pass one keeps it: its lungs and volumes (its CT is let go: ten phases of a
/// clinical CT would hold 1.5 GB of voxels).
struct SegmentedPhase {
    lungs: Volume<u8>,
    right_ml: f64,
    left_ml: f64,
}

/// Runs the validation of `input` (see the module documentation) and writes `report.json`,
/// `report.md` and the overlays into `out` (which must exist); `progress` hears each step.
pub fn validate_four_dct(
    input: &Path,
    out: &Path,
    options: &FourDctOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<FourDctReport> {
    let start = Instant::now();
    let config = &options.config;
    config.validate()?;
    config.tissue.check_target(false)?;
    let listed = list_four_dct_phases(input, out)?;
    let phases = &listed.phases;
    let dicom_options = config.dicom_read_options();
    let ingest_settings = config.ingest_settings();

    // Pass one: every phase read, checked against the first one's grid, segmented.
    let mut segmented: Vec<SegmentedPhase> = Vec::with_capacity(phases.len());
    let mut geometry: Option<VolumeGeometry> = None;
    let mut landmarks: Option<PhaseLandmarks> = None;
    for phase in phases {
        progress(&format!("segmenting phase {}", phase.name));
        let scan = load_ct_with(&phase.path, &dicom_options)?;
        match &geometry {
            Some(g) => check_same_grid((&phases[0], g), (phase, &scan.ct.geometry))?,
            None => {
                // Landmarks are checked against the grid as soon as it is known, so a bad
                // file is refused before minutes of segmentation.
                landmarks = options
                    .landmarks
                    .as_ref()
                    .map(|input| read_landmarks(input, phases, &scan.ct.geometry))
                    .transpose()?;
                geometry = Some(scan.ct.geometry);
            }
        }
        let seg = segment_lungs(&scan.ct, &ingest_settings.segmentation).map_err(|e| match e {
            Error::Cancelled(_) => e,
            e => Error::scan(
                &phase.path,
                format!("phase {:?}: no usable lungs: {e}", phase.name),
            ),
        })?;
        let voxel_ml = scan.ct.geometry.voxel_volume_mm3() / 1000.0;
        let count = |label: u8| seg.lungs.as_slice().iter().filter(|&&v| v == label).count();
        let (right_ml, left_ml) = (
            count(RIGHT_LUNG) as f64 * voxel_ml,
            count(LEFT_LUNG) as f64 * voxel_ml,
        );
        if !PLAUSIBLE_LUNG_ML.contains(&(right_ml + left_ml)) || right_ml == 0.0 || left_ml == 0.0 {
            return Err(Error::scan(
                &phase.path,
                format!(
                    "phase {:?}: no usable lungs: the segmentation holds {:.0} mL (right {:.0}, \
                     left {:.0}); both lungs and {:.0}–{:.0} mL together are expected",
                    phase.name,
                    right_ml + left_ml,
                    right_ml,
                    left_ml,
                    PLAUSIBLE_LUNG_ML.start(),
                    PLAUSIBLE_LUNG_ML.end()
                ),
            ));
        }
        segmented.push(SegmentedPhase {
            lungs: seg.lungs,
            right_ml,
            left_ml,
        });
    }
    let geometry = geometry.expect("a 4D-CT has phases");
    let reference = choose_reference(phases, &segmented, options.reference_phase.as_deref())?;

    // The model of the reference phase, as `lungmotion run` builds it.
    progress(&format!(
        "building the model of reference phase {}",
        reference.name
    ));
    let ref_scan = load_ct_with(&phases[reference.index].path, &dicom_options)?;
    let outcome = ingest_scan(&ref_scan, &ingest_settings)?;
    let tissue = crate::ingest::lung_model::element_tissue(
        &outcome.model,
        &ref_scan.ct,
        &outcome.segmentation.lungs,
        None,
        &config.tissue,
        config.material.youngs_modulus_pa,
    )?;
    drop(ref_scan);
    let ref_lungs = &segmented[reference.index].lungs;
    let scene = match &tissue {
        Some((tissue, _)) => crate::motion::run_scene_with_tissue(
            &outcome.model,
            &config.wall_motion(),
            tissue,
            config.tissue.stiffness_step,
        )?,
        None => crate::motion::run_scene(&outcome.model, &config.wall_motion())?,
    };
    let layout = CtMotionLayout::new(
        &geometry,
        &scene.mesh,
        CtMotionSettings {
            decay_length_mm: config.outputs.outside_lung_decay_mm,
            ..CtMotionSettings::default()
        },
    )?;
    let volume = |s: &SegmentedPhase| s.right_ml + s.left_ml;
    let ref_ml = volume(&segmented[reference.index]);
    let trace = BreathingTrace::new(
        (0..phases.len()).map(|k| k as f64 * PHASE_STEP_S).collect(),
        segmented.iter().map(|s| volume(s) - ref_ml).collect(),
    )?;
    let mut settings = config.motion_settings();
    settings.instants = OutputInstants::EverySample;
    let columns = [RIGHT_LUNG, LEFT_LUNG].map(|lung| base_columns(ref_lungs, lung));
    let coronal_y = lung_centroid_y_mm(ref_lungs);
    if options.overlays {
        let dir = out.join("overlays");
        std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
    }

    progress("predicting every phase");
    let mut reports = Vec::with_capacity(phases.len());
    run_motion(
        &scene,
        &config.material,
        &trace,
        &settings,
        &mut |frame, positions| {
            let k = frame.index;
            let (phase, own) = (&phases[k], &segmented[k]);
            progress(&format!("comparing phase {}", phase.name));
            let motion = layout.motion(&scene.mesh, positions)?;
            let predicted = carry_labels(ref_lungs, &motion);
            let lung_base = [RIGHT_LUNG, LEFT_LUNG]
                .iter()
                .zip(&columns)
                .map(|(&lung, cols)| {
                    let real = base_height_mm(&own.lungs, lung, cols);
                    let pred = base_height_mm(&predicted, lung, cols);
                    let none = base_height_mm(ref_lungs, lung, cols);
                    let diff = |a: Option<f64>| a.zip(real).map(|(a, r)| a - r);
                    BaseHeight {
                        lung,
                        real_z_mm: real,
                        predicted_z_mm: pred,
                        no_motion_z_mm: none,
                        error_mm: diff(pred),
                        no_motion_error_mm: diff(none),
                    }
                })
                .collect();
            let landmark_errors = landmarks
                .as_ref()
                .map(|l| landmark_errors(l, reference.index, k, &motion));
            let overlay = if options.overlays {
                Some(write_overlay(
                    out,
                    phase,
                    &dicom_options,
                    &own.lungs,
                    &predicted,
                    coronal_y,
                )?)
            } else {
                None
            };
            reports.push(PhaseReport {
                name: phase.name.clone(),
                index: k,
                source: phase.path.clone(),
                lung_volume_ml: volume(own),
                right_volume_ml: own.right_ml,
                left_volume_ml: own.left_ml,
                volume_change_ml: frame.target_volume_ml,
                simulated_volume_change_ml: frame.simulated_volume_ml,
                dice: binary_dice(&predicted, &own.lungs)?,
                no_motion_dice: binary_dice(ref_lungs, &own.lungs)?,
                lung_base,
                landmarks: landmark_errors,
                overlay,
            });
            Ok(())
        },
    )?;
    let report = FourDctReport {
        software_version: env!("CARGO_PKG_VERSION"),
        input: input.to_path_buf(),
        layout: listed.layout,
        geometry,
        reference,
        element_size_mm: outcome.summary.element_size_mm,
        rib_cage_share: config.motion.rib_cage_share,
        landmarks: landmarks.map(|l| LandmarkSummary {
            input: options
                .landmarks
                .clone()
                .expect("landmarks were read from an input"),
            count: l.names.len(),
        }),
        phases: reports,
        wall_time_s: start.elapsed().as_secs_f64(),
    };
    report.write(out)?;
    Ok(report)
}

/// The reference phase: the one asked for (name, else 0-based index) or the smallest volume.
fn choose_reference(
    phases: &[PhaseSource],
    segmented: &[SegmentedPhase],
    asked: Option<&str>,
) -> Result<ReferencePhase> {
    let index = match asked {
        Some(asked) => crate::ingest::four_dct::find_phase(phases, asked)
            .map_err(|reason| Error::argument("reference phase", reason))?,
        None => segmented
            .iter()
            .enumerate()
            .min_by(|a, b| (a.1.right_ml + a.1.left_ml).total_cmp(&(b.1.right_ml + b.1.left_ml)))
            .map(|(i, _)| i)
            .expect("a 4D-CT has phases"),
    };
    Ok(ReferencePhase {
        name: phases[index].name.clone(),
        index,
        chosen_by: if asked.is_some() {
            "--reference-phase".to_string()
        } else {
            "smallest lung volume (end-exhale)".to_string()
        },
    })
}

/// The reference labels carried by `motion` onto the same grid: each voxel takes the label
/// of the reference voxel nearest to its source.
fn carry_labels(reference: &Volume<u8>, motion: &CtGridMotion) -> Volume<u8> {
    let g = reference.geometry;
    let [nx, ny, _] = g.dims;
    let data: Vec<u8> = (0..g.voxel_count())
        .into_par_iter()
        .map(|idx| {
            let ijk = Vector3::new(
                (idx % nx) as f64,
                ((idx / nx) % ny) as f64,
                (idx / (nx * ny)) as f64,
            );
            let y = g.voxel_to_lps_mm(ijk);
            let x = motion.source_lps_mm([y.x, y.y, y.z]);
            let v = g.lps_mm_to_voxel(Vector3::from(x));
            let r = [v.x, v.y, v.z].map(f64::round);
            if (0..3).all(|a| r[a] >= 0.0 && r[a] < g.dims[a] as f64) {
                reference.get(r[0] as usize, r[1] as usize, r[2] as usize)
            } else {
                0
            }
        })
        .collect();
    Volume::from_data(g, data).expect("same grid as the reference")
}

/// Dice of the lungs (any non-zero label) of two masks on one grid.
fn binary_dice(a: &Volume<u8>, b: &Volume<u8>) -> Result<f64> {
    crate::ingest::segmentation::dice_where(a, |x| x != 0, b, |y| y != 0)
}

/// The (i, j) voxel columns within [`BASE_COLUMN_RADIUS_MM`] of the footprint centroid of
/// `lung` in `lungs` (columns run along the grid's k axis, the slice direction of an axial
/// CT): the same columns measure every phase and prediction.
fn base_columns(lungs: &Volume<u8>, lung: u8) -> Vec<(usize, usize)> {
    let g = lungs.geometry;
    let [nx, ny, nz] = g.dims;
    let mut footprint = vec![false; nx * ny];
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                if lungs.get(i, j, k) == lung {
                    footprint[i + nx * j] = true;
                }
            }
        }
    }
    let at = |i: usize, j: usize| g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, 0.0));
    let cells: Vec<(usize, usize)> = (0..nx * ny)
        .filter(|&c| footprint[c])
        .map(|c| (c % nx, c / nx))
        .collect();
    if cells.is_empty() {
        return Vec::new();
    }
    let centre = cells
        .iter()
        .fold(Vector3::zeros(), |s, &(i, j)| s + at(i, j))
        / cells.len() as f64;
    cells
        .into_iter()
        .filter(|&(i, j)| {
            let d = at(i, j) - centre;
            // Distance across the columns only: the k axis is the column's own.
            (d.x * d.x + d.y * d.y).sqrt() <= BASE_COLUMN_RADIUS_MM
        })
        .collect()
}

/// The lung base height of `lung`: the median over `columns` of each column's lowest LPS z
/// holding the label (columns without it are skipped); `None` when none holds it.
fn base_height_mm(lungs: &Volume<u8>, lung: u8, columns: &[(usize, usize)]) -> Option<f64> {
    let g = lungs.geometry;
    let mut lows: Vec<f64> = columns
        .iter()
        .filter_map(|&(i, j)| {
            (0..g.dims[2])
                .filter(|&k| lungs.get(i, j, k) == lung)
                .map(|k| {
                    g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64))
                        .z
                })
                .min_by(f64::total_cmp)
        })
        .collect();
    if lows.is_empty() {
        return None;
    }
    lows.sort_by(f64::total_cmp);
    let n = lows.len();
    Some(if n % 2 == 1 {
        lows[n / 2]
    } else {
        0.5 * (lows[n / 2 - 1] + lows[n / 2])
    })
}

/// LPS y of the centroid of every lung voxel (the coronal plane of the overlays).
fn lung_centroid_y_mm(lungs: &Volume<u8>) -> f64 {
    crate::outputs::ingest_quicklooks::lung_centroids_lps_mm(lungs)
        .both
        .map_or(lungs.geometry.origin_lps_mm[1], |c| c[1])
}

/// The errors of phase `k`'s landmarks: the reference's carried by `motion`, and unmoved.
fn landmark_errors(
    landmarks: &PhaseLandmarks,
    reference: usize,
    k: usize,
    motion: &CtGridMotion,
) -> LandmarkErrors {
    let dist = |a: [f64; 3], b: [f64; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let (from, to) = (&landmarks.points[reference], &landmarks.points[k]);
    let model: Vec<f64> = from
        .iter()
        .zip(to)
        .map(|(&p, &q)| dist(motion.moved_lps_mm(p), q))
        .collect();
    let none: Vec<f64> = from.iter().zip(to).map(|(&p, &q)| dist(p, q)).collect();
    LandmarkErrors {
        model: ErrorStats::of(&model),
        no_motion: ErrorStats::of(&none),
    }
}

/// Writes `overlays/<phase>-coronal.png`; returns its path relative to `out`.
fn write_overlay(
    out: &Path,
    phase: &PhaseSource,
    dicom_options: &crate::formats::dicom::DicomReadOptions,
    own: &Volume<u8>,
    predicted: &Volume<u8>,
    coronal_y_mm: f64,
) -> Result<String> {
    // The CT is read again rather than kept from pass one: one phase in memory at a time.
    let scan = load_ct_with(&phase.path, dicom_options)?;
    let green = [(RIGHT_LUNG, [40, 220, 60]), (LEFT_LUNG, [40, 220, 60])];
    let magenta = [(RIGHT_LUNG, [240, 40, 220]), (LEFT_LUNG, [240, 40, 220])];
    let overlays = [
        Overlay {
            labels: own,
            palette: &green,
            opacity: 1.0,
            outline_only: true,
        },
        Overlay {
            labels: predicted,
            palette: &magenta,
            opacity: 1.0,
            outline_only: true,
        },
    ];
    let image = render_slice_with_pixel(
        &scan.ct,
        &overlays,
        SlicePlane::Coronal,
        coronal_y_mm,
        HuWindow::LUNG,
        overview_pixel_mm(&scan.ct.geometry),
    )?;
    let relative = format!("overlays/{}-coronal.png", file_safe(&phase.name));
    write_png_with_text(
        &out.join(&relative),
        &image,
        &[
            ("Title", format!("phase {} (coronal)", phase.name)),
            (
                "Description",
                "green: the phase's own lung contour; magenta: predicted from the reference"
                    .to_string(),
            ),
        ],
    )?;
    Ok(relative)
}

/// A phase name as a file name: anything but letters, digits, `-` and `_` becomes `_`.
fn file_safe(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

impl FourDctReport {
    /// Writes `report.json` and `report.md` into `out`.
    pub fn write(&self, out: &Path) -> Result<()> {
        let json_path = out.join("report.json");
        let json = serde_json::to_string_pretty(self)
            .map_err(|e| Error::format(&json_path, format!("cannot serialise: {e}")))?;
        crate::durable::write_atomic(&json_path, json.as_bytes())?;
        crate::durable::write_atomic(&out.join("report.md"), self.to_markdown().as_bytes())
    }

    /// The report as Markdown: one table per measure, phase by phase.
    pub fn to_markdown(&self) -> String {
        use crate::markdown::Table;
        use std::fmt::Write as _;
        let mm = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:.1}"));
        let mut s = String::new();
        let _ = writeln!(s, "# The model against a 4D-CT\n");
        let _ = writeln!(
            s,
            "Input `{}` ({:?}, {} phases, grid {:?} at {:?} mm). Reference phase **{}** \
             (chosen by {}); elements {} mm, rib-cage share {}.\n",
            self.input.display(),
            self.layout,
            self.phases.len(),
            self.geometry.dims,
            self.geometry.spacing_mm,
            self.reference.name,
            self.reference.chosen_by,
            self.element_size_mm,
            self.rib_cage_share
        );
        let _ = writeln!(s, "## Lung volumes and masks\n");
        let mut t = Table::new([
            "phase",
            "lungs (mL)",
            "ΔV (mL)",
            "model ΔV (mL)",
            "Dice model",
            "Dice no motion",
        ]);
        for p in &self.phases {
            t.row([
                p.name.clone(),
                format!("{:.0}", p.lung_volume_ml),
                format!("{:+.0}", p.volume_change_ml),
                format!("{:+.0}", p.simulated_volume_change_ml),
                format!("{:.4}", p.dice),
                format!("{:.4}", p.no_motion_dice),
            ]);
        }
        t.write_to(&mut s);
        let _ = writeln!(
            s,
            "\n## Lung base (diaphragm) height under each lung's centre, mm\n"
        );
        let mut t = Table::new([
            "phase",
            "right real",
            "right error",
            "right no-motion error",
            "left real",
            "left error",
            "left no-motion error",
        ]);
        for p in &self.phases {
            let mut cells = vec![p.name.clone()];
            for b in &p.lung_base {
                cells.extend([mm(b.real_z_mm), mm(b.error_mm), mm(b.no_motion_error_mm)]);
            }
            t.row(cells);
        }
        t.write_to(&mut s);
        if let Some(l) = &self.landmarks {
            let _ = writeln!(s, "\n## Landmark error, mm ({} points)\n", l.count);
            let mut t = Table::new([
                "phase",
                "model mean",
                "SD",
                "p95",
                "max",
                "no motion mean",
                "SD",
                "p95",
                "max",
            ]);
            for p in &self.phases {
                if let Some(e) = &p.landmarks {
                    let mut cells = vec![p.name.clone()];
                    for st in [&e.model, &e.no_motion] {
                        cells.extend(
                            [st.mean_mm, st.sd_mm, st.p95_mm, st.max_mm].map(|v| format!("{v:.2}")),
                        );
                    }
                    t.row(cells);
                }
            }
            t.write_to(&mut s);
        }
        let overlays: Vec<&str> = self
            .phases
            .iter()
            .filter_map(|p| p.overlay.as_deref())
            .collect();
        if !overlays.is_empty() {
            let _ = writeln!(
                s,
                "\n## Overlays\n\nCoronal slices, the phase's own lung contour in green, the \
                 predicted one in magenta: {}.",
                overlays
                    .iter()
                    .map(|o| format!("[{o}]({o})"))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_statistics_are_the_textbook_ones() {
        let st = ErrorStats::of(&[1.0, 2.0, 3.0, 4.0]);
        assert_eq!(st.count, 4);
        assert!((st.mean_mm - 2.5).abs() < 1e-12);
        assert!((st.sd_mm - 1.25f64.sqrt()).abs() < 1e-12);
        assert_eq!(st.p95_mm, 4.0);
        assert_eq!(st.max_mm, 4.0);
        let many: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(ErrorStats::of(&many).p95_mm, 95.0);
    }
}
